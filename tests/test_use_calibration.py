"""Exports, remap tables and the uncertainty map on cameras with known answers."""

import cv2
import numpy as np

from gtsam_sphere.analysis.uncertainty import uncertainty_map
from gtsam_sphere.apps.export import export_camera
from gtsam_sphere.apps.undistort import apply_remap, remap_tables
from gtsam_sphere.core.camera import SphereCamera


def _equidistant():
    # an equidistant fisheye is Kannala-Brandt with k1..k4 = 0: the export must be exact
    return SphereCamera(1280, 960, 641.3, 478.9, 600.0, radial={})  # corners at 76 deg


def test_equidistant_exports_to_opencv_fisheye_exactly_and_cv2_agrees():
    cam = _equidistant()
    res = export_camera(cam, "opencv-fisheye", n_samples=4000)
    assert res.rms_px < 1e-3 and res.coverage > 0.99
    K = np.array(
        [
            [res.params["fx"], 0, res.params["cx"]],
            [0, res.params["fy"], res.params["cy"]],
            [0, 0, 1.0],
        ]
    )
    D = np.array([res.params[k] for k in ("k1", "k2", "k3", "k4")])
    rng = np.random.default_rng(0)
    rays = rng.normal(size=(500, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 0.3
    uv_cv, _ = cv2.fisheye.projectPoints(rays[None], np.zeros(3), np.zeros(3), K, D)
    uv = cam.project(rays)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 1279) & (uv[:, 1] > 0) & (uv[:, 1] < 959)
    assert np.abs(uv_cv[0][inside] - uv[inside]).max() < 1e-2


def test_a_lens_past_180_degrees_is_not_silently_exported_to_opencv():
    cam = SphereCamera(1000, 1000, 499.5, 499.5, 230.0, radial={})  # 1000 px circle ~250 deg
    res = export_camera(cam, "opencv-fisheye", n_samples=4000)
    assert res.coverage < 0.95  # rays past 90 deg are left out and reported
    ds = export_camera(cam, "kalibr-ds", n_samples=4000)
    assert ds.coverage > res.coverage


def test_equirectangular_remap_pixel_round_trips():
    cam = _equidistant()
    tables = remap_tables(cam, "equirectangular", fov_deg=180.0, size=(360, 180), step=1)
    h, w = tables.map_x.shape
    r, c = h // 3, w // 4
    uv = np.array([[tables.map_x[r, c], tables.map_y[r, c]]], float)
    ray = cam.unproject(uv)[0]
    lon = np.degrees(np.arctan2(ray[0], ray[2]))
    assert abs(lon - (-90.0 + 180.0 * (c + 0.5) / w)) < 0.6  # within one output pixel
    image = np.zeros((960, 1280), np.uint8)
    image[int(round(uv[0, 1])), int(round(uv[0, 0]))] = 255
    out = apply_remap(image, tables)
    assert out.shape == (h, w) and out.max() > 0


def test_uncertainty_map_is_zero_without_covariance_and_grows_with_it():
    cam = _equidistant()
    names = ["xp_px", "yp_px", "c_px"]
    zero = uncertainty_map(cam, np.zeros((3, 3)), names, n_cols=12)
    assert np.nanmax(zero.sigma_px) == 0.0
    small = uncertainty_map(cam, np.diag([0.01, 0.01, 0.01]), names, n_cols=12)
    large = uncertainty_map(cam, np.diag([1.0, 1.0, 1.0]), names, n_cols=12)
    np.testing.assert_allclose(
        np.nanmedian(large.sigma_px), 10 * np.nanmedian(small.sigma_px), rtol=1e-6
    )
    # the principal point's sigma alone moves every pixel by sqrt(0.01 + 0.01)
    assert np.nanmin(small.sigma_px) >= np.sqrt(0.02) - 1e-9
