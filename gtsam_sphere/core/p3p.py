"""Minimal absolute pose (P3P) for central cameras of any field of view, and RANSAC.

Bearings are unit vectors in the camera frame (x right, y down, z forward). A bearing may
point anywhere on the sphere, including behind the camera (z < 0), so the solver never
assumes a perspective image plane: a world point ``X`` is explained by a bearing ``f`` when
``R @ X + t = s * f`` with a positive *distance* ``s`` along the ray.

Solver (own derivation, Grunert-style)
--------------------------------------
With distances ``s1, s2, s3`` along the three bearings and the inter-point distances
``a = |X2 - X3|``, ``b = |X1 - X3|``, ``c = |X1 - X2|``, the law of cosines gives::

    a^2 = s2^2 + s3^2 - 2 s2 s3 cos_a        cos_a = f2 . f3
    b^2 = s1^2 + s3^2 - 2 s1 s3 cos_b        cos_b = f1 . f3
    c^2 = s1^2 + s2^2 - 2 s1 s2 cos_c        cos_c = f1 . f2

Substituting ``s2 = u s1, s3 = v s1`` and eliminating ``s1`` leaves two conics in ``(u, v)``,
both quadratic in ``u`` with the same leading coefficient ``b^2``::

    A(u, v) = b^2 u^2 - 2 b^2 cos_a v u + (b^2 - a^2) v^2 + 2 a^2 cos_b v - a^2 = 0
    B(u, v) = b^2 u^2 - 2 b^2 cos_c u   - c^2 v^2 + 2 c^2 cos_b v + b^2 - c^2 = 0

Their resultant in ``u`` is a quartic in ``v``, solved in closed form (Ferrari's
resolvent cubic, :func:`_quartic_roots`); ``A - B`` is linear in ``u`` and gives ``u``
from each real root. The distances are polished by Newton's method on the three original
equations, and ``R, t`` follow from aligning the camera-frame triangle ``s_i f_i`` with
the world triangle (their orthonormal edge/normal frames, exact for congruent
triangles). Everything is vectorised over batches of minimal samples so RANSAC can
evaluate hundreds of hypotheses per numpy call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .least_squares import Damping, levenberg_marquardt_batch, ridge_scaling
from .lie import nearest_rotation, skew, so3_exp_batch
from .robust import Loss, robust_weight

__all__ = ["PoseResult", "angular_errors_rad", "p3p", "ransac_pose", "ransac_poses"]

_DEGENERATE_SIN = 1e-9  # |f_i x f_j| below this: duplicate bearings
_DEGENERATE_AREA = 1e-9  # triangle area / longest side^2 below this: collinear points
_RESIDUAL_TOL = 1e-6  # relative residual of the cosine equations for an accepted root


# ---------------------------------------------------------------------------------------
# batched P3P
# ---------------------------------------------------------------------------------------
def _pmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Multiply batches of polynomials (ascending coefficients along the last axis)."""
    n = p.shape[-1] + q.shape[-1] - 1
    out = np.zeros(np.broadcast_shapes(p.shape[:-1], q.shape[:-1]) + (n,))
    for i in range(p.shape[-1]):
        out[..., i : i + q.shape[-1]] += p[..., i : i + 1] * q
    return out


def _quartic_roots_eig(coef: np.ndarray) -> np.ndarray:
    """Roots of quartics, batched, as the eigenvalues of their companion matrices.

    Parameters
    ----------
    coef : (K, 5) ascending coefficients.

    Returns
    -------
    (K, 4) complex roots; NaN where the polynomial is degenerate (all zero).
    """
    k = coef.shape[0]
    roots = np.full((k, 4), np.nan + 0j)
    scale = np.max(np.abs(coef), axis=1)
    lead = coef[:, 4]
    good = np.abs(lead) > 1e-10 * scale
    if np.any(good):
        c = coef[good] / lead[good, None]
        comp = np.zeros((c.shape[0], 4, 4))
        comp[:, 1:, :3] = np.eye(3)
        comp[:, :, 3] = -c[:, :4]
        roots[good] = np.linalg.eigvals(comp)
    for i in np.flatnonzero(~good & (scale > 0)):
        r = np.roots(coef[i, ::-1])  # np.roots strips the vanishing leading terms
        roots[i, : r.size] = r
    return roots


#: the Ferrari split ``s = sqrt(2 m)`` below this (relative) is left to the eigenvalues:
#: at ``s = 0`` (a biquadratic) the split's ``q / (2 s)`` is undefined
_FERRARI_MIN_SPLIT = 1e-7


def _quartic_roots(coef: np.ndarray) -> np.ndarray:
    """Roots of quartics, batched, in closed form (Ferrari), real arithmetic only.

    The monic quartic is depressed (``x = y - a/4``: ``y^4 + p y^2 + q y + r``) and
    split into two real quadratics ``y^2 -+ s y + (p/2 + m +- q / (2 s))`` with
    ``s = sqrt(2 m)``, ``m`` the largest real root of the resolvent cubic
    ``m^3 + p m^2 + (p^2/4 - r) m - q^2/8`` (non-negative: the cubic is ``-q^2/8 <= 0``
    at 0; trigonometric or Cardano form, then two Newton steps). Real roots get one
    Newton step on the quartic. About 9x faster than the companion matrices'
    eigenvalues on RANSAC batches (thousands of quartics per call); the rows where the
    split is ill-defined (``s`` near 0, non-finite values) and the degenerate ones use
    :func:`_quartic_roots_eig`.

    Parameters
    ----------
    coef : (K, 5) ascending coefficients.

    Returns
    -------
    (K, 4) complex roots (conjugate pairs where not real); NaN where the polynomial is
    degenerate (all zero).
    """
    coef = np.asarray(coef, dtype=float)
    k = coef.shape[0]
    roots = np.full((k, 4), np.nan + 0j)
    scale = np.max(np.abs(coef), axis=1)
    lead = coef[:, 4]
    good = np.abs(lead) > 1e-10 * scale
    c = coef[good] / lead[good, None]
    a, b, c1_, d = c[:, 3], c[:, 2], c[:, 1], c[:, 0]
    a2 = a * a
    p = b - 0.375 * a2
    q = c1_ - 0.5 * a * b + 0.125 * a2 * a
    r = d - 0.25 * a * c1_ + 0.0625 * a2 * b - 3.0 / 256.0 * a2 * a2
    # the resolvent's largest real root, through its depressed form z^3 + P z + Q
    r1 = 0.25 * p * p - r
    r0 = -0.125 * q * q
    big_p = r1 - p * p / 3.0
    big_q = 2.0 / 27.0 * p**3 - p * r1 / 3.0 + r0
    disc = (0.5 * big_q) ** 2 + (big_p / 3.0) ** 3
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        one_real = disc >= 0
        sq = np.sqrt(np.where(one_real, disc, 0.0))
        cardano = np.cbrt(-0.5 * big_q + sq) + np.cbrt(-0.5 * big_q - sq)
        rad = np.sqrt(np.maximum(-big_p / 3.0, 0.0))
        cos3 = np.where(one_real | (rad == 0), 0.0, -0.5 * big_q / rad**3)
        trig = 2.0 * rad * np.cos(np.arccos(np.clip(cos3, -1.0, 1.0)) / 3.0)
        m = np.where(one_real, cardano, trig) - p / 3.0
        for _ in range(2):
            g = ((m + p) * m + r1) * m + r0
            step = g / ((3.0 * m + 2.0 * p) * m + r1)
            m = np.where(np.isfinite(step), m - step, m)
        m = np.maximum(m, 0.0)
        s = np.sqrt(2.0 * m)
        split_ok = np.isfinite(s) & (s > _FERRARI_MIN_SPLIT * (1.0 + np.sqrt(np.abs(p))))
        t = q / (2.0 * np.where(split_ok, s, 1.0))
        re = np.empty((c.shape[0], 4))
        im = np.zeros((c.shape[0], 4))
        for j, (sign, e) in enumerate(((-1.0, 0.5 * p + m - t), (1.0, 0.5 * p + m + t))):
            dq = s * s - 4.0 * e  # y = (sign s +- sqrt(dq)) / 2
            root = np.sqrt(np.abs(dq))
            real = dq >= 0
            re[:, 2 * j] = 0.5 * (sign * s + np.where(real, root, 0.0))
            re[:, 2 * j + 1] = 0.5 * (sign * s - np.where(real, root, 0.0))
            im[:, 2 * j] = np.where(real, 0.0, 0.5 * root)
            im[:, 2 * j + 1] = -im[:, 2 * j]
        x = re - 0.25 * a[:, None]
        cc = (a[:, None], b[:, None], c1_[:, None], d[:, None])
        f = (((x + cc[0]) * x + cc[1]) * x + cc[2]) * x + cc[3]
        step = f / (((4.0 * x + 3.0 * cc[0]) * x + 2.0 * cc[1]) * x + cc[2])
        x = np.where((im == 0) & np.isfinite(step), x - step, x)
    closed = x + 1j * im
    ok = split_ok & np.all(np.isfinite(closed), axis=1)
    rows = np.flatnonzero(good)
    roots[rows[ok]] = closed[ok]
    rest = np.ones(k, bool)
    rest[rows[ok]] = False
    rest &= scale > 0
    if np.any(rest):
        roots[rest] = _quartic_roots_eig(coef[rest])
    return roots


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product along the last axis (faster than ``np.cross`` for small batches)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _inv3(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched 3x3 inverse by cofactors; returns (inverse, determinant)."""
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    c0, c1, c2 = _cross(r1, r2), _cross(r2, r0), _cross(r0, r1)
    det = np.einsum("...i,...i->...", r0, c0)
    adj = np.stack([c0, c1, c2], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = adj / det[..., None, None]
    return inv, det


def _p3p_batch(
    bearings: np.ndarray, points: np.ndarray, n_polish: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All P3P solutions for a batch of minimal samples.

    Parameters
    ----------
    bearings : (K, 3, 3) unit bearing vectors (rows), camera frame.
    points : (K, 3, 3) world points (rows), metres.
    n_polish : Newton iterations polishing the distances along the rays.

    Returns
    -------
    R : (K, 4, 3, 3) cam_from_world rotations (the identity where not valid).
    t : (K, 4, 3) cam_from_world translations, metres (0 where not valid).
    valid : (K, 4) bool, which of the (up to 4) solution slots are real solutions.
    """
    bearings = np.asarray(bearings, dtype=float)
    points = np.asarray(points, dtype=float)
    k = bearings.shape[0]
    f1, f2, f3 = bearings[:, 0], bearings[:, 1], bearings[:, 2]
    x1, x2, x3 = points[:, 0], points[:, 1], points[:, 2]

    # degeneracy: duplicate / antipodal bearings, collinear world points
    sin_min = np.min(
        np.stack(
            [
                np.linalg.norm(_cross(f1, f2), axis=1),
                np.linalg.norm(_cross(f1, f3), axis=1),
                np.linalg.norm(_cross(f2, f3), axis=1),
            ]
        ),
        axis=0,
    )
    a2 = np.sum((x2 - x3) ** 2, axis=1)
    b2 = np.sum((x1 - x3) ** 2, axis=1)
    c2 = np.sum((x1 - x2) ** 2, axis=1)
    longest2 = np.maximum(np.maximum(a2, b2), c2)
    area2 = np.linalg.norm(_cross(x2 - x1, x3 - x1), axis=1)
    ok_sample = (
        np.all(np.isfinite(bearings), axis=(1, 2))
        & np.all(np.isfinite(points), axis=(1, 2))
        & (sin_min > _DEGENERATE_SIN)
        & (area2 > _DEGENERATE_AREA * np.where(longest2 > 0, longest2, 1.0))
        & (longest2 > 0)
    )
    # normalise the scale for conditioning (restored through the rigid fit)
    scale2 = np.where(ok_sample, (a2 + b2 + c2) / 3.0, 1.0)
    a2n, b2n, c2n = a2 / scale2, b2 / scale2, c2 / scale2
    ca = np.einsum("ki,ki->k", f2, f3)
    cb = np.einsum("ki,ki->k", f1, f3)
    cc = np.einsum("ki,ki->k", f1, f2)

    zeros = np.zeros(k)
    # polynomials in v (ascending), after dividing the resultant by b^4
    a0 = np.stack([-a2n, 2 * a2n * cb, b2n - a2n], axis=1)  # A0(v)
    b0 = np.stack([b2n - c2n, 2 * c2n * cb, -c2n], axis=1)  # B0(v)
    d = b0 - a0  # (B0 - A0)(v)
    e = np.stack([-2 * b2n * cc, 2 * b2n * ca], axis=1)  # (B1 - A1)(v) / b^2
    g = 2 * (cc[:, None] * np.concatenate([a0, zeros[:, None]], axis=1))
    g -= 2 * ca[:, None] * np.concatenate([zeros[:, None], b0], axis=1)
    quartic = _pmul(d, d) - _pmul(e, g)
    quartic[~ok_sample] = 0.0

    roots = _quartic_roots(quartic)  # (K, 4)
    re = roots.real
    with np.errstate(invalid="ignore"):
        nearly_real = np.abs(roots.imag) <= 1e-4 * (1.0 + np.abs(re))
        v = np.where(nearly_real, re, np.nan)
        # u from A - B = 0 (linear in u): (A1 - B1) u + (A0 - B0) = 0
        dv = d[:, None, 0] + d[:, None, 1] * v + d[:, None, 2] * v * v
        ev = e[:, None, 0] + e[:, None, 1] * v
        u = -dv / ev
        den = 1.0 + u * u - 2.0 * u * cc[:, None]
        s1 = np.sqrt(c2n[:, None] / den)
    s = np.stack([s1, u * s1, v * s1], axis=-1)  # (K, 4, 3) normalised distances

    # Newton polish on the three cosine equations
    cab = np.stack([ca, cb, cc], axis=1)[:, None, :]  # (K,1,3)
    rhs = np.stack([a2n, b2n, c2n], axis=1)[:, None, :]
    for _ in range(n_polish):
        resid, jac = _cosine_equations(s, cab, rhs)
        inv, det = _inv3(jac)
        with np.errstate(invalid="ignore"):
            step = np.einsum("...ij,...j->...i", inv, resid)
        usable = np.isfinite(step).all(axis=-1) & (np.abs(det) > 1e-14)
        s = np.where(usable[..., None], s - step, s)
    resid, _ = _cosine_equations(s, cab, rhs)
    with np.errstate(invalid="ignore"):
        valid = (
            ok_sample[:, None]
            & np.all(np.isfinite(s), axis=-1)
            & np.all(s > 0, axis=-1)
            & (np.max(np.abs(resid), axis=-1) < _RESIDUAL_TOL)
        )
    # drop duplicated roots (double roots reported twice)
    for j in range(1, 4):
        for i in range(j):
            same = np.max(np.abs(s[:, j] - s[:, i]), axis=-1) < 1e-7
            valid[:, j] &= ~(same & valid[:, i])

    # the rigid fit of the real solutions only (the others: identity placeholders)
    kk, jj = np.nonzero(valid)
    s_m = s[kk, jj] * np.sqrt(scale2)[kk, None]
    rot = np.broadcast_to(np.eye(3), (k, 4, 3, 3)).copy()
    t = np.zeros((k, 4, 3))
    rot[kk, jj], t[kk, jj] = _triangle_pose(points[kk], s_m[..., None] * bearings[kk])
    return rot, t, valid


def _triangle_frame(p: np.ndarray) -> np.ndarray:
    """Orthonormal frames (M, 3, 3) (columns: edge 1->2, in-plane normal, plane normal)
    of triangles ``p`` (M, 3, 3) (rows are the corners)."""
    e1 = p[:, 1] - p[:, 0]
    n = _cross(e1, p[:, 2] - p[:, 0])
    e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    e3 = n / np.linalg.norm(n, axis=1, keepdims=True)
    return np.stack([e1, _cross(e3, e1), e3], axis=-1)


def _triangle_pose(world: np.ndarray, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` with ``cam ~= R world + t`` for congruent triangles (M, 3, 3), rows corners.

    The rotation maps the world triangle's frame onto the camera triangle's (exact for
    the P3P solutions, whose distances reproduce the sides; no SVD); the translation
    maps the centroids.
    """
    R = _triangle_frame(cam) @ _triangle_frame(world).transpose(0, 2, 1)
    return R, cam.mean(axis=1) - np.einsum("mij,mj->mi", R, world.mean(axis=1))


def _cosine_equations(
    s: np.ndarray, cab: np.ndarray, rhs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (..., 3) and Jacobian (..., 3, 3) of the law-of-cosines system."""
    s1, s2, s3 = s[..., 0], s[..., 1], s[..., 2]
    ca, cb, cc = cab[..., 0], cab[..., 1], cab[..., 2]
    resid = np.stack(
        [
            s2 * s2 + s3 * s3 - 2 * s2 * s3 * ca,
            s1 * s1 + s3 * s3 - 2 * s1 * s3 * cb,
            s1 * s1 + s2 * s2 - 2 * s1 * s2 * cc,
        ],
        axis=-1,
    ) - np.broadcast_to(rhs, s.shape)
    z = np.zeros_like(s1)
    jac = np.stack(
        [
            np.stack([z, 2 * (s2 - s3 * ca), 2 * (s3 - s2 * ca)], axis=-1),
            np.stack([2 * (s1 - s3 * cb), z, 2 * (s3 - s1 * cb)], axis=-1),
            np.stack([2 * (s1 - s2 * cc), 2 * (s2 - s1 * cc), z], axis=-1),
        ],
        axis=-2,
    )
    return resid, jac


def p3p(bearings_cam: np.ndarray, points_world: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Solve the perspective-three-point problem for bearings in any direction.

    Parameters
    ----------
    bearings_cam : (3, 3) array
        Unit bearing vectors (rows) in the camera frame (x right, y down, z forward).
        They may point sideways or behind the camera (z <= 0).
    points_world : (3, 3) array
        The matching world points (rows), metres.

    Returns
    -------
    list of (R, t)
        All real solutions (at most 4) with ``R @ X + t = s * f`` and ``s > 0`` for the
        three correspondences; ``R`` (3, 3) rotation, ``t`` (3,) metres, cam_from_world.
        Degenerate input (collinear world points, duplicate or antipodal bearings, non-finite
        values) returns an empty list.
    """
    f = np.asarray(bearings_cam, dtype=float).reshape(1, 3, 3)
    x = np.asarray(points_world, dtype=float).reshape(1, 3, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        norms = np.linalg.norm(f, axis=-1, keepdims=True)
        f = f / norms
    rot, t, valid = _p3p_batch(f, x, n_polish=4)
    return [(rot[0, j].copy(), t[0, j].copy()) for j in range(4) if valid[0, j]]


# ---------------------------------------------------------------------------------------
# RANSAC
# ---------------------------------------------------------------------------------------
@dataclass
class PoseResult:
    """Outcome of :func:`ransac_pose`.

    Attributes
    ----------
    R : (3, 3) cam_from_world rotation (NaN when ``success`` is False and no pose exists).
    t : (3,) cam_from_world translation, metres.
    inlier_mask : (N,) bool, observations within the angular threshold.
    n_inliers : int, ``inlier_mask.sum()``.
    median_error_rad : float, median angular error of the inliers, radians (NaN if none).
    success : bool, a pose with at least ``min_inliers`` inliers was found.
    reason : str, human-readable explanation when ``success`` is False.
    """

    R: np.ndarray
    t: np.ndarray
    inlier_mask: np.ndarray
    n_inliers: int
    median_error_rad: float
    success: bool
    reason: str = ""


def angular_errors_rad(
    bearings_cam: np.ndarray, points_world: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Angles between measured bearings and the rays to the transformed world points.

    Parameters
    ----------
    bearings_cam : (N, 3) unit bearings, camera frame.
    points_world : (N, 3) world points, metres.
    R : (3, 3) or (H, 3, 3) cam_from_world rotation(s).
    t : (3,) or (H, 3) cam_from_world translation(s), metres.

    Returns
    -------
    (N,) or (H, N) angular errors in radians, in [0, pi]. NaN rows of the input give NaN.
    """
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    p = np.einsum("...ij,nj->...ni", R, points_world) + t[..., None, :]
    return _angles_rad(bearings_cam, p)


def _angles_rad(bearings: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Angles (radians, ``[0, pi]``) between bearings (N, 3) and camera-frame points
    (..., N, 3), row by row."""
    cross = np.linalg.norm(_cross(bearings, p), axis=-1)
    dot = np.einsum("...ni,ni->...n", p, bearings)
    return np.arctan2(cross, dot)


def _sample_triplets(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(k, 3) triplets of distinct indices in [0, n), uniformly."""
    i0 = rng.integers(0, n, size=k)
    i1 = rng.integers(0, n - 1, size=k)
    i1 += i1 >= i0
    lo, hi = np.minimum(i0, i1), np.maximum(i0, i1)
    i2 = rng.integers(0, n - 2, size=k)
    i2 += i2 >= lo
    i2 += i2 >= hi
    return np.stack([i0, i1, i2], axis=1)


#: damping of the pose refinement: 6 tries per iteration, equal cost accepted
_REFINE_DAMPING = Damping(floor=1e-9, max_tries=6, accept_equal=True, scaling=ridge_scaling)


class _Segments:
    """Rows of many problems stored end to end: problem ``p`` owns rows
    ``start[p] : start[p] + size[p]`` of the concatenated arrays."""

    def __init__(self, sizes: np.ndarray):
        self.size = np.asarray(sizes, int)
        self.start = np.concatenate([[0], np.cumsum(self.size)[:-1]]).astype(int)

    def rows(self, pid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows of problems ``pid`` (in that order), the position in ``pid`` owning each
        row, and where each problem's rows begin in that list (for ``np.add.reduceat``)."""
        size = self.size[pid]
        owner = np.repeat(np.arange(pid.size), size)
        first = np.concatenate([[0], np.cumsum(size)[:-1]]).astype(int)
        rows = np.arange(int(size.sum())) - first[owner] + self.start[pid][owner]
        return rows, owner, first


def _refine_poses(
    bearings: np.ndarray,
    points: np.ndarray,
    sizes: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    huber_rad: np.ndarray,
    n_iter: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the chord error ``p/|p| - f`` (~ angle) over 6-DoF poses,
    for many problems at once (:func:`~gtsam_sphere.core.least_squares.levenberg_marquardt_batch`).

    The rotation is updated on the left, ``R <- exp([w]) R``, the translation additively.
    Residuals get Huber weights with knee ``huber_rad``. Each problem's sums run over its
    own rows only (``np.add.reduceat``), so its result does not depend on the others.
    Every problem runs its ``n_iter`` iterations (IRLS converges linearly, about 20x
    per iteration here; stopping at a relative cost decrease of 1e-6, after 4-5 of the
    8, saved 5-10 % of the initialisation but moved its refits enough to flip a chaotic
    zoo case, seed 13 case 05, from trusted to not trusted: session 15's note).

    Parameters
    ----------
    bearings : (M, 3) unit bearings, camera frame, the problems' rows end to end.
    points : (M, 3) world points, metres.
    sizes : (B,) rows per problem (each at least 1), summing to M.
    R : (B, 3, 3) cam_from_world rotations to start from.
    t : (B, 3) cam_from_world translations, metres.
    huber_rad : (B,) Huber knee per problem, radians.
    n_iter : int
        Linearisations at most.

    Returns
    -------
    R : (B, 3, 3) refined rotations (re-orthonormalised); t : (B, 3).
    """
    seg = _Segments(sizes)
    huber_rad = np.asarray(huber_rad, float)

    def residuals(pose):
        R_, t_, pid = pose
        rows, owner, first = seg.rows(pid)
        p = np.einsum("nij,nj->ni", R_[owner], points[rows]) + t_[owner]
        nrm = np.linalg.norm(p, axis=1)
        ph = p / nrm[:, None]
        r = ph - bearings[rows]
        e = np.linalg.norm(r, axis=1)
        w, rho = robust_weight(e, Loss.HUBER, huber_rad[pid][owner])
        return p, nrm, ph, r, w, rho, owner, first

    def cost(pose):
        *_, rho, _owner, first = residuals(pose)
        return np.add.reduceat(rho, first)

    def linearize(pose):
        t_ = pose[1]
        p, nrm, ph, r, w, _rho, owner, first = residuals(pose)
        # d(ph)/dp = (I - ph ph^T)/|p| ; dp/dw = -[R X]x ; dp/dt = I, and
        # ph^T [R X]x = (ph x R X)^T, so d(ph)/dw = (-[R X]x + ph (ph x R X)^T) / |p|
        proj = (np.eye(3)[None] - ph[:, :, None] * ph[:, None, :]) / nrm[:, None, None]
        rx = p - t_[owner]
        d_rot = (ph[:, :, None] * _cross(ph, rx)[:, None, :] - skew(rx)) / nrm[:, None, None]
        jac = np.concatenate([d_rot, proj], axis=2)  # (n, 3, 6)
        jw = jac * w[:, None, None]
        H = np.add.reduceat(np.einsum("nki,nkj->nij", jw, jac), first)
        g = np.add.reduceat(np.einsum("nki,nk->ni", jw, r), first)
        return H, g

    def retract(pose, delta):
        R_, t_, pid = pose
        return so3_exp_batch(delta[:, :3]) @ R_, t_ + delta[:, 3:], pid

    fit = levenberg_marquardt_batch(
        (np.asarray(R, float), np.asarray(t, float), np.arange(seg.size.size)),
        cost,
        linearize,
        retract=retract,
        converged=lambda _c0, _c1, delta: np.linalg.norm(delta, axis=1) < 1e-12,
        damping=_REFINE_DAMPING,
        max_iterations=n_iter,
    )
    R, t, _ = fit.x
    return nearest_rotation(R), t  # re-orthonormalised


def ransac_pose(
    bearings_cam: np.ndarray,
    points_world: np.ndarray,
    threshold_rad: float,
    rng: np.random.Generator,
    max_iterations: int = 1000,
    confidence: float = 0.999,
    *,
    min_inliers: int = 4,
    refine: bool = True,
    batch_size: int = 64,
) -> PoseResult:
    """Robust absolute pose from bearings in any direction (P3P + MSAC + LM refinement).

    Parameters
    ----------
    bearings_cam : (N, 3) array
        Unit bearing vectors in the camera frame; rows with non-finite values are never
        inliers.
    points_world : (N, 3) array
        Matching world points, metres.
    threshold_rad : float
        Inlier threshold on the angle between a bearing and the ray ``R p + t``, radians.
    rng : numpy.random.Generator
        Source of the random minimal samples.
    max_iterations : int
        Upper bound on the number of minimal samples drawn.
    confidence : float
        Stop once the probability of having drawn an all-inlier sample exceeds this,
        estimated from the current best inlier ratio (adaptive iteration count).
    min_inliers : int, keyword-only
        ``success`` requires at least this many inliers (at least 4: three define the pose).
    refine : bool, keyword-only
        Refine the best hypothesis on its inliers (LM over 6 pose parameters, angular
        error, Huber) and recompute the inliers.
    batch_size : int, keyword-only
        Minimal samples solved per vectorised call.

    Returns
    -------
    PoseResult
        cam_from_world ``R, t``; ``inlier_mask`` (N,); ``median_error_rad`` of the inliers.
    """
    return ransac_poses(
        [bearings_cam],
        [points_world],
        [threshold_rad],
        [rng],
        max_iterations,
        confidence,
        min_inliers=min_inliers,
        refine=refine,
        batch_size=batch_size,
    )[0]


class _RansacState:
    """One problem of :func:`ransac_poses`: its usable rows, draws and best hypothesis."""

    def __init__(self, bearings, points, threshold_rad, rng, max_iterations):
        f = np.asarray(bearings, dtype=float).reshape(-1, 3)
        x = np.asarray(points, dtype=float).reshape(-1, 3)
        if f.shape != x.shape:
            raise ValueError(
                f"bearings_cam and points_world must both have shape (N, 3), got {f.shape} "
                f"and {x.shape}"
            )
        self.n = f.shape[0]
        finite = np.all(np.isfinite(f), axis=1) & np.all(np.isfinite(x), axis=1)
        self.idx_ok = np.flatnonzero(finite)
        self.fo, self.xo = f[self.idx_ok], x[self.idx_ok]
        self.m = self.idx_ok.size
        self.threshold_rad = float(threshold_rad)
        self.rng = rng
        self.max_iterations = int(max_iterations)
        self.best_cost = np.inf
        self.best = None
        self.needed = self.max_iterations
        self.drawn = 0

    @property
    def active(self) -> bool:
        return self.drawn < min(self.needed, self.max_iterations)


#: (hypotheses x observations) of the problems scored in one vectorised call
_SCORE_BUDGET = 2_000_000


def ransac_poses(
    bearings_cam: list,
    points_world: list,
    thresholds_rad,
    rngs: list,
    max_iterations: int = 1000,
    confidence: float = 0.999,
    *,
    min_inliers: int = 4,
    refine: bool = True,
    batch_size: int = 64,
) -> list[PoseResult]:
    """:func:`ransac_pose` of many independent problems at once.

    Each problem draws its minimal samples from its own generator, in the same order and
    with the same adaptive stopping rule as alone, so its result is that of
    :func:`ransac_pose` with the same arguments; the P3P solutions and the MSAC scores of
    every problem still drawing are computed in shared vectorised calls (the lens
    initialisation poses thousands of small images under hundreds of hypotheses).

    Parameters
    ----------
    bearings_cam : list of P arrays, each (N_p, 3)
        Unit bearings per problem, camera frame.
    points_world : list of P arrays, each (N_p, 3)
        Matching world points, metres.
    thresholds_rad : (P,) array-like
        Angular inlier threshold per problem, radians.
    rngs : list of P numpy.random.Generator
        One source of minimal samples per problem.
    max_iterations, confidence, min_inliers, refine, batch_size
        As in :func:`ransac_pose`, shared by every problem.

    Returns
    -------
    list of P PoseResult
    """
    thresholds = np.broadcast_to(np.asarray(thresholds_rad, dtype=float), (len(bearings_cam),))
    if not (len(points_world) == len(rngs) == len(bearings_cam)):
        raise ValueError(
            f"bearings_cam, points_world and rngs must have one entry per problem, got "
            f"{len(bearings_cam)}, {len(points_world)} and {len(rngs)}"
        )
    min_inliers = max(int(min_inliers), 4)
    states = [
        _RansacState(f, x, thr, rng, max_iterations)
        for f, x, thr, rng in zip(bearings_cam, points_world, thresholds, rngs)
    ]
    results: list[PoseResult | None] = [None] * len(states)
    nan_pose = (np.full((3, 3), np.nan), np.full(3, np.nan))
    for p, s in enumerate(states):
        if s.m < max(4, min_inliers):
            s.needed = 0  # never drawn
            results[p] = PoseResult(
                *nan_pose,
                np.zeros(s.n, bool),
                0,
                float("nan"),
                False,
                f"only {s.m} usable observations (need at least {max(4, min_inliers)})",
            )
    while True:
        active = [s for s in states if s.active]
        if not active:
            break
        group: list[_RansacState] = []
        load = 0
        for s in active:  # groups of problems scored together, within the memory budget
            group.append(s)
            load += 4 * min(batch_size, s.max_iterations - s.drawn) * s.m
            if load >= _SCORE_BUDGET:
                _ransac_round(group, batch_size, confidence)
                group, load = [], 0
        if group:
            _ransac_round(group, batch_size, confidence)

    pending = [p for p in range(len(states)) if results[p] is None]
    finished = _ransac_finish([states[p] for p in pending], min_inliers, refine)
    for p, r in zip(pending, finished):
        results[p] = r
    return results


def _ransac_round(group: list[_RansacState], batch_size: int, confidence: float) -> None:
    """One batch of minimal samples for every problem of ``group``: P3P, MSAC scores and
    each problem's best hypothesis, needed sample count updated (as :func:`ransac_pose`)."""
    tris, sizes = [], []
    for s in group:
        k = min(batch_size, s.max_iterations - s.drawn)
        tris.append(_sample_triplets(s.rng, s.m, k))
        s.drawn += k
        sizes.append(k)
    f = np.concatenate([s.fo[tri] for s, tri in zip(group, tris)])
    x = np.concatenate([s.xo[tri] for s, tri in zip(group, tris)])
    rot, t, valid = _p3p_batch(f, x)
    n_hyp = [int(valid[o : o + k].sum()) for o, k in zip(np.cumsum([0, *sizes]), sizes)]
    h_max, n_max = max(n_hyp), max(s.m for s in group)
    if h_max == 0:
        return
    # padded (P, H, ...) hypotheses and (P, N, 3) observations; padding scores nothing
    n_p = len(group)
    R_pad = np.broadcast_to(np.eye(3), (n_p, h_max, 3, 3)).copy()
    t_pad = np.zeros((n_p, h_max, 3))
    f_pad = np.zeros((n_p, n_max, 3))
    x_pad = np.zeros((n_p, n_max, 3))
    obs = np.zeros((n_p, n_max), bool)
    hyp = np.zeros((n_p, h_max), bool)
    o = 0
    for p, (s, k) in enumerate(zip(group, sizes)):
        v = valid[o : o + k]
        R_pad[p, : n_hyp[p]] = rot[o : o + k][v]
        t_pad[p, : n_hyp[p]] = t[o : o + k][v]
        f_pad[p, : s.m], x_pad[p, : s.m] = s.fo, s.xo
        obs[p, : s.m] = True
        hyp[p, : n_hyp[p]] = True
        o += k
    cosang = _cosines(R_pad, t_pad, f_pad, x_pad, obs)
    thr = np.array([s.threshold_rad for s in group])
    cost = _msac_costs(cosang, thr, obs)  # (P, H)
    cost = np.where(hyp, cost, np.inf)
    for p, s in enumerate(group):
        if n_hyp[p] == 0:
            continue
        j = int(np.argmin(cost[p]))
        if cost[p, j] < s.best_cost:
            s.best_cost = float(cost[p, j])
            s.best = (R_pad[p, j].copy(), t_pad[p, j].copy())
            w = int(np.sum(cosang[p, j, : s.m] >= np.cos(s.threshold_rad))) / s.m
            if w >= 1.0:
                s.needed = 0
            elif w > 0:
                s.needed = int(np.ceil(np.log(1 - confidence) / np.log1p(-(w**3))))


#: margin (in cosine) below ``cos(threshold)`` within which :func:`_msac_costs` still
#: takes the arccos: far beyond rounding, so no angle at or below the threshold is missed
_COS_MARGIN = 1e-6


def _msac_costs(cosang: np.ndarray, thr_rad: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """MSAC costs ``sum_n min(angle^2, thr^2)`` over the real rows, (P, H).

    ``cosang`` (P, H, N) cosines of the angular errors (NaN: no ray, cost ``thr^2``),
    ``thr_rad`` (P,) thresholds, ``obs`` (P, N) the real (unpadded) rows. An angle
    beyond the threshold costs ``thr^2`` whatever it is, so the arccos is taken only
    where the cosine is within :data:`_COS_MARGIN` of ``cos(thr)`` or above it (the
    inliers of a hypothesis, a few percent of the pairs of a RANSAC batch); the costs
    are those of the arccos of every pair, to the bit.
    """
    thr2 = (thr_rad * thr_rad)[:, None, None]
    capped = np.empty(cosang.shape)
    capped[...] = np.where(obs[:, None, :], thr2, 0.0)
    near = (cosang >= (np.cos(thr_rad) - _COS_MARGIN)[:, None, None]) & obs[:, None, :]
    ang = np.arccos(np.clip(cosang[near], -1.0, 1.0))
    capped[near] = np.minimum(ang * ang, np.broadcast_to(thr2, capped.shape)[near])
    return capped.sum(axis=2)


def _cosines(R, t, f, x, obs):
    """Cosine of the angle between bearings and the rays to the posed points, (P, H, N).

    ``R`` (P, H, 3, 3), ``t`` (P, H, 3) cam_from_world hypotheses; ``f`` (P, N, 3)
    bearings, ``x`` (P, N, 3) world points, ``obs`` (P, N) the real (unpadded) rows.
    Written as two batched matrix products: with ``p = R x + t``,
    ``f . p = vec(f x^T) . vec(R) + f . t`` and ``|p|^2 = |x|^2 + 2 (R^T t) . x + |t|^2``
    (``|R x| = |x|``), the points taken about their centroid (so the expansion of
    ``|p|^2`` does not cancel for maps far from the origin). NaN where ``p = 0``.
    """
    n_obs = np.maximum(obs.sum(axis=1), 1)
    centroid = (x * obs[..., None]).sum(axis=1) / n_obs[:, None]  # (P, 3)
    xc = np.where(obs[..., None], x - centroid[:, None, :], 0.0)
    tc = t + np.einsum("phij,pj->phi", R, centroid)
    fx = (f[:, :, :, None] * xc[:, :, None, :]).reshape(f.shape[0], f.shape[1], 9)
    lhs = np.concatenate([R.reshape(*R.shape[:2], 9), tc], axis=2)  # (P, H, 12)
    rhs = np.concatenate([fx, f], axis=2).transpose(0, 2, 1)  # (P, 12, N)
    dot = lhs @ rhs
    rt_t = np.einsum("phji,phj->phi", R, tc)  # R^T t
    norm2 = (xc * xc).sum(axis=2)[:, None, :] + 2.0 * (rt_t @ xc.transpose(0, 2, 1))
    norm2 += (tc * tc).sum(axis=2)[:, :, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return dot / np.sqrt(np.maximum(norm2, 0.0))


def _ransac_finish(states: list[_RansacState], min_inliers: int, refine: bool) -> list:
    """The PoseResults of many problems: each best hypothesis, refined (LM) when asked.

    A refinement round refits every problem still improving on its inliers (one batched
    LM, :func:`_refine_poses`) and keeps the refit unless it scores worse; a problem stops
    when its inlier set no longer changes, after three rounds, or with fewer than four
    inliers.
    """
    out: list = [None] * len(states)
    todo = []
    for q, s in enumerate(states):
        if s.best is None:
            out[q] = PoseResult(
                np.full((3, 3), np.nan),
                np.full(3, np.nan),
                np.zeros(s.n, bool),
                0,
                float("nan"),
                False,
                f"no valid P3P solution from {s.drawn} minimal samples of {s.m} observations",
            )
        else:
            todo.append(q)
    if todo:
        sub = [states[q] for q in todo]
        seg = _Segments([s.m for s in sub])
        fo = np.concatenate([s.fo for s in sub])
        xo = np.concatenate([s.xo for s in sub])
        thr = np.array([s.threshold_rad for s in sub])
        R_b = np.stack([s.best[0] for s in sub])
        t_b = np.stack([s.best[1] for s in sub])

        def score(pid, R_, t_):
            """Angular errors (rows of ``pid``) and each problem's MSAC cost."""
            rows, owner, first = seg.rows(pid)
            p = np.einsum("nij,nj->ni", R_[owner], xo[rows]) + t_[owner]
            ang_ = np.nan_to_num(_angles_rad(fo[rows], p), nan=np.pi)
            thr_row = thr[pid][owner]
            return ang_, np.add.reduceat(np.minimum(ang_ * ang_, thr_row * thr_row), first)

        everyone = np.arange(len(sub))
        ang, cost = score(everyone, R_b, t_b)
        live = np.ones(len(sub), bool)
        rounds = 3 if refine else 0
        for _ in range(rounds):
            inl = ang < thr[np.repeat(everyone, seg.size)]
            n_in = np.add.reduceat(inl.astype(int), seg.start)
            live &= n_in >= 4
            pid = np.flatnonzero(live)
            if not pid.size:
                break
            rows, owner, _first = seg.rows(pid)
            keep = inl[rows]
            R_r, t_r = _refine_poses(
                fo[rows][keep],
                xo[rows][keep],
                n_in[pid],
                R_b[pid],
                t_b[pid],
                thr[pid] / 2,
            )
            ang_r, cost_r = score(pid, R_r, t_r)
            worse = cost_r > cost[pid]
            inl_r = ang_r < thr[pid][owner]
            changed = np.add.reduceat((inl_r != inl[rows]).astype(int), _first) > 0
            take = ~worse
            R_b[pid[take]], t_b[pid[take]] = R_r[take], t_r[take]
            cost[pid[take]] = cost_r[take]
            row_take = take[owner]
            ang[rows[row_take]] = ang_r[row_take]
            live[pid[worse | ~changed]] = False
        for j, q in enumerate(todo):
            s = sub[j]
            a_j = ang[seg.start[j] : seg.start[j] + seg.size[j]]
            ok = a_j < s.threshold_rad
            mask = np.zeros(s.n, bool)
            mask[s.idx_ok] = ok
            n_inl = int(mask.sum())
            med = float(np.median(a_j[ok])) if n_inl else float("nan")
            success = n_inl >= min_inliers
            reason = (
                "" if success else f"RANSAC found {n_inl} inliers of {s.n} (need {min_inliers})"
            )
            out[q] = PoseResult(R_b[j].copy(), t_b[j].copy(), mask, n_inl, med, success, reason)
    return out
