"""``compare CALIB --with camchain.yaml`` (issue 15, item 5): Kalibr cameras read back."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import bare_calibration
from test_export import equidistant_like, observed_pixels

from gtsam_sphere.apps.export import export_camera, write_export
from gtsam_sphere.apps.kalibr_compare import compare_with_kalibr, read_kalibr_camchain
from gtsam_sphere.cli import main
from gtsam_sphere.core.errors import DatasetError, OptionsError


@pytest.fixture(scope="module")
def cam():
    return equidistant_like()


@pytest.fixture(scope="module")
def obs75(cam):
    return observed_pixels(cam, 75.0)


@pytest.mark.parametrize(
    "target, model",
    [
        ("kalibr-equi", "pinhole-equi"),
        ("kalibr-ds", "ds-none"),
        ("kalibr-omni", "omni-radtan"),
        ("kalibr-eucm", "eucm-none"),
    ],
)
def test_export_then_compare_gives_the_fit_error(cam, obs75, tmp_path, target, model):
    result = export_camera(cam, target, obs75, n_samples=3000)
    path = write_export(result, tmp_path / "camchain.yaml")
    cams = read_kalibr_camchain(str(path))
    assert list(cams) == ["cam0"] and cams["cam0"].model == model
    assert cams["cam0"].resolution == (cam.width, cam.height)
    cmp = compare_with_kalibr(bare_calibration(cam, obs75), cams["cam0"], n_samples=3000)
    print(f"{target}: export RMS {result.rms_px:.4f} px; read back {cmp.summary()}")
    # the same grid over the same region: the round trip gives the export's fit error
    assert cmp.field_stats["n_projected"] == cmp.field_stats["n"]
    assert cmp.field_stats["rms_px"] == pytest.approx(result.rms_px, rel=0.05, abs=1e-3)
    assert cmp.observed["rms_px"] <= 2 * result.max_px + 1e-3
    yaml = pytest.importorskip("yaml")  # the reader agrees with a YAML parser
    doc = yaml.safe_load(path.read_text())["cam0"]
    np.testing.assert_allclose(cams["cam0"].intrinsics, doc["intrinsics"])
    np.testing.assert_allclose(cams["cam0"].distortion, doc["distortion_coeffs"])


def test_a_different_camera_shows_its_difference(cam, obs75, tmp_path):
    result = export_camera(cam, "kalibr-equi", obs75, n_samples=3000)
    path = write_export(result, tmp_path / "camchain.yaml")
    text = path.read_text()
    cx = repr(float(result.K[0, 2]))
    path.write_text(text.replace(cx, repr(float(result.K[0, 2]) + 2.0), 1))
    cmp = compare_with_kalibr(bare_calibration(cam, obs75), read_kalibr_camchain(str(path))["cam0"])
    assert cmp.field_stats["rms_px"] == pytest.approx(2.0, abs=0.05)  # a 2 px shift of pu


def test_rig_camchain_with_transforms_parses(tmp_path):
    text = """cam0:
  camera_model: ds
  intrinsics: [-0.2, 0.6, 300.0, 300.5, 320.0, 240.0]
  distortion_model: none
  distortion_coeffs: []
  resolution: [640, 480]
  cam_overlaps: [1]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
  - [1.0, 0.0, 0.0, -0.1]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: omni
  intrinsics: [1.1, 700.0, 700.0, 320.0, 240.0]
  distortion_model: radtan
  distortion_coeffs: [-0.1, 0.01, 0.0, 0.0]
  resolution: [640, 480]
  rostopic: '/cam1/image_raw'
"""
    path = tmp_path / "camchain.yaml"
    path.write_text(text)
    cams = read_kalibr_camchain(str(path))
    assert [c.model for c in cams.values()] == ["ds-none", "omni-radtan"]
    assert cams["cam1"].rostopic == "/cam1/image_raw"
    uv = cams["cam0"].project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(uv[0], [320.0, 240.0])
    assert np.all(np.isnan(uv[1]))  # straight back: outside the double sphere's field


@pytest.mark.parametrize(
    "change, error, part",
    [
        (("equidistant", "radtan"), OptionsError, "pinhole-radtan"),
        (("resolution: [1200, 900]", "resolution: [1200]"), DatasetError, "resolution"),
        (("camera_model: pinhole", "camera_model: pinhole\n  camera_model2: x"), None, None),
    ],
)
def test_camchain_errors_name_the_item(cam, obs75, tmp_path, change, error, part):
    result = export_camera(cam, "kalibr-equi", obs75, n_samples=500)
    path = write_export(result, tmp_path / "camchain.yaml")
    path.write_text(path.read_text().replace(*change))
    if error is None:
        assert read_kalibr_camchain(str(path))["cam0"].model == "pinhole-equi"
        return
    with pytest.raises(error, match=part):
        read_kalibr_camchain(str(path))


def test_cli_compare_with(cam, obs75, tmp_path, capsys):
    calib_path = bare_calibration(cam, obs75).save(tmp_path / "calib.json")
    result = export_camera(cam, "kalibr-ds", obs75, n_samples=2000)
    chain = write_export(result, tmp_path / "camchain.yaml")
    assert main(["compare", str(calib_path), "--with", str(chain)]) == 0
    out = capsys.readouterr().out
    assert "Kalibr cam0 (ds-none)" in out and "field:" in out and "60-90 deg" in out
    assert main(["compare", str(calib_path), "--with", str(chain), "--camera", "cam3"]) == 2
    assert "cam3" in capsys.readouterr().err
    assert main(["compare", str(calib_path)]) == 2  # neither --checkpoints nor --with
