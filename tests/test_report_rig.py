"""The rig report (gtsam_sphere.apps.report_rig) and the rig use end to end (slow)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml
from test_export_rig import small_rig

from gtsam_sphere.apps.report_rig import (
    extrinsic_sigmas,
    rotation_angle_deg,
    rotation_vector_deg,
    write_any_report,
    write_rig_report,
)
from gtsam_sphere.cli import main
from gtsam_sphere.io.calibration import load_calibration


def _with_frames(calib, n=5):
    """Frames moving along world X, the rig upright (camera y = world -Z), targets around."""
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # rig z forward = world Y
    calib.frame_ids = [f"{k:03d}" for k in range(n)]
    centres = np.array([[0.3 * k, 0.1 * k, 1.5] for k in range(n)])
    calib.rig_from_world_R = np.repeat(R[None], n, axis=0)
    calib.rig_from_world_t = np.array([-R @ c for c in centres])
    calib.target_ids = [f"T{k}" for k in range(20)]
    calib.target_xyz = np.random.default_rng(0).uniform([0, 3, 0], [4, 4, 3], size=(20, 3))
    calib.statistics["cameras"]["cam1"]["cam_from_rig_precision"] = {
        "rotation_sigma_deg": 0.012,
        "translation_sigma": [1e-4, 2e-4, 3e-4],
        "baseline_sigma": 2.5e-4,
        "sigma_source": "marginal covariance of the joint adjustment",
    }
    return calib


def test_rotation_helpers():
    R = cv2.Rodrigues(np.radians([10.0, -20.0, 5.0]))[0]
    assert np.allclose(rotation_vector_deg(R), [10.0, -20.0, 5.0])
    assert rotation_angle_deg(R) == pytest.approx(np.linalg.norm([10, -20, 5]))
    flip = np.diag([-1.0, 1.0, -1.0])  # 180 deg about y
    assert np.allclose(np.abs(rotation_vector_deg(flip)), [0, 180, 0])


def test_extrinsic_sigmas_as_the_file_gives_them():
    calib = _with_frames(small_rig(3))
    rot, tr = extrinsic_sigmas(calib.statistics, "cam1")
    assert rot == 0.012 and np.allclose(tr, [1e-4, 2e-4, 3e-4])
    assert extrinsic_sigmas(calib.statistics, "cam2") == (None, None)


def test_rig_page(tmp_path):
    calib = _with_frames(small_rig(3))
    path = calib.save(tmp_path / "rig.json")
    paths = write_rig_report(
        load_calibration(path), tmp_path / "rep", source=str(path), camera_pages=False
    )
    assert paths["rig"].stat().st_size > 10_000
    md = paths["markdown"].read_text()
    assert "| [cam1](cam1/index.html) | `radial` | 800 x 640 |" in md
    assert "0.0120" in md and "0.0001, 0.0002, 0.0003" in md  # the file's sigmas
    assert "2.5000e-04 | marginal covariance of the joint adjustment |" in md
    assert "| cam2 |" in md and "n/a" in md  # no sigma in the file: said so
    html = paths["html"].read_text()
    assert '<a href="cam0/index.html">cam0</a>' in html and "rig.png" in html


@pytest.mark.slow
def test_report_cli_on_a_rig_writes_camera_pages(tmp_path, capsys):
    path = _with_frames(small_rig(2)).save(tmp_path / "rig.json")
    assert main(["report", str(path), "-o", str(tmp_path / "rep")]) == 0
    out = capsys.readouterr().out
    assert "rig page" in out
    for cid in ("cam0", "cam1"):
        assert (tmp_path / "rep" / cid / "index.html").is_file()
        assert (tmp_path / "rep" / cid / "coverage.png").is_file()
    assert main(["report", str(path), "-o", str(tmp_path / "r2"), "--compare", str(path)]) == 2
    assert "--compare" in capsys.readouterr().err


@pytest.mark.slow  # end to end: simulate a stereo rig, calibrate, report, export
def test_simulated_stereo_rig_report_and_exports(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert (
        main(["simulate", "--rig", "stereo", "--frames", "4", "--seed", "3", "-o", str(sim)]) == 0
    )
    calib_path = tmp_path / "calib.json"
    assert main(["calibrate", str(sim / "dataset.json"), "-o", str(calib_path), "--quiet"]) in (
        0,
        1,
    )
    capsys.readouterr()
    rig = load_calibration(calib_path)
    paths = write_any_report(calib_path, tmp_path / "rep")
    assert set(paths) >= {"rig", "html", "markdown", "camera:left", "camera:right"}
    md = paths["markdown"].read_text()
    assert "| [right](right/index.html) |" in md and "rotation sigma (deg)" in md
    # the sigma shown is the file's
    rot_s, _ = extrinsic_sigmas(rig.statistics, "right")
    if rot_s is not None:
        assert f"{rot_s:.4f}" in md

    out = tmp_path / "camchain.yaml"
    assert main(["export", str(calib_path), "--to", "kalibr", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    doc = yaml.safe_load(out.read_text())
    truth = json.loads((sim / "truth.json").read_text())
    print(printed)
    T = np.array(doc["cam1"]["T_cn_cnm1"])
    R, t = rig.cam_from_rig["right"]
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], t)
    assert doc["cam0"]["resolution"] == [rig.cameras["left"].width, rig.cameras["left"].height]
    # the fitted models reproduce the calibrated cameras at their observations
    for cid in rig.camera_ids:
        fit = rig.camera_calibration(cid)
        assert f"camera {cid}: kalibr-" in printed
        assert fit.statistics["rms_px"] < 1.0
    true_t = next(c for c in truth["cameras"] if c["id"] == "right")["cam_from_rig"]["t"]
    assert abs(np.linalg.norm(T[:3, 3]) - np.linalg.norm(true_t)) < 0.01  # baseline (m)

    stereo = tmp_path / "stereo.yaml"
    assert main(["export", str(calib_path), "--to", "opencv-stereo", "-o", str(stereo)]) == 0
    fs = cv2.FileStorage(str(stereo), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("R").mat(), R) and np.allclose(fs.getNode("T").mat().ravel(), t)
