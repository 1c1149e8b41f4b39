"""Learned measurement corrections: kNN regression on the adjustment's residuals.

The paper's grey-box loop (Chow et al. 2018, Sec. 3): adjust -> train a
k-nearest-neighbour regressor mapping image position to the corrections
``(dx, dy)`` -> rewrite the measurements -> rebuild the graph -> adjust, until
the reprojection error and the cross-validation score are both stable.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.model_selection import GridSearchCV, KFold
from sklearn.neighbors import KNeighborsRegressor

from .camera import check_uv

K_GRID = (3, 5, 8, 12, 16, 24, 32, 48, 64)


class KNNCorrection(RegressorMixin, BaseEstimator):
    """k-nearest-neighbour model of the measurement corrections, px -> px.

    Parameters
    ----------
    n_neighbors : int or None
        ``None`` chooses ``k`` from ``k_grid`` by ``cv_folds``-fold cross-validation.
    weights : {"uniform", "distance"} or None
        ``None`` chooses by cross-validation too.
    cv_folds : int
        Folds of the (shuffled, seeded) cross-validation.
    k_grid : tuple of int
        Candidate ``k``.
    random_state : int
        Seed of the fold shuffling.

    Attributes
    ----------
    n_neighbors_, weights_ : chosen hyper-parameters.
    cv_rmse_px_ : float
        Cross-validated RMS of the correction error (px, over both coordinates).
    regressor_ : KNeighborsRegressor
    uv_px_, corrections_px_ : ndarray, shape (N, 2)
        Training set (kept: the model is the data).
    """

    def __init__(self, n_neighbors=None, weights=None, cv_folds=10, k_grid=K_GRID, random_state=0):
        self.n_neighbors = n_neighbors
        self.weights = weights
        self.cv_folds = cv_folds
        self.k_grid = k_grid
        self.random_state = random_state

    def fit(self, uv_px, corrections_px):
        """Fit on raw pixels (N, 2) and their corrections (N, 2) px; returns ``self``."""
        X = check_uv(uv_px)
        y = check_uv(corrections_px, "corrections_px")
        if len(X) != len(y):
            raise ValueError(f"uv_px has {len(X)} rows but corrections_px {len(y)}")
        ks = [self.n_neighbors] if self.n_neighbors else [k for k in self.k_grid if k < len(X)]
        ws = [self.weights] if self.weights else ["uniform", "distance"]
        if not ks:
            raise ValueError(f"too few training points ({len(X)}) for kNN")
        folds = KFold(min(self.cv_folds, len(X)), shuffle=True, random_state=self.random_state)
        search = GridSearchCV(
            KNeighborsRegressor(),
            {"n_neighbors": ks, "weights": ws},
            cv=folds,
            scoring="neg_mean_squared_error",
        )
        search.fit(X, y)
        self.n_neighbors_ = int(search.best_params_["n_neighbors"])
        self.weights_ = str(search.best_params_["weights"])
        # neg MSE averages over both outputs: RMS per coordinate -> per point (u and v)
        self.cv_rmse_px_ = float(np.sqrt(-2.0 * search.best_score_))
        self.uv_px_ = X.copy()
        self.corrections_px_ = y.copy()
        self.regressor_ = KNeighborsRegressor(
            n_neighbors=self.n_neighbors_, weights=self.weights_
        ).fit(X, y)
        return self

    def predict(self, uv_px):
        """Corrections (N, 2) px at raw pixels (N, 2)."""
        X = check_uv(uv_px)
        if len(X) == 0:
            return np.zeros((0, 2))
        return self.regressor_.predict(X)

    def predict_without_self(self) -> np.ndarray:
        """Leave-one-out corrections at the training pixels, (N, 2) px.

        Each training point's prediction from its ``k`` nearest *other*
        training points. With ``weights="distance"`` a point's own value
        would otherwise dominate its prediction (zero distance), and with
        ``"uniform"`` it would leak in with weight ``1/k``: the adjustment
        would then fit its own noise and the in-sample statistics would be
        optimistic.
        """
        X, y = self.uv_px_, self.corrections_px_
        n = len(X)
        n_q = min(self.n_neighbors_ + 1, n)
        dist, ind = self.regressor_.kneighbors(X, n_neighbors=n_q)
        is_self = ind == np.arange(n)[:, None]
        drop = np.where(is_self.any(1), is_self.argmax(1), n_q - 1)
        keep = np.ones_like(ind, bool)
        keep[np.arange(n), drop] = False
        ind = ind[keep].reshape(n, n_q - 1)
        dist = dist[keep].reshape(n, n_q - 1)
        if self.weights_ == "uniform":
            return y[ind].mean(axis=1)
        exact = dist == 0
        with np.errstate(divide="ignore"):
            w = np.where(exact.any(1, keepdims=True), exact.astype(float), 1.0 / dist)
        return (w[..., None] * y[ind]).sum(1) / w.sum(1)[:, None]

    def to_dict(self) -> dict:
        """JSON form stored in ``calibration@1`` (``camera.correction``)."""
        return {
            "kind": "knn",
            "n_neighbors": self.n_neighbors_,
            "weights": self.weights_,
            "cv_rmse_px": self.cv_rmse_px_,
            "uv_px": self.uv_px_.tolist(),
            "corrections_px": self.corrections_px_.tolist(),
        }


def correction_from_dict(d: dict) -> KNNCorrection:
    """Rebuild a fitted :class:`KNNCorrection` from :meth:`KNNCorrection.to_dict`."""
    if d.get("kind") != "knn":
        raise ValueError(f"unknown correction kind {d.get('kind')!r}")
    model = KNNCorrection(n_neighbors=int(d["n_neighbors"]), weights=str(d["weights"]))
    model.n_neighbors_ = model.n_neighbors
    model.weights_ = model.weights
    model.cv_rmse_px_ = float(d.get("cv_rmse_px", np.nan))
    model.uv_px_ = np.asarray(d["uv_px"], float).reshape(-1, 2)
    model.corrections_px_ = np.asarray(d["corrections_px"], float).reshape(-1, 2)
    model.regressor_ = KNeighborsRegressor(
        n_neighbors=model.n_neighbors_, weights=model.weights_
    ).fit(model.uv_px_, model.corrections_px_)
    return model


def _inlier_rms(adj) -> float:
    """RMS (px) of the residuals within 5 sigma: blunders must not steer the loop."""
    r = np.linalg.norm(adj.residuals_px, axis=1)
    keep = r < 5.0 * adj.sigma_px
    return float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float(np.sqrt(np.mean(r**2)))


def grey_box_loop(problem, adj, optimizer, options, say: Callable[[str], None]):
    """Alternate kNN training and adjustment until both are stable.

    Each round trains on the total correction each observation needs,
    ``current correction + residual`` (observations down-weighted below 0.5
    are left out of the training set), rewrites the measurements with the
    prediction, rebuilds the graph and adjusts. Stops when the RMS residual
    (of the observations within 5 sigma: blunders cannot steer it) and the CV
    score both change by less than ``knn["tolerance"]`` (relative, default
    2%) between rounds, or after ``knn["max_rounds"]`` (default 8).
    The round with the lowest RMS is kept.

    Returns
    -------
    adj : Adjustment
    model : KNNCorrection
    history : list of dict
        Optimiser iterations of every round, with ``knn_round`` and
        ``cv_rmse_px`` keys.
    """
    from .calibrate import adjust

    cfg = {"max_rounds": 8, "tolerance": 0.02, **(options.knn or {})}
    history = [dict(h, knn_round=0) for h in adj.result.history]
    rms = _inlier_rms(adj)
    best = (rms, adj, None, problem.corrections_px.copy())
    prev_rms, prev_cv = rms, None
    say(f"kNN round 0: RMS {rms:.4f} px within 5 sigma (no correction)")
    for rnd in range(1, int(cfg["max_rounds"]) + 1):
        target = problem.corrections_px + adj.residuals_px
        train = adj.weights >= 0.5
        model = KNNCorrection(random_state=options.seed).fit(problem.uv_px[train], target[train])
        corrections = model.predict(problem.uv_px)
        corrections[train] = model.predict_without_self()  # no observation corrects itself
        problem.corrections_px = corrections
        # the first (least-squares) stage leaves out the previous round's outliers
        consistent = np.linalg.norm(adj.residuals_px, axis=1) < 5.0 * adj.sigma_px
        adj = adjust(
            problem, adj.values, optimizer, None, estimate_sigma=True, first_stage_mask=consistent
        )
        rms = _inlier_rms(adj)
        offset = history[-1]["iteration"] + 1
        history += [
            dict(h, iteration=h["iteration"] + offset, knn_round=rnd, cv_rmse_px=model.cv_rmse_px_)
            for h in adj.result.history
        ]
        say(
            f"kNN round {rnd}: k = {model.n_neighbors_} ({model.weights_}), "
            f"CV RMS {model.cv_rmse_px_:.4f} px, adjustment RMS {rms:.4f} px"
        )
        if rms < best[0]:
            best = (rms, adj, model, problem.corrections_px.copy())
        stable_rms = abs(prev_rms - rms) <= cfg["tolerance"] * prev_rms
        stable_cv = prev_cv is not None and abs(prev_cv - model.cv_rmse_px_) <= cfg[
            "tolerance"
        ] * max(prev_cv, 1e-12)
        if stable_rms and stable_cv:
            say(f"kNN loop stable after {rnd} rounds")
            break
        prev_rms, prev_cv = rms, model.cv_rmse_px_
    _, adj, model, corrections = best
    problem.corrections_px = corrections
    problem.build()  # blocks in step with the kept corrections
    return adj, model, history
