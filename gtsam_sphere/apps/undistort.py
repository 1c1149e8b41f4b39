"""Resample a calibrated camera's image onto a standard projection with ``cv2.remap``.

For every output pixel: output pixel -> ray (the output projection) -> raw
input pixel (the calibrated camera, :func:`gtsam_sphere.core.rays.project_rays`)
-> ``map_x, map_y`` (float32, OpenCV pixel convention on both sides). The
whole field of view the camera sees is kept where the output projection can
hold it: ``equirectangular`` and ``cylindrical`` span any longitude range
(past 180 deg too), ``perspective`` stays below 180 deg.

Output projections (output pixel ``(u, v)``, ``(0, 0)`` the centre of the
top-left pixel; output size ``W x H``; rays in the camera frame, x right, y
down, z forward):

``perspective``
    ``f = (W / 2) / tan(fov / 2)``, ray ``((u - (W-1)/2) / f, (v - (H-1)/2) / f, 1)``;
    ``fov`` is the horizontal field of view.
``equirectangular``
    longitude ``lon = (u - (W-1)/2) * s`` and latitude ``lat = (v - (H-1)/2) * s``
    with ``s = fov / W`` rad per pixel (square pixels on the sphere); ray
    ``(sin lon cos lat, sin lat, cos lon cos lat)``; ``fov`` is the longitude span.
``cylindrical``
    ``lon`` as above, ``f = 1 / s`` px per rad; ray ``(sin lon, (v - (H-1)/2) / f, cos lon)``.
``epipolar``
    an equirectangular grid whose poles lie on the x axis (a stereo pair's baseline
    after :func:`stereo_rectification`): ``lon = (u - (W-1)/2) * s`` is the angle out
    of the y-z plane, ``lat = (v - (H-1)/2) * s`` the rotation about x; ray
    ``(sin lon, cos lon sin lat, cos lon cos lat)``. Every row is one plane through the
    baseline (an epipolar plane), so corresponding points of the two rectified images
    share a row for any field of view, past 180 deg too (rows span up to 360 deg of
    ``lat``, columns up to 180 deg of ``lon``).

A stereo pair (``undistort --stereo``): both images are resampled into one rectified
frame (:func:`stereo_rectification`: x along the baseline, z the mean optical axis
made orthogonal to it), ``perspective`` (rows are epipolar lines, below 180 deg) or
``epipolar`` (the whole field of view).

Output pixels whose ray the camera does not see (outside its image, or
outside its field of view) map to :data:`INVALID` and come out as the border
value.
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import OptionsError
from ..core.rays import RayGrid, project_rays
from ..io.dataset import DatasetError, write_bytes_atomic

KINDS: tuple[str, ...] = ("perspective", "equirectangular", "cylindrical", "epipolar")
#: ``--to`` choices of one camera; ``epipolar`` is the stereo pair's equirectangular output
MONO_KINDS: tuple[str, ...] = KINDS[:3]
#: ``--to`` of ``undistort --stereo`` -> the output projection of both images
STEREO_KINDS: dict[str, str] = {"perspective": "perspective", "equirectangular": "epipolar"}
#: map value of output pixels without a source pixel (outside any input image)
INVALID = -1.0e4
#: default horizontal field of view cap of the perspective output (deg)
PERSPECTIVE_MAX_FOV_DEG = 120.0
#: about how many output pixels :func:`remap_tables` projects exactly by default
EXACT_PIXELS = 250000
#: latitude cap of the cylindrical output (deg); its rows go as tan(latitude)
CYLINDRICAL_MAX_LAT_DEG = 75.0


@dataclass
class RemapTables:
    """``cv2.remap`` tables from an output projection to a camera's raw image.

    Attributes
    ----------
    map_x, map_y : ndarray of float32, shape (H, W)
        Input pixel (OpenCV convention) of each output pixel; :data:`INVALID`
        where the camera does not see the output ray.
    kind : str
        One of ``KINDS``.
    fov_deg : float
        Horizontal field of view (perspective) or longitude span
        (equirectangular, cylindrical) of the output, in degrees.
    K : ndarray, shape (3, 3)
        Output camera matrix (px): perspective ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``;
        for the others ``f`` is pixels per radian of longitude.
    valid_fraction : float
        Fraction of output pixels with a source pixel.
    step : int
        Exact projection at every ``step``-th pixel, bilinear in between
        (see :func:`remap_tables`).
    interpolation_error_px : float
        Largest interpolation error found (input px), 0 for ``step = 1``.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    kind: str
    fov_deg: float
    K: np.ndarray
    valid_fraction: float
    step: int = 1
    interpolation_error_px: float = 0.0

    @property
    def size(self) -> tuple[int, int]:
        """Output ``(width, height)`` in pixels."""
        return int(self.map_x.shape[1]), int(self.map_x.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """Output pixels (H, W) with a source pixel, bool."""
        return self.map_x > INVALID / 2


def output_rays(
    kind: str, size: tuple[int, int], fov_deg: float, uv_px: np.ndarray | None = None
) -> np.ndarray:
    """Rays of output pixels of a projection (see the module docstring).

    Parameters
    ----------
    kind : str
        One of ``KINDS``.
    size : (int, int)
        Output ``(width, height)`` (px).
    fov_deg : float
        Horizontal field of view (perspective, < 180) or longitude span
        (equirectangular, cylindrical, <= 360), degrees.
    uv_px : ndarray, shape (N, 2), optional
        Output pixels; default every pixel in row-major order (``N = W * H``).

    Returns
    -------
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward); unit length except for
        ``perspective`` / ``cylindrical`` (unnormalised, as written above).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown projection {kind!r}; choose from {KINDS}")
    w, h = int(size[0]), int(size[1])
    if uv_px is None:
        v, u = np.mgrid[0:h, 0:w]
        uv_px = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    x = uv[:, 0] - (w - 1) / 2.0
    y = uv[:, 1] - (h - 1) / 2.0
    fov = math.radians(float(fov_deg))
    if kind == "perspective":
        f = _perspective_focal(w, fov_deg)
        return np.column_stack([x / f, y / f, np.ones(len(uv))])
    s = fov / w
    lon = x * s
    if kind == "equirectangular":
        lat = y * s
        return np.column_stack([np.sin(lon) * np.cos(lat), np.sin(lat), np.cos(lon) * np.cos(lat)])
    if kind == "epipolar":
        lat = y * s
        return np.column_stack([np.sin(lon), np.cos(lon) * np.sin(lat), np.cos(lon) * np.cos(lat)])
    return np.column_stack([np.sin(lon), y * s, np.cos(lon)])


def output_pixels(kind: str, size: tuple[int, int], fov_deg: float, rays: np.ndarray) -> np.ndarray:
    """Output pixels of rays: the inverse of :func:`output_rays`.

    Parameters
    ----------
    kind : str
        One of ``KINDS``.
    size : (int, int)
        Output ``(width, height)`` (px).
    fov_deg : float
        As in :func:`output_rays` (degrees).
    rays : ndarray, shape (N, 3)
        Output frame (x right, y down, z forward), any length.

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
        NaN for a ray the projection cannot hold (perspective: ``z <= 0``).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown projection {kind!r}; choose from {KINDS}")
    w, h = int(size[0]), int(size[1])
    r = np.asarray(rays, float).reshape(-1, 3)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        if kind == "perspective":
            f = _perspective_focal(w, fov_deg)
            z = np.where(r[:, 2] > 0, r[:, 2], np.nan)
            return np.column_stack([cx + f * r[:, 0] / z, cy + f * r[:, 1] / z])
        s = math.radians(float(fov_deg)) / w
        n = np.linalg.norm(r, axis=1)
        if kind == "equirectangular":
            lon = np.arctan2(r[:, 0], r[:, 2])
            return np.column_stack([cx + lon / s, cy + np.arcsin(r[:, 1] / n) / s])
        if kind == "epipolar":
            lat = np.arctan2(r[:, 1], r[:, 2])
            return np.column_stack([cx + np.arcsin(r[:, 0] / n) / s, cy + lat / s])
        lon = np.arctan2(r[:, 0], r[:, 2])
        return np.column_stack([cx + lon / s, cy + r[:, 1] / np.hypot(r[:, 0], r[:, 2]) / s])


def _perspective_focal(width: int, fov_deg: float) -> float:
    if not 0 < fov_deg < 180:
        raise ValueError(f"perspective field of view must be in (0, 180) deg, got {fov_deg}")
    return (width / 2.0) / math.tan(math.radians(fov_deg) / 2)


def camera_extent_deg(
    camera,
    n_cols: int = 96,
    output_from_cam: np.ndarray | None = None,
    kind: str = "equirectangular",
) -> tuple[float, float]:
    """Largest ``|longitude|`` and ``|latitude|`` (deg) of the camera's rays over its image.

    Longitude ``atan2(x, z)``, latitude ``asin(y)`` of each unit ray (``kind``
    ``"epipolar"``: longitude ``asin(x)``, latitude ``atan2(y, z)``), on a grid of
    about ``n_cols`` columns; pixels without a ray are skipped.

    Parameters
    ----------
    camera : SphereCamera
    n_cols : int
    output_from_cam : ndarray, shape (3, 3), optional
        Rotation of the rays into the output frame first (a rectified stereo frame).
    kind : str
        The output projection whose longitude / latitude are meant.

    Returns
    -------
    (max_abs_lon_deg, max_abs_lat_deg) : tuple of float
    """
    rays = RayGrid(camera, n_cols).rays
    if len(rays) == 0:
        raise ValueError("the camera has no ray anywhere in its image")
    if output_from_cam is not None:
        rays = rays @ np.asarray(output_from_cam, float).T
    if kind == "epipolar":
        lon = np.degrees(np.arcsin(np.clip(rays[:, 0], -1, 1)))
        lat = np.degrees(np.arctan2(rays[:, 1], rays[:, 2]))
    else:
        lon = np.degrees(np.arctan2(rays[:, 0], rays[:, 2]))
        lat = np.degrees(np.arcsin(np.clip(rays[:, 1], -1, 1)))
    return float(np.max(np.abs(lon))), float(np.max(np.abs(lat)))


def default_geometry(
    camera,
    kind: str,
    fov_deg: float | None = None,
    size: tuple[int, int] | None = None,
    output_from_cam: np.ndarray | None = None,
) -> tuple[float, tuple[int, int]]:
    """Field of view and output size used when not given.

    ``fov_deg``: the camera's full longitude span (twice the largest
    ``|longitude|`` of :func:`camera_extent_deg`), capped at
    :data:`PERSPECTIVE_MAX_FOV_DEG` for ``perspective`` and at 360.
    ``size``: width of the camera image; height the camera's for
    ``perspective``, else enough rows for its latitude span (square pixels
    on the sphere; cylindrical capped at :data:`CYLINDRICAL_MAX_LAT_DEG`).
    ``epipolar``: longitude span capped at 180, latitude at 360 deg.
    ``camera`` may be a list of cameras with ``output_from_cam`` a list of
    rotations (a stereo pair): the extents are their union.

    Returns
    -------
    fov_deg : float
    size : (int, int)
        ``(width, height)`` px.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown projection {kind!r}; choose from {KINDS}")
    cams = list(camera) if isinstance(camera, (list, tuple)) else [camera]
    rots = list(output_from_cam) if isinstance(camera, (list, tuple)) else [output_from_cam]
    if output_from_cam is None:
        rots = [None] * len(cams)
    ext = np.array([camera_extent_deg(c, 96, r, kind) for c, r in zip(cams, rots)])
    lon, lat = (float(v) for v in ext.max(axis=0))
    if fov_deg is None:
        fov_deg = min(2 * lon, 180.0 if kind == "epipolar" else 360.0)
        if kind == "perspective":
            fov_deg = min(fov_deg, PERSPECTIVE_MAX_FOV_DEG)
    if size is None:
        w = max(int(c.width) for c in cams)
        if kind == "perspective":
            h = max(int(c.height) for c in cams)
        elif kind == "equirectangular":
            h = int(math.ceil(w * min(2 * lat, 180.0) / fov_deg))
        elif kind == "epipolar":
            h = int(math.ceil(w * min(2 * lat, 360.0) / fov_deg))
        else:
            f = w / math.radians(fov_deg)
            h = int(math.ceil(2 * f * math.tan(math.radians(min(lat, CYLINDRICAL_MAX_LAT_DEG)))))
        size = (w, max(h, 1))
    return float(fov_deg), (int(size[0]), int(size[1]))


def remap_tables(
    camera,
    kind: str = "equirectangular",
    fov_deg: float | None = None,
    size: tuple[int, int] | None = None,
    step: int | None = None,
    tol_px: float = 0.01,
    chunk: int = 262144,
    output_from_cam: np.ndarray | None = None,
) -> RemapTables:
    """Build ``cv2.remap`` tables from an output projection to the camera's raw image.

    Parameters
    ----------
    camera : SphereCamera
        The calibrated camera (``project`` / ``unproject``).
    kind : str
        One of ``KINDS``.
    fov_deg : float, optional
        See :func:`output_rays`; default :func:`default_geometry`.
    size : (int, int), optional
        Output ``(width, height)`` px; default :func:`default_geometry`.
    step : int, optional
        ``1``: every output pixel is projected exactly. ``k > 1``: every
        ``k``-th pixel (rows and columns) is, the tables are interpolated
        bilinearly in between; cells next to the edge of the valid area, or
        where the tables bend enough for bilinear interpolation to err by more
        than ``tol_px``, are projected exactly; the largest interpolation error
        found at up to
        2000 random pixels is reported (``interpolation_error_px``). Default:
        the smallest ``k`` keeping about :data:`EXACT_PIXELS` exact pixels.
    tol_px : float
        Interpolation tolerance (input px) for ``step > 1``.
    chunk : int
        Output pixels per batch (memory).
    output_from_cam : ndarray, shape (3, 3), optional
        Rotation from the camera frame to the output frame (a rectified stereo
        frame, :func:`stereo_rectification`); default the identity.

    Returns
    -------
    RemapTables
    """
    if output_from_cam is not None:
        output_from_cam = np.asarray(output_from_cam, float)
        if output_from_cam.shape != (3, 3):
            raise ValueError(f"output_from_cam must have shape (3, 3), got {output_from_cam.shape}")
    fov_deg, size = default_geometry(camera, kind, fov_deg, size, output_from_cam)
    w, h = size
    if w <= 0 or h <= 0:
        raise ValueError(f"output size must be positive, got {w}x{h}")
    if kind == "perspective":
        f = _perspective_focal(w, fov_deg)
    else:
        span = 180.0 if kind == "epipolar" else 360.0
        if not 0 < fov_deg <= span:
            raise ValueError(f"{kind} longitude span must be in (0, {span:g}] deg, got {fov_deg}")
        f = w / math.radians(fov_deg)
    if step is None:
        step = max(1, int(math.ceil(math.sqrt(w * h / EXACT_PIXELS))))
    step = int(step)
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    grid = RayGrid(camera)

    def exact(uv: np.ndarray) -> np.ndarray:
        out = np.full((len(uv), 2), np.nan)
        for s in range(0, len(uv), chunk):
            rays = output_rays(kind, size, fov_deg, uv[s : s + chunk])
            if output_from_cam is not None:
                rays = rays @ output_from_cam  # cam_from_output @ ray, row-wise
            out[s : s + chunk] = project_rays(camera, rays, grid=grid)
        return out

    error = 0.0
    if step == 1:
        v, u = np.mgrid[0:h, 0:w]
        src = exact(np.column_stack([u.ravel(), v.ravel()]).astype(float))
        mx, my = src[:, 0].reshape(h, w), src[:, 1].reshape(h, w)
    else:
        cols = np.unique(np.append(np.arange(0, w, step), w - 1))
        rows = np.unique(np.append(np.arange(0, h, step), h - 1))
        gu, gv = np.meshgrid(cols, rows)
        nodes = exact(np.column_stack([gu.ravel(), gv.ravel()]).astype(float))
        mx = _bilinear(nodes[:, 0].reshape(len(rows), len(cols)), rows, cols, h, w)
        my = _bilinear(nodes[:, 1].reshape(len(rows), len(cols)), rows, cols, h, w)
        # cells touching the edge of the valid area or where the tables bend more than
        # bilinear interpolation follows: project those pixels exactly
        node_ok = np.isfinite(nodes[:, 0]).reshape(len(rows), len(cols)).astype(float)
        frac = _bilinear(node_ok, rows, cols, h, w)
        bent = _bilinear(_curved_nodes(nodes, len(rows), len(cols), tol_px), rows, cols, h, w)
        # (NaN * 0 spreads along node lines too: those pixels are redone as well)
        near = frac > 1e-9
        edge = np.flatnonzero(
            (near & ((frac < 1 - 1e-9) | ~np.isfinite(mx) | (bent > 1e-9))).ravel()
        )
        if len(edge):
            uv_edge = np.column_stack([edge % w, edge // w]).astype(float)
            src = exact(uv_edge)
            mx[edge // w, edge % w] = src[:, 0]
            my[edge // w, edge % w] = src[:, 1]
        error = _interpolation_error(exact, mx, my, w, h)
    valid = np.isfinite(mx) & np.isfinite(my)
    map_x = np.where(valid, mx, INVALID).astype(np.float32)
    map_y = np.where(valid, my, INVALID).astype(np.float32)
    return RemapTables(
        map_x, map_y, kind, float(fov_deg), K, float(np.mean(valid)), step, float(error)
    )


@dataclass
class StereoRectification:
    """The common frame of a rectified stereo pair.

    Attributes
    ----------
    left, right : str
        Camera ids.
    rect_from_left, rect_from_right : ndarray, shape (3, 3)
        Rotations from each camera's frame to the rectified frame (x along the
        baseline from the left to the right camera, z the mean optical axis made
        orthogonal to it, y = z x x).
    baseline : float
        Distance between the two perspective centres (the calibration's units).
    """

    left: str
    right: str
    rect_from_left: np.ndarray
    rect_from_right: np.ndarray
    baseline: float


def stereo_rectification(calib, left: str, right: str) -> StereoRectification:
    """Rectifying rotations of two cameras of a rig (``calibration@2``).

    In the rectified frame the baseline is the x axis, so every plane through it
    (an epipolar plane) is a row of the ``perspective`` and ``epipolar`` outputs.
    The z axis is the mean of the two optical axes made orthogonal to the baseline
    (the left camera's axis when the two point in opposite directions).

    Parameters
    ----------
    calib : RigCalibration
        Its ``cam_from_rig[id] = (R, t)``: ``p_cam = R p_rig + t``.
    left, right : str
        Camera ids.

    Returns
    -------
    StereoRectification

    Raises
    ------
    OptionsError
        An unknown camera, the same camera twice, or two cameras at one point (no
        baseline).
    """
    ids = list(getattr(calib, "camera_ids", []))
    for cid in (left, right):
        if cid not in ids:
            raise OptionsError(f"stereo camera {cid!r}: no such camera (cameras {ids})")
    if left == right:
        raise OptionsError(f"stereo needs two different cameras, got {left!r} twice")
    Rl, tl = (np.asarray(v, float) for v in calib.cam_from_rig[left])
    Rr, tr = (np.asarray(v, float) for v in calib.cam_from_rig[right])
    R = Rr @ Rl.T  # right_from_left: p_r = R p_l + t
    t = tr - R @ tl
    centre = -R.T @ t  # the right camera's centre in the left frame
    baseline = float(np.linalg.norm(centre))
    if not baseline > 1e-9:
        raise OptionsError(f"cameras {left!r} and {right!r} share one centre: no baseline")
    x = centre / baseline
    z = np.array([0.0, 0.0, 1.0]) + R.T @ np.array([0.0, 0.0, 1.0])
    if np.linalg.norm(z - (z @ x) * x) < 1e-6:  # opposite axes (or both along the baseline)
        z = np.array([0.0, 0.0, 1.0])
    z = z - (z @ x) * x
    if np.linalg.norm(z) < 1e-6:  # the left axis along the baseline: any perpendicular
        z = np.cross(x, [0.0, 1.0, 0.0]) if abs(x[1]) < 0.9 else np.cross(x, [1.0, 0.0, 0.0])
    z = z / np.linalg.norm(z)
    y = np.cross(z, x)
    rect_from_left = np.stack([x, y, z])
    return StereoRectification(left, right, rect_from_left, rect_from_left @ R.T, baseline)


def rectified_pixels(
    camera, rect_from_cam: np.ndarray, tables: RemapTables, uv_px: np.ndarray
) -> np.ndarray:
    """Where raw pixels of a camera land in its rectified image.

    Parameters
    ----------
    camera : SphereCamera
    rect_from_cam : ndarray, shape (3, 3)
        From :class:`StereoRectification`.
    tables : RemapTables
        The rectified image's tables (their projection, field of view and size).
    uv_px : ndarray, shape (N, 2)
        Raw pixels.

    Returns
    -------
    uv_rect_px : ndarray, shape (N, 2)
        NaN where the pixel has no ray.
    """
    rays = camera.unproject(np.asarray(uv_px, float)) @ np.asarray(rect_from_cam, float).T
    return output_pixels(tables.kind, tables.size, tables.fov_deg, rays)


def stereo_remap_tables(
    calib,
    left: str,
    right: str,
    kind: str = "epipolar",
    fov_deg: float | None = None,
    size: tuple[int, int] | None = None,
) -> tuple[StereoRectification, RemapTables, RemapTables]:
    """``cv2.remap`` tables rectifying a stereo pair of a rig into one frame.

    Parameters
    ----------
    calib : RigCalibration
    left, right : str
        Camera ids.
    kind : str
        ``"perspective"`` or ``"epipolar"`` (the whole field of view; see the
        module docstring).
    fov_deg : float, optional
        Longitude span (deg); default the union of the two cameras' fields.
    size : (int, int), optional
        Output ``(width, height)`` px of both images; default from the cameras.

    Returns
    -------
    (rectification, left_tables, right_tables)
    """
    if kind not in ("perspective", "epipolar"):
        raise ValueError(f"a stereo pair is rectified to perspective or epipolar, not {kind!r}")
    rect = stereo_rectification(calib, left, right)
    cams = [calib.cameras[left], calib.cameras[right]]
    rots = [rect.rect_from_left, rect.rect_from_right]
    fov_deg, size = default_geometry(cams, kind, fov_deg, size, rots)
    tables = [remap_tables(c, kind, fov_deg, size, output_from_cam=r) for c, r in zip(cams, rots)]
    return rect, tables[0], tables[1]


def _curved_nodes(nodes: np.ndarray, n_rows: int, n_cols: int, tol_px: float) -> np.ndarray:
    """1.0 at nodes (R, C) where bilinear interpolation may err by more than ``tol_px``.

    The error of linear interpolation between nodes is about a second
    difference / 8; nodes next to one whose second difference (along rows or
    columns, either table) exceeds ``8 tol_px`` or is undefined are flagged.
    """
    flag = np.zeros((n_rows, n_cols), bool)
    for k in range(2):
        m = nodes[:, k].reshape(n_rows, n_cols)
        for axis in (0, 1):
            if m.shape[axis] < 3:
                continue
            a = np.moveaxis(m, axis, 0)
            d2 = np.abs(a[2:] - 2 * a[1:-1] + a[:-2])
            bad = ~(d2 <= 8 * tol_px) & np.isfinite(a[1:-1])
            f = np.moveaxis(flag, axis, 0)
            f[1:-1] |= bad
            f[2:] |= bad
            f[:-2] |= bad
    return flag.astype(float)


def _bilinear(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, h: int, w: int):
    """Bilinear interpolation (H, W) of node values (R, C) at rows x cols; NaN spreads."""
    iu = np.clip(np.searchsorted(cols, np.arange(w), side="right") - 1, 0, len(cols) - 2)
    iv = np.clip(np.searchsorted(rows, np.arange(h), side="right") - 1, 0, len(rows) - 2)
    if len(cols) == 1 or len(rows) == 1:
        raise ValueError("output too small for step > 1; use step=1")
    tu = (np.arange(w) - cols[iu]) / (cols[iu + 1] - cols[iu])
    tv = (np.arange(h) - rows[iv]) / (rows[iv + 1] - rows[iv])
    top = values[iv][:, iu] * (1 - tu) + values[iv][:, iu + 1] * tu
    bottom = values[iv + 1][:, iu] * (1 - tu) + values[iv + 1][:, iu + 1] * tu
    return np.ascontiguousarray(top * (1 - tv[:, None]) + bottom * tv[:, None])


def _interpolation_error(exact, mx, my, w, h, n: int = 2000, seed: int = 0) -> float:
    """Largest distance (px) between interpolated and exact tables at random valid pixels."""
    ok = np.flatnonzero(np.isfinite(mx.ravel()))
    if len(ok) == 0:
        return 0.0
    pick = np.random.default_rng(seed).choice(ok, min(n, len(ok)), replace=False)
    uv = np.column_stack([pick % w, pick // w]).astype(float)
    ref = exact(uv)
    pv, pu = pick // w, pick % w
    err = np.hypot(mx[pv, pu] - ref[:, 0], my[pv, pu] - ref[:, 1])
    err = err[np.isfinite(err)]
    return float(err.max()) if len(err) else 0.0


def apply_remap(
    image: np.ndarray,
    tables: RemapTables,
    interpolation: int | None = None,
    border_value: float | tuple = 0,
) -> np.ndarray:
    """Resample a raw camera image with :func:`remap_tables` output.

    Parameters
    ----------
    image : ndarray, shape (height, width) or (height, width, channels)
        The camera's raw image (any dtype ``cv2.remap`` takes).
    tables : RemapTables
    interpolation : int, optional
        ``cv2.INTER_*``; default ``cv2.INTER_LINEAR``.
    border_value : scalar or tuple
        Value of output pixels without a source pixel.

    Returns
    -------
    out : ndarray, shape (H, W[, channels])
        Same dtype as ``image``.
    """
    import cv2

    if interpolation is None:
        interpolation = cv2.INTER_LINEAR
    return cv2.remap(
        image,
        tables.map_x,
        tables.map_y,
        interpolation,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border_value,
    )


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an image atomically; the format follows the extension of ``path`` (``.png`` ...).

    Raises
    ------
    ValueError
        OpenCV cannot encode that format.
    """
    import cv2

    suffix = Path(path).suffix or ".png"
    ok, data = cv2.imencode(suffix, image)
    if not ok:
        raise OptionsError(f"{path}: OpenCV cannot write a {suffix!r} image")
    return write_bytes_atomic(path, data.tobytes())


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise OptionsError(f"--size must look like 1920x1080, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise OptionsError(f"--size must be positive, got {text!r}")
    return w, h


# --------------------------------------------------------------------------- CLI


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere undistort``."""
    parser.add_argument(
        "calibration", help="gtsam-sphere/calibration@1 file, or @2 (rig) with --camera"
    )
    parser.add_argument("image", help="raw image of the calibrated camera")
    parser.add_argument(
        "--camera",
        default=None,
        metavar="ID",
        help="rig calibration (calibration@2): the camera that took the image",
    )
    parser.add_argument(
        "--to",
        required=True,
        choices=MONO_KINDS,
        dest="kind",
        help="projection (with --stereo: perspective, or equirectangular with the baseline "
        "as its polar axis, rows = epipolar planes)",
    )
    parser.add_argument(
        "--stereo",
        default=None,
        metavar="IMAGE",
        help="rig calibration: rectify a stereo pair; IMAGE is the second camera's image "
        "(--camera and --stereo-camera name the two cameras, default the rig's first two)",
    )
    parser.add_argument(
        "--stereo-camera", default=None, metavar="ID", help="--stereo: the second camera"
    )
    parser.add_argument(
        "--stereo-output", default=None, metavar="OUT", help="--stereo: the second output image"
    )
    parser.add_argument(
        "--fov-deg",
        type=float,
        default=None,
        help="horizontal field of view (perspective) or longitude span (others); "
        "default: the camera's own, perspective capped at "
        f"{PERSPECTIVE_MAX_FOV_DEG:g}",
    )
    parser.add_argument("--size", default=None, help="output WxH (default from the camera)")
    parser.add_argument("-o", "--output", required=True, help="output image (.png)")


def run_cli(args) -> int:
    """Run ``gtsam-sphere undistort``; 0 on success (bad input raises an ``InputError``)."""
    from ..io.calibration import load_calibration, single_camera

    calib = load_calibration(args.calibration)
    if not Path(args.image).is_file():
        raise DatasetError(f"{args.image}: no such image file")
    if getattr(args, "stereo", None) is not None:
        return _run_stereo(args, calib)
    for option in ("stereo_camera", "stereo_output"):
        if getattr(args, option, None) is not None:
            raise OptionsError(f"--{option.replace('_', '-')} applies to --stereo only")
    cam = single_camera(calib, getattr(args, "camera", None), args.calibration).camera
    image = _read_image(args.image, cam, args.calibration)
    try:
        tables = remap_tables(cam, args.kind, args.fov_deg, _parse_size(args.size))
    except ValueError as exc:
        raise DatasetError(f"{args.calibration}: {exc}") from None
    out = apply_remap(image, tables)
    path = write_image_atomic(args.output, out)
    w, h = tables.size
    print(
        f"wrote {path}: {args.kind} {w}x{h} px, field of view {tables.fov_deg:.1f} deg, "
        f"{100 * tables.valid_fraction:.1f}% of the output has a source pixel"
    )
    return 0


def _read_image(path, cam, calibration_path) -> np.ndarray:
    """The image at ``path``, checked against the camera's size (``DatasetError`` if not)."""
    import cv2

    if not Path(path).is_file():
        raise DatasetError(f"{path}: no such image file")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: not an image cv2 can read")
    if image.shape[1] != cam.width or image.shape[0] != cam.height:
        raise DatasetError(
            f"{path}: image is {image.shape[1]}x{image.shape[0]} px but calibration "
            f"{calibration_path} is for {cam.width}x{cam.height} px"
        )
    return image


def _run_stereo(args, calib) -> int:
    """``undistort --stereo``: both images of a rig's pair into one rectified frame."""
    if not hasattr(calib, "camera_ids"):
        raise OptionsError(f"--stereo needs a rig calibration (calibration@2): {args.calibration}")
    if args.stereo_output is None:
        raise OptionsError("--stereo needs --stereo-output OUT for the second image")
    ids = calib.camera_ids
    if len(ids) < 2:
        raise OptionsError(f"--stereo: {args.calibration} has one camera ({ids})")
    left = args.camera if args.camera is not None else ids[0]
    right = args.stereo_camera
    if right is None:
        right = next(c for c in ids if c != left)
    rect, lt, rt = stereo_remap_tables(
        calib, left, right, STEREO_KINDS[args.kind], args.fov_deg, _parse_size(args.size)
    )
    images = [
        _read_image(p, calib.cameras[c], args.calibration)
        for p, c in ((args.image, left), (args.stereo, right))
    ]
    paths = [
        write_image_atomic(out, apply_remap(img, t))
        for out, img, t in ((args.output, images[0], lt), (args.stereo_output, images[1], rt))
    ]
    w, h = lt.size
    print(
        f"rectified {left} / {right} (baseline {rect.baseline:.4g} {calib.units}): "
        f"{STEREO_KINDS[args.kind]} {w}x{h} px, field of view {lt.fov_deg:.1f} deg; "
        f"rows are epipolar planes"
    )
    for path, t in zip(paths, (lt, rt)):
        print(f"wrote {path}: {100 * t.valid_fraction:.1f}% of the output has a source pixel")
    return 0
