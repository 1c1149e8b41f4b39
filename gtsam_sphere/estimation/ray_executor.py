"""Partitioned map refinement on a Ray cluster (``pip install gtsam-sphere[distributed]``).

:class:`RayExecutor` runs :class:`~gtsam_sphere.estimation.partitioned.SubmapHost`
as Ray actors (https://docs.ray.io, "Actors", "Fault tolerance"): each actor
(one worker process, one CPU) holds some submaps, balanced by observations.
Each submap's data is put in the object store once (``ray.put``) and handed to
its actor's constructor; per iteration the driver sends the separator step and
``lambda`` and receives the reduced systems and costs. The submaps' states
(their current values) are returned as object references that stay in the
object store and are passed back to the same actor, so they reach the driver
only for a checkpoint and the final result.

Faults: actors are created with ``max_restarts`` and ``max_task_retries``. A
worker process that dies is restarted by Ray, its constructor runs again from
the same object references (the data, not re-sent by the driver), and the call
that was running or waiting is repeated with the same arguments: the state it
starts from is an argument, so the repeated call gives the same answer and the
iteration goes on.

Ray is imported when an executor is made, never at the package's import: the
package works without it, and :func:`import_ray` raises an
:class:`~gtsam_sphere.core.errors.OptionsError` naming the extra when it is
missing. The package itself must be importable on every node of a real cluster
(installed there, or shipped with Ray's ``runtime_env``).
"""

from __future__ import annotations

import logging

import numpy as np

from ..core.errors import OptionsError
from .map_problem import MapProblem
from .partitioned import SubmapHost

logger = logging.getLogger(__name__)

__all__ = ["RayExecutor", "assign_parts", "import_ray"]

EXTRA_HINT = "pip install 'gtsam-sphere[distributed]' (or pip install 'ray>=2.9')"


def import_ray():
    """The ``ray`` module, or an :class:`OptionsError` naming the extra to install."""
    try:
        import ray
    except ImportError as exc:
        raise OptionsError(f"--engine ray needs Ray, which is not installed: {EXTRA_HINT}") from exc
    return ray


def assign_parts(sizes, n_workers: int) -> list[list[int]]:
    """Submaps per worker: largest first to the least loaded (balanced by observations).

    Parameters
    ----------
    sizes : sequence of int
        Observations of each submap.
    n_workers : int

    Returns
    -------
    list of list of int
        Submap indices of each worker (every worker gets at least one when
        ``n_workers <= len(sizes)``).
    """
    load = np.zeros(n_workers)
    out: list[list[int]] = [[] for _ in range(n_workers)]
    for k in np.argsort(-np.asarray(sizes), kind="stable"):
        w = int(np.argmin(load))
        out[w].append(int(k))
        load[w] += sizes[k]
    return [sorted(p) for p in out if p]


class _ActorHost(SubmapHost):
    """``SubmapHost`` whose submaps arrive as separate (resolved) constructor arguments."""

    def __init__(self, parts: list[int], separator: np.ndarray, resident, *submaps: MapProblem):
        super().__init__(parts, list(submaps), separator, resident)


class RayExecutor:
    """Submaps on Ray actors; the interface of :class:`~.partitioned.LocalExecutor`.

    Parameters
    ----------
    submaps : list of MapProblem, or of recipes (``build() -> MapProblem``, ``n_observations``)
        A recipe is shipped instead of the data and built in its actor.
    separator : ndarray of uint64
    n_workers : int or None
        Actors (worker processes); default: one per submap, at most the
        cluster's CPUs. More actors than CPUs share them (fractional ``num_cpus``).
    address : str or None
        Ray cluster address (``ray.init(address=...)``, e.g. ``"auto"`` or
        ``"ray://head:10001"``); None: a local cluster started here (unless Ray
        is already initialised in this process, which is then used as it is).
    max_restarts : int
        Restarts of a dead actor (Ray ``max_restarts``); its calls are retried
        as many times (``max_task_retries``).
    init_kwargs : dict, optional
        More arguments of ``ray.init`` (``num_cpus``, ``include_dashboard``, ...).
    resident : int or None
        Submaps kept alive per actor between calls (:class:`~.partitioned.SubmapHost`):
        with fewer actors than submaps, e.g. 1, an actor's memory is that of one
        submap's work and the others' data, for more CPU per iteration. None: all.
    """

    def __init__(
        self,
        submaps: list[MapProblem],
        separator: np.ndarray,
        n_workers: int | None = None,
        address: str | None = None,
        max_restarts: int = 4,
        init_kwargs: dict | None = None,
        resident: int | None = None,
    ):
        ray = import_ray()
        self.ray = ray
        self._started = False
        if not ray.is_initialized():
            kwargs = {"include_dashboard": False, "logging_level": logging.WARNING}
            kwargs.update(init_kwargs or {})
            ray.init(address=address, **kwargs)
            self._started = True
        cpus = int(ray.cluster_resources().get("CPU", 1))
        n = len(submaps)
        n_workers = max(1, min(n, n_workers or cpus))
        self.groups = assign_parts([s.n_observations for s in submaps], n_workers)
        self.n_parts = n
        self._refs = [ray.put(s) for s in submaps]  # the data, once; held for restarts
        # one CPU per actor; more actors than CPUs share them (each still one process)
        per_actor = min(1.0, cpus / len(self.groups))
        remote = ray.remote(
            num_cpus=per_actor, max_restarts=max_restarts, max_task_retries=max_restarts
        )(_ActorHost)
        self._sep_ref = sep_ref = ray.put(np.asarray(separator, np.uint64))  # held for restarts
        self.hosts = [
            remote.remote(parts, sep_ref, resident, *[self._refs[k] for k in parts])
            for parts in self.groups
        ]
        self.host_of = {k: self.hosts[w] for w, parts in enumerate(self.groups) for k in parts}

    @classmethod
    def factory(cls, **kwargs):
        """A ``(submaps, separator) -> RayExecutor`` for :func:`~.partitioned.refine_map`."""
        return lambda submaps, separator: cls(submaps, separator, **kwargs)

    def call(self, part: int, method: str, *args, num_returns: int = 1):
        """Submit ``SubmapWorker.method(*args)`` of submap ``part``: object reference(s)."""
        handle = self.host_of[int(part)].call
        if num_returns != 1:
            handle = handle.options(num_returns=num_returns)
        return handle.remote(part, method, *args)

    def get(self, refs):
        """``ray.get``."""
        return self.ray.get(refs)

    def put(self, obj):
        """``ray.put`` (a state read from a checkpoint)."""
        return self.ray.put(obj)

    def infos(self) -> list[dict]:
        """:meth:`SubmapHost.info` of every actor (pid, peak memory, CPU seconds)."""
        return self.ray.get([h.info.remote() for h in self.hosts])

    def shutdown(self) -> None:
        """Stop the actors; stop Ray when this executor started it."""
        for h in self.hosts:
            try:
                self.ray.kill(h)
            except Exception:  # already gone
                logger.debug("actor already gone", exc_info=True)
        self.hosts = []
        if self._started:
            self.ray.shutdown()
