"""Remap tables to perspective / equirectangular / cylindrical images (apps.undistort)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from helpers import bare_calibration

from gtsam_sphere import SphereCamera
from gtsam_sphere.apps.export import incidence_deg, pixel_rays
from gtsam_sphere.apps.undistort import (
    INVALID,
    KINDS,
    apply_remap,
    default_geometry,
    output_rays,
    remap_tables,
)
from gtsam_sphere.cli import main

W, H, C = 400, 300, 130.0


def equidistant_like(width=W, height=H, c=C) -> SphereCamera:
    """Sphere + Brown camera with image radius ~ ``c * alpha``; sees past 90 deg in the corners."""
    s = 0.5 * max(width, height)
    brown = {"k1": s**2 / (6 * c**2), "k2": -(s**4) / (120 * c**4), "k3": s**6 / (5040 * c**6)}
    return SphereCamera(width, height, width / 2 - 0.5 + 1.5, height / 2 - 0.5 - 1.0, c, brown, s)


@pytest.fixture(scope="module")
def cam():
    return equidistant_like()


def _angle(a, b):
    a = a / np.linalg.norm(a, axis=1)[:, None]
    b = b / np.linalg.norm(b, axis=1)[:, None]
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


@pytest.mark.parametrize("kind", KINDS)
def test_a_pixels_ray_round_trips(cam, kind):
    # the epipolar grid's columns span at most 180 deg (its rows go around the baseline)
    fov = {"perspective": 100.0, "epipolar": 170.0}.get(kind, 220.0)
    t = remap_tables(cam, kind, fov_deg=fov, size=(180, 120), step=1)
    assert t.map_x.dtype == np.float32 and t.map_x.shape == (120, 180)
    assert t.size == (180, 120) and t.step == 1
    valid = t.valid
    assert 0.3 < valid.mean() <= 1.0
    v, u = np.nonzero(valid)
    out_rays = output_rays(kind, t.size, fov, np.column_stack([u, v]).astype(float))
    src = np.column_stack([t.map_x[v, u], t.map_y[v, u]]).astype(float)
    # output pixel -> ray -> input pixel -> the camera's ray of that pixel: the same ray
    ang = _angle(pixel_rays(cam, src), out_rays)
    assert np.median(ang) < 1e-6
    assert ang.max() < 0.06 / C + 2e-5  # round-trip tolerance plus float32 rounding
    # and the invalid output pixels are exactly those whose ray the camera does not see
    assert np.all(t.map_x[~valid] == INVALID)
    if kind == "perspective":
        uvh = np.column_stack([u, v, np.ones(len(u))])
        assert np.allclose(_angle(uvh @ np.linalg.inv(t.K).T, out_rays), 0, atol=1e-9)


def test_equirectangular_keeps_the_field_past_180_degrees(cam):
    t = remap_tables(cam, "equirectangular", size=(240, 120), step=1)
    fov, _ = default_geometry(cam, "equirectangular")
    assert t.fov_deg == pytest.approx(fov) and fov > 180
    v, u = np.nonzero(t.valid)
    inc = incidence_deg(output_rays("equirectangular", t.size, t.fov_deg, np.column_stack([u, v])))
    assert inc.max() > 100  # rays behind the camera are in the output
    # every corner of the input image is somewhere in the output
    src = np.column_stack([t.map_x[v, u], t.map_y[v, u]])
    for corner in ([0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]):
        assert np.min(np.linalg.norm(src - corner, axis=1)) < 6.0


def test_apply_remap_samples_the_input_at_the_table(cam):
    t = remap_tables(cam, "cylindrical", fov_deg=200.0, size=(160, 100), step=1)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
    img = np.dstack([uu, vv]).astype(np.float32)  # each pixel holds its own coordinates
    # (cv2.remap resolves positions to 1/32 px)
    out = apply_remap(img, t, border_value=(-7.0, -7.0, 0.0, 0.0))
    inner = t.valid & (t.map_x >= 0) & (t.map_x <= W - 1) & (t.map_y >= 0) & (t.map_y <= H - 1)
    assert np.allclose(out[..., 0][inner], t.map_x[inner], atol=1 / 32)
    assert np.allclose(out[..., 1][inner], t.map_y[inner], atol=1 / 32)
    assert np.all(out[..., 0][~t.valid] == -7.0)
    # uint8 images keep their dtype and channels
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 1] = 200
    res = apply_remap(rgb, t)
    assert res.dtype == np.uint8 and res.shape == (100, 160, 3)
    assert np.all(res[..., 1][t.valid & inner] == 200) and np.all(res[~t.valid] == 0)


def test_interpolated_tables_match_the_exact_ones(cam):
    exact = remap_tables(cam, "equirectangular", fov_deg=200.0, size=(200, 140), step=1)
    fast = remap_tables(cam, "equirectangular", fov_deg=200.0, size=(200, 140), step=4)
    assert fast.step == 4
    both = exact.valid & fast.valid
    assert np.array_equal(exact.valid, fast.valid)
    d = np.hypot(exact.map_x - fast.map_x, exact.map_y - fast.map_y)[both]
    assert d.max() < 0.05
    assert fast.interpolation_error_px <= d.max() + 1e-6


def test_cli(cam, tmp_path, capsys):
    calib = bare_calibration(cam).save(tmp_path / "calib.json")
    img_path = tmp_path / "raw.png"
    img = np.zeros((H, W, 3), np.uint8)
    img[::20] = 255
    cv2.imwrite(str(img_path), img)
    out = tmp_path / "pano.png"
    args = ["undistort", str(calib), str(img_path), "--to", "equirectangular"]
    assert main([*args, "--size", "120x80", "-o", str(out)]) == 0
    assert "has a source pixel" in capsys.readouterr().out
    res = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert res.shape == (80, 120, 3) and res.max() == 255
    assert not list(tmp_path.glob(".*tmp*"))
    # bad input: missing image, wrong size, bad --size, missing calibration
    assert main([*args[:2], str(tmp_path / "none.png"), *args[3:], "-o", str(out)]) == 2
    assert "none.png" in capsys.readouterr().err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), img[:100, :100])
    assert main([*args[:2], str(small), *args[3:], "-o", str(out)]) == 2
    assert "100x100" in capsys.readouterr().err
    assert main([*args, "--size", "12by8", "-o", str(out)]) == 2
    assert main(["undistort", str(tmp_path / "c.json"), str(img_path), "--to", "perspective",
                 "-o", str(out)]) == 2  # fmt: skip
