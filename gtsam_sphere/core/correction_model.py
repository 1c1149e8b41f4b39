"""The camera's learned correction model: a kNN regressor from pixels to corrections.

:class:`KNNCorrection` maps a raw pixel ``(u, v)`` to the correction ``(dx, dy)`` the
camera subtracts before its model (``SphereCamera.correction``); it is part of the
camera, so it lives in the core (issue 14), where ``io.calibration`` rebuilds it from a
file (:func:`correction_from_dict`). Training it in the adjustment loop (the grey-box
loop of Chow et al. 2018) is ``estimation.correct``, which re-exports these names.
"""

from __future__ import annotations

import hashlib
import math
import numbers
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.model_selection import KFold
from sklearn.neighbors import KNeighborsRegressor, NearestNeighbors
from sklearn.utils.validation import check_array, check_is_fitted

from .camera import check_uv

K_GRID = (3, 5, 8, 12, 16, 24, 32, 48, 64)
DEGREES = (0, 1)
WEIGHTS = ("uniform", "distance")


def _neighbour_weights(dist: np.ndarray, weights: str) -> np.ndarray:
    """Weights (M, k) of the neighbours at distances ``dist`` (M, k).

    ``"distance"`` is ``1 / d``; a query that coincides with training points
    takes those points only (as scikit-learn's ``KNeighborsRegressor``).
    """
    if weights == "uniform":
        return np.ones_like(dist)
    exact = dist == 0
    with np.errstate(divide="ignore"):
        return np.where(exact.any(1, keepdims=True), exact.astype(float), 1.0 / dist)


def local_fit(
    X: np.ndarray,
    y: np.ndarray,
    Xq: np.ndarray,
    ind: np.ndarray,
    dist: np.ndarray,
    weights: str = "uniform",
    degree: int = 0,
    mask: np.ndarray | None = None,
    yn: np.ndarray | None = None,
) -> np.ndarray:
    """Prediction at ``Xq`` (M, 2) from the neighbours ``ind`` (M, k) of each query.

    Parameters
    ----------
    X, y : ndarray, shape (N, 2)
        Training pixels and values.
    Xq : ndarray, shape (M, 2)
        Query pixels.
    ind, dist : ndarray, shape (M, k)
        Each query's neighbours (indices into ``X``) and their distances.
    weights : {"uniform", "distance"}
        Neighbour weighting.
    degree : {0, 1}
        0: the weighted mean of the neighbours (plain kNN regression). 1: the
        value at the query of a weighted least-squares plane through the
        neighbours (local linear regression), which has no first-order bias
        where the neighbours lie on one side of the query (the image border)
        or the values change fast.
    mask : ndarray of bool, shape (M, k), optional
        Neighbours to use (weight 0 elsewhere).
    yn : ndarray, shape (M, k, 2), optional
        ``y[ind]``, when the caller has it already.

    Returns
    -------
    ndarray, shape (M, 2)
    """
    w = _neighbour_weights(dist, weights)
    if mask is not None:
        w = w * mask
    yn = y[ind] if yn is None else yn  # (M, k, 2)
    sw = w.sum(1)
    sw = np.where(sw > 0, sw, 1.0)
    mean = (w[..., None] * yn).sum(1) / sw[:, None]
    if degree == 0:
        return mean
    # offsets scaled by the neighbourhood radius (conditioning); a small ridge on the
    # slope keeps a collinear or tiny neighbourhood solvable (it then tends to the mean)
    d = X[ind] - Xq[:, None, :]
    h = np.max(np.abs(d), axis=(1, 2))
    h = np.where(h > 0, h, 1.0)
    d = d / h[:, None, None]
    a = np.concatenate([np.ones(d.shape[:2] + (1,)), d], axis=2)  # (M, k, 3)
    wa = w[..., None] * a
    normal = np.einsum("mki,mkj->mij", wa, a)
    normal[:, 0, 0] += 1e-12 * sw  # no weight at all: the prediction is 0
    normal[:, 1, 1] += 1e-6 * sw
    normal[:, 2, 2] += 1e-6 * sw
    rhs = np.einsum("mki,mkj->mij", wa, yn)  # (M, 3, 2)
    coef = np.linalg.solve(normal, rhs)
    exact = (dist == 0).any(1) if weights == "distance" else np.zeros(len(dist), bool)
    return np.where(exact[:, None], mean, coef[:, 0, :])


def _prefix_means(yn: np.ndarray, dist: np.ndarray, weights: str) -> Callable[[int], np.ndarray]:
    """``k -> local_fit(..., degree=0)`` of the first ``k`` of the neighbours ``yn``.

    ``yn`` (M, K, 2) and ``dist`` (M, K), neighbours by increasing distance. The weighted
    sums of every prefix come from one cumulative sum; it adds the neighbours in the
    order ``local_fit``'s sum does, so each mean is the same number (a test checks it).
    """
    w = _neighbour_weights(dist, weights)  # a zero distance comes first: same per prefix
    sums = np.cumsum(w[..., None] * yn, axis=1)

    def mean(k: int) -> np.ndarray:
        sw = w[:, :k].sum(1)
        sw = np.where(sw > 0, sw, 1.0)
        return sums[:, k - 1] / sw[:, None]

    return mean


def neighbours_without_self(nn, X: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices (N, k) of each training point's ``k`` nearest *other* points."""
    n = len(X)
    n_q = min(k + 1, n)
    dist, ind = nn.kneighbors(X, n_neighbors=n_q)
    is_self = ind == np.arange(n)[:, None]
    drop = np.where(is_self.any(1), is_self.argmax(1), n_q - 1)
    keep = np.ones_like(ind, bool)
    keep[np.arange(n), drop] = False
    return dist[keep].reshape(n, n_q - 1), ind[keep].reshape(n, n_q - 1)


class NeighbourSearches:
    """Memo of nearest-neighbour searches, for the rounds of the grey-box loop.

    The loop trains on the same raw pixels every round (only the corrections they need
    change), so its searches (the cross-validation folds', each training point's other
    neighbours, the consistency check's) are the same every round: each is done once
    and served from here after. A search is keyed by a digest of its points and its
    parameters, so a different training set is searched anew; the results are the
    arrays scikit-learn returned (the same numbers as searching again).
    """

    def __init__(self) -> None:
        self._memo: dict = {}
        self.hits = 0
        self.searches = 0

    @staticmethod
    def digest(*arrays: np.ndarray) -> bytes:
        """SHA-256 of the arrays' shapes and bytes."""
        h = hashlib.sha256()
        for a in arrays:
            a = np.ascontiguousarray(a)
            h.update(repr((a.shape, a.dtype.str)).encode())
            h.update(a.tobytes())
        return h.digest()

    def get(self, key: tuple, search: Callable[[], Any]) -> Any:
        """The memoised result of ``search()`` under ``key`` (computed on first use)."""
        if key in self._memo:
            self.hits += 1
        else:
            self.searches += 1
            self._memo[key] = search()
        return self._memo[key]


def memoised_search(
    searches: NeighbourSearches | None, key: tuple, search: Callable[[], Any]
) -> Any:
    """``search()``, through ``searches`` (:class:`NeighbourSearches`) when one is given."""
    return search() if searches is None else searches.get(key, search)


class KNNCorrection(RegressorMixin, BaseEstimator):
    """k-nearest-neighbour model of the measurement corrections, px -> px.

    A scikit-learn regressor with two inputs (the raw pixel ``u, v``) and two
    outputs (the correction ``dx, dy`` in px): ``fit`` returns the estimator,
    every fitted attribute ends in ``_``, ``predict`` before ``fit`` raises
    ``sklearn.exceptions.NotFittedError``, and ``__init__`` only stores its
    arguments (checked by ``sklearn.utils.estimator_checks`` in the tests).

    Parameters
    ----------
    n_neighbors : int >= 1 or None
        ``None`` (default) chooses ``k`` from ``k_grid`` by ``cv_folds``-fold
        cross-validation. ``0`` meant the same before and still does, with a
        ``FutureWarning``: it will be refused in a later version.
    weights : {"uniform", "distance"} or None
        ``None`` chooses by cross-validation too.
    cv_folds : int
        Folds of the (shuffled, seeded) cross-validation.
    k_grid : tuple of int
        Candidate ``k``.
    random_state : int
        Seed of the fold shuffling.
    degree : {0, 1} or None
        0 (default): the prediction is the (weighted) mean of the ``k``
        neighbours, plain kNN regression as in the paper. 1: the value at the
        query of a weighted least-squares plane through the ``k`` neighbours
        (local linear kNN), free of the first-order bias of the mean where the
        neighbours are one-sided (the image border) or the correction changes
        fast (hundreds of pixels of lens mapping). ``None``: chosen by the
        cross-validation together with ``k`` and ``weights``.

    Attributes
    ----------
    n_features_in_ : int
        2: the pixel coordinates ``u, v``.
    n_neighbors_, weights_, degree_ : chosen hyper-parameters.
    cv_rmse_px_ : float
        Cross-validated RMS of the correction error (px, over both coordinates).
    cv_scores_ : dict
        Cross-validated RMS (px) of every candidate ``(degree, k, weights)``.
    regressor_ : KNeighborsRegressor
        The neighbour search (and, for ``degree_ == 0``, the predictor).
    uv_px_, corrections_px_ : ndarray, shape (N, 2)
        Training set (kept: the model is the data).
    """

    def __init__(
        self,
        n_neighbors=None,
        weights=None,
        cv_folds=10,
        k_grid=K_GRID,
        random_state=0,
        degree=0,
    ):
        self.n_neighbors = n_neighbors
        self.weights = weights
        self.cv_folds = cv_folds
        self.k_grid = k_grid
        self.random_state = random_state
        self.degree = degree

    def fit(self, uv_px, corrections_px, searches: NeighbourSearches | None = None):
        """Fit on raw pixels and their corrections.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Raw pixels.
        corrections_px : array_like, shape (N, 2)
            Corrections (px) at those pixels.
        searches : NeighbourSearches, optional
            Memo of the cross-validation's neighbour searches (the grey-box loop's
            rounds train on the same pixels); the fit is the same with or without.

        Returns
        -------
        self : KNNCorrection
        """
        if corrections_px is None:
            raise ValueError("KNNCorrection requires y to be passed, but the target y is None")
        # scikit-learn's checks first (sparse, complex, empty, NaN or inf: its messages), then
        # the shapes of pixels and corrections
        X = check_uv(check_array(uv_px, dtype=np.float64, input_name="uv_px"))
        y = check_array(corrections_px, dtype=np.float64, ensure_2d=False, input_name="y")
        y = check_uv(y, "corrections_px")
        if len(X) != len(y):
            raise ValueError(f"uv_px has {len(X)} rows but corrections_px {len(y)}")
        if self.degree not in (None, *DEGREES):
            raise ValueError(f"degree must be 0, 1 or None, got {self.degree!r}")
        if self.weights not in (None, *WEIGHTS):
            raise ValueError(f"weights must be 'uniform', 'distance' or None, got {self.weights!r}")
        n_neighbors = self._n_neighbors_or_none()
        ks = [n_neighbors] if n_neighbors is not None else [k for k in self.k_grid if k < len(X)]
        ws = [self.weights] if self.weights is not None else list(WEIGHTS)
        degrees = list(DEGREES) if self.degree is None else [self.degree]
        if not ks:
            raise ValueError(f"too few training points ({len(X)}) for kNN")
        scores = self._cross_validate(X, y, ks, ws, degrees, searches)
        # the first best in (degree, k, weights) order: the simplest model wins a tie
        best = min(scores, key=scores.get)
        self.n_features_in_ = X.shape[1]
        self.degree_, self.n_neighbors_, self.weights_ = int(best[0]), int(best[1]), str(best[2])
        self.cv_scores_ = scores
        self.cv_rmse_px_ = float(scores[best])
        self.uv_px_ = X.copy()
        self.corrections_px_ = y.copy()
        self.regressor_ = KNeighborsRegressor(
            n_neighbors=min(self.n_neighbors_, len(X)), weights=self.weights_
        ).fit(X, y)
        return self

    def __sklearn_tags__(self):
        """Tags for scikit-learn >= 1.6: a target is required, with two outputs."""
        tags = super().__sklearn_tags__()
        tags.target_tags.required = True
        tags.target_tags.multi_output = True
        tags.target_tags.single_output = False
        return tags

    def _n_neighbors_or_none(self) -> int | None:
        """``n_neighbors`` checked: an int >= 1, or None for the cross-validation's choice."""
        k = self.n_neighbors
        if k is None:
            return None
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 0:
            raise ValueError(f"n_neighbors must be an int >= 1 or None, got {k!r}")
        if k == 0:
            warnings.warn(
                "KNNCorrection(n_neighbors=0) is deprecated: use n_neighbors=None to choose k "
                "by cross-validation (0 will be refused in a later version)",
                FutureWarning,
                stacklevel=3,
            )
            return None
        return int(k)

    def _cross_validate(self, X, y, ks, ws, degrees, searches=None) -> dict:
        """Pooled ``cv_folds``-fold RMS (px, per point) of every candidate.

        One neighbour search per fold (``max(ks)`` neighbours) serves every candidate,
        the neighbours' values are gathered once per fold, and the plain means
        (``degree`` 0) of every ``k`` come from one cumulative sum
        (:func:`_prefix_means`).
        """
        n_splits = min(self.cv_folds, len(X))
        k_max = min(max(ks), len(X))

        def fold_searches():
            folds = KFold(n_splits, shuffle=True, random_state=self.random_state)
            out = []
            for train, test in folds.split(X):
                nn = NearestNeighbors().fit(X[train])
                dist, ind = nn.kneighbors(X[test], n_neighbors=min(k_max, len(train)))
                out.append((train, test, dist, ind))
            return out

        key = ("cv", NeighbourSearches.digest(X), n_splits, self.random_state, k_max)
        sse = {(d, k, w): 0.0 for d in degrees for k in ks for w in ws}
        for train, test, dist, ind in memoised_search(searches, key, fold_searches):
            k_fold = ind.shape[1]
            yn = y[train][ind]  # (M, k_fold, 2): every candidate's neighbours' values
            means = {w: _prefix_means(yn, dist, w) for w in ws} if 0 in degrees else {}
            for d, k, w in sse:
                kk = min(k, k_fold)
                if d == 0:
                    pred = means[w](kk)
                else:
                    pred = local_fit(
                        X[train], y[train], X[test], ind[:, :kk], dist[:, :kk], w, d, yn=yn[:, :kk]
                    )
                sse[(d, k, w)] += float(np.sum((pred - y[test]) ** 2))
        return {key: float(np.sqrt(v / len(X))) for key, v in sse.items()}

    def predict(self, uv_px):
        """Corrections at raw pixels.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)

        Returns
        -------
        ndarray, shape (N, 2)
            Corrections (px).
        """
        check_is_fitted(self)
        X = check_uv(uv_px)
        if len(X) == 0:
            return np.zeros((0, 2))
        if self.degree_ == 0:
            return self.regressor_.predict(X)
        dist, ind = self.regressor_.kneighbors(X)
        return local_fit(
            self.uv_px_, self.corrections_px_, X, ind, dist, self.weights_, self.degree_
        )

    def prediction_bound_px(self) -> float:
        """A bound on ``|predict(uv_px)|`` (px) at any pixel.

        With ``degree_ == 0`` a prediction is a weighted mean of training corrections
        (uniform or inverse-distance weights), so no longer than the longest of them;
        a local linear fit (``degree_ == 1``) extrapolates: ``inf``.

        Returns
        -------
        float
        """
        check_is_fitted(self)
        if self.degree_ != 0 or len(self.corrections_px_) == 0:
            return math.inf
        return float(np.max(np.linalg.norm(self.corrections_px_, axis=1)))

    def predict_without_self(self, searches: NeighbourSearches | None = None) -> np.ndarray:
        """Leave-one-out corrections at the training pixels, (N, 2) px.

        Each training point's prediction from its ``k`` nearest *other*
        training points. With ``weights="distance"`` a point's own value
        would otherwise dominate its prediction (zero distance), and with
        ``"uniform"`` it would leak in with weight ``1/k``: the adjustment
        would then fit its own noise and the in-sample statistics would be
        optimistic. ``searches`` (:class:`NeighbourSearches`) memoises the search.
        """
        check_is_fitted(self)
        X, y = self.uv_px_, self.corrections_px_
        dist, ind = memoised_search(
            searches,
            ("without_self", NeighbourSearches.digest(X), self.n_neighbors_),
            lambda: neighbours_without_self(self.regressor_, X, self.n_neighbors_),
        )
        return local_fit(X, y, X, ind, dist, self.weights_, self.degree_)

    def to_dict(self) -> dict:
        """JSON form stored in ``calibration@1`` (``camera.correction``)."""
        check_is_fitted(self)
        return {
            "kind": "knn",
            "n_neighbors": self.n_neighbors_,
            "weights": self.weights_,
            "degree": self.degree_,
            "cv_rmse_px": self.cv_rmse_px_,
            "uv_px": self.uv_px_.tolist(),
            "corrections_px": self.corrections_px_.tolist(),
        }


def correction_from_dict(d: dict) -> KNNCorrection:
    """Rebuild a fitted :class:`KNNCorrection` from :meth:`KNNCorrection.to_dict`."""
    if d.get("kind") != "knn":
        raise ValueError(f"unknown correction kind {d.get('kind')!r}")
    model = KNNCorrection(
        n_neighbors=int(d["n_neighbors"]), weights=str(d["weights"]), degree=int(d.get("degree", 0))
    )
    model.n_features_in_ = 2
    model.n_neighbors_ = model.n_neighbors
    model.weights_ = model.weights
    model.degree_ = model.degree
    model.cv_rmse_px_ = float(d.get("cv_rmse_px", np.nan))
    model.uv_px_ = np.asarray(d["uv_px"], float).reshape(-1, 2)
    model.corrections_px_ = np.asarray(d["corrections_px"], float).reshape(-1, 2)
    model.regressor_ = KNeighborsRegressor(
        n_neighbors=model.n_neighbors_, weights=model.weights_
    ).fit(model.uv_px_, model.corrections_px_)
    return model
