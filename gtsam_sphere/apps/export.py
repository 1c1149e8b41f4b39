"""Export a calibrated camera to standard models: OpenCV fisheye / rational, Kalibr.

The calibrated camera (:class:`~gtsam_sphere.core.camera.SphereCamera`) is a ray
field: every pixel of the observed region has a ray. A standard model is
fitted to that field by Levenberg-Marquardt (numpy, analytic Jacobians),
minimising the pixel distance between the standard model's projection of
each ray and the pixel the calibrated camera assigns to it. What the export
loses is reported with it (:class:`ExportResult`): the fit residual in
pixels (RMS, 95th percentile, max) over the rays the standard model can
represent, and the fraction of the observed region it covers.

Targets (``TARGETS``)

``opencv-fisheye``
    Kannala-Brandt as ``cv2.fisheye`` uses it: ``theta = atan(r)``, ``r =
    |(x, y)| / z``, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3
    theta^6 + k4 theta^8)``, ``u = fx theta_d x / |(x, y)| + cx`` (likewise
    ``v``); ``K`` (3x3, no skew) and ``D = (k1, k2, k3, k4)``.
    ``cv2.fisheye`` cannot project rays at or beyond 90 deg (``z <= 0``):
    they are left out of the fit and counted as not covered.
``opencv-rational``
    Pinhole ``K`` with ``dist = (k1, k2, p1, p2, k3, k4, k5, k6)``
    (``cv2.CALIB_RATIONAL_MODEL``), over rays below ``max_incidence_deg``
    (80 deg by default; a pinhole image goes to infinity at 90 deg).
``kalibr-equi``
    Kalibr ``pinhole`` + ``equidistant``: the same model as
    ``opencv-fisheye``, written as a camchain YAML.
``kalibr-ds``
    Kalibr ``ds``, the double-sphere model (Usenko et al. 2018)
    ``intrinsics = [xi, alpha, fu, fv, pu, pv]``: ``d1 = |P|``, ``w = xi d1
    + z``, ``d2 = |(x, y, w)|``, ``u = fu x / (alpha d2 + (1 - alpha) w) +
    pu``; valid where ``z > -w2 d1`` (Eq. 43 of the paper), which reaches past
    90 deg, so fields of view beyond 180 deg are representable.
``opencv-omnidir``
    The unified (Mei) model of ``cv2.omnidir`` (opencv_contrib): the ray is
    put on the unit sphere, ``xs = P / |P|``, projected from ``(0, 0, -xi)``:
    ``a = xs_x / (xs_z + xi)``, ``b = xs_y / (xs_z + xi)``, then radial-
    tangential distortion ``D = (k1, k2, p1, p2)`` and ``K`` (no skew);
    valid where ``xs_z > -min(xi, 1 / xi)`` (beyond 90 deg for ``xi > 0``):
    catadioptric and >180 deg fisheye lenses.
``kalibr-omni``
    Kalibr ``omni`` + ``radtan`` (``intrinsics = [xi, fu, fv, pu, pv]``): the
    same model as ``opencv-omnidir``, written as a camchain YAML.
``kalibr-eucm``
    Kalibr ``eucm`` + ``none`` (basalt's ``eucm``), the extended unified model
    (Khomutenko et al. 2016) ``intrinsics = [alpha, beta, fu, fv, pu, pv]``: ``d =
    sqrt(beta (x^2 + y^2) + z^2)``, ``u = fu x / (alpha d + (1 - alpha) z) + pu``;
    reaches past 90 deg.

Fits the format exports use (``FORMAT_FITS``, written by
:mod:`gtsam_sphere.apps.export_formats` as ``--to ros``, ``mrcal``, ``basalt``):

``opencv-plumb-bob``
    ``opencv-rational`` with ``k4 = k5 = k6 = 0`` (ROS ``plumb_bob``).
``mrcal-splined``
    mrcal's ``LENSMODEL_SPLINED_STEREOGRAPHIC_order=3`` (:mod:`gtsam_sphere.apps.splined`):
    the intrinsics core fixed from the principal point and the focal length near the
    axis, the spline's control points fitted with a smoothness prior
    (``SPLINE_SMOOTHING``), ``SPLINE_NX`` control points across a valid region
    spanning the whole image.

Every target uses OpenCV's pixel convention (``(0, 0)`` is the centre of
the top-left pixel), as this package does; no half-pixel shift is applied.

Observed region: the pixels a calibration is trustworthy at. With the
calibration's observations (``extra["observations"]["uv_px"]``) it is their
convex hull (``region="hull"``, the default) or the disc around the
principal point through the farthest one (``"radius"``); without them, or
with ``"image"``, the whole image where the camera has a ray. The region is
sampled on a regular pixel grid (about ``n_samples`` pixels), each pixel
unprojected to its ray (the camera's ``pixel_hemisphere`` says which half of
the image sphere a pixel lies on; :mod:`gtsam_sphere.core.rays`).

Inside and outside: the fit error (``rms_px``, ``max_px``) is the error
inside the observed region. A standard model fitted there can diverge fast
beyond it, so every export also measures its error outside
(:func:`outside_statistics`, ``ExportResult.outside``): image pixels whose
rays lie between the observed region's widest ray and ``OUTSIDE_BAND_DEG``
(20 deg) beyond it (at most the camera's one-to-one field), per
``OUTSIDE_STEP_DEG`` (5 deg) band, against the calibration's own pixels.
When that error exceeds ``OUTSIDE_WARN_PX`` (1 px) the export logs a
warning naming the incidence past which the model must not be used; the
summary, the JSON ``fit.outside`` block and the YAML comments state both
errors.

Files: ``opencv-*`` write JSON (``format: "gtsam-sphere/export-opencv@1"``:
``image_size = [width, height]``, ``K``, ``D`` or ``dist``, ``xi`` for
``opencv-omnidir``, ``fit``), ``kalibr-*`` write a camchain YAML (``cam0:
camera_model, intrinsics, distortion_model, distortion_coeffs, resolution``)
with the fit residual in comments. Both are written atomically.

Rigs (``calibration@2``): ``--camera ID`` exports one camera with any target;
``--to kalibr`` (a camchain of every camera with ``T_cn_cnm1``) and ``--to
opencv-stereo`` (``R``, ``T`` and two cameras' models) are
:mod:`gtsam_sphere.apps.export_rig`.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# the ray helpers live in the core; re-exported here for the export's callers
from ..core.geometry import incidence_deg as incidence_deg
from ..core.least_squares import Damping, LMResult
from ..core.least_squares import levenberg_marquardt as _levenberg_marquardt
from ..core.rays import RayGrid as RayGrid
from ..core.rays import pixel_rays as pixel_rays
from ..core.rays import project_rays as project_rays
from ..io.dataset import DatasetError, write_bytes_atomic, write_json_atomic
from .splined import SplineConfig, choose_config, spline_weights, splined_project, stereographic_u

logger = logging.getLogger(__name__)

TARGETS: tuple[str, ...] = (
    "opencv-fisheye",
    "opencv-rational",
    "opencv-omnidir",
    "kalibr-equi",
    "kalibr-ds",
    "kalibr-omni",
    "kalibr-eucm",
)
#: fits the format exports use (:mod:`gtsam_sphere.apps.export_formats`: ROS ``plumb_bob``,
#: mrcal's splined model), not written on their own
FORMAT_FITS: tuple[str, ...] = ("opencv-plumb-bob", "mrcal-splined")
#: model family fitted for each target
TARGET_FAMILY: dict[str, str] = {
    "opencv-fisheye": "kannala-brandt",
    "kalibr-equi": "kannala-brandt",
    "opencv-rational": "rational",
    "kalibr-ds": "double-sphere",
    "opencv-omnidir": "omni",
    "kalibr-omni": "omni",
    "opencv-plumb-bob": "plumb-bob",
    "kalibr-eucm": "eucm",
    "mrcal-splined": "splined-stereographic",
}
REGIONS: tuple[str, ...] = ("hull", "radius", "image")
EXPORT_FORMAT = "gtsam-sphere/export-opencv@1"
#: default incidence limit (deg) of the rational (pinhole) export
RATIONAL_MAX_INCIDENCE_DEG = 80.0
#: width (deg) of the incidence band beyond the observed field where an export's error is measured
OUTSIDE_BAND_DEG = 20.0
#: width (deg) of the sub-bands of that band reported one by one
OUTSIDE_STEP_DEG = 5.0
#: error (px) outside the observed field above which an export warns
OUTSIDE_WARN_PX = 1.0

# parameter names of each fitted model, in the order of the parameter vector
_KB_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
_RATIONAL_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
_DS_NAMES = ("xi", "alpha", "fx", "fy", "cx", "cy")
_OMNI_NAMES = ("xi", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
_PLUMB_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_EUCM_NAMES = ("alpha", "beta", "fx", "fy", "cx", "cy")
_CORE_NAMES = ("fx", "fy", "cx", "cy")
_FAMILY_NAMES = {
    "kannala-brandt": _KB_NAMES,
    "rational": _RATIONAL_NAMES,
    "double-sphere": _DS_NAMES,
    "omni": _OMNI_NAMES,
    "plumb-bob": _PLUMB_NAMES,
    "eucm": _EUCM_NAMES,
    "splined-stereographic": _CORE_NAMES,
}
#: default control points across of the ``mrcal-splined`` fit
SPLINE_NX = 16
#: weight (px of residual per px of second difference) of the spline's smoothness prior
SPLINE_SMOOTHING = 0.01
#: weight of the image pixels beyond the observed field in the spline fit (the observed region's: 1)
SPLINE_OUTSIDE_WEIGHT = 0.1
#: at most this many region samples enter the (dense) spline fit
SPLINE_MAX_FIT_SAMPLES = 6000


# --------------------------------------------------------------------------- observed region


@dataclass
class RegionSample:
    """Pixels sampled over a camera's observed region and their rays.

    Attributes
    ----------
    uv_px : ndarray, shape (N, 2)
        Raw pixels on a regular grid (OpenCV convention).
    rays : ndarray, shape (N, 3)
        Unit rays of those pixels, camera frame (x right, y down, z forward).
    step_px : float
        Grid spacing (px); each sample stands for ``step_px**2`` px of image.
    description : str
        What the region is, for messages.
    """

    uv_px: np.ndarray
    rays: np.ndarray
    step_px: float
    description: str

    def __len__(self) -> int:
        return len(self.uv_px)

    @property
    def incidence_deg(self) -> np.ndarray:
        """Incidence angle (deg) of each sample's ray, shape (N,)."""
        return incidence_deg(self.rays)


def _inside_convex(points: np.ndarray, hull: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Points (N, 2) inside or on a convex polygon ``hull`` (V, 2) in either orientation."""
    if len(hull) < 3:
        return np.zeros(len(points), bool)
    a = hull
    e = np.roll(hull, -1, axis=0) - hull
    inside = np.empty(len(points), bool)
    for s in range(0, len(points), 8192):
        p = points[s : s + 8192]
        cross = e[None, :, 0] * (p[:, None, 1] - a[None, :, 1]) - e[None, :, 1] * (
            p[:, None, 0] - a[None, :, 0]
        )
        scale = tol * max(1.0, float(np.abs(hull).max()))
        inside[s : s + 8192] = np.all(cross >= -scale, axis=1) | np.all(cross <= scale, axis=1)
    return inside


def sample_region(
    camera,
    observations_uv_px: np.ndarray | None = None,
    region: str = "hull",
    n_samples: int = 20000,
) -> RegionSample:
    """Sample the observed region of a camera on a pixel grid and unproject it.

    Parameters
    ----------
    camera : SphereCamera
    observations_uv_px : ndarray, shape (M, 2), optional
        Observed pixels of the calibration. Without them (or fewer than 3
        finite ones) the region is the whole image.
    region : {"hull", "radius", "image"}
        ``hull``: convex hull of the observations; ``radius``: disc around
        the principal point through the farthest observation, clipped to the
        image; ``image``: the whole image. Always limited to the pixels where
        the camera has a ray.
    n_samples : int
        About how many grid pixels to sample.

    Returns
    -------
    RegionSample

    Raises
    ------
    ValueError
        Unknown ``region`` or an empty region.
    """
    if region not in REGIONS:
        raise ValueError(f"unknown region {region!r}; choose from {REGIONS}")
    w, h = int(camera.width), int(camera.height)
    obs = None
    if observations_uv_px is not None:
        obs = np.asarray(observations_uv_px, float).reshape(-1, 2)
        obs = obs[np.all(np.isfinite(obs), axis=1)]
        if len(obs) < 3:
            obs = None
    kind = region if obs is not None else "image"
    if kind == "hull":
        import cv2

        hull = cv2.convexHull(obs.astype(np.float32)).reshape(-1, 2).astype(float)
        area = float(cv2.contourArea(hull.astype(np.float32)))
        desc = f"convex hull of {len(obs)} observed pixels"
    elif kind == "radius":
        pp = np.array([camera.xp, camera.yp], float)
        r_max = float(np.max(np.linalg.norm(obs - pp, axis=1)))
        area = min(math.pi * r_max**2, float(w * h))
        desc = f"disc of radius {r_max:.1f} px around the principal point (farthest observation)"
    else:
        area = float(w * h)
        desc = "whole image" + (" (no observations in the calibration)" if obs is None else "")
    step = math.sqrt(max(area, 1.0) / max(int(n_samples), 16))
    gu = np.arange(-0.5 + step / 2, w - 0.5, step)
    gv = np.arange(-0.5 + step / 2, h - 0.5, step)
    uv = np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)
    if kind == "hull":
        uv = uv[_inside_convex(uv, hull)]
    elif kind == "radius":
        uv = uv[np.linalg.norm(uv - pp, axis=1) <= r_max]
    rays = pixel_rays(camera, uv)
    ok = np.all(np.isfinite(rays), axis=1)
    if not ok.any():
        raise ValueError(f"the observed region ({desc}) holds no pixel with a ray")
    n_out = int((~ok).sum())
    if n_out:
        desc += f", {n_out} grid pixels without a ray left out"
    return RegionSample(uv[ok], rays[ok], step, desc)


# --------------------------------------------------------------------------- model functions


def kb_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """Kannala-Brandt (``cv2.fisheye``) projection of rays with ``z > 0``.

    Parameters
    ----------
    params : ndarray, shape (8,)
        ``fx, fy, cx, cy`` (px) and ``k1..k4`` (dimensionless).
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward); meaningful for ``z > 0``.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 8).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    fx, fy, cx, cy, k1, k2, k3, k4 = (float(v) for v in params)
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    rxy = np.hypot(x, y)
    theta = np.arctan2(rxy, z)
    t2 = theta * theta
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    with np.errstate(invalid="ignore", divide="ignore"):
        t_over_r = np.where(rxy > 1e-12 * np.abs(z), theta / np.where(rxy > 0, rxy, 1.0), 1 / z)
    xd = t_over_r * poly * x
    yd = t_over_r * poly * y
    uv = np.column_stack([fx * xd + cx, fy * yd + cy])
    if not jacobians:
        return uv
    J = np.zeros((len(rays), 2, 8))
    J[:, 0, 0] = xd
    J[:, 1, 1] = yd
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    for i in range(4):
        tp = t_over_r * t2 ** (i + 1)
        J[:, 0, 4 + i] = fx * tp * x
        J[:, 1, 4 + i] = fy * tp * y
    return uv, J


def rational_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """OpenCV rational pinhole projection (``CALIB_RATIONAL_MODEL``) of rays with ``z > 0``.

    ``a, b = x / z, y / z``, ``r2 = a^2 + b^2``, ``R = (1 + k1 r2 + k2 r2^2 +
    k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)``, ``x'' = a R + 2 p1 a b + p2
    (r2 + 2 a^2)``, ``y'' = b R + p1 (r2 + 2 b^2) + 2 p2 a b``, ``u = fx x'' +
    cx``, ``v = fy y'' + cy``.

    Parameters
    ----------
    params : ndarray, shape (12,)
        ``fx, fy, cx, cy`` (px), then ``k1, k2, p1, p2, k3, k4, k5, k6``
        (OpenCV's order of ``dist``).
    rays : ndarray, shape (N, 3)
        Camera frame; meaningful for ``z > 0``.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 12).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in params)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = rays[:, 0] / rays[:, 2]
        b = rays[:, 1] / rays[:, 2]
    r2 = a * a + b * b
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    R = num / den
    xd = a * R + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
    yd = b * R + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
    uv = np.column_stack([fx * xd + cx, fy * yd + cy])
    if not jacobians:
        return uv
    J = np.zeros((len(rays), 2, 12))
    J[:, 0, 0] = xd
    J[:, 1, 1] = yd
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    for col, power in ((4, 1), (5, 2), (8, 3)):  # k1, k2, k3: numerator
        J[:, 0, col] = fx * a * r2**power / den
        J[:, 1, col] = fy * b * r2**power / den
    for col, power in ((9, 1), (10, 2), (11, 3)):  # k4, k5, k6: denominator
        J[:, 0, col] = -fx * a * num * r2**power / den**2
        J[:, 1, col] = -fy * b * num * r2**power / den**2
    J[:, 0, 6] = fx * 2 * a * b
    J[:, 1, 6] = fy * (r2 + 2 * b * b)
    J[:, 0, 7] = fx * (r2 + 2 * a * a)
    J[:, 1, 7] = fy * 2 * a * b
    return uv, J


def ds_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """Double-sphere projection (Usenko et al. 2018, Eq. 40-41).

    Parameters
    ----------
    params : ndarray, shape (6,)
        ``xi, alpha`` (dimensionless), ``fx, fy, cx, cy`` (px).
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward), any direction; see
        :func:`ds_valid` for where the model is defined.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 6).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    xi, alpha, fx, fy, cx, cy = (float(v) for v in params)
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    d1 = np.sqrt(x * x + y * y + z * z)
    w = xi * d1 + z
    d2 = np.sqrt(x * x + y * y + w * w)
    den = alpha * d2 + (1 - alpha) * w
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = x / den
        my = y / den
    uv = np.column_stack([fx * mx + cx, fy * my + cy])
    if not jacobians:
        return uv
    dden_dxi = alpha * w * d1 / d2 + (1 - alpha) * d1
    dden_dalpha = d2 - w
    J = np.zeros((len(rays), 2, 6))
    with np.errstate(invalid="ignore", divide="ignore"):
        J[:, 0, 0] = -fx * mx / den * dden_dxi
        J[:, 1, 0] = -fy * my / den * dden_dxi
        J[:, 0, 1] = -fx * mx / den * dden_dalpha
        J[:, 1, 1] = -fy * my / den * dden_dalpha
    J[:, 0, 2] = mx
    J[:, 1, 3] = my
    J[:, 0, 4] = 1.0
    J[:, 1, 5] = 1.0
    return uv, J


def ds_valid(params: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Rays (N, 3) the double-sphere model projects (Usenko et al. 2018, Eq. 43), (N,) bool.

    ``z > -w2 |P|`` with ``w1 = alpha / (1 - alpha)`` if ``alpha <= 0.5``
    else ``(1 - alpha) / alpha`` and ``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2
    + 1)``; also ``0 <= alpha <= 1`` and a positive denominator.
    """
    xi, alpha = float(params[0]), float(params[1])
    n = len(rays)
    if not (0.0 <= alpha <= 1.0) or not math.isfinite(xi):
        return np.zeros(n, bool)
    w1 = alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha
    w2 = (w1 + xi) / math.sqrt(max(2 * w1 * xi + xi * xi + 1, 1e-300))
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    d1 = np.sqrt(x * x + y * y + z * z)
    w = xi * d1 + z
    den = alpha * np.sqrt(x * x + y * y + w * w) + (1 - alpha) * w
    return (z > -w2 * d1) & (den > 0)


def omni_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """Unified (Mei) projection with radial-tangential distortion (``cv2.omnidir``, Kalibr
    ``omni-radtan``).

    ``xs = P / |P|``, ``a = xs_x / (xs_z + xi)``, ``b = xs_y / (xs_z + xi)``, ``r2 = a^2 +
    b^2``, ``R = 1 + k1 r2 + k2 r2^2``, ``x'' = a R + 2 p1 a b + p2 (r2 + 2 a^2)``, ``y'' =
    b R + p1 (r2 + 2 b^2) + 2 p2 a b``, ``u = fx x'' + cx``, ``v = fy y'' + cy``.

    Parameters
    ----------
    params : ndarray, shape (9,)
        ``xi`` (dimensionless), ``fx, fy, cx, cy`` (px), ``k1, k2, p1, p2``.
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward), any direction; see
        :func:`omni_valid` for where the model is defined.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 9).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    xi, fx, fy, cx, cy, k1, k2, p1, p2 = (float(v) for v in params)
    d = np.linalg.norm(rays, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        den = rays[:, 2] / d + xi
        a = rays[:, 0] / d / den
        b = rays[:, 1] / d / den
    r2 = a * a + b * b
    R = 1 + r2 * (k1 + r2 * k2)
    xd = a * R + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
    yd = b * R + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
    uv = np.column_stack([fx * xd + cx, fy * yd + cy])
    if not jacobians:
        return uv
    dR = k1 + 2 * k2 * r2  # dR / dr2
    dxd_da = R + 2 * a * a * dR + 2 * p1 * b + 6 * p2 * a
    dxd_db = 2 * a * b * dR + 2 * p1 * a + 2 * p2 * b
    dyd_da = 2 * a * b * dR + 2 * p1 * a + 2 * p2 * b
    dyd_db = R + 2 * b * b * dR + 6 * p1 * b + 2 * p2 * a
    with np.errstate(invalid="ignore", divide="ignore"):
        da, db = -a / den, -b / den  # d a / d xi, d b / d xi
    J = np.zeros((len(rays), 2, 9))
    J[:, 0, 0] = fx * (dxd_da * da + dxd_db * db)
    J[:, 1, 0] = fy * (dyd_da * da + dyd_db * db)
    J[:, 0, 1] = xd
    J[:, 1, 2] = yd
    J[:, 0, 3] = 1.0
    J[:, 1, 4] = 1.0
    J[:, 0, 5] = fx * a * r2
    J[:, 1, 5] = fy * b * r2
    J[:, 0, 6] = fx * a * r2 * r2
    J[:, 1, 6] = fy * b * r2 * r2
    J[:, 0, 7] = fx * 2 * a * b
    J[:, 1, 7] = fy * (r2 + 2 * b * b)
    J[:, 0, 8] = fx * (r2 + 2 * a * a)
    J[:, 1, 8] = fy * 2 * a * b
    return uv, J


def omni_valid(params: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Rays (N, 3) the unified model projects one-to-one: ``xs_z > -min(xi, 1 / xi)``, (N,) bool.

    For ``xi <= 1`` the limit is where the projection centre's denominator
    vanishes, for ``xi > 1`` where the mapping folds back (Mei 2007, Kalibr's
    ``omni`` model); ``xi`` must be non-negative.
    """
    xi = float(params[0])
    n = len(rays)
    if not (xi >= 0.0 and math.isfinite(xi)):
        return np.zeros(n, bool)
    limit = xi if xi <= 1.0 else 1.0 / xi
    d = np.linalg.norm(rays, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (rays[:, 2] / d > -limit + 1e-9) & (d > 0)


def plumb_bob_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """OpenCV's five-coefficient pinhole model (ROS ``plumb_bob``) of rays with ``z > 0``.

    :func:`rational_project` with ``k4 = k5 = k6 = 0``.

    Parameters
    ----------
    params : ndarray, shape (9,)
        ``fx, fy, cx, cy`` (px), then ``k1, k2, p1, p2, k3`` (OpenCV's order).
    rays : ndarray, shape (N, 3)
        Camera frame; meaningful for ``z > 0``.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 9).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    full = np.concatenate([np.asarray(params, float)[:9], np.zeros(3)])
    out = rational_project(full, rays, jacobians)
    if not jacobians:
        return out
    uv, J = out
    return uv, J[:, :, :9]


def eucm_project(params: np.ndarray, rays: np.ndarray, jacobians: bool = False):
    """Extended unified camera model (Khomutenko et al. 2016; basalt ``eucm``).

    ``d = sqrt(beta (x^2 + y^2) + z^2)``, ``den = alpha d + (1 - alpha) z``, ``u = fx x /
    den + cx``, ``v = fy y / den + cy``.

    Parameters
    ----------
    params : ndarray, shape (6,)
        ``alpha, beta`` (dimensionless), ``fx, fy, cx, cy`` (px).
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward), any direction; see
        :func:`eucm_valid` for where the model is defined.
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 6).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
    """
    alpha, beta, fx, fy, cx, cy = (float(v) for v in params)
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    r2 = x * x + y * y
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(beta * r2 + z * z)
        den = alpha * d + (1 - alpha) * z
        mx = x / den
        my = y / den
    uv = np.column_stack([fx * mx + cx, fy * my + cy])
    if not jacobians:
        return uv
    J = np.zeros((len(rays), 2, 6))
    with np.errstate(invalid="ignore", divide="ignore"):
        dden_dalpha = d - z
        dden_dbeta = alpha * r2 / (2 * d)
        J[:, 0, 0] = -fx * mx / den * dden_dalpha
        J[:, 1, 0] = -fy * my / den * dden_dalpha
        J[:, 0, 1] = -fx * mx / den * dden_dbeta
        J[:, 1, 1] = -fy * my / den * dden_dbeta
    J[:, 0, 2] = mx
    J[:, 1, 3] = my
    J[:, 0, 4] = 1.0
    J[:, 1, 5] = 1.0
    return uv, J


def eucm_valid(params: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Rays (N, 3) the extended unified model projects one-to-one, (N,) bool.

    ``z > -w d`` (``d`` as in :func:`eucm_project`) with ``w = alpha / (1 - alpha)`` for
    ``alpha <= 0.5`` (a positive denominator) and ``w = (1 - alpha) / alpha`` for ``alpha
    > 0.5`` (where the mapping folds back), as Usenko et al. 2018 (Sec. III) state it;
    also ``0 <= alpha <= 1`` and ``beta > 0``.
    """
    alpha, beta = float(params[0]), float(params[1])
    n = len(rays)
    if not (0.0 <= alpha <= 1.0) or not (beta > 0.0 and math.isfinite(beta)):
        return np.zeros(n, bool)
    if alpha <= 0.5:
        w = alpha / (1 - alpha)
    else:
        w = (1 - alpha) / alpha
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    d = np.sqrt(beta * (x * x + y * y) + z * z)
    den = alpha * d + (1 - alpha) * z
    return (z > -w * d) & (den > 0)


# --------------------------------------------------------------------------- least squares


#: the export's damping: Marquardt's scaling, x4 on a worse step, /3 on a better one
_EXPORT_DAMPING = Damping(
    initial=1e-3, increase=4.0, increase_singular=10.0, decrease=3.0, floor=1e-12, ceiling=1e16
)


def levenberg_marquardt(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0: np.ndarray,
    feasible: Callable[[np.ndarray], bool] | None = None,
    max_iterations: int = 200,
    rtol: float = 1e-12,
) -> LMResult:
    """Minimise ``sum(r(x)^2)`` by Levenberg-Marquardt with Marquardt's diagonal scaling.

    The loop is :func:`gtsam_sphere.core.least_squares.levenberg_marquardt`.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (r (M,), J (M, P))``: residuals and their Jacobian.
    x0 : ndarray, shape (P,)
        Start; must be feasible.
    feasible : callable, optional
        ``feasible(x) -> bool``; a step to an infeasible point is rejected
        like one that increases the cost (a barrier).
    max_iterations : int
    rtol : float
        Stop when an accepted step lowers the cost by less than ``rtol``
        times the cost.

    Returns
    -------
    LMResult
        ``converged`` unless the iteration limit stopped it (a stall, no step
        lowering the cost at this precision, counts as converged).
    """
    last: dict = {}

    def cost(x):
        r, J = fun(x)
        last["x"], last["r"], last["J"] = x, r, J
        return float(r @ r)

    def linearize(x):
        if last.get("x") is not x:
            cost(x)
        J, r = last["J"], last["r"]
        return J.T @ J, J.T @ r

    def small(c_old, c_new, _delta):
        return c_old - c_new <= rtol * c_old or c_new == 0.0

    x0 = np.asarray(x0, float).copy()
    return _levenberg_marquardt(
        x0,
        cost,
        linearize,
        converged=small,
        feasible=feasible,
        damping=_EXPORT_DAMPING,
        max_iterations=max_iterations,
    )


def _fit(project_fn, params0, rays, uv, feasible=None, max_iterations=200) -> LMResult:
    """Least-squares fit of ``project_fn(params, rays)`` to ``uv`` (N, 2) px."""

    def fun(p):
        pred, J = project_fn(p, rays, jacobians=True)
        return (pred - uv).ravel(), J.reshape(-1, len(p))

    return levenberg_marquardt(fun, params0, feasible, max_iterations)


# --------------------------------------------------------------------------- initial values


def _radial_polynomial_init(rays, uv, pp, n_terms):
    """Fit ``|uv - pp| = f (theta + k1 theta^3 + ...)`` linearly; returns ``(f, ks)``."""
    theta = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
    rpix = np.linalg.norm(uv - pp, axis=1)
    A = np.column_stack([theta ** (2 * i + 1) for i in range(n_terms + 1)])
    sol, *_ = np.linalg.lstsq(A, rpix, rcond=None)
    f = float(sol[0]) if sol[0] > 0 else float(np.median(rpix / np.maximum(theta, 1e-9)))
    return f, sol[1:] / f if sol[0] > 0 else np.zeros(n_terms)


def _kb_initial(rays, uv, pp) -> np.ndarray:
    f, ks = _radial_polynomial_init(rays, uv, pp, 4)
    return np.array([f, f, pp[0], pp[1], *ks])


def _rational_initial(rays, uv, pp) -> np.ndarray:
    f, _ = _radial_polynomial_init(rays, uv, pp, 4)
    rho_u = np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]
    rho_d = np.linalg.norm(uv - pp, axis=1) / f
    r2 = rho_u**2
    # rho_d (1 + k4 r2 + k5 r2^2 + k6 r2^3) = rho_u (1 + k1 r2 + k2 r2^2 + k3 r2^3)
    A = np.column_stack(
        [rho_u * r2, rho_u * r2**2, rho_u * r2**3, -rho_d * r2, -rho_d * r2**2, -rho_d * r2**3]
    )
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, *_ = np.linalg.lstsq(A / scale, rho_d - rho_u, rcond=None)
    k = sol / scale
    params = np.array([f, f, pp[0], pp[1], k[0], k[1], 0.0, 0.0, k[2], k[3], k[4], k[5]])
    if not _rational_feasible(params, rays):
        # a denominator crossing zero: start from the polynomial part alone
        A = A[:, :3]
        sol, *_ = np.linalg.lstsq(A / scale[:3], rho_d - rho_u, rcond=None)
        k = sol / scale[:3]
        params = np.array([f, f, pp[0], pp[1], k[0], k[1], 0.0, 0.0, k[2], 0.0, 0.0, 0.0])
    return params


def _rational_feasible(params, rays) -> bool:
    k4, k5, k6 = params[9:12]
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = (rays[:, 0] ** 2 + rays[:, 1] ** 2) / rays[:, 2] ** 2
    # the denominator must stay positive from the axis to the widest ray
    grid = np.linspace(0.0, float(np.max(r2)) if len(r2) else 1.0, 512)
    return bool(np.all(1 + grid * (k4 + grid * (k5 + grid * k6)) > 0))


def _grid_initial(rays, uv, pp, shapes, params_of, valid_of, project_of, what) -> np.ndarray:
    """A start for a model with shape parameters: over the grid ``shapes`` (no distortion),
    focal lengths solved linearly; the most valid rays, then the lowest cost, win.
    ``params_of(shape, fx, fy)`` builds the parameter vector."""
    best = None
    sub = np.unique(np.linspace(0, len(rays) - 1, min(len(rays), 2000)).astype(int))
    rs = rays[sub]
    du = uv[sub, 0] - pp[0]
    dv = uv[sub, 1] - pp[1]
    for shape in shapes:
        p = params_of(shape, 1.0, 1.0)
        n_valid = int(valid_of(p, rays).sum())
        valid = valid_of(p, rs)
        if valid.sum() < 10:
            continue
        m = project_of(p, rs[valid]) - pp
        fx = float(m[:, 0] @ du[valid] / max(m[:, 0] @ m[:, 0], 1e-300))
        fy = float(m[:, 1] @ dv[valid] / max(m[:, 1] @ m[:, 1], 1e-300))
        if not (fx > 0 and fy > 0):
            continue
        res = np.column_stack([fx * m[:, 0] - du[valid], fy * m[:, 1] - dv[valid]])
        key = (-n_valid, float(np.sum(res**2)))
        if best is None or key < best[0]:
            best = (key, params_of(shape, fx, fy))
    if best is None:
        raise ValueError(f"no {what} start projects the observed region")
    return best[1]


def _omni_initial(rays, uv, pp) -> np.ndarray:
    """Grid over ``xi`` (:func:`_grid_initial`)."""
    return _grid_initial(
        rays, uv, pp, np.linspace(0.0, 3.0, 31),
        lambda xi, fx, fy: np.array([xi, fx, fy, pp[0], pp[1], 0.0, 0.0, 0.0, 0.0]),
        omni_valid, omni_project, "unified-model",
    )  # fmt: skip


def _ds_initial(rays, uv, pp) -> np.ndarray:
    """Grid over ``(xi, alpha)`` (:func:`_grid_initial`)."""
    shapes = [(xi, a) for xi in np.linspace(-0.6, 1.6, 23) for a in np.linspace(0.0, 0.95, 20)]
    return _grid_initial(
        rays, uv, pp, shapes,
        lambda s, fx, fy: np.array([s[0], s[1], fx, fy, pp[0], pp[1]]),
        ds_valid, ds_project, "double-sphere",
    )  # fmt: skip


def _eucm_initial(rays, uv, pp) -> np.ndarray:
    """Grid over ``(alpha, beta)`` (:func:`_grid_initial`)."""
    shapes = [(a, b) for a in np.linspace(0.0, 0.95, 20) for b in (0.5, 1.0, 1.5, 2.0)]
    return _grid_initial(
        rays, uv, pp, shapes,
        lambda s, fx, fy: np.array([s[0], s[1], fx, fy, pp[0], pp[1]]),
        eucm_valid, eucm_project, "extended-unified-model",
    )  # fmt: skip


def _plumb_initial(rays, uv, pp) -> np.ndarray:
    """``rho_d = rho_u (1 + k1 r2 + k2 r2^2 + k3 r2^3)`` solved linearly, no tangential terms."""
    f, _ = _radial_polynomial_init(rays, uv, pp, 4)
    rho_u = np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]
    rho_d = np.linalg.norm(uv - pp, axis=1) / f
    r2 = rho_u**2
    A = np.column_stack([rho_u * r2, rho_u * r2**2, rho_u * r2**3])
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, *_ = np.linalg.lstsq(A / scale, rho_d - rho_u, rcond=None)
    k = sol / scale
    return np.array([f, f, pp[0], pp[1], k[0], k[1], 0.0, 0.0, k[2]])


def _smoothing_operator(config: SplineConfig) -> np.ndarray:
    """Second differences of a control-point grid along x and y, (R, Nx Ny)."""
    nx, ny = config.Nx, config.Ny
    rows = []
    for j in range(ny):
        for i in range(1, nx - 1):
            r = np.zeros(nx * ny)
            r[j * nx + i - 1 : j * nx + i + 2] = (1.0, -2.0, 1.0)
            rows.append(r)
    for j in range(1, ny - 1):
        for i in range(nx):
            r = np.zeros(nx * ny)
            r[[(j - 1) * nx + i, j * nx + i, (j + 1) * nx + i]] = (1.0, -2.0, 1.0)
            rows.append(r)
    return np.array(rows)


def _fit_splined(
    camera, rays, uv, pp, nx: int | None = None
) -> tuple[SplineConfig, np.ndarray, LMResult]:
    """Fit a splined stereographic model (:mod:`gtsam_sphere.apps.splined`) to ``uv`` (N, 2).

    The configuration's valid region spans the camera's whole image (the stereographic
    points of its pixels' rays, :func:`~gtsam_sphere.apps.splined.choose_config`). The
    intrinsics core is fixed first: ``cx, cy`` the principal point, ``fx = fy`` the
    stereographic focal length near the axis (the median of ``|uv - pp| / |u|`` over the
    innermost fifth of the samples); then the control points are fitted (the problem is
    linear in them) with a smoothness prior (``SPLINE_SMOOTHING`` times ``f`` times their
    second differences, as pixel residuals). Image pixels whose rays lie beyond the
    observed region's widest ray enter with weight ``SPLINE_OUTSIDE_WEIGHT``: there the
    spline follows the calibration's own extrapolation (as the other exports are measured
    against it) instead of a blind continuation. Returns ``(config, params, fit)``.
    """
    w, h = int(camera.width), int(camera.height)
    step = max(2.0, math.sqrt(w * h / 20000.0))
    gu = np.arange(0.0, w, step)
    gv = np.arange(0.0, h, step)
    edge = np.concatenate(
        [
            np.column_stack([gu, np.zeros_like(gu)]),
            np.column_stack([gu, np.full_like(gu, h - 1.0)]),
            np.column_stack([np.zeros_like(gv), gv]),
            np.column_stack([np.full_like(gv, w - 1.0), gv]),
            np.stack(np.meshgrid(gu[::4], gv[::4]), -1).reshape(-1, 2),
            uv,
        ]
    )
    image_rays = pixel_rays(camera, edge)
    u_all = stereographic_u(image_rays[np.all(np.isfinite(image_rays), axis=1)])
    config = choose_config(np.concatenate([u_all, stereographic_u(rays)]), nx or SPLINE_NX)
    # the image beyond the observed field, weighted down
    grid, grid_rays = edge[: len(edge) - len(uv)], image_rays[: len(edge) - len(uv)]
    beyond = np.all(np.isfinite(grid_rays), axis=1)
    beyond[beyond] = incidence_deg(grid_rays[beyond]) > float(np.max(incidence_deg(rays)))
    if len(rays) > SPLINE_MAX_FIT_SAMPLES:
        sub = np.unique(np.linspace(0, len(rays) - 1, SPLINE_MAX_FIT_SAMPLES).astype(int))
        rays, uv = rays[sub], uv[sub]
    n_in = len(rays)
    rays = np.concatenate([rays, grid_rays[beyond]])
    uv = np.concatenate([uv, grid[beyond]])
    row_weight = np.concatenate([np.ones(n_in), np.full(int(beyond.sum()), SPLINE_OUTSIDE_WEIGHT)])
    u = stereographic_u(rays)
    ru = np.linalg.norm(u[:n_in], axis=1)
    rp = np.linalg.norm(uv[:n_in] - pp, axis=1)
    inner = ru <= np.percentile(ru, 20)
    inner &= ru > 1e-6
    f = (
        float(np.median(rp[inner] / ru[inner]))
        if inner.sum() >= 5
        else float(np.sum(rp * ru) / max(np.sum(ru * ru), 1e-300))
    )
    core = np.array([f, f, pp[0], pp[1]])
    index, weight = spline_weights(config, u)
    n, m = len(u), config.Nx * config.Ny
    B = np.zeros((n, m))
    np.put_along_axis(B, index, weight, axis=1)  # the indices of a row are distinct
    L = _smoothing_operator(config) * (SPLINE_SMOOTHING * f)
    target = (uv - pp - f * u) * row_weight[:, None]  # f * du must equal this
    Jx = np.vstack([f * B * row_weight[:, None], L])  # the same design for dux and duy (fx = fy)
    zeros = np.zeros(len(L))

    def fun(c):
        cc = c.reshape(-1, 2)
        r = np.concatenate(
            [
                (Jx @ cc[:, 0]) - np.concatenate([target[:, 0], zeros]),
                (Jx @ cc[:, 1]) - np.concatenate([target[:, 1], zeros]),
            ]
        )
        J = np.zeros((len(r), 2 * m))
        J[: len(Jx), 0::2] = Jx
        J[len(Jx) :, 1::2] = Jx
        return r, J

    fit = levenberg_marquardt(fun, np.zeros(2 * m), max_iterations=50)
    return config, np.concatenate([core, fit.x]), fit


# --------------------------------------------------------------------------- the result


@dataclass
class ExportResult:
    """A standard camera model fitted to a calibrated camera, with what the fit loses.

    Attributes
    ----------
    target : str
        One of ``TARGETS`` or ``FORMAT_FITS``.
    params : dict
        Named parameters (``fx, fy, cx, cy`` px; ``k1..`` / ``p1, p2``
        dimensionless; ``xi, alpha`` for the double sphere).
    width, height : int
        Image size (px).
    rms_px, p95_px, max_px : float
        Pixel distance between the standard model's projection of each
        sampled ray and the calibrated camera's pixel, over the covered
        samples: root mean square, 95th percentile, maximum.
    coverage : float
        Fraction (0..1) of the observed region (by area: grid samples) whose
        rays the standard model represents and the fit used.
    n_samples, n_covered : int
        Grid samples of the observed region, and those covered.
    region : str
        Description of the observed region.
    domain : str
        Which rays the standard model takes.
    max_incidence_deg_region, max_incidence_deg_covered : float
        Widest ray of the observed region and of the covered part (deg).
    observations : dict
        The same residual at the calibration's own observed pixels (``n``,
        ``n_covered``, ``rms_px``, ``max_px``), empty without observations.
    outside : dict
        The error outside the observed region (:func:`outside_statistics`):
        image pixels whose rays lie in the incidence band from the observed
        field (``from_deg``) up to ``OUTSIDE_BAND_DEG`` beyond it or the
        camera's one-to-one field (``to_deg``); ``n``, ``rms_px``, ``max_px``
        (projection), ``unproject_max_deg`` (``opencv-fisheye``:
        ``cv2.fisheye.undistortPoints``), ``bands`` (per ``OUTSIDE_STEP_DEG``)
        and ``valid_to_deg`` (the incidence up to which the error stays within
        ``threshold_px``). Empty when not measured. The error inside the
        observed region is ``rms_px`` / ``max_px``.
    iterations : int
    converged : bool
        Levenberg-Marquardt outcome.
    source : str or None
        The calibration file.
    """

    target: str
    params: dict[str, float]
    width: int
    height: int
    rms_px: float
    p95_px: float
    max_px: float
    coverage: float
    n_samples: int
    n_covered: int
    region: str
    domain: str
    max_incidence_deg_region: float
    max_incidence_deg_covered: float
    observations: dict = field(default_factory=dict)
    outside: dict = field(default_factory=dict)
    iterations: int = 0
    converged: bool = True
    source: str | None = None
    spline: SplineConfig | None = None
    coefficients: np.ndarray | None = None

    @property
    def family(self) -> str:
        """``"kannala-brandt"``, ``"rational"``, ``"double-sphere"``, ``"omni"``,
        ``"plumb-bob"``, ``"eucm"`` or ``"splined-stereographic"``."""
        return TARGET_FAMILY[self.target]

    @property
    def vector(self) -> np.ndarray:
        """The parameters as the vector of the model functions (``kb_project`` ...); for
        the splined model mrcal's intrinsics (core, then ``coefficients``)."""
        core = np.array([self.params[n] for n in _FAMILY_NAMES[self.family]], float)
        if self.family == "splined-stereographic":
            return np.concatenate([core, np.asarray(self.coefficients, float).ravel()])
        return core

    @property
    def K(self) -> np.ndarray:
        """Camera matrix (3, 3) ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (px)."""
        p = self.params
        return np.array([[p["fx"], 0.0, p["cx"]], [0.0, p["fy"], p["cy"]], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        """Distortion vector: ``(k1..k4)`` (fisheye), ``(k1, k2, p1, p2, k3..k6)`` (rational),
        ``(k1, k2, p1, p2)`` (omni), empty for the double sphere."""
        names = {
            "kannala-brandt": _KB_NAMES[4:],
            "rational": _RATIONAL_NAMES[4:],
            "omni": _OMNI_NAMES[5:],
            "plumb-bob": _PLUMB_NAMES[4:],
        }.get(self.family, ())
        return np.array([self.params[n] for n in names], float)

    def in_domain(self, rays: np.ndarray) -> np.ndarray:
        """Rays (N, 3) the exported model projects: (N,) bool (see ``domain``)."""
        rays = np.asarray(rays, float).reshape(-1, 3)
        if self.family == "double-sphere":
            return ds_valid(self.vector, rays)
        if self.family == "omni":
            return omni_valid(self.vector, rays)
        if self.family == "eucm":
            return eucm_valid(self.vector, rays)
        if self.family == "splined-stereographic":
            return self.spline.in_valid_region(stereographic_u(rays))
        inc = incidence_deg(rays)
        limit = self.params.get("max_incidence_deg", 90.0)
        return (rays[:, 2] > 0) & (inc < limit)

    def project(self, rays: np.ndarray, use_cv2: bool = True) -> np.ndarray:
        """Project camera-frame rays with the exported model.

        Parameters
        ----------
        rays : ndarray, shape (N, 3)
            Camera frame (x right, y down, z forward).
        use_cv2 : bool
            OpenCV targets: project with ``cv2.fisheye.projectPoints`` /
            ``cv2.projectPoints`` themselves (else the numpy model).

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            NaN outside :meth:`in_domain`.
        """
        rays = np.asarray(rays, float).reshape(-1, 3)
        out = np.full((len(rays), 2), np.nan)
        ok = self.in_domain(rays) & np.all(np.isfinite(rays), axis=1)
        if not ok.any():
            return out
        r = rays[ok]
        if use_cv2 and self.target in ("opencv-fisheye", "opencv-rational", "opencv-plumb-bob"):
            import cv2

            zero = np.zeros(3)
            obj = np.ascontiguousarray(r[None], np.float64)
            if self.target == "opencv-fisheye":
                uv, _ = cv2.fisheye.projectPoints(obj, zero, zero, self.K, self.D)
            else:
                uv, _ = cv2.projectPoints(obj[0], zero, zero, self.K, self.D)
            out[ok] = np.asarray(uv, float).reshape(-1, 2)
            return out
        if self.family == "splined-stereographic":
            out[ok] = splined_project(self.vector, r, self.spline)
            return out
        fn = {
            "kannala-brandt": kb_project,
            "rational": rational_project,
            "omni": omni_project,
            "plumb-bob": plumb_bob_project,
            "eucm": eucm_project,
        }.get(self.family, ds_project)
        out[ok] = fn(self.vector, r)
        return out

    def summary(self) -> str:
        """Several lines saying what was fitted and what it loses."""
        lines = [
            f"{self.target}: fitted over {self.n_covered} of {self.n_samples} samples of the "
            f"observed region ({self.region})",
            f"  fit residual: RMS {self.rms_px:.4f} px, 95% {self.p95_px:.4f} px, "
            f"max {self.max_px:.4f} px",
            f"  covers {100 * self.coverage:.1f}% of the observed region ({self.domain}); "
            f"widest ray {self.max_incidence_deg_covered:.1f} deg of "
            f"{self.max_incidence_deg_region:.1f} deg observed",
        ]
        if self.coverage < 1.0:
            lines.append(
                f"  excluded: {100 * (1 - self.coverage):.1f}% of the observed region "
                f"({self.n_samples - self.n_covered} samples) lies outside the model's domain"
            )
        o = self.observations
        if o:
            lines.append(
                f"  at the calibration's {o['n']} observed pixels: {o['n_covered']} covered, "
                f"RMS {o['rms_px']:.4f} px, max {o['max_px']:.4f} px"
            )
        lines.extend(self.outside_lines())
        if not self.converged:
            lines.append("  the fit did not converge")
        return "\n".join(lines)

    def outside_lines(self) -> list[str]:
        """Summary lines of the error inside and outside the observed region."""
        o = self.outside
        if not o:
            return []
        lines = [
            f"  inside the observed region (up to {self.max_incidence_deg_region:.1f} deg): "
            f"RMS {self.rms_px:.4f} px, max {self.max_px:.4f} px"
        ]
        head = f"  outside it ({o['from_deg']:.1f}-{o['to_deg']:.1f} deg incidence"
        if not o.get("n"):
            lines.append(f"{head}): no image pixel there in the model's domain")
            return lines
        un = o.get("unproject_max_deg")
        un = "" if un is None or not math.isfinite(un) else f", unproject max {un:.2f} deg"
        lines.append(
            f"{head}, {o['n']} image pixels): RMS {o['rms_px']:.4f} px, "
            f"max {o['max_px']:.4f} px{un}"
        )
        bands = [
            f"{b['from_deg']:.0f}-{b['to_deg']:.0f} deg {b['max_px']:.3g} px"
            for b in o.get("bands", [])
            if b["n"]
        ]
        if bands:
            lines.append("  outside, max per band: " + ", ".join(bands))
        if o.get("exceeds"):
            lines.append(
                f"  do not use this model past {o['valid_to_deg']:.1f} deg incidence: its error "
                f"exceeds {o['threshold_px']:g} px there"
            )
        return lines

    def fit_dict(self) -> dict:
        """The fit statistics as a JSON-ready dict."""
        return {
            "rms_px": self.rms_px,
            "p95_px": self.p95_px,
            "max_px": self.max_px,
            "coverage": self.coverage,
            "n_samples": self.n_samples,
            "n_covered": self.n_covered,
            "region": self.region,
            "domain": self.domain,
            "max_incidence_deg_region": self.max_incidence_deg_region,
            "max_incidence_deg_covered": self.max_incidence_deg_covered,
            "observations": self.observations,
            "outside": self.outside,
            "iterations": self.iterations,
            "converged": self.converged,
        }

    def to_dict(self) -> dict:
        """The JSON document of an ``opencv-*`` export (``EXPORT_FORMAT``)."""
        doc = {
            "format": EXPORT_FORMAT,
            "target": self.target,
            "image_size": [self.width, self.height],
            "pixel_convention": "(0, 0) is the centre of the top-left pixel (OpenCV)",
            "K": self.K.tolist(),
        }
        if self.target == "opencv-fisheye":
            doc["D"] = self.D.tolist()
            doc["model"] = "cv2.fisheye (Kannala-Brandt), valid for rays with z > 0"
        elif self.target == "opencv-rational":
            doc["dist"] = self.D.tolist()
            doc["flags"] = ["CALIB_RATIONAL_MODEL"]
            doc["max_incidence_deg"] = self.params["max_incidence_deg"]
            doc["model"] = "cv2 pinhole, rational distortion (k1, k2, p1, p2, k3, k4, k5, k6)"
        elif self.family == "omni":
            doc["D"] = self.D.tolist()
            doc["xi"] = self.params["xi"]
            doc["model"] = "cv2.omnidir (unified / Mei), D = (k1, k2, p1, p2), no skew"
        elif self.family == "plumb-bob":
            doc["dist"] = self.D.tolist()
            doc["model"] = "cv2 pinhole, dist = (k1, k2, p1, p2, k3) (ROS plumb_bob)"
        elif self.family == "splined-stereographic":
            doc["lensmodel"] = self.spline.lensmodel
            doc["intrinsics"] = self.vector.tolist()
            doc["model"] = "mrcal splined stereographic (see gtsam_sphere.apps.splined)"
        else:
            doc["params"] = dict(self.params)
        doc["fit"] = self.fit_dict()
        if self.source:
            doc["source"] = self.source
        return doc

    def to_kalibr_yaml(self) -> str:
        """Kalibr camchain YAML (``cam0``) of a ``kalibr-*`` or fisheye export."""
        p = self.params
        if self.family == "kannala-brandt":
            model, dist_model = "pinhole", "equidistant"
            intr = [p["fx"], p["fy"], p["cx"], p["cy"]]
            dist = list(self.D)
        elif self.family == "double-sphere":
            model, dist_model = "ds", "none"
            intr = [p["xi"], p["alpha"], p["fx"], p["fy"], p["cx"], p["cy"]]
            dist = []
        elif self.family == "omni":
            model, dist_model = "omni", "radtan"
            intr = [p["xi"], p["fx"], p["fy"], p["cx"], p["cy"]]
            dist = list(self.D)
        elif self.family == "eucm":
            model, dist_model = "eucm", "none"
            intr = [p["alpha"], p["beta"], p["fx"], p["fy"], p["cx"], p["cy"]]
            dist = []
        else:
            raise ValueError(f"Kalibr has no {self.family} model; export {self.target} as JSON")

        def seq(values) -> str:
            return "[" + ", ".join(repr(float(v)) for v in values) + "]"

        comments = [f"# {line}" for line in self.summary().splitlines()]
        if self.source:
            comments.insert(0, f"# exported by gtsam-sphere from {self.source}")
        lines = [
            *comments,
            "cam0:",
            f"  camera_model: {model}",
            f"  intrinsics: {seq(intr)}",
            f"  distortion_model: {dist_model}",
            f"  distortion_coeffs: {seq(dist)}",
            f"  resolution: [{int(self.width)}, {int(self.height)}]",
            "  cam_overlaps: []",
            "  rostopic: /cam0/image_raw",
        ]
        return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- fitting


def _observation_rays(camera, uv_px, incidence=None):
    """Rays of observed pixels; the half of the sphere from their incidence when known."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    hemi = None
    if incidence is not None:
        inc = np.asarray(incidence, float).reshape(-1)
        if len(inc) == len(uv) and np.all(np.isfinite(inc)):
            hemi = np.where(inc > 90.0, -1.0, 1.0)
    return pixel_rays(camera, uv, hemi)


def export_camera(
    camera,
    target: str,
    observations_uv_px: np.ndarray | None = None,
    observations_incidence_deg: np.ndarray | None = None,
    region: str = "hull",
    max_incidence_deg: float | None = None,
    n_samples: int = 20000,
    source: str | None = None,
) -> ExportResult:
    """Fit a standard camera model (``target``) to a calibrated camera's ray field.

    Parameters
    ----------
    camera : SphereCamera
        ``project`` / ``unproject`` in the camera frame (x right, y down, z
        forward), raw pixels in OpenCV's convention.
    target : str
        One of ``TARGETS`` or ``FORMAT_FITS``.
    observations_uv_px : ndarray, shape (M, 2), optional
        The calibration's observed pixels: they define the observed region
        and the fit is also evaluated at them.
    observations_incidence_deg : ndarray, shape (M,), optional
        Their incidence angles (deg), to put each on the right half of the
        image sphere.
    region : {"hull", "radius", "image"}
        See :func:`sample_region`.
    max_incidence_deg : float, optional
        Use only rays below this incidence (deg). Default: 80 for
        ``opencv-rational``, none otherwise (the model's own domain).
    n_samples : int
        About how many grid samples of the observed region to fit.
    source : str, optional
        Calibration file name recorded in the output.

    Returns
    -------
    ExportResult

    Raises
    ------
    ValueError
        Unknown target, or no sampled ray inside the model's domain.
    """
    if target not in TARGETS + FORMAT_FITS:
        raise ValueError(f"unknown export target {target!r}; choose from {TARGETS}")
    sample = sample_region(camera, observations_uv_px, region, n_samples)
    rays, uv = sample.rays, sample.uv_px
    inc = sample.incidence_deg
    pp = np.array([camera.xp, camera.yp], float)
    family = TARGET_FAMILY[target]
    if family in ("rational", "plumb-bob") and max_incidence_deg is None:
        max_incidence_deg = RATIONAL_MAX_INCIDENCE_DEG
    use = np.ones(len(rays), bool)
    if max_incidence_deg is not None:
        use &= inc < float(max_incidence_deg)
    if family in ("kannala-brandt", "rational", "plumb-bob"):
        use &= rays[:, 2] > 1e-9
    if use.sum() < 20:
        raise ValueError(
            f"{target}: only {int(use.sum())} of {len(rays)} samples of the observed region are "
            f"inside the model's domain; nothing to fit"
        )
    extra: dict[str, float] = {}
    spline = coefficients = None
    if family == "kannala-brandt":
        names = _KB_NAMES
        p0 = _kb_initial(rays[use], uv[use], pp)
        fit = _fit(kb_project, p0, rays[use], uv[use])
        domain = "rays with z > 0 (incidence below 90 deg; cv2.fisheye cannot project others)"
        if max_incidence_deg is not None and max_incidence_deg < 90:
            domain = f"rays below {max_incidence_deg:g} deg incidence"
            extra["max_incidence_deg"] = float(max_incidence_deg)
        covered_p = fit.x
    elif family == "rational":
        names = _RATIONAL_NAMES
        p0 = _rational_initial(rays[use], uv[use], pp)
        r_use = rays[use]
        fit = _fit(
            rational_project, p0, r_use, uv[use], lambda p: _rational_feasible(p, r_use), 300
        )
        domain = f"rays below {max_incidence_deg:g} deg incidence (pinhole model)"
        extra["max_incidence_deg"] = float(max_incidence_deg)
        covered_p = fit.x
    elif family == "plumb-bob":
        names = _PLUMB_NAMES
        p0 = _plumb_initial(rays[use], uv[use], pp)
        fit = _fit(plumb_bob_project, p0, rays[use], uv[use], max_iterations=300)
        domain = f"rays below {max_incidence_deg:g} deg incidence (pinhole model)"
        extra["max_incidence_deg"] = float(max_incidence_deg)
        covered_p = fit.x
    elif family == "eucm":
        names = _EUCM_NAMES
        p0 = _eucm_initial(rays[use], uv[use], pp)
        use &= eucm_valid(p0, rays)
        r_use = rays[use]
        fit = _fit(eucm_project, p0, r_use, uv[use], lambda p: bool(np.all(eucm_valid(p, r_use))))
        domain = "rays the extended unified model projects (Khomutenko et al. 2016)"
        if max_incidence_deg is not None:
            domain += f", below {max_incidence_deg:g} deg incidence"
        covered_p = fit.x
    elif family == "splined-stereographic":
        names = _CORE_NAMES
        use &= np.all(np.isfinite(stereographic_u(rays)), axis=1)
        spline, full, fit = _fit_splined(camera, rays[use], uv[use], pp)
        covered_p, coefficients = full[:4], full[4:]
        domain = f"rays inside the spline's valid region ({spline.lensmodel})"
        if max_incidence_deg is not None:
            domain += f", below {max_incidence_deg:g} deg incidence"
    elif family == "omni":
        names = _OMNI_NAMES
        p0 = _omni_initial(rays[use], uv[use], pp)
        use &= omni_valid(p0, rays)
        r_use = rays[use]
        fit = _fit(omni_project, p0, r_use, uv[use], lambda p: bool(np.all(omni_valid(p, r_use))))
        domain = "rays the unified (Mei) model projects one-to-one"
        if max_incidence_deg is not None:
            domain += f", below {max_incidence_deg:g} deg incidence"
        covered_p = fit.x
    else:
        names = _DS_NAMES
        p0 = _ds_initial(rays[use], uv[use], pp)
        use &= ds_valid(p0, rays)
        r_use = rays[use]
        fit = _fit(ds_project, p0, r_use, uv[use], lambda p: bool(np.all(ds_valid(p, r_use))))
        domain = "rays the double-sphere model projects (Usenko et al. 2018, Eq. 43)"
        if max_incidence_deg is not None:
            domain += f", below {max_incidence_deg:g} deg incidence"
        covered_p = fit.x
    params = dict(zip(names, map(float, covered_p)))
    params.update(extra)
    result = ExportResult(
        target=target,
        params=params,
        width=int(camera.width),
        height=int(camera.height),
        rms_px=math.nan,
        p95_px=math.nan,
        max_px=math.nan,
        coverage=0.0,
        n_samples=len(rays),
        n_covered=0,
        region=sample.description,
        domain=domain,
        max_incidence_deg_region=float(np.max(inc)),
        max_incidence_deg_covered=math.nan,
        iterations=fit.iterations,
        converged=fit.converged,
        source=source,
        spline=spline,
        coefficients=coefficients,
    )
    covered = use & result.in_domain(rays)
    pred = result.project(rays[covered])
    err = np.linalg.norm(pred - uv[covered], axis=1)
    finite = np.isfinite(err)
    covered[np.flatnonzero(covered)[~finite]] = False
    err = err[finite]
    result.n_covered = int(covered.sum())
    result.coverage = result.n_covered / max(len(rays), 1)
    if len(err):
        result.rms_px = float(np.sqrt(np.mean(err**2)))
        result.p95_px = float(np.percentile(err, 95))
        result.max_px = float(np.max(err))
        result.max_incidence_deg_covered = float(np.max(inc[covered]))
    if observations_uv_px is not None:
        result.observations = _observation_statistics(
            camera,
            result,
            observations_uv_px,
            observations_incidence_deg,
            max_incidence_deg,
        )
    result.outside = outside_statistics(camera, result, n_samples=n_samples)
    if result.outside.get("exceeds"):
        o = result.outside
        logger.warning(
            "%s: error up to %.2f px (above %g px) between %.1f and %.1f deg incidence, outside "
            "the observed region: the exported model must not be used past %.1f deg",
            target,
            o["max_px"],
            o["threshold_px"],
            o["from_deg"],
            o["to_deg"],
            o["valid_to_deg"],
        )
    return result


def _camera_field_deg(camera) -> float:
    """The camera's one-to-one field (deg): ``max_alpha_rad`` with a radial mapping, else 180."""
    try:
        if getattr(camera, "radial", None) is not None:
            return float(np.degrees(camera.max_alpha_rad()))
    except Exception:  # a camera without that method
        pass
    return 180.0


def outside_statistics(
    camera,
    result: ExportResult,
    band_deg: float = OUTSIDE_BAND_DEG,
    step_deg: float = OUTSIDE_STEP_DEG,
    threshold_px: float = OUTSIDE_WARN_PX,
    step_px: float | None = None,
    n_samples: int = 20000,
) -> dict:
    """The export's error in the band of incidence just beyond the observed region.

    Image pixels (a regular grid) whose rays have an incidence between the
    observed region's widest ray (``result.max_incidence_deg_region``) and
    ``band_deg`` beyond it (at most the camera's one-to-one field), inside
    the exported model's domain: the distance between the model's
    projection of each ray and the calibrated pixel.

    Parameters
    ----------
    camera : SphereCamera
    result : ExportResult
    band_deg, step_deg : float
        Width of the band and of its sub-bands (deg).
    threshold_px : float
        Error (px) above which the band ``exceeds``.
    step_px : float, optional
        Grid spacing (px); default about ``n_samples`` pixels over the image.
    n_samples : int

    Returns
    -------
    dict
        ``from_deg``, ``to_deg``, ``n``, ``rms_px``, ``max_px``, ``p95_px``,
        ``unproject_max_deg`` (``opencv-fisheye`` only, else NaN),
        ``bands`` (list of ``from_deg, to_deg, n, rms_px, max_px``),
        ``threshold_px``, ``exceeds`` and ``valid_to_deg`` (the smallest
        incidence of a pixel whose error exceeds ``threshold_px``, at least
        ``from_deg``; when none does, the widest incidence measured, or
        ``from_deg`` when no pixel of the band is in the model's domain).
        The reference pixels are the calibrated camera's own beyond its
        observed field (itself an extrapolation there): the numbers say how
        far the exported model departs from the calibration, not from the
        true lens.
    """
    lo = float(result.max_incidence_deg_region)
    if not math.isfinite(lo):
        return {}
    hi = min(lo + float(band_deg), _camera_field_deg(camera), 180.0)
    out = {
        "from_deg": lo,
        "to_deg": hi,
        "n": 0,
        "rms_px": math.nan,
        "p95_px": math.nan,
        "max_px": math.nan,
        "unproject_max_deg": math.nan,
        "bands": [],
        "threshold_px": float(threshold_px),
        "exceeds": False,
        "valid_to_deg": lo,
    }
    if not hi > lo:
        return out
    w, h = int(camera.width), int(camera.height)
    if step_px is None:
        step_px = math.sqrt(w * h / max(int(n_samples), 16))
    gu = np.arange(-0.5 + step_px / 2, w - 0.5, step_px)
    gv = np.arange(-0.5 + step_px / 2, h - 0.5, step_px)
    uv = np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)
    rays = pixel_rays(camera, uv)
    ok = np.all(np.isfinite(rays), axis=1)
    inc = np.full(len(uv), np.nan)
    inc[ok] = incidence_deg(rays[ok])
    ok[ok] = (inc[ok] > lo) & (inc[ok] <= hi)
    ok[ok] = result.in_domain(rays[ok])
    if not ok.any():
        return out
    uv, rays, inc = uv[ok], rays[ok], inc[ok]
    err = np.linalg.norm(result.project(rays) - uv, axis=1)
    err = np.where(np.isfinite(err), err, np.inf)  # the model has no pixel: unusable there
    out["n"] = int(len(err))
    out["rms_px"] = float(np.sqrt(np.mean(err**2)))
    out["p95_px"] = float(np.percentile(err, 95))
    out["max_px"] = float(np.max(err))
    if result.target == "opencv-fisheye":
        import cv2

        xy = cv2.fisheye.undistortPoints(
            np.ascontiguousarray(uv[None], np.float64), result.K, result.D
        ).reshape(-1, 2)
        back = np.column_stack([xy, np.ones(len(xy))])
        back /= np.linalg.norm(back, axis=1, keepdims=True)
        ang = np.degrees(np.arccos(np.clip(np.sum(back * rays, axis=1), -1.0, 1.0)))
        ang = np.where(np.isfinite(ang), ang, 180.0)
        out["unproject_max_deg"] = float(np.max(ang))
    edges = np.arange(lo, hi, float(step_deg))
    for a in edges:
        b = min(a + float(step_deg), hi)
        m = (inc > a) & (inc <= b)
        band = {"from_deg": float(a), "to_deg": float(b), "n": int(m.sum())}
        band["rms_px"] = float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else math.nan
        band["max_px"] = float(np.max(err[m])) if m.any() else math.nan
        out["bands"].append(band)
    bad = err > threshold_px
    if bad.any():
        out["exceeds"] = True
        out["valid_to_deg"] = float(max(lo, np.min(inc[bad])))
    else:
        out["valid_to_deg"] = float(np.max(inc))
    return out


def _observation_statistics(camera, result, uv_px, incidence, max_incidence_deg) -> dict:
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    finite = np.all(np.isfinite(uv), axis=1)
    uv = uv[finite]
    inc = None if incidence is None else np.asarray(incidence, float).reshape(-1)[finite]
    rays = _observation_rays(camera, uv, inc)
    ok = np.all(np.isfinite(rays), axis=1)
    ok[ok] = result.in_domain(rays[ok])
    if max_incidence_deg is not None:
        ok &= incidence_deg(rays) < max_incidence_deg
    out = {"n": int(len(uv)), "n_covered": int(ok.sum()), "rms_px": math.nan, "max_px": math.nan}
    if ok.any():
        err = np.linalg.norm(result.project(rays[ok]) - uv[ok], axis=1)
        err = err[np.isfinite(err)]
        if len(err):
            out["rms_px"] = float(np.sqrt(np.mean(err**2)))
            out["max_px"] = float(np.max(err))
    return out


def export_calibration(
    calib,
    target: str,
    region: str = "hull",
    max_incidence_deg: float | None = None,
    n_samples: int = 20000,
    source: str | None = None,
) -> ExportResult:
    """Fit ``target`` to a loaded calibration (see :func:`export_camera`).

    The observed region comes from ``calib.extra["observations"]["uv_px"]``
    (with ``incidence_deg`` when present); without it the whole image.

    Parameters
    ----------
    calib : Calibration
    target : str
        One of ``TARGETS`` or ``FORMAT_FITS``.
    region, max_incidence_deg, n_samples
        As :func:`export_camera`.
    source : str, optional
        Calibration file name recorded in the output.

    Returns
    -------
    ExportResult

    Raises
    ------
    DatasetError
        The calibration's observations are malformed or its camera has no
        usable ray field.
    """
    obs = calib.extra.get("observations") if isinstance(calib.extra, dict) else None
    uv = inc = None
    if isinstance(obs, dict) and obs.get("uv_px") is not None:
        try:
            uv = np.asarray(obs["uv_px"], float).reshape(-1, 2)
        except (TypeError, ValueError) as exc:
            raise DatasetError(
                f"{source or 'calibration'}: observations.uv_px is malformed ({exc})"
            ) from None
        if obs.get("incidence_deg") is not None:
            try:
                inc = np.asarray(obs["incidence_deg"], float).reshape(-1)
            except (TypeError, ValueError):
                inc = None
            if inc is not None and len(inc) != len(uv):
                inc = None
    cam = calib.camera
    for name in ("xp", "yp", "c"):
        if not math.isfinite(float(getattr(cam, name))):
            raise DatasetError(f"{source or 'calibration'}: camera {name} is not finite")
    if not float(cam.c) > 0:
        raise DatasetError(f"{source or 'calibration'}: camera c_px must be positive")
    try:
        return export_camera(
            cam,
            target,
            uv,
            inc,
            region=region,
            max_incidence_deg=max_incidence_deg,
            n_samples=n_samples,
            source=source,
        )
    except ValueError as exc:
        if target not in TARGETS + FORMAT_FITS or region not in REGIONS:
            raise
        raise DatasetError(f"{source or 'calibration'}: {exc}") from None


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (``dataset.write_bytes_atomic``)."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_export(result: ExportResult, path: str | os.PathLike) -> Path:
    """Write an export atomically: JSON for ``opencv-*``, camchain YAML for ``kalibr-*``.

    Parameters
    ----------
    result : ExportResult
    path : path-like

    Returns
    -------
    Path
    """
    if result.target.startswith("kalibr-"):
        return write_text_atomic(path, result.to_kalibr_yaml())
    return write_json_atomic(path, _finite_or_none(result.to_dict()))


def _finite_or_none(obj):
    """Replace NaN / inf (an empty statistic) by ``None`` for JSON."""
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


# --------------------------------------------------------------------------- CLI


#: rig targets of the command line (:mod:`gtsam_sphere.apps.export_rig`)
RIG_TARGETS: tuple[str, ...] = ("kalibr", "opencv-stereo")
#: other tools' file formats, single cameras and rigs (:mod:`gtsam_sphere.apps.export_formats`)
FORMAT_TARGETS: tuple[str, ...] = ("ros", "mrcal", "basalt")


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere export``."""
    parser.add_argument("calibration", help="gtsam-sphere/calibration@1 or @2 (rig) file")
    parser.add_argument(
        "--to",
        required=True,
        choices=TARGETS + RIG_TARGETS + FORMAT_TARGETS,
        dest="target",
        help="model; kalibr (camchain.yaml of every camera, with T_cn_cnm1) and opencv-stereo "
        "(R, T and both cameras' models) export a rig; ros (CameraInfo YAML), mrcal "
        "(.cameramodel) and basalt (calibration.json) write those tools' files for a camera "
        "or a rig (ros, mrcal: one file per rig camera, OUTPUT-ID.ext)",
    )
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        help="file to write (JSON for opencv-*, YAML for kalibr*, .yaml or .json for "
        "opencv-stereo)",
    )
    parser.add_argument(
        "--camera",
        default=None,
        metavar="ID",
        help="rig calibration: the camera a single-camera target (opencv-*, kalibr-*) exports; "
        "with ros, mrcal, basalt only that camera (default every camera)",
    )
    parser.add_argument(
        "--kalibr-model",
        action="append",
        default=None,
        metavar="[ID=]MODEL",
        help="--to kalibr: auto, pinhole-equi, omni-radtan, ds-none or eucm-none for every "
        "camera, or ID=MODEL for one (repeat); default auto: per camera the model (of the "
        "first three) covering most of the observed region, then the smallest fit residual",
    )
    parser.add_argument(
        "--ros-model",
        default=None,
        choices=("auto", "equidistant", "plumb_bob", "rational_polynomial"),
        help="--to ros: distortion_model (default auto: equidistant or rational_polynomial, "
        "whichever covers more of the observed region, then fits better)",
    )
    parser.add_argument(
        "--mrcal-model",
        default=None,
        choices=("auto", "opencv8", "splined"),
        help="--to mrcal: LENSMODEL_OPENCV8 or LENSMODEL_SPLINED_STEREOGRAPHIC (default auto: "
        "OPENCV8 when the observed field is below 75 deg and it fits within 0.1 px everywhere "
        "there, else the splined model)",
    )
    parser.add_argument(
        "--basalt-model",
        default=None,
        choices=("auto", "kb4", "ds", "eucm"),
        help="--to basalt: camera_type of every camera (default auto: per camera the model "
        "covering most of the observed region, then the smallest residual)",
    )
    parser.add_argument(
        "--stereo-model",
        default="auto",
        choices=("auto", "fisheye", "omnidir"),
        help="--to opencv-stereo: cv2.fisheye or cv2.omnidir models (default auto: fisheye "
        "when it covers both cameras' observed regions)",
    )
    parser.add_argument(
        "--stereo-cameras",
        default=None,
        metavar="ID1,ID2",
        help="--to opencv-stereo: the two cameras (default the rig's first two)",
    )
    parser.add_argument(
        "--region",
        choices=REGIONS,
        default="hull",
        help="observed region to fit over: convex hull of the observations (default), "
        "disc through the farthest one, or the whole image",
    )
    parser.add_argument(
        "--max-incidence-deg",
        type=float,
        default=None,
        help=f"fit only rays below this incidence (default {RATIONAL_MAX_INCIDENCE_DEG:g} for "
        "opencv-rational, the model's own domain otherwise)",
    )
    parser.add_argument("--samples", type=int, default=20000, help="grid samples of the region")
    parser.add_argument(
        "--max-rms-px",
        type=float,
        default=1.0,
        help="exit 1 (file still written) when the fit RMS exceeds this (px)",
    )


def check_target_options(args) -> None:
    """Refuse an option meant for another ``--to`` target (``OptionsError`` naming it)."""
    from ..core.errors import OptionsError

    for option, given, target in (
        ("--kalibr-model", getattr(args, "kalibr_model", None), "kalibr"),
        ("--stereo-model", getattr(args, "stereo_model", "auto") != "auto", "opencv-stereo"),
        ("--stereo-cameras", getattr(args, "stereo_cameras", None), "opencv-stereo"),
        ("--ros-model", getattr(args, "ros_model", None), "ros"),
        ("--mrcal-model", getattr(args, "mrcal_model", None), "mrcal"),
        ("--basalt-model", getattr(args, "basalt_model", None), "basalt"),
    ):
        if given and args.target != target:
            raise OptionsError(f"{option} applies to --to {target}, not --to {args.target}")


def run_cli(args) -> int:
    """Run ``gtsam-sphere export``: 0 on success, 1 if the fit is poor (bad input raises)."""
    from ..core.errors import OptionsError
    from ..io.calibration import load_calibration, single_camera

    check_target_options(args)
    if args.target in RIG_TARGETS:  # export_rig.run_cli (the command line routes it)
        raise OptionsError(f"--to {args.target} is a rig export: run it with export_rig.run_cli")
    if args.target in FORMAT_TARGETS:  # export_formats.run_cli (the command line routes it)
        raise OptionsError(f"--to {args.target}: run it with export_formats.run_cli")
    calib = load_calibration(args.calibration)
    calib = single_camera(
        calib, args.camera, args.calibration, ", or use --to kalibr / --to opencv-stereo"
    )
    result = export_calibration(
        calib,
        args.target,
        region=args.region,
        max_incidence_deg=args.max_incidence_deg,
        n_samples=args.samples,
        source=str(args.calibration),
    )
    path = write_export(result, args.output)
    print(f"wrote {path}")
    print(result.summary())
    if not (result.rms_px <= args.max_rms_px) or not result.converged:
        # a warning (standard error through logging), not part of the result on stdout
        logger.warning(
            "fit RMS %.4f px exceeds %g px or the fit did not converge: the exported model "
            "does not reproduce the calibration",
            result.rms_px,
            args.max_rms_px,
        )
        return 1
    return 0
