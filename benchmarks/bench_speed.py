"""Calibration speed: end-to-end ``calibrate`` next to a C++ bundle adjustment (issue 14).

Not a test: prints a table, one run per row. For each dataset:

- ``ours``: the default calibration end to end (initialisation, robust stages, term
  selection, kNN rounds), wall time and its parts (initialisation / the rest), and the
  process CPU time of each (the steadier figure on a shared machine);
- ``C++``: GTSAM's ``GeneralSFMFactor2Cal3Fisheye`` bundle adjustment (one C++
  factor per observation, Huber k = 1.345 on a 1 px sigma, intrinsics
  ``Cal3Fisheye(f, f, 0, cx, cy, k1..k4)`` free, a ``PriorFactorPoint3`` per target
  with the sigma our run used) from the SAME initial values (our initialisation's
  poses, principal point and focal length), GTSAM's Levenberg-Marquardt with its
  default tolerances. ``Cal3Fisheye`` projects through ``x / z``: observations at 89
  degrees of incidence or more are left out of the C++ graph (counted).

Datasets: the GoPro-like room (simulated, 52 images, ~6,000 observations) and
``../shared/data/opencv_fisheye_left.dataset.json`` (skipped with a message when the
shared data are absent).

    python benchmarks/bench_speed.py [--only gopro,opencv_fisheye_left]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gtsam
import numpy as np

from gtsam_sphere.estimation.calibrate import (
    CalibrationOptions,
    calibrate,
    initialise,
    resolve_control_sigma,
)
from gtsam_sphere.io.dataset import load_dataset, parse_dataset
from gtsam_sphere.simulate import gopro_like, simulate_room

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _datasets(only: set[str]):
    if "gopro" in only:
        yield "gopro", parse_dataset(simulate_room(gopro_like(seed=0)).dataset)
    path = SHARED / "opencv_fisheye_left.dataset.json"
    if "opencv_fisheye_left" in only:
        if path.exists():
            yield "opencv_fisheye_left", load_dataset(path)
        else:
            print(f"skipping opencv_fisheye_left: {path} not found (the shared data)")


def cpp_bundle(dataset, init, target_sigma: np.ndarray) -> dict:
    """GeneralSFMFactor2Cal3Fisheye bundle adjustment from ``init``; timings and RMS."""
    X = gtsam.symbol_shorthand.X
    L = gtsam.symbol_shorthand.L
    K = gtsam.symbol_shorthand.K
    R, t = init.cam_from_world_R, init.cam_from_world_t
    d = init.dataset
    pc = np.einsum("nij,nj->ni", R[d.obs_image], d.target_xyz[d.obs_target]) + t[d.obs_image]
    inc = np.degrees(np.arctan2(np.hypot(pc[:, 0], pc[:, 1]), pc[:, 2]))
    keep = inc < 89.0
    huber = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    )
    graph = gtsam.NonlinearFactorGraph()
    for n in np.flatnonzero(keep):
        i, j = int(d.obs_image[n]), int(d.obs_target[n])
        uv = gtsam.Point2(*d.uv_px[n])
        graph.add(gtsam.GeneralSFMFactor2Cal3Fisheye(uv, huber, X(i), L(j), K(0)))
    values = gtsam.Values()
    for i in range(len(d.image_ids)):
        values.insert(X(i), gtsam.Pose3(gtsam.Rot3(R[i]), gtsam.Point3(*t[i])).inverse())
    for j in np.unique(d.obs_target[keep]):
        s = float(target_sigma[j]) if np.isfinite(target_sigma[j]) and target_sigma[j] > 0 else 1.0
        graph.add(
            gtsam.PriorFactorPoint3(
                L(int(j)), gtsam.Point3(*d.target_xyz[j]), gtsam.noiseModel.Isotropic.Sigma(3, s)
            )
        )
        values.insert(L(int(j)), gtsam.Point3(*d.target_xyz[j]))
    pp = init.principal_point_px
    values.insert(K(0), gtsam.Cal3Fisheye(init.f_px, init.f_px, 0.0, pp[0], pp[1], 0, 0, 0, 0))
    params = gtsam.LevenbergMarquardtParams()
    t0, c0 = time.perf_counter(), time.process_time()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    res = []
    for n in np.flatnonzero(keep):
        cam = gtsam.PinholeCameraCal3Fisheye(
            result.atPose3(X(int(d.obs_image[n]))), result.atCal3Fisheye(K(0))
        )
        try:
            res.append(cam.project(result.atPoint3(L(int(d.obs_target[n])))) - d.uv_px[n])
        except RuntimeError:
            continue
    res = np.asarray(res)
    return {
        "time_s": dt,
        "cpu_s": cpu,
        "iterations": opt.iterations(),
        "rms_px": float(np.sqrt((res**2).sum(1).mean())),
        "left_out": int((~keep).sum()),
        "n_obs": int(keep.sum()),
    }


def main(argv: list[str] | None = None) -> int:
    """Print the speed table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="gopro,opencv_fisheye_left")
    args = ap.parse_args(argv)
    rows = []
    for name, dataset in _datasets(set(args.only.split(","))):
        options = CalibrationOptions(seed=0)
        t0, c0 = time.perf_counter(), time.process_time()
        init = initialise(dataset, 0)
        t_init, c_init = time.perf_counter() - t0, time.process_time() - c0
        calib = calibrate(dataset, options, init=init)
        t_all, c_all = time.perf_counter() - t0, time.process_time() - c0
        sigma = dataset.target_sigma.copy()
        auto = resolve_control_sigma(dataset, options.control_sigma)
        if auto is not None:
            sigma[sigma == 0] = auto
        cpp = cpp_bundle(dataset, init, sigma)
        cpu = (c_init, c_all)
        rows.append(
            (name, dataset.n_observations, t_init, t_all, cpu, calib.statistics["rms_px"], cpp)
        )
        print(f"{name}: ours {t_all:.1f} s, C++ {cpp['time_s']:.2f} s", flush=True)
    # process CPU time too: on a shared machine the wall clock also counts the others' work
    print(
        "\n| dataset | observations | ours: init s | ours: total s | ours CPU s: init / rest "
        "/ total | ours RMS px | C++ BA s | C++ CPU s | C++ iterations | C++ RMS px "
        "| C++ left out (>= 89 deg) | ours / C++ (wall) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, n, t_init, t_all, (c_init, c_all), rms, cpp in rows:
        print(
            f"| {name} | {n} | {t_init:.1f} | {t_all:.1f} "
            f"| {c_init:.1f} / {c_all - c_init:.1f} / {c_all:.1f} | {rms:.3f} "
            f"| {cpp['time_s']:.2f} | {cpp['cpu_s']:.2f} "
            f"| {cpp['iterations']} | {cpp['rms_px']:.3f} | {cpp['left_out']} "
            f"| {t_all / cpp['time_s']:.1f}x |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
