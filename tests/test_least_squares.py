"""Tests of gtsam_sphere.core.least_squares: the one dense Levenberg-Marquardt loop."""

from __future__ import annotations

import numpy as np
import pytest

from gtsam_sphere.core.least_squares import (
    Damping,
    LMStatus,
    levenberg_marquardt,
    levenberg_marquardt_batch,
)


def _exp_fit():
    """Residuals and normal equations of ``y = a exp(b t)`` (exact data a=2, b=-1.5)."""
    t = np.linspace(0.0, 2.0, 30)
    y = 2.0 * np.exp(-1.5 * t)

    def residual(x):
        return x[0] * np.exp(x[1] * t) - y

    def jacobian(x):
        e = np.exp(x[1] * t)
        return np.column_stack([e, x[0] * t * e])

    def cost(x):
        r = residual(x)
        return float(r @ r)

    def linearize(x):
        J, r = jacobian(x), residual(x)
        return J.T @ J, J.T @ r

    return cost, linearize


def test_converges_on_a_small_curve_fit():
    cost, linearize = _exp_fit()
    res = levenberg_marquardt(
        np.array([1.0, 0.0]),
        cost,
        linearize,
        converged=lambda c0, c1, d: c0 - c1 <= 1e-14 * c0 or c1 == 0.0,
    )
    assert res.status is LMStatus.CONVERGED and res.converged
    np.testing.assert_allclose(res.x, [2.0, -1.5], atol=1e-7)


def test_iteration_limit_and_stall_are_reported():
    cost, linearize = _exp_fit()
    res = levenberg_marquardt(np.array([1.0, 0.0]), cost, linearize, max_iterations=2)
    assert res.status is LMStatus.MAX_ITERATIONS and not res.converged and res.iterations == 2
    # at the exact minimum no step lowers the cost: the run stalls at once
    stuck = levenberg_marquardt(
        np.array([2.0, -1.5]), cost, linearize, damping=Damping(max_tries=3)
    )
    assert stuck.status is LMStatus.STALLED and stuck.iterations == 1
    np.testing.assert_array_equal(stuck.x, [2.0, -1.5])


def test_an_infeasible_region_is_never_entered():
    cost, linearize = _exp_fit()
    res = levenberg_marquardt(
        np.array([1.0, 0.0]),
        cost,
        linearize,
        feasible=lambda x: x[0] <= 1.5,
        max_iterations=50,
    )
    assert res.x[0] <= 1.5


def _exp_fit_batch():
    """:func:`_exp_fit` for a batch of states (B, 2)."""
    cost1, linearize1 = _exp_fit()

    def cost(xs):
        return np.array([cost1(x) for x in xs])

    def linearize(xs):
        pairs = [linearize1(x) for x in xs]
        return np.stack([H for H, _ in pairs]), np.stack([g for _, g in pairs])

    return cost, linearize


def test_a_batch_runs_each_problem_as_alone():
    """Every problem of a batch takes the steps, damping and status it takes alone: one
    converges, one is at the minimum already (stalls), one hits the iteration limit, one
    starts where the normal equations are singular (the damping makes them solvable)."""
    cost1, linearize1 = _exp_fit()
    cost, linearize = _exp_fit_batch()
    starts = np.array([[1.0, 0.0], [2.0, -1.5], [0.0, 0.0], [0.01, 3.0]])
    damping = Damping(max_tries=8)

    def conv1(c0, c1, d):
        return c0 - c1 <= 1e-14 * c0 or c1 == 0.0

    with np.errstate(over="ignore"):  # the last start tries steps to huge exponents
        batch = _run_batch_and_alone(starts, cost, linearize, cost1, linearize1, conv1, damping)
    for b, alone in enumerate(batch[1]):
        np.testing.assert_array_equal(batch[0].x[b], alone.x)
        assert batch[0].cost[b] == alone.cost and batch[0].damping[b] == alone.damping
        assert batch[0].iterations[b] == alone.iterations
        assert batch[0].status[b] is alone.status
    batch = batch[0]
    assert batch.status[0] is LMStatus.CONVERGED
    assert batch.status[1] is LMStatus.STALLED
    assert batch.status[2] is LMStatus.CONVERGED  # from a singular start
    assert batch.status[3] is LMStatus.MAX_ITERATIONS and batch.iterations[3] == 10


def _run_batch_and_alone(starts, cost, linearize, cost1, linearize1, conv1, damping):
    batch = levenberg_marquardt_batch(
        starts,
        cost,
        linearize,
        converged=lambda c0, c1, d: (c0 - c1 <= 1e-14 * c0) | (c1 == 0.0),
        damping=damping,
        max_iterations=10,
    )
    alone = [
        levenberg_marquardt(
            x0, cost1, linearize1, converged=conv1, damping=damping, max_iterations=10
        )
        for x0 in starts
    ]
    return batch, alone


def test_a_batch_rejects_infeasible_and_negligible_steps_per_problem():
    """A tuple state: each problem carries its own fence, and the callbacks see the rows
    of the problems they are asked about."""
    cost, linearize = _exp_fit_batch()
    starts = (np.array([[1.0, 0.0], [1.2, -0.5]]), np.array([1.5, 9.0]))
    res = levenberg_marquardt_batch(
        starts,
        lambda s: cost(s[0]),
        lambda s: linearize(s[0]),
        retract=lambda s, d: (s[0] + d, s[1]),
        feasible=lambda s: s[0][:, 0] <= s[1],
        damping=Damping(ceiling=1e10),
        max_iterations=50,
    )
    x = res.x[0]
    assert x[0, 0] <= 1.5  # only the first problem is fenced
    np.testing.assert_allclose(x[1], [2.0, -1.5], atol=1e-6)
    stop = levenberg_marquardt_batch(
        starts[0], cost, linearize, negligible=lambda d, g, c: np.ones(len(d), bool)
    )
    assert stop.status == [LMStatus.CONVERGED] * 2 and (stop.x == starts[0]).all()


def test_singular_systems_of_a_batch_are_found_one_by_one():
    from gtsam_sphere.core.least_squares import _solve_damped

    H = np.stack([np.diag([2.0, 3.0]), np.array([[1.0, 1.0], [1.0, 1.0]])])
    g = np.array([[1.0, -1.0], [1.0, 2.0]])
    delta, singular = _solve_damped(H, g, np.zeros(2), np.ones((2, 2)))
    assert singular.tolist() == [False, True]
    np.testing.assert_array_equal(delta[0], np.linalg.solve(H[0], -g[0]))
    delta, singular = _solve_damped(H, g, np.array([0.0, 1.0]), np.ones((2, 2)))
    assert not singular.any()
    np.testing.assert_allclose((H[1] + np.eye(2)) @ delta[1], -g[1])


def _arrow_system(rng, n_shared, block, m, batch):
    """Random symmetric positive definite normal equations of arrow structure."""
    n_p = n_shared + m * block
    H = np.zeros((batch, n_p, n_p))
    for b in range(batch):
        J = np.zeros((3 * n_p, n_p))
        for k in range(m):
            rows = slice(3 * block * k, 3 * block * (k + 1))
            J[rows, :n_shared] = rng.normal(size=(3 * block, n_shared))
            J[rows, n_shared + k * block : n_shared + (k + 1) * block] = rng.normal(
                size=(3 * block, block)
            )
        H[b] = J.T @ J
    g = rng.normal(size=(batch, n_p))
    return H, g


@pytest.mark.parametrize("n_shared", [0, 2, 6])
def test_the_arrow_solve_is_the_dense_solve(n_shared):
    """``arrow_solve`` eliminates the blocks: the same damped steps as the dense solve,
    per problem of a batch, with their own damping."""
    from gtsam_sphere.core.least_squares import _solve_damped, arrow_solve

    rng = np.random.default_rng(3)
    H, g = _arrow_system(rng, n_shared, 6, 5, 3)
    lam = np.array([0.0, 1e-3, 10.0])
    s = np.abs(rng.normal(size=g.shape)) + 0.5
    dense, sing_dense = _solve_damped(H, g, lam, s)
    arrow, sing_arrow = arrow_solve(n_shared, 6)(H, g, lam, s)
    assert not sing_dense.any() and not sing_arrow.any()
    np.testing.assert_allclose(arrow, dense, rtol=1e-8, atol=1e-10)
    # H untouched (the damping is added to copies)
    H2, _ = _arrow_system(np.random.default_rng(3), n_shared, 6, 5, 3)
    np.testing.assert_array_equal(H, H2)


def test_the_arrow_solve_flags_a_singular_block_and_a_bad_layout():
    """A block with no information and no damping is singular (its step left at zero,
    the other problems of the batch solved); a size that is not shared + blocks raises."""
    from gtsam_sphere.core.least_squares import _solve_damped, arrow_solve

    rng = np.random.default_rng(4)
    H, g = _arrow_system(rng, 3, 4, 3, 2)
    H[0, 7:11, :] = 0.0
    H[0, :, 7:11] = 0.0
    lam = np.zeros(2)
    s = np.ones_like(g)
    delta, singular = arrow_solve(3, 4)(H, g, lam, s)
    assert singular.tolist() == [True, False]
    np.testing.assert_array_equal(delta[0], 0.0)
    np.testing.assert_allclose(delta[1], _solve_damped(H[1:], g[1:], lam[1:], s[1:])[0][0])
    with pytest.raises(ValueError, match="not 2 shared unknowns plus blocks of 4"):
        arrow_solve(2, 4)(H, g, lam, s)
