"""Exports to other tools' files (issue 15): ROS CameraInfo YAML, mrcal .cameramodel, basalt
calibration.json (gtsam_sphere.apps.export_formats), the splined stereographic model."""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
import yaml
from helpers import bare_calibration
from test_export import equidistant_like, observed_pixels
from test_export_rig import small_rig

from gtsam_sphere import SphereCamera
from gtsam_sphere.apps.export import eucm_project, pixel_rays, sample_region
from gtsam_sphere.apps.export_formats import (
    basalt_calibration,
    basalt_project,
    mrcal_cameramodels,
    read_cameramodel,
    ros_camera_infos,
)
from gtsam_sphere.apps.export_rig import relative_pose
from gtsam_sphere.apps.kalibr_compare import compare_with_kalibr
from gtsam_sphere.apps.splined import SplineConfig, splined_project
from gtsam_sphere.cli import main
from gtsam_sphere.core.errors import DatasetError, OptionsError

#: the keys (and matrix shapes) camera_calibration_parsers writes for a CameraInfo
ROS_KEYS = {
    "image_width",
    "image_height",
    "camera_name",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "rectification_matrix",
    "projection_matrix",
}
ROS_SHAPES = {"camera_matrix": (3, 3), "rectification_matrix": (3, 3), "projection_matrix": (3, 4)}
N_SAMPLES = 3000


@pytest.fixture(scope="module")
def calib75():
    cam = equidistant_like()
    return bare_calibration(cam, observed_pixels(cam, 75.0))


@pytest.fixture(scope="module")
def wide():
    """A 200-deg-field camera (rays past 90 deg): only splined / ds / eucm cover it."""
    return SphereCamera(800, 640, 401.5, 318.5, 255.0, radial={"g3": -0.03})


def _matrix(entry) -> np.ndarray:
    return np.asarray(entry["data"], float).reshape(entry["rows"], entry["cols"])


def _field(calib):
    obs = calib.extra["observations"]["uv_px"]
    s = sample_region(calib.camera, obs, "hull", N_SAMPLES)
    return s.rays, s.uv_px


# --------------------------------------------------------------------------- ROS


@pytest.mark.parametrize("model", ["equidistant", "rational_polynomial", "plumb_bob"])
def test_ros_camera_info_projects_like_the_calibration(calib75, model):
    out = ros_camera_infos(calib75, model, n_samples=N_SAMPLES)
    fit = out.fits["cam0"]
    doc = yaml.safe_load(out.files[""])
    assert set(doc) == ROS_KEYS and doc["distortion_model"] == model
    assert (doc["image_width"], doc["image_height"]) == (1200, 900)
    for key, shape in ROS_SHAPES.items():
        assert (doc[key]["rows"], doc[key]["cols"]) == shape
        assert len(doc[key]["data"]) == shape[0] * shape[1]
    n_d = {"equidistant": 4, "plumb_bob": 5, "rational_polynomial": 8}[model]
    D = doc["distortion_coefficients"]
    assert (D["rows"], D["cols"], len(D["data"])) == (1, n_d, n_d)
    K = _matrix(doc["camera_matrix"])
    np.testing.assert_allclose(_matrix(doc["projection_matrix"])[:, :3], K)
    np.testing.assert_allclose(_matrix(doc["rectification_matrix"]), np.eye(3))
    rays, uv = _field(calib75)
    ok = fit.in_domain(rays)
    obj = np.ascontiguousarray(rays[ok][None], np.float64)
    dist = np.asarray(D["data"], float)
    if model == "equidistant":  # project with the written numbers through OpenCV itself
        got, _ = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
    else:
        got, _ = cv2.projectPoints(obj[0], np.zeros(3), np.zeros(3), K, dist)
    err = np.linalg.norm(got.reshape(-1, 2) - uv[ok], axis=1)
    print(f"ROS {model}: fit RMS {fit.rms_px:.4f} max {fit.max_px:.4f} px; cv2 re-projection "
          f"RMS {np.sqrt(np.mean(err**2)):.4f} max {err.max():.4f} px")  # fmt: skip
    assert err.max() <= fit.max_px + 1e-6  # within the stated fit error
    text = out.files[""]
    assert "inside the observed region" in text and "outside it" in text  # states both


def test_ros_auto_picks_the_model_covering_the_field(calib75, wide):
    out = ros_camera_infos(calib75, n_samples=N_SAMPLES)
    assert out.models["cam0"] in ("equidistant", "rational_polynomial")
    assert out.fits["cam0"].coverage == 1.0 and out.fits["cam0"].rms_px < 0.01
    # past 90 deg no ROS model covers the field: equidistant covers the most, and says so
    out = ros_camera_infos(bare_calibration(wide), n_samples=N_SAMPLES)
    assert out.models["cam0"] == "equidistant" and out.fits["cam0"].coverage < 1.0
    assert "excluded" in out.files[""]
    with pytest.raises(OptionsError, match="--ros-model 'fov'"):
        ros_camera_infos(calib75, "fov")


def test_ros_rig_one_file_per_camera(tmp_path, capsys):
    path = small_rig(2).save(tmp_path / "rig.json")
    out = tmp_path / "camera_info.yaml"
    args = ["export", str(path), "--to", "ros", "--samples", "1500", "-o", str(out)]
    assert main([*args, "--ros-model", "equidistant"]) in (0, 1)  # > 180 deg: partly covered
    assert "camera cam1: equidistant" in capsys.readouterr().out
    for cid in ("cam0", "cam1"):
        doc = yaml.safe_load((tmp_path / f"camera_info-{cid}.yaml").read_text())
        assert set(doc) == ROS_KEYS and doc["camera_name"] == cid
    assert not out.exists()


# --------------------------------------------------------------------------- splined model


def test_splined_jacobian_and_eucm_jacobian_match_finite_differences():
    rng = np.random.default_rng(3)
    rays = rng.normal(size=(30, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 0.2
    cfg = SplineConfig(6, 5, 160)
    p = np.concatenate([[300.0, 310.0, 400.0, 300.0], 0.01 * rng.normal(size=2 * 30)])
    for fn, params in (
        (lambda q, r, jacobians=False: splined_project(q, r, cfg, jacobians), p),
        (eucm_project, np.array([0.6, 1.1, 300.0, 310.0, 400.0, 300.0])),
    ):
        _, J = fn(params, rays, jacobians=True)
        for k in range(len(params)):
            d = np.zeros(len(params))
            d[k] = 1e-6 * max(1.0, abs(params[k]))
            num = (fn(params + d, rays) - fn(params - d, rays)) / (2 * d[k])
            np.testing.assert_allclose(J[:, :, k], num, atol=1e-5, rtol=1e-5)


def test_spline_config_round_trips_the_model_string():
    cfg = SplineConfig.parse("LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=194")
    assert (cfg.Nx, cfg.Ny, cfg.fov_x_deg, cfg.n_params) == (16, 12, 194, 4 + 2 * 16 * 12)
    assert SplineConfig.parse(cfg.lensmodel) == cfg
    kx, ky = cfg.knots()
    assert kx[1] == pytest.approx(-cfg.u_edge_x) and kx[-2] == pytest.approx(cfg.u_edge_x)
    assert ky[-2] == pytest.approx(cfg.u_edge_y)
    with pytest.raises(ValueError, match="order=2"):
        SplineConfig(8, 6, 120, order=2)
    with pytest.raises(ValueError, match="not LENSMODEL_SPLINED"):
        SplineConfig.parse("LENSMODEL_SPLINED_STEREOGRAPHIC_Nx=3")


# --------------------------------------------------------------------------- mrcal


@pytest.mark.parametrize("model, lens", [("auto", "LENSMODEL_OPENCV8"), ("splined", "SPLINED")])
def test_mrcal_round_trip(calib75, tmp_path, model, lens):
    out = mrcal_cameramodels(calib75, model, n_samples=N_SAMPLES)
    fit = out.fits["cam0"]
    assert lens in out.models["cam0"]
    doc = ast.literal_eval(out.files[""])  # the format's grammar: a Python dict literal
    assert set(doc) == {"lensmodel", "intrinsics", "valid_intrinsics_region", "extrinsics",
                        "imagersize"}  # fmt: skip
    assert doc["imagersize"] == [1200, 900] and doc["extrinsics"] == [0.0] * 6
    region = np.asarray(doc["valid_intrinsics_region"])
    assert region.shape[1] == 2 and np.allclose(region[0], region[-1])  # closed
    path = tmp_path / "cam.cameramodel"
    path.write_text(out.files[""])
    back = read_cameramodel(path)
    assert back.model == doc["lensmodel"] and back.resolution == (1200, 900)
    rays, uv = _field(calib75)
    err = np.linalg.norm(back.project(rays) - uv, axis=1)
    print(f"mrcal {back.model}: fit RMS {fit.rms_px:.4f} max {fit.max_px:.4f} px; read back "
          f"RMS {np.sqrt(np.mean(err**2)):.4f} max {err.max():.4f} px")  # fmt: skip
    assert err.max() <= fit.max_px + 1e-6 and fit.max_px < 0.1
    cmp = compare_with_kalibr(calib75, back, n_samples=N_SAMPLES)
    assert cmp.field_stats["rms_px"] == pytest.approx(fit.rms_px, rel=0.05, abs=1e-4)
    assert "mrcal" in cmp.summary()


def test_mrcal_splined_covers_a_field_past_180_degrees(wide):
    out = mrcal_cameramodels(bare_calibration(wide), n_samples=N_SAMPLES)
    fit = out.fits["cam0"]
    assert "SPLINED" in out.models["cam0"] and fit.coverage == 1.0
    assert fit.max_incidence_deg_region > 95.0
    print(f"splined over {fit.max_incidence_deg_region:.1f} deg: {fit.spline.lensmodel}, "
          f"RMS {fit.rms_px:.4f} px, max {fit.max_px:.4f} px")  # fmt: skip
    assert fit.rms_px < 0.1
    assert "valid_intrinsics_region" not in ast.literal_eval(out.files[""])  # no observations


def test_mrcal_rig_files_carry_rt_cam_ref_from_camera_0(tmp_path, capsys):
    rig = small_rig(3)
    out = mrcal_cameramodels(rig, "opencv8", n_samples=1500, max_incidence_deg=60.0)
    assert set(out.files) == {"cam0", "cam1", "cam2"}
    for cid, text in out.files.items():
        rt = np.asarray(ast.literal_eval(text)["extrinsics"])
        R, t = relative_pose(rig, "cam0", cid)
        np.testing.assert_allclose(cv2.Rodrigues(rt[:3])[0], R, atol=1e-12)
        np.testing.assert_allclose(rt[3:], t, atol=1e-12)
    path = rig.save(tmp_path / "rig.json")
    args = ["export", str(path), "--to", "mrcal", "--samples", "1500"]
    opencv8 = ["--mrcal-model", "opencv8", "-o", str(tmp_path / "m.cameramodel")]
    assert main([*args, *opencv8]) in (0, 1)
    assert sorted(p.name for p in tmp_path.glob("*.cameramodel")) == [
        "m-cam0.cameramodel", "m-cam1.cameramodel", "m-cam2.cameramodel"]  # fmt: skip
    capsys.readouterr()
    assert main(["compare", str(path), "--with", str(tmp_path / "m-cam1.cameramodel"),
                 "--camera", "cam1"]) == 0  # fmt: skip
    assert "mrcal m-cam1.cameramodel" in capsys.readouterr().out


def test_cameramodel_errors_name_the_item(tmp_path):
    path = tmp_path / "x.cameramodel"
    for text, error, word in (
        ("{'lensmodel': 'LENSMODEL_CAHVORE_linearity=0.00', 'intrinsics': [1], "
         "'imagersize': [2, 2]}", OptionsError, "CAHVORE"),
        ("{'lensmodel': 'LENSMODEL_OPENCV8', 'intrinsics': [1, 2], 'imagersize': [2, 2]}",
         DatasetError, "12 finite intrinsics"),
        ("{'lensmodel': 'LENSMODEL_OPENCV8', 'intrinsics': 'abc', 'imagersize': [2, 2]}",
         DatasetError, "'intrinsics' is not a list"),
        ("{'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [1] * 8}", DatasetError, "dict literal"),
        ("{'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [1, 1, 1, 1, 0, 0, 0, 0]}",
         DatasetError, "'imagersize'"),
    ):  # fmt: skip
        path.write_text(text)
        with pytest.raises(error, match=word):
            read_cameramodel(path)


_MRCAL_CHECK = r"""
import json, sys
import numpy as np
import mrcal
m = mrcal.cameramodel(sys.argv[1])
rays = np.array(json.loads(sys.argv[2]))
lensmodel, intrinsics = m.intrinsics()
print(json.dumps({"lensmodel": lensmodel, "imagersize": [int(v) for v in m.imagersize()],
                  "rt": m.extrinsics_rt_fromref().tolist(),
                  "uv": mrcal.project(rays, lensmodel, intrinsics).tolist()}))
"""


def _system_mrcal() -> str:
    """The system python3 with Debian's python3-mrcal, or skip."""
    exe = shutil.which("python3", path="/usr/bin")
    if exe is None or exe == sys.executable:
        pytest.skip("no system python3")
    probe = subprocess.run([exe, "-c", "import mrcal"], capture_output=True)
    if probe.returncode:
        pytest.skip("python3-mrcal is not installed (apt-get install python3-mrcal)")
    return exe


@pytest.mark.parametrize("which", ["opencv8", "splined", "wide", "rig"])
def test_mrcal_itself_loads_and_projects_our_file(calib75, wide, tmp_path, which):
    exe = _system_mrcal()
    if which == "rig":
        rig = small_rig(2)
        out = mrcal_cameramodels(rig, "splined", camera="cam1", n_samples=1500)
    elif which == "wide":
        out = mrcal_cameramodels(bare_calibration(wide), "splined", n_samples=N_SAMPLES)
    else:
        out = mrcal_cameramodels(calib75, which, n_samples=N_SAMPLES)
    fit = next(iter(out.fits.values()))
    path = tmp_path / "ours.cameramodel"
    path.write_text(next(iter(out.files.values())))
    rng = np.random.default_rng(0)
    uv_img = rng.uniform([0, 0], [fit.width - 1, fit.height - 1], size=(400, 2))
    cam = {"wide": wide, "rig": small_rig(2).cameras["cam1"]}.get(which, calib75.camera)
    rays = pixel_rays(cam, uv_img)
    rays = rays[np.all(np.isfinite(rays), axis=1) & fit.in_domain(rays)]
    res = subprocess.run([exe, "-c", _MRCAL_CHECK, str(path), json.dumps(rays.tolist())],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout)
    assert got["lensmodel"] == out.models[next(iter(out.fits))]
    assert got["imagersize"] == [fit.width, fit.height]
    ours = fit.project(rays, use_cv2=False)
    diff = np.linalg.norm(np.asarray(got["uv"]) - ours, axis=1)
    print(f"mrcal {got['lensmodel']}: {len(rays)} rays, |mrcal - ours| max {diff.max():.2e} px")
    assert diff.max() < 1e-6
    if which == "rig":
        R, t = relative_pose(rig, "cam0", "cam1")
        np.testing.assert_allclose(cv2.Rodrigues(np.asarray(got["rt"][:3]))[0], R, atol=1e-9)


# --------------------------------------------------------------------------- basalt


@pytest.mark.parametrize("model", ["kb4", "ds", "eucm"])
def test_basalt_round_trip_through_the_model_formulas(calib75, model):
    out = basalt_calibration(calib75, model, n_samples=N_SAMPLES)
    doc = json.loads(out.files[""])["value0"]
    assert doc["T_imu_cam"] == [{"px": 0.0, "py": 0.0, "pz": 0.0, "qx": 0.0, "qy": 0.0,
                                 "qz": 0.0, "qw": 1.0}]  # fmt: skip
    assert doc["resolution"] == [[1200, 900]] and len(doc["calib_gyro_bias"]) == 12
    entry = doc["intrinsics"][0]
    assert entry["camera_type"] == model
    fit = out.fits["cam0"]
    rays, uv = _field(calib75)
    err = np.linalg.norm(basalt_project(entry, rays) - uv, axis=1)
    print(f"basalt {model}: fit RMS {fit.rms_px:.4f} max {fit.max_px:.4f}; formulas RMS "
          f"{np.sqrt(np.nanmean(err**2)):.4f} max {np.nanmax(err):.4f} px")  # fmt: skip
    assert np.all(np.isfinite(err)) and err.max() <= fit.max_px + 1e-9


def test_basalt_rig_one_file_with_every_camera(tmp_path, capsys):
    rig = small_rig(3)
    out = basalt_calibration(rig, n_samples=1500)
    doc = json.loads(out.files[""])["value0"]
    assert len(doc["T_imu_cam"]) == len(doc["intrinsics"]) == len(doc["resolution"]) == 3
    for k, cid in enumerate(rig.camera_ids):
        pose = doc["T_imu_cam"][k]
        q = np.array([pose["qx"], pose["qy"], pose["qz"], pose["qw"]])
        x, y, z, w = q
        R_imu_cam = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])  # fmt: skip
        R, t = rig.cam_from_rig[cid]  # T_imu_cam = inverse(cam_from_rig), the rig frame as IMU
        np.testing.assert_allclose(R_imu_cam, R.T, atol=1e-12)
        np.testing.assert_allclose([pose["px"], pose["py"], pose["pz"]], -R.T @ t, atol=1e-12)
        assert doc["intrinsics"][k]["camera_type"] == out.models[cid]
    path = rig.save(tmp_path / "rig.json")
    assert main(["export", str(path), "--to", "basalt", "--basalt-model", "ds", "--samples",
                 "1500", "-o", str(tmp_path / "calibration.json")]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "camera cam2: ds" in text and "inside the observed region" in text
    doc = json.loads((tmp_path / "calibration.json").read_text())["value0"]
    assert {e["camera_type"] for e in doc["intrinsics"]} == {"ds"}


# --------------------------------------------------------------------------- CLI


def test_cli_formats_and_options(calib75, tmp_path, capsys):
    path = calib75.save(tmp_path / "calib.json")
    args = ["export", str(path), "--samples", "2000"]
    assert main([*args, "--to", "ros", "-o", str(tmp_path / "camera.yaml")]) == 0
    assert set(yaml.safe_load((tmp_path / "camera.yaml").read_text())) == ROS_KEYS
    assert main([*args, "--to", "mrcal", "-o", str(tmp_path / "cam.cameramodel")]) == 0
    assert "LENSMODEL_OPENCV8" in capsys.readouterr().out
    assert main(["compare", str(path), "--with", str(tmp_path / "cam.cameramodel")]) == 0
    assert "mrcal cam.cameramodel (LENSMODEL_OPENCV8)" in capsys.readouterr().out
    for extra, word in (
        (["--to", "ros", "--mrcal-model", "splined"], "--mrcal-model"),
        (["--to", "basalt", "--ros-model", "plumb_bob"], "--ros-model"),
        (["--to", "mrcal", "--camera", "cam0"], "single-camera"),
    ):
        assert main([*args, *extra, "-o", str(tmp_path / "x.out")]) == 2
        assert word in capsys.readouterr().err
    assert not (tmp_path / "x.out").exists()
