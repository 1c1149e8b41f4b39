"""The robust losses of ``core.robust``: each weight is the IRLS weight of its cost."""

import numpy as np
import pytest

from gtsam_sphere.core.robust import Loss, robust_weight, whitening_scale

K = 2.45


@pytest.mark.parametrize("loss", list(Loss))
def test_every_loss_is_least_squares_near_zero(loss):
    r = np.array([0.0, 1e-4, 1e-3])
    w, rho = robust_weight(r, loss, K)
    np.testing.assert_allclose(rho, 0.5 * r * r, rtol=1e-5, atol=1e-14)
    np.testing.assert_allclose(w, 1.0, atol=1e-5)


@pytest.mark.parametrize("loss", list(Loss))
def test_the_weight_is_the_derivative_of_the_cost_over_r(loss):
    """IRLS: ``w(r) = rho'(r) / r``, checked by central differences away from the kinks."""
    r = np.array([0.3, 1.0, 2.0, 3.1, 7.0, 40.0])
    h = 1e-6
    w, _ = robust_weight(r, loss, K)
    drho = (robust_weight(r + h, loss, K)[1] - robust_weight(r - h, loss, K)[1]) / (2 * h)
    np.testing.assert_allclose(w, drho / r, rtol=1e-6, atol=1e-9)
    assert np.all((w >= 0.0) & (w <= 1.0))


def test_the_truncated_loss_costs_every_outlier_the_same():
    r = np.array([0.5, K, K + 0.1, 10.0, 1e6])
    w, rho = robust_weight(r, Loss.TRUNCATED, K)
    np.testing.assert_allclose(rho, [0.125, K * K / 2, K * K / 2, K * K / 2, K * K / 2])
    np.testing.assert_array_equal(w, [1.0, 1.0, 0.0, 0.0, 0.0])
    # a bounded cost put into a residual: |s r|^2 / 2 == rho
    s = whitening_scale(r, rho)
    np.testing.assert_allclose(0.5 * (s * r) ** 2, rho)


def test_an_unknown_loss_is_refused():
    with pytest.raises(ValueError, match="bogus"):
        robust_weight(np.ones(3), "bogus", K)
