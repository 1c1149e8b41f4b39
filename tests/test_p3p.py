"""Tests of gtsam_sphere.core.p3p: the minimal solver and RANSAC, for bearings in any direction."""

from __future__ import annotations

import numpy as np
import pytest

from gtsam_sphere.core.lie import so3_exp
from gtsam_sphere.core.p3p import PoseResult, angular_errors_rad, p3p, ransac_pose, ransac_poses


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def _bearings_at(off_axis_rad: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Unit bearings at the given angles from +z, random azimuth."""
    phi = rng.uniform(-np.pi, np.pi, off_axis_rad.shape)
    s = np.sin(off_axis_rad)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(off_axis_rad)], axis=-1)


def _scene(rng, off_axis_rad):
    """Random pose and world points seen along bearings at ``off_axis_rad``."""
    rot = _random_rotation(rng)
    t = rng.normal(size=3)
    f = _bearings_at(np.asarray(off_axis_rad, dtype=float), rng)
    dist = rng.uniform(0.5, 5.0, len(f))
    p_cam = f * dist[:, None]
    x = (p_cam - t) @ rot  # rot.T @ (p_cam - t), row-wise
    return rot, t, f, x


def _closest(solutions, rot, t) -> float:
    return min(max(np.abs(r - rot).max(), np.abs(tt - t).max()) for r, tt in solutions)


@pytest.mark.parametrize(
    "off_axis_deg",
    [
        (0.0, 10.0, 30.0),  # narrow, one on the axis
        (5.0, 45.0, 80.0),
        (90.0, 90.0, 30.0),  # exactly sideways
        (120.0, 150.0, 170.0),  # all behind the camera
        (10.0, 100.0, 175.0),  # mixed hemispheres
    ],
)
def test_p3p_exact_recovery(off_axis_deg):
    rng = np.random.default_rng(abs(hash(off_axis_deg)) % 2**32)
    for _ in range(50):
        rot, t, f, x = _scene(rng, np.radians(off_axis_deg))
        sols = p3p(f, x)
        assert 1 <= len(sols) <= 4
        assert _closest(sols, rot, t) < 1e-9
        for r, tt in sols:  # every solution is a rotation and explains the 3 bearings
            np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
            assert np.linalg.det(r) > 0
            assert angular_errors_rad(f, x, r, tt).max() < 1e-7


def test_p3p_random_directions_many():
    rng = np.random.default_rng(7)
    for _ in range(500):
        rot, t, f, x = _scene(rng, rng.uniform(0, np.radians(178.0), 3))
        sols = p3p(f, x)
        assert sols and _closest(sols, rot, t) < 1e-9


def test_p3p_accepts_unnormalised_bearings():
    rng = np.random.default_rng(8)
    rot, t, f, x = _scene(rng, np.radians([20.0, 60.0, 130.0]))
    assert _closest(p3p(f * [[2.0], [0.5], [7.0]], x), rot, t) < 1e-9


def test_p3p_degenerate_inputs_return_empty():
    rng = np.random.default_rng(9)
    f = _bearings_at(np.radians([10.0, 40.0, 70.0]), rng)
    collinear = np.array([[0.0, 0.0, 1.0], [1.0, 1.0, 2.0], [2.0, 2.0, 3.0]])
    assert p3p(f, collinear) == []
    duplicate = f.copy()
    duplicate[1] = duplicate[0]
    assert p3p(duplicate, rng.normal(size=(3, 3))) == []
    antipodal = f.copy()
    antipodal[2] = -antipodal[0]
    assert p3p(antipodal, rng.normal(size=(3, 3))) == []
    coincident = np.zeros((3, 3))
    assert p3p(f, coincident) == []
    assert p3p(np.full((3, 3), np.nan), rng.normal(size=(3, 3))) == []


def _ransac_scene(rng, n, outlier_fraction, max_off_axis_deg=170.0, noise_rad=0.0):
    rot = _random_rotation(rng)
    t = rng.normal(size=3)
    f = _bearings_at(rng.uniform(0, np.radians(max_off_axis_deg), n), rng)
    p_cam = f * rng.uniform(1.0, 5.0, n)[:, None]
    x = (p_cam - t) @ rot
    meas = f + rng.normal(scale=noise_rad, size=f.shape)
    n_out = int(round(outlier_fraction * n))
    out = rng.permutation(n)[:n_out]
    meas[out] = rng.normal(size=(n_out, 3))
    meas /= np.linalg.norm(meas, axis=1, keepdims=True)
    is_out = np.zeros(n, bool)
    is_out[out] = True
    return rot, t, meas, x, is_out


def _rot_angle(a, b) -> float:
    return float(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ransac_pose_30_percent_outliers(seed):
    rng = np.random.default_rng(seed)
    rot, t, f, x, is_out = _ransac_scene(rng, 120, 0.3, noise_rad=2e-4)
    res = ransac_pose(f, x, threshold_rad=2e-3, rng=rng)
    assert isinstance(res, PoseResult) and res.success
    assert _rot_angle(res.R, rot) < 1e-3
    assert np.linalg.norm(res.t - t) < 1e-3 * max(1.0, np.linalg.norm(t))
    # every true inlier found; random outliers essentially never within 2 mrad
    assert res.inlier_mask[~is_out].all()
    assert res.inlier_mask[is_out].sum() <= 1
    assert res.n_inliers == res.inlier_mask.sum()
    assert 0 < res.median_error_rad < 2e-3


def test_ransac_pose_exact_data_is_exact_and_handles_nan_rows():
    rng = np.random.default_rng(4)
    rot, t, f, x, _ = _ransac_scene(rng, 40, 0.0)
    f[5] = np.nan
    res = ransac_pose(f, x, threshold_rad=1e-6, rng=rng)
    assert res.success and res.n_inliers == 39 and not res.inlier_mask[5]
    assert _rot_angle(res.R, rot) < 1e-9 and np.abs(res.t - t).max() < 1e-9


def test_ransac_pose_too_few_points_is_a_reported_failure():
    rng = np.random.default_rng(5)
    rot, t, f, x, _ = _ransac_scene(rng, 3, 0.0)
    res = ransac_pose(f, x, threshold_rad=1e-3, rng=rng)
    assert not res.success and res.n_inliers == 0
    assert "only 3 usable observations" in res.reason
    assert res.inlier_mask.shape == (3,) and not res.inlier_mask.any()


def test_ransac_pose_pure_noise_fails_cleanly():
    rng = np.random.default_rng(6)
    f = rng.normal(size=(30, 3))
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    x = rng.normal(size=(30, 3))
    res = ransac_pose(f, x, threshold_rad=1e-4, rng=rng, max_iterations=200, min_inliers=10)
    assert not res.success and "inliers of 30" in res.reason


def test_angular_errors_batched_matches_single():
    rng = np.random.default_rng(7)
    rot, t, f, x, _ = _ransac_scene(rng, 10, 0.5)
    rots = np.stack([rot, _random_rotation(rng)])
    ts = np.stack([t, rng.normal(size=3)])
    both = angular_errors_rad(f, x, rots, ts)
    np.testing.assert_allclose(both[1], angular_errors_rad(f, x, rots[1], ts[1]))
    assert both.shape == (2, 10) and np.all((both >= 0) & (both <= np.pi))


@pytest.mark.parametrize("refine", [False, True])
def test_ransac_poses_of_many_problems_equal_each_alone(refine):
    """The batched RANSAC draws each problem's samples from its own generator and scores
    them in shared calls: every result is bit for bit that of ransac_pose alone, for
    problems of different sizes, outlier rates, thresholds and a too-small one."""
    rng = np.random.default_rng(8)
    problems = []
    for n, frac, thr in [(40, 0.0, 1e-3), (120, 0.3, 2e-3), (3, 0.0, 1e-3), (75, 0.6, 5e-3)]:
        _, _, f, x, _ = _ransac_scene(rng, n, frac, noise_rad=2e-4 if frac else 0.0)
        f[n // 2] = np.nan  # a non-finite row
        problems.append((f, x, thr))
    seeds = [11, 12, 13, 14]
    alone = [
        ransac_pose(f, x, thr, np.random.default_rng(s), 300, refine=refine)
        for (f, x, thr), s in zip(problems, seeds)
    ]
    together = ransac_poses(
        [f for f, _, _ in problems],
        [x for _, x, _ in problems],
        [thr for _, _, thr in problems],
        [np.random.default_rng(s) for s in seeds],
        300,
        refine=refine,
    )
    assert len(together) == len(problems)
    for a, b in zip(alone, together):
        assert a.success == b.success and a.reason == b.reason
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    assert not together[2].success and "only 2 usable observations" in together[2].reason
    assert together[1].success and together[3].success


def test_ransac_poses_rejects_mismatched_lists():
    f = np.tile([0.0, 0.0, 1.0], (5, 1))
    with pytest.raises(ValueError, match="one entry per problem"):
        ransac_poses([f, f], [f], [1e-3, 1e-3], [np.random.default_rng(0)] * 2)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        ransac_poses([f], [f[:4]], [1e-3], [np.random.default_rng(0)])


def test_pose_refinement_gradient_matches_finite_differences(monkeypatch):
    """The pose LM's normal equations: ``g = J^T W r`` is the gradient of its cost along
    the retraction ``(exp(w) R, t + dt)`` and ``H = J^T W J`` its Gauss-Newton matrix
    (checked where every residual is inside the Huber knee, so the weights are 1), for
    each problem of a batch of two of different sizes."""
    import gtsam_sphere.core.p3p as p3p_module

    rng = np.random.default_rng(9)
    rot, t, f, x, _ = _ransac_scene(rng, 30, 0.0, noise_rad=3e-3)
    rot2, t2, f2, x2, _ = _ransac_scene(rng, 17, 0.0, noise_rad=3e-3)
    seen = {}
    real = p3p_module.levenberg_marquardt_batch

    def spy(x0, cost, linearize, *, retract, **kwargs):
        seen.update(x0=x0, cost=cost, linearize=linearize, retract=retract)
        return real(x0, cost, linearize, retract=retract, **kwargs)

    monkeypatch.setattr(p3p_module, "levenberg_marquardt_batch", spy)
    R0 = np.stack([so3_exp(np.array([0.01, -0.02, 0.005])) @ rot, rot2])
    t0 = np.stack([t + 0.01, t2 - 0.02])
    p3p_module._refine_poses(
        np.concatenate([f, f2]), np.concatenate([x, x2]), [30, 17], R0, t0, [1.0, 1.0]
    )
    pose, cost, retract = seen["x0"], seen["cost"], seen["retract"]
    H, g = seen["linearize"](pose)
    assert H.shape == (2, 6, 6) and g.shape == (2, 6)
    h = 1e-6
    steps = [h * np.stack([e, e]) for e in np.eye(6)]
    grad = np.stack(
        [(cost(retract(pose, d)) - cost(retract(pose, -d))) / (2 * h) for d in steps], axis=1
    )
    np.testing.assert_allclose(g, grad, rtol=1e-5, atol=1e-9)
    # H: the Jacobian of g along each direction, up to the second-order residual term
    dg = np.stack(
        [
            (seen["linearize"](retract(pose, d))[1] - seen["linearize"](retract(pose, -d))[1])
            / (2 * h)
            for d in steps
        ],
        axis=2,
    )
    for b in range(2):
        np.testing.assert_allclose(H[b], dg[b], atol=0.05 * np.abs(H[b]).max())
        assert np.allclose(H[b], H[b].T) and np.all(np.linalg.eigvalsh(H[b]) > 0)


def test_msac_costs_equal_the_arccos_of_every_pair_to_the_bit():
    """``_msac_costs`` takes the arccos only near or inside the threshold; the costs are
    those of capping the arccos of every (hypothesis, row) pair, bit for bit: cosines
    just either side of ``cos(thr)``, NaN (no ray), padded rows, thresholds per problem."""
    from gtsam_sphere.core.p3p import _msac_costs

    rng = np.random.default_rng(3)
    n_p, n_h, n_n = 3, 40, 50
    thr = np.array([1e-3, 5e-3, 2e-2])
    ang = np.abs(rng.normal(0.0, 1.5, (n_p, n_h, n_n))) * thr[:, None, None]
    cosang = np.cos(ang)
    c_thr = np.cos(thr)[:, None]
    cosang[:, 0, :10] = np.nextafter(c_thr, 2.0)  # one ulp inside
    cosang[:, 0, 10:20] = np.nextafter(c_thr, -2.0)  # one ulp outside
    cosang[:, 0, 20:25] = c_thr
    cosang[:, 1, :5] = np.nan
    cosang[:, 2, :5] = 1.0 + 1e-15  # rounding past 1
    cosang[:, 3, :5] = -1.0  # opposite
    obs = np.ones((n_p, n_n), bool)
    obs[1, 40:] = False  # padding
    full = np.arccos(np.clip(np.nan_to_num(cosang, nan=-1.0), -1.0, 1.0))
    capped = np.minimum(full * full, (thr * thr)[:, None, None])
    expected = np.where(obs[:, None, :], capped, 0.0).sum(axis=2)
    got = _msac_costs(cosang, thr, obs)
    assert got.shape == (n_p, n_h)
    np.testing.assert_array_equal(got, expected)


def test_closed_form_quartic_roots_match_the_companion_eigenvalues():
    """Ferrari's roots (``_quartic_roots``) against the eigenvalues of the companion
    matrices: random quartics with 0, 2 and 4 real roots, scaled, plus the rows the
    closed form hands over (biquadratic, degenerate, vanishing leading term)."""
    from gtsam_sphere.core.p3p import _quartic_roots, _quartic_roots_eig

    rng = np.random.default_rng(3)
    n = 3000
    real = rng.normal(scale=2.0, size=(n, 4))
    pair = rng.normal(size=(n, 2)) + 1j * rng.uniform(0.05, 2.0, size=(n, 2))
    kind = rng.integers(0, 3, size=n)  # 4, 2 or 0 real roots
    z = np.where(
        (kind == 0)[:, None],
        real.astype(complex),
        np.where(
            (kind == 1)[:, None],
            np.column_stack([real[:, :2], pair[:, 0], np.conj(pair[:, 0])]),
            np.column_stack([pair[:, 0], np.conj(pair[:, 0]), pair[:, 1], np.conj(pair[:, 1])]),
        ),
    )
    coef = np.array([np.poly(r)[::-1].real for r in z]) * rng.uniform(0.1, 10.0, size=(n, 1))
    extra = np.array(
        [
            [4.0, 0.0, -5.0, 0.0, 1.0],  # x^4 - 5x^2 + 4: q = 0, split by the eigenvalues
            [0.0, 0.0, 0.0, 0.0, 0.0],  # degenerate: NaN
            [1.0, 2.0, 3.0, 4.0, 0.0],  # a cubic
            [0.0, 0.0, 1.0, -2.0, 1.0],  # double roots 0 and 1
        ]
    )
    coef = np.vstack([coef, extra])
    got, want = _quartic_roots(coef), _quartic_roots_eig(coef)
    assert got.shape == want.shape == (n + 4, 4)
    assert np.all(np.isnan(got[n + 1])) and np.all(np.isnan(want[n + 1]))
    for g, w in zip(got[np.arange(n + 4) != n + 1], want[np.arange(n + 4) != n + 1]):
        g, w = g[np.isfinite(g)], w[np.isfinite(w)]
        assert g.size == w.size
        # every root of one set has a partner in the other
        d = np.abs(g[:, None] - w[None, :]) / (1.0 + np.abs(w[None, :]))
        assert d.min(axis=1).max() < 1e-6 and d.min(axis=0).max() < 1e-6, (g, w)
    real_got = np.abs(got.imag) <= 1e-4 * (1.0 + np.abs(got.real))
    real_want = np.abs(want.imag) <= 1e-4 * (1.0 + np.abs(want.real))
    assert np.array_equal(real_got.sum(axis=1), real_want.sum(axis=1))
    assert np.array_equal(np.sort(real_got.sum(axis=1)[:n]), np.sort(4 - 2 * kind))
