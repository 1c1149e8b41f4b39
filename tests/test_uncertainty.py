"""Projection uncertainty maps (gtsam_sphere.uncertainty) and their report figure."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gtsam_sphere import SphereCamera
from gtsam_sphere.calibration import Calibration
from gtsam_sphere.correct import KNNCorrection
from gtsam_sphere.dataset import DatasetError
from gtsam_sphere.export import pixel_rays
from gtsam_sphere.report import PLOTS, write_report
from gtsam_sphere.uncertainty import (
    intrinsic_value,
    intrinsics_covariance,
    knn_sigma_px,
    uncertainty_map,
    uncertainty_map_of,
    with_intrinsic,
)

W, H = 800, 600
NAMES = ["xp_px", "yp_px", "c_px", "k1", "k2", "p1"]


def brown_camera() -> SphereCamera:
    return SphereCamera(
        W, H, xp=402.0, yp=297.0, c=330.0, brown={"k1": 0.2, "k2": -0.02, "p1": 5e-4}
    )


def covariance(scale: float = 1.0) -> np.ndarray:
    sig = np.array([0.3, 0.25, 0.5, 1e-3, 5e-4, 2e-5])
    corr = np.eye(6)
    corr[2, 3] = corr[3, 2] = 0.6  # c and k1 are correlated in a real adjustment
    corr[3, 4] = corr[4, 3] = -0.8
    return scale * corr * np.outer(sig, sig)


def test_adapter_maps_names_to_camera_attributes():
    cam = brown_camera()
    assert intrinsic_value(cam, "xp_px") == 402.0 and intrinsic_value(cam, "c") == 330.0
    assert intrinsic_value(cam, "k3") == 0.0  # a Brown term the model does not carry
    moved = with_intrinsic(cam, "k1", 0.25)
    assert moved.brown["k1"] == 0.25 and cam.brown["k1"] == 0.2  # a copy
    assert with_intrinsic(cam, "yp_px", 1.0).yp == 1.0 and cam.yp == 297.0
    assert with_intrinsic(cam, "k3", 1e-3).brown["k3"] == 1e-3 and "k3" not in cam.brown
    with pytest.raises(ValueError, match="'g9'"):
        with_intrinsic(cam, "g9", 0.1)
    if any(f.name == "radial" for f in dataclasses.fields(SphereCamera)):
        rad = dataclasses.replace(cam, radial={"g3": 0.01})
        assert with_intrinsic(rad, "g3", 0.02).radial["g3"] == 0.02 and rad.radial["g3"] == 0.01


def test_zero_covariance_gives_a_zero_map():
    m = uncertainty_map(brown_camera(), np.zeros((6, 6)), NAMES, n_cols=16)
    ok = np.isfinite(m.sigma_px)
    assert ok.mean() > 0.9
    assert np.all(m.sigma_px[ok] == 0.0) and np.all(m.sigma_knn_px[ok] == 0.0)


def test_map_grows_with_the_covariance():
    cam = brown_camera()
    a = uncertainty_map(cam, covariance(1.0), NAMES, n_cols=16)
    b = uncertainty_map(cam, covariance(4.0), NAMES, n_cols=16)
    ok = np.isfinite(a.sigma_px)
    assert np.all(a.sigma_px[ok] > 0)
    assert np.allclose(b.sigma_px[ok] / a.sigma_px[ok], 2.0, rtol=0.03)
    # a principal-point-only covariance shifts every pixel by the same amount
    pp = np.zeros((6, 6))
    pp[0, 0], pp[1, 1] = 0.3**2, 0.4**2
    m = uncertainty_map(cam, pp, NAMES, n_cols=16)
    assert np.allclose(m.sigma_px[ok], 0.5, atol=1e-6)
    # c and the radial terms matter more away from the principal point
    cc = np.zeros((6, 6))
    cc[2, 2] = 1.0
    m = uncertainty_map(cam, cc, NAMES, n_cols=16)
    r = np.hypot(*np.meshgrid(m.u_px - cam.xp, m.v_px - cam.yp))
    inner, outer = ok & (r < 80), ok & (r > 250)
    assert m.sigma_px[outer].min() > 2 * m.sigma_px[inner].max()


def test_map_matches_monte_carlo():
    cam = brown_camera()
    cov = covariance()
    m = uncertainty_map(cam, cov, NAMES, n_cols=8)
    rows, cols = np.nonzero(np.isfinite(m.sigma_px))
    uv = np.column_stack([m.u_px[cols], m.v_px[rows]])
    rays = pixel_rays(cam, uv)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(np.zeros(6), cov, size=300)
    theta0 = np.array([intrinsic_value(cam, n) for n in NAMES])
    pix = []
    for d in draws:
        c = cam
        for name, value in zip(NAMES, theta0 + d):
            c = with_intrinsic(c, name, value)
        pix.append(c.project(rays))
    pix = np.array(pix)
    mc = np.sqrt(np.sum(pix.var(axis=0), axis=1))
    full_err = np.abs(m.sigma_px[rows, cols] / mc - 1)
    assert full_err.max() < 0.15
    # the diagonal-only map ignores the correlations: farther from the truth
    diag = uncertainty_map(cam, np.diag(np.diag(cov)), NAMES, n_cols=8)
    diag_err = np.abs(diag.sigma_px[rows, cols] / mc - 1)
    assert diag_err.mean() > 2 * full_err.mean()


def test_covariance_from_statistics():
    cov = covariance()
    names, got, note = intrinsics_covariance(
        {"intrinsics_covariance": cov.tolist(), "intrinsics_names": NAMES}
    )
    assert names == NAMES and np.allclose(got, cov) and note.startswith("full")
    names, got, note = intrinsics_covariance({"intrinsics_sigma": {"xp_px": 0.3, "c_px": 0.5}})
    assert names == ["xp_px", "c_px"] and np.allclose(got, np.diag([0.09, 0.25]))
    assert "diagonal only" in note
    with pytest.raises(DatasetError, match="neither"):
        intrinsics_covariance({"rms_px": 1.0}, "c.json")
    with pytest.raises(DatasetError, match=r"shape \(2, 2\)"):
        intrinsics_covariance(
            {"intrinsics_covariance": [[1, 0], [0, 1]], "intrinsics_names": NAMES}
        )
    with pytest.raises(DatasetError, match="intrinsics_names"):
        intrinsics_covariance({"intrinsics_covariance": [[1.0]]})
    with pytest.raises(DatasetError, match="negative"):
        intrinsics_covariance({"intrinsics_covariance": [[-1.0]], "intrinsics_names": ["c_px"]})


def _knn(noise_px: float, k: int = 16, n: int = 3000, seed: int = 0) -> KNNCorrection:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [W, H], size=(n, 2))
    smooth = 0.5 * np.column_stack([np.sin(uv[:, 0] / 200), np.cos(uv[:, 1] / 150)])
    y = smooth + rng.normal(0, noise_px, size=(n, 2))
    return KNNCorrection(n_neighbors=k, weights="uniform", cv_folds=2).fit(uv, y)


def test_knn_term_is_the_standard_error_of_the_local_mean():
    model = _knn(0.3, k=16)
    uv = np.random.default_rng(1).uniform([100, 100], [W - 100, H - 100], size=(400, 2))
    s = knn_sigma_px(model, uv)
    # per point: sqrt(2) * noise / sqrt(k) (both coordinates); the smooth part adds a little
    assert np.median(s) == pytest.approx(np.sqrt(2) * 0.3 / 4, rel=0.15)
    assert knn_sigma_px(object(), uv) is None
    cam = brown_camera()
    cam.correction = model
    m = uncertainty_map(cam, covariance(), NAMES, n_cols=10)
    ok = np.isfinite(m.sigma_px)
    assert np.all(m.sigma_knn_px[ok] > 0) and "kNN" in m.note
    assert np.allclose(
        m.sigma_px[ok] ** 2, m.sigma_intrinsics_px[ok] ** 2 + m.sigma_knn_px[ok] ** 2
    )
    quieter = _knn(0.1, k=16)
    cam.correction = quieter
    m2 = uncertainty_map(cam, covariance(), NAMES, n_cols=10)
    assert np.nanmedian(m2.sigma_knn_px) < 0.5 * np.nanmedian(m.sigma_knn_px)


def _calibration(stats: dict) -> Calibration:
    rng = np.random.default_rng(0)
    uv = rng.uniform([150, 100], [650, 500], size=(300, 2))
    return Calibration(
        model="brown",
        camera=brown_camera(),
        image_ids=[],
        cam_from_world_R=np.zeros((0, 3, 3)),
        cam_from_world_t=np.zeros((0, 3)),
        target_ids=[],
        target_xyz=np.zeros((0, 3)),
        statistics={"rms_px": 0.3, "n_observations": 300, "n_rejected": 0, **stats},
        extra={"observations": {"uv_px": uv, "residual_px": rng.normal(0, 0.3, (300, 2))}},
    )


def test_uncertainty_of_a_calibration_and_its_report_section(tmp_path):
    calib = _calibration(
        {"intrinsics_covariance": covariance().tolist(), "intrinsics_names": NAMES}
    )
    m = uncertainty_map_of(calib, n_cols=12)
    assert m.note.startswith("full") and np.nanmax(m.sigma_px) > 0
    paths = write_report(calib, tmp_path / "rep")
    assert "uncertainty" in PLOTS and paths["uncertainty"].stat().st_size > 1000
    md = paths["markdown"].read_text()
    assert "## Projection uncertainty" in md and "How to read it" in md
    assert "(uncertainty.png)" in md and "full covariance" in md
    # sigmas only: the page says the correlations are missing
    sig = dict(zip(NAMES, np.sqrt(np.diag(covariance()))))
    md = write_report(_calibration({"intrinsics_sigma": sig}), tmp_path / "b")["markdown"]
    assert "diagonal only" in md.read_text()
    # nothing: a placeholder image and a sentence, no failure
    paths = write_report(_calibration({}), tmp_path / "c")
    assert paths["uncertainty"].exists() and "No map" in paths["markdown"].read_text()
    with pytest.raises(DatasetError, match="neither"):
        uncertainty_map_of(_calibration({}))
