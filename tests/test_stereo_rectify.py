"""Stereo rectification of a rig's pair (undistort --stereo): rows are epipolar planes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_export_rig import H, W, small_rig

from gtsam_sphere.apps.undistort import (
    output_pixels,
    output_rays,
    rectified_pixels,
    stereo_rectification,
    stereo_remap_tables,
)
from gtsam_sphere.cli import main
from gtsam_sphere.core.errors import OptionsError


def _in_camera(calib, cid, p_rig):
    R, t = calib.cam_from_rig[cid]
    return p_rig @ np.asarray(R).T + np.asarray(t)


def test_rectifying_rotations_put_the_baseline_on_x():
    calib = small_rig(2)
    rect = stereo_rectification(calib, "cam0", "cam1")
    for Rm in (rect.rect_from_left, rect.rect_from_right):
        np.testing.assert_allclose(Rm @ Rm.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(Rm) == pytest.approx(1.0)
    R, t = calib.cam_from_rig["cam1"]
    centre_rig = -np.asarray(R).T @ np.asarray(t)  # cam0 is the rig frame
    c = rect.rect_from_left @ centre_rig
    assert c[0] == pytest.approx(rect.baseline) and abs(c[1]) < 1e-12 and abs(c[2]) < 1e-12
    assert rect.baseline == pytest.approx(np.linalg.norm(centre_rig))
    # one world direction seen from both cameras: the same rectified direction
    d_rig = np.array([0.3, -0.2, 1.0])
    d_right = np.asarray(R) @ d_rig
    np.testing.assert_allclose(
        rect.rect_from_right @ d_right, rect.rect_from_left @ d_rig, atol=1e-12
    )


@pytest.mark.parametrize("kind", ["perspective", "equirectangular", "epipolar", "cylindrical"])
def test_output_pixels_invert_output_rays(kind):
    size, fov = (320, 200), (100.0 if kind == "perspective" else 170.0)
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], size, (500, 2))
    back = output_pixels(kind, size, fov, output_rays(kind, size, fov, uv))
    np.testing.assert_allclose(back, uv, atol=1e-8)


@pytest.mark.parametrize("kind", ["epipolar", "perspective"])
def test_corresponding_points_share_a_row(kind):
    """Points seen by both cameras land on the same row of the two rectified images,
    including (epipolar) rays past 90 deg from the optical axes."""
    calib = small_rig(2, radial={})  # equidistant fisheyes, c = 260 px: 180 deg and more
    rect, lt, rt = stereo_remap_tables(calib, "cam0", "cam1", kind, size=(400, 300))
    rng = np.random.default_rng(3)
    p_rig = rng.normal(size=(4000, 3)) * rng.uniform(1.0, 8.0, (4000, 1))
    uv = {c: calib.cameras[c].project(_in_camera(calib, c, p_rig)) for c in ("cam0", "cam1")}
    inside = np.ones(len(p_rig), bool)
    for c in uv:
        u, v = uv[c].T
        inside &= np.isfinite(u) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    left = rectified_pixels(calib.cameras["cam0"], rect.rect_from_left, lt, uv["cam0"][inside])
    right = rectified_pixels(calib.cameras["cam1"], rect.rect_from_right, rt, uv["cam1"][inside])
    ok = np.isfinite(left).all(1) & np.isfinite(right).all(1)
    assert ok.sum() > 200
    np.testing.assert_allclose(left[ok, 1], right[ok, 1], atol=1e-6)
    if kind == "epipolar":  # the whole field: rays beyond 90 deg of an optical axis too
        a = np.degrees(
            np.arccos(
                _in_camera(calib, "cam0", p_rig)[inside][:, 2]
                / np.linalg.norm(p_rig[inside], axis=1)
            )
        )
        assert (a[ok] > 95.0).sum() > 10


def test_cli_writes_both_rectified_images_and_names_bad_options(tmp_path, capsys):
    calib = small_rig(2)
    rig = calib.save(tmp_path / "rig.json")
    rng = np.random.default_rng(0)
    for name in ("l.png", "r.png"):
        cv2.imwrite(
            str(tmp_path / name),
            cv2.resize(rng.integers(0, 255, (H // 8, W // 8), np.uint8), (W, H)),
        )
    args = [
        "undistort",
        str(rig),
        str(tmp_path / "l.png"),
        "--stereo",
        str(tmp_path / "r.png"),
        "--to",
        "equirectangular",
        "--size",
        "240x160",
    ]
    assert (
        main([*args, "-o", str(tmp_path / "lo.png"), "--stereo-output", str(tmp_path / "ro.png")])
        == 0
    )
    out = capsys.readouterr().out
    assert "epipolar" in out and "baseline" in out
    assert cv2.imread(str(tmp_path / "lo.png")).shape[:2] == (160, 240)
    assert cv2.imread(str(tmp_path / "ro.png")).shape[:2] == (160, 240)
    # errors name the bad item and write nothing
    assert main([*args, "-o", str(tmp_path / "x.png")]) == 2
    assert "--stereo-output" in capsys.readouterr().err
    assert (
        main(
            [
                *args,
                "-o",
                str(tmp_path / "x.png"),
                "--stereo-output",
                str(tmp_path / "y.png"),
                "--stereo-camera",
                "cam9",
            ]
        )
        == 2
    )
    assert "cam9" in capsys.readouterr().err
    one = calib.camera_calibration("cam0").save(tmp_path / "one.json")
    assert (
        main(
            [
                "undistort",
                str(one),
                *args[2:],
                "-o",
                str(tmp_path / "x.png"),
                "--stereo-output",
                str(tmp_path / "y.png"),
            ]
        )
        == 2
    )
    assert "calibration@2" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()
    with pytest.raises(OptionsError, match="twice"):
        stereo_rectification(calib, "cam0", "cam0")
