"""Tests of the calibration report (gtsam_sphere.apps.report)."""

from __future__ import annotations

import argparse

import matplotlib.image as mpimg
import numpy as np
import pytest

from gtsam_sphere.apps.report import (
    PLOTS,
    add_cli_arguments,
    binned_mean_field,
    cv_curve,
    linear_trend,
    observations_of,
    radial_components,
    radial_trends,
    robust_limits,
    run_cli,
    write_report,
)
from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.io.calibration import Calibration

W, H = 1200, 900


class ShiftCorrection:
    """A smooth learned correction: a small radial field."""

    def predict(self, uv_px):
        uv = np.asarray(uv_px, float)
        return 1e-3 * (uv - np.array([W / 2, H / 2]))


def synthetic_calibration(
    n=800,
    slope_y=0.0,
    intercept_y=0.0,
    history=True,
    correction=False,
    cv=False,
    n_outliers=5,
    seed=0,
    noise_px=0.3,
) -> Calibration:
    """A Calibration with fake observations: Gaussian noise, optional linear y trend in radius."""
    rng = np.random.default_rng(seed)
    cam = SphereCamera(width=W, height=H, xp=W / 2 + 3.0, yp=H / 2 - 2.0, c=400.0)
    if correction:
        cam.correction = ShiftCorrection()
    uv = rng.uniform([0, 0], [W, H], size=(n, 2))
    r = np.linalg.norm(uv - cam.principal_point_px, axis=1)
    res = rng.normal(0, noise_px, size=(n, 2))
    res[:, 1] += slope_y * r + intercept_y
    weight = np.ones(n)
    bad = rng.choice(n, n_outliers, replace=False)
    res[bad] += rng.choice([-1, 1], size=(n_outliers, 2)) * 25.0
    weight[bad] = 0.05
    images = [f"img{k % 10:02d}" for k in range(n)]
    targets = [f"t{k}" for k in range(n)]
    rms = float(np.sqrt(np.mean((res**2).sum(1))))
    stats = {
        "rms_px": rms,
        "n_observations": n,
        "n_rejected": 2,
        "variance_factor": 1.02,
        "redundancy": 2 * n - 100,
        "converged": True,
        "intrinsics_sigma": {"xp": 0.05, "yp": 0.06, "c": 0.1},
    }
    extra = {
        "observations": {
            "image": images,
            "target": targets,
            "uv_px": uv,
            "residual_px": res,
            "weight": weight,
            "incidence_deg": np.degrees(r / cam.c),
        },
        "downweighted": [
            {
                "image": images[o],
                "target": targets[o],
                "residual_px": res[o].tolist(),
                "weight": 0.05,
                "outlier": True,
            }
            for o in bad
        ],
    }
    if history:
        hist = [
            {"iteration": k, "cost": 1e5 * 0.5**k + 10.0, "seconds": 0.1 * k, "stage": 1 + k // 8}
            for k in range(15)
        ]
        if cv:
            hist += [
                {
                    "iteration": 15 + k,
                    "cost": 9.0 - k,
                    "knn_iteration": k,
                    "cv_score": 0.5 / (k + 1),
                }
                for k in range(4)
            ]
        extra["history"] = hist
    return Calibration(
        model="sphere+knn" if correction else "sphere",
        camera=cam,
        image_ids=sorted(set(images)),
        cam_from_world_R=np.tile(np.eye(3), (10, 1, 1)),
        cam_from_world_t=np.zeros((10, 3)),
        target_ids=targets,
        target_xyz=rng.normal(size=(n, 3)),
        statistics=stats,
        extra=extra,
    )


def _check_outputs(paths):
    for key in PLOTS:
        assert paths[key].name == f"{key}.png"
        assert paths[key].stat().st_size > 1000
        img = mpimg.imread(paths[key])
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert paths["markdown"].name == "report.md"
    assert paths["html"].name == "index.html"
    md = paths["markdown"].read_text()
    page = paths["html"].read_text()
    for key in PLOTS:
        assert f"({key}.png)" in md
        assert f'src="{key}.png"' in page
    return md, page


@pytest.mark.slow  # end-to-end
def test_full_report(tmp_path):
    calib = synthetic_calibration(correction=True, cv=True)
    paths = write_report(calib, tmp_path / "rep", title="Synthetic | test")
    md, page = _check_outputs(paths)
    rms = calib.statistics["rms_px"]
    assert f"{rms:.4f}" in md and f"{rms:.4f}" in page
    assert "# Synthetic | test" in md and "<h1>Synthetic | test</h1>" in page
    # intrinsics sigma, down-weighted list, statistics keys
    assert "| parameter | value | sigma | unit |" in md and "| xp | 603.0000 | 0.0500 | px |" in md
    assert "`variance_factor`" in md and "`redundancy`" in md
    assert "5 observations have a robust weight below 1" in md
    assert md.count("| yes |") >= 5


@pytest.mark.slow  # end-to-end
def test_missing_optional_parts(tmp_path):
    class Zero:
        def predict(self, uv_px):
            return np.zeros((len(uv_px), 2))

    # no history, no down-weighted list, no sigmas, a zero correction, plain lists as
    # loaded from JSON
    calib = synthetic_calibration(n=300, history=False)
    calib.camera.correction = Zero()
    calib.extra.pop("downweighted")
    del calib.statistics["intrinsics_sigma"]
    obs = calib.extra["observations"]
    for k in ("uv_px", "residual_px", "weight", "incidence_deg"):
        obs[k] = np.asarray(obs[k]).tolist()
    md, _ = _check_outputs(write_report(calib, tmp_path / "a"))
    assert "| parameter | value | unit |" in md
    # nothing per observation at all, no statistics, no correction
    calib.camera.correction = None
    calib.extra.clear()
    calib.statistics = {}
    _check_outputs(write_report(calib, tmp_path / "b"))


@pytest.mark.slow  # end-to-end
def test_file_round_trip_cli_and_compare(tmp_path):
    a = synthetic_calibration(seed=1)
    b = synthetic_calibration(seed=2, correction=False, slope_y=1e-3)
    pa = a.save(tmp_path / "a.json")
    pb = b.save(tmp_path / "b.json")
    parser = argparse.ArgumentParser()
    add_cli_arguments(parser)
    args = parser.parse_args([str(pa), "-o", str(tmp_path / "out"), "--compare", str(pb)])
    assert run_cli(args) == 0
    md = (tmp_path / "out" / "report.md").read_text()
    assert "## Comparison" in md
    assert "a.json (`sphere`)" in md and "b.json (`sphere`)" in md
    assert (tmp_path / "out" / "index.html").exists()


def test_linear_trend_recovers_injected_slope():
    calib = synthetic_calibration(
        n=3000, slope_y=-1.7e-4, intercept_y=0.21, n_outliers=20, noise_px=0.05
    )
    obs = observations_of(calib)
    tr = radial_trends(obs, calib.camera.principal_point_px)
    slope, icpt = tr["y"]
    assert slope == pytest.approx(-1.7e-4, abs=2.5e-5)
    assert icpt == pytest.approx(0.21, abs=0.03)
    assert abs(tr["x"][0]) < 2.5e-5
    # exact on noise-free data
    x = np.linspace(0, 800, 50)
    assert linear_trend(x, 2e-3 * x - 0.5) == pytest.approx((2e-3, -0.5))
    assert all(np.isnan(linear_trend([1.0], [2.0])))


def test_helpers():
    uv = np.array([[110.0, 100.0], [100.0, 120.0]])
    res = np.array([[1.0, 0.5], [0.5, 2.0]])
    r, rad, tan = radial_components(uv, res, np.array([100.0, 100.0]))
    np.testing.assert_allclose(r, [10, 20])
    np.testing.assert_allclose(rad, [1.0, 2.0])
    np.testing.assert_allclose(tan, [0.5, -0.5])
    v = np.concatenate([np.random.default_rng(0).normal(0, 1, 1000), [500.0]])
    lo, hi = robust_limits(v)
    assert -10 < lo < -3 and 3 < hi < 10
    cx, cy, mean, count = binned_mean_field(
        np.array([[10.0, 10.0]] * 3 + [[90.0, 90.0]]), np.ones((4, 2)), 100, 100, n_cols=2
    )
    assert count[0, 0] == 3 and count[1, 1] == 1
    np.testing.assert_allclose(mean[0, 0], [1, 1])
    assert np.isnan(mean[1, 1]).all()


def test_cv_curve_key_spellings():
    # the correction loop's spelling: one CV value repeated on every row of a round
    hist = [
        {"iteration": k, "cost": 1.0, "knn_round": k // 3, "cv_rmse_px": 0.5 - 0.1 * (k // 3)}
        for k in range(9)
    ]
    x, y, xk, ck = cv_curve(hist)
    np.testing.assert_allclose(x, [0, 1, 2])
    np.testing.assert_allclose(y, [0.5, 0.4, 0.3])
    assert (xk, ck) == ("knn_round", "cv_rmse_px")
    x, y, xk, ck = cv_curve([{"iteration": 4, "cost": 1.0, "cv_score": 0.2}])
    assert (list(x), list(y), xk, ck) == ([4.0], [0.2], "iteration", "cv_score")
    assert cv_curve([{"iteration": 0, "cost": 1.0}]) is None
    assert cv_curve(None) is None
