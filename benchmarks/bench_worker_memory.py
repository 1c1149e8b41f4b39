"""Benchmark: what holds a submap worker's memory, object by object (issue 16).

Not a test: prints a table. One part of a :class:`~gtsam_sphere.simulate.building.BuildingPart`
building (``--part-obs`` observations, 200 per image) is built into a
:class:`~gtsam_sphere.estimation.partitioned.SubmapWorker` in this process and taken
through one LM iteration's work by hand: its graph, a state's values, the first
evaluation (the factor engine's caches and Jacobian buffer), the linearisation, the
damped elimination of the interior (its Bayes net; the elimination's transient peak
apart), then each dropped again. Each row is the change of the process's resident
size (``/proc/self/status`` VmRSS after ``gc.collect`` and glibc's ``malloc_trim``, so
freed C++ memory counts as freed), in MB and in KB per observation.

Usage::

    nice python benchmarks/bench_worker_memory.py --part-obs 5e4
"""

from __future__ import annotations

import argparse
import gc
import resource

import numpy as np


def rss_mb() -> float:
    """Resident size of this process (MB), after collecting and trimming the C heap."""
    from gtsam_sphere.estimation.partitioned import release_freed_memory

    gc.collect()
    release_freed_memory()
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def peak_mb() -> float:
    """Peak resident size of this process (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part-obs", type=lambda v: int(float(v)), default=50000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from gtsam_sphere.estimation.graph import pose_key
    from gtsam_sphere.estimation.partitioned import SubmapWorker
    from gtsam_sphere.simulate.building import BuildingOptions, building_parts

    rooms = max(1, round(args.part_obs / 200.0 / 25))
    options = BuildingOptions(n_images=2 * 25 * rooms, obs_per_image=200.0, seed=args.seed)
    parts, shared = building_parts(options, 2)  # the first of two: a separator to keep
    separator = np.array([pose_key(int(i)) for i in shared], np.uint64)
    rows = []
    now = rss_mb()
    problem = parts[0].build()
    n = problem.n_observations

    def row(label: str) -> None:
        nonlocal now
        before, now = now, rss_mb()
        rows.append((label, now - before, (now - before) * 1024 / n, peak_mb()))

    row("the part's data (MapProblem)")
    worker = SubmapWorker(0, problem, separator)
    row("its graph (CustomFactor blocks, factor engine)")
    state = worker.initial_state()
    values, passes = worker._at(state)
    row("one state's gtsam.Values")
    worker.error(state)
    row("first evaluation (engine caches, Jacobian buffer)")
    with passes:
        lin = worker.built.graph.linearize(values)
    row("linearisation (GaussianFactorGraph)")
    damped = worker._damping.damped(lin, 1e-5)
    before_peak = max(peak_mb(), now)
    bayes, rest = damped.eliminatePartialSequential(worker.interior)
    row("elimination of the interior (Bayes net, separator factor)")
    transient = peak_mb() - max(before_peak, now)
    rows.append(("  its transient peak, above both", transient, transient * 1024 / n, peak_mb()))
    del damped, lin
    row("linearisation dropped")
    del bayes, rest
    row("Bayes net dropped")
    print(
        f"part of {n:,} observations, {len(worker.pose_keys)} poses, "
        f"{len(worker.point_keys)} landmarks, {worker.built.graph.size()} factors"
    )
    print("| object | MB | KB / observation | process peak MB |")
    print("|---|---|---|---|")
    for label, mb, kb, pk in rows:
        print(f"| {label} | {mb:+.1f} | {kb:+.2f} | {pk:,.0f} |")


if __name__ == "__main__":
    main()
