"""Learned measurement corrections: kNN regression on the adjustment's residuals.

The paper's grey-box loop (Chow et al. 2018, Sec. 3): adjust -> train a
k-nearest-neighbour regressor mapping image position to the corrections
``(dx, dy)`` -> rewrite the measurements -> rebuild the graph -> adjust, until
the reprojection error and the cross-validation score are both stable.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sklearn.neighbors import NearestNeighbors

# the correction model itself lives in the core (issue 14); re-exported here
from ..core.camera import has_radial_brown
from ..core.correction_model import DEGREES as DEGREES
from ..core.correction_model import K_GRID as K_GRID
from ..core.correction_model import WEIGHTS as WEIGHTS
from ..core.correction_model import KNNCorrection as KNNCorrection
from ..core.correction_model import NeighbourSearches as NeighbourSearches
from ..core.correction_model import correction_from_dict as correction_from_dict
from ..core.correction_model import local_fit as local_fit
from ..core.correction_model import memoised_search as memoised_search
from ..core.correction_model import neighbours_without_self as neighbours_without_self
from ..core.robust import robust_sigma_px


def _inlier_rms(adj) -> float:
    """RMS (px) of the residuals within 5 sigma: blunders must not steer the loop."""
    r = np.linalg.norm(adj.residuals_px, axis=1)
    keep = r < 5.0 * adj.sigma_px
    return float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float(np.sqrt(np.mean(r**2)))


def _close(old: float, new: float, tol: float) -> bool:
    """``new`` within the relative tolerance ``tol`` of ``old`` (> 0)."""
    return abs(old - new) <= tol * max(old, 1e-12)


def _rms(residuals_px: np.ndarray, mask: np.ndarray) -> float:
    """RMS (px) of the residuals of the observations in ``mask``."""
    r2 = np.sum(residuals_px[mask] ** 2, axis=1)
    return float(np.sqrt(np.mean(r2))) if len(r2) else float("nan")


def blunders(uv_px: np.ndarray, residuals_px: np.ndarray, sigma_px: float) -> np.ndarray:
    """Observations that are blunders, (N,) bool: beyond 5 sigma and unlike their image
    neighbours (:func:`consistent_with_neighbours`).

    A residual beyond 5 sigma that its neighbours share is a systematic error the model
    does not hold (large at the border of a wide lens), not a blunder: a blunder is
    gross relative to its neighbours, not only to the global sigma.

    Parameters
    ----------
    uv_px, residuals_px : ndarray, shape (N, 2)
        Raw pixels and the adjustment's residuals ``measured - predicted`` (px).
    sigma_px : float
        The adjustment's robust scale (px).
    """
    residuals_px = np.asarray(residuals_px, float).reshape(-1, 2)
    out = np.linalg.norm(residuals_px, axis=1) > 5.0 * sigma_px
    if out.any():
        out &= ~consistent_with_neighbours(uv_px, residuals_px)
    return out


def consistent_with_neighbours(
    uv_px: np.ndarray,
    target_px: np.ndarray,
    k: int = 12,
    threshold: float = 5.0,
    passes: int = 3,
    searches: NeighbourSearches | None = None,
) -> np.ndarray:
    """Observations whose target agrees with their image neighbours', (N,) bool.

    A blunder (a mislabelled target, a gross offset) is a point-wise jump in
    the correction an observation needs; a lens mapping the adjustment cannot
    represent is a large but smooth field, large at the image border. The
    adjustment's robust weights cannot tell them apart (both have large
    residuals), so the training set is chosen here instead: each target is
    compared with the local linear fit through its ``k`` nearest other
    observations (no first-order bias from the field's gradient or from
    one-sided neighbours), in ``passes`` passes (each without the neighbours
    the previous pass rejected: a blunder among the neighbours tilts the
    plane); an observation is inconsistent beyond ``threshold``
    times the robust scale of these deviations, ``median / sqrt(2 ln 2)``
    (the median of the norm of a 2-D normal).

    Parameters
    ----------
    uv_px, target_px : ndarray, shape (N, 2)
        Raw pixels and the corrections they need (px).
    k : int
        Neighbours of the local fit.
    threshold : float
        Rejection threshold in robust sigmas.
    passes : int
        Rejection passes.
    searches : NeighbourSearches, optional
        Memo of the neighbour search (the same pixels every round of the loop).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    n = len(uv_px)
    if n <= k + 3:
        return np.ones(n, bool)
    dist, ind = memoised_search(
        searches,
        ("consistent", NeighbourSearches.digest(uv_px), k),
        lambda: neighbours_without_self(NearestNeighbors().fit(uv_px), uv_px, k),
    )
    good = np.ones(n, bool)
    for _ in range(passes):
        pred = local_fit(uv_px, target_px, uv_px, ind, dist, "uniform", 1, good[ind])
        dev = np.linalg.norm(target_px - pred, axis=1)
        good = dev <= threshold * robust_sigma_px(dev[good], 1e-9)
    return good


def train_correction(
    uv_px: np.ndarray,
    target_px: np.ndarray,
    seed: int,
    degree: int | None,
    train=None,
    searches: NeighbourSearches | None = None,
) -> tuple[KNNCorrection, np.ndarray, np.ndarray]:
    """One training step of the grey-box loop: fit the kNN field, predict every
    observation's correction (the training observations without themselves).

    Parameters
    ----------
    uv_px : ndarray, shape (N, 2)
        Raw pixels.
    target_px : ndarray, shape (N, 2)
        The correction each observation needs (current correction + residual), px.
    seed : int
    degree : int or None
        :class:`KNNCorrection`'s local fit degree (None: chosen by cross-validation).
    train : ndarray of bool, shape (N,), optional
        The training set; default the observations consistent with their neighbours
        (:func:`consistent_with_neighbours`).
    searches : NeighbourSearches, optional
        Memo of the neighbour searches, shared by the rounds of :func:`grey_box_loop`.

    Returns
    -------
    model : KNNCorrection
    corrections : ndarray, shape (N, 2)
    train : ndarray of bool, shape (N,)
    """
    if train is None:
        train = consistent_with_neighbours(uv_px, target_px, searches=searches)
    model = KNNCorrection(random_state=seed, degree=degree)
    model.fit(uv_px[train], target_px[train], searches=searches)
    corrections = model.predict(uv_px)
    # no observation corrects itself
    corrections[train] = model.predict_without_self(searches)
    return model, corrections, train


def grey_box_loop(problem, adj, optimizer, options, say: Callable[[str], None], adjust):
    """Alternate kNN training and adjustment until both are stable.

    Each round trains on the total correction each observation needs,
    ``current correction + residual``, rewrites the measurements with the
    prediction, rebuilds the graph and adjusts. The training set is every
    observation whose total correction agrees with its image neighbours'
    (:func:`consistent_with_neighbours`): blunders are left out, the border
    of a wide lens is not, however large its residuals (``knn["train"] =
    "weights"`` restores the former rule, observations down-weighted below 0.5
    left out). The kNN regressor is plain (``knn["degree"] = 0``, the default
    on top of a radial or Brown lens model), local linear (1) or whichever of
    the two the cross-validation prefers in that round (None, the default of
    the pure sphere mapping), see :class:`KNNCorrection`.

    Stops when the RMS residual (of the training set of the round, in the
    previous and the new adjustment) and the CV score both change by less
    than ``knn["tolerance"]`` (relative, default 2%) between rounds, or when both
    come back within it to those of the round before the previous one (a cycle of
    two rounds: the training set flips between two choices, which further rounds only
    repeat; a 46 deg pinhole room of 161 observations with 2 % blunders alternated 145
    and 142 trained, CV RMS 0.0969 and 0.0902 px, for 25 rounds and was not trusted at
    1.00x the oracle's 3D error), or after
    ``knn["max_rounds"]`` (default 25: with the sphere mapping the field
    is hundreds of pixels and the poses and ``c`` give up what they absorbed
    in the first adjustment over 10-20 rounds; a limit of 8 on top of a radial or
    Brown model, tried in session 15, left the narrow pinhole of a mixed rig not
    trusted). The round with the lowest RMS (of the
    observations within 5 sigma: blunders cannot steer it) is kept.

    ``adjust`` is :func:`gtsam_sphere.estimation.calibrate.adjust` (passed in by the
    calibration, so that this module does not import the one that imports it).

    Returns
    -------
    adj : Adjustment
    model : KNNCorrection
    history : list of dict
        Optimiser iterations of every round, with ``knn_round`` and
        ``cv_rmse_px`` keys.
    stable : bool
        Both figures became stable within ``knn["max_rounds"]`` (False: the loop ran
        out of rounds, which the calibration reports as a reason not to trust it).
    rounds : int
        Rounds run (round 0, the adjustment without a correction, not counted).
    """
    # local-linear kNN pays where the field is hundreds of pixels (the pure sphere
    # mapping); on top of a parametric lens (radial, Brown) the field is small and smooth
    # and the plain average generalises better to new views (fish_1 leave-one-view-out:
    # 0.262 px plain, 0.271 px with the CV's choice), so it stays the paper's plain kNN
    # (decentering and affinity alone do not shape the mapping: the sphere fallback's
    # field is the sphere mapping's, as without them)
    parametric = problem.radial_names is not None or has_radial_brown(problem.brown_names)
    cfg = {
        "max_rounds": 25,
        "tolerance": 0.02,
        "degree": 0 if parametric else None,
        "train": "consistent",
    }
    cfg.update(options.knn or {})
    history = [dict(h, knn_round=0) for h in adj.result.history]
    rms = _inlier_rms(adj)
    best = (rms, adj, None, problem.corrections_px.copy())
    prev_cv = None
    figures: list[tuple[float, float]] = []  # (training RMS, CV RMS) of each round
    say(f"kNN round 0: RMS {rms:.4f} px within 5 sigma (no correction)")
    searches = NeighbourSearches()  # the rounds search the same pixels
    stable = False
    rnd = 0
    for rnd in range(1, int(cfg["max_rounds"]) + 1):
        target = problem.corrections_px + adj.residuals_px
        train = adj.weights >= 0.5 if cfg["train"] == "weights" else None
        model, corrections, train = train_correction(
            problem.uv_px, target, options.seed, cfg["degree"], train, searches
        )
        prev_rms = _rms(adj.residuals_px, train)
        problem.corrections_px = corrections
        # a warm start: the robust stages go on from the previous round's solution and
        # scale (no least-squares stage; a sigma the user gave (--sigma-px) stays fixed)
        adj = adjust(
            problem,
            adj.values,
            optimizer,
            None,
            estimate_sigma=options.sigma_px is None,
            warm=True,
        )
        rms_train = _rms(adj.residuals_px, train)
        rms = _inlier_rms(adj)
        offset = history[-1]["iteration"] + 1
        history += [
            dict(h, iteration=h["iteration"] + offset, knn_round=rnd, cv_rmse_px=model.cv_rmse_px_)
            for h in adj.result.history
        ]
        say(
            f"kNN round {rnd}: k = {model.n_neighbors_} ({model.weights_}, degree "
            f"{model.degree_}), {int(train.sum())} of {len(train)} trained, "
            f"CV RMS {model.cv_rmse_px_:.4f} px, adjustment RMS {rms_train:.4f} px "
            f"(was {prev_rms:.4f}), {rms:.4f} px within 5 sigma"
        )
        if rms < best[0]:
            best = (rms, adj, model, problem.corrections_px.copy())
        tol = cfg["tolerance"]
        if (
            prev_cv is not None
            and _close(prev_rms, rms_train, tol)
            and _close(prev_cv, model.cv_rmse_px_, tol)
        ):
            say(f"kNN loop stable after {rnd} rounds")
            stable = True
            break
        if len(figures) >= 2:
            rms_2, cv_2 = figures[-2]
            if _close(rms_2, rms_train, tol) and _close(cv_2, model.cv_rmse_px_, tol):
                say(f"kNN loop stable after {rnd} rounds (a cycle of two rounds)")
                stable = True
                break
        figures.append((rms_train, model.cv_rmse_px_))
        prev_cv = model.cv_rmse_px_
    if not stable:
        say(f"kNN loop not stable after {cfg['max_rounds']} rounds: the best round is kept")
    _, adj, model, corrections = best
    problem.corrections_px = corrections
    problem.build()  # blocks in step with the kept corrections
    return adj, model, history, stable, rnd
