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
of :class:`~gtsam_sphere.correct.KNNCorrection`) adds a local term: the
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
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from .camera import BROWN_TERMS
from .dataset import DatasetError

# names of the base intrinsics -> SphereCamera attribute
_BASE = {"xp_px": "xp", "xp": "xp", "yp_px": "yp", "yp": "yp", "c_px": "c", "c": "c"}


def _radial_names() -> tuple[str, ...]:
    from . import camera as camera_module

    return tuple(getattr(camera_module, "RADIAL_TERMS", ()))


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
    from .export import project_rays

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


def knn_sigma_px(correction, uv_px: np.ndarray) -> np.ndarray | None:
    """Standard error (px) of a kNN correction's prediction at pixels (N, 2), shape (N,).

    ``sqrt(sum_j |y_j - y_hat|^2 / (k - 1)) / sqrt(k)`` over the ``k``
    training neighbours ``j`` (``y`` their training corrections, ``y_hat``
    the prediction, the uniform mean). ``None`` when ``correction`` is not a
    fitted :class:`~gtsam_sphere.correct.KNNCorrection` (no training set).
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
        ``sqrt(trace(J Sigma J^T))`` (px).
    sigma_knn_px : ndarray, shape (R, C)
        Local kNN term (px); zeros without a learned correction.
    cov_px : ndarray, shape (R, C, 2, 2)
        ``J Sigma J^T`` (px^2).
    names : list of str
        Intrinsics propagated.
    note : str
        Where the covariance came from, and the kNN term if any.
    """

    u_px: np.ndarray
    v_px: np.ndarray
    sigma_px: np.ndarray
    sigma_intrinsics_px: np.ndarray
    sigma_knn_px: np.ndarray
    cov_px: np.ndarray
    names: list[str]
    note: str

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


def uncertainty_map(
    camera,
    covariance: np.ndarray,
    names: list[str],
    n_cols: int = 40,
    note: str = "",
    include_knn: bool = True,
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

    Returns
    -------
    UncertaintyMap

    Raises
    ------
    ValueError
        Shapes disagree or a name is not a parameter of the camera.
    """
    from .export import pixel_rays

    cov = np.asarray(covariance, float)
    names = list(names)
    if cov.shape != (len(names), len(names)):
        raise ValueError(f"covariance has shape {cov.shape}, expected {len(names)} x {len(names)}")
    for n in names:
        intrinsic_value(camera, n)  # raises for an unknown name
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
    C = np.einsum("nik,kl,njl->nij", J, cov, J)
    s_intr = np.sqrt(np.clip(C[:, 0, 0] + C[:, 1, 1], 0.0, None))
    s_intr[~ok] = np.nan
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
    return UncertaintyMap(
        u_px=u,
        v_px=v,
        sigma_px=total.reshape(shape),
        sigma_intrinsics_px=s_intr.reshape(shape),
        sigma_knn_px=s_knn.reshape(shape),
        cov_px=C.reshape(shape + (2, 2)),
        names=names,
        note=note,
    )


def uncertainty_map_of(calib, n_cols: int = 40, source: str | None = None) -> UncertaintyMap:
    """:func:`uncertainty_map` of a loaded calibration, covariance from its statistics.

    Parameters
    ----------
    calib : Calibration
    n_cols : int
        Grid columns.
    source : str, optional
        Name used in messages.

    Returns
    -------
    UncertaintyMap

    Raises
    ------
    DatasetError
        No usable covariance in ``calib.statistics``, or it names a
        parameter the camera does not have.
    """
    where = source or str(calib.extra.get("source", "<calibration>"))
    names, cov, note = intrinsics_covariance(calib.statistics, where)
    try:
        return uncertainty_map(calib.camera, cov, names, n_cols=n_cols, note=note)
    except ValueError as exc:
        raise DatasetError(f"{where}: {exc}") from None
