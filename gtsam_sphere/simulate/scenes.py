"""Calibration objects seen from outside: a planar board and a 3D cube corner.

World frames (metres):

- ``"board"``: the board lies in ``Z = 0``, corners on a ``cols x rows``
  grid of ``spacing`` metres with ``X`` along the columns, ``Y`` along the
  rows, its printed (front) side facing ``+Z``.
- ``"object3d"``: three orthogonal grids forming the inside of a cube corner
  at the origin, on the planes ``Z = 0`` (front ``+Z``), ``Y = 0`` (front
  ``+Y``) and ``X = 0`` (front ``+X``), ``n x n`` points each at
  ``(i + 1) * spacing`` (none on the shared edges).

Poses aim the object at a chosen place of the image so that a set of images
covers the whole field (:class:`AimedPoses`): a pixel is drawn over the part
of the image the lens images (inside the image margin, at most ``fov / 2``
incidence), for half of the images uniformly over that area, for the other
half uniformly in the distance from the principal point (central views as
frequent as peripheral ones), and unprojected; the camera stands on a viewing
direction ``v`` on the object's front side, at the distance where the object
subtends a half angle ``beta`` (about 40% of the largest incidence the image
shows, 8-35 degrees), and is rotated so that the object's centre lands on the
drawn ray, with a uniformly random roll about it. For a 250 degree lens the
drawn rays reach 125 degrees, so the object is then behind the camera plane;
for a narrow lens the object fills a good part of the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "AimedPoses",
    "aim_rotation",
    "board_targets",
    "board_view_dir",
    "corner_view_dir",
    "field_half_angle_rad",
    "inside_image",
    "object3d_targets",
]

_HALF_PI = 0.5 * math.pi


def board_targets(shape: tuple[int, int], spacing_m: float):
    """Corners of a planar board.

    Parameters
    ----------
    shape : tuple of int
        ``(cols, rows)`` number of corners.
    spacing_m : float
        Distance between neighbouring corners (metres).

    Returns
    -------
    xyz : ndarray, shape (cols * rows, 3)
        Corner coordinates in the board frame (``Z = 0``), metres, row-major.
    normals : ndarray, shape (cols * rows, 3)
        Front-side normals (all ``+Z``).
    labels : list of str
        ``"board"`` for every corner.
    """
    cols, rows = (int(v) for v in shape)
    ii, jj = np.meshgrid(np.arange(cols), np.arange(rows))
    xyz = np.stack([ii.ravel() * spacing_m, jj.ravel() * spacing_m, np.zeros(ii.size)], axis=1)
    normals = np.repeat(np.array([[0.0, 0.0, 1.0]]), xyz.shape[0], axis=0)
    return xyz, normals, ["board"] * xyz.shape[0]


def object3d_targets(n: int, spacing_m: float):
    """Three orthogonal ``n x n`` grids forming the inside of a cube corner.

    Parameters
    ----------
    n : int
        Points per side of each grid.
    spacing_m : float
        Grid spacing (metres); points at ``(i + 1) * spacing_m``, ``i < n``.

    Returns
    -------
    xyz : ndarray, shape (3 * n * n, 3)
        Coordinates (metres) on ``Z = 0``, ``Y = 0`` and ``X = 0`` in turn.
    normals : ndarray, shape (3 * n * n, 3)
        Front-side normals ``+Z``, ``+Y``, ``+X`` (towards the corner's inside).
    labels : list of str
        ``"plane_xy"``, ``"plane_xz"``, ``"plane_yz"``.
    """
    g = (np.arange(n) + 1.0) * spacing_m
    a, b = (m.ravel() for m in np.meshgrid(g, g))
    zero = np.zeros(a.size)
    planes = [
        ("plane_xy", np.stack([a, b, zero], axis=1), np.array([0.0, 0.0, 1.0])),
        ("plane_xz", np.stack([a, zero, b], axis=1), np.array([0.0, 1.0, 0.0])),
        ("plane_yz", np.stack([zero, a, b], axis=1), np.array([1.0, 0.0, 0.0])),
    ]
    xyz = np.concatenate([p for _, p, _ in planes])
    normals = np.concatenate([np.repeat(nv[None, :], p.shape[0], axis=0) for _, p, nv in planes])
    labels = [name for name, p, _ in planes for _ in range(p.shape[0])]
    return xyz, normals, labels


def inside_image(uv_px: np.ndarray, width: int, height: int, margin_px: float) -> np.ndarray:
    """Which pixels lie at least ``margin_px`` inside the image.

    Parameters
    ----------
    uv_px : ndarray, shape (N, 2)
        Pixels (``(0, 0)`` = centre of the top-left pixel); NaN rows are outside.
    width, height : int
        Image size (pixels).
    margin_px : float
        Required distance from the image border (pixels).

    Returns
    -------
    inside : ndarray of bool, shape (N,)
    """
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(uv_px).all(axis=1)
            & (uv_px[:, 0] >= -0.5 + margin_px)
            & (uv_px[:, 0] <= width - 0.5 - margin_px)
            & (uv_px[:, 1] >= -0.5 + margin_px)
            & (uv_px[:, 1] <= height - 0.5 - margin_px)
        )


def _base_lens(lens: Any) -> Any:
    while hasattr(lens, "lens"):
        lens = lens.lens
    return lens


def _unproject_any_hemisphere(lens: Any, uv: np.ndarray, back: np.ndarray) -> np.ndarray:
    """Rays of pixels; for the folding sphere lens ``back`` picks the hemisphere."""
    if getattr(_base_lens(lens), "kind", "") == "sphere":
        return lens.unproject(uv, hemisphere=np.where(back, -1, 1))
    return lens.unproject(uv)


def _usable_pixels(
    lens: Any,
    uv: np.ndarray,
    back: np.ndarray,
    half_fov: float,
    margin: float,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    rays = _unproject_any_hemisphere(lens, uv, back)
    alpha = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
    ok = np.isfinite(alpha) & (alpha <= half_fov) & inside_image(uv, width, height, margin)
    return ok, rays


def field_half_angle_rad(lens: Any, fov_deg: float, width: int, height: int, margin_px: float):
    """Largest incidence angle (rad) the image shows.

    ``fov_deg / 2`` when the lens's circle lies (partly) inside the image,
    otherwise the largest incidence on the image border (a cropped
    full-frame fisheye or a diagonal-filling lens).

    Parameters
    ----------
    lens : lens object
        With ``unproject``.
    fov_deg : float
        Full field of view (degrees).
    width, height : int
        Image size (pixels).
    margin_px : float
        Border margin (pixels).

    Returns
    -------
    half_rad : float
    """
    half = math.radians(fov_deg / 2.0)
    m = margin_px
    s = np.linspace(0.0, 1.0, 401)
    u0, u1, v0, v1 = -0.5 + m, width - 0.5 - m, -0.5 + m, height - 0.5 - m
    border = np.concatenate(
        [
            np.stack([u0 + s * (u1 - u0), np.full_like(s, v0)], axis=1),
            np.stack([u0 + s * (u1 - u0), np.full_like(s, v1)], axis=1),
            np.stack([np.full_like(s, u0), v0 + s * (v1 - v0)], axis=1),
            np.stack([np.full_like(s, u1), v0 + s * (v1 - v0)], axis=1),
        ]
    )
    back = np.full(border.shape[0], half > _HALF_PI)
    rays = _unproject_any_hemisphere(lens, border, back)
    alpha = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
    alpha = np.where(np.isfinite(alpha), alpha, half)
    return float(min(half, alpha.max()))


def _frame(vec: np.ndarray) -> np.ndarray:
    """Orthonormal frame (columns) whose first column is ``vec / |vec|``."""
    a = vec / np.linalg.norm(vec)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b = np.cross(a, helper)
    b /= np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], axis=1)


def aim_rotation(ray_cam: np.ndarray, dir_world: np.ndarray, roll_rad: float) -> np.ndarray:
    """``world_from_cam`` rotation mapping a camera-frame ray onto a world direction.

    Parameters
    ----------
    ray_cam : ndarray, shape (3,)
        Direction in the camera frame.
    dir_world : ndarray, shape (3,)
        Direction it must point to in the world frame.
    roll_rad : float
        Rotation about ``dir_world`` (radians), the remaining freedom.

    Returns
    -------
    R_wc : ndarray, shape (3, 3)
        Rotation with ``R_wc @ ray_cam`` parallel to ``dir_world``.
    """
    cam = _frame(ray_cam)
    world = _frame(dir_world)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    spun = world.copy()
    spun[:, 1] = c * world[:, 1] + s * world[:, 2]
    spun[:, 2] = -s * world[:, 1] + c * world[:, 2]
    return spun @ cam.T


@dataclass
class AimedPoses:
    """Pose sampler that aims an object at random places of the image.

    Attributes
    ----------
    lens : lens object
        The true lens (``unproject``).
    centre_world : ndarray, shape (3,)
        The object's centre (metres).
    radius_m : float
        Largest distance of a target from the centre (metres).
    view_dir : callable(rng) -> ndarray, shape (3,)
        Draws a unit direction from the centre towards the camera (front side).
    half_fov_rad : float
        ``fov_deg / 2`` (radians); rays beyond it are not drawn.
    field_half_rad : float
        Largest incidence the image shows (:func:`field_half_angle_rad`).
    width, height : int
        Image size (pixels).
    margin_px : float
        Border margin (pixels).
    """

    lens: Any
    centre_world: np.ndarray
    radius_m: float
    view_dir: Any
    half_fov_rad: float
    field_half_rad: float
    width: int
    height: int
    margin_px: float

    def _ray(self, rng: np.random.Generator) -> np.ndarray:
        """A ray through a usable pixel (camera frame, unit).

        Half of the draws are uniform over the usable image area (the
        periphery and the corners), half uniform in the distance from the
        principal point: candidates uniform over the image are then kept with
        probability ``r0 / max(r, r0)`` (``r`` their distance from the
        principal point, ``r0`` 5% of the short side), so central views are
        as frequent as peripheral ones.
        """
        by_radius = rng.uniform() < 0.5
        r0 = 0.05 * min(self.width, self.height)
        pp = np.array([self.lens.cx, self.lens.cy])
        for _ in range(100):
            uv = np.stack(
                [
                    rng.uniform(-0.5, self.width - 0.5, 64),
                    rng.uniform(-0.5, self.height - 0.5, 64),
                ],
                axis=1,
            )
            back = rng.uniform(size=64) < 0.5
            keep = rng.uniform(size=64) * np.maximum(np.linalg.norm(uv - pp, axis=1), r0) < r0
            keep |= not by_radius
            ok, rays = _usable_pixels(
                self.lens, uv, back, self.half_fov_rad, self.margin_px, self.width, self.height
            )
            ok &= keep
            if ok.any():
                return rays[int(np.flatnonzero(ok)[0])]
        return np.array([0.0, 0.0, 1.0])

    def __call__(self, j: int, rng: np.random.Generator):
        """Draw one pose.

        Parameters
        ----------
        j : int
            Image index (unused: every image draws alike).
        rng : numpy.random.Generator

        Returns
        -------
        R : ndarray, shape (3, 3)
            ``cam_from_world`` rotation.
        t : ndarray, shape (3,)
            ``cam_from_world`` translation (metres).
        centre : ndarray, shape (3,)
            Camera centre in the world frame (metres).
        orientation : str
            ``"aimed"``.
        """
        ray = self._ray(rng)
        v = self.view_dir(rng)
        beta = float(np.clip(0.4 * self.field_half_rad, math.radians(8.0), math.radians(35.0)))
        beta *= rng.uniform(0.8, 1.2)
        distance = self.radius_m / math.tan(beta)
        centre = self.centre_world + distance * v
        r_wc = aim_rotation(ray, -v, rng.uniform(-math.pi, math.pi))
        R = r_wc.T
        return R, -R @ centre, centre, "aimed"


def board_view_dir(max_tilt_rad: float):
    """Sampler of viewing directions on a board's front side (``+Z``).

    Parameters
    ----------
    max_tilt_rad : float
        Largest angle between the viewing direction and the board normal.

    Returns
    -------
    draw : callable(rng) -> ndarray, shape (3,)
        Unit direction from the board towards the camera; the tilt is drawn
        uniformly in ``[0.15, 1] * max_tilt_rad`` (always some tilt, so the
        principal distance is observable), the azimuth uniformly.
    """

    def draw(rng: np.random.Generator) -> np.ndarray:
        tilt = rng.uniform(0.15 * max_tilt_rad, max_tilt_rad)
        az = rng.uniform(-math.pi, math.pi)
        st = math.sin(tilt)
        return np.array([st * math.cos(az), st * math.sin(az), math.cos(tilt)])

    return draw


def corner_view_dir(min_cos: float = 0.25):
    """Sampler of viewing directions into a cube corner (every component positive).

    Parameters
    ----------
    min_cos : float
        Smallest cosine between the direction and each of the three plane
        normals, so every plane is seen from its front side.

    Returns
    -------
    draw : callable(rng) -> ndarray, shape (3,)
        Unit direction from the corner towards the camera.
    """
    diag = np.ones(3) / math.sqrt(3.0)

    def draw(rng: np.random.Generator) -> np.ndarray:
        for _ in range(1000):
            v = diag + 0.45 * rng.normal(size=3)
            v /= np.linalg.norm(v)
            if v.min() >= min_cos:
                return v
        return diag

    return draw
