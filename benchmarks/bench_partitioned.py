"""Benchmark: partitioned map refinement (local and on Ray) against the global solve.

Not a test: prints a table, one run per row. The simulated building of
``bench_map.py`` (:func:`gtsam_sphere.simulate.building.building_map_problem`:
~190 deg fisheye, 0.5 px noise, 200 observations per image, perturbed start,
prior on the first pose, odometry between consecutive poses) is refined by

- ``global``: :func:`gtsam_sphere.estimation.map_problem.refine_global`, the
  package's one Python LM on the whole graph in one process;
- ``local-P``: :func:`gtsam_sphere.estimation.partitioned.refine_map` with ``P``
  submaps in this process (the driver runs every submap);
- ``ray-WxP``: the same with ``P`` submaps on ``W`` Ray actors (a local Ray
  cluster of ``W`` CPUs started by the run).

Every row is a separate process (``--worker``); its peak memory is its own
``ru_maxrss`` (the driver) and, for Ray, each actor's own ``ru_maxrss``
(reported by the actor); times exclude the simulation and the graph
construction. ``cost vs global`` is ``(cost - cost_global) / cost_global``
against the global row of the same size; ``3D vs global`` the ratio of the
landmark RMS error after a similarity per room (``room_aligned_rms_m``). The
growth exponent is the least-squares slope of log(time per iteration) against
log(observations) per engine.

Usage::

    nice python benchmarks/bench_partitioned.py --sizes 1e5 --runs global,local-2,ray-1x2,ray-2x2
    nice python benchmarks/bench_partitioned.py --sizes 1e6 --runs global,ray-2x2 --json out.json
    python benchmarks/bench_partitioned.py --report a.json,b.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

import numpy as np


def images_for(n_obs: int) -> int:
    """Images of a run with ``n_obs`` observations (200 per image, as bench_map.py)."""
    return int(max(100, n_obs // 200))


def worker(args) -> dict:
    """One run in this process: simulate, refine, measure."""
    from gtsam_sphere.estimation.map_problem import refine_global
    from gtsam_sphere.estimation.partitioned import refine_map
    from gtsam_sphere.simulate.building import (
        building_map_problem,
        room_aligned_rms_m,
        simulate_building,
    )

    scene = simulate_building(n_images=images_for(args.n_obs), obs_per_image=200.0, seed=args.seed)
    problem = building_map_problem(scene, seed=args.seed + 1)
    run = args.run
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    if run == "global":
        result = refine_global(problem)
        parts, workers = 1, 1
    elif run.startswith("local-"):
        parts, workers = int(run.split("-")[1]), 1
        result = refine_map(problem, parts)
    elif run.startswith("ray-"):
        from gtsam_sphere.estimation.ray_executor import RayExecutor

        workers, parts = (int(x) for x in run.split("-")[1].split("x"))
        factory = RayExecutor.factory(
            n_workers=workers, init_kwargs={"num_cpus": workers, "include_dashboard": False}
        )
        result = refine_map(problem, parts, executor_factory=factory)
    else:
        raise SystemExit(f"unknown run {run!r}")
    wall, cpu = time.perf_counter() - t_wall, time.process_time() - t_cpu
    stats = result.stats
    infos = stats.get("workers", [])
    remote = run.startswith("ray-")
    return {
        "run": run,
        "n_obs": problem.n_observations,
        "n_images": problem.n_images,
        "n_points": problem.n_points,
        "partitions": parts,
        "workers": workers,
        "iterations": result.iterations,
        "status": str(result.status),
        "initial_error": result.initial_error,
        "error": result.error,
        "point_rms_m": room_aligned_rms_m(scene, result.points_world),
        "wall_s": wall,
        "driver_cpu_s": cpu,
        "worker_cpu_s": [i["cpu_s"] for i in infos] if remote else [],
        "iter_s": wall / max(result.iterations, 1),
        "driver_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "worker_peak_mb": [i["peak_rss_mb"] for i in infos] if remote else [],
        "separator_dim": stats.get("separator_dim", 0),
        "observations_per_part": stats.get("observations_per_part", [problem.n_observations]),
    }


def _run_one(n_obs: int, run: str, seed: int, timeout: float) -> dict | None:
    cmd = [sys.executable, __file__, "--worker", "--n-obs", str(n_obs), "--run", run]
    cmd += ["--seed", str(seed)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        print(f"  {run} at {n_obs:,}: timed out after {timeout:.0f} s", file=sys.stderr)
        return None
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        print(f"  {run} at {n_obs:,} failed:\n{out.stderr[-2000:]}", file=sys.stderr)
        return None
    return json.loads(lines[-1])


def _fmt_mb(values) -> str:
    return "-" if not values else f"{max(values):,.0f}"


def table(rows: list[dict]) -> str:
    """The markdown table of the runs, with the comparisons to the global row."""
    glob = {r["n_obs"]: r for r in rows if r["run"] == "global"}
    head = (
        "| observations | run | submaps | workers | separator dim | iterations | final cost "
        "| cost vs global | 3D RMS (mm) | 3D vs global | wall s | s / iteration "
        "| driver CPU s | worker CPU s (max) | driver peak MB | worker peak MB (max) |"
    )
    out = [head, "|" + "---|" * 16]
    for r in sorted(rows, key=lambda r: (r["n_obs"], r["run"] != "global", r["run"])):
        g = glob.get(r["n_obs"])
        dc = f"{(r['error'] - g['error']) / g['error']:+.2e}" if g else "-"
        d3 = f"{r['point_rms_m'] / g['point_rms_m']:.4f}" if g else "-"
        wc = f"{max(r['worker_cpu_s']):.1f}" if r["worker_cpu_s"] else "-"
        out.append(
            f"| {r['n_obs']:,} | {r['run']} | {r['partitions']} | {r['workers']} "
            f"| {r['separator_dim']} | {r['iterations']} | {r['error']:.6e} | {dc} "
            f"| {1e3 * r['point_rms_m']:.3f} | {d3} | {r['wall_s']:.1f} | {r['iter_s']:.2f} "
            f"| {r['driver_cpu_s']:.1f} | {wc} | {r['driver_peak_mb']:,.0f} "
            f"| {_fmt_mb(r['worker_peak_mb'])} |"
        )
    by_run: dict[str, list] = {}
    for r in rows:
        by_run.setdefault(r["run"].split("x")[0] if r["run"].startswith("ray") else r["run"], [])
        by_run[r["run"].split("x")[0] if r["run"].startswith("ray") else r["run"]].append(r)
    for run, rs in sorted(by_run.items()):
        sizes = sorted({r["n_obs"] for r in rs})
        if len(sizes) >= 2:
            x = np.log([r["n_obs"] for r in rs])
            y = np.log([r["iter_s"] for r in rs])
            slope = float(np.polyfit(x, y, 1)[0])
            out.append(f"\ngrowth exponent of s / iteration, {run}: {slope:.2f}")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="1e5")
    parser.add_argument("--runs", default="global,local-2,ray-1x2,ray-2x2")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--json", default=None, help="also write the rows to this file")
    parser.add_argument("--report", default=None, help="comma-separated --json files: one table")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--n-obs", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--run", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args)))
        return
    if args.report:
        rows = [r for f in args.report.split(",") for r in json.load(open(f))]
        print(table(rows))
        return
    rows = []
    for size in (int(float(s)) for s in args.sizes.split(",")):
        for run in args.runs.split(","):
            r = _run_one(size, run, args.seed, args.timeout)
            if r is not None:
                rows.append(r)
                print(
                    f"  {run} at {r['n_obs']:,}: {r['wall_s']:.1f} s, cost {r['error']:.6e}",
                    file=sys.stderr,
                    flush=True,
                )
                if args.json:
                    with open(args.json + ".tmp", "w") as f:
                        json.dump(rows, f, indent=1)
                    os.replace(args.json + ".tmp", args.json)
    load = os.getloadavg()
    print(f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; {math.nan if False else ''}")
    print(table(rows))


if __name__ == "__main__":
    main()
