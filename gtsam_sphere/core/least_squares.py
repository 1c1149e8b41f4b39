"""One dense Levenberg-Marquardt loop for the package's small numpy problems (issue 14).

The pose refinements (``core.p3p``, ``estimation.resect``) and the export's model
fits (``apps.export``) solve a few to a dozen unknowns by damped Gauss-Newton. They
share this loop; what differs between them is data, not code:

- the normal equations ``(H, g)`` at a point (``linearize``; ``g = J^T W r``, so the
  step solves ``(H + lam diag(s)) delta = -g``), which carry any robust (IRLS)
  weights;
- the cost (``cost``), robust or not, and how a step moves the point
  (``retract``: ``x + delta`` by default, ``Exp(w) R`` for a rotation);
- the damping schedule (:class:`Damping`) and the convergence test
  (``converged(cost_before, cost_after, delta)``).

The graph adjustment itself runs in GTSAM (``estimation.optimize``); this is for the
dense problems around it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._compat import StrEnum

__all__ = ["Damping", "LMResult", "LMStatus", "levenberg_marquardt"]


class LMStatus(StrEnum):
    """How a :func:`levenberg_marquardt` run ended."""

    #: the convergence test passed after an accepted step (or the next step was negligible)
    CONVERGED = "converged"
    #: no step lowered the cost (the damping ran out of tries or past its ceiling)
    STALLED = "stalled"
    #: the iteration limit was reached, every iteration having moved the point
    MAX_ITERATIONS = "max_iterations"
    #: the cost grew past any reason or stopped being finite (the graph optimiser's
    #: dogleg, ``estimation.optimize``; this loop never accepts an increase)
    DIVERGED = "diverged"


def marquardt_scaling(H: np.ndarray) -> np.ndarray:
    """Marquardt's diagonal scaling ``diag(H)``, non-positive entries replaced by 1."""
    d = np.diag(H).copy()
    d[~(d > 0)] = 1.0
    return d


def ridge_scaling(H: np.ndarray) -> np.ndarray:
    """Diagonal scaling ``diag(H) + 1e-12`` (a zero column still gets some damping)."""
    return np.diag(H) + 1e-12


@dataclass(frozen=True)
class Damping:
    """The damping ``lam`` schedule of :func:`levenberg_marquardt`.

    Attributes
    ----------
    initial : float
        ``lam`` at the start.
    increase : float
        Factor on ``lam`` after a rejected step (higher cost, non-finite, infeasible).
    increase_singular : float
        Factor on ``lam`` when the damped system is singular.
    decrease : float
        Divisor of ``lam`` after an accepted step ...
    floor : float
        ... never below this.
    ceiling : float
        Give up an iteration (stalled) once ``lam`` reaches this.
    max_tries : int or None
        Give up an iteration after this many tries (solves attempted); None: no limit.
    accept_equal : bool
        Accept a step that leaves the cost unchanged (``<=``) rather than only one
        that lowers it (``<``).
    scaling : callable
        ``scaling(H) -> s`` (P,), the diagonal ``lam`` multiplies.
    """

    initial: float = 1e-3
    increase: float = 10.0
    increase_singular: float = 10.0
    decrease: float = 10.0
    floor: float = 1e-12
    ceiling: float = math.inf
    max_tries: int | None = None
    accept_equal: bool = False
    scaling: Callable[[np.ndarray], np.ndarray] = marquardt_scaling


@dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes
    ----------
    x : Any
        The last accepted point (``x0`` if none was).
    cost : float
        Its cost.
    iterations : int
        Linearisations done.
    status : LMStatus
    damping : float
        ``lam`` at the end.
    """

    x: Any
    cost: float
    iterations: int
    status: LMStatus
    damping: float

    @property
    def converged(self) -> bool:
        """True unless the iteration limit stopped the run."""
        return self.status is not LMStatus.MAX_ITERATIONS


def _add(x, delta):
    return x + delta


def levenberg_marquardt(
    x0: Any,
    cost: Callable[[Any], float],
    linearize: Callable[[Any], tuple[np.ndarray, np.ndarray]],
    *,
    retract: Callable[[Any, np.ndarray], Any] = _add,
    converged: Callable[[float, float, np.ndarray], bool] | None = None,
    negligible: Callable[[np.ndarray, np.ndarray, float], bool] | None = None,
    feasible: Callable[[Any], bool] | None = None,
    damping: Damping = Damping(),
    max_iterations: int = 100,
    cost0: float | None = None,
) -> LMResult:
    """Minimise ``cost(x)`` by Levenberg-Marquardt on the normal equations.

    Each iteration linearises at the current point, then solves
    ``(H + lam diag(s)) delta = -g`` for growing ``lam`` until the point
    ``retract(x, delta)`` is feasible and its cost finite and lower (or equal, with
    ``damping.accept_equal``); the point moves there and ``lam`` shrinks.

    Parameters
    ----------
    x0 : any
        Start (an array, or any state ``retract`` understands, e.g. ``(R, t)``).
    cost : callable
        ``cost(x) -> float``.
    linearize : callable
        ``linearize(x) -> (H (P, P), g (P,))``: Gauss-Newton matrix ``J^T W J`` and
        gradient ``J^T W r`` at ``x``.
    retract : callable
        ``retract(x, delta (P,)) -> x'``; default ``x + delta``.
    converged : callable, optional
        ``converged(cost_before, cost_after, delta) -> bool``, asked after each
        accepted step; default: never (run to ``max_iterations`` or a stall).
    negligible : callable, optional
        ``negligible(delta, g, cost) -> bool``, asked of each solved step before it is
        tried: True ends the run as converged without taking it (e.g. a predicted
        decrease ``-delta @ g`` below a fraction of the cost).
    feasible : callable, optional
        ``feasible(x') -> bool``: an infeasible trial point is rejected like a worse one.
    damping : Damping
    max_iterations : int
        Linearisations at most.
    cost0 : float, optional
        ``cost(x0)`` when the caller has it already.

    Returns
    -------
    LMResult
    """
    x = x0
    c = float(cost(x)) if cost0 is None else float(cost0)
    lam = damping.initial
    iterations = 0
    status = LMStatus.MAX_ITERATIONS
    while iterations < max_iterations:
        iterations += 1
        H, g = linearize(x)
        s = damping.scaling(H)
        accepted = stop_here = False
        tries = 0
        while lam < damping.ceiling and (damping.max_tries is None or tries < damping.max_tries):
            tries += 1
            try:
                delta = np.linalg.solve(H + lam * np.diag(s), -g)
            except np.linalg.LinAlgError:
                lam *= damping.increase_singular
                continue
            if negligible is not None and negligible(delta, g, c):
                stop_here = True
                break
            x_new = retract(x, delta)
            if feasible is None or feasible(x_new):
                c_new = float(cost(x_new))
                better = c_new <= c if damping.accept_equal else c_new < c
                if math.isfinite(c_new) and better:
                    accepted = True
                    break
            lam *= damping.increase
        if not accepted:
            status = LMStatus.CONVERGED if stop_here else LMStatus.STALLED
            break
        c_old = c
        x, c = x_new, c_new
        lam = max(lam / damping.decrease, damping.floor)
        if converged is not None and converged(c_old, c, delta):
            status = LMStatus.CONVERGED
            break
    return LMResult(x, c, iterations, status, lam)
