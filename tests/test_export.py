"""Exports to OpenCV / Kalibr models (gtsam_sphere.apps.export): fits, cv2 agreement, files, CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from helpers import bare_calibration

from gtsam_sphere import SphereCamera, load_calibration
from gtsam_sphere.apps.export import (
    TARGETS,
    ds_project,
    export_calibration,
    export_camera,
    incidence_deg,
    kb_project,
    pixel_rays,
    project_rays,
    rational_project,
    sample_region,
    write_export,
)
from gtsam_sphere.cli import main
from gtsam_sphere.io.dataset import DatasetError

W, H, C = 1200, 900, 400.0


def equidistant_like(width=W, height=H, c=C, shift=(3.0, -2.0)) -> SphereCamera:
    """A sphere + Brown camera whose image radius is ``c * alpha`` (equidistant).

    ``r - brown(r) = c sin(r / c)``: the Brown terms are the first three of the
    series of ``r - c sin(r / c)``; exact to 1e-4 rad up to 75 deg, and the
    image folds near 90 deg so rays past 90 deg land outside it.
    """
    s = 0.5 * max(width, height)
    brown = {"k1": s**2 / (6 * c**2), "k2": -(s**4) / (120 * c**4), "k3": s**6 / (5040 * c**6)}
    return SphereCamera(
        width,
        height,
        xp=width / 2 - 0.5 + shift[0],
        yp=height / 2 - 0.5 + shift[1],
        c=c,
        brown=brown,
        brown_scale_px=s,
    )


def observed_pixels(cam, max_deg, n=3000, seed=0):
    """Random pixels inside the image within ``max_deg`` incidence (equidistant radius)."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n)
    rad = cam.c * np.radians(max_deg) * np.sqrt(rng.uniform(0, 1, n))
    uv = np.column_stack([cam.xp + rad * np.cos(ang), cam.yp + rad * np.sin(ang)])
    inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] > 0)
    return uv[inside & (uv[:, 1] < cam.height - 1)]


@pytest.fixture(scope="module")
def cam():
    return equidistant_like()


@pytest.fixture(scope="module")
def obs75(cam):
    return observed_pixels(cam, 75.0)


def _cv2_fisheye(result, rays):
    uv, _ = cv2.fisheye.projectPoints(
        np.ascontiguousarray(rays[None], np.float64), np.zeros(3), np.zeros(3), result.K, result.D
    )
    return uv.reshape(-1, 2)


def test_model_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    rays = rng.normal(size=(50, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 0.3
    cases = (
        (kb_project, np.array([400.0, 410.0, 600.0, 450.0, 0.01, -0.02, 0.003, -0.001])),
        (
            rational_project,
            np.array([400, 405, 600, 450, 0.3, 0.05, 1e-3, -2e-3, 1e-3, 0.4, 0.06, 2e-3]),
        ),
        (ds_project, np.array([-0.2, 0.6, 300.0, 310.0, 600.0, 450.0])),
    )
    for fn, p in cases:
        _, J = fn(p, rays, jacobians=True)
        for k in range(len(p)):
            h = 1e-7 * max(abs(p[k]), 1.0)
            dp = np.zeros_like(p)
            dp[k] = h
            num = (fn(p + dp, rays) - fn(p - dp, rays)) / (2 * h)
            assert np.allclose(J[:, :, k], num, rtol=1e-5, atol=1e-5), (fn.__name__, k)


def test_fisheye_export_recovers_an_equidistant_camera(cam, obs75):
    res = export_camera(cam, "opencv-fisheye", obs75, n_samples=5000)
    # representable source: tiny residual, the true focal length and principal point
    assert res.rms_px < 0.005 and res.max_px < 0.02
    assert res.coverage == 1.0 and res.n_covered == res.n_samples
    assert res.params["fx"] == pytest.approx(C, abs=0.05)
    assert res.params["fy"] == pytest.approx(C, abs=0.05)
    assert res.params["cx"] == pytest.approx(cam.xp, abs=0.01)
    assert np.all(np.abs(res.D) < 1e-3)
    # cv2 itself re-projects fresh rays of the region to within the reported residual
    rays = pixel_rays(cam, observed_pixels(cam, 74.0, n=500, seed=7))
    err = np.linalg.norm(_cv2_fisheye(res, rays) - cam.project(rays), axis=1)
    assert err.max() <= res.max_px + 1e-3
    assert res.observations["n"] == len(obs75) and res.observations["rms_px"] < 0.005


def test_fisheye_export_reports_what_lies_past_90_degrees(cam):
    obs = observed_pixels(cam, 100.0, seed=3)
    res = export_camera(cam, "opencv-fisheye", obs, n_samples=5000)
    sample = sample_region(cam, obs, n_samples=5000)
    inc = sample.incidence_deg
    assert inc.max() > 95  # the region reaches behind the camera ...
    # ... and exactly the rays at or past 90 deg are excluded and counted
    assert res.coverage == pytest.approx(np.mean(inc < 90), abs=2e-3)
    assert 0.01 < 1 - res.coverage < 0.2
    assert "excluded" in res.summary() and res.max_incidence_deg_covered < 90
    # the fit is still good where cv2.fisheye can project
    rays = sample.rays[inc < 85]
    err = np.linalg.norm(_cv2_fisheye(res, rays) - sample.uv_px[inc < 85], axis=1)
    assert np.sqrt(np.mean(err**2)) <= 1.5 * res.rms_px + 1e-3


def test_rational_export_agrees_with_cv2_project_points(cam, obs75):
    res = export_camera(cam, "opencv-rational", obs75, n_samples=5000)
    assert res.params["max_incidence_deg"] == 80.0
    assert res.rms_px < 0.02 and res.coverage == 1.0
    rays = pixel_rays(cam, observed_pixels(cam, 74.0, n=500, seed=8))
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), res.K, res.D)
    err = np.linalg.norm(uv.reshape(-1, 2) - cam.project(rays), axis=1)
    assert err.max() <= res.max_px + 1e-3
    assert np.allclose(res.project(rays, use_cv2=False), uv.reshape(-1, 2), atol=1e-6)
    # the incidence limit is honoured: a 60 deg export covers only what lies below 60 deg
    res60 = export_camera(cam, "opencv-rational", obs75, max_incidence_deg=60.0, n_samples=3000)
    inc = sample_region(cam, obs75, n_samples=3000).incidence_deg
    assert res60.coverage == pytest.approx(np.mean(inc < 60), abs=2e-3)
    assert res60.max_incidence_deg_covered < 60


def test_double_sphere_covers_a_field_past_180_degrees(cam):
    obs = observed_pixels(cam, 100.0, seed=3)
    res = export_camera(cam, "kalibr-ds", obs, n_samples=4000)
    assert res.coverage == 1.0 and res.max_incidence_deg_covered > 95
    assert res.rms_px < 1.5  # the source is only equidistant-like near 90 deg
    assert 0 <= res.params["alpha"] <= 1
    # representable part: tight
    near = export_camera(cam, "kalibr-ds", observed_pixels(cam, 60.0), n_samples=3000)
    assert near.rms_px < 0.02


def _ds_reference(xi, alpha, fx, fy, cx, cy, p):
    """Double-sphere projection written out independently (Usenko et al. 2018, Eq. 40-41)."""
    x, y, z = p.T
    d1 = np.sqrt(x**2 + y**2 + z**2)
    d2 = np.sqrt(x**2 + y**2 + (xi * d1 + z) ** 2)
    den = alpha * d2 + (1 - alpha) * (xi * d1 + z)
    return np.column_stack([fx * x / den + cx, fy * y / den + cy])


def test_kalibr_yaml_files(cam, obs75, tmp_path):
    yaml = pytest.importorskip("yaml")
    ds = export_camera(cam, "kalibr-ds", obs75, n_samples=3000, source="calib.json")
    doc = yaml.safe_load(write_export(ds, tmp_path / "ds.yaml").read_text())["cam0"]
    assert doc["camera_model"] == "ds" and doc["distortion_model"] == "none"
    assert doc["distortion_coeffs"] == [] and doc["resolution"] == [W, H]
    rays = pixel_rays(cam, observed_pixels(cam, 74.0, n=300, seed=9))
    err = np.linalg.norm(_ds_reference(*doc["intrinsics"], rays) - cam.project(rays), axis=1)
    assert err.max() <= ds.max_px + 1e-3
    equi = export_camera(cam, "kalibr-equi", obs75, n_samples=3000)
    doc = yaml.safe_load(write_export(equi, tmp_path / "equi.yaml").read_text())["cam0"]
    assert doc["camera_model"] == "pinhole" and doc["distortion_model"] == "equidistant"
    assert doc["intrinsics"] == pytest.approx(list(equi.K[[0, 1, 0, 1], [0, 1, 2, 2]]))
    assert doc["distortion_coeffs"] == pytest.approx(list(equi.D))


def test_project_rays_handles_the_back_half_past_a_fold(cam):
    obs = observed_pixels(cam, 100.0, seed=4)
    hemi = cam.pixel_hemisphere(obs)
    rays = pixel_rays(cam, obs, hemi)
    ok = np.all(np.isfinite(rays), axis=1)
    inc = incidence_deg(rays[ok])
    # the fold rule puts pixels past 90 deg (equidistant radius) on the back half
    r_deg = np.degrees(np.linalg.norm(obs[ok] - [cam.xp, cam.yp], axis=1) / cam.c)
    clear = np.abs(r_deg - 90) > 2
    assert np.array_equal(inc[clear] > 90, r_deg[clear] > 90)
    back = ok.copy()
    back[ok] = (inc > 92) & (inc < 99)
    assert back.sum() > 20
    uv = project_rays(cam, rays[back])
    assert np.nanmax(np.linalg.norm(uv - obs[back], axis=1)) < 1e-6
    assert np.all(np.isfinite(uv))


def test_cli_writes_every_target_and_prints_the_residual(cam, obs75, tmp_path, capsys):
    path = bare_calibration(cam, obs75).save(tmp_path / "calib.json")
    calib = load_calibration(path)
    for target in TARGETS:
        ext = "yaml" if target.startswith("kalibr") else "json"
        out = tmp_path / f"out_{target}.{ext}"
        assert main(["export", str(path), "--to", target, "-o", str(out), "--samples", "2000"]) == 0
        text = capsys.readouterr().out
        assert "fit residual: RMS" in text and "covers 100.0%" in text
        assert not list(tmp_path.glob(".*.tmp"))  # atomic write left no temporary file
        if ext == "json":
            doc = json.loads(out.read_text())
            ref = export_calibration(calib, target, n_samples=2000)
            assert doc["image_size"] == [W, H]
            assert np.allclose(doc["K"], ref.K)
            assert np.allclose(doc["dist" if target == "opencv-rational" else "D"], ref.D)
            assert doc["fit"]["rms_px"] == pytest.approx(ref.rms_px)
        else:
            assert out.read_text().count("cam0:") == 1


def test_cli_bad_input(tmp_path, capsys):
    out = tmp_path / "x.json"
    assert (
        main(["export", str(tmp_path / "missing.json"), "--to", "kalibr-ds", "-o", str(out)]) == 2
    )
    assert "missing.json" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "gtsam-sphere/calibration@1", "camera": {"width": 10}}')
    assert main(["export", str(bad), "--to", "opencv-fisheye", "-o", str(out)]) == 2
    assert "bad.json" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(DatasetError, match="nothing to fit"):
        # a camera whose observed region lies entirely past 90 deg has nothing for cv2.fisheye
        cam = equidistant_like()
        ring = observed_pixels(cam, 100.0, seed=5)
        d = ring - [cam.xp, cam.yp]
        r_deg = np.degrees(np.linalg.norm(d, axis=1) / cam.c)
        patch = (r_deg > 93) & (np.abs(np.arctan2(d[:, 1], d[:, 0]) - 0.6435) < 0.1)  # corner
        export_calibration(bare_calibration(cam, ring[patch]), "opencv-fisheye")


def test_export_reports_the_error_outside_the_observed_region(cam, tmp_path, caplog):
    yaml = pytest.importorskip("yaml")
    obs = observed_pixels(cam, 40.0)
    # the camera is equidistant well past the observed 40 deg: cv2.fisheye extrapolates it
    with caplog.at_level("WARNING", logger="gtsam_sphere.apps.export"):
        res = export_camera(cam, "opencv-fisheye", obs, n_samples=3000)
    assert not caplog.records
    o = res.outside
    assert o["from_deg"] == pytest.approx(res.max_incidence_deg_region)
    assert o["to_deg"] == pytest.approx(o["from_deg"] + 20.0)
    assert o["n"] > 100 and o["max_px"] < 0.05 and not o["exceeds"]
    assert o["unproject_max_deg"] < 0.01
    assert sum(b["n"] for b in o["bands"]) == o["n"]
    # an independent check of the band: cv2 against the calibrated pixels
    w, h = cam.width, cam.height
    uv = np.stack(np.meshgrid(np.arange(0, w, 7.0), np.arange(0, h, 7.0)), -1).reshape(-1, 2)
    rays = pixel_rays(cam, uv)
    inc = incidence_deg(rays)
    band = (inc > o["from_deg"]) & (inc <= o["to_deg"])
    err = np.linalg.norm(_cv2_fisheye(res, rays[band]) - uv[band], axis=1)
    assert err.max() < 0.05
    # written: the JSON fit block and the summary (Kalibr comments) both state it
    doc = json.loads(write_export(res, tmp_path / "f.json").read_text())
    assert doc["fit"]["outside"]["max_px"] == pytest.approx(o["max_px"])
    assert doc["fit"]["rms_px"] == pytest.approx(res.rms_px)
    equi = export_camera(cam, "kalibr-equi", obs, n_samples=3000)
    text = write_export(equi, tmp_path / "e.yaml").read_text()
    assert "# " + equi.summary().splitlines()[-1].strip() in text.replace("#   ", "# ")
    assert "outside it (" in text and "inside the observed region" in text
    assert yaml.safe_load(text)["cam0"]["camera_model"] == "pinhole"


def test_export_warns_when_the_model_diverges_past_the_observed_field(cam, caplog):
    obs = observed_pixels(cam, 55.0)
    with caplog.at_level("WARNING", logger="gtsam_sphere.apps.export"):
        res = export_camera(cam, "opencv-rational", obs, n_samples=3000)
    # inside: as good as ever
    assert res.rms_px < 0.02 and res.coverage == 1.0
    o = res.outside
    assert o["exceeds"] and o["max_px"] > 1.0
    assert o["from_deg"] <= o["valid_to_deg"] < o["to_deg"]
    assert f"do not use this model past {o['valid_to_deg']:.1f} deg" in res.summary()
    msgs = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(msgs) == 1 and "must not be used past" in msgs[0]
    assert f"{o['valid_to_deg']:.1f} deg" in msgs[0]
