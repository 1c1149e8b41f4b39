"""kNN correction model: estimator rules, cross-validation, exact reload."""

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.utils.estimator_checks import parametrize_with_checks

from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.estimation.correct import (
    K_GRID,
    WEIGHTS,
    KNNCorrection,
    NeighbourSearches,
    consistent_with_neighbours,
    correction_from_dict,
    train_correction,
)
from gtsam_sphere.io.calibration import camera_from_dict


def _field(uv):
    return np.column_stack([2.0 * np.sin(uv[:, 0] / 300.0), -1.5 * np.cos(uv[:, 1] / 250.0)])


def test_estimator_rules_and_learning():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 1000, size=(800, 2))
    y = _field(uv) + 0.1 * rng.normal(size=uv.shape)
    model = KNNCorrection(random_state=0)
    assert clone(model).get_params() == model.get_params()  # no logic in __init__
    assert model.fit(uv, y) is model
    assert model.n_neighbors_ in model.k_grid and model.weights_ in ("uniform", "distance")
    test = rng.uniform(100, 900, size=(200, 2))
    err = model.predict(test) - _field(test)
    assert np.sqrt(np.mean(err**2)) < 0.25
    assert 0.1 < model.cv_rmse_px_ < 0.6
    # seeded: same result twice
    again = KNNCorrection(random_state=0).fit(uv, y)
    assert again.n_neighbors_ == model.n_neighbors_ and again.cv_rmse_px_ == model.cv_rmse_px_


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"shape \(N, 2\), got \(5, 3\)"):
        KNNCorrection().fit(np.zeros((5, 3)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="rows"):
        KNNCorrection().fit(np.zeros((5, 2)), np.zeros((4, 2)))


def test_camera_with_correction_reloads_exactly():
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 1200, size=(500, 2))
    model = KNNCorrection(random_state=0).fit(uv, _field(uv))
    cam = SphereCamera(1200, 1000, 601.0, 498.0, 450.0, brown={"k1": 0.01}, correction=model)
    d = cam.to_dict()
    d["correction"] = model.to_dict()
    import json

    back = camera_from_dict(json.loads(json.dumps(d)))
    pts = rng.normal(size=(300, 3)) + [0, 0, 1.5]
    np.testing.assert_array_equal(back.project(pts), cam.project(pts))
    # project inverts the correction: unproject(project(P)) is the ray of P, exactly where
    # the kNN field is continuous; at a switch of the neighbour set the field jumps and the
    # inversion lands within that jump (docs/conventions.md)
    rays = back.unproject(back.project(pts), hemisphere=np.sign(pts[:, 2]))
    err = np.linalg.norm(rays - pts / np.linalg.norm(pts, axis=1)[:, None], axis=1)
    assert np.mean(err < 1e-9) > 0.95
    assert err.max() < 2e-3
    assert isinstance(correction_from_dict(model.to_dict()), KNNCorrection)


def _steep(uv):
    # a lens-mapping-like field: hundreds of px, 0.6 px/px at the border (the sphere mapping's
    # error on a 150 degree lens)
    r = uv - 500.0
    return 0.6 * r * (np.linalg.norm(r, axis=1, keepdims=True) / 700.0)


def test_local_linear_removes_the_one_sided_border_bias():
    rng = np.random.default_rng(2)
    uv = rng.uniform(0, 1000, size=(1500, 2))
    y = _steep(uv) + 0.1 * rng.normal(size=uv.shape)
    border = np.min(np.minimum(uv, 1000 - uv), axis=1) < 30
    errs = {}
    for degree in (0, 1):
        model = KNNCorrection(n_neighbors=8, weights="uniform", degree=degree).fit(uv, y)
        err = np.linalg.norm(model.predict_without_self() - _steep(uv), axis=1)
        errs[degree] = np.sqrt(np.mean(err[border] ** 2))
    assert errs[0] > 5.0  # the mean of one-sided neighbours on a steep field
    assert errs[1] < 0.15 * errs[0]  # the local plane has no first-order bias (curvature left)
    # cross-validation chooses the local plane for such a field, and a new pixel is predicted
    # as well as a training one
    model = KNNCorrection(degree=None, random_state=0).fit(uv, y)
    assert model.degree_ == 1 and (1, model.n_neighbors_, model.weights_) in model.cv_scores_
    test = rng.uniform(0, 1000, size=(300, 2))
    assert np.sqrt(np.mean((model.predict(test) - _steep(test)) ** 2)) < 0.5
    back = correction_from_dict(model.to_dict())
    np.testing.assert_array_equal(back.predict(test), model.predict(test))
    with pytest.raises(ValueError, match="degree"):
        KNNCorrection(degree=2).fit(uv, y)


def test_blunders_are_left_out_of_training_but_not_the_border():
    rng = np.random.default_rng(3)
    uv = rng.uniform(0, 1000, size=(2000, 2))
    y = _steep(uv) + 0.3 * rng.normal(size=uv.shape)
    bad = rng.random(len(uv)) < 0.05
    y[bad] += rng.normal(scale=30.0, size=(bad.sum(), 2)) + 15.0 * np.sign(rng.normal(size=2))
    good = consistent_with_neighbours(uv, y)
    assert np.mean(~good[bad]) > 0.95
    assert np.mean(good[~bad]) > 0.99
    border = np.min(np.minimum(uv, 1000 - uv), axis=1) < 30
    assert np.mean(good[border & ~bad]) > 0.98


def test_robust_sigma_of_2d_residual_norms():
    """One robust scale for calibrate, resect and the kNN training set."""
    from gtsam_sphere.estimation.graph import robust_sigma_px

    rng = np.random.default_rng(4)
    r = np.linalg.norm(rng.normal(0.0, 0.3, (100_000, 2)), axis=1)
    r[:20_000] += 50.0  # 20% blunders move the median only a little
    assert abs(robust_sigma_px(r[20_000:]) - 0.3) < 0.01
    assert robust_sigma_px(r) < 0.45
    one = robust_sigma_px(np.array([np.nan, np.inf, 1.0]))
    assert one == pytest.approx(1.0 / np.sqrt(2 * np.log(2)))
    assert robust_sigma_px(np.zeros(5), 0.005) == 0.005
    assert robust_sigma_px(np.array([np.nan]), 0.1) == 0.1


# scikit-learn's estimator checks that cannot apply: they feed X of 1, 3, 4, 5 or 10
# columns, or a single-output y, while the model maps raw pixels (u, v), two columns, to
# a correction (dx, dy), two columns, and refuses any other shape with a ValueError.
_NOT_TWO_PIXEL_COLUMNS = "X must be pixels (u, v): two columns; the check uses another number"
_NOT_TWO_OUTPUTS = "y must be corrections (dx, dy): two columns; the check uses one"
_EXPECTED_FAILED_CHECKS = {
    name: _NOT_TWO_PIXEL_COLUMNS
    for name in (
        "check_fit_score_takes_y",
        "check_dont_overwrite_parameters",
        "check_n_features_in_after_fitting",
        "check_positive_only_tag_during_fit",
        "check_estimators_dtypes",
        "check_dtype_object",
        "check_pipeline_consistency",
        "check_estimators_nan_inf",
        "check_estimators_pickle",
        "check_f_contiguous_array_estimator",
        "check_regressors_train",
        "check_regressor_data_not_an_array",
        "check_regressor_multioutput",
        "check_regressors_no_decision_function",
        "check_regressors_int",
        "check_methods_sample_order_invariance",
        "check_methods_subset_invariance",
        "check_fit2d_1sample",
        "check_fit2d_1feature",
        "check_dict_unchanged",
        "check_fit2d_predict1d",
    )
} | {
    name: _NOT_TWO_OUTPUTS
    for name in (
        "check_estimators_overwrite_params",
        "check_estimators_fit_returns_self",
        "check_readonly_memmap_input",
        "check_fit_idempotent",
        "check_fit_check_is_fitted",
        "check_n_features_in",
    )
}


# some scikit-learn versions hand pytest a generator of checks, which pytest deprecates
# (PytestRemovedIn10Warning): the same parametrisation with the checks listed
_CHECKS = parametrize_with_checks(
    [KNNCorrection()], expected_failed_checks=lambda estimator: _EXPECTED_FAILED_CHECKS
)


@pytest.mark.parametrize(_CHECKS.args[0], list(_CHECKS.args[1]), **_CHECKS.kwargs)
def test_scikit_learn_estimator_checks(estimator, check):
    check(estimator)


def test_fitted_state_follows_the_scikit_learn_contract():
    rng = np.random.default_rng(5)
    uv = rng.uniform(0, 1000, size=(300, 2))
    model = KNNCorrection(random_state=0)
    for use in (lambda: model.predict(uv), model.predict_without_self, model.to_dict):
        with pytest.raises(NotFittedError):
            use()
    assert model.fit(uv, _field(uv)) is model
    assert model.n_features_in_ == 2
    fitted = [k for k in vars(model) if k not in model.get_params()]
    assert fitted and all(k.endswith("_") for k in fitted), fitted
    assert correction_from_dict(model.to_dict()).n_features_in_ == 2
    with pytest.raises(ValueError, match="requires y"):
        KNNCorrection().fit(uv, None)


def test_n_neighbors_none_is_cross_validation_and_zero_is_deprecated():
    rng = np.random.default_rng(6)
    uv = rng.uniform(0, 1000, size=(400, 2))
    y = _field(uv) + 0.1 * rng.normal(size=uv.shape)
    chosen = KNNCorrection(n_neighbors=None, random_state=0).fit(uv, y)
    assert len({k for _, k, _ in chosen.cv_scores_}) > 1  # every k of the grid was tried
    with pytest.warns(FutureWarning, match="n_neighbors=None"):
        old = KNNCorrection(n_neighbors=0, random_state=0).fit(uv, y)
    assert old.cv_scores_ == chosen.cv_scores_ and old.n_neighbors_ == chosen.n_neighbors_
    np.testing.assert_array_equal(old.predict(uv), chosen.predict(uv))
    fixed = KNNCorrection(n_neighbors=5, weights="uniform").fit(uv, y)
    assert fixed.n_neighbors_ == 5 and set(fixed.cv_scores_) == {(0, 5, "uniform")}
    for bad in (-1, 2.5, "5", True):
        with pytest.raises(ValueError, match="n_neighbors"):
            KNNCorrection(n_neighbors=bad).fit(uv, y)
    with pytest.raises(ValueError, match="weights"):
        KNNCorrection(weights="gaussian").fit(uv, y)


def test_memoised_neighbour_searches_give_the_same_training():
    """The grey-box loop's rounds share their neighbour searches (NeighbourSearches): the
    same pixels are searched once, and the training (folds, scores, predictions) is the
    same number for number as with fresh searches, for new corrections and for a
    different training set."""
    rng = np.random.default_rng(3)
    uv = rng.uniform(0, 800, (600, 2))
    searches = NeighbourSearches()
    for round_ in range(3):
        target = np.column_stack([np.sin(uv[:, 0] / 90.0), np.cos(uv[:, 1] / 70.0)])
        target += rng.normal(0, 0.05 * (round_ + 1), target.shape)
        for degree in (0, None):
            fresh = train_correction(uv, target, 0, degree)
            shared = train_correction(uv, target, 0, degree, searches=searches)
            assert fresh[0].cv_scores_ == shared[0].cv_scores_
            np.testing.assert_array_equal(fresh[1], shared[1])
            np.testing.assert_array_equal(fresh[2], shared[2])
    # three kinds of search (consistency, folds, leave-one-out neighbours), per degree's k
    assert searches.searches <= 6 and searches.hits >= 3 * 2 * 3 - searches.searches
    subset = np.arange(len(uv)) % 7 != 0  # another training set: searched anew
    before = searches.searches
    fresh = train_correction(uv, target, 0, 0, subset)
    shared = train_correction(uv, target, 0, 0, subset, searches)
    assert searches.searches > before
    np.testing.assert_array_equal(fresh[1], shared[1])


def test_cross_validation_prefix_means_equal_local_fit():
    """The cross-validation's plain means of every k (one cumulative sum per fold) are
    local_fit's numbers exactly, for both weightings, with coinciding pixels (a zero
    distance) among the training points."""
    from sklearn.model_selection import KFold
    from sklearn.neighbors import NearestNeighbors

    from gtsam_sphere.core.correction_model import local_fit

    rng = np.random.default_rng(8)
    uv = rng.uniform(0, 500, (700, 2))
    uv[650:] = uv[:50]  # duplicated pixels
    y = _field(uv) + rng.normal(0, 0.1, uv.shape)
    model = KNNCorrection(degree=None)
    ks, ws = list(K_GRID), list(WEIGHTS)
    scores = model._cross_validate(uv, y, ks, ws, [0, 1])
    sse = dict.fromkeys(scores, 0.0)
    for train, test in KFold(10, shuffle=True, random_state=0).split(uv):
        dist, ind = NearestNeighbors().fit(uv[train]).kneighbors(uv[test], n_neighbors=max(ks))
        for d, k, w in sse:
            pred = local_fit(uv[train], y[train], uv[test], ind[:, :k], dist[:, :k], w, d)
            sse[(d, k, w)] += float(np.sum((pred - y[test]) ** 2))
    assert scores == {key: float(np.sqrt(v / len(uv))) for key, v in sse.items()}
