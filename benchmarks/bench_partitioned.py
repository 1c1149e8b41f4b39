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
  cluster of ``W`` CPUs started by the run);
- ``gen-P``: scaling without the whole map anywhere: a building of ``P`` parts of
  ``--part-obs`` observations each (:class:`~gtsam_sphere.simulate.building.BuildingPart`,
  whole rooms), each part generated and refined by its own Ray actor (``P``
  actors sharing the machine's CPUs); the driver only holds the separator and,
  at the end, the states; ``gen-WxP``: the same ``P`` parts on ``W`` actors;
  ``gen-global-P``: the same building generated whole in one process and refined
  by the global LM (the reference, where it fits).

``--resident K`` (local, ray and gen runs): each worker process keeps ``K`` submaps'
workers alive between calls and makes the others again from their data when called
(:class:`~gtsam_sphere.estimation.partitioned.SubmapHost`); the run's name gets `` rK``.

Every row is a separate process (``--worker``); its peak memory is its own
``ru_maxrss`` (the driver) and, for Ray, each actor's own ``ru_maxrss``
(reported by the actor); ``wall s`` is the whole refinement after the simulation (graph
construction included; for ``gen`` runs also each part's generation inside its
actor), ``s / iteration`` the mean LM iteration alone. ``cost vs global`` is
``(cost - cost_global) / cost_global`` against the global row of the same size;
``3D vs global`` the ratio of the
landmark RMS error after a similarity per room (``room_aligned_rms_m``). The
growth exponent is the least-squares slope of log(time per iteration) against
log(observations) per engine.

Usage::

    nice python benchmarks/bench_partitioned.py --sizes 1e5 --runs global,local-2,ray-1x2,ray-2x2
    nice python benchmarks/bench_partitioned.py --sizes 1e6 --runs global,ray-2x2 --json out.json
    nice python benchmarks/bench_partitioned.py --sizes 0 --runs gen-1x4 --part-obs 5e4 --resident 1
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

    run = args.run
    if run.startswith("gen"):
        return generated(args)
    from gtsam_sphere.estimation.partitioned import LocalExecutor

    scene = simulate_building(n_images=images_for(args.n_obs), obs_per_image=200.0, seed=args.seed)
    problem = building_map_problem(scene, seed=args.seed + 1)
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    if run == "global":
        result = refine_global(problem)
        parts, workers = 1, 1
    elif run.startswith("local-"):
        parts, workers = int(run.split("-")[1]), 1
        factory = lambda s, sep: LocalExecutor(s, sep, resident=args.resident)  # noqa: E731
        result = refine_map(problem, parts, executor_factory=factory)
    elif run.startswith("ray-"):
        from gtsam_sphere.estimation.ray_executor import RayExecutor

        workers, parts = (int(x) for x in run.split("-")[1].split("x"))
        factory = RayExecutor.factory(
            n_workers=workers,
            init_kwargs={"num_cpus": workers, "include_dashboard": False},
            resident=args.resident,
        )
        result = refine_map(problem, parts, executor_factory=factory)
    else:
        raise SystemExit(f"unknown run {run!r}")
    wall, cpu = time.perf_counter() - t_wall, time.process_time() - t_cpu
    stats = result.stats
    infos = stats.get("workers", [])
    remote = run.startswith("ray-")
    return {
        "run": _label(args),
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
        "worker_solve_cpu_s": [i["solve_cpu_s"] for i in infos] if remote else [],
        "iter_s": float(np.mean(result.iteration_s)),
        "driver_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "worker_peak_mb": [i["peak_rss_mb"] for i in infos] if remote else [],
        "separator_dim": stats.get("separator_dim", 0),
        "observations_per_part": stats.get("observations_per_part", [problem.n_observations]),
    }


def generated(args) -> dict:
    """A ``gen-P``, ``gen-WxP`` or ``gen-global-P`` run: parts generated by their workers."""
    from gtsam_sphere.estimation.graph import pose_key
    from gtsam_sphere.estimation.map_problem import refine_global
    from gtsam_sphere.estimation.partitioned import PartitionedOptions, refine_submaps
    from gtsam_sphere.estimation.ray_executor import RayExecutor
    from gtsam_sphere.simulate.building import BuildingOptions, building_parts

    spec = args.run.split("-")[-1]
    n_hosts, n_parts = (int(x) for x in spec.split("x")) if "x" in spec else (0, int(spec))
    n_hosts = n_hosts or n_parts
    rooms_per_part = max(1, round(args.part_obs / 200.0 / 25))
    options = BuildingOptions(
        n_images=25 * rooms_per_part * n_parts, obs_per_image=200.0, seed=args.seed
    )
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    if args.run.startswith("gen-global"):
        whole = building_parts(options, 1)[0][0].build()
        t_wall, t_cpu = time.perf_counter(), time.process_time()
        result = refine_global(whole)
        n_obs, error, iterations = whole.n_observations, result.error, result.iterations
        iteration_s = result.iteration_s
        status, infos, sep_dim, workers = str(result.status), [], 0, 1
        per_part = [n_obs]
    else:
        parts, shared = building_parts(options, n_parts)
        separator = np.array([pose_key(int(i)) for i in shared], np.uint64)
        cpus = min(2, os.cpu_count() or 1)
        factory = RayExecutor.factory(
            n_workers=n_hosts,
            init_kwargs={"num_cpus": cpus, "include_dashboard": False},
            resident=args.resident,
        )
        lm = PartitionedOptions(max_iterations=args.max_iterations)
        states, info, infos = refine_submaps(parts, separator, factory, lm, progress=_stderr_line)
        per_part = [int(v) for i in infos for v in i["n_observations"].values()]
        error, iterations, status = info["error"], info["iterations"], str(info["status"])
        iteration_s = info["iteration_s"]
        sep_dim, workers = info["separator_dim"], len(infos)
        n_obs = sum(per_part)
    wall, cpu = time.perf_counter() - t_wall, time.process_time() - t_cpu
    return {
        "run": _label(args),
        "n_obs": n_obs,
        "n_images": options.n_images,
        "n_points": 0,
        "partitions": n_parts if not args.run.startswith("gen-global") else 1,
        "workers": workers,
        "iterations": iterations,
        "status": status,
        "initial_error": math.nan,
        "error": error,
        "point_rms_m": math.nan,
        "wall_s": wall,
        "driver_cpu_s": cpu,
        "worker_cpu_s": [i["cpu_s"] for i in infos],
        "worker_solve_cpu_s": [i["solve_cpu_s"] for i in infos],
        "worker_build_cpu_s": [i["build_cpu_s"] for i in infos],
        "iter_s": float(np.mean(iteration_s)),
        "driver_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "worker_peak_mb": [i["peak_rss_mb"] for i in infos],
        "separator_dim": sep_dim,
        "observations_per_part": per_part,
    }


def _stderr_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _label(args) -> str:
    return args.run + (f" r{args.resident}" if args.resident is not None else "")


def _run_one(n_obs: int, run: str, args) -> dict | None:
    cmd = [sys.executable, __file__, "--worker", "--n-obs", str(n_obs), "--run", run]
    cmd += ["--seed", str(args.seed), "--part-obs", str(args.part_obs)]
    if args.resident is not None:
        cmd += ["--resident", str(args.resident)]
    cmd += ["--max-iterations", str(args.max_iterations)]
    timeout = args.timeout
    try:
        # the run's progress (stderr) streams through; its row is the last JSON line
        out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        print(f"  {run} at {n_obs:,}: timed out after {timeout:.0f} s", file=sys.stderr)
        return None
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        print(f"  {run} at {n_obs:,} failed (exit {out.returncode}, see above)", file=sys.stderr)
        return None
    return json.loads(lines[-1])


def _fmt_mb(values) -> str:
    return "-" if not values else f"{max(values):,.0f}"


def table(rows: list[dict]) -> str:
    """The markdown table of the runs, with the comparisons to the global row."""
    glob = {r["n_obs"]: r for r in rows if r["run"] in ("global",) or "global" in r["run"]}
    head = (
        "| observations | run | submaps | workers | separator dim | iterations | final cost "
        "| cost vs global | 3D RMS (mm) | 3D vs global | wall s | s / iteration "
        "| driver CPU s | worker CPU s (max) | worker solve CPU s / iteration (sum) "
        "| driver peak MB | worker peak MB (max) |"
    )
    out = [head, "|" + "---|" * 17]
    for r in sorted(rows, key=lambda r: (r["n_obs"], "global" not in r["run"], r["run"])):
        g = glob.get(r["n_obs"])
        dc = f"{(r['error'] - g['error']) / g['error']:+.2e}" if g else "-"
        d3 = f"{r['point_rms_m'] / g['point_rms_m']:.4f}" if g else "-"
        if not math.isfinite(r["point_rms_m"]):
            d3 = "-"
        mm = f"{1e3 * r['point_rms_m']:.3f}" if math.isfinite(r["point_rms_m"]) else "-"
        wc = f"{max(r['worker_cpu_s']):.1f}" if r["worker_cpu_s"] else "-"
        solve = r.get("worker_solve_cpu_s") or []
        ws = f"{sum(solve) / max(r['iterations'], 1):.2f}" if solve else "-"
        out.append(
            f"| {r['n_obs']:,} | {r['run']} | {r['partitions']} | {r['workers']} "
            f"| {r['separator_dim']} | {r['iterations']} | {r['error']:.6e} | {dc} "
            f"| {mm} | {d3} | {r['wall_s']:.1f} | {r['iter_s']:.2f} "
            f"| {r['driver_cpu_s']:.1f} | {wc} | {ws} | {r['driver_peak_mb']:,.0f} "
            f"| {_fmt_mb(r['worker_peak_mb'])} |"
        )
    by_run: dict[str, list] = {}
    for r in rows:
        if "global" in r["run"] and r["run"] != "global":
            continue  # gen-global-P: a reference, one size
        name = r["run"].split("x")[0] if r["run"].startswith("ray") else r["run"]
        by_run.setdefault("gen" if name.startswith("gen") else name, []).append(r)
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
    parser.add_argument(
        "--part-obs",
        type=lambda v: int(float(v)),
        default=250000,
        help="gen runs: observations per part",
    )
    parser.add_argument(
        "--resident", type=int, default=None, help="submaps kept alive per worker process"
    )
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=100,
        help="gen runs: LM iterations at most (a few measure the time per iteration and the "
        "memory of a map too large to run to convergence here)",
    )
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
            r = _run_one(size, run, args)
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
