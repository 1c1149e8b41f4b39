"""Offline map refinement with a calibrated fisheye inside your own GTSAM graph.

A short trajectory through a corridor of rooms (simulated, 190 degree fisheye)
is refined from a perturbed start twice: with the bearing path (pixels -> unit
rays through the calibration, GTSAM's C++ ``BearingFactor3D``) and with the
frozen pixel factors (``ProjectionBlocks``, exact pixel-space weighting).
Poses are GTSAM ``world_from_cam``; a prior on the first pose and odometry
between consecutive poses fix the gauge.

    python examples/map_refinement.py [--images 200] [--calibration CALIB.json]

With ``--calibration`` the lens of a ``calibration@1`` file is used (its
learned correction included); otherwise the simulator's lens.
"""

from __future__ import annotations

import argparse
import math
import time

import gtsam
import numpy as np

from gtsam_sphere import load_calibration
from gtsam_sphere.estimation.external import (
    ProjectionBlocks,
    levenberg_marquardt,
    make_bearing_factors,
)
from gtsam_sphere.estimation.graph import point_key, pose_key
from gtsam_sphere.simulate.building import perturb_poses, simulate_building


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=int, default=200)
    ap.add_argument("--calibration", default=None, help="a calibration@1 file (its camera)")
    args = ap.parse_args()
    camera = load_calibration(args.calibration).camera if args.calibration else None
    scene = simulate_building(n_images=args.images, obs_per_image=100, camera=camera, seed=1)
    print(
        f"{scene.n_images} images, {scene.n_points} landmarks, "
        f"{scene.n_observations} observations, {scene.camera.mapping} mapping"
    )
    rng = np.random.default_rng(2)
    R, t = perturb_poses(scene.world_from_cam_R, scene.world_from_cam_t, 0.005, 0.03, rng)
    P = scene.points_world + rng.normal(scale=0.05, size=scene.points_world.shape)
    initial = gtsam.Values()
    for i in range(scene.n_images):
        initial.insert(pose_key(i), gtsam.Pose3(gtsam.Rot3(R[i]), t[i]))
    for j in range(scene.n_points):
        initial.insert(point_key(j), P[j])

    truth = [
        gtsam.Pose3(gtsam.Rot3(scene.world_from_cam_R[i]), scene.world_from_cam_t[i])
        for i in range(scene.n_images)
    ]
    gauge = gtsam.NonlinearFactorGraph()
    gauge.add(
        gtsam.PriorFactorPose3(pose_key(0), truth[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3))
    )
    odometry = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[math.radians(0.1)] * 3, [0.01] * 3])
    for i in range(scene.n_images - 1):
        rel = truth[i].between(truth[i + 1])
        gauge.add(gtsam.BetweenFactorPose3(pose_key(i), pose_key(i + 1), rel, odometry))

    pose_keys = [pose_key(i) for i in scene.obs_image]
    point_keys = [point_key(j) for j in scene.obs_point]
    sigma_px = scene.options.noise_px
    huber = gtsam.noiseModel.mEstimator.Huber.Create(2.45)

    # bearing path: C++ factors, isotropic angular noise from the model's local scale
    graph = gtsam.NonlinearFactorGraph(gauge)
    for f in make_bearing_factors(
        scene.camera, scene.uv_px, pose_keys, point_keys, sigma_px, huber
    ):
        graph.add(f)
    t0 = time.perf_counter()
    bearing = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    report("bearing path (C++ BearingFactor3D)", scene, initial, bearing, time.perf_counter() - t0)

    # frozen pixel factors: exact pixel weighting, Python blocks, LM driven from Python
    noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, sigma_px))
    blocks = ProjectionBlocks(scene.camera, scene.uv_px, pose_keys, point_keys, noise)
    graph = gtsam.NonlinearFactorGraph(gauge)
    for f in blocks.factors():
        graph.add(f)
    t0 = time.perf_counter()
    pixel, info = levenberg_marquardt(graph, initial)
    report(
        "frozen pixel factors (ProjectionBlocks)", scene, initial, pixel, time.perf_counter() - t0
    )
    r = np.linalg.norm(blocks.residuals_px(pixel), axis=1)
    print(f"  pixel residuals: median {np.median(r):.3f} px, {info['iterations']} iterations")


def report(name, scene, initial, result, seconds) -> None:
    def rms(values):
        d = [
            np.linalg.norm(values.atPoint3(point_key(j)) - scene.points_world[j])
            for j in range(scene.n_points)
        ]
        return math.sqrt(np.mean(np.square(d)))

    print(f"{name}: {seconds:.2f} s, landmark RMS {rms(initial):.3f} m -> {rms(result):.3f} m")


if __name__ == "__main__":
    main()
