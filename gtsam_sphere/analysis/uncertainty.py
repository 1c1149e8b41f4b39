"""Projection uncertainty over the image, in pixels, from the covariance of the intrinsics.

For a fixed ray, the projected pixel ``uv = project(ray; theta)`` moves with
the intrinsics ``theta`` (``xp, yp, c``, Brown / radial terms). Its
covariance is propagated to first order,

    Sigma_uv = J Sigma_theta J^T,    J = d uv / d theta   (2 x K, px per unit of theta)

with ``J`` from central differences over ``+-1 sigma`` of each parameter on
copies of the camera (:func:`with_intrinsic` is the one adapter from
intrinsics names to camera attributes). The map reports ``sqrt(trace
Sigma_uv)``: the RMS length (px) of the 2-D projection error, the same
definition as ``rms_px``.

A learned kNN correction (``camera.correction`` with the fitted attributes
of :class:`~gtsam_sphere.core.correction_model.KNNCorrection`) adds a local term: the
correction at a pixel is the mean of its ``k`` neighbours' training
corrections, so its standard error is the spread of those corrections about
the prediction divided by ``sqrt(k)``:

    sigma_knn = sqrt(sum_j |y_j - y_hat|^2 / (k - 1)) / sqrt(k)     (px, both coordinates)

The two terms are independent and add in quadrature.

Inputs in a calibration file: ``statistics["intrinsics_covariance"]`` (K x K)
with ``statistics["intrinsics_names"]``; with only
``statistics["intrinsics_sigma"]`` (name -> sigma) the diagonal is used and
the result says so (correlations, e.g. between ``c`` and ``k1``, are then
ignored and the map is usually pessimistic).

Compensating the camera frame (``compensate_rotation=True``, the report's
map). A fixed camera-frame ray is pessimistic: the camera frame itself is
only known through the calibration's poses, and an error of the intrinsics
that looks like a small rotation of the camera (a shift of the principal
point is nearly one) is absorbed by the poses and does not move the image of
the world. So, as mrcal does when it compares two models, the change of the
projection is measured after the camera motion that best re-aligns the
perturbed projection with the nominal one over the observed region. In
linearised form, over the map's ``N`` grid cells with ``J`` (2N x K) the
Jacobian wrt the intrinsics and ``G`` (2N x m) wrt the camera motion,

    dq = (I - G (G^T W G)^+ G^T W) J dtheta,      Sigma_uv = Jc Sigma_theta Jc^T

with ``Jc`` the bracket times ``J`` and ``W`` the fit weights (one global
motion for the whole grid). The motion is a rotation ``omega`` (m = 3, rad;
the ray's point ``p -> Exp(omega) p``), the exact answer for points at
infinity. With ranges (``fit_ranges_m``, calibration units) a translation
``t`` is fitted too (m = 6, ``p -> Exp(omega) p + t`` for the grid's points
``p = r * ray`` at each range ``r``, all shells in one fit) and the map is
evaluated at ``range_m`` (``None``: infinity, where ``t`` has no effect).
Over a single shell only ``t / r`` is determined, so the map is the same for
every finite range, and the translation along the axis absorbs most of an
error of ``c`` (a sphere of points seen from a camera moved along its axis
scales nearly as with a changed ``c``): on the real ``opencv_fisheye_left``
calibration the median over the observed cells drops from 0.22 px
(rotation) to 0.025 px, an answer only for a scene at one depth. Shells
spanning the depths of the observations are the honest version: fitted at
its 5/50/95% target ranges (0.22, 0.33, 0.59 m) the same calibration gives
0.058 px at 0.33 m, 0.17 px at 1 m, 0.21 px at 3 m and 0.23 px at infinity
(the rotation-only map, 0.22 px, is the default).

Fit region and metric: the motion is fitted in pixels (the metric of the
adjustment, whose poses did the compensating), each grid cell weighted by
the number of observations that fall in it (times their robust weights when
given): an error of the intrinsics is absorbed where the observations are,
in proportion to how many there are, as in the adjustment's cost. Without
observations the fit is uniform over every cell with a ray. mrcal's
model differencing fits the angle between rays instead, over a region the
user chooses; in pixels, parts of the image with more pixels per radian
count more than they would in angle.

What holds: the fit minimises the weighted sum of squared projection
changes for every ``dtheta``, so ``sum_n W_n trace(Sigma_uv,n)`` over the
fit region never exceeds the fixed-ray value (and a fitted translation
lowers it further). Pointwise it can exceed it: beyond the fit region and
on its border a rotation fitted to the observed part of the image can move
a pixel further than the fixed ray does (by a few percent in the tests; on
the real ``opencv_fisheye_left`` calibration 1 of 1000 cells, outside the
observations).

Validity: first order, checked against Monte Carlo draws of the
intrinsics with the motion fitted by nonlinear least squares (within 15%
per cell in the tests; on the real calibration within 5% per cell with
600 draws, 9% with 300, both for a rotation and for three range shells). It
is an approximation of a full propagation: only the marginal covariance of
the intrinsics is used, and one global motion stands for the poses (the
adjustment had one per image, each able to absorb a different part);
mrcal's own uncertainty method propagates the joint covariance of
intrinsics and poses instead.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import BROWN_TERMS
from ..core.errors import OptionsError
from ..core.lie import skew
from ..core.rays import pixel_rays, project_rays
from ..io.dataset import DatasetError

# names of the base intrinsics -> SphereCamera attribute
_BASE = {"xp_px": "xp", "xp": "xp", "yp_px": "yp", "yp": "yp", "c_px": "c", "c": "c"}


def _radial_names() -> tuple[str, ...]:
    from ..core import camera as camera_module

    return (camera_module.WARP_TERM, *camera_module.RADIAL_TERMS)


def intrinsic_value(camera, name: str) -> float:
    """Current value of the intrinsic ``name`` of ``camera`` (see :func:`with_intrinsic`)."""
    if name in _BASE:
        return float(getattr(camera, _BASE[name]))
    brown = getattr(camera, "brown", None) or {}
    if name in brown:
        return float(brown[name])
    radial = getattr(camera, "radial", None)
    if isinstance(radial, dict) and (name in radial or name in _radial_names()):
        return float(radial.get(name, 0.0))
    if name in BROWN_TERMS:
        return 0.0
    raise ValueError(f"intrinsic {name!r} is not a parameter of this camera model")


def with_intrinsic(camera, name: str, value: float):
    """A copy of ``camera`` with the intrinsic ``name`` set to ``value``.

    The one place mapping intrinsics names (``statistics["intrinsics_names"]``)
    to camera attributes: ``xp_px``/``xp`` -> ``xp``, ``yp_px``/``yp`` ->
    ``yp``, ``c_px``/``c`` -> ``c``; a name of ``camera.brown`` (or any Brown
    term) -> ``camera.brown[name]``; a name of ``camera.radial`` (a dict of
    the radial mapping's coefficients) -> ``camera.radial[name]``. The
    learned correction is shared, not copied.

    Parameters
    ----------
    camera : SphereCamera
    name : str
    value : float
        In the parameter's unit (px for ``xp, yp, c``, else dimensionless).

    Returns
    -------
    SphereCamera

    Raises
    ------
    ValueError
        ``name`` is not a parameter of the camera.
    """
    cam = copy.copy(camera)
    if name in _BASE:
        setattr(cam, _BASE[name], float(value))
        return cam
    brown = getattr(camera, "brown", None) or {}
    radial = getattr(camera, "radial", None)
    if name in brown:
        cam.brown = dict(brown)
        cam.brown[name] = float(value)
    elif isinstance(radial, dict) and (name in radial or name in _radial_names()):
        cam.radial = dict(radial)
        cam.radial[name] = float(value)
    elif name in BROWN_TERMS:
        cam.brown = dict(brown)
        cam.brown[name] = float(value)
    else:
        raise ValueError(f"intrinsic {name!r} is not a parameter of this camera model")
    return cam


def _check_name(name: str, source: str) -> str:
    if not isinstance(name, str):
        raise DatasetError(f"{source}: intrinsics name {name!r} is not a string")
    return name


def intrinsics_covariance(statistics: dict, source: str = "<calibration>"):
    """The covariance of the intrinsics stored in a calibration's ``statistics``.

    Parameters
    ----------
    statistics : dict
        ``intrinsics_covariance`` (K x K list, units of the parameters
        squared) with ``intrinsics_names`` (K), or ``intrinsics_sigma``
        (name -> standard deviation).
    source : str
        Name used in messages.

    Returns
    -------
    names : list of str, length K
    cov : ndarray, shape (K, K)
    note : str
        Where the covariance came from (says when only the diagonal is known).

    Raises
    ------
    DatasetError
        Neither entry is present, or the stored covariance is malformed
        (wrong shape, names missing, not finite, negative variances).
    """
    stats = statistics or {}
    if stats.get("intrinsics_covariance") is not None:
        names = stats.get("intrinsics_names")
        if not isinstance(names, (list, tuple)):
            raise DatasetError(
                f"{source}: statistics.intrinsics_covariance needs statistics.intrinsics_names"
            )
        names = [_check_name(n, source) for n in names]
        try:
            cov = np.asarray(stats["intrinsics_covariance"], float)
        except (TypeError, ValueError) as exc:
            raise DatasetError(
                f"{source}: statistics.intrinsics_covariance is not a matrix ({exc})"
            ) from None
        k = len(names)
        if cov.shape != (k, k):
            raise DatasetError(
                f"{source}: statistics.intrinsics_covariance has shape {cov.shape}, "
                f"expected ({k}, {k}) for intrinsics_names {names}"
            )
        if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
            raise DatasetError(
                f"{source}: statistics.intrinsics_covariance has NaN/inf or negative variances"
            )
        return names, 0.5 * (cov + cov.T), "full covariance of the intrinsics"
    sig = stats.get("intrinsics_sigma")
    if isinstance(sig, dict) and sig:
        names = [_check_name(n, source) for n in sig]
        try:
            s = np.array([float(sig[n]) for n in names])
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{source}: statistics.intrinsics_sigma: {exc}") from None
        if not np.all(np.isfinite(s)) or np.any(s < 0):
            raise DatasetError(f"{source}: statistics.intrinsics_sigma has NaN/inf or negatives")
        return (
            names,
            np.diag(s**2),
            "diagonal only (intrinsics_sigma; correlations unknown, so usually pessimistic)",
        )
    raise DatasetError(
        f"{source}: statistics has neither 'intrinsics_covariance' nor 'intrinsics_sigma'"
    )


def projection_jacobian(
    camera, rays: np.ndarray, names: list[str], steps: np.ndarray, uv_px: np.ndarray | None = None
) -> np.ndarray:
    """``d uv / d theta`` (N, 2, K) of fixed rays, by central differences.

    Parameters
    ----------
    camera : SphereCamera
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward).
    names : list of str, length K
        Intrinsics (see :func:`with_intrinsic`).
    steps : ndarray, shape (K,)
        Difference step of each parameter (its unit); a zero step gives a
        zero column.
    uv_px : ndarray, shape (N, 2), optional
        The rays' pixels on the unperturbed camera, the start of the
        projection on the perturbed ones (rays past a fold of the image).

    Returns
    -------
    J : ndarray, shape (N, 2, K)
        px per unit of each parameter; NaN where a perturbed camera has no
        pixel for the ray.
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    J = np.zeros((len(rays), 2, len(names)))
    for k, (name, h) in enumerate(zip(names, steps)):
        if not h > 0:
            continue
        v0 = intrinsic_value(camera, name)
        plus = project_rays(
            with_intrinsic(camera, name, v0 + h), rays, uv_px, tol_px=0.05, inside_image=False
        )
        minus = project_rays(
            with_intrinsic(camera, name, v0 - h), rays, uv_px, tol_px=0.05, inside_image=False
        )
        J[:, :, k] = (plus - minus) / (2 * h)
    return J


def ray_jacobian(
    camera, rays: np.ndarray, uv_px: np.ndarray | None = None, step_rad: float | None = None
) -> np.ndarray:
    """``d uv / d ray`` (N, 2, 3) of unit camera-frame rays, by central differences.

    Parameters
    ----------
    camera : SphereCamera
    rays : ndarray, shape (N, 3)
        Unit rays, camera frame (x right, y down, z forward).
    uv_px : ndarray, shape (N, 2), optional
        Their pixels, the start of the projection of the moved rays.
    step_rad : float, optional
        Difference step along each camera axis (default ``0.5 / c``: half a
        pixel on the axis).

    Returns
    -------
    A : ndarray, shape (N, 2, 3)
        px per unit change of each ray component; the component along the
        ray itself has no effect (``A @ ray = 0`` to first order). NaN where a
        moved ray has no pixel.
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    h = float(step_rad) if step_rad is not None else 0.5 / max(abs(float(camera.c)), 1e-9)
    A = np.zeros((len(rays), 2, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        plus = project_rays(camera, rays + e, uv_px, tol_px=0.05, inside_image=False)
        minus = project_rays(camera, rays - e, uv_px, tol_px=0.05, inside_image=False)
        A[:, :, i] = (plus - minus) / (2 * h)
    return A


def motion_jacobian(
    camera,
    rays: np.ndarray,
    uv_px: np.ndarray | None = None,
    range_m: float | None = None,
) -> np.ndarray:
    """``d uv / d (omega[, t])`` of the rays' points under a small camera motion.

    The point ``p = range_m * ray`` (camera frame) becomes ``Exp(omega) p + t``:
    ``d uv / d omega = A (-[ray]x)`` and ``d uv / d t = A / range_m`` with
    ``A`` from :func:`ray_jacobian` (the projection ignores the length of
    the point).

    Parameters
    ----------
    camera : SphereCamera
    rays : ndarray, shape (N, 3)
        Unit rays, camera frame.
    uv_px : ndarray, shape (N, 2), optional
        Their pixels (start of the projections).
    range_m : float, optional
        Distance of the points along the rays (calibration units); ``None``
        (infinity): rotation only.

    Returns
    -------
    G : ndarray, shape (N, 2, 3) or (N, 2, 6)
        Columns ``omega_x, omega_y, omega_z`` (px/rad) and, with ``range_m``,
        ``t_x, t_y, t_z`` (px per calibration unit).

    Raises
    ------
    ValueError
        ``range_m`` is not finite and positive.
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    if range_m is not None and not (math.isfinite(float(range_m)) and float(range_m) > 0):
        raise ValueError(f"range_m must be finite and > 0, got {range_m!r}")
    A = ray_jacobian(camera, rays, uv_px)
    G_rot = _rotation_columns(A, rays)
    if range_m is None:
        return G_rot
    return np.concatenate([G_rot, A / float(range_m)], axis=2)


def _rotation_columns(A: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """``d uv / d omega = A (-[ray]x)`` (N, 2, 3) from the ray Jacobian ``A`` (N, 2, 3)."""
    return -np.einsum("nij,njk->nik", A, skew(rays))


def _positive_range(value, name: str) -> float:
    try:
        r = float(value)
    except (TypeError, ValueError):
        r = math.nan
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return r


def compensate_jacobian(
    J: np.ndarray, G: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Remove from ``J`` what one global camera motion can absorb (weighted least squares).

    ``Jc = J - G X`` with ``X = argmin sum_n w_n |J_n - G_n X|^2``: for any
    change ``dtheta`` of the intrinsics, ``X dtheta`` is the motion that best
    re-aligns the projections in the weighted sense and ``Jc dtheta`` what is
    left. The fit uses the cells with ``w_n > 0`` and finite ``J_n, G_n``;
    a motion the fit region cannot determine (e.g. a rotation about the
    ray of a single cell) is left at zero (minimum-norm solution).

    Parameters
    ----------
    J : ndarray, shape (N, 2, K)
        Projection Jacobian wrt the intrinsics (px per unit of each).
    G : ndarray, shape (N, 2, m)
        Projection Jacobian wrt the motion (:func:`motion_jacobian`).
    weights : ndarray, shape (N,)
        Non-negative fit weight of each cell.

    Returns
    -------
    Jc : ndarray, shape (N, 2, K)
        Compensated Jacobian; NaN where ``J`` or ``G`` is not finite.
    X : ndarray, shape (m, K)
        Fitted motion per unit of each intrinsic (rad, calibration units).

    Raises
    ------
    ValueError
        Shapes disagree, a weight is negative or not finite, or no cell
        can be fitted.
    """
    J = np.asarray(J, float)
    G = np.asarray(G, float)
    w = np.asarray(weights, float).reshape(-1)
    if J.ndim != 3 or J.shape[1] != 2 or G.ndim != 3 or G.shape[:2] != J.shape[:2]:
        raise ValueError(f"J {J.shape} and G {G.shape} must be (N, 2, K) and (N, 2, m)")
    if w.shape != (J.shape[0],):
        raise ValueError(f"weights has shape {w.shape}, expected ({J.shape[0]},)")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and >= 0")
    finite = np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(G), axis=(1, 2))
    use = finite & (w > 0)
    if not use.any():
        raise ValueError("no cell with a positive weight and a finite Jacobian to fit over")
    sw = np.sqrt(w[use])[:, None, None]
    A = (G[use] * sw).reshape(-1, G.shape[2])
    B = (J[use] * sw).reshape(-1, J.shape[2])
    scale = np.linalg.norm(A, axis=0)
    scale[~(scale > 0)] = 1.0
    Xs = np.linalg.lstsq(A / scale, B, rcond=1e-9)[0]
    X = Xs / scale[:, None]
    Jc = J - np.einsum("nim,mk->nik", G, X)
    Jc[~finite] = np.nan
    return Jc, X


def cell_weights(
    u_px: np.ndarray,
    v_px: np.ndarray,
    uv_px: np.ndarray,
    weight: np.ndarray | None = None,
) -> np.ndarray:
    """Observations per cell of a grid (the fit weights of the compensation).

    Parameters
    ----------
    u_px : ndarray, shape (C,)
        Column centres (px), evenly spaced.
    v_px : ndarray, shape (R,)
        Row centres (px), evenly spaced.
    uv_px : ndarray, shape (M, 2)
        Observed pixels; non-finite rows and pixels outside the grid's
        cells are ignored.
    weight : ndarray, shape (M,), optional
        Weight of each observation (e.g. its robust weight); default 1.

    Returns
    -------
    counts : ndarray, shape (R, C)
        Sum of the weights of the observations in each cell.

    Raises
    ------
    ValueError
        ``uv_px`` is not (M, 2), or ``weight`` has the wrong length, is not
        finite or negative.
    """
    u = np.asarray(u_px, float).reshape(-1)
    v = np.asarray(v_px, float).reshape(-1)
    uv = np.asarray(uv_px, float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"fit_uv_px must have shape (M, 2), got {uv.shape}")
    w = np.ones(len(uv)) if weight is None else np.asarray(weight, float).reshape(-1)
    if w.shape != (len(uv),):
        raise ValueError(f"fit_weight has shape {w.shape}, expected ({len(uv)},)")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("fit_weight must be finite and >= 0")
    du = u[1] - u[0] if len(u) > 1 else 1.0
    dv = v[1] - v[0] if len(v) > 1 else 1.0
    ok = np.all(np.isfinite(uv), axis=1)
    ci = np.floor((uv[ok, 0] - u[0]) / du + 0.5).astype(int)
    ri = np.floor((uv[ok, 1] - v[0]) / dv + 0.5).astype(int)
    inside = (ci >= 0) & (ci < len(u)) & (ri >= 0) & (ri < len(v))
    counts = np.zeros((len(v), len(u)))
    np.add.at(counts, (ri[inside], ci[inside]), w[ok][inside])
    return counts


def knn_sigma_px(correction, uv_px: np.ndarray) -> np.ndarray | None:
    """Standard error (px) of a kNN correction's prediction at pixels (N, 2), shape (N,).

    ``sqrt(sum_j |y_j - y_hat|^2 / (k - 1)) / sqrt(k)`` over the ``k``
    training neighbours ``j`` (``y`` their training corrections, ``y_hat``
    the prediction, the uniform mean). ``None`` when ``correction`` is not a
    fitted :class:`~gtsam_sphere.core.correction_model.KNNCorrection` (no training set).
    For a local-linear model (``degree_ == 1``, the pure sphere mapping) this
    is the plain average's figure, an approximation: the spread then holds the
    field's local gradient (too large) and the plane's leverage at the border
    is left out (too small).
    """
    reg = getattr(correction, "regressor_", None)
    y = getattr(correction, "corrections_px_", None)
    k = getattr(correction, "n_neighbors_", None)
    if reg is None or y is None or k is None or not hasattr(reg, "kneighbors"):
        return None
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    out = np.full(len(uv), np.nan)
    ok = np.all(np.isfinite(uv), axis=1)
    if not ok.any():
        return out
    k = int(min(k, len(y)))
    _, idx = reg.kneighbors(uv[ok], n_neighbors=k)
    yn = np.asarray(y, float)[idx]  # (M, k, 2)
    mean = yn.mean(axis=1, keepdims=True)
    ss = np.sum((yn - mean) ** 2, axis=(1, 2))
    out[ok] = np.sqrt(ss / max(k - 1, 1)) / math.sqrt(k)
    return out


@dataclass
class UncertaintyMap:
    """Projection uncertainty on a grid over the image.

    Attributes
    ----------
    u_px : ndarray, shape (C,)
        Column centres (px, OpenCV convention).
    v_px : ndarray, shape (R,)
        Row centres (px).
    sigma_px : ndarray, shape (R, C)
        Total: ``sqrt(sigma_intrinsics^2 + sigma_knn^2)`` (px); NaN where
        the camera has no ray.
    sigma_intrinsics_px : ndarray, shape (R, C)
        ``sqrt(trace(J Sigma J^T))`` (px), with the compensated ``Jc`` in
        place of ``J`` when :attr:`compensation` is not ``"none"``.
    sigma_knn_px : ndarray, shape (R, C)
        Local kNN term (px); zeros without a learned correction.
    cov_px : ndarray, shape (R, C, 2, 2)
        ``J Sigma J^T`` (or ``Jc Sigma Jc^T``) (px^2).
    names : list of str
        Intrinsics propagated.
    note : str
        Where the covariance came from, the compensation and the kNN term.
    sigma_fixed_ray_px : ndarray, shape (R, C), optional
        The intrinsics term of a fixed camera-frame ray (px), no
        compensation: equal to ``sigma_intrinsics_px`` when
        :attr:`compensation` is ``"none"``.
    compensation : str
        ``"none"`` (a fixed camera-frame ray), ``"rotation"`` or
        ``"rotation+translation"`` (the motion fitted, see the module
        docstring).
    fit_weight : ndarray, shape (R, C), optional
        Weight of each cell in the fit of the motion (observations per cell,
        or 1 on every cell with a ray); ``None`` without compensation.
    motion_sigma : ndarray, shape (m,), optional
        Standard deviation of the fitted motion, ``omega_x, omega_y,
        omega_z`` (rad) then ``t_x, t_y, t_z`` (calibration units): how much
        of the intrinsics' uncertainty is a motion of the camera frame.
    range_m : float, optional
        Range of the points the map is evaluated at (calibration units);
        ``None``: infinity.
    fit_note : str
        The fit region in words (empty without compensation).
    fit_ranges_m : tuple of float
        Ranges of the points the translation was fitted at (calibration
        units); empty for a rotation only.
    motion_per_intrinsic : ndarray, shape (m, K), optional
        The fitted motion per unit of each intrinsic (``X`` of
        :func:`compensate_jacobian`: rad, calibration units): the
        compensation, reusable at other rays (:func:`ray_sigma_px`);
        ``None`` without compensation.
    """

    u_px: np.ndarray
    v_px: np.ndarray
    sigma_px: np.ndarray
    sigma_intrinsics_px: np.ndarray
    sigma_knn_px: np.ndarray
    cov_px: np.ndarray
    names: list[str]
    note: str
    sigma_fixed_ray_px: np.ndarray | None = None
    compensation: str = "none"
    fit_weight: np.ndarray | None = None
    motion_sigma: np.ndarray | None = None
    range_m: float | None = None
    fit_note: str = ""
    fit_ranges_m: tuple[float, ...] = ()
    motion_per_intrinsic: np.ndarray | None = None

    def summary(self, mask: np.ndarray | None = None) -> dict:
        """Median and max of ``sigma_px`` (px) over the finite cells (and ``mask`` (R, C))."""
        v = self.sigma_px
        ok = np.isfinite(v) if mask is None else np.isfinite(v) & mask
        if not ok.any():
            return {"median_px": math.nan, "max_px": math.nan, "n_cells": 0}
        return {
            "median_px": float(np.median(v[ok])),
            "max_px": float(np.max(v[ok])),
            "n_cells": int(ok.sum()),
        }

    def fit_region(self) -> np.ndarray | None:
        """Cells (R, C) the motion was fitted over (``fit_weight > 0``), or ``None``."""
        return None if self.fit_weight is None else self.fit_weight > 0

    def describe(self) -> str:
        """Which map this is, in one phrase (for captions and reports)."""
        if self.compensation == "none":
            return "a fixed camera-frame ray (camera frame not compensated)"
        what = "rotation" if self.compensation == "rotation" else "rotation and translation"
        at = (
            "points at infinity"
            if self.range_m is None
            else f"points at range {self.range_m:.4g} (calibration units)"
        )
        return f"{at}, after the camera {what} that best re-aligns the image over {self.fit_note}"


def uncertainty_map(
    camera,
    covariance: np.ndarray,
    names: list[str],
    n_cols: int = 40,
    note: str = "",
    include_knn: bool = True,
    compensate_rotation: bool = False,
    fit_uv_px: np.ndarray | None = None,
    fit_weight: np.ndarray | None = None,
    range_m: float | None = None,
    fit_ranges_m=None,
) -> UncertaintyMap:
    """Projection uncertainty (px) on a grid over the image.

    Parameters
    ----------
    camera : SphereCamera
    covariance : ndarray, shape (K, K)
        Covariance of the intrinsics ``names`` (their units squared).
    names : list of str, length K
        Intrinsics names (``xp_px, yp_px, c_px``, Brown / radial terms).
    n_cols : int
        Grid columns (rows follow the aspect ratio); cell centres are used.
    note : str
        Where ``covariance`` came from (kept in the result).
    include_knn : bool
        Add the local kNN term when the camera has a fitted kNN correction.
    compensate_rotation : bool
        ``False`` (default here, for a fixed camera-frame ray): the pixel of
        a fixed ray. ``True``: after the camera motion that best re-aligns
        the perturbed projection with the nominal one over the fit region
        (module docstring); :func:`uncertainty_map_of` and the report use
        this.
    fit_uv_px : ndarray, shape (M, 2), optional
        Observed pixels (raw, OpenCV convention): the fit weight of a cell is
        the number of them in it. Default: every cell with a ray, weight 1.
    fit_weight : ndarray, shape (M,), optional
        Weight of each of ``fit_uv_px`` (e.g. the robust weights).
    range_m : float, optional
        With compensation: the range (calibration units) of the points the
        map is evaluated at. ``None``: points at infinity.
    fit_ranges_m : float or sequence of float, optional
        With compensation: fit a rotation and a translation over the grid's
        points at each of these ranges (calibration units, weights shared).
        Default: ``[range_m]`` when ``range_m`` is given, else a rotation
        only, fitted at infinity. One range alone gives the same map for any
        range (only ``t / range`` is determined): a single shell of points
        lets the translation absorb most of a change of ``c``, which is
        optimistic for a scene spanning several depths.

    Returns
    -------
    UncertaintyMap
        ``sigma_fixed_ray_px`` always holds the uncompensated term.

    Raises
    ------
    ValueError
        Shapes disagree, a name is not a parameter of the camera, a range is
        not finite and positive or given without compensation, or no
        observation falls on a cell with a ray.
    """
    cov = np.asarray(covariance, float)
    names = list(names)
    if cov.shape != (len(names), len(names)):
        raise ValueError(f"covariance has shape {cov.shape}, expected {len(names)} x {len(names)}")
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance has NaN/inf entries")
    for n in names:
        intrinsic_value(camera, n)  # raises for an unknown name
    if (range_m is not None or fit_ranges_m is not None) and not compensate_rotation:
        raise ValueError("range_m and fit_ranges_m only apply with compensate_rotation=True")
    if range_m is not None:
        range_m = _positive_range(range_m, "range_m")
    if fit_ranges_m is None:
        fit_ranges = [] if range_m is None else [range_m]
    else:
        fit_ranges = [
            _positive_range(r, "fit_ranges_m") for r in np.atleast_1d(np.asarray(fit_ranges_m))
        ]
        if not fit_ranges:
            raise ValueError("fit_ranges_m is empty")
    if fit_weight is not None and fit_uv_px is None:
        raise ValueError("fit_weight needs fit_uv_px")
    n_cols = max(int(n_cols), 2)
    n_rows = max(int(round(n_cols * camera.height / max(camera.width, 1))), 2)
    u = (np.arange(n_cols) + 0.5) * camera.width / n_cols - 0.5
    v = (np.arange(n_rows) + 0.5) * camera.height / n_rows - 0.5
    gu, gv = np.meshgrid(u, v)
    uv = np.column_stack([gu.ravel(), gv.ravel()])
    rays = pixel_rays(camera, uv)
    ok = np.all(np.isfinite(rays), axis=1)
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    J = np.full((len(uv), 2, len(names)), np.nan)
    if ok.any():
        J[ok] = projection_jacobian(camera, rays[ok], names, sig, uv[ok])
    J[:, :, ~(sig > 0)] = 0.0
    C_fixed = np.einsum("nik,kl,njl->nij", J, cov, J)
    s_fixed = np.sqrt(np.clip(C_fixed[:, 0, 0] + C_fixed[:, 1, 1], 0.0, None))
    s_fixed[~ok] = np.nan
    C, s_intr = C_fixed, s_fixed
    compensation, weights, motion_sigma, fit_note, X = "none", None, None, "", None
    if compensate_rotation:
        A = np.full((len(uv), 2, 3), np.nan)
        if ok.any():
            A[ok] = ray_jacobian(camera, rays[ok], uv[ok])
        G_rot = _rotation_columns(A, np.where(ok[:, None], rays, 0.0))
        usable = ok & np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(A), axis=(1, 2))
        if fit_uv_px is None:
            w = usable.astype(float)
            fit_note = f"every cell with a ray ({int(usable.sum())} cells, uniform weights)"
        else:
            w = cell_weights(u, v, fit_uv_px, fit_weight).ravel() * usable
            if not np.any(w > 0):
                raise ValueError("no observation of fit_uv_px falls on a cell with a ray")
            per = (
                "its number of observations"
                if fit_weight is None
                else "the sum of its observations' weights"
            )
            fit_note = (
                f"the {int(np.sum(w > 0))} cells holding observations, each weighted by {per}"
            )
        if fit_ranges:
            # one block of rows per range shell: p = r ray, d uv / d t = A / r
            G_fit = np.concatenate([np.concatenate([G_rot, A / r], axis=2) for r in fit_ranges])
            _, X = compensate_jacobian(
                np.concatenate([J] * len(fit_ranges)), G_fit, np.tile(w, len(fit_ranges))
            )
            G_t = 0.0 * A if range_m is None else A / range_m  # no effect at infinity
            G_eval = np.concatenate([G_rot, G_t], axis=2)
            fit_note += "; fitted with the points at range " + ", ".join(
                f"{r:.4g}" for r in fit_ranges
            )
        else:
            _, X = compensate_jacobian(J, G_rot, w)
            G_eval = G_rot
        Jc = J - np.einsum("nim,mk->nik", G_eval, X)
        C = np.einsum("nik,kl,njl->nij", Jc, cov, Jc)
        s_intr = np.sqrt(np.clip(C[:, 0, 0] + C[:, 1, 1], 0.0, None))
        s_intr[~usable] = np.nan
        C[~usable] = np.nan
        motion_sigma = np.sqrt(np.clip(np.diag(X @ cov @ X.T), 0.0, None))
        compensation = "rotation" if not fit_ranges else "rotation+translation"
        weights = w.reshape(n_rows, n_cols)
    s_knn = np.zeros(len(uv))
    corr = getattr(camera, "correction", None)
    if include_knn and corr is not None:
        knn = knn_sigma_px(corr, uv)
        if knn is not None:
            s_knn = np.where(np.isfinite(knn), knn, 0.0)
            note = (note + "; " if note else "") + (
                f"plus the kNN correction's local standard error (k = {corr.n_neighbors_})"
            )
        else:
            note = (note + "; " if note else "") + "learned correction without a kNN training set"
    s_knn[~ok] = np.nan
    total = np.sqrt(s_intr**2 + s_knn**2)
    shape = (n_rows, n_cols)
    result = UncertaintyMap(
        u_px=u,
        v_px=v,
        sigma_px=total.reshape(shape),
        sigma_intrinsics_px=s_intr.reshape(shape),
        sigma_knn_px=s_knn.reshape(shape),
        cov_px=C.reshape(shape + (2, 2)),
        names=names,
        note=note,
        sigma_fixed_ray_px=s_fixed.reshape(shape),
        compensation=compensation,
        fit_weight=weights,
        motion_sigma=motion_sigma,
        range_m=range_m,
        fit_note=fit_note,
        fit_ranges_m=tuple(fit_ranges),
        motion_per_intrinsic=X,
    )
    return result


def observed_pixels(calib) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Observed pixels (M, 2) and their robust weights (M,) stored in ``calib``, or ``None``s.

    From ``calib.extra["observations"]`` (``uv_px``, ``weight``); rows with a
    non-finite pixel are dropped, a missing or malformed ``weight`` is 1.
    """
    obs = calib.extra.get("observations") if isinstance(calib.extra, dict) else None
    if not isinstance(obs, dict) or obs.get("uv_px") is None:
        return None, None
    try:
        uv = np.asarray(obs["uv_px"], float).reshape(-1, 2)
    except (TypeError, ValueError):
        return None, None
    w = np.ones(len(uv))
    if obs.get("weight") is not None:
        try:
            wt = np.asarray(obs["weight"], float).reshape(-1)
        except (TypeError, ValueError):
            wt = w
        if wt.shape == w.shape and np.all(np.isfinite(wt)) and np.all(wt >= 0):
            w = wt
    keep = np.all(np.isfinite(uv), axis=1)
    if not keep.any():
        return None, None
    return uv[keep], w[keep]


def uncertainty_map_of(
    calib,
    n_cols: int = 40,
    source: str | None = None,
    compensate_rotation: bool = True,
    range_m: float | None = None,
    fit_ranges_m=None,
) -> UncertaintyMap:
    """:func:`uncertainty_map` of a loaded calibration, covariance from its statistics.

    The camera frame is compensated by default (the report's map), fitted
    over the calibration's own observations (:func:`observed_pixels`, each
    weighted by its robust weight); a calibration without stored
    observations is fitted uniformly over the image, and the note says so.

    Parameters
    ----------
    calib : Calibration
    n_cols : int
        Grid columns.
    source : str, optional
        Name used in messages.
    compensate_rotation : bool
        ``False``: the map of a fixed camera-frame ray.
    range_m, fit_ranges_m : optional
        Evaluation range and the ranges a translation is fitted at
        (calibration units), as in :func:`uncertainty_map`; default: points
        at infinity, rotation only.

    Returns
    -------
    UncertaintyMap

    Raises
    ------
    DatasetError
        No usable covariance in ``calib.statistics``, it names a parameter
        the camera does not have, or a range is invalid.
    """
    where = source or str(calib.extra.get("source", "<calibration>"))
    names, cov, note = intrinsics_covariance(calib.statistics, where)
    uv, w = observed_pixels(calib) if compensate_rotation else (None, None)
    kwargs = dict(
        n_cols=n_cols,
        note=note,
        compensate_rotation=compensate_rotation,
        range_m=range_m,
        fit_ranges_m=fit_ranges_m,
    )
    try:
        try:
            return uncertainty_map(calib.camera, cov, names, fit_uv_px=uv, fit_weight=w, **kwargs)
        except ValueError as exc:
            if uv is None or "no observation" not in str(exc):
                raise
        umap = uncertainty_map(calib.camera, cov, names, **kwargs)
        umap.fit_note += " (no stored observation falls on a cell with a ray)"
        return umap
    except ValueError as exc:
        raise DatasetError(f"{where}: {exc}") from None


# -- the valid region: where the projection uncertainty is small ---------------------------------


def ray_sigma_px(
    camera,
    rays: np.ndarray,
    covariance: np.ndarray,
    names: list[str],
    motion_per_intrinsic: np.ndarray | None = None,
    range_m: float | None = None,
    include_knn: bool = True,
) -> np.ndarray:
    """Projection uncertainty (px) of camera-frame rays, the quantity of :class:`UncertaintyMap`.

    ``sqrt(trace(Jc Sigma Jc^T) + sigma_knn^2)`` at each ray's pixel, with
    ``Jc = J - G X`` the Jacobian wrt the intrinsics after the compensating
    camera motion ``X`` fitted by :func:`uncertainty_map` (its
    :attr:`UncertaintyMap.motion_per_intrinsic`; ``None``: a fixed
    camera-frame ray, ``Jc = J``).

    Parameters
    ----------
    camera : SphereCamera
    rays : ndarray, shape (N, 3)
        Unit rays, camera frame (x right, y down, z forward).
    covariance : ndarray, shape (K, K)
        Covariance of the intrinsics ``names`` (their units squared).
    names : list of str, length K
    motion_per_intrinsic : ndarray, shape (3, K) or (6, K), optional
        Motion per unit of each intrinsic (rotation rad, then translation in
        calibration units).
    range_m : float, optional
        With a 6-row motion: range of the points (calibration units);
        ``None``: infinity, the translation has no effect.
    include_knn : bool
        Add the kNN correction's local standard error (:func:`knn_sigma_px`).

    Returns
    -------
    sigma_px : ndarray, shape (N,)
        NaN where the camera (or a perturbed one) has no pixel for the ray.

    Raises
    ------
    ValueError
        Shapes disagree or a name is not a parameter of the camera.
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    cov = np.asarray(covariance, float)
    names = list(names)
    if cov.shape != (len(names), len(names)):
        raise ValueError(f"covariance has shape {cov.shape}, expected {len(names)} x {len(names)}")
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        uv = np.asarray(camera.project(rays), float).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1)
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    J = np.full((len(rays), 2, len(names)), np.nan)
    if ok.any():
        J[ok] = projection_jacobian(camera, rays[ok], names, sig, uv[ok])
    J[:, :, ~(sig > 0)] = 0.0
    if motion_per_intrinsic is not None:
        X = np.asarray(motion_per_intrinsic, float)
        if X.ndim != 2 or X.shape[0] not in (3, 6) or X.shape[1] != len(names):
            raise ValueError(
                f"motion_per_intrinsic has shape {X.shape}, expected (3|6, {len(names)})"
            )
        A = np.full((len(rays), 2, 3), np.nan)
        if ok.any():
            A[ok] = ray_jacobian(camera, rays[ok], uv[ok])
        G = _rotation_columns(A, np.where(ok[:, None], rays, 0.0))
        if X.shape[0] == 6:
            G_t = 0.0 * A if range_m is None else A / _positive_range(range_m, "range_m")
            G = np.concatenate([G, G_t], axis=2)
        J = J - np.einsum("nim,mk->nik", G, X)
    C = np.einsum("nik,kl,njl->nij", J, cov, J)
    var = C[:, 0, 0] + C[:, 1, 1]
    corr = getattr(camera, "correction", None)
    if include_knn and corr is not None and ok.any():
        knn = knn_sigma_px(corr, np.where(ok[:, None], uv, 0.0))
        if knn is not None:
            var = var + np.where(np.isfinite(knn), knn, 0.0) ** 2
    out = np.sqrt(np.clip(var, 0.0, None))
    out[~ok | ~np.isfinite(out)] = np.nan
    return out


@dataclass
class ValidRegion:
    """Where a calibration's projection uncertainty is small, on a polar grid of rays.

    The rays at azimuth ``phi`` (``atan2(y, x)`` of the camera-frame ray,
    x right, y down) and incidence ``alpha`` (from the optical axis z) are
    ``(sin a cos phi, sin a sin phi, cos a)``.

    Attributes
    ----------
    azimuth_rad : ndarray, shape (A,)
        ``2 pi i / A`` (rad).
    alpha_rad : ndarray, shape (L,)
        Incidence angles of the grid (rad), up to the camera's
        ``valid_alpha_rad()`` (observed field plus margin, one-to-one field).
    sigma_px : ndarray, shape (A, L)
        Projection uncertainty (px, :func:`ray_sigma_px`) of each grid ray.
    alpha_max_rad : ndarray, shape (A,)
        Per azimuth, the incidence up to which every grid ray from the axis
        outwards has ``sigma_px <= max_sigma_px`` (linear interpolation to the
        crossing); 0 when the axis already exceeds it. What the camera holds
        as ``valid_region_alpha_rad``.
    max_sigma_px : float
        The threshold (px).
    note : str
        The map's description (covariance, compensation, kNN term).
    """

    azimuth_rad: np.ndarray
    alpha_rad: np.ndarray
    sigma_px: np.ndarray
    alpha_max_rad: np.ndarray
    max_sigma_px: float
    note: str = ""

    def solid_angle_sr(self) -> float:
        """Solid angle of the region (sr): ``sum_i (1 - cos alpha_max_i) 2 pi / A``."""
        return float(np.sum(1.0 - np.cos(self.alpha_max_rad)) * 2 * math.pi / len(self.azimuth_rad))


def valid_region(
    calib,
    max_sigma_px: float = 1.0,
    n_azimuth: int = 72,
    n_alpha: int = 48,
    n_cols: int = 40,
    source: str | None = None,
) -> ValidRegion:
    """The valid region of a calibration: rays whose projection uncertainty is small.

    Like mrcal's valid-intrinsics region (the part of the image where the
    projection uncertainty stays below a threshold, see
    https://mrcal.secretsauce.net/uncertainty.html), but stored on the ray
    sphere as a star-shaped region about the optical axis: per azimuth, the
    largest incidence up to which the uncertainty of :func:`uncertainty_map_of`
    (camera frame compensated by the rotation fitted over the observations,
    plus the kNN term) stays below ``max_sigma_px``, within the camera's
    ``valid_alpha_rad()`` (the observed field plus its margin, and the lens's
    one-to-one field). A region that is not star-shaped (a hole of large
    uncertainty inside the field) is cut at its first crossing. A ray whose
    sigma is NaN counts as outside: a model moved by one sigma of an
    intrinsic has no pixel for it, e.g. the radial polynomial with one
    sigma more of a weakly determined high-order term folds there (on the
    real ``opencv_fisheye_left`` calibration, past 61 deg on every azimuth,
    just inside its 63 deg field).

    Parameters
    ----------
    calib : Calibration
        With ``statistics["intrinsics_covariance"]`` (or ``intrinsics_sigma``).
    max_sigma_px : float
        Threshold on the projection uncertainty (px, RMS length of the 2-D
        error as ``rms_px``).
    n_azimuth : int
        Azimuths of the table (>= 4).
    n_alpha : int
        Incidence samples per azimuth (>= 2).
    n_cols : int
        Grid columns of the map the compensation is fitted on.
    source : str, optional
        Name used in messages.

    Returns
    -------
    ValidRegion

    Raises
    ------
    DatasetError
        No usable covariance in ``calib.statistics`` (see
        :func:`uncertainty_map_of`).
    OptionsError
        ``max_sigma_px`` not finite and positive, or a grid size too small.
    """
    try:
        thr = float(max_sigma_px)
    except (TypeError, ValueError):
        thr = math.nan
    if not (math.isfinite(thr) and thr > 0):
        raise OptionsError(f"max_sigma_px must be finite and > 0, got {max_sigma_px!r}")
    if int(n_azimuth) < 4 or int(n_alpha) < 2:
        raise OptionsError(f"need n_azimuth >= 4 and n_alpha >= 2, got {n_azimuth}, {n_alpha}")
    camera = copy.copy(calib.camera)
    camera.valid_region_alpha_rad = None  # the region is computed on the plain camera
    plain = copy.copy(calib)
    plain.camera = camera
    umap = uncertainty_map_of(plain, n_cols=n_cols, source=source)
    where = source or str(calib.extra.get("source", "<calibration>"))
    names, cov, _ = intrinsics_covariance(calib.statistics, where)
    az = 2 * math.pi * np.arange(int(n_azimuth)) / int(n_azimuth)
    top = camera.valid_alpha_rad() * (1 - 1e-9)
    # the differences step past the edge of the field: evaluate without the observed limit
    camera = copy.copy(camera)
    camera.observed_alpha_rad = None
    alpha = np.linspace(0.0, top, int(n_alpha) + 1)[1:]
    A, L = np.meshgrid(alpha, az)  # (n_azimuth, n_alpha)
    rays = np.stack([np.sin(A) * np.cos(L), np.sin(A) * np.sin(L), np.cos(A)], axis=-1).reshape(
        -1, 3
    )
    sigma = ray_sigma_px(camera, rays, cov, names, umap.motion_per_intrinsic).reshape(A.shape)
    alpha_max = np.empty(len(az))
    for i, row in enumerate(sigma):
        bad = np.flatnonzero(~(row <= thr))
        if not len(bad):
            alpha_max[i] = alpha[-1]
        elif bad[0] == 0:
            alpha_max[i] = 0.0
        else:
            j = bad[0]
            f = (thr - row[j - 1]) / (row[j] - row[j - 1]) if np.isfinite(row[j]) else 0.0
            alpha_max[i] = alpha[j - 1] + f * (alpha[j] - alpha[j - 1])
    note = umap.describe() + (f"; {umap.note}" if umap.note else "")
    return ValidRegion(az, alpha, sigma, alpha_max, thr, note)


def with_valid_region(calib, max_sigma_px: float = 1.0, **kwargs):
    """A copy of ``calib.camera`` holding its valid region (:func:`valid_region`).

    The copy's ``project`` (``valid_only=True``, the default) then returns
    NaN for rays outside the region, and ``valid_mask`` / ``valid_pixel_mask``
    exclude them; ``project(..., valid_only=False)`` still answers every ray.
    Written to calibration files as ``camera.valid_region_alpha_rad``.

    Parameters
    ----------
    calib : Calibration
    max_sigma_px : float
        Threshold on the projection uncertainty (px).
    **kwargs
        Passed to :func:`valid_region` (``n_azimuth``, ``n_alpha``, ``n_cols``,
        ``source``).

    Returns
    -------
    SphereCamera
        ``valid_region_alpha_rad`` set (shape (n_azimuth,), rad); the
        learned correction and its tables are shared with ``calib.camera``.

    Examples
    --------
    >>> calib.camera = with_valid_region(calib, max_sigma_px=0.5)  # doctest: +SKIP
    >>> uv = calib.camera.project(points_cam)  # NaN where sigma > 0.5 px  # doctest: +SKIP
    """
    region = valid_region(calib, max_sigma_px, **kwargs)
    cam = copy.copy(calib.camera)
    cam.valid_region_alpha_rad = tuple(float(a) for a in region.alpha_max_rad)
    return cam
