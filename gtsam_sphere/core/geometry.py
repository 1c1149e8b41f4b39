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
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (a**2).sum() / len(src)
    scale = float(np.trace(np.diag(S) @ D) / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)


def incidence_deg(points_cam: np.ndarray) -> np.ndarray:
    """Angle between camera-frame points (N, 3) and the optical axis +z, degrees in [0, 180]."""
    p = np.asarray(points_cam, float)
    return np.degrees(np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]))
