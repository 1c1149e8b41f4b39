"""Tests of gtsam_sphere.core.lie: the one home of skew, SO(3) Exp and Log."""

from __future__ import annotations

import numpy as np

from gtsam_sphere.core.lie import (
    skew,
    so3_exp,
    so3_exp_batch,
    so3_left_jacobian_batch,
    so3_log,
    so3_log_batch,
)


def _vectors(n=500, seed=0):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(n, 3))
    return w * (rng.uniform(0.0, np.pi * 0.999, n) / np.linalg.norm(w, axis=1))[:, None]


def test_skew_is_the_cross_product():
    a, b = np.random.default_rng(1).normal(size=(2, 7, 3))
    assert np.allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-15)
    assert skew(a[0]).shape == (3, 3)


def test_exp_is_a_rotation_and_batch_agrees():
    w = _vectors()
    R = so3_exp_batch(w)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-14)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(R, np.stack([so3_exp(x) for x in w]), atol=1e-15)
    assert np.array_equal(so3_exp(np.zeros(3)), np.eye(3))


def test_log_inverts_exp_including_tiny_angles_and_pi():
    w = _vectors()
    w[:3] *= 1e-13
    assert np.allclose(so3_log_batch(so3_exp_batch(w)), w, atol=1e-12)
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    w_pi = np.pi * axis
    back = so3_log(so3_exp(w_pi))
    assert np.isclose(np.linalg.norm(back), np.pi)
    assert np.allclose(so3_exp(back), so3_exp(w_pi), atol=1e-12)


def test_nearest_rotation_and_rotation_angle():
    from gtsam_sphere.core.lie import nearest_rotation, rotation_angle

    w = _vectors(20, seed=3)
    R = so3_exp_batch(w)
    noisy = R + 1e-6 * np.random.default_rng(4).normal(size=R.shape)
    fixed = np.stack([nearest_rotation(m) for m in noisy])
    assert np.allclose(fixed @ fixed.transpose(0, 2, 1), np.eye(3), atol=1e-14)
    assert np.allclose(fixed, R, atol=1e-5)
    assert np.allclose(rotation_angle(R), np.linalg.norm(w, axis=1), atol=1e-12)
    # a reflection's nearest rotation has det +1
    assert np.isclose(np.linalg.det(nearest_rotation(np.diag([1.0, 1.0, -1.0]))), 1.0)


def test_left_jacobian_against_central_differences():
    """d(exp(w) y)/dw = -[exp(w) y]x J_l(w), at angles from 0 to near pi (both branches
    of the closed form and its series)."""
    rng = np.random.default_rng(3)
    y = rng.normal(size=3)
    for th in (0.0, 1e-7, 5e-4, 2e-3, 0.3, 1.5, 3.0):
        axis = rng.normal(size=3)
        w = th * axis / np.linalg.norm(axis)
        jl = so3_left_jacobian_batch(w[None])[0]
        analytic = -skew(so3_exp(w) @ y) @ jl
        h = 1e-6
        numeric = np.column_stack(
            [(so3_exp(w + h * e) @ y - so3_exp(w - h * e) @ y) / (2 * h) for e in np.eye(3)]
        )
        np.testing.assert_allclose(analytic, numeric, atol=1e-8)


def test_nearest_rotation_of_a_stack_equals_each_alone():
    from gtsam_sphere.core.lie import nearest_rotation

    rng = np.random.default_rng(4)
    stack = rng.normal(size=(6, 3, 3))
    stack[2] = np.diag([1.0, 1.0, -1.0])  # a reflection: det +1 is enforced
    out = nearest_rotation(stack)
    for m, r in zip(stack, out):
        np.testing.assert_allclose(r, nearest_rotation(m), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(out), 1.0)
    np.testing.assert_allclose(
        out @ out.transpose(0, 2, 1), np.broadcast_to(np.eye(3), out.shape), atol=1e-14
    )
