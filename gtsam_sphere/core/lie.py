"""Rotations as a Lie group: cross-product matrices, the SO(3) exponential and logarithm.

The one home of these helpers (issue 14): the pose solvers (``core.p3p``,
``estimation.resect``, ``estimation.initialize``), the factors
(``estimation.external``) and the uncertainty maps use them. Rotation vectors are
in radians; ``Exp(w) = I + sin|w|/|w| [w]x + (1 - cos|w|)/|w|^2 [w]x^2``
(Rodrigues).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "nearest_rotation",
    "rotation_angle",
    "skew",
    "so3_exp",
    "so3_exp_batch",
    "so3_left_jacobian_batch",
    "so3_log",
    "so3_log_batch",
]

#: below this angle (rad) the exponential is its first-order expansion ``I + [w]x``
SMALL_ANGLE = 1e-12


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product (skew-symmetric) matrices of vectors.

    Parameters
    ----------
    v : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``skew(a) @ b == cross(a, b)``.
    """
    v = np.asarray(v, float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of one rotation vector (Rodrigues).

    Parameters
    ----------
    w : array_like, shape (3,)
        Rotation vector, radians.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    th = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < SMALL_ANGLE:
        return np.eye(3) + k
    return np.eye(3) + math.sin(th) / th * k + (1.0 - math.cos(th)) / th**2 * (k @ k)


def so3_exp_batch(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors, vectorised (Rodrigues).

    Parameters
    ----------
    w : array_like, shape (N, 3)
        Rotation vectors, radians.

    Returns
    -------
    ndarray, shape (N, 3, 3)
    """
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)
    k = skew(w)
    small = th < SMALL_ANGLE
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_left_jacobian_batch(w: np.ndarray) -> np.ndarray:
    """Left Jacobians of SO(3), vectorised: ``d/dw exp(w) = exp(J_l(w) dw) exp(w)``.

    ``J_l(w) = I + (1 - cos th) / th^2 [w]x + (th - sin th) / th^3 [w]x^2``, so for a
    point ``y``, ``d(exp(w) y)/dw = -[exp(w) y]x J_l(w)``.

    Parameters
    ----------
    w : array_like, shape (N, 3)
        Rotation vectors, radians.

    Returns
    -------
    ndarray, shape (N, 3, 3)
    """
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)
    k = skew(w)
    small = th < 1e-3  # Taylor series there: the closed forms cancel (error ~eps / th^2)
    safe = np.where(small, 1.0, th)
    t2 = th * th
    a = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices, accurate near 0 and pi.

    Parameters
    ----------
    R : array_like, shape (N, 3, 3)

    Returns
    -------
    ndarray, shape (N, 3)
        ``w`` with ``so3_exp(w) == R`` and ``|w| <= pi``.
    """
    R = np.asarray(R, float)
    v = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    s = 0.5 * np.linalg.norm(v, axis=-1)  # sin(theta)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)  # cos(theta)
    th = np.arctan2(s, c)
    small = s < 1e-9
    # generic and near-zero angles: w = theta / (2 sin theta) * v
    scale = np.where(small, 0.5, 0.5 * th / np.where(small, 1.0, s))
    out = scale[..., None] * v
    # near pi: the axis from the diagonal of (R + I) / 2 = a a^T (up to the small sine part)
    near_pi = small & (c < 0.0)
    if np.any(near_pi):
        B = 0.5 * (R[near_pi] + np.eye(3))
        col = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        a = B[np.arange(len(B)), :, col]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        # choose the sign agreeing with the (tiny) skew part when it is not zero
        sign = np.where(np.einsum("ni,ni->n", a, v[near_pi]) < 0.0, -1.0, 1.0)
        out[near_pi] = (sign * th[near_pi])[:, None] * a
    return out


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of one rotation matrix (see :func:`so3_log_batch`).

    Parameters
    ----------
    R : array_like, shape (3, 3)

    Returns
    -------
    ndarray, shape (3,)
    """
    return so3_log_batch(np.asarray(R, float)[None])[0]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in radians, accurate near 0 and pi.

    Parameters
    ----------
    R : ndarray, shape (3, 3) or (n, 3, 3)

    Returns
    -------
    float or ndarray, shape (n,)
        ``atan2(|axis * sin|, cos)`` from the skew and trace parts.
    """
    R = np.asarray(R, float)
    w = np.stack(
        [
            R[..., 2, 1] - R[..., 1, 2],
            R[..., 0, 2] - R[..., 2, 0],
            R[..., 1, 0] - R[..., 0, 1],
        ],
        axis=-1,
    )
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), cos)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (SVD), det +1.

    Parameters
    ----------
    M : ndarray, shape (3, 3) or (..., 3, 3)

    Returns
    -------
    ndarray, shape of ``M``
        ``U diag(1, 1, sign det(U V^T)) V^T`` of ``M = U S V^T`` (each matrix of a stack).
    """
    M = np.asarray(M, float)
    if M.ndim > 2:
        U, _, Vt = np.linalg.svd(M)
        sign = np.sign(np.linalg.det(U @ Vt))
        sign[sign == 0] = 1.0
        U = U.copy()
        U[..., :, 2] *= sign[..., None]
        return U @ Vt
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt
