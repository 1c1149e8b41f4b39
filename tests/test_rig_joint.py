"""Joint rig adjustment: composed-pose observation blocks (Jacobians vs numerical
derivatives on the manifold) and the joint stage on a simulated rig."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11, numericalDerivative21

from gtsam_sphere.core.camera import RADIAL_TERMS
from gtsam_sphere.estimation.graph import (
    BundleProblem,
    Loss,
    NoiseOptions,
    ObservationBlock,
    extrinsics_key,
    frame_key,
    intrinsics_key,
    point_key,
    pose_key,
)


def _pose(rng, scale=1.0):
    R = gtsam.Rot3.Rodrigues(*(0.8 * rng.normal(size=3)))
    return gtsam.Pose3(R, gtsam.Point3(*(scale * rng.normal(size=3))))


def test_compose_jacobians_are_gtsam_right_perturbation():
    """For c = a.compose(b): dc/da = Ad(b^-1), dc/db = I (the chain the blocks use)."""
    rng = np.random.default_rng(0)
    a, b = _pose(rng), _pose(rng)

    def f(x, y):
        return x.compose(y)

    da = numericalDerivative21(f, a, b, delta=1e-6)
    np.testing.assert_allclose(da, b.inverse().AdjointMap(), atol=1e-7)
    from gtsam.utils.numerical_derivative import numericalDerivative22

    db = numericalDerivative22(f, a, b, delta=1e-6)
    np.testing.assert_allclose(db, np.eye(6), atol=1e-7)


def _rig_values(rng, radial_names, brown_names):
    """Values of a small rig graph: frames 0-2 (world_from_rig), camera 1's rig_from_cam,
    an unframed image pose, targets, camera 1's intrinsics."""
    values = gtsam.Values()
    for f in range(3):
        values.insert(frame_key(f), _pose(rng))
    values.insert(extrinsics_key(1), _pose(rng, 0.2))
    values.insert(pose_key(7), _pose(rng))
    for t in range(6):
        values.insert(point_key(t), 3.0 * rng.normal(size=3))
    radial = [] if radial_names is None else [-0.05, 0.01, -0.002, 0.001][: len(radial_names)]
    brown = 0.02 * rng.normal(size=len(brown_names))
    theta = np.concatenate([[640.2, 401.7, 350.0], radial, brown])
    values.insert(intrinsics_key(1), theta)
    return values


MODELS = {
    "sphere": ((), None),
    "radial4+p1p2a1a2": (("p1", "p2", "a1", "a2"), RADIAL_TERMS[:4]),
}


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("loss", [Loss.L2, Loss.HUBER])
def test_composed_block_jacobians_match_numerical(model, loss):
    """One block mixing composed observations (frames x rig_from_cam), an unframed
    image's own pose, free and exact targets: every key's Jacobian block."""
    brown_names, radial_names = MODELS[model]
    rng = np.random.default_rng(3)
    values = _rig_values(rng, radial_names, brown_names)
    pose_keys = [frame_key(0), frame_key(1), frame_key(2), pose_key(7)]
    # observations: (pose index, point index or -1, composed?)
    obs = [(0, 0, 1), (0, 1, 1), (1, 2, 1), (1, -1, 1), (2, 3, 1), (2, 0, 0), (3, 4, 0)]
    obs += [(3, -1, 0), (1, 5, 1), (2, 5, 1)]
    pose_local = np.array([o[0] for o in obs])
    point_local = np.array([o[1] for o in obs])
    ext_local = np.array([0 if o[2] else -1 for o in obs])
    fixed = rng.normal(size=(len(obs), 3)) * 3.0
    uv = 640.0 + rng.normal(0.0, 150.0, (len(obs), 2))
    noise = NoiseOptions(sigma_px=2.0, loss=loss, loss_threshold=1.5)
    block = ObservationBlock(
        pose_keys,
        [point_key(t) for t in range(6)],
        pose_local,
        point_local,
        fixed,
        uv,
        brown_names,
        500.0,
        noise,
        radial_names,
        [extrinsics_key(1)],
        ext_local,
        intrinsics_key(1),
    )
    assert block.keys[-2:] == [extrinsics_key(1), intrinsics_key(1)]
    H = [None] * len(block.keys)
    block.evaluate(None, values, H)
    e = block.residuals_px(values)
    # residuals against the poses composed by GTSAM itself
    pc, _, _ = block.state(values)
    for n, (i, j, c) in enumerate(obs):
        wc = values.atPose3(pose_keys[i])
        if c:
            wc = wc.compose(values.atPose3(extrinsics_key(1)))
        p = values.atPoint3(point_key(j)) if j >= 0 else fixed[n]
        np.testing.assert_allclose(pc[n], wc.transformTo(p), atol=1e-12)
    r = np.linalg.norm(e, axis=1) / noise.sigma_px
    w = np.ones_like(r) if loss is Loss.L2 else np.minimum(1.0, noise.loss_threshold / r)
    scale = np.repeat(np.sqrt(w), 2) / noise.sigma_px

    def err(key):
        def f(x):
            v = gtsam.Values(values)
            v.update(key, x)
            return block.residuals_px(v).ravel()

        return f

    getters = {"l": values.atPoint3, "f": values.atPose3, "e": values.atPose3}
    getters |= {"x": values.atPose3, "k": values.atVector}
    for q, key in enumerate(block.keys):
        x = getters[chr(gtsam.Symbol(key).chr())](key)
        numeric = numericalDerivative11(err(key), x, delta=1e-6) * scale[:, None]
        np.testing.assert_allclose(H[q], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
        assert H[q].flags.f_contiguous


def test_rig_problem_blocks_shared_match_alone():
    """A BundleProblem with frame and extrinsic keys: the shared, tiled evaluation's
    linearisation equals every block evaluated alone; numerical Jacobians of the
    largest block."""
    rng = np.random.default_rng(5)
    n_images, n_targets = 10, 30
    xyz = rng.uniform(-3.0, 3.0, (n_targets, 3))
    sigma = np.full(n_targets, np.nan)
    sigma[:4] = 0.0
    obs = [(i, t) for i in range(n_images) for t in range(n_targets) if rng.random() < 0.6]
    # images 0-7 in frames 0-7 seen through camera 1's rig_from_cam, 8-9 unframed
    image_pose = np.array([frame_key(i) for i in range(8)] + [pose_key(8), pose_key(9)])
    image_ext = np.array([extrinsics_key(1)] * 8 + [-1, -1])
    problem = BundleProblem(
        obs_image=np.array([o[0] for o in obs]),
        obs_target=np.array([o[1] for o in obs]),
        uv_px=640.0 + rng.normal(0.0, 200.0, (len(obs), 2)),
        target_xyz=xyz,
        target_sigma=sigma,
        n_images=n_images,
        brown_names=("p1", "p2"),
        brown_scale_px=500.0,
        noise=NoiseOptions(sigma_px=2.0, loss=Loss.HUBER, loss_threshold=1.5),
        points_per_factor=4,
        radial_names=RADIAL_TERMS[:2],
        image_pose_keys=image_pose,
        image_extrinsic_keys=image_ext,
        intrinsics_key=intrinsics_key(1),
    )
    values = gtsam.Values()
    for k in image_pose:
        values.insert(int(k), _pose(rng))
    values.insert(extrinsics_key(1), _pose(rng, 0.2))
    for t in problem.free_targets:
        values.insert(point_key(int(t)), xyz[t])
    values.insert(intrinsics_key(1), np.array([640.0, 400.0, 300.0, -0.03, 0.01, 1e-3, -2e-3]))
    graph = problem.build()
    lin = graph.linearize(values)
    for q, block in enumerate(problem.blocks):
        alone = ObservationBlock(
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
            block.extrinsic_keys,
            block.extrinsic_local,
            block.intrinsics_key,
        )
        H = [None] * len(block.keys)
        e = alone.evaluate(None, values, H)
        factor = lin.at(q)
        assert list(factor.keys()) == block.keys
        np.testing.assert_allclose(factor.getA(), np.hstack(H), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(factor.getb(), -e, rtol=1e-12, atol=1e-12)
    assert any(b.extrinsic_keys for b in problem.blocks)
    block = max(problem.blocks, key=lambda b: len(b.point_keys) * len(b.pose_keys))
    H = [None] * len(block.keys)
    block.evaluate(None, values, H)
    r = np.linalg.norm(block.residuals_px(values), axis=1) / block.noise.sigma_px
    scale = np.repeat(np.sqrt(np.minimum(1.0, block.noise.loss_threshold / r)), 2) / 2.0
    for q, key in enumerate(block.keys):
        kind = chr(gtsam.Symbol(key).chr())
        get = {"l": values.atPoint3, "k": values.atVector}.get(kind, values.atPose3)

        def f(x, key=key):
            v = gtsam.Values(values)
            v.update(key, x)
            return block.residuals_px(v).ravel()

        numeric = numericalDerivative11(f, get(key), delta=1e-6) * scale[:, None]
        np.testing.assert_allclose(H[q], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
