"""Tests of gtsam_sphere.core.geometry's point-set fits (one Umeyama core for both)."""

from __future__ import annotations

import numpy as np

from gtsam_sphere.core.geometry import fit_rigid, fit_similarity
from gtsam_sphere.core.lie import so3_exp_batch


def test_similarity_and_batched_rigid_fits_recover_the_transform():
    rng = np.random.default_rng(0)
    R = so3_exp_batch(rng.normal(size=(6, 3)))
    t = rng.normal(size=(6, 3))
    src = rng.normal(size=(6, 10, 3))
    dst = np.einsum("kij,knj->kni", R, src) + t[:, None]
    R_fit, t_fit = fit_rigid(src, dst)
    assert np.allclose(R_fit, R, atol=1e-12) and np.allclose(t_fit, t, atol=1e-12)
    sim = fit_similarity(src[0], 2.5 * dst[0])
    assert np.isclose(sim.scale, 2.5) and np.allclose(sim.R, R[0], atol=1e-12)
    assert np.allclose(sim.apply(src[0]), 2.5 * dst[0], atol=1e-12)
    rigid = fit_similarity(src[1], dst[1], with_scale=False)
    assert rigid.scale == 1.0 and np.allclose(rigid.R, R_fit[1], atol=1e-14)


def test_a_reflection_is_never_returned():
    src = np.random.default_rng(1).normal(size=(8, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: the best rotation, det +1
    R, _ = fit_rigid(src, dst)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.isclose(np.linalg.det(fit_similarity(src, dst).R), 1.0)
