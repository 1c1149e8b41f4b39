"""Tests of gtsam_sphere.core.least_squares: the one dense Levenberg-Marquardt loop."""

from __future__ import annotations

import numpy as np

from gtsam_sphere.core.least_squares import Damping, LMStatus, levenberg_marquardt


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
