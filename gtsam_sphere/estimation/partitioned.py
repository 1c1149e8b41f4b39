"""Partitioned map refinement: submaps on workers, a reduced separator system solved centrally.

The method is Levenberg-Marquardt on the whole map whose linear systems are
solved by domain decomposition (a Schur complement on the separator), the
submap scheme of K. Ni, D. Steedly and F. Dellaert, "Out-of-Core Bundle
Adjustment for Large-Scale 3D Reconstruction" (ICCV 2007) and of K. Ni and
F. Dellaert, "Multi-Level Submap Based SLAM Using Nested Dissection" (IROS
2010). Each iteration:

1. every submap worker linearises its own factors (the factor engine's
   vectorised blocks, :meth:`MapProblem.graph
   <gtsam_sphere.estimation.map_problem.MapProblem.graph>`) at its current
   values, adds the damping ``lambda * I`` of its interior variables and
   eliminates them (GTSAM's partial sequential elimination, COLAMD order): what
   is left is a dense Hessian factor on its separator variables (the Schur
   complement of its interior);
2. the driver sums the submaps' Hessians on the separator, adds
   ``lambda * I`` there and solves the reduced system (SciPy sparse LU);
3. every worker back-substitutes its interior given the separator's step,
   retracts, and returns its cost at the trial point and its predicted decrease;
4. the step is accepted when the summed cost went down (``lambda`` divided by
   ``lambdaFactor``), or rejected (``lambda`` multiplied, the workers
   re-eliminate at the same linearisation point).

The loop itself (damping, acceptance, convergence, status) is the package's one
graph LM, :func:`~gtsam_sphere.estimation.optimize.lm_driver`, which the global
:func:`~gtsam_sphere.estimation.optimize.levenberg_marquardt` runs on one graph;
:class:`PartitionedBackend` is its linear algebra over the submaps (steps 1-3).
Every factor lives in exactly one submap (:mod:`.partition`), so the summed
costs and reduced systems are those of the whole graph: each step is the step
of the global LM (GTSAM's default LM, ``lambda * I`` on every variable) up to
rounding, hence the same answer as the global solve. Unlike a consensus scheme
(ADMM) nothing is approximate and no extra iterations are needed; the price is
the separator system on the driver (its size is the cut of the covisibility graph, small for
maps that follow a trajectory).

Where the work runs is an *executor* (:class:`LocalExecutor` here, in process;
:class:`~gtsam_sphere.estimation.ray_executor.RayExecutor` on a Ray cluster):
workers each hold some submaps, built once from their data (or, for less memory,
only ``resident`` of them alive and the others made again from their data when
called: :class:`SubmapHost`); per iteration only
the separator step (driver -> worker), the reduced systems and three numbers per
submap (worker -> driver) travel. A worker's current values are returned as
opaque states (with Ray: object references that stay in the object store), so a
worker that dies is recreated from its data and its last state and the call is
repeated: no iteration is lost. The driver writes a checkpoint (the states,
``lambda``, the cost, the iteration) atomically after every accepted iteration;
a run started again with the same checkpoint path resumes from it.
"""

from __future__ import annotations

import ctypes
import gc
import hashlib
import io
import logging
import math
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from ..core._compat import StrEnum
from ..core.errors import InputError
from ..io.dataset import write_bytes_atomic
from .engine import TrustedPass
from .map_problem import MapProblem, RefineResult, lm_params
from .optimize import LambdaDamping, LMIteration, lm_driver
from .partition import covisibility_partition, separator_keys

logger = logging.getLogger(__name__)

__all__ = [
    "Engine",
    "LocalExecutor",
    "PartitionedBackend",
    "PartitionedOptions",
    "SubmapHost",
    "SubmapWorker",
    "make_submaps",
    "refine_partitioned",
]

CHECKPOINT_VERSION = 1


class Engine(StrEnum):
    """Where a map refinement runs."""

    LOCAL = "local"  # this process (the global LM, or the submaps one after the other)
    RAY = "ray"  # the submaps on a Ray cluster (RayExecutor)


@dataclass
class PartitionedOptions:
    """Options of :func:`refine_partitioned`.

    Attributes
    ----------
    max_iterations : int
        LM iterations at most.
    relative_tolerance : float
        Converged when an accepted step lowers the cost by at most this fraction.
    checkpoint : str or Path or None
        File of the checkpoint (written atomically after each accepted
        iteration; read at the start when it exists and belongs to the same
        submaps). None: no checkpoint.
    keep_checkpoint : bool
        Keep the checkpoint file after a finished run (default: removed).
    """

    max_iterations: int = 100
    relative_tolerance: float = 1e-5
    checkpoint: str | os.PathLike | None = None
    keep_checkpoint: bool = False


# --------------------------------------------------------------------------- submaps


def make_submaps(problem: MapProblem, n_parts: int) -> tuple[list[MapProblem], np.ndarray]:
    """Cut a map into ``n_parts`` submaps (:func:`covisibility_partition`).

    Parameters
    ----------
    problem : MapProblem
    n_parts : int

    Returns
    -------
    submaps : list of MapProblem
    part : ndarray of int, shape (M,)
        Submap of each image row.
    """
    part = covisibility_partition(problem.obs_image, problem.obs_point, n_parts, problem.n_images)
    # a landmark's prior goes with the submap of its first observation (once in the map)
    first = np.full(problem.n_points, -1, np.int64)
    first[problem.obs_point[::-1]] = part[problem.obs_image[::-1]]
    submaps = [
        problem.submap(np.flatnonzero(part == k), prior_points=first == k) for k in range(n_parts)
    ]
    return submaps, part


def _state_token(part: int, counter: int) -> str:
    return f"{part}:{counter}:{os.getpid()}:{time.monotonic_ns()}"


class SubmapWorker:
    """One submap's graph and values: linearise, eliminate the interior, step.

    Parameters
    ----------
    part : int
        Submap index.
    submap : MapProblem
        Its data (observations, initial values, priors, odometry).
    separator : ndarray of uint64
        Keys shared between submaps (the whole map's separator; this submap's
        separator variables are the ones among its keys).

    Notes
    -----
    A *state* is a dict of numpy arrays: ``R`` (m, 3, 3), ``t`` (m, 3)
    (world_from_cam, metres), ``P`` (l, 3) (world, metres) in the submap's rows,
    and a ``token`` naming it; a worker keeps the ``gtsam.Values`` of the states it
    made, and rebuilds one it does not know (after a restart) from its arrays.
    """

    def __init__(self, part: int, submap: MapProblem, separator: np.ndarray):
        self.part = int(part)
        self.problem = submap
        self.built = submap.graph()
        self.pose_keys = submap.pose_keys()
        self.point_keys = submap.point_keys()
        keys = np.r_[self.pose_keys, self.point_keys]
        sep = np.intersect1d(keys, np.asarray(separator, np.uint64))
        self.separator = [int(k) for k in sep]
        sep_set = set(self.separator)
        self.interior = [int(k) for k in keys if int(k) not in sep_set]
        self.dims = {int(k): 6 for k in self.pose_keys}
        self.dims.update({int(k): 3 for k in self.point_keys})
        self._counter = 0
        self._values: dict[str, tuple[gtsam.Values, TrustedPass]] = {}
        self._linear: tuple | None = None  # (token, linearisation, its cost at zero)
        self._elimination: tuple | None = None  # (token, lam, Bayes net of the interior)
        # lambda * I on the interior variables (the driver damps the separator)
        self._damping = LambdaDamping((k, self.dims[k]) for k in self.interior)

    # ------------------------------------------------------------------ states

    def initial_state(self) -> dict:
        """The state of the submap's initial values."""
        p = self.problem
        return {
            "token": f"{self.part}:initial",
            "R": p.world_from_cam_R.copy(),
            "t": p.world_from_cam_t.copy(),
            "P": p.points_world.copy(),
        }

    def _remember(self, token: str, values: gtsam.Values, passes: TrustedPass) -> None:
        self._values[token] = (values, passes)
        while len(self._values) > 3:  # the current state and the last trials
            self._values.pop(next(iter(self._values)))

    def _at(self, state: dict) -> tuple[gtsam.Values, TrustedPass]:
        got = self._values.get(state["token"])
        if got is None:
            from .map_problem import values_from_arrays

            values = values_from_arrays(
                self.pose_keys, state["R"], state["t"], self.point_keys, state["P"]
            )
            got = (values, TrustedPass(values, jacobians=True))
            self._remember(state["token"], *got)
        return got

    def _state_of(self, values: gtsam.Values) -> dict:
        from .map_problem import arrays_from_values

        R, t, P = arrays_from_values(values, self.pose_keys, self.point_keys)
        self._counter += 1
        return {"token": _state_token(self.part, self._counter), "R": R, "t": t, "P": P}

    # ------------------------------------------------------------------ the work

    def error(self, state: dict) -> float:
        """The submap's cost at ``state`` (GTSAM's error: half the weighted sum of squares)."""
        values, passes = self._at(state)
        with passes:
            return float(self.built.graph.error(values))

    def _linearization(self, state: dict) -> tuple[gtsam.GaussianFactorGraph, float]:
        """The linearisation at ``state`` and its cost at the zero step (made once a state)."""
        if self._linear is not None and self._linear[0] == state["token"]:
            return self._linear[1:]
        self._linear = self._elimination = None  # one linearisation alive at a time
        values, passes = self._at(state)
        with passes:
            lin = self.built.graph.linearize(values)
        self._linear = (state["token"], lin, float(lin.error(values.zeroVectors())))
        return self._linear[1:]

    def _eliminate(self, state: dict, lam: float):
        """``(bayes net, separator factors)`` of the interior's elimination, damped by ``lam``."""
        lin, _ = self._linearization(state)
        damped = self._damping.damped(lin, lam)
        if self.separator:
            bayes, rest = damped.eliminatePartialSequential(self.interior)
        else:
            bayes, rest = damped.eliminateSequential(), None
        self._elimination = (state["token"], lam, bayes)
        return bayes, rest

    def reduce(self, state: dict, lam: float) -> dict:
        """Eliminate the interior (damped by ``lam``): the Schur complement on the separator.

        Parameters
        ----------
        state : dict
        lam : float
            LM damping ``lambda`` (``lambda * I`` on the interior variables).

        Returns
        -------
        dict
            ``keys`` (list of int, separator keys of this submap, the Hessian's
            order), ``dims`` (list of int), ``information`` (n, n) and ``linear``
            (n,): the reduced cost ``0.5 (c - 2 x^T linear + x^T information x)``
            of a separator step ``x``; ``model`` (float): the undamped linearised
            cost at the zero step.
        """
        _, rest = self._eliminate(state, lam)
        _, model = self._linearization(state)
        if rest is None or rest.size() == 0:
            return {
                "keys": [],
                "dims": [],
                "information": np.zeros((0, 0)),
                "linear": np.zeros(0),
                "model": model,
            }
        hessian = gtsam.HessianFactor(rest)
        keys = [int(k) for k in hessian.keys()]
        return {
            "keys": keys,
            "dims": [self.dims[k] for k in keys],
            "information": np.array(hessian.information(), dtype=float, copy=True),
            "linear": np.array(hessian.linearTerm(), dtype=float, copy=True).reshape(-1),
            "model": model,
        }

    def step(self, state: dict, lam: float, keys: list, delta: np.ndarray):
        """Back-substitute the interior given the separator step, retract, evaluate.

        The linearisation and the elimination :meth:`reduce` made are used here
        (made again if this worker has not kept them: after a restart, or when its
        host holds more submaps than it keeps resident) and then dropped: they
        would serve only a rejected step's next :meth:`reduce`, which linearises
        again, and are not held through the trial's evaluation (the peak memory).

        Parameters
        ----------
        state : dict
        lam : float
        keys : list of int
            Separator keys of ``delta`` (the order :meth:`reduce` returned).
        delta : ndarray, shape (n,)
            Separator step (tangent coordinates, ``[omega, v]`` per pose, metres per point).

        Returns
        -------
        summary : dict
            ``error`` (cost at the trial point) and ``predicted`` (decrease of the
            undamped linearised cost).
        trial : dict
            The trial state.
        """
        if self._elimination is not None and self._elimination[:2] == (state["token"], lam):
            bayes = self._elimination[2]
        else:
            bayes, _ = self._eliminate(state, lam)
        lin, model = self._linearization(state)
        given = gtsam.VectorValues()
        at = 0
        for k in keys:
            d = self.dims[int(k)]
            given.insert(int(k), np.asarray(delta[at : at + d], float))
            at += d
        step = bayes.optimize(given) if self.separator else bayes.optimize()
        predicted = model - lin.error(step)
        del lin, bayes
        self._linear = self._elimination = None
        release_freed_memory()
        values, _ = self._at(state)
        trial = values.retract(step)
        passes = TrustedPass(trial, jacobians=True)
        with passes:
            error = float(self.built.graph.error(trial))
        new_state = self._state_of(trial)
        self._remember(new_state["token"], trial, passes)
        return {"error": error, "predicted": float(predicted)}, new_state


def release_freed_memory() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``).

    A linearisation is many small C++ allocations; freed, glibc keeps their pages
    (the process's resident size does not fall) while the next evaluation's numpy
    temporaries are mapped afresh, so both count in the peak. Elsewhere than
    glibc: nothing.
    """
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        try:
            _MALLOC_TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _MALLOC_TRIM = False
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM = None


class SubmapHost:
    """The submaps of one worker process (a Ray actor, or the driver itself locally).

    Parameters
    ----------
    parts : list of int
        Submap indices held here.
    submaps : list of MapProblem, or of objects with ``build() -> MapProblem``
        Their data, same order; a recipe (e.g. a
        :class:`~gtsam_sphere.simulate.building.BuildingPart`) is built here, in
        the worker, so the whole map never exists in one process.
    separator : ndarray of uint64
    resident : int or None
        Submaps whose :class:`SubmapWorker` (graph, factor engine, values) stays
        alive between calls; the others keep only their data (a
        :class:`MapProblem`: tens of bytes per observation, against kilobytes for a
        worker) and their worker is made again when called, in the place of the
        worker made last (the same results; the graph's construction, a
        linearisation and an elimination more per call). None: all (no submap is
        made twice).
    """

    def __init__(
        self,
        parts: list[int],
        submaps: list,
        separator: np.ndarray,
        resident: int | None = None,
    ):
        t0 = time.process_time()
        submaps = [s if isinstance(s, MapProblem) else s.build() for s in submaps]
        self.separator = np.asarray(separator, np.uint64)
        self.problems = {int(k): s for k, s in zip(parts, submaps)}
        self.resident = None if resident is None else max(1, int(resident))
        self.workers: dict[int, SubmapWorker] = {}  # alive, in the order they were made
        self.workers_made = 0
        if self.resident is None:
            for k in self.problems:
                self._worker(k)
        self.fingerprints = {int(k): _fingerprint(s) for k, s in zip(parts, submaps)}
        self.nbytes = {int(k): s.nbytes() for k, s in zip(parts, submaps)}
        self.n_observations = {int(k): s.n_observations for k, s in zip(parts, submaps)}
        self.build_cpu_s = time.process_time() - t0
        self.solve_cpu_s = 0.0

    def _worker(self, part: int) -> SubmapWorker:
        worker = self.workers.get(part)
        if worker is None:
            if self.resident is not None and len(self.workers) >= self.resident:
                # the submaps are called in turn, each once per round: the most recently
                # made goes (least recently used would make every one again each round),
                # and out before the new one is made (one at a time in memory)
                self.workers.popitem()
                release_freed_memory()
            gc.disable()  # tens of thousands of objects: the collector would scan them often
            try:
                worker = SubmapWorker(part, self.problems[part], self.separator)
            finally:
                gc.enable()
            self.workers[part] = worker
            self.workers_made += 1
        return worker

    def call(self, part: int, method: str, *args):
        """Run ``SubmapWorker.method(*args)`` of submap ``part`` (its CPU time is counted)."""
        t0 = time.process_time()
        try:
            return getattr(self._worker(int(part)), method)(*args)
        finally:
            self.solve_cpu_s += time.process_time() - t0

    def info(self) -> dict:
        """Process id, peak resident memory (MB), CPU seconds (all, building the
        submaps, in the solver's calls), data bytes, observations, fingerprints and
        the number of :class:`SubmapWorker` s made (``workers_made``)."""
        return {
            "pid": os.getpid(),
            "peak_rss_mb": peak_rss_mb(),
            "cpu_s": time.process_time(),
            "build_cpu_s": self.build_cpu_s,
            "solve_cpu_s": self.solve_cpu_s,
            "nbytes": dict(self.nbytes),
            "n_observations": dict(self.n_observations),
            "fingerprints": dict(self.fingerprints),
            "workers_made": self.workers_made,
        }


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB, ``getrusage`` ``ru_maxrss``)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _fingerprint(problem: MapProblem) -> str:
    h = hashlib.sha256()
    for arr in (
        problem.uv_px,
        problem.obs_image,
        problem.obs_point,
        problem.image_ids,
        problem.point_ids,
        problem.world_from_cam_t,
        problem.points_world,
    ):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()[:16]


class LocalExecutor:
    """Runs every submap in this process (the reference for the Ray executor).

    Parameters
    ----------
    submaps : list of MapProblem
    separator : ndarray of uint64
    resident : int or None
        As :class:`SubmapHost` (None: every submap's worker alive throughout).
    """

    def __init__(
        self, submaps: list[MapProblem], separator: np.ndarray, resident: int | None = None
    ):
        self.n_parts = len(submaps)
        self.host = SubmapHost(list(range(len(submaps))), submaps, separator, resident)

    def call(self, part: int, method: str, *args, num_returns: int = 1):
        """Run the method now; returns its result (a tuple for two returns)."""
        return self.host.call(part, method, *args)

    def get(self, results):
        """The results themselves (nothing is remote)."""
        return results

    def put(self, obj):
        """``obj`` itself."""
        return obj

    def infos(self) -> list[dict]:
        """One :meth:`SubmapHost.info` (this process)."""
        return [self.host.info()]

    def shutdown(self) -> None:
        """Nothing to stop."""


# --------------------------------------------------------------------------- checkpoints


def _save_checkpoint(path, fingerprint: str, iteration: int, lam: float, error: float, states):
    arrays = {
        "version": np.array(CHECKPOINT_VERSION),
        "fingerprint": np.array(fingerprint),
        "iteration": np.array(iteration),
        "lam": np.array(lam),
        "error": np.array(error),
        "n_parts": np.array(len(states)),
    }
    for k, s in enumerate(states):
        arrays[f"R{k}"], arrays[f"t{k}"], arrays[f"P{k}"] = s["R"], s["t"], s["P"]
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_bytes_atomic(path, buffer.getvalue())


def _load_checkpoint(path, fingerprint: str):
    """``(iteration, lam, error, states)`` of a checkpoint of these submaps, or None."""
    if path is None or not Path(path).is_file():
        return None
    try:
        with np.load(path) as z:
            if int(z["version"]) != CHECKPOINT_VERSION or str(z["fingerprint"]) != fingerprint:
                logger.warning("checkpoint %s belongs to another map or partition: ignored", path)
                return None
            n = int(z["n_parts"])
            states = [
                {"token": f"{k}:checkpoint", "R": z[f"R{k}"], "t": z[f"t{k}"], "P": z[f"P{k}"]}
                for k in range(n)
            ]
            return int(z["iteration"]), float(z["lam"]), float(z["error"]), states
    except (OSError, ValueError, KeyError) as exc:
        logger.warning("checkpoint %s unreadable (%s): ignored", path, exc)
        return None


# --------------------------------------------------------------------------- the driver


def _solve_separator(reduced: list[dict], lam: float):
    """Sum the submaps' reduced systems, damp, solve. Returns (layout, step) or None."""
    import scipy.sparse
    import scipy.sparse.linalg

    offset: dict[int, int] = {}
    dims: dict[int, int] = {}
    for r in reduced:
        for k, d in zip(r["keys"], r["dims"]):
            if k not in offset:
                offset[k] = sum(dims.values())
                dims[k] = d
    n = sum(dims.values())
    if n == 0:
        return offset, np.zeros(0)
    rows, cols, vals = [], [], []
    g = np.zeros(n)
    for r in reduced:
        if not r["keys"]:
            continue
        idx = np.concatenate(
            [np.arange(offset[k], offset[k] + d) for k, d in zip(r["keys"], r["dims"])]
        )
        rows.append(np.repeat(idx, len(idx)))
        cols.append(np.tile(idx, len(idx)))
        vals.append(r["information"].reshape(-1))
        np.add.at(g, idx, r["linear"])
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(np.full(n, lam))
    H = scipy.sparse.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    try:
        x = scipy.sparse.linalg.splu(H).solve(g)
    except RuntimeError:  # exactly singular
        return None
    if not np.all(np.isfinite(x)):
        return None
    return offset, x


class PartitionedBackend:
    """:class:`~gtsam_sphere.estimation.optimize.LMBackend` of submaps on an executor.

    The state is one opaque state per submap (with Ray: object references). Per
    :meth:`solve`, every worker eliminates its interior (``reduce``), the driver
    solves the damped separator system (:func:`_solve_separator`) and every
    worker back-substitutes, retracts and evaluates its trial (``step``): the
    trial's cost comes back with the predicted decrease, in one round trip.

    Parameters
    ----------
    executor : LocalExecutor or RayExecutor
    n_parts : int
    states : list
        The submaps' current states.

    Attributes
    ----------
    states : list
        The current states.
    separator_dim : int
        Dimension of the last separator system solved.
    model_cost : float
        The summed linearised cost at the zero step (the workers' ``reduce``).
    """

    def __init__(self, executor, n_parts: int, states: list):
        self.executor = executor
        self.n_parts = n_parts
        self.states = states
        self.separator_dim = 0
        self.model_cost = math.nan
        self._trial: tuple[float, list] | None = None

    def _each(self, method: str, *args) -> list:
        ex = self.executor
        return ex.get([ex.call(k, method, self.states[k], *args) for k in range(self.n_parts)])

    def error(self) -> float:
        """The summed cost of the current states."""
        return float(sum(self._each("error")))

    def linearize(self) -> None:
        """Nothing here: each worker linearises in its first ``reduce`` at a new state."""
        self.model_cost = math.nan

    def solve(self, lam: float) -> float | None:
        """Reduce, solve the separator, step every submap (the trial's cost kept)."""
        ex = self.executor
        reduced = self._each("reduce", lam)
        self.model_cost = float(sum(r["model"] for r in reduced))
        solved = _solve_separator(reduced, lam)
        if solved is None:
            return None
        offset, x = solved
        self.separator_dim = len(x)
        calls = []
        for k in range(self.n_parts):
            keys = reduced[k]["keys"]
            idx = [np.arange(offset[q], offset[q] + d) for q, d in zip(keys, reduced[k]["dims"])]
            delta = x[np.concatenate(idx)] if idx else np.zeros(0)
            calls.append(ex.call(k, "step", self.states[k], lam, keys, delta, num_returns=2))
        summaries = ex.get([c[0] for c in calls])
        self._trial = (float(sum(s["error"] for s in summaries)), [c[1] for c in calls])
        return float(sum(s["predicted"] for s in summaries))

    def evaluate(self) -> float:
        """The summed cost of the trial (evaluated by the workers' ``step``)."""
        return self._trial[0]

    def accept(self) -> None:
        """The trial states become the current ones."""
        self.states = self._trial[1]


def refine_partitioned(
    executor,
    n_parts: int,
    options: PartitionedOptions | None = None,
    progress: Callable[[str], None] | None = None,
    on_iteration: Callable[[int, dict], None] | None = None,
) -> tuple[list[dict], dict]:
    """Levenberg-Marquardt over submaps with the separator solved centrally (see the module).

    :func:`~gtsam_sphere.estimation.optimize.lm_driver` on a
    :class:`PartitionedBackend`, with a checkpoint after each accepted iteration.

    Parameters
    ----------
    executor : LocalExecutor or RayExecutor
        Holds the submaps (``call``, ``get``, ``put``, ``infos``).
    n_parts : int
        Number of submaps.
    options : PartitionedOptions
    progress : callable(str), optional
        One line per iteration.
    on_iteration : callable(iteration, info), optional
        Called after each iteration (tests use it to kill a worker).

    Returns
    -------
    states : list of dict
        Final state of each submap (``R``, ``t``, ``P`` in its rows).
    info : dict
        ``initial_error`` (the cost this run started from: the checkpoint's when resumed),
        ``error``, ``iterations``, ``status`` (LMStatus),
        ``iteration_s``, ``lambda``, ``resumed_from`` (iteration or None),
        ``separator_dim``.
    """
    opts = options or PartitionedOptions()
    p = lm_params(opts.max_iterations, opts.relative_tolerance)
    fingerprint = hashlib.sha256(
        "".join(
            f"{k}:{v};"
            for info in executor.infos()
            for k, v in sorted(info["fingerprints"].items())
        ).encode()
    ).hexdigest()[:16]
    resumed = _load_checkpoint(opts.checkpoint, fingerprint)
    if resumed is not None:
        first_iteration, lam, error, loaded = resumed
        backend = PartitionedBackend(executor, n_parts, [executor.put(s) for s in loaded])
        if progress:
            progress(
                f"resumed from {opts.checkpoint}: iteration {first_iteration}, cost {error:.6e}"
            )
    else:
        first_iteration, lam = 0, p.getlambdaInitial()
        states = [executor.call(k, "initial_state") for k in range(n_parts)]
        backend = PartitionedBackend(executor, n_parts, states)
        error = backend.error()
    if progress:
        progress(f"iteration {first_iteration:3d}  cost {error:.6e}  ({n_parts} submaps)")

    def report(it: LMIteration) -> None:
        if progress:
            progress(
                f"iteration {it.iteration:3d}  cost {it.error:.6e}  lambda {it.lam:.1e}  "
                f"separator {backend.separator_dim}  {it.seconds:.2f} s"
            )
        if opts.checkpoint is not None and not it.converged:
            _save_checkpoint(
                opts.checkpoint,
                fingerprint,
                it.iteration,
                it.lam,
                it.error,
                executor.get(backend.states),
            )
        if on_iteration is not None:
            on_iteration(it.iteration, {"error": it.error, "lambda": it.lam})

    run = lm_driver(backend, p, error, lam=lam, iteration=first_iteration, on_iteration=report)
    final = executor.get(backend.states)
    if opts.checkpoint is not None and not opts.keep_checkpoint:
        Path(opts.checkpoint).unlink(missing_ok=True)
    info = {
        "initial_error": error,
        "resumed_from": resumed and resumed[0],
        **run,
        "separator_dim": backend.separator_dim,
    }
    return final, info


def assemble(problem_image_ids, problem_point_ids, submaps: list[MapProblem], states: list[dict]):
    """The whole map's arrays from the submaps' states.

    Parameters
    ----------
    problem_image_ids : ndarray of int, shape (M,)
    problem_point_ids : ndarray of int, shape (L,)
        Global ids of the rows wanted.
    submaps : list of MapProblem
    states : list of dict

    Returns
    -------
    R : ndarray, shape (M, 3, 3)
    t : ndarray, shape (M, 3)
    P : ndarray, shape (L, 3)
    """
    M, L = len(problem_image_ids), len(problem_point_ids)
    row_i = {int(g): q for q, g in enumerate(problem_image_ids)}
    row_l = {int(g): q for q, g in enumerate(problem_point_ids)}
    R, t, P = np.full((M, 3, 3), np.nan), np.full((M, 3), np.nan), np.full((L, 3), np.nan)
    for s, st in zip(submaps, states):
        ri = np.array([row_i[int(g)] for g in s.image_ids])
        rl = np.array([row_l[int(g)] for g in s.point_ids])
        R[ri], t[ri], P[rl] = st["R"], st["t"], st["P"]
    return R, t, P


def refine_submaps(
    submaps: list,
    separator: np.ndarray,
    executor_factory: Callable | None = None,
    options: PartitionedOptions | None = None,
    progress: Callable[[str], None] | None = None,
    on_iteration: Callable[[int, dict], None] | None = None,
) -> tuple[list[dict], dict, list[dict]]:
    """Refine given submaps (data or recipes built by the workers) on an executor.

    Parameters
    ----------
    submaps : list of MapProblem, or of objects with ``build() -> MapProblem``
        Every factor of the map in exactly one of them (see :func:`make_submaps`).
    separator : ndarray of uint64
        Keys of the variables in more than one submap.
    executor_factory : callable(submaps, separator) -> executor, optional
        Default :class:`LocalExecutor`.
    options, progress, on_iteration
        As :func:`refine_partitioned`.

    Returns
    -------
    states : list of dict
        Final state of each submap.
    info : dict
        As :func:`refine_partitioned`.
    workers : list of dict
        :meth:`SubmapHost.info` of each worker process.
    """
    factory = executor_factory or LocalExecutor
    executor = factory(submaps, separator)
    try:
        states, info = refine_partitioned(executor, len(submaps), options, progress, on_iteration)
        workers = executor.infos()
    finally:
        executor.shutdown()
    return states, info, workers


def refine_map(
    problem: MapProblem,
    n_parts: int = 1,
    executor_factory: Callable | None = None,
    options: PartitionedOptions | None = None,
    progress: Callable[[str], None] | None = None,
    on_iteration: Callable[[int, dict], None] | None = None,
) -> RefineResult:
    """Refine a map in ``n_parts`` submaps (see the module), in process or on an executor.

    Parameters
    ----------
    problem : MapProblem
    n_parts : int
        Number of submaps (>= 1).
    executor_factory : callable(submaps, separator) -> executor, optional
        E.g. ``RayExecutor.factory(...)``; default :class:`LocalExecutor`.
    options : PartitionedOptions
    progress : callable(str), optional
    on_iteration : callable(iteration, info), optional

    Returns
    -------
    RefineResult
        ``stats`` holds ``partitions``, ``separator_dim``, ``separator_keys``,
        ``observations_per_part``, ``workers`` (per worker process: ``pid``,
        ``peak_rss_mb``, ``cpu_s``) and ``resumed_from``.
    """
    problem.validate()
    if n_parts < 1:
        raise InputError(f"partitions must be >= 1, got {n_parts}")
    submaps, _ = make_submaps(problem, n_parts)
    sep = separator_keys([np.r_[s.pose_keys(), s.point_keys()] for s in submaps])
    states, info, workers = refine_submaps(
        submaps, sep, executor_factory, options, progress, on_iteration
    )
    R, t, P = assemble(problem.image_ids, problem.point_ids, submaps, states)
    return RefineResult.from_run(
        R,
        t,
        P,
        info,
        {
            "partitions": n_parts,
            "separator_dim": int(info["separator_dim"]),
            "separator_keys": len(sep),
            "observations_per_part": [s.n_observations for s in submaps],
            "workers": workers,
            "resumed_from": info["resumed_from"],
        },
    )
