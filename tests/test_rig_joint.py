"""Joint rig adjustment: composed-pose observation blocks (Jacobians vs numerical
derivatives on the manifold) and the joint stage on a simulated rig."""

from __future__ import annotations

from dataclasses import replace

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


# -- the joint stage on a rig simulated with the package's own camera models ----------


def _rot(axis, deg):
    a = np.asarray(axis, float)
    return gtsam.Rot3.AxisAngle(gtsam.Point3(*(a / np.linalg.norm(a))), np.radians(deg)).matrix()


TRUE_CAM1_FROM_RIG = (_rot([0.2, 1.0, 0.1], 8.0), np.array([-0.16, 0.01, 0.005]))


def _in_model_rig(seed=0, n_frames=12, noise_px=0.3, n_surveyed=12):
    """Two cameras of the package's own models (truth exactly representable) on a rig,
    targets around them (12 surveyed at 5 mm, the rest approximate only), one unframed
    image of camera 0. Returns (rig dataset, truth dict, per-camera start Calibrations,
    start cam_from_rig, rig_from_world, target xyz): the start is the truth perturbed
    as a per-camera stage leaves it (0.05 deg, 1 mm, a few px of intrinsics)."""
    from gtsam_sphere.core.camera import SphereCamera
    from gtsam_sphere.io.calibration import Calibration
    from gtsam_sphere.io.dataset import parse_rig_dataset

    rng = np.random.default_rng(seed)
    cams = {
        "cam0": SphereCamera(
            1000,
            1000,
            500.3,
            498.7,
            318.0,
            brown={"p1": 2e-4, "p2": -1e-4},
            radial={"g3": -0.02, "g5": 0.003},
        ),
        "cam1": SphereCamera(900, 900, 451.2, 447.9, 290.0, radial={"g3": 0.01}),
    }
    ext = {"cam0": (np.eye(3), np.zeros(3)), "cam1": TRUE_CAM1_FROM_RIG}
    n_t = 160
    d = rng.normal(size=(n_t, 3))
    xyz = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.5, 4.0, (n_t, 1))
    frames = {}
    for k in range(n_frames):
        R = _rot(rng.normal(size=3), rng.uniform(0, 60))
        frames[f"{k:02d}"] = (R, -R @ rng.uniform(-0.8, 0.8, 3))
    shots = [
        (f"{cid}_{f}", cid, f, ext[cid][0] @ R, ext[cid][0] @ t + ext[cid][1])
        for f, (R, t) in frames.items()
        for cid in cams
    ]
    R_own = _rot([1, 0, 0], 30.0)
    shots.append(("cam0_own", "cam0", None, R_own, np.array([0.2, -0.1, 0.3])))
    images = []
    for iid, cid, f, R, t in shots:
        pc = xyz @ R.T + t
        alpha = np.degrees(np.arccos(pc[:, 2] / np.linalg.norm(pc, axis=1)))
        uv = cams[cid].project(pc)
        ok = (alpha < 100.0) & np.isfinite(uv).all(axis=1)
        w = cams[cid].width
        ok[ok] &= ((uv[ok] > 2.0) & (uv[ok] < w - 3.0)).all(axis=1)
        uv = uv + rng.normal(0.0, noise_px, uv.shape)
        im = {
            "id": iid,
            "camera": cid,
            "observations": [
                {"target": f"T{j:03d}", "uv": uv[j].tolist()} for j in np.flatnonzero(ok)
            ],
        }
        if f is not None:
            im["frame"] = f
        images.append(im)
    approx = xyz + rng.normal(0.0, 0.02, xyz.shape)
    targets = [{"id": f"T{j:03d}", "xyz": approx[j].tolist()} for j in range(n_t)]
    for j in range(n_surveyed):
        p = xyz[j] + rng.normal(0.0, 0.005, 3)
        targets[j] = {"id": f"T{j:03d}", "xyz": p.tolist(), "sigma": 0.005}
    doc = {
        "format": "gtsam-sphere/dataset@2",
        "units": "m",
        "cameras": [{"id": c, "width": cams[c].width, "height": cams[c].height} for c in cams],
        "targets": targets,
        "images": images,
    }
    rig = parse_rig_dataset(doc)

    def nudge(pose, deg=0.05, m=0.001):
        R = _rot(rng.normal(size=3), deg) @ pose[0]
        return R, pose[1] + rng.normal(0.0, m / np.sqrt(3), 3)

    calibs = {}
    by_id = {im["id"]: im for im in images}
    for cid, cam in cams.items():
        mine = [s for s in shots if s[1] == cid]
        obs = [(s[0], o["target"], o["uv"]) for s in mine for o in by_id[s[0]]["observations"]]
        start = replace(
            cam, xp=cam.xp + 0.8, yp=cam.yp - 0.5, c=cam.c * 1.002, radial=dict(cam.radial)
        )
        poses = [nudge((s[3], s[4])) for s in mine]
        calibs[cid] = Calibration(
            model="radial",
            camera=start,
            image_ids=[s[0] for s in mine],
            cam_from_world_R=np.array([p[0] for p in poses]),
            cam_from_world_t=np.array([p[1] for p in poses]),
            target_ids=[t["id"] for t in targets],
            target_xyz=approx,
            statistics={"sigma_px": noise_px},
            extra={
                "observations": {
                    "image": [o[0] for o in obs],
                    "target": [o[1] for o in obs],
                    "uv_px": np.array([o[2] for o in obs]),
                }
            },
        )
    start_ext = {"cam0": ext["cam0"], "cam1": nudge(ext["cam1"], 0.1, 0.005)}
    start_frames = {f: nudge(p) for f, p in frames.items()}
    start_xyz = {f"T{j:03d}": xyz[j] + rng.normal(0.0, 0.002, 3) for j in range(n_t)}
    truth = {"cameras": cams, "cam_from_rig": ext, "frames": frames, "xyz": xyz}
    return rig, truth, calibs, start_ext, start_frames, start_xyz


def _extrinsic_error(R, t, truth):
    """Rotation error (rad, camera axes: R = exp(phi) R_true) and translation error."""
    phi = gtsam.Rot3.Logmap(gtsam.Rot3(R @ truth[0].T))
    return np.asarray(phi), t - truth[1]


@pytest.mark.parametrize("seed", [0, 1])
def test_joint_stage_recovers_in_model_rig(seed):
    from gtsam_sphere.estimation.rig_joint import adjust_rig_jointly, precision_from_covariance

    rig, truth, calibs, ext0, frames0, xyz0 = _in_model_rig(seed)
    jr = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    assert jr.result.converged and jr.datum == "control"
    assert np.allclose(jr.cam_from_rig["cam0"][0], np.eye(3))
    phi0, dt0 = _extrinsic_error(*ext0["cam1"], TRUE_CAM1_FROM_RIG)
    phi, dt = _extrinsic_error(*jr.cam_from_rig["cam1"], TRUE_CAM1_FROM_RIG)
    cov = jr.cam_from_rig_covariance["cam1"]
    sigma = np.sqrt(np.diag(cov))
    # the error is consistent with the reported precision, and far below the start's
    assert np.all(np.abs(phi) < 3.0 * sigma[:3]), (np.degrees(phi), np.degrees(sigma[:3]))
    assert np.all(np.abs(dt) < 3.0 * sigma[3:]), (dt, sigma[3:])
    assert np.linalg.norm(phi) < 0.5 * np.linalg.norm(phi0)
    assert np.linalg.norm(dt) < 0.5 * np.linalg.norm(dt0)
    pr = precision_from_covariance(cov, jr.cam_from_rig["cam1"][1])
    assert pr["rotation_sigma_deg"] == pytest.approx(np.degrees(np.linalg.norm(sigma[:3])))
    assert 0 < pr["baseline_sigma"] < np.linalg.norm(sigma[3:])
    # noise 0.3 px per axis: the raw residuals' RMS near 0.3 sqrt(2)
    for cid in rig.camera_ids:
        r = jr.residuals_px[cid]
        used = np.isfinite(r).all(axis=1)  # targets seen in one image only: left out
        assert np.array_equal(used, jr.weights[cid] > 0) and used.mean() > 0.9
        rms = np.sqrt(np.mean(np.sum(r[used] ** 2, axis=1)))
        assert 0.35 < rms < 0.5 and 0.25 < jr.sigma_px[cid] < 0.35
        cam, true = jr.cameras[cid], truth["cameras"][cid]
        assert abs(cam.c - true.c) < 0.3 and abs(cam.xp - true.xp) < 0.3
    assert 0.8 < jr.variance_factor < 1.2
    # every framed image's pose is cam_from_rig * rig_from_world; the unframed one its own
    for iid, (R, t) in jr.cam_from_world.items():
        cid, _, f = iid.partition("_")
        if f == "own":
            R_true, t_true = _rot([1, 0, 0], 30.0), np.array([0.2, -0.1, 0.3])
            assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R @ R_true.T)))) < 0.3
            assert np.linalg.norm(t - t_true) < 0.01
            continue
        Rr, tr = jr.rig_from_world[f]
        Rc, tc = jr.cam_from_rig[cid]
        assert np.allclose(R, Rc @ Rr, atol=1e-12) and np.allclose(t, Rc @ tr + tc, atol=1e-12)


# -- end to end: the simulator's rig, per-camera calibrations, averaged vs joint -------


@pytest.mark.slow
def test_joint_stage_on_simulated_rig_improves_on_the_averaged_extrinsics():
    """The simulator's stereo rig (lenses outside the package's models): per-camera
    calibrations, then the averaged extrinsics (joint=False) and the joint adjustment.
    The joint error is no larger than the averaged one and within 3 reported sigma."""
    from test_rig import rotation, rotation_vector, simulate_rig

    from gtsam_sphere.core.camera import Model
    from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate
    from gtsam_sphere.estimation.rig import RIG_ADJUSTMENT, RIG_ADJUSTMENT_AVERAGED, assemble_rig
    from gtsam_sphere.io.dataset import parse_rig_dataset, split_rig

    truth = (rotation([0.2, 1.0, 0.1], 8.0), np.array([-0.16, 0.01, 0.005]))
    rig = parse_rig_dataset(simulate_rig(truth, seed=0))
    opts = CalibrationOptions(model=Model.RADIAL)
    calibs = {cid: calibrate(ds, opts) for cid, ds in split_rig(rig).items()}
    per_camera = dict.fromkeys(rig.camera_ids, opts)
    errors = {}
    for joint in (False, True):
        calib = assemble_rig(rig, calibs, per_camera, lambda _line: None, joint)
        R, t = calib.cam_from_rig["cam1"]
        errors[joint] = (rotation_vector(R @ truth[0].T), t - truth[1])
        st = calib.statistics
        assert st["rig_adjustment"] == (RIG_ADJUSTMENT if joint else RIG_ADJUSTMENT_AVERAGED)
    (phi0, dt0), (phi, dt) = errors[False], errors[True]
    assert np.linalg.norm(phi) <= np.linalg.norm(phi0)
    assert np.linalg.norm(dt) <= np.linalg.norm(dt0)
    pr = st["cameras"]["cam1"]["cam_from_rig_precision"]
    assert np.all(np.abs(phi) < 3.0 * np.radians(pr["rotation_sigma_deg_axes"]))
    assert np.all(np.abs(dt) < 3.0 * pr["translation_sigma"])
    # the spread's standard error is kept beside the joint sigma
    assert pr["rotation_sigma_deg_spread"] > 0 and len(pr["translation_sigma_spread"]) == 3
    assert st["trusted"] and st["joint"]["converged"]
    for cid in rig.camera_ids:
        assert st["cameras"][cid]["rms_px_rig"] < 0.45  # noise 0.3 px per axis


def test_joint_stage_free_network():
    """No target has a sigma: minimal constraints, then the S-transform onto the
    approximate coordinates (as a single camera's free network)."""
    from gtsam_sphere.estimation.rig_joint import adjust_rig_jointly

    rig, truth, calibs, ext0, frames0, xyz0 = _in_model_rig(0, n_surveyed=0)
    jr = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    assert jr.result.converged and jr.datum == "free"
    phi, dt = _extrinsic_error(*jr.cam_from_rig["cam1"], TRUE_CAM1_FROM_RIG)
    # the datum (2 cm approximations of 160 targets) sets the scale to a few 1e-4
    assert np.degrees(np.linalg.norm(phi)) < 0.05 and np.linalg.norm(dt) < 0.002
    assert jr.cam_from_rig_covariance["cam1"] is not None
    for iid, (R, t) in jr.cam_from_world.items():
        cid, _, f = iid.partition("_")
        if f != "own":
            Rr, tr = jr.rig_from_world[f]
            Rc, tc = jr.cam_from_rig[cid]
            assert np.allclose(R, Rc @ Rr, atol=1e-12) and np.allclose(t, Rc @ tr + tc, atol=1e-12)
