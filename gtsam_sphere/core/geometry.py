"""Rigid and similarity transforms between point sets and pose conventions.

Frames follow ``docs/conventions.md``: ``cam_from_world`` maps world points
into the camera frame, ``p_cam = R @ p_world + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """Return ``points`` as a float (N, 3) array or raise ``ValueError``.

    Parameters
    ----------
    points : array_like, shape (N, 3)
    name : str
        Name used in the error message.
    """
    arr = np.asarray(points, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


@dataclass(frozen=True)
class Similarity:
    """A 7-parameter similarity ``dst = scale * R @ src + t``.

    Attributes
    ----------
    scale : float
    R : ndarray, shape (3, 3)
    t : ndarray, shape (3,)
    """

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (N, 3) of the source frame into the destination frame."""
        return self.scale * np.asarray(points, float) @ self.R.T + self.t

    def apply_to_cam_from_world(
        self, R_cw: np.ndarray, t_cw: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Re-express poses ``cam_from_world`` (M,3,3), (M,3) in the destination frame.

        The camera frame keeps metric units of the source scaled by ``scale``:
        ``p_cam' = scale * p_cam``, so ``R' = R @ self.R.T`` and
        ``t' = scale * t - R' @ self.t``.
        """
        R_new = np.asarray(R_cw) @ self.R.T
        t_new = self.scale * np.asarray(t_cw) - np.einsum("...ij,j->...i", R_new, self.t)
        return R_new, t_new


def _umeyama(src: np.ndarray, dst: np.ndarray):
    """Shared core of :func:`fit_rigid` and :func:`fit_similarity`, batched over leading axes.

    Returns the rotation ``R`` (..., 3, 3) (det +1) maximising ``tr(R^T cov)`` with
    ``cov = sum_n (dst_n - mean dst)(src_n - mean src)^T``, the means (..., 3), the
    centred ``src`` (..., N, 3), the singular values (..., 3) of ``cov`` and the sign
    (..., ) given to the last one.
    """
    mu_s = src.mean(axis=-2)
    mu_d = dst.mean(axis=-2)
    a = src - mu_s[..., None, :]
    cov = np.einsum("...ni,...nj->...ij", dst - mu_d[..., None, :], a)
    u, sv, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt, mu_s, mu_d, a, sv, d


def fit_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform ``dst ~= R @ src + t`` (Kabsch), batched, unchecked.

    Parameters
    ----------
    src, dst : ndarray, shape (..., N, 3)
        Corresponding points (no checks: the minimal solvers call this on thousands of
        candidate sets at once, some of them placeholders).

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
        Rotation, det +1.
    t : ndarray, shape (..., 3)
    """
    R, mu_s, mu_d, _, _, _ = _umeyama(src, dst)
    return R, mu_d - np.einsum("...ij,...j->...i", R, mu_s)


def fit_similarity(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping ``src`` onto ``dst``.

    Parameters
    ----------
    src, dst : ndarray, shape (N, 3)
        Corresponding points, N >= 3 and not collinear.
    with_scale : bool
        Estimate the scale; otherwise a rigid transform (scale 1).

    Returns
    -------
    Similarity
        ``dst ~= scale * R @ src + t`` minimising the sum of squared 3D distances.
    """
    src = check_points(src, "src")
    dst = check_points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src and dst shapes differ: {src.shape} vs {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"need at least 3 points for a similarity, got {len(src)}")
    R, mu_s, mu_d, a, sv, d = _umeyama(src, dst)
    scale = float((sv[0] + sv[1] + d * sv[2]) / (a**2).sum()) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)


#: :func:`fit_similarity_trimmed` leaves out of the fit the source points farther than
#: this many times the median distance from the source's median point
SOURCE_SPREAD_LIMIT = 20.0
#: and, while it iterates, the points whose misfit exceeds this many times the median
#: misfit of the points kept
MISFIT_LIMIT = 5.0


def fit_similarity_trimmed(
    src: np.ndarray, dst: np.ndarray, max_rounds: int = 10
) -> tuple[Similarity, np.ndarray]:
    """:func:`fit_similarity` that a few wild points cannot pull.

    A datum transform (a free network S-transformed onto its approximate coordinates),
    not an evaluation: a point that flew off in the adjustment (a free target whose
    second ray was a blunder, 5 km away in a 7 m room) took the least-squares scale of
    all the others to 5e-4. Points farther than ``SOURCE_SPREAD_LIMIT`` times the
    median distance from the source's median point are left out of the first fit; then
    points whose misfit ``|S(src) - dst|`` exceeds ``MISFIT_LIMIT`` times the median
    misfit of the points kept are left out of the next, until the set stops changing.
    A set that would drop below half the points (or 3) is not taken.

    Parameters
    ----------
    src, dst : ndarray, shape (N, 3)
        Corresponding points, N >= 3 and not collinear.
    max_rounds : int
        Refits at most.

    Returns
    -------
    Similarity
        Fitted on the points kept.
    kept : ndarray of bool, shape (N,)
        The points the last fit used.
    """
    src = check_points(src, "src")
    dst = check_points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src and dst shapes differ: {src.shape} vs {dst.shape}")
    n = len(src)
    need = max(3, (n + 1) // 2)
    kept = np.ones(n, bool)
    spread = np.linalg.norm(src - np.median(src, axis=0), axis=1)
    core = spread <= SOURCE_SPREAD_LIMIT * np.median(spread)
    if core.sum() >= need:
        kept = core
    sim = fit_similarity(src[kept], dst[kept])
    for _ in range(max_rounds):
        misfit = np.linalg.norm(sim.apply(src) - dst, axis=1)
        limit = MISFIT_LIMIT * np.median(misfit[kept])
        nxt = misfit <= limit if limit > 0 else kept
        if nxt.sum() < need or np.array_equal(nxt, kept):
            break
        kept = nxt
        sim = fit_similarity(src[kept], dst[kept])
    return sim, kept


def incidence_deg(points_cam: np.ndarray) -> np.ndarray:
    """Angle (deg, in [0, 180]) between camera-frame points or rays (N, 3) and the axis +z.

    ``atan2(hypot(x, y), z)``; shape (N,).
    """
    p = np.asarray(points_cam, float).reshape(-1, 3)
    return np.degrees(np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]))
