"""Benchmark: linearising our bundle graph versus GTSAM's built-in C++ factor.

Not a test: prints a table. The problem is a GoPro-sized room simulation
(52 images, 370 targets, about 6,000 observations) at the TRUE poses and
target coordinates; targets are free variables with weighted priors.

Rows:

- ``ours ppf=G``: :meth:`BundleProblem.build` with ``points_per_factor=G``
  (tiles of at most ``G`` targets by ``graph.IMAGES_PER_FACTOR`` images, each a
  ``gtsam.CustomFactor``, all evaluated in one numpy pass per ``Values``, Huber
  per observation);
- ``one CustomFactor per observation``: the same spherical residual, one
  single-observation :class:`ObservationBlock` per observation (the naive cost);
- ``built-in``: ``gtsam.GeneralSFMFactor2Cal3Fisheye`` per observation with
  ``Cal3Fisheye(f, f, 0, cx, cy, 0, 0, 0, 0)``, plain and Huber-robust (2.45).

Every graph also holds the same ``PriorFactorPoint3`` per target. Timings are
medians over repeats (after one warm-up) of ``graph.linearize(values)``, one
``LevenbergMarquardtOptimizer.iterate()`` from a slightly perturbed start and
``lin.eliminateMultifrontal(ordering)`` (targets, then poses, then intrinsics).
Successive linearisations alternate between two ``Values`` (the true state and
the perturbed start), as in an optimisation: ours keeps the evaluation of the
last ``Values`` and would otherwise answer a repeat from it. Each timing is
taken as wall clock and as this process's CPU time (less sensitive to other
processes on a shared machine).

``--breakdown`` adds, for ``points_per_factor`` = the :class:`BundleProblem`
default: where one linearisation and one cost evaluation spend their CPU time
(the one vectorised evaluation, the per-block checks that the stored
evaluation is the one for the ``Values`` at hand, the per-block copies into
GTSAM, GTSAM's own work), and the binding floor: the same factors with
callbacks that only hand over precomputed arrays.

Usage::

    python benchmarks/bench_linearize.py            # 7 repeats (about a minute)
    python benchmarks/bench_linearize.py --quick    # 3 repeats
    python benchmarks/bench_linearize.py --breakdown
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

from gtsam_sphere.estimation import graph as graph_module
from gtsam_sphere.estimation.calibrate import initial_principal_distance, initial_values
from gtsam_sphere.estimation.engine import FactorEngine
from gtsam_sphere.estimation.graph import (
    INTRINSICS_KEY,
    BundleProblem,
    NoiseOptions,
    ObservationBlock,
    point_key,
    pose_key,
)
from gtsam_sphere.estimation.optimize import make_ordering
from gtsam_sphere.io.dataset import parse_dataset
from gtsam_sphere.simulate import gopro_like, simulate_room

CALIB_KEY = gtsam.symbol("K", 0)  # Cal3Fisheye of the built-in graph
POINTS_PER_FACTOR = (1, 4, 8, 16)
HUBER_K = 2.45


def version(package: str) -> str:
    """Installed version of ``package`` or ``"?"``."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def lm_iteration(graph, values, ordering) -> tuple[float, float, int]:
    """Wall and CPU seconds of one LM ``iterate()`` (optimizer built outside the timer)
    and the number of trial steps it took, read from lambda."""
    params = gtsam.LevenbergMarquardtParams()
    params.setOrdering(ordering)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    wall, cpu = timed(opt.iterate)
    # fixed lambda factor: each rejected trial multiplies lambda by the factor,
    # the accepted one divides it
    ratio = opt.lambda_() / params.getlambdaInitial()
    return wall, cpu, round(math.log(ratio) / math.log(params.getlambdaFactor())) + 2


def timed(fn) -> tuple[float, float]:
    """Wall-clock and CPU seconds of one call of ``fn()``."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


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


def breakdown(problem: BundleProblem, values: gtsam.Values, other: gtsam.Values, repeats: int):
    """Print where one linearisation and one cost evaluation of ``problem`` spend CPU time,
    and the binding floor (the same factors handing over precomputed arrays)."""
    problem.build()
    blocks = problem.blocks
    views = [v for b in blocks for v in b.engine()[0]._blocks[b._index].views]
    engine = FactorEngine
    spent: dict[str, float] = {}

    def timing(cls, name):
        original = getattr(cls, name)

        def wrapper(*args, **kwargs):
            c0 = time.process_time()
            try:
                return original(*args, **kwargs)
            finally:
                spent[name] = spent.get(name, 0.0) + time.process_time() - c0

        setattr(cls, name, wrapper)
        return original

    originals = [
        (cls, name, timing(cls, name))
        for cls, name in ((engine, "_full_pass"), (engine, "_result"))
    ]
    timed_graph = gtsam.NonlinearFactorGraph()
    for b in blocks:
        timed_graph.add(b.factor())  # the factors hold the (wrapped) bound method
    parts: dict[str, list[dict[str, float]]] = {"linearize": [], "error": []}
    for r in range(2 * repeats + 1):
        for label, call in (("linearize", timed_graph.linearize), ("error", timed_graph.error)):
            spent.clear()
            at = values if (r + (label == "error")) % 2 else other  # never the last Values
            _, total = timed(lambda call=call, at=at: call(at))
            if r:
                parts[label].append(dict(spent, total=total))
    for cls, name, original in originals:
        setattr(cls, name, original)

    print(
        f"\nbreakdown, points_per_factor={problem.points_per_factor}, images per factor "
        f"{graph_module.IMAGES_PER_FACTOR}: {len(blocks)} blocks, "
        f"{sum(len(b.keys) for b in blocks)} Jacobian blocks, "
        f"{(sum(v.size for v in views) + 2 * len(problem.uv_px)) / 1e6:.2f} M numbers "
        "(A and b); median process CPU ms"
    )
    for label, rows in parts.items():
        m = {
            k: 1e3 * statistics.median([row.get(k, 0.0) for row in rows])
            for k in ("total", "_result", "_full_pass")
        }
        print(
            f"  {label:9s} {m['total']:6.2f} = evaluation of all observations "
            f"{m['_full_pass']:5.2f} + per-block checks {m['_result'] - m['_full_pass']:5.2f} "
            f"+ per-block copies, returns and GTSAM (C++) {m['total'] - m['_result']:5.2f}"
        )

    # binding floor: the same keys and shapes, callbacks that only hand over arrays
    floors = {
        "H[q] = array": gtsam.NonlinearFactorGraph(),
        "one copy": gtsam.NonlinearFactorGraph(),
    }
    for b in blocks:
        H = [None] * len(b.keys)
        e = b.evaluate(None, values, H)
        native = gtsam.JacobianVector(H)

        def per_key(this, v, out, H=H, e=e):
            if out is not None:
                for q, block in enumerate(H):
                    out[q] = block
            return e

        def one_copy(this, v, out, native=native, e=e):
            if out is not None:
                out[:] = native
            return e

        noise = gtsam.noiseModel.Unit.Create(2 * b.n)
        floors["H[q] = array"].add(gtsam.CustomFactor(noise, b.keys, per_key))
        floors["one copy"].add(gtsam.CustomFactor(noise, b.keys, one_copy))
    copies = [timed(lambda: gtsam.Values(values))[1] for _ in range(20 * repeats + 1)][1:]
    print(
        f"  a copy of the Values ({values.size()} variables): "
        f"{1e6 * statistics.median(copies):.0f} us. Inside GTSAM's optimizers (iterate() "
        "linearises and evaluates Values that Python does not hold) the binding hands each "
        f"callback such a copy: about {1e3 * len(blocks) * statistics.median(copies):.1f} ms "
        "per pass over these blocks, not in the linearize column above"
    )
    for label, g in floors.items():
        lin = [timed(lambda g=g: g.linearize(values))[1] for _ in range(2 * repeats + 1)][1:]
        err = [timed(lambda g=g: g.error(values))[1] for _ in range(2 * repeats + 1)][1:]
        print(
            f"  floor ({label}): linearize {1e3 * statistics.median(lin):6.2f}, "
            f"error {1e3 * statistics.median(err):6.2f}"
        )


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
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also where our linearisation spends its time, and the binding floor",
    )
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
        name: {k: [] for k in ("lin", "lin_cpu", "elim", "lm", "lm_cpu")} for name, *_ in designs
    }
    tries: dict[str, int] = {}
    linear = {name: g.linearize(vals) for name, g, vals, _ in designs}
    lm_starts = {
        name: start if vals is values else copy_with(vals, start, pose_keys, point_keys)
        for name, _, vals, _ in designs
    }
    for r in range(repeats + 1):  # r == 0 is the warm-up pass
        for name, g, vals, order in designs:
            at = vals if r % 2 else lm_starts[name]  # a new Values at every linearisation
            lin_s = timed(lambda g=g, at=at: g.linearize(at))
            elim_s, _ = timed(lambda lin=linear[name], o=order: lin.eliminateMultifrontal(o))
            *lm_s, tries[name] = lm_iteration(g, lm_starts[name], order)
            if r:
                row = samples[name]
                for key, sec in zip(
                    ("lin", "lin_cpu", "elim", "lm", "lm_cpu"), (*lin_s, elim_s, *lm_s)
                ):
                    row[key].append(sec)
        print(f"  pass {r}/{repeats} done", file=sys.stderr, flush=True)

    med = {
        name: {k: 1e3 * statistics.median(v) for k, v in samples[name].items()} for name in samples
    }
    ref = med["built-in + Huber"]
    header = (
        f"{'design':34s} {'factors':>7s} {'linearize ms':>12s} {'ratio':>6s} {'cpu':>5s} "
        f"{'LM iteration ms':>15s} {'ratio':>6s} {'cpu':>5s} {'LM tries':>8s} "
        f"{'eliminate ms':>12s}"
    )
    print(header)
    print("-" * len(header))
    for name, g, _, _ in designs:
        m = med[name]
        print(
            f"{name:34s} {g.size():7d} {m['lin']:12.1f} {m['lin'] / ref['lin']:6.2f} "
            f"{m['lin_cpu'] / ref['lin_cpu']:5.2f} {m['lm']:15.1f} {m['lm'] / ref['lm']:6.2f} "
            f"{m['lm_cpu'] / ref['lm_cpu']:5.2f} {tries[name]:8d} {m['elim']:12.1f}"
        )
    print(
        "\nratios are to 'built-in + Huber' (like-for-like robust weighting): 'ratio' of "
        "wall-clock medians, 'cpu' of process CPU-time medians. 'factors' includes "
        f"{len(priors)} PriorFactorPoint3 (one per target) in every graph.\n"
        "linearize = graph.linearize(values), alternating between two Values.\n"
        "LM iteration = one LevenbergMarquardtOptimizer.iterate() from the same perturbed "
        "start (2 mrad, 5 mm): one linearisation, the damped elimination and one cost "
        "evaluation per trial step ('LM tries', read from lambda).\n"
        "eliminate = lin.eliminateMultifrontal(ordering), targets then poses then intrinsics. "
        "Times are wall clock unless 'cpu': a loaded machine (see load average) inflates "
        "them all."
    )
    if args.breakdown:
        breakdown(problem_with(BundleProblem.points_per_factor), values, start, repeats)
    print(
        f"total benchmark time {time.perf_counter() - t_start:.1f} s; "
        f"load average now {os.getloadavg()[0]:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
