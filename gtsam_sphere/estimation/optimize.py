"""Nonlinear least squares on the bundle graph: Levenberg-Marquardt or dogleg.

Wraps GTSAM's optimizers, iterating one step at a time so that progress is
shown and the cost history is kept (the paper's Figure 5).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..core._compat import StrEnum


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
        Stop when the cost decreases by less than this fraction.
    absolute_tolerance : float
        Stop when the cost decreases by less than this.
    """

    kind: OptimizerKind = OptimizerKind.LM
    max_iterations: int = 100
    relative_tolerance: float = 1e-9
    absolute_tolerance: float = 1e-9


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
    status : str
        ``"converged"``, ``"max-iterations"`` or ``"stalled: ..."``.
    """

    values: gtsam.Values
    history: list[dict] = field(default_factory=list)
    converged: bool = False
    status: str = ""

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
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    else:
        opt = gtsam.DoglegOptimizer(graph, initial, params)
    t0 = time.perf_counter()
    cost = opt.error()
    history = [{"iteration": 0, "cost": cost, "seconds": 0.0}]
    result = OptimizationResult(values=initial, history=history)
    if progress:
        progress(f"{label}iteration   0  cost {cost:.6e}")
    status = "max-iterations"
    best_cost, best_values = cost, initial
    for it in range(1, options.max_iterations + 1):
        try:
            opt.iterate()
        except RuntimeError as exc:  # indeterminate system, cheirality, ...
            status = f"stalled: {str(exc).strip().splitlines()[0]}"
            break
        new_cost = opt.error()
        history.append({"iteration": it, "cost": new_cost, "seconds": time.perf_counter() - t0})
        if progress:
            progress(f"{label}iteration {it:3d}  cost {new_cost:.6e}")
        if not np.isfinite(new_cost) or new_cost > 1e3 * max(best_cost, 1e-300):
            status = (
                "diverged: cost is not finite"
                if not np.isfinite(new_cost)
                else (f"diverged: cost grew from {best_cost:.3e} to {new_cost:.3e}")
            )
            break
        if new_cost <= best_cost:
            best_cost, best_values = new_cost, opt.values()
        decrease = cost - new_cost
        if (
            kind is OptimizerKind.LM
            and decrease <= 0
            and opt.lambda_() >= params.getlambdaUpperBound()
        ):
            status = "stalled: LM damping reached its upper bound"
            break
        if 0 <= decrease <= max(options.absolute_tolerance, options.relative_tolerance * cost):
            status = "converged"
            break
        if decrease < 0 and kind is OptimizerKind.DOGLEG:
            status = "stalled: dogleg could not decrease the cost"
            break
        cost = new_cost
    # the best state seen (LM never accepts an increase; dogleg and a diverging
    # system can end above it)
    result.values = opt.values() if opt.error() <= best_cost else gtsam.Values(best_values)
    result.converged = status == "converged"
    result.status = status
    return result


def stderr_progress(line: str) -> None:
    """Default progress sink: one line on standard error."""
    print(line, file=sys.stderr, flush=True)
