"""Split a map into submaps: a partition of the images over their covisibility.

Two images are covisible when they observe a common landmark; the covisibility
graph has an edge for each such pair. The partition orders the images along
that graph with the reverse Cuthill-McKee ordering (a breadth-first ordering
from a peripheral image that keeps covisible images close, E. Cuthill and
J. McKee, "Reducing the bandwidth of sparse symmetric matrices", ACM 1969;
``scipy.sparse.csgraph.reverse_cuthill_mckee``), then cuts that order into
``n_parts`` contiguous runs of about equal numbers of observations (each cut
moved, within a tolerance on the balance, to where the fewest landmarks are
seen from both sides). A banded
order makes the cuts small: only the landmarks seen from both sides of a cut
(and poses tied by odometry across it) are shared.

Each observation belongs to the submap of its image, so every factor is in
exactly one submap and the map's cost is the sum of the submaps' costs. The
variables in more than one submap are the separator
(:func:`separator_keys`); every other variable is interior to one submap.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import InputError

__all__ = ["covisibility_partition", "separator_keys"]


def covisibility_partition(
    obs_image: np.ndarray,
    obs_point: np.ndarray,
    n_parts: int,
    n_images: int | None = None,
    balance: float = 0.1,
) -> np.ndarray:
    """Part of each image: covisibility order cut into runs balanced by observations.

    Parameters
    ----------
    obs_image, obs_point : array_like of int, shape (N,)
        Image row and landmark row of each observation.
    n_parts : int
        Number of submaps (>= 1, at most the number of images).
    n_images : int, optional
        Number of images M (default ``max(obs_image) + 1``).
    balance : float
        Each cut may move by up to this fraction of a part's share of the
        observations from the balanced position, to where it cuts the fewest
        landmarks (a room's door instead of its middle).

    Returns
    -------
    part : ndarray of int, shape (M,)
        Submap index ``0 .. n_parts - 1`` of every image; each part is non-empty.
    """
    import scipy.sparse
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    obs_image = np.asarray(obs_image, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    M = int(n_images if n_images is not None else obs_image.max() + 1)
    if not 1 <= n_parts <= M:
        raise InputError(f"partitions must be between 1 and the number of images ({M})")
    if n_parts == 1:
        return np.zeros(M, np.int64)
    L = int(obs_point.max()) + 1
    A = scipy.sparse.csr_matrix((np.ones(len(obs_image)), (obs_image, obs_point)), shape=(M, L))
    C = (A @ A.T).tocsr()
    order = np.asarray(reverse_cuthill_mckee(C, symmetric_mode=True), np.int64)
    weight = np.bincount(obs_image, minlength=M).astype(float)[order]
    cum = np.r_[0.0, np.cumsum(weight)]
    # landmarks cut by a cut before position c of the order: first view < c <= last view
    pos = np.empty(M, np.int64)
    pos[order] = np.arange(M)
    p_obs = pos[obs_image]
    lo = np.full(L, M, np.int64)
    hi = np.full(L, -1, np.int64)
    np.minimum.at(lo, obs_point, p_obs)
    np.maximum.at(hi, obs_point, p_obs)
    crossing = np.zeros(M + 1, np.int64)
    np.add.at(crossing, lo + 1, 1)
    np.add.at(crossing, hi + 1, -1)
    crossing = np.cumsum(crossing)  # crossing[c]: landmarks seen before and from c on
    # each cut: the smallest crossing within +-balance of a part's share around its target
    share = cum[-1] / n_parts
    cuts = []
    for k in range(1, n_parts):
        window = np.flatnonzero(np.abs(cum - k * share) <= balance * share)
        window = window[(window > (cuts[-1] if cuts else 0)) & (window < M)]
        if len(window) == 0:
            window = np.array(
                [max(int(np.searchsorted(cum, k * share)), (cuts[-1] if cuts else 0) + 1)]
            )
        cuts.append(int(window[np.argmin(crossing[window])]))
    cuts = np.minimum(np.array(cuts), M - n_parts + np.arange(1, n_parts))
    cuts = np.maximum.accumulate(np.maximum(cuts, np.arange(1, n_parts)))
    part_in_order = np.searchsorted(cuts, np.arange(M), side="right")
    part = np.empty(M, np.int64)
    part[order] = part_in_order
    return part


def separator_keys(submap_keys: list[np.ndarray]) -> np.ndarray:
    """Keys that occur in more than one submap.

    Parameters
    ----------
    submap_keys : list of ndarray of uint64
        The variable keys of each submap (each without repeats).

    Returns
    -------
    ndarray of uint64, sorted
    """
    allk = np.concatenate([np.asarray(k, np.uint64) for k in submap_keys])
    keys, counts = np.unique(allk, return_counts=True)
    return keys[counts > 1]
