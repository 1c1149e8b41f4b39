"""Analytic Jacobians of the observation blocks vs numerical derivatives on the manifold."""

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11

from gtsam_sphere.camera import BROWN_TERMS, RADIAL_TERMS
from gtsam_sphere.graph import (
    INTRINSICS_KEY,
    Loss,
    NoiseOptions,
    ObservationBlock,
    point_key,
    pose_key,
)


def _values(rng, direction_cam, brown_names, radial_names=None):
    """One pose and one point placed so the point is seen along ``direction_cam``."""
    R = gtsam.Rot3.Rodrigues(*rng.normal(size=3))
    world_from_cam = gtsam.Pose3(R, gtsam.Point3(*rng.normal(size=3)))
    d = np.asarray(direction_cam, float)
    point_world = world_from_cam.transformFrom(2.5 * d / np.linalg.norm(d))
    radial = [] if radial_names is None else [-0.05, 0.01, -0.002, 0.001][: len(radial_names)]
    theta = np.concatenate(
        [[640.2, 401.7, 350.0], radial, 0.02 * rng.normal(size=len(brown_names))]
    )
    values = gtsam.Values()
    values.insert(pose_key(0), world_from_cam)
    values.insert(point_key(0), point_world)
    values.insert(INTRINSICS_KEY, theta)
    return values


DIRECTIONS = {
    "ordinary": [0.3, -0.2, 1.0],
    "optical axis": [0.0, 0.0, 1.0],
    "90 degrees": [1.0, 0.4, 0.0],
    "behind camera": [0.2, -0.5, -1.0],
    "nearly backwards": [1e-3, 0.0, -1.0],
}


MODELS = {
    "sphere": ((), None),
    "brown-all": (BROWN_TERMS, None),
    "equidistant": ((), ()),
    "radial4": ((), RADIAL_TERMS[:4]),
    "radial4+p1p2a1a2": (("p1", "p2", "a1", "a2"), RADIAL_TERMS[:4]),
}


@pytest.mark.parametrize("name", list(DIRECTIONS))
@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("loss", [Loss.L2, Loss.HUBER])
def test_block_jacobians_match_numerical(name, model, loss):
    brown_names, radial_names = MODELS[model]
    rng = np.random.default_rng(1)
    values = _values(rng, DIRECTIONS[name], brown_names, radial_names)
    uv = np.array([[640.0 + 3.0, 401.0 - 2.0]])  # residual big enough to be in Huber's tail
    noise = NoiseOptions(sigma_px=0.5, loss=loss, loss_threshold=1.0)
    block = ObservationBlock(
        [pose_key(0)],
        [point_key(0)],
        [0],
        [0],
        np.zeros((1, 3)),
        uv,
        brown_names,
        500.0,
        noise,
        radial_names,
    )
    H = [None] * 3
    block.evaluate(None, values, H)

    def with_value(key, value):
        v = gtsam.Values(values)
        v.update(key, value)
        return v

    def err(key):
        # derivative of the (weighted) residual with the IRLS weight frozen, as GTSAM's
        # robust noise model linearises: compare sqrt(w) * de/dx with the numeric de/dx.
        return lambda x: block.residuals_px(with_value(key, x)).ravel()

    r = np.linalg.norm(block.residuals_px(values)) / noise.sigma_px
    w = 1.0 if loss is Loss.L2 else min(1.0, noise.loss_threshold / r)
    scale = np.sqrt(w) / noise.sigma_px
    keys = [point_key(0), pose_key(0), INTRINSICS_KEY]
    getters = [values.atPoint3, values.atPose3, values.atVector]
    for q, (key, get) in enumerate(zip(keys, getters)):
        numeric = numericalDerivative11(err(key), get(key), delta=1e-6) * scale
        np.testing.assert_allclose(H[q], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
        assert H[q].flags.f_contiguous


def test_cost_branch_returns_rho():
    """With H None the squared norm is 2 * rho(r): GTSAM's error() equals the robust cost."""
    rng = np.random.default_rng(2)
    values = _values(rng, DIRECTIONS["ordinary"], ())
    uv = np.array([[700.0, 350.0]])
    noise = NoiseOptions(sigma_px=1.0, loss=Loss.HUBER, loss_threshold=2.0)
    block = ObservationBlock(
        [pose_key(0)], [point_key(0)], [0], [0], np.zeros((1, 3)), uv, (), 500.0, noise
    )
    e = block.evaluate(None, values, None)
    r = np.linalg.norm(block.residuals_px(values))
    assert r > 2.0
    np.testing.assert_allclose(0.5 * e @ e, 2.0 * r - 2.0, rtol=1e-12)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(block.factor())
    np.testing.assert_allclose(graph.error(values), 2.0 * r - 2.0, rtol=1e-12)
