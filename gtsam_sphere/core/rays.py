"""Rays of pixels and pixels of rays for a calibrated camera (issue 14: one home in the core).

:func:`bearings` unprojects raw pixels on the half of the sphere given;
:func:`pixel_rays` unprojects raw pixels, each on its own half of the image
sphere (:meth:`~gtsam_sphere.core.camera.SphereCamera.pixel_hemisphere`);
:func:`project_rays` projects rays and keeps the pixels whose own ray comes back;
:class:`RayGrid` is a regular pixel grid's rays with a nearest-ray index. Used by
the export, the undistortion and the uncertainty maps.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import SphereCamera, check_uv
from .geometry import incidence_deg

__all__ = ["RayGrid", "bearings", "camera_of", "pixel_rays", "project_rays"]


def camera_of(calibration_or_camera) -> SphereCamera:
    """The :class:`SphereCamera` of a ``Calibration`` (``.camera``) or the camera itself."""
    cam = getattr(calibration_or_camera, "camera", calibration_or_camera)
    if not isinstance(cam, SphereCamera):
        raise TypeError(
            f"expected a Calibration or a SphereCamera, got {type(calibration_or_camera).__name__}"
        )
    return cam


def bearings(calibration_or_camera, uv_px: np.ndarray, hemisphere=1.0) -> np.ndarray:
    """Unit rays of raw pixels in the camera frame (measurement corrections included).

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (N, 2)
        Raw measured pixels.
    hemisphere : float or array_like, shape (N,)
        "sphere" mapping only: ``+1`` front half (incidence below 90 deg),
        ``-1`` back half; the mapping is two-to-one past 90 deg. The "radial"
        mapping is one-to-one up to ``camera.max_alpha_rad()`` and ignores it.

    Returns
    -------
    rays : ndarray, shape (N, 3)
        Unit vectors, camera frame (x right, y down, z forward); NaN rows
        for pixels outside the model's image.
    """
    camera = camera_of(calibration_or_camera)
    uv = check_uv(uv_px)
    h = np.asarray(hemisphere, float)
    if h.ndim and h.shape != (len(uv),):
        raise ValueError(f"hemisphere must be a scalar or have shape ({len(uv)},), got {h.shape}")
    return camera.unproject(uv, hemisphere=h)


def pixel_rays(camera, uv_px: np.ndarray, hemisphere: np.ndarray | None = None) -> np.ndarray:
    """Unit rays (camera frame) of raw pixels, each on its own half of the image sphere.

    Parameters
    ----------
    camera : SphereCamera
    uv_px : ndarray, shape (N, 2)
        Raw pixels (OpenCV convention).
    hemisphere : ndarray, shape (N,), optional
        ``+1`` / ``-1`` per pixel; default ``camera.pixel_hemisphere(uv_px)``
        (:meth:`~gtsam_sphere.core.camera.SphereCamera.pixel_hemisphere`).

    Returns
    -------
    rays : ndarray, shape (N, 3)
        Unit vectors, x right, y down, z forward; NaN where the camera has no
        ray.
    """
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 3))
    if hemisphere is None:
        hemisphere = camera.pixel_hemisphere(uv)
    return np.asarray(camera.unproject(uv, hemisphere=hemisphere), float).reshape(-1, 3)


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between rows of two (N, 3) arrays; NaN where either is not finite."""
    with np.errstate(invalid="ignore", divide="ignore"):
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        return np.arctan2(cross, np.sum(a * b, axis=1))


class RayGrid:
    """Rays of a regular pixel grid over a camera's image, with a nearest-ray index.

    Parameters
    ----------
    camera : SphereCamera
    n_cols : int
        Grid columns (rows follow the aspect ratio).

    Attributes
    ----------
    uv_px : ndarray, shape (G, 2)
        Grid pixels that have a ray.
    rays : ndarray, shape (G, 3)
        Their unit rays (:func:`pixel_rays`).
    step_px : float
        Grid spacing (px).
    max_incidence_deg : float
        Widest ray of the grid.
    """

    def __init__(self, camera, n_cols: int = 160):
        from sklearn.neighbors import KDTree

        self.step_px = max(camera.width, camera.height) / n_cols
        gu = np.arange(-0.5 + self.step_px / 2, camera.width - 0.5, self.step_px)
        gv = np.arange(-0.5 + self.step_px / 2, camera.height - 0.5, self.step_px)
        grid = np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)
        grays = pixel_rays(camera, grid)
        ok = np.all(np.isfinite(grays), axis=1)
        self.uv_px, self.rays = grid[ok], grays[ok]
        self.max_incidence_deg = (
            float(np.max(incidence_deg(self.rays))) if len(self.rays) else math.nan
        )
        self._tree = KDTree(self.rays) if len(self.rays) else None
        # a ray farther than a few grid steps from every grid ray is outside the image
        self.max_angle_rad = 5.0 * self.step_px / max(abs(float(camera.c)), 1e-9)

    def nearest(self, rays: np.ndarray) -> np.ndarray:
        """Pixel (N, 2) of the nearest grid ray to each ray (N, 3); NaN when none is close."""
        out = np.full((len(rays), 2), np.nan)
        if self._tree is None or len(rays) == 0:
            return out
        norm = np.linalg.norm(rays, axis=1)
        finite = np.isfinite(norm) & (norm > 0)
        if not finite.any():
            return out
        unit = rays[finite] / norm[finite, None]
        dist, idx = self._tree.query(unit, k=1)
        chord = 2.0 * math.sin(min(self.max_angle_rad, math.pi) / 2)
        near = dist[:, 0] <= chord
        sub = np.full((len(unit), 2), np.nan)
        sub[near] = self.uv_px[idx[near, 0]]
        out[finite] = sub
        return out


def project_rays(
    camera,
    rays: np.ndarray,
    seed_uv_px: np.ndarray | None = None,
    tol_px: float = 0.05,
    inside_image: bool = True,
    grid: RayGrid | None = None,
) -> np.ndarray:
    """Raw pixels of camera-frame rays, NaN where the camera has no pixel for the ray.

    The pixels of ``camera.project`` (which puts a ray behind the camera
    beyond the fold of a lens seeing past 90 deg), each accepted when its own
    ray (:func:`pixel_rays`) comes back to the input ray within ``tol_px /
    c`` rad (and, with ``inside_image``, it lies in the image). Without
    ``seed_uv_px``, rays wider than the widest ray of a :class:`RayGrid` by
    more than 2 deg are not tried at all.

    Parameters
    ----------
    camera : SphereCamera
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward); need not be unit.
    seed_uv_px : ndarray, shape (N, 2), optional
        Not needed any more (``camera.project`` finds the pixel on the
        ray's side of the fold); kept for callers. Given, no grid is built
        and every ray is tried.
    tol_px : float
        Round-trip tolerance in pixels at the scale ``c`` (px per rad).
    inside_image : bool
        Also reject pixels outside ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.
    grid : RayGrid, optional
        Reused between calls on the same camera; built when needed.

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    n = len(rays)
    uv = np.full((n, 2), np.nan)
    if n == 0:
        return uv
    tol_rad = tol_px / max(abs(float(camera.c)), 1e-9)

    def accepted(uv_try: np.ndarray, idx: np.ndarray) -> np.ndarray:
        ok = np.all(np.isfinite(uv_try), axis=1)
        if inside_image:
            ok &= (
                (uv_try[:, 0] >= -0.5)
                & (uv_try[:, 0] <= camera.width - 0.5)
                & (uv_try[:, 1] >= -0.5)
                & (uv_try[:, 1] <= camera.height - 0.5)
            )
        back = np.full((len(idx), 3), np.nan)
        if ok.any():
            back[ok] = pixel_rays(camera, uv_try[ok])
        ang = _angle_between(back, rays[idx])
        return ok & (ang < tol_rad)

    todo = np.flatnonzero(np.all(np.isfinite(rays), axis=1) & (np.linalg.norm(rays, axis=1) > 0))
    if seed_uv_px is None:
        if grid is None:
            grid = RayGrid(camera)
        if math.isfinite(grid.max_incidence_deg):
            todo = todo[incidence_deg(rays[todo]) <= grid.max_incidence_deg + 2.0]
        else:
            todo = todo[:0]
    if len(todo):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            trial = np.asarray(camera.project(rays[todo]), float).reshape(-1, 2)
        ok = accepted(trial, todo)
        uv[todo[ok]] = trial[ok]
    return uv
