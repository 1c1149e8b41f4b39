"""The runtime camera: tabulated kNN correction, fast project/unproject, the valid field."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import bare_calibration, shared_data_file

from gtsam_sphere.core.camera import (
    VALID_MARGIN_RAD,
    SphereCamera,
    brown_distortion,
    radial_g,
    radial_g_horner,
)
from gtsam_sphere.core.tabulated import CorrectionTable, check_pixels, choose_table
from gtsam_sphere.estimation.correct import KNNCorrection
from gtsam_sphere.io.calibration import camera_from_dict, load_calibration

W, H = 1280, 800


def _knn(seed=0, n=1600, k=None):
    """A kNN fitted to a smooth 0.3 px field plus 0.1 px noise, as the grey-box loop's."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([40, 30], [W - 40, H - 30], (n, 2))
    field = 0.3 * np.column_stack([np.sin(uv[:, 0] / 150), np.cos(uv[:, 1] / 110)])
    return KNNCorrection(n_neighbors=k, degree=0).fit(uv, field + rng.normal(0, 0.1, (n, 2)))


def _camera(correction=None, observed_deg=None, brown=None):
    """A radial+knn camera like opencv_fisheye_left's (560 px, decentering terms)."""
    return SphereCamera(
        W,
        H,
        622.3,
        381.5,
        563.0,
        brown=brown if brown is not None else {"p1": 5e-5, "p2": 7e-4},
        brown_scale_px=640.0,
        correction=correction,
        radial={"g3": -0.04, "g5": 0.05},
        observed_alpha_rad=None if observed_deg is None else math.radians(observed_deg),
    )


def _rays_at(alpha_deg, azimuth_deg=30.0):
    a, b = np.radians(alpha_deg), np.radians(azimuth_deg)
    a, b = np.broadcast_arrays(np.atleast_1d(a), b)
    return np.column_stack([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)])


@pytest.mark.parametrize("k", [None, 5])
def test_table_agrees_with_the_exact_knn(k):
    knn = _knn(k=k)
    table = choose_table(knn, W, H)
    assert table.check["rms_px"] <= 0.01
    uv = check_pixels(knn, W, H, n=20000, seed=5)  # other pixels than the build's check
    agree = table.agreement(knn, uv)
    assert agree["rms_px"] < 0.01, agree
    # the largest differences sit on the kNN's own jumps (where the set of neighbours
    # changes, the field is discontinuous and the table spans the step): bounded by them
    assert agree["max_px"] < 0.3, agree
    # the nodes hold the exact values
    nodes = table.nodes()[::97]
    np.testing.assert_allclose(table.predict(nodes), knn.predict(nodes), atol=1e-12)


def test_table_lookup_nan_edges_and_jacobian():
    knn = _knn()
    table = CorrectionTable(knn, W, H, spacing_px=4.0)
    uv = np.array([[np.nan, 3.0], [-500.0, -500.0], [1e6, 1e6], [100.3, 200.7]])
    out = table.predict(uv)
    assert np.isnan(out[0]).all() and np.isfinite(out[1:]).all()
    # far outside: the value of the nearest corner node is held
    np.testing.assert_allclose(out[1], table.values[0, 0])
    np.testing.assert_allclose(out[2], table.values[-1, -1])
    # Jacobian against central differences inside a cell
    x = np.array([[101.1, 203.3], [640.2, 400.9]])
    _, J = table.predict_with_jacobian(x)
    e = 1e-4
    for j in range(2):
        d = np.zeros(2)
        d[j] = e
        num = (table.predict(x + d) - table.predict(x - d)) / (2 * e)
        np.testing.assert_allclose(J[:, :, j], num, atol=1e-8)


def test_horner_radial_g_matches_radial_g():
    a = np.linspace(0.0, math.pi, 1001)
    coeffs = np.array([-0.04, 0.5, -3.38, 11.19, -18.14, 11.39])
    for warp in (None, math.log(4.0), math.log(0.25)):
        g, dg, _ = radial_g(a, coeffs, derivative=True, warp=warp)
        g2, dg2 = radial_g_horner(a, coeffs, warp, derivative=True)
        np.testing.assert_allclose(g2, g, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(dg2, dg, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(radial_g_horner(a, np.zeros(0)), a)


def test_table_project_unproject_round_trip_and_agreement_with_exact():
    cam = _camera(_knn(), observed_deg=75.0)
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [W - 1, H - 1], (20000, 2))
    uv = uv[cam.valid_pixel_mask(uv)]
    assert len(uv) > 10000
    rays = cam.unproject(uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    back = cam.project(rays * rng.uniform(0.2, 30.0, (len(rays), 1)))
    assert np.abs(back - uv).max() < 1e-8
    # the table path stays within the table's agreement of the exact kNN path
    exact_uv = cam.project(rays[:2000], exact=True)
    d = np.linalg.norm(cam.project(rays[:2000]) - exact_uv, axis=1)
    assert np.sqrt(np.mean(d**2)) < 0.01 and d.max() < 0.1
    exact_rays = cam.unproject(uv[:2000], exact=True)
    ang = np.arccos(np.clip(np.sum(exact_rays * rays[:2000], axis=1), -1, 1))
    assert (cam.c * ang).max() < 0.1
    # the exact path is the exact kNN (then Brown at the pixel it corrected)
    ideal = cam.ideal_from_pixels(uv[:50], exact=True)
    w = uv[:50] - cam.correction.predict(uv[:50]) - cam.principal_point_px
    expect = w - brown_distortion(w, cam.brown, cam.brown_scale_px)
    assert np.abs(ideal - expect).max() < 1e-12
    # the default path: the tabulated Brown terms add nothing measurable to the table's error
    d_brown = cam.distortion_table().predict(uv) - cam.correction_table().predict(uv)
    w = uv - cam.correction_table().predict(uv) - cam.principal_point_px
    assert np.abs(d_brown - brown_distortion(w, cam.brown, cam.brown_scale_px)).max() < 1e-4
    # the same camera without a correction is untouched by the table
    plain = _camera(None, observed_deg=75.0)
    assert plain.correction_table() is None


@pytest.mark.slow
def test_table_is_cached_and_follows_a_new_correction():
    cam = _camera(_knn())
    t1 = cam.correction_table()
    assert cam.correction_table() is t1
    cam.project(_rays_at([10.0, 40.0]))
    assert cam.correction_table() is t1
    cam.correction = _knn(seed=1)
    t2 = cam.correction_table()
    assert t2 is not t1
    assert cam.correction_table(spacing_px=2.0).spacing_px == 2.0
    # not written to the calibration file
    d = cam.to_dict()
    assert not any("table" in k for k in d)


def test_project_is_nan_beyond_the_valid_field():
    cam = _camera(_knn(), observed_deg=60.0)
    limit = math.radians(60.0) + VALID_MARGIN_RAD
    assert cam.valid_alpha_rad() == pytest.approx(limit)
    alpha = np.array([0.0, 30.0, 59.0, 61.9, 62.1, 90.0, 120.0, 179.0])
    uv = cam.project(_rays_at(alpha))
    finite = np.isfinite(uv).all(axis=1)
    np.testing.assert_array_equal(finite, alpha <= 62.0)
    np.testing.assert_array_equal(cam.valid_mask(_rays_at(alpha)), alpha <= 62.0)
    # the exact path says the same; valid_only=False restores the unrestricted model
    exact = cam.project(_rays_at(alpha), exact=True)
    np.testing.assert_array_equal(np.isfinite(exact).all(axis=1), finite)
    assert np.isfinite(cam.project(_rays_at([120.0]), valid_only=False)).all()
    # pixels: those inside the valid field are exactly the projections of valid rays
    rng = np.random.default_rng(0)
    uv = rng.uniform([-50, -50], [W + 50, H + 50], (5000, 2))
    ok = cam.valid_pixel_mask(uv)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
    assert not ok[~inside].any()
    a = np.arccos(np.clip(cam.unproject(uv[inside])[:, 2], -1, 1))
    np.testing.assert_array_equal(ok[inside], a <= limit)
    assert 0.2 < ok.mean() < 0.9


def test_radial_mapping_is_nan_past_its_one_to_one_field():
    # g turns over before 180 deg: without data limits the lens's own field still holds
    cam = SphereCamera(W, H, 640.0, 400.0, 300.0, radial={"g3": -0.2})
    a_max = math.degrees(cam.max_alpha_rad())
    assert a_max < 170.0
    assert cam.valid_alpha_rad() == cam.max_alpha_rad()
    uv = cam.project(_rays_at([a_max - 1.0, a_max + 1.0, 179.0]))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1:]).all()
    assert np.isfinite(cam.project(_rays_at([a_max + 1.0]), valid_only=False)).all()


def test_camera_without_a_known_field_projects_as_before():
    cam = SphereCamera(W, H, 640.0, 400.0, 300.0, radial={})  # equidistant: one-to-one to 180
    assert cam.observed_alpha_rad is None and cam.valid_alpha_rad() == math.pi
    assert np.isfinite(cam.project(_rays_at([120.0, 170.0]))).all()


def test_observed_field_round_trips_and_old_files_load(tmp_path):
    cam = _camera(_knn(), observed_deg=61.2)
    calib = bare_calibration(cam)
    calib.statistics["max_incidence_deg"] = 70.0
    path = calib.save(tmp_path / "new.json")
    loaded = load_calibration(path).camera
    assert loaded.observed_alpha_rad == pytest.approx(math.radians(61.2))
    # an old file: no camera.observed_alpha_rad; the statistics' max_incidence_deg stands in
    calib.camera = _camera(_knn(), observed_deg=None)
    old = load_calibration(calib.save(tmp_path / "old.json")).camera
    assert old.observed_alpha_rad == pytest.approx(math.radians(70.0))
    assert np.isnan(old.project(_rays_at([120.0]))).all()
    # older still: neither (a camera dict alone)
    d = calib.camera.to_dict()
    assert "observed_alpha_rad" not in d
    assert camera_from_dict(d).observed_alpha_rad is None
    with pytest.raises(ValueError, match="observed_alpha_rad"):
        SphereCamera(W, H, 1.0, 1.0, 10.0, observed_alpha_rad=-1.0)


@pytest.mark.slow
def test_opencv_fisheye_left_folds_nothing_back_and_the_table_agrees(tmp_path):
    """The issue's case: calibrate opencv_fisheye_left, a ray at 120 deg must not land."""
    import subprocess
    import sys

    data = shared_data_file("opencv_fisheye_left.dataset.json")
    out = tmp_path / "calib.json"
    cmd = [sys.executable, "-m", "gtsam_sphere", "calibrate", str(data), "-o", str(out)]
    subprocess.run(cmd, check=True, capture_output=True)
    calib = load_calibration(out)
    cam = calib.camera
    assert cam.observed_alpha_rad == pytest.approx(
        math.radians(calib.statistics["max_incidence_deg"]), abs=1e-3
    )
    assert np.isnan(cam.project(_rays_at([120.0, 140.0]))).all()
    if cam.correction is None:  # the loop kept round 0: a kNN on the residuals, as round 1
        obs = calib.extra["observations"]
        cam.correction = KNNCorrection(degree=0).fit(
            np.asarray(obs["uv_px"]), np.asarray(obs["residual_px"])
        )
    agree = cam.correction_table().agreement(
        cam.correction, check_pixels(cam.correction, W, H, n=20000, seed=9)
    )
    assert agree["rms_px"] < 0.01


def test_visibility_by_projection_has_no_phantom_observations():
    """Points all around the camera: those landing in the image are exactly the valid ones."""
    # a fisheye whose polynomial turns over past the data (as real fits do): without the
    # valid field, rays far behind the camera land inside the image
    cam = SphereCamera(
        W, H, 640.0, 400.0, 300.0, radial={"g3": 0.05, "g5": -0.3}, correction=_knn()
    )
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(200000, 3)) * rng.uniform(0.5, 20.0, (200000, 1))
    inside = lambda uv: (  # noqa: E731
        np.isfinite(uv).all(axis=1)
        & (uv[:, 0] >= -0.5)
        & (uv[:, 0] <= W - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] <= H - 0.5)
    )
    alpha = np.degrees(np.arctan2(np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]))
    folded = inside(cam.project(pts, valid_only=False))
    assert (folded & (alpha > math.degrees(cam.max_alpha_rad()) + 5)).sum() > 100  # phantoms
    cam.observed_alpha_rad = math.radians(80.0)
    seen = inside(cam.project(pts))
    assert not (seen & ~cam.valid_mask(pts)).any()
    assert seen.sum() > 0.2 * len(pts) and alpha[seen].max() <= 82.0 + 1e-9


# every model family: (kwargs of SphereCamera, observed field in degrees or None)
_FAMILIES = {
    "sphere-75": (dict(), 75.0),
    "sphere-past-180": (dict(), 120.0),  # the paper's >180 deg lens: two halves, one disc
    "sphere-brown": (dict(brown={"k1": -0.05, "p1": 2e-4, "a1": 1e-4}, brown_scale_px=640.0), 80.0),
    "radial-narrow": (dict(radial={"g3": 0.3, "w": math.log(0.25)}), 45.0),
    "radial-fisheye": (dict(radial={"g3": -0.04, "g5": 0.05}), 100.0),
    "radial-250": (dict(radial={}), 125.0),
    "radial-warped-rim": (dict(radial={"g3": 0.02, "w": math.log(4.0)}), 150.0),
    "radial-folding-polynomial": (dict(radial={"g3": -0.2}), None),
}


@pytest.mark.parametrize("with_knn", [False, True], ids=["plain", "knn"])
@pytest.mark.parametrize("family", sorted(_FAMILIES))
def test_every_family_is_nan_exactly_beyond_its_valid_field(family, with_knn):
    """project: finite (and inverted by unproject) inside the valid field, NaN beyond it.

    Inside: every ray up to ``valid_alpha_rad`` projects and comes back (the sphere
    mapping's back half with ``hemisphere=-1``); beyond, up to 180 deg: NaN, and
    ``valid_mask`` says the same. No ray beyond the field lands in the image.
    """
    kwargs, observed_deg = _FAMILIES[family]
    cam = SphereCamera(
        W,
        H,
        640.0,
        400.0,
        300.0,
        correction=_knn() if with_knn else None,
        observed_alpha_rad=None if observed_deg is None else math.radians(observed_deg),
        **kwargs,
    )
    limit_deg = math.degrees(cam.valid_alpha_rad())
    if observed_deg is not None:
        assert limit_deg == pytest.approx(
            min(
                observed_deg + 2.0,
                math.degrees(cam.max_alpha_rad()) if cam.radial is not None else 180.0,
            )
        )
    else:
        assert limit_deg == pytest.approx(math.degrees(cam.max_alpha_rad()))
        assert limit_deg < 179.0  # this polynomial folds: its own field is the limit
    inside = np.linspace(0.0, limit_deg - 0.05, 60)
    beyond = np.linspace(limit_deg + 0.05, 180.0, 40)
    for azimuth in (0.0, 37.0, 135.0, 250.0):
        rays_in = _rays_at(inside, azimuth)
        rays_out = _rays_at(beyond, azimuth)
        uv_in = cam.project(rays_in)
        uv_out = cam.project(rays_out)
        assert np.isfinite(uv_in).all(), (family, azimuth)
        assert np.isnan(uv_out).all(), (family, azimuth)
        np.testing.assert_array_equal(cam.valid_mask(rays_in), True)
        np.testing.assert_array_equal(cam.valid_mask(rays_out), False)
        back = np.where(inside > 90.0, -1.0, 1.0) if cam.radial is None else 1.0
        if cam.radial is None and cam.brown:
            back = cam.pixel_hemisphere(uv_in)
        rays_back = cam.unproject(uv_in, hemisphere=back)
        err_deg = np.degrees(np.arccos(np.clip(np.sum(rays_back * rays_in, axis=1), -1, 1)))
        # the sphere mapping is flat at 90 deg: its inverse loses precision there
        near_fold = (
            (np.abs(inside - 90.0) < 3.0) if cam.radial is None else np.zeros_like(inside, bool)
        )
        assert err_deg[~near_fold].max() < 1e-3, (family, azimuth, err_deg.max())
