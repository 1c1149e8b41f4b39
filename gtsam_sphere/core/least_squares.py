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

__all__ = [
    "Damping",
    "LMBatchResult",
    "LMResult",
    "LMStatus",
    "arrow_solve",
    "levenberg_marquardt",
    "levenberg_marquardt_batch",
]


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
    """Marquardt's scaling ``diag(H)`` of H (..., P, P), non-positive entries replaced by 1."""
    d = np.diagonal(H, axis1=-2, axis2=-1).copy()
    d[~(d > 0)] = 1.0
    return d


def ridge_scaling(H: np.ndarray) -> np.ndarray:
    """Scaling ``diag(H) + 1e-12`` of H (..., P, P) (a zero column still gets some damping)."""
    return np.diagonal(H, axis1=-2, axis2=-1) + 1e-12


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


def _take(x: Any, idx: np.ndarray) -> Any:
    """The problems ``idx`` of a batch state (array: leading axis; tuple: each member;
    list: its items)."""
    if isinstance(x, tuple):
        return tuple(_take(e, idx) for e in x)
    if isinstance(x, list):
        return [x[i] for i in idx]
    return np.asarray(x)[idx]


def _put(x: Any, idx: np.ndarray, sub: Any) -> Any:
    """A batch state with the problems ``idx`` replaced by ``sub`` (a copy; as :func:`_take`)."""
    if isinstance(x, tuple):
        return tuple(_put(e, idx, s) for e, s in zip(x, sub))
    if isinstance(x, list):
        out = list(x)
        for i, v in zip(idx, sub):
            out[i] = v
        return out
    out = np.array(x, copy=True)
    out[idx] = sub
    return out


@dataclass
class LMBatchResult:
    """Outcome of :func:`levenberg_marquardt_batch`, one entry per problem.

    Attributes
    ----------
    x : Any
        The batch state of the last accepted points (``x0``'s rows where none was).
    cost : ndarray, shape (B,)
    iterations : ndarray of int, shape (B,)
        Linearisations done per problem.
    status : list of B LMStatus
    damping : ndarray, shape (B,)
        ``lam`` at the end.
    """

    x: Any
    cost: np.ndarray
    iterations: np.ndarray
    status: list
    damping: np.ndarray


def _solve_damped(H: np.ndarray, g: np.ndarray, lam: np.ndarray, s: np.ndarray):
    """Steps ``(H + lam diag(s)) delta = -g`` of a batch, (B, P), and which were singular (B,)."""
    A = H.copy()
    diag = np.einsum("bii->bi", A)  # a view: the damping goes onto the diagonal in place
    diag += lam[:, None] * s
    try:
        return np.linalg.solve(A, -g[..., None])[..., 0], np.zeros(len(H), bool)
    except np.linalg.LinAlgError:  # find the singular ones
        delta = np.zeros_like(g)
        singular = np.zeros(len(H), bool)
        for b in range(len(H)):
            try:
                delta[b] = np.linalg.solve(A[b], -g[b])
            except np.linalg.LinAlgError:
                singular[b] = True
        return delta, singular


def arrow_solve(n_shared: int, block: int) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """A damped solve (the ``solve`` of :func:`levenberg_marquardt_batch`) for normal
    equations of "arrow" structure: ``n_shared`` unknowns coupled with everything (e.g.
    a lens), then blocks of ``block`` unknowns coupled with the shared ones only (e.g.
    one pose per image; ``P = n_shared + m block``).

    The blocks are eliminated (the Schur complement on the shared unknowns, ``m``
    inverses of ``block x block``), so a step costs ``O(m)`` instead of the ``O(P^3)``
    of a dense solve: a refit of the lens and the poses of 300 images solves 6 + 1,800
    unknowns in a few milliseconds.

    Parameters
    ----------
    n_shared : int
        Unknowns first in the layout, coupled with every block.
    block : int
        Size of each block after them.

    Returns
    -------
    callable
        ``solve(H (B, P, P), g (B, P), lam (B,), s (B, P)) -> (delta (B, P), singular
        (B,) bool)``: the steps ``(H + lam diag(s)) delta = -g``; an entry whose damped
        system is singular is flagged and its step left at zero.
    """
    a, q = int(n_shared), int(block)

    def solve(H, g, lam, s):
        n_b, n_p = g.shape
        m = (n_p - a) // q
        if a + m * q != n_p:
            raise ValueError(
                f"normal equations of size {n_p} are not {a} shared unknowns plus blocks of {q}"
            )
        idx = a + np.arange(m)[:, None] * q + np.arange(q)  # (m, q)
        delta = np.zeros_like(g)
        singular = np.zeros(n_b, bool)
        for b in range(n_b):
            d = lam[b] * s[b]
            C = H[b][idx[:, :, None], idx[:, None, :]]  # (m, q, q)
            C[:, np.arange(q), np.arange(q)] += d[idx]
            E = H[b, :a, a:].reshape(a, m, q).transpose(1, 0, 2)  # (m, a, q)
            g_p = g[b, a:].reshape(m, q)
            try:
                C_inv = np.linalg.inv(C)
                EC = E @ C_inv  # (m, a, q)
                S = H[b, :a, :a] + np.diag(d[:a]) - np.einsum("kij,klj->il", EC, E)
                rhs = -g[b, :a] + np.einsum("kij,kj->i", EC, g_p)
                d_s = np.linalg.solve(S, rhs) if a else np.zeros(0)
            except np.linalg.LinAlgError:
                singular[b] = True
                continue
            d_p = -np.einsum("kij,kj->ki", C_inv, g_p + np.einsum("kji,j->ki", E, d_s))
            delta[b, :a] = d_s
            delta[b, a:] = d_p.ravel()
            if not np.all(np.isfinite(delta[b])):
                delta[b] = 0.0
                singular[b] = True
        return delta, singular

    return solve


def levenberg_marquardt_batch(
    x0: Any,
    cost: Callable[[Any], np.ndarray],
    linearize: Callable[[Any], tuple[np.ndarray, np.ndarray]],
    *,
    retract: Callable[[Any, np.ndarray], Any] = _add,
    converged: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
    negligible: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
    feasible: Callable[[Any], np.ndarray] | None = None,
    damping: Damping = Damping(),
    max_iterations: int = 100,
    cost0: np.ndarray | None = None,
    solve: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None,
) -> LMBatchResult:
    """Levenberg-Marquardt on ``B`` independent problems at once (the package's one loop).

    Each problem runs exactly the loop of :func:`levenberg_marquardt` (its own ``lam``,
    tries, acceptance and status); the problems still running share every call, so a
    thousand small fits (e.g. the pose refinements of a RANSAC over many images and lens
    hypotheses) cost a few dozen numpy calls instead of tens of thousands. Each call
    receives the state of the problems it concerns only, in the order of the batch.

    Parameters
    ----------
    x0 : batch state
        ``B`` starting points: an array (B, ...), a tuple of such arrays (e.g.
        ``(R (B, 3, 3), t (B, 3))``) or a list of ``B`` arbitrary objects. Callbacks
        receive sub-batches of the same kind (rows selected).
    cost : callable
        ``cost(x) -> (B',)``.
    linearize : callable
        ``linearize(x) -> (H (B', P, P), g (B', P))``: Gauss-Newton matrices
        ``J^T W J`` and gradients ``J^T W r``.
    retract : callable
        ``retract(x, delta (B', P)) -> x'``; default ``x + delta``.
    converged : callable, optional
        ``converged(cost_before (B',), cost_after (B',), delta (B', P)) -> (B',) bool``,
        asked after each accepted step; default: never.
    negligible : callable, optional
        ``negligible(delta (B', P), g (B', P), cost (B',)) -> (B',) bool``, asked of each
        solved step before it is tried: True ends that problem as converged.
    feasible : callable, optional
        ``feasible(x') -> (B',) bool``: an infeasible trial point is rejected like a
        worse one.
    damping : Damping
        Its ``scaling`` receives ``H`` (B', P, P) and returns (B', P).
    max_iterations : int
        Linearisations at most, per problem.
    cost0 : (B,) array, optional
        ``cost(x0)`` when the caller has it already.
    solve : callable, optional
        ``solve(H (B', P, P), g (B', P), lam (B',), s (B', P)) -> (delta (B', P),
        singular (B',) bool)``: the damped steps ``(H + lam diag(s)) delta = -g``, for
        normal equations with a structure a dense solve ignores (e.g.
        :func:`arrow_solve`); default a dense solve.

    Returns
    -------
    LMBatchResult
    """
    x = x0
    c = np.array(cost(x) if cost0 is None else cost0, dtype=float).reshape(-1)
    n = c.size
    lam = np.full(n, float(damping.initial))
    iterations = np.zeros(n, int)
    tries = np.zeros(n, int)
    status = [LMStatus.MAX_ITERATIONS] * n
    running = np.ones(n, bool)
    relinearize = np.ones(n, bool)
    H = g = s = None
    while True:
        lin = np.flatnonzero(running & relinearize)
        if lin.size:
            spent = lin[iterations[lin] >= max_iterations]
            running[spent] = False  # status stays MAX_ITERATIONS
            lin = lin[iterations[lin] < max_iterations]
        if lin.size:
            iterations[lin] += 1
            H_l, g_l = linearize(_take(x, lin))
            H_l, g_l = np.asarray(H_l, float), np.asarray(g_l, float)
            if H is None:
                H = np.zeros((n, *H_l.shape[1:]))
                g = np.zeros((n, *g_l.shape[1:]))
                s = np.zeros_like(g)
            H[lin], g[lin] = H_l, g_l
            s[lin] = damping.scaling(H_l)
            tries[lin] = 0
            relinearize[lin] = False
        act = np.flatnonzero(running)
        if not act.size:
            break
        # one try of every running problem; those out of tries or damping stall
        gate = lam[act] < damping.ceiling
        if damping.max_tries is not None:
            gate &= tries[act] < damping.max_tries
        for b in act[~gate]:
            status[b] = LMStatus.STALLED
        running[act[~gate]] = False
        act = act[gate]
        if not act.size:
            continue
        tries[act] += 1
        delta, singular = (solve or _solve_damped)(H[act], g[act], lam[act], s[act])
        lam[act[singular]] *= damping.increase_singular
        ok = ~singular
        act, delta = act[ok], delta[ok]
        if negligible is not None and act.size:
            stop = np.asarray(negligible(delta, g[act], c[act]), bool)
            for b in act[stop]:
                status[b] = LMStatus.CONVERGED
            running[act[stop]] = False
            act, delta = act[~stop], delta[~stop]
        if not act.size:
            continue
        x_new = retract(_take(x, act), delta)
        c_new = np.full(act.size, np.inf)
        fine = (
            np.ones(act.size, bool)
            if feasible is None
            else np.asarray(feasible(x_new), bool).reshape(-1)
        )
        if fine.all():
            c_new[:] = cost(x_new)
        elif fine.any():
            c_new[fine] = cost(_take(x_new, np.flatnonzero(fine)))
        better = c_new <= c[act] if damping.accept_equal else c_new < c[act]
        good = fine & np.isfinite(c_new) & better
        lam[act[~good]] *= damping.increase
        if not good.any():
            continue
        acc, kept = act[good], np.flatnonzero(good)
        c_old = c[acc].copy()
        x = _put(x, acc, _take(x_new, kept))
        c[acc] = c_new[good]
        lam[acc] = np.maximum(lam[acc] / damping.decrease, damping.floor)
        relinearize[acc] = True
        if converged is not None:
            done = np.asarray(converged(c_old, c[acc], delta[good]), bool).reshape(-1)
            for b in acc[done]:
                status[b] = LMStatus.CONVERGED
            running[acc[done]] = False
    return LMBatchResult(x, c, iterations, status, lam)


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
    solve: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None,
) -> LMResult:
    """Minimise ``cost(x)`` by Levenberg-Marquardt on the normal equations.

    Each iteration linearises at the current point, then solves
    ``(H + lam diag(s)) delta = -g`` for growing ``lam`` until the point
    ``retract(x, delta)`` is feasible and its cost finite and lower (or equal, with
    ``damping.accept_equal``); the point moves there and ``lam`` shrinks. This is
    :func:`levenberg_marquardt_batch` of one problem.

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
    solve : callable, optional
        The damped solve, batched as in :func:`levenberg_marquardt_batch` (B = 1).

    Returns
    -------
    LMResult
    """

    def lin(xs):
        H, g = linearize(xs[0])
        return np.asarray(H, float)[None], np.asarray(g, float)[None]

    fit = levenberg_marquardt_batch(
        [x0],
        lambda xs: np.array([cost(xs[0])], dtype=float),
        lin,
        retract=lambda xs, d: [retract(xs[0], d[0])],
        converged=None
        if converged is None
        else lambda c0, c1, d: np.array([bool(converged(float(c0[0]), float(c1[0]), d[0]))]),
        negligible=None
        if negligible is None
        else lambda d, g, c: np.array([bool(negligible(d[0], g[0], float(c[0])))]),
        feasible=None if feasible is None else lambda xs: np.array([bool(feasible(xs[0]))]),
        damping=damping,
        max_iterations=max_iterations,
        cost0=None if cost0 is None else np.array([cost0], dtype=float),
        solve=solve,
    )
    return LMResult(
        fit.x[0], float(fit.cost[0]), int(fit.iterations[0]), fit.status[0], float(fit.damping[0])
    )
