"""Benchmark: linearising our bundle graph versus GTSAM's built-in C++ factor.

Not a test: prints a table. The problem is a GoPro-sized room simulation
(52 images, 370 targets, about 6,000 observations) at the TRUE poses and
target coordinates; targets are free variables with weighted priors.

Rows:

- ``ours ppf=G``: :meth:`BundleProblem.build` with ``points_per_factor=G``
  (vectorised ``gtsam.CustomFactor`` blocks, Huber per observation);
- ``one CustomFactor per observation``: the same spherical residual, one
  single-observation :class:`ObservationBlock` per observation (the naive cost);
- ``built-in``: ``gtsam.GeneralSFMFactor2Cal3Fisheye`` per observation with
  ``Cal3Fisheye(f, f, 0, cx, cy, 0, 0, 0, 0)``, plain and Huber-robust (2.45).

Every graph also holds the same ``PriorFactorPoint3`` per target. Timings are
medians over repeats (after one warm-up) of ``graph.linearize(values)``, one
``LevenbergMarquardtOptimizer.iterate()`` from a slightly perturbed start and
``lin.eliminateMultifrontal(ordering)`` (targets, then poses, then intrinsics).

Usage::

    python benchmarks/bench_linearize.py            # 7 repeats (about a minute)
    python benchmarks/bench_linearize.py --quick    # 3 repeats
"""

from __future__ import annotations

import argparse
import importlib.metadata
import math
import os
import platform
import statistics
import sys
import time

import gtsam
import numpy as np

from gtsam_sphere.calibrate import initial_principal_distance, initial_values
from gtsam_sphere.dataset import parse_dataset
from gtsam_sphere.graph import (
    INTRINSICS_KEY,
    BundleProblem,
    NoiseOptions,
    ObservationBlock,
    point_key,
    pose_key,
)
from gtsam_sphere.optimize import make_ordering
from gtsam_sphere.simulate import gopro_like, simulate_room

CALIB_KEY = gtsam.symbol("K", 0)  # Cal3Fisheye of the built-in graph
POINTS_PER_FACTOR = (1, 2, 4, 8, 16)
HUBER_K = 2.45


def version(package: str) -> str:
    """Installed version of ``package`` or ``"?"``."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def lm_iteration(graph, values, ordering) -> tuple[float, int]:
    """Seconds of one LM ``iterate()`` (optimizer built outside the timer) and the
    number of trial steps it took, read from lambda."""
    params = gtsam.LevenbergMarquardtParams()
    params.setOrdering(ordering)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    t0 = time.perf_counter()
    opt.iterate()
    dt = time.perf_counter() - t0
    # fixed lambda factor: each rejected trial multiplies lambda by the factor,
    # the accepted one divides it
    ratio = opt.lambda_() / params.getlambdaInitial()
    return dt, round(math.log(ratio) / math.log(params.getlambdaFactor())) + 2


def timed(fn) -> float:
    """Seconds of one call of ``fn()``."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def simulate(targets_per_image: int, seed: int):
    """GoPro-like simulation; returns (sim, dataset, true world_from_cam, true xyz)."""
    options = gopro_like(
        n_targets=370,
        preferred_targets_per_image=targets_per_image,
        sigma_mode="weighted",
        seed=seed,
    )
    sim = simulate_room(options)
    ds = parse_dataset(sim.dataset)
    truth_img = {im["id"]: im["cam_from_world"] for im in sim.truth["images"]}
    world_from_cam = []
    for image_id in ds.image_ids:
        cfw = truth_img[image_id]
        pose = gtsam.Pose3(gtsam.Rot3(np.array(cfw["R"])), np.array(cfw["t"], float))
        world_from_cam.append(pose.inverse())
    truth_xyz = {t["id"]: t["xyz"] for t in sim.truth["targets"]}
    xyz = np.array([truth_xyz[t] for t in ds.target_ids], float)
    return sim, ds, world_from_cam, xyz


def camera_points(ds, world_from_cam, xyz) -> np.ndarray:
    """Camera-frame coordinates (N, 3) of every observation."""
    R = np.array([p.inverse().rotation().matrix() for p in world_from_cam])
    t = np.array([p.inverse().translation() for p in world_from_cam])
    return np.einsum("nij,nj->ni", R[ds.obs_image], xyz[ds.obs_target]) + t[ds.obs_image]


def perturbed(values: gtsam.Values, keys_pose, keys_point, seed: int) -> gtsam.Values:
    """Copy of ``values`` with poses moved by ~2 mrad / 5 mm and points by ~5 mm."""
    rng = np.random.default_rng(seed)
    out = gtsam.Values(values)
    for k in keys_pose:
        delta = np.concatenate([rng.normal(0, 2e-3, 3), rng.normal(0, 5e-3, 3)])
        out.update(k, values.atPose3(k).retract(delta))
    for k in keys_point:
        out.update(k, values.atPoint3(k) + rng.normal(0, 5e-3, 3))
    return out


def copy_with(values: gtsam.Values, source: gtsam.Values, keys_pose, keys_point) -> gtsam.Values:
    """``values`` with the poses and points of ``source`` (same perturbation for all graphs)."""
    out = gtsam.Values(values)
    for k in keys_pose:
        out.update(k, source.atPose3(k))
    for k in keys_point:
        out.update(k, source.atPoint3(k))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 repeats instead of 7")
    parser.add_argument("--repeats", type=int, default=None, help="override the repeat count")
    parser.add_argument(
        "--targets-per-image",
        type=int,
        default=55,
        help="simulator's preferred_targets_per_image (55 gives ~5,850 observations)",
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 7)
    t_start = time.perf_counter()

    print(
        f"machine: {platform.platform()} ({platform.machine()}), {os.cpu_count()} CPUs; "
        f"python {platform.python_version()}; gtsam {version('gtsam')}; "
        f"numpy {np.__version__}; load average {os.getloadavg()[0]:.2f}"
    )

    # -- problem ------------------------------------------------------------------------
    sim, ds, world_from_cam, xyz = simulate(args.targets_per_image, args.seed)
    pc = camera_points(ds, world_from_cam, xyz)
    front = pc[:, 2] > 0
    n_all = ds.n_observations
    obs_image, obs_target, uv = ds.obs_image[front], ds.obs_target[front], ds.uv_px[front]
    lens = sim.lens
    cx, cy, f = float(lens.cx), float(lens.cy), float(lens.f)
    c = initial_principal_distance(uv, pc[front], np.array([cx, cy]))
    theta = np.array([cx, cy, c])
    print(
        f"problem: gopro_like(preferred_targets_per_image={args.targets_per_image}, "
        f"seed={args.seed}): {len(ds.image_ids)} images, "
        f"{len(np.unique(obs_target))} targets, {n_all} observations; "
        f"{n_all - int(front.sum())} excluded (z_cam <= 0), {int(front.sum())} used"
    )
    print(
        f"values: true poses and targets; ours theta = [cx, cy, c] = "
        f"[{cx:.1f}, {cy:.1f}, {c:.1f}] (least-squares c; lens f = {f:.1f}); "
        f"built-in Cal3Fisheye(f, f, 0, cx, cy, 0, 0, 0, 0)"
    )
    print(f"repeats: median of {repeats} after 1 warm-up pass (designs timed round-robin)\n")

    def problem_with(ppf: int) -> BundleProblem:
        return BundleProblem(
            obs_image=obs_image,
            obs_target=obs_target,
            uv_px=uv,
            target_xyz=ds.target_xyz,
            target_sigma=ds.target_sigma,
            n_images=len(ds.image_ids),
            noise=NoiseOptions(1.0, "huber", HUBER_K),
            points_per_factor=ppf,
        )

    base = problem_with(1)
    base_graph = base.build()
    pose_keys = [pose_key(int(i)) for i in np.unique(obs_image)]
    point_keys = [point_key(int(t)) for t in base.free_targets]
    # everything but the observation blocks: one PriorFactorPoint3 per target
    priors = [base_graph.at(i) for i in range(len(base.blocks), base_graph.size())]
    values = initial_values(base, world_from_cam, theta, target_xyz=xyz)
    start = perturbed(values, pose_keys, point_keys, seed=1)
    ordering = make_ordering(point_keys, pose_keys, [INTRINSICS_KEY])

    designs: list[tuple[str, gtsam.NonlinearFactorGraph, gtsam.Values, gtsam.Ordering]] = []

    # built-in C++ factor, plain and Huber
    calib = gtsam.Cal3Fisheye(f, f, 0.0, cx, cy, 0.0, 0.0, 0.0, 0.0)
    b_values = gtsam.Values()
    for k in pose_keys:
        b_values.insert(k, values.atPose3(k))
    for k in point_keys:
        b_values.insert(k, values.atPoint3(k))
    b_values.insert(CALIB_KEY, calib)
    b_ordering = make_ordering(point_keys, pose_keys, [CALIB_KEY])
    gaussian = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    huber = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), gaussian
    )
    for name, model in (("built-in GeneralSFMFactor2", gaussian), ("built-in + Huber", huber)):
        g = gtsam.NonlinearFactorGraph()
        for i, t, m in zip(obs_image, obs_target, uv):
            g.add(
                gtsam.GeneralSFMFactor2Cal3Fisheye(
                    m, model, pose_key(int(i)), point_key(int(t)), CALIB_KEY
                )
            )
        for p in priors:
            g.add(p)
        designs.append((name, g, b_values, b_ordering))

    # ours, grouped
    for ppf in POINTS_PER_FACTOR:
        designs.append((f"ours ppf={ppf}", problem_with(ppf).build(), values, ordering))

    # naive: one CustomFactor per observation (same residual, same robust weighting)
    g = gtsam.NonlinearFactorGraph()
    for o in range(len(uv)):
        block = ObservationBlock(
            [pose_key(int(obs_image[o]))],
            [point_key(int(obs_target[o]))],
            [0],
            [0],
            xyz[obs_target[o]][None, :],
            uv[o][None, :],
            (),
            base.brown_scale_px,
            base.noise,
        )
        g.add(block.factor())
    for p in priors:
        g.add(p)
    designs.append(("one CustomFactor per observation", g, values, ordering))

    # -- timing: round-robin over the designs, so load changes hit all of them alike --
    samples: dict[str, dict[str, list[float]]] = {
        name: {"lin": [], "elim": [], "lm": []} for name, *_ in designs
    }
    tries: dict[str, int] = {}
    linear = {name: g.linearize(vals) for name, g, vals, _ in designs}
    lm_starts = {
        name: start if vals is values else copy_with(vals, start, pose_keys, point_keys)
        for name, _, vals, _ in designs
    }
    for r in range(repeats + 1):  # r == 0 is the warm-up pass
        for name, g, vals, order in designs:
            lin_s = timed(lambda g=g, vals=vals: g.linearize(vals))
            elim_s = timed(lambda lin=linear[name], o=order: lin.eliminateMultifrontal(o))
            lm_s, tries[name] = lm_iteration(g, lm_starts[name], order)
            if r:
                for key, sec in (("lin", lin_s), ("elim", elim_s), ("lm", lm_s)):
                    samples[name][key].append(sec)
        print(f"  pass {r}/{repeats} done", file=sys.stderr, flush=True)

    rows = []
    for name, g, _, _ in designs:
        med = {k: 1e3 * statistics.median(v) for k, v in samples[name].items()}
        rows.append((name, g.size(), med["lin"], med["lm"], tries[name], med["elim"]))

    ref = next(r for r in rows if r[0] == "built-in + Huber")
    header = (
        f"{'design':34s} {'factors':>7s} {'linearize ms':>12s} {'ratio':>6s} "
        f"{'LM iteration ms':>15s} {'ratio':>6s} {'LM tries':>8s} {'eliminate ms':>12s}"
    )
    print(header)
    print("-" * len(header))
    for name, n_factors, lin_ms, lm_ms, tries, elim_ms in rows:
        print(
            f"{name:34s} {n_factors:7d} {lin_ms:12.1f} {lin_ms / ref[2]:6.2f} "
            f"{lm_ms:15.1f} {lm_ms / ref[3]:6.2f} {tries:8d} {elim_ms:12.1f}"
        )
    print(
        "\nratios are to 'built-in + Huber' (like-for-like robust weighting). 'factors' "
        f"includes {len(priors)} PriorFactorPoint3 (one per target) in every graph.\n"
        "LM iteration = one LevenbergMarquardtOptimizer.iterate() from the same perturbed "
        "start (2 mrad, 5 mm): one linearisation, the damped elimination and one cost "
        "evaluation per trial step ('LM tries', read from lambda).\n"
        "eliminate = lin.eliminateMultifrontal(ordering), targets then poses then intrinsics. "
        "Times are wall clock: a loaded machine (see load average) inflates them all."
    )
    print(
        f"total benchmark time {time.perf_counter() - t_start:.1f} s; "
        f"load average now {os.getloadavg()[0]:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
