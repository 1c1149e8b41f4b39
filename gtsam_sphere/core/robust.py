"""Robust M-estimators: the one home of the loss functions and robust scales (issue 14).

Every robust weighting of the package goes through here: the factor blocks
(``estimation.graph``), the GTSAM-noise-model blocks (``estimation.external``),
the single-image resection (``estimation.resect``), P3P's pose refinement
(``core.p3p``) and the rig's robust pose means (``estimation.rig``).

For a whitened residual norm ``r`` and threshold ``k``, :func:`robust_weight`
gives the IRLS weight ``w(r)`` and the cost ``rho(r)`` (``r^2 / 2`` near zero for
every loss); :func:`whitening_scale` turns ``rho`` into the factor on the residual
whose squared norm is ``2 rho``.
"""

from __future__ import annotations

import numpy as np

from ._compat import StrEnum

__all__ = [
    "MEDIAN_NORM_2D",
    "MEDIAN_NORM_3D",
    "MAD_TO_SIGMA",
    "MAD_RELATIVE_SE",
    "MIN_REDUNDANCY",
    "Loss",
    "mad_sigma",
    "robust_sigma_px",
    "robust_weight",
    "whitening_scale",
]

#: median of the norm of a 2-D standard normal vector, ``sqrt(2 ln 2)``
MEDIAN_NORM_2D = float(np.sqrt(2.0 * np.log(2.0)))
#: median of the norm of a 3-D standard normal vector: turns a median deviation into a
#: per-axis standard deviation
MEDIAN_NORM_3D = 1.5382
#: the median absolute deviation of a 1-D normal is this fraction of its sigma, inverted
MAD_TO_SIGMA = 1.4826
#: relative standard error of that sigma on ``n`` normal values, times ``sqrt(n)``: the
#: MAD's efficiency is 37 % of the standard deviation's, whose relative error is
#: ``0.707 / sqrt(n)``; ``0.707 / sqrt(0.37) = 1.166``
MAD_RELATIVE_SE = 1.166


class Loss(StrEnum):
    """Robust M-estimators, applied per observation to the whitened residual norm."""

    L2 = "l2"
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"
    GEMAN_MCCLURE = "geman-mcclure"
    #: truncated quadratic, ``min(r, k)^2 / 2``: every residual beyond ``k`` costs the
    #: same wherever it lands, so it ranks solutions without rewarding one for moving
    #: toward blunders (the first stage's starts, ``estimation.calibrate``); as an IRLS
    #: loss it gives weight 1 inside ``k`` and 0 beyond
    TRUNCATED = "truncated"


def robust_weight(r: np.ndarray, loss: Loss | str, k: float) -> tuple[np.ndarray, np.ndarray]:
    """IRLS weight ``w(r)`` and cost ``rho(r)`` of whitened residual norms ``r`` (N,).

    ``rho(r) = r^2 / 2`` near zero for every loss, so costs compare with L2.
    """
    loss = Loss(loss)
    r = np.asarray(r, float)
    if loss is Loss.L2:
        return np.ones_like(r), 0.5 * r * r
    if loss is Loss.HUBER:
        big = r > k
        w = np.where(big, k / np.maximum(r, 1e-300), 1.0)
        rho = np.where(big, k * r - 0.5 * k * k, 0.5 * r * r)
        return w, rho
    if loss is Loss.CAUCHY:
        q = (r / k) ** 2
        return 1.0 / (1.0 + q), 0.5 * k * k * np.log1p(q)
    if loss is Loss.TUKEY:
        q = np.minimum((r / k) ** 2, 1.0)
        return (1.0 - q) ** 2 * (r <= k), k * k / 6.0 * (1.0 - (1.0 - q) ** 3)
    if loss is Loss.GEMAN_MCCLURE:
        d = k * k + r * r
        return k**4 / d**2, 0.5 * k * k * r * r / d
    if loss is Loss.TRUNCATED:
        return (r <= k).astype(float), 0.5 * np.minimum(r, k) ** 2
    raise ValueError(f"unknown loss {loss!r}")


#: observations whose local redundancy (of 2) is below this carry too little of the
#: noise to scale it (:func:`robust_sigma_px`): e.g. a target seen in one image only
MIN_REDUNDANCY = 0.5


def robust_sigma_px(
    residual_norms_px: np.ndarray,
    floor_px: float = 0.0,
    redundancy: np.ndarray | None = None,
) -> float:
    """Robust image-noise sigma (px) from 2-D residual norms (N,): ``median / sqrt(2 ln 2)``.

    The median of the norm of a 2-D isotropic normal with per-axis sigma ``s`` is
    ``s sqrt(2 ln 2)``; non-finite norms are ignored. Never below ``floor_px``.

    An adjusted residual is smaller than the noise by the share of it the unknowns
    absorbed: with ``redundancy`` (N,) (each observation's redundancy number, 0 to 2,
    the trace of its block of ``I - H``; :func:`gtsam_sphere.estimation.graph.
    observation_redundancy`) the norms are standardised by ``sqrt(2 / redundancy)``
    and the observations below :data:`MIN_REDUNDANCY` are left out. Without it, a
    network whose targets are mostly seen once (each absorbing its own residual)
    gives a median near zero, and an iterated scale estimate collapses to the floor.
    When fewer than 10 observations are left, the plain estimate is returned.
    """
    r = np.asarray(residual_norms_px, dtype=float).ravel()
    ok = np.isfinite(r)
    if redundancy is not None:
        red = np.asarray(redundancy, float).ravel()
        use = ok & np.isfinite(red) & (red >= MIN_REDUNDANCY)
        if use.sum() >= 10:
            r = r[use] * np.sqrt(2.0 / red[use])
            return max(float(np.median(r)) / MEDIAN_NORM_2D, float(floor_px))
    r = r[ok]
    if len(r) == 0:
        return float(floor_px)
    return max(float(np.median(r)) / MEDIAN_NORM_2D, float(floor_px))


def whitening_scale(r: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Factor ``sqrt(2 rho) / r`` (1 where ``r == 0``) putting a robust cost into a residual.

    Parameters
    ----------
    r : ndarray, shape (N,)
        Whitened residual norms.
    rho : ndarray, shape (N,)
        Their robust costs (:func:`robust_weight`).

    Returns
    -------
    ndarray, shape (N,)
        ``s`` with ``|s r|^2 / 2 == rho``: scaling a whitened residual by ``s`` makes
        its least-squares cost the robust one.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(r > 0, np.sqrt(2.0 * rho) / r, 1.0)


def mad_sigma(values: np.ndarray) -> float:
    """Robust sigma of 1-D values, ``1.4826 * median(|x - median(x)|)``.

    Parameters
    ----------
    values : ndarray, shape (N,)
        Finite values (a NaN gives NaN).

    Returns
    -------
    float
    """
    v = np.asarray(values, float)
    return MAD_TO_SIGMA * float(np.median(np.abs(v - np.median(v))))
