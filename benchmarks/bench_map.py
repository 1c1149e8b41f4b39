"""Benchmark: offline map refinement with a calibrated fisheye in a user's GTSAM graph.

Not a test: prints a table. A simulated trajectory through a corridor of rooms
(:mod:`gtsam_sphere.simulate.building`, ~190 degree radial-mapping fisheye,
0.5 px noise, 25 images per room, landmarks on walls, floor and ceiling) is
refined from a perturbed start (poses 0.3 deg and 3 cm, landmarks 5 cm) with
a prior on the first pose and noisy odometry between consecutive poses
(0.1 deg, 1 cm). Paths:

- ``bearing``: :func:`gtsam_sphere.estimation.external.make_bearing_factors` (pixels ->
  unit rays through the calibration, ``gtsam.BearingFactor3D``, angular sigma
  from the model's local scale, Huber 2.45); the build time includes the
  unprojection;
- ``python``: :class:`gtsam_sphere.estimation.external.ProjectionBlocks` (frozen pixel
  factors, one landmark and up to ``--max-obs`` images per ``CustomFactor``,
  Huber 2.45 per observation), LM through
  :func:`gtsam_sphere.estimation.external.levenberg_marquardt`, ISAM2 with its
  linearisation point held (both avoid the per-callback copy of the
  ``Values``, see that function);
- ``python-gtsam``: the same factors in ``gtsam.LevenbergMarquardtOptimizer``
  / ``gtsam.ISAM2`` as they come (every callback receives a copy of the
  whole ``Values``: cost grows with factors x variables; small sizes only);
- ``cpp-ref``: the pure C++ reference of the same size: ``BearingFactor3D``
  on the true rays with the same angular noise added, one isotropic sigma
  (no camera model anywhere);
- ``pinhole-ref``: ``GenericProjectionFactorCal3_S2`` (C++ pinhole, Huber) on
  the observations within 70 deg of the axis (fewer observations: its count
  is printed), for a per-observation comparison with GTSAM's classic factor.

Modes: ``lm`` (batch Levenberg-Marquardt to GTSAM's default tolerances, at
most ``--lm-iterations``) and ``isam2`` (images added in trajectory order; a
landmark enters with its second view and a weak 1 m prior at its initial
value (two views along the direction of travel leave its depth almost free),
a Python block when all its images are in; GTSAM's default ISAM2
parameters). Every run is a separate process (peak memory from
``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss``, read by a wrapper process
that runs nothing else); times exclude the simulation. The paths of one size run
back to back, ``--repeat`` times round-robin; the table shows each path's median
run (by time per LM iteration or ISAM2 update) and the ratios add the range of
the run-by-run ratios (run ``k`` of a path against run ``k`` of ``cpp-ref``).
The growth exponent is the least-squares slope of log(time) against
log(observations) over the sizes run.

Usage::

    nice python benchmarks/bench_map.py --quick            # < 1 min
    nice python benchmarks/bench_map.py                    # 1e4 .. 3e5 observations
    nice python benchmarks/bench_map.py --sizes 1e6 --paths bearing,cpp-ref --modes lm
    nice python benchmarks/bench_map.py --sizes 1e4,3e4,1e5 --repeat 3   # medians of 3 runs
    python benchmarks/bench_map.py --report a.json,b.json   # one table from --json files
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np

PATHS = ("bearing", "python", "python-gtsam", "cpp-ref", "pinhole-ref")
SIGMA_PX = 0.5
HUBER_K = 2.45


def images_for(n_obs: int, quick: bool) -> int:
    """Images of a run with ``n_obs`` observations: 200 per image, 500 to 5,000 images."""
    if quick:
        return max(40, min(100, n_obs // 60))
    return int(min(5000, max(500, n_obs // 200)))


# ----------------------------------------------------------------------------- worker


def _scene(n_obs: int, n_images: int, seed: int):
    from gtsam_sphere.simulate.building import simulate_building

    return simulate_building(n_images=n_images, obs_per_image=n_obs / n_images, seed=seed)


def _initial_and_gauge(scene, rng):
    """Perturbed start (Values) and the prior + odometry factors (NonlinearFactorGraph)."""
    import gtsam

    from gtsam_sphere.estimation.graph import point_key, pose_key
    from gtsam_sphere.simulate.building import perturb_poses, rotation_exp

    R, t = scene.world_from_cam_R, scene.world_from_cam_t
    R0, t0 = perturb_poses(R, t, math.radians(0.3), 0.03, rng)
    P0 = scene.points_world + rng.normal(scale=0.05, size=scene.points_world.shape)
    values = gtsam.Values()
    for i in range(scene.n_images):
        values.insert(pose_key(i), gtsam.Pose3(gtsam.Rot3(R0[i]), t0[i]))
    for j in range(scene.n_points):
        values.insert(point_key(j), P0[j])
    gauge = gtsam.NonlinearFactorGraph()
    first = gtsam.Pose3(gtsam.Rot3(R[0]), t[0])
    gauge.add(gtsam.PriorFactorPose3(pose_key(0), first, gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    s_rot, s_m = math.radians(0.1), 0.01
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[s_rot] * 3, [s_m] * 3])
    M = scene.n_images
    dR = np.einsum("mji,mjk->mik", R[:-1], R[1:]) @ rotation_exp(
        rng.normal(scale=s_rot, size=(M - 1, 3))
    )
    dt = np.einsum("mji,mj->mi", R[:-1], t[1:] - t[:-1]) + rng.normal(scale=s_m, size=(M - 1, 3))
    for i in range(M - 1):
        rel = gtsam.Pose3(gtsam.Rot3(dR[i]), dt[i])
        gauge.add(gtsam.BetweenFactorPose3(pose_key(i), pose_key(i + 1), rel, odo))
    return values, gauge


def _factors(path: str, scene, rng, max_obs: int):
    """(list of factors, observation indices each factor covers, extra info) for a path."""
    import gtsam

    from gtsam_sphere.estimation.external import ProjectionBlocks, make_bearing_factors
    from gtsam_sphere.estimation.graph import point_key, pose_key

    M = gtsam.noiseModel
    pk = np.array([pose_key(i) for i in range(scene.n_images)], np.uint64)[scene.obs_image]
    lk = np.array([point_key(j) for j in range(scene.n_points)], np.uint64)[scene.obs_point]
    obs = np.arange(scene.n_observations)
    if path == "bearing":
        huber = M.mEstimator.Huber.Create(HUBER_K)
        factors = make_bearing_factors(scene.camera, scene.uv_px, pk, lk, SIGMA_PX, robust=huber)
        return factors, [obs[k : k + 1] for k in obs], None
    if path.startswith("python"):
        noise = M.Robust.Create(M.mEstimator.Huber.Create(HUBER_K), M.Isotropic.Sigma(2, SIGMA_PX))
        groups = _incremental_groups(scene.obs_point, max_obs)
        blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, noise, groups=groups)
        return blocks.factors(), blocks.groups, blocks
    if path == "cpp-ref":
        sigma = SIGMA_PX / scene.camera.c
        rays = scene.true_bearings()
        noise = M.Robust.Create(M.mEstimator.Huber.Create(HUBER_K), M.Isotropic.Sigma(2, sigma))
        factors = []
        for k in obs:
            u = gtsam.Unit3(rays[k]).retract(rng.normal(scale=sigma, size=2))
            factors.append(gtsam.BearingFactor3D(int(pk[k]), int(lk[k]), u, noise))
        return factors, [obs[k : k + 1] for k in obs], None
    if path == "pinhole-ref":
        c = scene.camera.c
        K = gtsam.Cal3_S2(c, c, 0.0, scene.camera.xp, scene.camera.yp)
        pc = scene.points_cam()
        front = pc[:, 2] > math.cos(math.radians(70.0)) * np.linalg.norm(pc, axis=1)
        front &= np.bincount(scene.obs_point[front], minlength=scene.n_points)[scene.obs_point] >= 2
        uv = c * pc[:, :2] / pc[:, 2:3] + [scene.camera.xp, scene.camera.yp]
        uv += rng.normal(scale=SIGMA_PX, size=uv.shape)
        noise = M.Robust.Create(M.mEstimator.Huber.Create(HUBER_K), M.Isotropic.Sigma(2, SIGMA_PX))
        factors, cover = [], []
        for k in obs[front]:
            factors.append(
                gtsam.GenericProjectionFactorCal3_S2(uv[k], noise, int(pk[k]), int(lk[k]), K)
            )
            cover.append(obs[k : k + 1])
        return factors, cover, None
    raise ValueError(f"unknown path {path!r}")


def _incremental_groups(obs_point: np.ndarray, max_obs: int) -> list[np.ndarray]:
    """Per landmark (observations in trajectory order): the first two views, then chunks
    of ``max_obs`` (a landmark enters ISAM2 with its second view, as in the C++ paths)."""
    order = np.argsort(obs_point, kind="stable")
    sp = obs_point[order]
    starts = np.flatnonzero(np.r_[True, sp[1:] != sp[:-1]])
    ends = np.r_[starts[1:], len(sp)]
    groups = []
    for s, e in zip(starts, ends):
        cut = [s, min(s + 2, e)]
        while cut[-1] < e:
            cut.append(min(cut[-1] + max_obs, e))
        groups.extend(order[a:b] for a, b in zip(cut[:-1], cut[1:]))
    return groups


def _accuracy(scene, values) -> dict:
    """Map accuracy: landmark RMS (m) after a 7-parameter similarity per room onto the
    truth (the walls hide one room from the next, so rooms are tied together by the
    odometry alone and drift with it), and the RMS rotation error of the poses (deg)."""
    from gtsam_sphere.core.geometry import fit_similarity
    from gtsam_sphere.estimation.graph import point_key, pose_key

    rot = []
    for i in range(scene.n_images):
        dR = scene.world_from_cam_R[i].T @ values.atPose3(pose_key(i)).rotation().matrix()
        rot.append(math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2)))))
    sq = []
    for r in np.unique(scene.room_of_point):
        idx = [
            j for j in np.flatnonzero(scene.room_of_point == r) if values.exists(point_key(int(j)))
        ]
        if len(idx) < 4:
            continue
        est = np.array([values.atPoint3(point_key(int(j))) for j in idx])
        aligned = fit_similarity(est, scene.points_world[idx]).apply(est)
        sq.append(np.sum((aligned - scene.points_world[idx]) ** 2, axis=1))
    return {
        "rot_rms_deg": float(np.sqrt(np.mean(np.square(rot)))),
        "point_rms_m": float(np.sqrt(np.mean(np.concatenate(sq)))),
    }


def worker(args) -> dict:
    """One run: simulate, build, optimise; returns the measurements."""
    import gtsam

    from gtsam_sphere.estimation.external import levenberg_marquardt
    from gtsam_sphere.estimation.graph import point_key

    rng = np.random.default_rng(args.seed + 1)
    t0 = time.perf_counter()
    scene = _scene(args.n_obs, args.n_images, args.seed)
    sim_s = time.perf_counter() - t0
    values, gauge = _initial_and_gauge(scene, rng)
    start = _accuracy(scene, values)
    t0 = time.perf_counter()
    factors, cover, blocks = _factors(args.path, scene, rng, args.max_obs)
    build_s = time.perf_counter() - t0
    n_used = int(sum(len(c) for c in cover))
    out = {
        "path": args.path,
        "mode": args.mode,
        "n_obs": n_used,
        "n_images": scene.n_images,
        "n_points": scene.n_points,
        "n_factors": len(factors),
        "sim_s": sim_s,
        "build_s": build_s,
    }
    if args.mode == "lm":
        graph = gtsam.NonlinearFactorGraph(gauge)
        for f in factors:
            graph.add(f)
        used = np.zeros(scene.n_points, bool)
        used[scene.obs_point[np.concatenate(cover)]] = True
        if not used.all():  # pinhole-ref: landmarks without observations are left out
            for j in np.flatnonzero(~used):
                values.erase(point_key(j))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(args.lm_iterations)
        t0 = time.perf_counter()
        if args.path == "python":
            result, info = levenberg_marquardt(graph, values, params)
            iterations, error = info["iterations"], info["error"]
        else:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            result = opt.optimize()
            iterations, error = opt.iterations(), opt.error()
        opt_s = time.perf_counter() - t0
        out.update(iterations=int(iterations), error=float(error), optimize_s=opt_s)
        out["iter_s"] = opt_s / max(iterations, 1)
    else:
        opt_s, result, n_updates = _isam2(args.path, scene, values, gauge, factors, cover)
        out.update(optimize_s=opt_s, iterations=n_updates, iter_s=opt_s / n_updates)
    out["total_s"] = build_s + opt_s
    if args.path != "pinhole-ref":
        out.update(_accuracy(scene, result))
        out["start_point_rms_m"] = start["point_rms_m"]
    if blocks is not None:
        out["cache"] = dict(blocks.stats)
    return out


def _isam2(path, scene, values, gauge, factors, cover):
    """Images in trajectory order; a factor goes in when all its images are in, a landmark
    with its first factor. Returns (seconds, estimate, number of updates)."""
    import gtsam

    from gtsam_sphere.estimation.graph import point_key, pose_key

    isam = gtsam.ISAM2()
    keep = isam.getLinearizationPoint() if path == "python" else None  # noqa: F841 (held)
    last_image = np.array([scene.obs_image[c].max() for c in cover])
    first_point = np.array([scene.obs_point[c[0]] for c in cover])
    # no factor of a landmark before its second view (one bearing leaves its depth free)
    used = np.concatenate(cover)
    by_point = used[np.argsort(scene.obs_point[used], kind="stable")]  # trajectory order kept
    pts = scene.obs_point[by_point]
    start = np.flatnonzero(np.r_[True, pts[1:] != pts[:-1]])
    second = np.full(scene.n_points, scene.n_images)
    has_two = np.r_[start[1:], len(pts)] - start >= 2
    second[pts[start[has_two]]] = scene.obs_image[by_point[start[has_two] + 1]]
    last_image = np.maximum(last_image, second[first_point])
    order = np.argsort(last_image, kind="stable")
    bounds = np.searchsorted(last_image[order], np.arange(scene.n_images + 1))
    in_graph = np.zeros(scene.n_points, bool)
    # a landmark seen twice along the direction of travel has almost no parallax: a weak
    # prior (1 m) at its initial value keeps the incremental system determinate
    weak = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    t0 = time.perf_counter()
    for i in range(scene.n_images):
        graph, new = gtsam.NonlinearFactorGraph(), gtsam.Values()
        new.insert(pose_key(i), values.atPose3(pose_key(i)))
        graph.add(gauge.at(i))  # prior (i = 0) or odometry (i - 1, i)
        for f in order[bounds[i] : bounds[i + 1]]:
            j = first_point[f]
            if not in_graph[j]:
                p0 = values.atPoint3(point_key(j))
                new.insert(point_key(j), p0)
                graph.add(gtsam.PriorFactorPoint3(point_key(j), p0, weak))
                in_graph[j] = True
            graph.add(factors[f])
        isam.update(graph, new)
    result = isam.calculateEstimate()
    return time.perf_counter() - t0, result, scene.n_images


# ----------------------------------------------------------------------------- driver


def measure(cmd: list[str], timeout_s: float) -> dict:
    """Run ``cmd`` (a worker printing one JSON line) as this process's only child; add its
    peak resident memory (MB) from ``getrusage(RUSAGE_CHILDREN)``."""
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"status": f"timeout {timeout_s:.0f} s"}
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    if proc.returncode != 0:
        return {"status": "failed: " + proc.stderr.strip().splitlines()[-1][:120]}
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out.update(status="ok", peak_mb=peak_mb)
    return out


def run_one(args, path, mode, n_obs) -> dict:
    """Spawn a wrapper process that spawns the worker (so RUSAGE_CHILDREN is that run's)."""
    worker_cmd = [
        sys.executable,
        os.path.abspath(__file__),
        "--worker",
        "--path",
        path,
        "--mode",
        mode,
        "--n-obs",
        str(n_obs),
        "--n-images",
        str(images_for(n_obs, args.quick)),
        "--seed",
        str(args.seed),
        "--lm-iterations",
        str(args.lm_iterations),
        "--max-obs",
        str(args.max_obs),
    ]
    wrapper = [sys.executable, os.path.abspath(__file__), "--measure", str(args.timeout), "--"]
    try:
        proc = subprocess.run(
            wrapper + worker_cmd, capture_output=True, text=True, timeout=args.timeout + 60
        )
        out = json.loads(proc.stdout.strip().splitlines()[-1])
    except (subprocess.TimeoutExpired, IndexError, json.JSONDecodeError) as exc:
        out = {"status": f"wrapper failed ({type(exc).__name__})"}
    out.setdefault("path", path)
    out.setdefault("mode", mode)
    out.setdefault("n_obs_requested", n_obs)
    return out


def median_run(runs: list[dict]) -> dict:
    """The run with the median time per iteration/update among the successful ones (the
    first failure if none succeeded); ``iter_s_runs`` lists every run's, in run order
    (NaN for a failed run)."""
    ok = sorted((r for r in runs if r.get("status") == "ok"), key=lambda r: r["iter_s"])
    if not ok:
        return runs[0]
    row = dict(ok[(len(ok) - 1) // 2])
    row["iter_s_runs"] = [r.get("iter_s", math.nan) for r in runs]
    return row


def growth_exponent(rows, key: str) -> float:
    """Slope of log(row[key]) against log(n_obs) (NaN with fewer than 2 sizes)."""
    pts = [(r["n_obs"], r[key]) for r in rows if r.get("status") == "ok" and r.get(key, 0) > 0]
    if len(pts) < 2:
        return float("nan")
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def print_table(rows) -> None:
    print(
        "| observations | images | landmarks | path | mode | iterations | build s | "
        "time per LM iteration / ISAM2 update (s) | total s | peak MB | rot rms deg | "
        "landmark rms m per room (start) |"
    )
    print("|" + "---|" * 12)
    for r in rows:
        if r.get("status") != "ok":
            print(
                f"| {r.get('n_obs_requested', '?'):,} | | | {r['path']} | {r['mode']} | "
                f"{r.get('status')} | | | | | | |"
            )
            continue
        acc = ["-", "-"]
        if "point_rms_m" in r:
            acc = [
                f"{r['rot_rms_deg']:.3f}",
                f"{r['point_rms_m']:.4f} ({r['start_point_rms_m']:.3f})",
            ]
        print(
            f"| {r['n_obs']:,} | {r['n_images']:,} | {r['n_points']:,} | {r['path']} | "
            f"{r['mode']} | {r['iterations']} | {r['build_s']:.2f} | {r['iter_s']:.4f} | "
            f"{r['total_s']:.2f} | {r['peak_mb']:.0f} | " + " | ".join(acc) + " |"
        )


def summarise(rows) -> None:
    ok = [r for r in rows if r.get("status") == "ok"]
    print(
        "\ngrowth exponent (log-log slope of time against observations; below 1e5 the images "
        "stay at 500 and get denser, above they grow at ~200 observations each):"
    )
    for mode in ("lm", "isam2"):
        for path in PATHS:
            sel = [r for r in ok if r["path"] == path and r["mode"] == mode]
            if len(sel) >= 2:
                key = "iter_s" if mode == "lm" else "total_s"
                dense = [r for r in sel if r["n_obs"] / r["n_images"] > 150]
                print(
                    f"  {path:12s} {mode:5s}: {key} {growth_exponent(sel, key):.2f} "
                    f"(at ~200 observations per image: {growth_exponent(dense, key):.2f})"
                )
    print("\nratios against cpp-ref at the same size (goal: bearing <= 1.5, python <= 3):")
    for r in ok:
        if r["path"] in ("cpp-ref", "pinhole-ref"):
            continue
        ref = [
            q
            for q in ok
            if q["path"] == "cpp-ref"
            and q["mode"] == r["mode"]
            and q["n_obs_requested"] == r["n_obs_requested"]
        ]
        if ref:
            q = ref[0]
            paired = ""
            a, b = r.get("iter_s_runs", []), q.get("iter_s_runs", [])
            if len(a) > 1 and len(a) == len(b):  # run k of both paths ran back to back
                x = np.array(a) / np.array(b)
                x = x[np.isfinite(x)]
                if len(x):
                    paired = f" (run by run {x.min():.2f}x to {x.max():.2f}x)"
            print(
                f"  {r['path']:12s} {r['mode']:5s} {r['n_obs']:>9,}: per iteration/update "
                f"{r['iter_s'] / q['iter_s']:.2f}x{paired}, total "
                f"{r['total_s'] / q['total_s']:.2f}x"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes, < 1 minute")
    ap.add_argument("--sizes", default=None, help="observations, comma separated (1e4,1e5)")
    ap.add_argument("--paths", default="bearing,python,cpp-ref,pinhole-ref")
    ap.add_argument("--modes", default="lm,isam2")
    ap.add_argument(
        "--python-max-n", type=float, default=3.0e5, help="largest size for the python path"
    )
    ap.add_argument(
        "--python-gtsam-max-n", type=float, default=3.0e4, help="largest size for python-gtsam"
    )
    ap.add_argument("--lm-iterations", type=int, default=20)
    ap.add_argument("--max-obs", type=int, default=8, help="observations per Python block")
    ap.add_argument("--timeout", type=float, default=540.0, help="seconds per run")
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="runs per path and size (round-robin); the table shows the median run",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="also write the rows to this file")
    ap.add_argument(
        "--report",
        default=None,
        help="print the table of earlier --json files (comma separated) instead of running",
    )
    # internal
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--measure", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--path", default="bearing", help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="lm", help=argparse.SUPPRESS)
    ap.add_argument("--n-obs", type=int, default=10000, help=argparse.SUPPRESS)
    ap.add_argument("--n-images", type=int, default=500, help=argparse.SUPPRESS)
    ap.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.measure is not None:
        cmd = args.rest[1:] if args.rest[:1] == ["--"] else args.rest
        print(json.dumps(measure(cmd, args.measure)))
        return 0
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    if args.report:
        rows = []
        for name in args.report.split(","):
            with open(name) as fh:
                rows.extend(json.load(fh))
        order = {p: k for k, p in enumerate(PATHS)}
        rows.sort(key=lambda r: (r["mode"] != "lm", order.get(r["path"], 99), r["n_obs_requested"]))
        print_table(rows)
        summarise(rows)
        return 0
    if args.sizes:
        sizes = [int(float(s)) for s in args.sizes.split(",")]
    elif args.quick:
        sizes = [3000, 6000]
    else:
        sizes = [10_000, 30_000, 100_000, 300_000]
    paths = [p for p in args.paths.split(",") if p]
    if args.quick and args.paths == ap.get_default("paths"):
        paths = ["bearing", "python", "cpp-ref"]
    modes = [m for m in args.modes.split(",") if m]
    for p in paths:
        if p not in PATHS:
            ap.error(f"unknown path {p!r}; choose from {PATHS}")
    load = os.getloadavg()
    print(
        f"# bench_map: python {platform.python_version()}, {os.cpu_count()} cores, "
        f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} at start"
    )
    print(f"# command: {' '.join([os.path.basename(sys.executable)] + sys.argv)}")
    rows = []
    t_start = time.perf_counter()
    limit = {"python": args.python_max_n, "python-gtsam": args.python_gtsam_max_n}
    for mode in modes:
        for n in sizes:
            # the paths of one size run back to back (round-robin over --repeat), so
            # their ratios see the same machine load
            runs: dict[str, list[dict]] = {p: [] for p in paths if n <= limit.get(p, math.inf)}
            for rep in range(args.repeat):
                for path in runs:
                    row = run_one(args, path, mode, n)
                    runs[path].append(row)
                    status = row.get("status")
                    took = row.get("total_s", float("nan"))
                    print(
                        f"# {path} {mode} {n:,} (run {rep + 1}/{args.repeat}): {status}, "
                        f"{took:.1f} s, per iteration/update {row.get('iter_s', math.nan):.4f} s, "
                        f"load {os.getloadavg()[0]:.2f}",
                        flush=True,
                    )
            rows.extend(median_run(r) for r in runs.values())
    order = {p: k for k, p in enumerate(PATHS)}
    rows.sort(key=lambda r: (r["mode"] != "lm", order.get(r["path"], 99), r["n_obs_requested"]))
    print()
    print_table(rows)
    summarise(rows)
    load = os.getloadavg()
    print(
        f"\n# wall {time.perf_counter() - t_start:.0f} s; load average at end "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
