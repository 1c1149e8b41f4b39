"""Shared fixtures: simulated rooms with known truth, and the real data folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_data_file(name: str) -> Path:
    """Path of a file in ``../shared/data``; skips the test with a message if absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"real data not available: {path} is absent (see ../shared/data/README.md)")
    return path


def benchmark_module(name: str):
    """``benchmarks/<name>.py`` imported as module ``name`` (once: registered in
    ``sys.modules``, where its dataclasses look their module up)."""
    import importlib.util
    import sys

    if name in sys.modules:
        return sys.modules[name]
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def stress_case(seed: int, prefix: str):
    """The lens zoo's stress case ``prefix`` (e.g. ``"s07-"``) of
    ``bench_lens_zoo.py --stress 40 --seed SEED --targets --defects --shapes``."""
    zoo = benchmark_module("bench_lens_zoo")
    cases = zoo.build_stress_cases(seed, 40, defects=True, targets=True, shapes=True)
    return next(c for c in cases if c.id.startswith(prefix))


def dataset_doc(targets, images, width=640, height=480):
    """A ``dataset@1`` document (metres) of ``targets`` and ``images`` (lists of dicts)."""
    return {
        "format": "gtsam-sphere/dataset@1",
        "units": "m",
        "camera": {"width": width, "height": height},
        "targets": targets,
        "images": images,
    }


def checkpoints_of(sim):
    """Check point ids and coordinates (K, 3) of a simulation."""
    ids = [t["id"] for t in sim.checkpoints["targets"]]
    xyz = np.array([t["xyz"] for t in sim.checkpoints["targets"]])
    return ids, xyz


def bare_calibration(camera, uv_px=None):
    """A Calibration holding only ``camera`` (and, optionally, observed pixels (N, 2))."""
    from gtsam_sphere.io.calibration import Calibration

    extra = {}
    if uv_px is not None:
        extra["observations"] = {"uv_px": uv_px, "residual_px": np.zeros_like(uv_px)}
    return Calibration(
        model="brown",
        camera=camera,
        image_ids=[],
        cam_from_world_R=np.zeros((0, 3, 3)),
        cam_from_world_t=np.zeros((0, 3)),
        target_ids=[],
        target_xyz=np.zeros((0, 3)),
        statistics={
            "rms_px": 0.1,
            "n_observations": 0 if uv_px is None else len(uv_px),
            "n_rejected": 0,
        },
        extra=extra,
    )


def scene_pose(scene, i):
    """``world_from_cam`` of image ``i`` of a simulated building scene, as a ``gtsam.Pose3``."""
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(scene.world_from_cam_R[i]), scene.world_from_cam_t[i])


def perturbed_values(scene, seed, rot=0.01, trans=0.05, pts=0.08):
    """``gtsam.Values`` of a building scene's poses and landmarks, perturbed (seeded): poses by
    ``rot`` rad / ``trans`` m (``perturb_poses``), landmarks by ``pts`` m per coordinate."""
    import gtsam

    from gtsam_sphere.estimation.graph import point_key, pose_key
    from gtsam_sphere.simulate.building import perturb_poses

    rng = np.random.default_rng(seed)
    R, t = perturb_poses(scene.world_from_cam_R, scene.world_from_cam_t, rot, trans, rng)
    P = scene.points_world + rng.normal(scale=pts, size=scene.points_world.shape)
    values = gtsam.Values()
    for i in range(scene.n_images):
        values.insert(pose_key(i), gtsam.Pose3(gtsam.Rot3(R[i]), t[i]))
    for j in range(scene.n_points):
        values.insert(point_key(j), P[j])
    return values


def bare_rig_calibration(cameras, cam_from_rig, model="radial", units="m", rms_px=0.3):
    """A ``RigCalibration`` holding only its cameras (id -> SphereCamera) and their
    ``cam_from_rig`` (id -> (R (3, 3), t (3,))): no frames, images or targets."""
    from gtsam_sphere.io.calibration import RigCalibration

    ids = list(cameras)
    stats = {"rms_px": rms_px, "n_observations": 0, "n_rejected": 0}
    return RigCalibration(
        camera_ids=ids,
        cameras=dict(cameras),
        models=dict.fromkeys(ids, model),
        cam_from_rig=dict(cam_from_rig),
        frame_ids=[],
        rig_from_world_R=np.zeros((0, 3, 3)),
        rig_from_world_t=np.zeros((0, 3)),
        image_ids=[],
        image_camera=[],
        image_frame=[],
        cam_from_world_R=np.zeros((0, 3, 3)),
        cam_from_world_t=np.zeros((0, 3)),
        target_ids=[],
        target_xyz=np.zeros((0, 3)),
        statistics={**stats, "cameras": {c: dict(stats) for c in ids}},
        units=units,
    )


def initialise_simulation(sim):
    """``initialize_poses`` of a simulated room's dataset, lens unknown, as
    ``calibrate`` runs it; returns (parsed dataset, result, progress lines)."""
    from gtsam_sphere.estimation.initialize import initialize_poses
    from gtsam_sphere.io.dataset import parse_dataset

    data = parse_dataset(sim.dataset)
    messages: list[str] = []
    res = initialize_poses(
        data.uv_px,
        data.obs_image,
        data.obs_target,
        data.target_xyz,
        data.width,
        data.height,
        len(data.image_ids),
        progress=messages.append,
    )
    return data, res, messages


def small_free_room(seed=21, **overrides):
    """A free room (no target sigma) of 10 images, 150 targets, 150 deg equidistant lens
    on 1024x768, 0.3 px: the end-to-end case of the target-reliability tests.
    ``overrides``: other ``SimulationOptions`` (e.g. ``sigma_mode=None,
    target_sigma_m=0.01`` for the room surveyed to 1 cm)."""
    from gtsam_sphere.simulate import SimulationOptions, simulate_room

    options = dict(
        lens="equidistant",
        fov_deg=150,
        noise_px=0.3,
        n_images=10,
        n_targets=150,
        n_checkpoints=10,
        width=1024,
        height=768,
        sigma_mode="free",
        seed=seed,
    )
    return simulate_room(SimulationOptions(**{**options, **overrides}))


def summary_statistics(**extra):
    """The statistics ``cli.common.print_statistics`` needs (a weak 5-image geometry),
    with ``extra`` keys added."""
    return {
        "rms_px": 0.5,
        "rms_px_without_outliers": 0.45,
        "n_observations": 120,
        "n_rejected": 0,
        "n_images": 5,
        "n_images_skipped": 0,
        "n_downweighted": 5,
        "n_outliers": 4,
        "sigma_px": 0.53,
        "weighted_sum_squares": 76.2,
        "redundancy": 48,
        "variance_factor": 1.59,
        "max_incidence_deg": 38.9,
        "status": "converged",
        "iterations": 163,
        **extra,
    }


def three_view_problem(gross: dict, sigma: dict | None = None, noise_px=0.5):
    """A free network: 3 images (world_from_cam translations along x) of 40 targets on
    a sphere camera (c 300 px), each target seen in the images of ``gross``'s key or in
    all three; ``gross`` maps target -> images whose observation is moved 200 px;
    ``sigma`` target -> its sigma (m). Returns (problem built, values at the truth)."""
    import gtsam

    from gtsam_sphere.core.camera import SphereCamera
    from gtsam_sphere.estimation.graph import (
        INTRINSICS_KEY,
        BundleProblem,
        NoiseOptions,
        point_key,
        pose_key,
    )

    rng = np.random.default_rng(11)
    cam = SphereCamera(width=1000, height=800, xp=500.0, yp=400.0, c=300.0)
    xyz = np.c_[rng.uniform(-3, 3, (40, 2)), rng.uniform(4, 6, 40)]
    xyz[:3] = [[0.1, 0.2, 5.0], [-0.2, 0.1, 5.1], [0.0, -0.1, 4.9]]  # inside the cloud
    centres = np.array([[-0.5, 0, 0], [0, 0, 0], [0.5, 0, 0.0]])
    obs_image, obs_target, uv = [], [], []
    for t in range(40):
        for i in range(3):
            if t in gross and i not in gross[t][0]:
                continue
            obs_image.append(i)
            obs_target.append(t)
            p = cam.project((xyz[t] - centres[i])[None])[0]
            if t in gross and i in gross[t][1]:
                p = p + [200.0, 0.0]
            uv.append(p)
    target_sigma = np.full(40, np.nan)
    for t, s in (sigma or {}).items():
        target_sigma[t] = s
    problem = BundleProblem(
        obs_image=np.array(obs_image),
        obs_target=np.array(obs_target),
        uv_px=np.array(uv) + rng.normal(0, 0.01, (len(uv), 2)),
        target_xyz=xyz,
        target_sigma=target_sigma,
        n_images=3,
        noise=NoiseOptions(noise_px),
    )
    values = gtsam.Values()
    for i in range(3):
        values.insert(pose_key(i), gtsam.Pose3(gtsam.Rot3(), centres[i]))
    for t in problem.free_targets:
        values.insert(point_key(int(t)), xyz[t])
    values.insert(INTRINSICS_KEY, np.array([500.0, 400.0, 300.0]))
    problem.build()
    return problem, values
