"""Rig exports (gtsam_sphere.apps.export_rig): Kalibr camchain, OpenCV stereo, the omni model."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import yaml
from helpers import bare_rig_calibration

from gtsam_sphere import SphereCamera
from gtsam_sphere.apps.export import ds_project, eucm_project, kb_project, omni_project, pixel_rays
from gtsam_sphere.apps.export_rig import (
    camera_overlaps,
    kalibr_camchain,
    opencv_stereo,
    relative_pose,
)
from gtsam_sphere.cli import main
from gtsam_sphere.io.calibration import RigCalibration, load_calibration

W, H = 800, 640


def rot(rx, ry, rz):
    return cv2.Rodrigues(np.array([rx, ry, rz], float))[0]


def small_rig(n=3, radial=None, units="m") -> RigCalibration:
    """A calibration@2 of ``n`` cameras (radial mapping, no observations: whole image)."""
    ids = [f"cam{k}" for k in range(n)]
    cams = {
        c: SphereCamera(
            W,
            H,
            W / 2 - 0.5 + 2 * k,
            H / 2 - 0.5 - k,
            260.0 + 15 * k,
            radial={"g3": -0.03} if radial is None else radial,
        )
        for k, c in enumerate(ids)
    }
    poses = {ids[0]: (np.eye(3), np.zeros(3))}
    for k, c in enumerate(ids[1:], 1):
        poses[c] = (rot(0.01 * k, 0.3 * k, -0.02), np.array([-0.12 * k, 0.003, 0.01 * k]))
    return bare_rig_calibration(cams, poses, units=units)


def test_omni_jacobian_matches_finite_differences():
    p = np.array([1.3, 300.0, 310.0, 400.0, 320.0, -0.1, 0.02, 0.001, -0.002])
    rays = np.random.default_rng(0).normal(size=(40, 3))
    rays[:, 2] = np.abs(rays[:, 2])
    _, J = omni_project(p, rays, jacobians=True)
    for k in range(len(p)):
        h = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros_like(p)
        dp[k] = h
        num = (omni_project(p + dp, rays) - omni_project(p - dp, rays)) / (2 * h)
        assert np.allclose(num, J[:, :, k], atol=1e-5 * max(1.0, np.abs(num).max()))


def _fitted_project(entry: dict, rays: np.ndarray) -> np.ndarray:
    """Project with a camchain entry's model (the package's numpy models of Kalibr's)."""
    intr, dist = entry["intrinsics"], entry["distortion_coeffs"]
    if entry["camera_model"] == "pinhole":
        return kb_project(np.array(intr + dist), rays)
    if entry["camera_model"] == "omni":
        return omni_project(np.array(intr + dist), rays)
    if entry["camera_model"] == "eucm":
        return eucm_project(np.array(intr), rays)
    return ds_project(np.array(intr), rays)


@pytest.mark.parametrize("model", ["auto", "pinhole-equi", "omni-radtan", "ds-none", "eucm-none"])
def test_kalibr_camchain_round_trip(model):
    calib = small_rig(3)
    out = kalibr_camchain(calib, model=model, n_samples=3000, source="rig.json")
    doc = yaml.safe_load(out.text)
    assert list(doc) == ["cam0", "cam1", "cam2"]
    assert "T_cn_cnm1" not in doc["cam0"]
    # the chain of T_cn_cnm1 gives back every camera's cam_from_rig (rig = cam0)
    T = np.eye(4)
    for n, cid in enumerate(calib.camera_ids):
        entry = doc[f"cam{n}"]
        assert entry["resolution"] == [W, H]
        if n:
            T = np.array(entry["T_cn_cnm1"]) @ T
        R, t = calib.cam_from_rig[cid]
        assert np.allclose(T[:3, :3], R, atol=1e-12) and np.allclose(T[:3, 3], t, atol=1e-12)
        # the fitted model reprojects points the calibrated camera sees within the
        # printed fit error
        printed = re.findall(r"fit RMS ([\d.]+) px, max ([\d.]+) px", out.text)[n]
        max_px = float(printed[1])
        assert max_px == pytest.approx(out.fits[cid].max_px, abs=1e-4)
        cam = calib.cameras[cid]
        rng = np.random.default_rng(n)
        uv = rng.uniform([0, 0], [W - 1, H - 1], size=(400, 2))
        rays = pixel_rays(cam, uv)
        fit = out.fits[cid]
        ok = np.isfinite(rays).all(1) & fit.in_domain(rays)
        pts = rays[ok] * rng.uniform(0.5, 5.0, size=(ok.sum(), 1))
        err = np.linalg.norm(_fitted_project(entry, pts) - cam.project(pts), axis=1)
        assert ok.sum() > 100
        assert np.max(err) <= max_px + 1e-3, (cid, np.max(err), max_px)
        if model == "auto":
            assert entry["camera_model"] in ("pinhole", "omni", "ds")
        else:
            assert (
                entry["camera_model"]
                == {
                    "pinhole-equi": "pinhole",
                    "omni-radtan": "omni",
                    "ds-none": "ds",
                    "eucm-none": "eucm",
                }[model]
            )


def test_kalibr_translation_in_metres():
    calib = small_rig(2, units="mm")
    calib.cam_from_rig["cam1"] = (np.eye(3), np.array([-120.0, 0.0, 0.0]))
    doc = yaml.safe_load(kalibr_camchain(calib, model="pinhole-equi", n_samples=2000).text)
    assert np.allclose(np.array(doc["cam1"]["T_cn_cnm1"])[:3, 3], [-0.12, 0, 0])


@pytest.mark.parametrize("model, ext", [("fisheye", "yaml"), ("omnidir", "json")])
def test_opencv_stereo_reads_back_with_filestorage(tmp_path, model, ext):
    calib = small_rig(3, radial={})  # equidistant: cv2.fisheye is exact below 90 deg
    out = opencv_stereo(calib, ("cam1", "cam2"), model=model, fmt=ext, n_samples=3000)
    path = tmp_path / f"stereo.{ext}"
    path.write_text(out.text)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("model").string() == model
    assert fs.getNode("camera_1").string() == "cam1"
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat()
    R_ref, t_ref = relative_pose(calib, "cam1", "cam2")
    assert np.allclose(R, R_ref) and np.allclose(T.ravel(), t_ref)
    # p_cam2 = R p_cam1 + T, composed from cam_from_rig
    p_rig = np.array([0.3, -0.2, 2.0])
    R1, t1 = calib.cam_from_rig["cam1"]
    R2, t2 = calib.cam_from_rig["cam2"]
    assert np.allclose(R @ (R1 @ p_rig + t1) + T.ravel(), R2 @ p_rig + t2)
    K1, D1 = fs.getNode("K1").mat(), fs.getNode("D1").mat()
    assert fs.getNode("image_size_1").mat().ravel().tolist() == [W, H]
    cam = calib.cameras["cam1"]
    rays = pixel_rays(cam, np.array([[100.0, 120.0], [400.0, 300.0], [700.0, 500.0]]))
    if model == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(rays[None], np.zeros(3), np.zeros(3), K1, D1)
        uv = uv.reshape(-1, 2)
    else:
        xi = float(fs.getNode("xi1").mat().ravel()[0])
        p = [xi, K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2], *D1.ravel()]
        uv = omni_project(np.array(p), rays)
    assert np.max(np.linalg.norm(uv - cam.project(rays), axis=1)) < 0.05
    assert fs.getNode("fit_rms_px_1").real() == pytest.approx(out.fits["cam1"].rms_px)
    # the error outside the observed region is written next to it
    o = out.fits["cam1"].outside
    assert fs.getNode("fit_outside_max_px_1").real() == pytest.approx(o["max_px"], nan_ok=True)
    assert fs.getNode("fit_inside_to_deg_1").real() == pytest.approx(o["from_deg"])
    assert fs.getNode("fit_valid_to_deg_1").real() == pytest.approx(o["valid_to_deg"])
    assert "outside the observed region" in out.summary()


def test_cli_rig_exports_and_errors_name_the_option(tmp_path, capsys):
    path = small_rig(2).save(tmp_path / "rig.json")
    calib = load_calibration(path)
    assert isinstance(calib, RigCalibration)
    out = tmp_path / "camchain.yaml"
    args = ["export", str(path), "--samples", "2000"]
    assert main([*args, "--to", "kalibr", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "camera cam0: kalibr-" in text and "fit RMS" in text
    assert set(yaml.safe_load(out.read_text())) == {"cam0", "cam1"}
    per_camera = ["--kalibr-model", "omni-radtan", "--kalibr-model", "cam1=ds-none"]
    assert main([*args, "--to", "kalibr", *per_camera, "-o", str(out)]) == 0
    doc = yaml.safe_load(out.read_text())
    assert [doc["cam0"]["camera_model"], doc["cam1"]["camera_model"]] == ["omni", "ds"]
    assert main([*args, "--to", "opencv-stereo", "-o", str(tmp_path / "s.yml")]) == 0
    one = ["--to", "opencv-fisheye", "--camera", "cam1", "-o", str(tmp_path / "f.json")]
    assert main([*args, *one]) == 0
    capsys.readouterr()
    for extra, word in (
        (["--to", "opencv-fisheye", "-o", str(tmp_path / "x.json")], "--camera"),
        (["--to", "opencv-fisheye", "--camera", "camX", "-o", str(tmp_path / "x.json")], "camX"),
        (["--to", "opencv-stereo", "-o", str(tmp_path / "x.txt")], "--output"),
        (["--to", "opencv-stereo", "--stereo-cameras", "cam0,cam9", "-o", "x.yaml"], "cam9"),
        (["--to", "kalibr", "--camera", "cam0", "-o", str(tmp_path / "x.yaml")], "--camera"),
        (["--to", "kalibr", "--kalibr-model", "cam5=ds-none", "-o", "x.yaml"], "cam5"),
        (["--to", "kalibr", "--kalibr-model", "cam1=fov", "-o", "x.yaml"], "'fov'"),
        (["--to", "opencv-stereo", "--kalibr-model", "ds-none", "-o", "x.yaml"], "--kalibr-model"),
        (["--to", "kalibr", "--stereo-model", "fisheye", "-o", "x.yaml"], "--stereo-model"),
    ):
        assert main([*args, *extra]) == 2
        err = capsys.readouterr().err
        assert word in err, err
    assert not (tmp_path / "x.json").exists() and not (tmp_path / "x.yaml").exists()


def test_undistort_one_camera_of_a_rig(tmp_path, capsys):
    calib = small_rig(2)
    rig_path = calib.save(tmp_path / "rig.json")
    one_path = calib.camera_calibration("cam1").save(tmp_path / "cam1.json")
    rng = np.random.default_rng(0)
    image = cv2.resize(rng.integers(0, 255, (H // 8, W // 8), np.uint8), (W, H))
    cv2.imwrite(str(tmp_path / "raw.png"), image)
    common = [str(tmp_path / "raw.png"), "--to", "equirectangular", "--size", "200x100"]
    rig_out, one_out = tmp_path / "rig_eq.png", tmp_path / "one_eq.png"
    assert main(["undistort", str(rig_path), *common, "--camera", "cam1", "-o", str(rig_out)]) == 0
    assert main(["undistort", str(one_path), *common, "-o", str(one_out)]) == 0
    assert np.array_equal(cv2.imread(str(rig_out)), cv2.imread(str(one_out)))
    capsys.readouterr()
    for path, extra, word in (
        (rig_path, [], "--camera"),
        (rig_path, ["--camera", "cam7"], "cam7"),
        (one_path, ["--camera", "cam1"], "single-camera"),
    ):
        assert main(["undistort", str(path), *common, *extra, "-o", str(tmp_path / "x.png")]) == 2
        assert word in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_cam_overlaps_from_shared_targets_in_a_frame():
    calib = small_rig(3)
    calib.image_ids = ["a0", "b0", "c0", "c1"]
    calib.image_camera = ["cam0", "cam1", "cam2", "cam2"]
    calib.image_frame = ["f0", "f0", "f0", None]
    calib.cam_from_world_R = np.repeat(np.eye(3)[None], 4, axis=0)
    calib.cam_from_world_t = np.zeros((4, 3))
    calib.extra = {
        "camera_results": {
            "cam0": {"observations": {"image": ["a0", "a0"], "target": ["T1", "T2"]}},
            "cam1": {"observations": {"image": ["b0"], "target": ["T2"]}},
            # cam2 sees T1 in f0's image? no: only in an unframed image
            "cam2": {"observations": {"image": ["c0", "c1"], "target": ["T9", "T1"]}},
        }
    }
    assert camera_overlaps(calib) == {"cam0": [1], "cam1": [0], "cam2": []}
    doc = yaml.safe_load(kalibr_camchain(calib, model="ds-none", n_samples=1000).text)
    assert [doc[f"cam{k}"]["cam_overlaps"] for k in range(3)] == [[1], [0], []]


def test_rig_targets_refuse_a_single_camera_calibration(tmp_path, capsys):
    path = small_rig(2).camera_calibration("cam0").save(tmp_path / "one.json")
    for target in ("kalibr", "opencv-stereo"):
        out = tmp_path / "x.yaml"
        assert main(["export", str(path), "--to", target, "-o", str(out)]) == 2
        assert "calibration@1" in capsys.readouterr().err and not out.exists()
