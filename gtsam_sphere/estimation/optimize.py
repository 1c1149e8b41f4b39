"""Nonlinear least squares on factor graphs: Levenberg-Marquardt or dogleg.

:func:`optimize` wraps GTSAM's optimizers, iterating one step at a time so that
progress is shown and the cost history is kept (the paper's Figure 5).
:func:`lm_driver` is the package's one Python-driven LM loop (damping, acceptance,
convergence, status) over an :class:`LMBackend` that holds the state and does the
linear algebra: :class:`GraphBackend` for one factor graph
(:func:`levenberg_marquardt`, for graphs of many engine blocks: no copy of the
``Values`` per callback) and
:class:`~gtsam_sphere.estimation.partitioned.PartitionedBackend` for submaps on
workers. All share the convergence test (:func:`decrease_converged`) and the
meaning of converged and stalled
(:class:`~gtsam_sphere.core.least_squares.LMStatus`).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np

from ..core._compat import StrEnum
from ..core.least_squares import LMStatus
from .engine import TrustedPass


class OptimizerKind(StrEnum):
    """Trust-region strategy."""

    LM = "lm"
    DOGLEG = "dogleg"


@dataclass
class OptimizerOptions:
    """Options of :func:`optimize`.

    Attributes
    ----------
    kind : OptimizerKind
    max_iterations : int
    relative_tolerance : float
        Stop when the cost decreases by less than this fraction (1e-6, Ceres'
        default ``function_tolerance``). It was 1e-9: robust stages then ran on for
        tens of iterations at changes of 1e-7 (IRLS converges linearly), a 340 deg
        lens's calibration took 197 iterations against 79, 21.3 s against 12.7 s,
        with the same 3D error (0.889x the oracle's).
    absolute_tolerance : float
        Stop when the cost decreases by less than this.
    lambda_upper_bound : float
        LM: the damping at which a run without a step that lowers the cost is stalled
        (``LevenbergMarquardtParams.lambdaUpperBound``; GTSAM's default is 1e5). The
        damping adds ``lambda * I`` to the whitened normal equations, whose diagonal
        grows as ``1 / sigma_px^2``: at 0.1 px of noise a target's is 1e6-1e7 per metre
        squared and a pose's rotation 1e9 and more, so 1e5 leaves the step as long as
        the undamped one. Zoo stress 2912 s15 (a 160 deg room, 0.1 px, 5 % blunders):
        every robust stage stalled at 1e5 with a step still moving a target 0.23 m and
        the result was not trusted (0.92x the oracle's 3D error); at 1e10 every stage
        converges, trusted at 0.93x.
    """

    kind: OptimizerKind = OptimizerKind.LM
    max_iterations: int = 100
    relative_tolerance: float = 1e-6
    absolute_tolerance: float = 1e-9
    lambda_upper_bound: float = 1e10


@dataclass
class OptimizationResult:
    """Outcome of :func:`optimize`.

    Attributes
    ----------
    values : gtsam.Values
        Best state found.
    history : list of dict
        Per iteration: ``iteration``, ``cost``, ``seconds``.
    converged : bool
    status : LMStatus
        How the run ended (a ``str``: ``"converged"``, ``"max_iterations"``,
        ``"stalled"``, ``"diverged"``).
    message : str
        What stalled or diverged it (empty otherwise).
    """

    values: gtsam.Values
    history: list[dict] = field(default_factory=list)
    converged: bool = False
    status: LMStatus = LMStatus.MAX_ITERATIONS
    message: str = ""

    def describe(self) -> str:
        """``status`` and, when there is one, ``: message``."""
        return f"{self.status}: {self.message}" if self.message else str(self.status)

    @property
    def cost(self) -> float:
        """Final cost (GTSAM's error: half the weighted sum of squares)."""
        return self.history[-1]["cost"] if self.history else math.nan


def make_ordering(first: list[int], then: list[int], last: list[int]) -> gtsam.Ordering:
    """Elimination ordering: ``first`` (targets), ``then`` (poses), ``last`` (intrinsics)."""
    ordering = gtsam.Ordering()
    for key in [*first, *then, *last]:
        ordering.push_back(key)
    return ordering


def optimize(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    options: OptimizerOptions | None = None,
    ordering: gtsam.Ordering | None = None,
    progress: Callable[[str], None] | None = None,
    label: str = "",
) -> OptimizationResult:
    """Minimise the graph's cost from ``initial``.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    initial : gtsam.Values
    options : OptimizerOptions
    ordering : gtsam.Ordering, optional
        Elimination ordering (targets first is best for bundle adjustment).
    progress : callable(str), optional
        Receives one line per iteration.
    label : str
        Prefix of the progress lines.

    Returns
    -------
    OptimizationResult
    """
    options = options or OptimizerOptions()
    kind = OptimizerKind(options.kind)
    if kind is OptimizerKind.LM:
        params = gtsam.LevenbergMarquardtParams()
    else:
        params = gtsam.DoglegParams()
    if ordering is not None:
        params.setOrdering(ordering)
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_tolerance)
    params.setAbsoluteErrorTol(options.absolute_tolerance)
    if kind is OptimizerKind.LM:
        params.setlambdaUpperBound(options.lambda_upper_bound)
        return _optimize_lm(graph, initial, params, ordering, progress, label)
    opt = gtsam.DoglegOptimizer(graph, initial, params)
    t0 = time.perf_counter()
    cost = opt.error()
    history = [{"iteration": 0, "cost": cost, "seconds": 0.0}]
    result = OptimizationResult(values=initial, history=history)
    if progress:
        progress(f"{label}iteration   0  cost {cost:.6e}")
    status, message = LMStatus.MAX_ITERATIONS, ""
    best_cost, best_values = cost, initial
    for it in range(1, options.max_iterations + 1):
        try:
            opt.iterate()
        except RuntimeError as exc:  # indeterminate system, cheirality, ...
            status, message = LMStatus.STALLED, str(exc).strip().splitlines()[0]
            break
        new_cost = opt.error()
        history.append({"iteration": it, "cost": new_cost, "seconds": time.perf_counter() - t0})
        if progress:
            progress(f"{label}iteration {it:3d}  cost {new_cost:.6e}")
        if not np.isfinite(new_cost) or new_cost > 1e3 * max(best_cost, 1e-300):
            status = LMStatus.DIVERGED
            message = (
                "cost is not finite"
                if not np.isfinite(new_cost)
                else f"cost grew from {best_cost:.3e} to {new_cost:.3e}"
            )
            break
        if new_cost <= best_cost:
            best_cost, best_values = new_cost, opt.values()
        decrease = cost - new_cost
        if decrease_converged(
            cost, new_cost, options.absolute_tolerance, options.relative_tolerance
        ):
            status = LMStatus.CONVERGED
            break
        if decrease < 0:
            status, message = LMStatus.STALLED, "dogleg could not decrease the cost"
            break
        cost = new_cost
    # the best state seen (a diverging system can end above it)
    result.values = opt.values() if opt.error() <= best_cost else gtsam.Values(best_values)
    result.converged = status is LMStatus.CONVERGED
    result.status, result.message = status, message
    return result


def _optimize_lm(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: gtsam.LevenbergMarquardtParams,
    ordering: gtsam.Ordering | None,
    progress: Callable[[str], None] | None,
    label: str,
) -> OptimizationResult:
    """:func:`optimize` with Levenberg-Marquardt: :func:`levenberg_marquardt` (Python-driven)
    taking GTSAM's steps (``gtsam_steps``) with the caller's ordering.

    GTSAM's C++ optimiser hands each ``CustomFactor`` callback a copy of its whole
    ``Values`` (see :func:`levenberg_marquardt`); the bundle graphs' hundreds of engine
    blocks made that copy a third of the optimiser's time (GoPro-like room: 2.7 s of
    process time over a calibration's 14 adjustments, 1.9 s driven from Python), for
    the same steps: the calibrations are the same bytes.
    """
    t0 = time.perf_counter()
    history: list[dict] = []
    last = [initial]  # the last accepted state: what an exception leaves

    def on_iteration(it: int, cost: float, values: gtsam.Values) -> None:
        history.append({"iteration": it, "cost": cost, "seconds": time.perf_counter() - t0})
        last[0] = values
        if progress:
            progress(f"{label}iteration {it:3d}  cost {cost:.6e}")

    result = OptimizationResult(values=initial, history=history)
    try:
        values, info = levenberg_marquardt(
            graph, initial, params, ordering, on_iteration, gtsam_steps=True
        )
    except RuntimeError as exc:  # cheirality, a factor that cannot be evaluated, ...
        result.status, result.message = LMStatus.STALLED, str(exc).strip().splitlines()[0]
        result.values = last[0]
        if not history:
            history.append({"iteration": 0, "cost": math.nan, "seconds": 0.0})
        return result
    result.values = values
    result.status = info["status"]
    if result.status is LMStatus.STALLED:
        result.message = "LM damping reached its upper bound"
    result.converged = result.status is LMStatus.CONVERGED
    return result


def stderr_progress(line: str) -> None:
    """Default progress sink: one line on standard error."""
    print(line, file=sys.stderr, flush=True)


def decrease_converged(cost: float, new_cost: float, absolute: float, relative: float) -> bool:
    """The convergence test of both optimisers: ``0 <= decrease <= max(absolute, relative cost)``.

    Parameters
    ----------
    cost, new_cost : float
        Cost (GTSAM's error) before and after an iteration.
    absolute, relative : float
        Tolerances on the decrease (cost units; fraction of ``cost``).
    """
    decrease = cost - new_cost
    return 0 <= decrease <= max(absolute, relative * cost)


#: ``LevenbergMarquardtParams.minModelFidelity``'s default (not exposed to Python)
GTSAM_MIN_MODEL_FIDELITY = 1e-3
_EPS = float(np.finfo(float).eps)
#: a predicted decrease below ``-_ROUNDING * cost`` is rounding, not an increase
_ROUNDING = 64.0 * _EPS


@dataclass(frozen=True)
class LMIteration:
    """One iteration of :func:`lm_driver`, as its ``on_iteration`` hook sees it.

    Attributes
    ----------
    iteration : int
        Iterations done (a resumed run's earlier ones included).
    error : float
        Cost of the current state (after the step when one was taken; GTSAM's error).
    lam : float
        The damping ``lambda`` the next iteration starts from.
    seconds : float
        Wall-clock time of the iteration (s).
    converged : bool
        The run ends converged after this iteration.
    """

    iteration: int
    error: float
    lam: float
    seconds: float
    converged: bool


class LMBackend(Protocol):
    """The state and linear algebra behind :func:`lm_driver`.

    Implementations: :class:`GraphBackend` (a factor graph in this process) and
    :class:`~gtsam_sphere.estimation.partitioned.PartitionedBackend` (submaps on
    workers, the separator solved centrally).
    """

    #: the current linearisation's cost at the zero step (set by :meth:`linearize` or,
    #: at the latest, by the :meth:`solve` after it)
    model_cost: float

    def linearize(self) -> None:
        """Linearise at the current state (or have the next :meth:`solve` do it)."""

    def solve(self, lam: float) -> float | None:
        """Solve the linear system damped by ``lambda * I``.

        Returns the step's predicted decrease of the undamped linearised cost, or
        None when the damped system is indeterminate (a failed step).
        """

    def evaluate(self) -> float:
        """The cost at the trial point: the current state retracted by the last step solved."""

    def accept(self) -> None:
        """Make the last evaluated trial point the current state."""


class LambdaDamping:
    """The damping ``lambda * I`` on some variables, as GTSAM's LM adds it to a linear system.

    One unit ``gtsam.JacobianFactor`` per variable, built once; :meth:`damped` sets
    their sigma ``1 / sqrt(lambda)`` (``setModel`` gives the isotropic model of
    equal sigmas) and appends them to a linearisation.

    Parameters
    ----------
    dims : iterable of (int, int)
        ``(key, dimension)`` of each damped variable (tangent-space dimension).
    """

    def __init__(self, dims):
        self.graph = gtsam.GaussianFactorGraph()
        ds = []
        for k, d in dims:
            self.graph.add(
                gtsam.JacobianFactor(k, np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d))
            )
            ds.append(d)
        # the graph's own factors (add() stores a copy): setModel acts on what the solver sees
        self._factors = [(self.graph.at(q), d) for q, d in enumerate(ds)]

    def damped(self, lin: gtsam.GaussianFactorGraph, lam: float) -> gtsam.GaussianFactorGraph:
        """``lin`` and ``lambda * I`` on the damped variables (a new graph; ``lin`` is shared)."""
        sigma = 1.0 / math.sqrt(lam)
        sigmas: dict[int, np.ndarray] = {}
        for factor, d in self._factors:
            sig = sigmas.get(d)
            if sig is None:
                sig = sigmas[d] = np.full(d, sigma)
            factor.setModel(False, sig)
        damped = gtsam.GaussianFactorGraph()
        damped.push_back(lin)
        damped.push_back(self.graph)
        return damped


def lm_driver(
    backend: LMBackend,
    params: gtsam.LevenbergMarquardtParams,
    error: float,
    *,
    lam: float | None = None,
    iteration: int = 0,
    gtsam_steps: bool = False,
    on_iteration: Callable[[LMIteration], None] | None = None,
) -> dict:
    """The package's one graph Levenberg-Marquardt loop: damping, acceptance, status.

    GTSAM's default LM: ``lambda`` divided by ``lambdaFactor`` after an accepted step
    (not below ``lambdaLowerBound``) and multiplied after a rejected one or an
    indeterminate system. Converged when an accepted step decreased the cost by at
    most ``max(absoluteErrorTol, relativeErrorTol * cost)``
    (:func:`decrease_converged`) or the cost fell below ``errorTol``; stalled when no
    step lowered the cost before ``lambda`` passed ``lambdaUpperBound``. The backend
    holds the state and does the linear algebra: :func:`levenberg_marquardt` on one
    graph, :func:`~gtsam_sphere.estimation.partitioned.refine_partitioned` on submaps.

    Parameters
    ----------
    backend : LMBackend
        Its current state is the start; at the end, the last accepted state.
    params : gtsam.LevenbergMarquardtParams
        ``maxIterations``, ``relativeErrorTol``, ``absoluteErrorTol``, ``errorTol``,
        ``lambdaInitial``, ``lambdaFactor``, ``lambdaLowerBound``,
        ``lambdaUpperBound`` are used.
    error : float
        Cost of the backend's current state.
    lam : float or None
        Damping to start from (a resumed run's); None: ``lambdaInitial``.
    iteration : int
        Iterations already done (a resumed run's); the run stops at ``maxIterations``.
    gtsam_steps : bool
        Take and refuse steps as ``gtsam.LevenbergMarquardtOptimizer`` does (see
        :func:`levenberg_marquardt`). Default: a step is accepted when it lowers the
        cost and its predicted decrease is positive.
    on_iteration : callable(LMIteration) or None
        Called after each accepted step and, with ``gtsam_steps``, after the last
        iteration when it took no step.

    Returns
    -------
    dict
        ``iterations`` (int, ``iteration`` included), ``error``, ``status``
        (:class:`~gtsam_sphere.core.least_squares.LMStatus`), ``converged`` (bool),
        ``lambda``, ``iteration_s`` (wall-clock seconds of each iteration of this run).
    """
    p = params
    lam = p.getlambdaInitial() if lam is None else lam
    iteration_s: list[float] = []
    status = LMStatus.MAX_ITERATIONS
    while iteration < p.getMaxIterations():
        t0 = time.perf_counter()
        backend.linearize()
        accepted = negligible = False
        while gtsam_steps or lam <= p.getlambdaUpperBound():
            predicted = backend.solve(lam)
            if predicted is None:  # as GTSAM's LM: an indeterminate system is a failed step
                lam *= p.getlambdaFactor()
                if gtsam_steps and lam >= p.getlambdaUpperBound():
                    break
                continue
            if gtsam_steps:
                # GTSAM's tryLambda: a valid step (predicted >= 0) is accepted when the
                # model's fidelity exceeds its floor; a negligible cost change ends the
                # search for a damping without a step
                success = False
                model = backend.model_cost
                if predicted < 0 and -predicted <= _ROUNDING * model:
                    # no decrease beyond rounding at any damping (perfect data at the
                    # noise floor): converged, where GTSAM would raise lambda to its bound
                    # and stall
                    negligible = True
                    break
                if predicted >= 0:
                    trial_error = backend.evaluate()
                    change = error - trial_error
                    if predicted > _EPS * model:
                        success = change / predicted > GTSAM_MIN_MODEL_FIDELITY
                    negligible = abs(change) < p.getRelativeErrorTol() * error
            else:
                trial_error = backend.evaluate()
                success = trial_error < error and predicted > 0
            if success:
                lam = max(lam / p.getlambdaFactor(), p.getlambdaLowerBound())
                accepted = True
                break
            if negligible:
                break
            lam *= p.getlambdaFactor()
            if gtsam_steps and lam >= p.getlambdaUpperBound():
                break
        iteration_s.append(time.perf_counter() - t0)
        iteration += 1
        if not accepted:
            if gtsam_steps and on_iteration is not None:  # an iteration without a step
                on_iteration(LMIteration(iteration, error, lam, iteration_s[-1], negligible))
            # negligible: GTSAM's own convergence test then sees no decrease (converged);
            # otherwise the damping reached its upper bound (stalled), as optimize() says
            status = LMStatus.CONVERGED if negligible else LMStatus.STALLED
            break
        previous = error
        backend.accept()
        error = trial_error
        done = (
            decrease_converged(previous, error, p.getAbsoluteErrorTol(), p.getRelativeErrorTol())
            or error < p.getErrorTol()
        )
        if on_iteration is not None:
            on_iteration(LMIteration(iteration, error, lam, iteration_s[-1], done))
        if done:
            status = LMStatus.CONVERGED
            break
    return {
        "iterations": iteration,
        "error": error,
        "status": status,
        "converged": status is LMStatus.CONVERGED,
        "lambda": lam,
        "iteration_s": iteration_s,
    }


class GraphBackend:
    """:class:`LMBackend` of a ``gtsam.NonlinearFactorGraph`` in this process.

    Linearises and evaluates on Python-owned ``Values`` through the factor engine's
    passes (see :func:`levenberg_marquardt`); damping, elimination and retraction
    are GTSAM's C++.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    initial : gtsam.Values
        Not modified.
    ordering : gtsam.Ordering or None
        Elimination ordering; None: COLAMD of the first linearisation.

    Attributes
    ----------
    values : gtsam.Values
        The current state (not to be modified).
    error : float
        Its cost (GTSAM's error: half the weighted sum of squares).
    """

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        initial: gtsam.Values,
        ordering: gtsam.Ordering | None = None,
    ):
        self.graph = graph
        self.ordering = ordering
        self.values = gtsam.Values(initial)
        # the passes at one Values share a TrustedPass (no Values is modified here), and the
        # evaluation of a point LM may step to next computes its Jacobians on the way
        self.passes = TrustedPass(self.values, jacobians=True)
        with self.passes:
            self.error = graph.error(self.values)
        self.zero = self.values.zeroVectors()
        self.damping = LambdaDamping((k, len(self.zero.at(k))) for k in self.values.keys())
        self.lin = self.delta = self._trial = None
        self.use_qr = False
        self.model_cost = math.nan
        self._first_trial = True

    def linearize(self) -> None:
        """Linearise at the current state (the Jacobians its evaluation computed)."""
        with self.passes:
            self.lin = self.graph.linearize(self.values)
        if self.ordering is None:
            self.ordering = gtsam.Ordering.Colamd(gtsam.VariableIndex(self.lin))
        self.model_cost = self.lin.error(self.zero)
        # after a rejected step, evaluate the next trials' cost only
        self._first_trial = True

    def solve(self, lam: float) -> float | None:
        """Multifrontal elimination of the damped system: Cholesky, then QR for good.

        Cholesky factors the normal equations, which square the Jacobian's condition
        number; it finds a damped system indeterminate that is not (``lambda > 0``) when
        that number nears ``1e8`` (a radial mapping of six terms over 130 degrees of
        incidence). LM then raised the damping instead and crawled: a 262 deg sphere
        lens took 100 iterations at 1 % each, where QR of the Jacobian (twice the
        elimination time) converges in 7. So the first indeterminate Cholesky is
        retried with QR, and this backend keeps QR.
        """
        damped = self.damping.damped(self.lin, lam)
        try:
            if self.use_qr:
                self.delta = damped.optimize(self.ordering, gtsam.EliminateQR)
            else:
                self.delta = damped.optimize(self.ordering)
        except RuntimeError as exc:
            if "ndeterminate" not in str(exc):
                raise
            if self.use_qr:
                return None
            self.use_qr = True
            return self.solve(lam)
        if not np.all(np.isfinite(self.delta.vector())):
            return None
        return self.model_cost - self.lin.error(self.delta)

    def evaluate(self) -> float:
        """Retract and evaluate; the first trial of an iteration also computes Jacobians."""
        trial = self.values.retract(self.delta)
        passes = TrustedPass(trial, jacobians=self._first_trial)
        self._first_trial = False
        with passes:
            trial_error = self.graph.error(trial)
        self._trial = (trial, passes, trial_error)
        return trial_error

    def accept(self) -> None:
        """The trial becomes the current state."""
        self.values, self.passes, self.error = self._trial


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: gtsam.LevenbergMarquardtParams | None = None,
    ordering: gtsam.Ordering | None = None,
    on_iteration: Callable[[int, float, gtsam.Values], None] | None = None,
    gtsam_steps: bool = False,
) -> tuple[gtsam.Values, dict]:
    """Levenberg-Marquardt driven from Python, for graphs holding many ``CustomFactor`` s.

    :func:`lm_driver` on a :class:`GraphBackend` (:func:`optimize` runs GTSAM's own
    optimisers). Why: GTSAM's C++ optimisers hand their internal ``gtsam.Values``
    to every ``CustomFactor`` callback, and the Python wrapper (pybind11) copies a
    ``Values`` that Python does not own before each call. Inside
    ``gtsam.LevenbergMarquardtOptimizer`` a callback therefore costs time
    proportional to the number of variables, and a graph of Python factors costs
    ``O(factors x variables)`` per iteration (measured: 22 us per callback with 100
    variables, 2.3 ms with 10,000). This loop linearises and evaluates the graph on
    Python-owned ``Values`` (no copy) and leaves the damping, elimination and
    retraction to GTSAM's C++. For ``gtsam.ISAM2``, hold
    ``isam.getLinearizationPoint()`` (a reference to its internal ``Values``) in a
    variable for as long as the ``ISAM2`` lives: the callbacks then receive that
    registered object instead of a copy.

    The algorithm is GTSAM's default LM (:func:`lm_driver`): damping ``lambda * I``
    on every variable, COLAMD ordering computed once, multifrontal elimination
    (Cholesky preferred); an indeterminate linear system counts as a rejected step
    (``lambda`` grows), as in GTSAM. The status has the meaning of :func:`optimize`'s.

    The factor engine's blocks (:mod:`~gtsam_sphere.estimation.engine`) are
    evaluated once per pass (:class:`~gtsam_sphere.estimation.engine.TrustedPass`),
    all blocks in one numpy call. The cost evaluation of an iteration's first trial
    step also computes their Jacobians (LM usually accepts it, and the next
    linearisation is at that point), so the linearisation at an accepted step only
    hands the Jacobians over; a rejected step costs that extra work once.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    initial : gtsam.Values
        Not modified.
    params : gtsam.LevenbergMarquardtParams or None
        As :func:`lm_driver`; GTSAM's defaults if None.
    ordering : gtsam.Ordering or None
        Elimination ordering; None: COLAMD of the first linearisation.
    on_iteration : callable(int, float, gtsam.Values) or None
        Called with ``(0, initial error, initial)`` and, after each accepted step, with
        ``(iteration, error, values)`` (GTSAM's error: half the weighted sum of squares;
        ``values`` the accepted state, not to be modified).
    gtsam_steps : bool
        Take and refuse steps exactly as ``gtsam.LevenbergMarquardtOptimizer`` does
        (its ``tryLambda``; :func:`optimize` uses this): a step is accepted when the
        predicted decrease is not negative and the model fidelity (actual over
        predicted decrease) exceeds :data:`GTSAM_MIN_MODEL_FIDELITY`; when the cost
        change of a trial is below ``relativeErrorTol`` of the cost, the iteration ends
        without a step and the run has converged; the damping gives up when it reaches
        ``lambdaUpperBound`` (stalled). One departure: a predicted decrease that is
        negative only by rounding (``64 eps`` of the linearised cost; perfect data at
        the noise floor) ends the run converged, where GTSAM would raise the damping
        to its bound and stall. Every iteration, with or without a step, is
        reported to ``on_iteration``. Default (False): a step is accepted when it lowers
        the cost, and a run without a lowering step before the upper bound is stalled.

    Returns
    -------
    values : gtsam.Values
        The last accepted state.
    info : dict
        ``initial_error`` and :func:`lm_driver`'s ``iterations``, ``error``,
        ``lambda``, ``iteration_s`` (list of wall-clock seconds per iteration, float),
        ``status`` (:class:`~gtsam_sphere.core.least_squares.LMStatus`),
        ``converged`` (bool: ``status is LMStatus.CONVERGED``).
    """
    p = params or gtsam.LevenbergMarquardtParams()
    backend = GraphBackend(graph, initial, ordering)
    initial_error = backend.error
    report = None
    if on_iteration is not None:
        on_iteration(0, initial_error, backend.values)

        def report(it: LMIteration) -> None:
            on_iteration(it.iteration, it.error, backend.values)

    info = lm_driver(backend, p, initial_error, gtsam_steps=gtsam_steps, on_iteration=report)
    return backend.values, {"initial_error": initial_error, **info}


def marginal_covariances(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys
) -> dict[int, np.ndarray] | None:
    """Marginal covariances of some variables, or None when the system is singular.

    GTSAM's :class:`gtsam.Marginals` first. Its elimination refuses systems that are
    merely ill-conditioned (a 300 deg lens on a 3D object: largest/smallest singular
    value of the whitened Jacobian 2.5e6, and it reported "indeterminate near x5"), so
    when it raises, the same covariance comes from the normal equations
    ``H = A^T A`` of the whitened sparse Jacobian by an LU factorisation with
    pivoting (SciPy's ``splu``), solved for the columns of ``keys`` only, without the
    variables whose columns are all zero (no information, decoupled). A system
    that is singular there too (an exactly zero pivot, or a non-finite or
    non-positive variance) gives None.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
        Whitened factors (noise models included).
    values : gtsam.Values
        The linearisation point (the solution).
    keys : iterable of int
        Variables wanted.

    Returns
    -------
    dict or None
        Key -> covariance (d, d) in the variable's tangent space (units squared of
        its coordinates).
    """
    keys = [int(k) for k in keys]
    try:
        marginals = gtsam.Marginals(graph, values)
        return {k: np.asarray(marginals.marginalCovariance(k)) for k in keys}
    except RuntimeError:
        pass
    import scipy.sparse
    import scipy.sparse.linalg

    linear = graph.linearize(values)
    triplets = linear.sparseJacobian_()  # 1-based (row, column, value); columns by key
    zero = values.zeroVectors()
    offsets, start = {}, 0
    key_set = linear.keys()  # held: iterating a temporary KeySet crashes the binding
    for k in sorted(int(k) for k in key_set):  # the column layout of sparseJacobian_
        offsets[k] = (start, int(zero.at(k).size))
        start += offsets[k][1]
    if any(k not in offsets for k in keys):
        return None
    rows, columns = triplets[0].astype(np.int64) - 1, triplets[1].astype(np.int64) - 1
    in_a = columns < start  # the last column is the right-hand side b
    A = scipy.sparse.csc_matrix(
        (triplets[2][in_a], (rows[in_a], columns[in_a])), shape=(int(rows.max()) + 1, start)
    )
    cols = np.concatenate([np.arange(offsets[k][0], sum(offsets[k])) for k in keys])
    # a variable whose columns are all zero (a target whose every observation a robust
    # stage weighted 0) is decoupled from the others: left out, their marginals are
    # unchanged (stress 225 s22, a 151 deg room: one such target made the system
    # singular, and the lens was reported "not determined")
    used = np.asarray(A.multiply(A).sum(axis=0)).ravel() > 0
    if not used[cols].all():
        return None
    A = A[:, used]
    index = np.cumsum(used) - 1
    rhs = np.zeros((A.shape[1], cols.size))
    rhs[index[cols], np.arange(cols.size)] = 1.0
    try:
        solution = scipy.sparse.linalg.splu((A.T @ A).tocsc()).solve(rhs)
    except RuntimeError:  # exactly singular
        return None
    block = solution[index[cols]]
    block = 0.5 * (block + block.T)
    if not np.all(np.isfinite(block)) or np.any(np.diag(block) <= 0):
        return None
    out, at = {}, 0
    for k in keys:
        d = offsets[k][1]
        out[k] = block[at : at + d, at : at + d]
        at += d
    return out
