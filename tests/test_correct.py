"""kNN correction model: estimator rules, cross-validation, exact reload."""

import numpy as np
import pytest
from sklearn.base import clone

from gtsam_sphere.calibration import camera_from_dict
from gtsam_sphere.camera import SphereCamera
from gtsam_sphere.correct import KNNCorrection, correction_from_dict


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
