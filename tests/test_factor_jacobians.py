"""Analytic Jacobians of the observation blocks vs numerical derivatives on the manifold."""

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11

from gtsam_sphere.core.camera import BROWN_TERMS, RADIAL_TERMS
from gtsam_sphere.estimation.graph import (
    IMAGES_PER_FACTOR,
    INTRINSICS_KEY,
    BundleProblem,
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
@pytest.mark.parametrize("model", [*MODELS, "radial4+warp", "radial2+tan-warp"])
@pytest.mark.parametrize("loss", [Loss.L2, Loss.HUBER])
def test_block_jacobians_match_numerical(name, model, loss):
    # the warp (a fixed shape constant of the radial mapping): squeezing and stretching
    warped = {"radial4+warp": (4, np.log(4.0)), "radial2+tan-warp": (2, -1.0)}
    if model in warped:
        brown_names, radial_names, warp = (), RADIAL_TERMS[: warped[model][0]], warped[model][1]
    else:
        (brown_names, radial_names), warp = MODELS[model], None
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
        radial_warp=warp,
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


def _scene(model="sphere", n_images=12, n_targets=40, n_control=5, seed=3):
    """A small network: every image sees most targets (any direction: the model has no
    front/back), exact control targets and free ones, measurements off by a few px so
    the robust weights differ per observation. Returns (problem, values)."""
    brown_names, radial_names = MODELS[model]
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-3.0, 3.0, (n_targets, 3))
    poses = [
        gtsam.Pose3(gtsam.Rot3.Rodrigues(*rng.normal(size=3)), gtsam.Point3(*rng.normal(size=3)))
        for _ in range(n_images)
    ]
    obs = [(i, t) for i in range(n_images) for t in range(n_targets) if rng.random() < 0.7]
    obs_image = np.array([i for i, _ in obs])
    obs_target = np.array([t for _, t in obs])
    uv = 640.0 + rng.normal(0.0, 200.0, (len(obs), 2))
    sigma = np.full(n_targets, np.nan)
    sigma[:n_control] = 0.0
    problem = BundleProblem(
        obs_image=obs_image,
        obs_target=obs_target,
        uv_px=uv,
        target_xyz=xyz,
        target_sigma=sigma,
        n_images=n_images,
        brown_names=brown_names,
        brown_scale_px=500.0,
        noise=NoiseOptions(sigma_px=2.0, loss=Loss.HUBER, loss_threshold=1.5),
        points_per_factor=4,
        radial_names=radial_names,
    )
    values = _values(rng, DIRECTIONS["ordinary"], brown_names, radial_names)
    values.erase(point_key(0))
    values.erase(pose_key(0))
    for i, p in enumerate(poses):
        values.insert(pose_key(i), p)
    for t in problem.free_targets:
        values.insert(point_key(int(t)), xyz[t])
    return problem, values


def _alone(block):
    """A copy of ``block`` evaluated on its own (nothing shared, nothing stored)."""
    return ObservationBlock(
        block.pose_keys,
        block.point_keys,
        block.pose_local,
        block.point_local,
        block.fixed_xyz,
        block.uv_px,
        block.brown_names,
        block.brown_scale_px,
        block.noise,
        block.radial_names,
    )


def _nudged(values, key, rng, scale=1e-9):
    """The value of ``key`` in ``values`` moved by a tiny amount (the last digits differ)."""
    if key == INTRINSICS_KEY:
        return values.atVector(key) * (1.0 + scale)
    if gtsam.Symbol(key).chr() == ord("x"):
        return values.atPose3(key).retract(scale * rng.normal(size=6))
    return values.atPoint3(key) + scale * rng.normal(size=3)


def _with(values, key, value):
    out = gtsam.Values(values)
    out.update(key, value)
    return out


def _check_linear(graph, problem, values):
    """Every block's JacobianFactor (through GTSAM's JacobianVector path) equals the
    same block evaluated alone, which the tests above check numerically."""
    lin = graph.linearize(values)
    for q, block in enumerate(problem.blocks):
        H = [None] * len(block.keys)
        e = _alone(block).evaluate(None, values, H)
        factor = lin.at(q)
        assert list(factor.keys()) == block.keys
        np.testing.assert_allclose(factor.getA(), np.hstack(H), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(factor.getb(), -e, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("model", list(MODELS))
def test_shared_blocks_match_blocks_alone(model):
    problem, values = _scene(model)
    graph = problem.build()
    # tiles: every observation in exactly one block; control in per-image blocks
    idx = np.sort(np.concatenate(problem.block_obs))
    np.testing.assert_array_equal(idx, np.arange(len(problem.uv_px)))
    for block, obs in zip(problem.blocks, problem.block_obs):
        assert len(block.point_keys) <= problem.points_per_factor
        assert len(block.pose_keys) <= IMAGES_PER_FACTOR
        if not block.point_keys:
            assert problem.fixed[problem.obs_target[obs]].all()
            assert len(block.pose_keys) == 1
    _check_linear(graph, problem, values)
    rho = sum(0.5 * np.sum(_alone(b).evaluate(None, values, None) ** 2) for b in problem.blocks)
    n_blocks = len(problem.blocks)
    cost = sum(graph.at(q).error(values) for q in range(n_blocks))
    np.testing.assert_allclose(cost, rho, rtol=1e-12)
    np.testing.assert_allclose(
        np.vstack([b.residuals_px(values) for b in problem.blocks]),
        np.vstack([_alone(b).residuals_px(values) for b in problem.blocks]),
        rtol=1e-12,
        atol=1e-9,
    )


def test_shared_block_jacobians_match_numerical():
    """A multi-observation block (several targets and images) of a shared set."""
    problem, values = _scene("radial4+p1p2a1a2")
    problem.build()
    block = max(problem.blocks, key=lambda b: len(b.point_keys) * len(b.pose_keys))
    assert len(block.point_keys) > 1 and len(block.pose_keys) > 1
    H = [None] * len(block.keys)
    block.evaluate(None, values, H)
    e = block.residuals_px(values)
    r = np.linalg.norm(e, axis=1) / block.noise.sigma_px
    scale = np.repeat(np.sqrt(np.minimum(1.0, block.noise.loss_threshold / r)), 2)
    scale /= block.noise.sigma_px

    def err(key):
        def f(x):
            v = gtsam.Values(values)
            v.update(key, x)
            return block.residuals_px(v).ravel()

        return f

    getters = {"l": values.atPoint3, "x": values.atPose3, "k": values.atVector}
    for q, key in enumerate(block.keys):
        x = getters[chr(gtsam.Symbol(key).chr())](key)
        numeric = numericalDerivative11(err(key), x, delta=1e-6) * scale[:, None]
        np.testing.assert_allclose(H[q], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def test_stored_evaluation_is_never_stale():
    """Blocks called in any order with Values that differ in one key (by the last
    digits), a Values object reused after an in-place update, and values missing
    keys of other blocks: every answer is the block's own at the Values it gets."""
    rng = np.random.default_rng(5)
    problem, values = _scene("brown-all")
    graph = problem.build()
    blocks = problem.blocks
    keys = [pose_key(2), point_key(int(problem.free_targets[3])), INTRINSICS_KEY]
    states = [values] + [_with(values, k, _nudged(values, k, rng)) for k in keys]
    for _ in range(3 * len(blocks)):
        block = blocks[rng.integers(len(blocks))]
        v = states[rng.integers(len(states))]
        jacobians = bool(rng.integers(2))
        H = [None] * len(block.keys) if jacobians else None
        H_alone = [None] * len(block.keys) if jacobians else None
        np.testing.assert_array_equal(
            block.evaluate(None, v, H), _alone(block).evaluate(None, v, H_alone)
        )
        if jacobians:
            for a, b in zip(H, H_alone):
                np.testing.assert_array_equal(a, b)
    # the same Values object, updated in place (its C++ memory is reused)
    v = gtsam.Values(values)
    _check_linear(graph, problem, v)
    for key in keys:
        v.update(key, _nudged(v, key, rng))
        _check_linear(graph, problem, v)
    # only the block's own keys: evaluated alone
    block = next(b for b in blocks if b.point_keys)
    own = values.extract(block.keys)
    H = [None] * len(block.keys)
    H_alone = [None] * len(block.keys)
    np.testing.assert_array_equal(
        block.evaluate(None, own, H), _alone(block).evaluate(None, values, H_alone)
    )


def test_non_finite_values_are_not_stored():
    problem, values = _scene()
    graph = problem.build()
    bad = gtsam.Values(values)
    t = int(problem.free_targets[0])
    bad.update(point_key(t), np.array([np.nan, 0.0, 1.0]))
    lin = graph.linearize(bad)
    for q, block in enumerate(problem.blocks):
        b = lin.at(q).getb()
        if point_key(t) in block.keys:
            assert np.isnan(b).any()
        else:
            e = _alone(block).evaluate(None, bad, [None] * len(block.keys))
            np.testing.assert_array_equal(b, -e)
    _check_linear(graph, problem, values)
