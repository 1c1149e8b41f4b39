"""Marginal covariances (gtsam_sphere.estimation.optimize.marginal_covariances): GTSAM's
Marginals, and the sparse-LU path taken when GTSAM refuses an ill-conditioned system."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gtsam_sphere.estimation import optimize


def _small_graph():
    """Two poses and a point: a prior, an odometry factor and a point prior."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.02, 0.03, 0.1, 0.2, 0.3]))
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 0.0, 0.0]))
    graph.add(gtsam.PriorFactorPose3(1, gtsam.Pose3(), noise))
    graph.add(gtsam.BetweenFactorPose3(1, 2, step, noise))
    graph.add(
        gtsam.PriorFactorPoint3(
            3, np.array([1.0, 2.0, 3.0]), gtsam.noiseModel.Isotropic.Sigma(3, 0.5)
        )
    )
    values.insert(1, gtsam.Pose3())
    values.insert(2, step)
    values.insert(3, np.array([1.0, 2.0, 3.0]))
    return graph, values


class _Refusing:
    """Stands in for gtsam.Marginals on a system GTSAM calls indeterminate."""

    def __init__(self, *args):
        raise RuntimeError("Indeterminant linear system detected")


def test_sparse_lu_path_equals_gtsam_marginals(monkeypatch):
    graph, values = _small_graph()
    expected = optimize.marginal_covariances(graph, values, [2, 3])
    monkeypatch.setattr(optimize.gtsam, "Marginals", _Refusing)
    got = optimize.marginal_covariances(graph, values, [2, 3])
    assert set(got) == {2, 3}
    np.testing.assert_allclose(got[2], expected[2], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(got[3], expected[3], rtol=1e-9, atol=1e-15)
    assert got[3][0, 0] == pytest.approx(0.25)


def test_a_truly_singular_system_gives_none(monkeypatch):
    """Two points tied only to each other (a free translation) are not determined."""
    monkeypatch.setattr(optimize.gtsam, "Marginals", _Refusing)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.BetweenFactorPoint3(3, 4, np.ones(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    values.insert(3, np.zeros(3))
    values.insert(4, np.ones(3))
    assert optimize.marginal_covariances(graph, values, [3]) is None
    values.insert(5, np.zeros(3))  # in the values, in no factor
    assert optimize.marginal_covariances(graph, values, [5]) is None


def test_a_variable_without_information_is_left_out_of_the_others_marginals():
    """A point whose only factor has a zero Jacobian (a target every observation of
    which a robust stage weighted 0) makes the whole system singular; the other
    variables' marginals are those of the graph without it, and its own is None."""
    graph, values = _small_graph()
    expected = optimize.marginal_covariances(graph, values, [2, 3])

    def no_information(this, vals, H):
        if H is not None:
            H[0] = np.zeros((3, 3), order="F")
        return np.zeros(3)

    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(3), [7], no_information))
    values.insert(7, np.array([5.0, 5.0, 5.0]))
    with pytest.raises(RuntimeError):
        gtsam.Marginals(graph, values)
    got = optimize.marginal_covariances(graph, values, [2, 3])
    np.testing.assert_allclose(got[2], expected[2], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(got[3], expected[3], rtol=1e-9, atol=1e-15)
    assert optimize.marginal_covariances(graph, values, [2, 7]) is None
