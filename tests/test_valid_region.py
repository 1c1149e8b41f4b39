"""The valid region: where a calibration's projection uncertainty is small (issue 13)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import bare_calibration

from gtsam_sphere.analysis.uncertainty import (
    ray_sigma_px,
    uncertainty_map_of,
    valid_region,
    with_valid_region,
)
from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.core.errors import OptionsError
from gtsam_sphere.io.calibration import Calibration, camera_from_dict, camera_to_dict
from gtsam_sphere.simulate.building import fisheye_camera

W, H = 800, 600


def _brown():
    cam = SphereCamera(
        W, H, xp=402.0, yp=297.0, c=330.0, brown={"k1": 0.2, "k2": -0.02, "p1": 5e-4}
    )
    cam.observed_alpha_rad = math.radians(75.0)
    sig = np.array([0.3, 0.25, 0.5, 1e-3, 5e-4, 2e-5])
    corr = np.eye(6)
    corr[2, 3] = corr[3, 2] = 0.6
    corr[3, 4] = corr[4, 3] = -0.8
    return cam, ["xp_px", "yp_px", "c_px", "k1", "k2", "p1"], corr * np.outer(sig, sig)


def _radial():
    cam = fisheye_camera(190.0, size_px=H)
    cam.width = W  # a wider sensor: the image circle is cut at the top and bottom
    cam.xp = 0.5 * (W - 1)
    cam.observed_alpha_rad = math.radians(80.0)
    sig = np.array([0.3, 0.25, 0.4, 2e-3])
    return cam, ["xp_px", "yp_px", "c_px", "g3"], np.diag(sig**2)


def _calibration(kind: str) -> Calibration:
    """A calibration whose observations cover the centre of the image only."""
    cam, names, cov = {"brown": _brown, "radial": _radial}[kind]()
    rng = np.random.default_rng(0)
    uv = rng.uniform([200, 150], [600, 450], size=(300, 2))
    calib = bare_calibration(cam, uv)
    calib.statistics.update(rms_px=0.3, intrinsics_covariance=cov.tolist(), intrinsics_names=names)
    return calib


def _rays(n: int, max_alpha: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.arccos(rng.uniform(math.cos(max_alpha), 1.0, n))
    phi = rng.uniform(0, 2 * math.pi, n)
    return np.column_stack([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])


KINDS = ["brown", "radial"]


@pytest.mark.parametrize("kind", KINDS)
def test_region_shrinks_as_the_threshold_tightens(kind):
    """Measured (observations over the central 400 x 300 px): the Brown camera's region
    reaches 28-31, 47-49 and 70 deg for 0.3, 0.6 and 1.2 px (its field: 77 deg, the
    observed 75 deg plus the margin); the radial fisheye's 37-48, 70-76 and 82 deg
    (its whole field)."""
    calib = _calibration(kind)
    regions = [valid_region(calib, t, n_azimuth=36, n_alpha=30, n_cols=16) for t in (0.3, 0.6, 1.2)]
    for r in regions:
        print(kind, r.max_sigma_px, "px:", np.degrees(r.alpha_max_rad).round(1)[::6], "deg")
    solid = [r.solid_angle_sr() for r in regions]
    assert solid[0] < solid[1] < solid[2], solid
    for tight, loose in zip(regions, regions[1:]):
        assert np.all(tight.alpha_max_rad <= loose.alpha_max_rad + 1e-12)
    # every grid ray inside the region is below the threshold
    for r in regions:
        inside = r.alpha_rad[None, :] <= r.alpha_max_rad[:, None]
        assert np.all(r.sigma_px[inside] <= r.max_sigma_px)
    with pytest.raises(OptionsError):
        valid_region(calib, 0.0)
    with pytest.raises(OptionsError):
        valid_region(calib, 1.0, n_azimuth=2)


@pytest.mark.parametrize("kind", KINDS)
def test_project_is_nan_where_the_uncertainty_is_large(kind):
    calib = _calibration(kind)
    thr = 0.6
    cam = with_valid_region(calib, thr, n_azimuth=36, n_alpha=30, n_cols=16)
    assert calib.camera.valid_region_alpha_rad is None  # the calibration's camera is untouched
    assert len(cam.valid_region_alpha_rad) == 36
    rays = _rays(3000, calib.camera.valid_alpha_rad() - 1e-6)
    names = calib.statistics["intrinsics_names"]
    cov = np.asarray(calib.statistics["intrinsics_covariance"])
    X = uncertainty_map_of(calib, n_cols=16).motion_per_intrinsic
    sigma = ray_sigma_px(calib.camera, rays, cov, names, X)
    plain = calib.camera.project(rays)
    region = cam.project(rays)
    assert np.isfinite(plain).all()  # every ray is within the observed field
    large = sigma > 1.1 * thr  # 10% for the interpolation between the table's samples
    small = sigma < 0.9 * thr
    assert large.sum() > 100 and small.sum() > 100
    assert np.isnan(region[large]).all()
    assert np.isfinite(cam.project(rays[large], valid_only=False)).all()
    # inside the region the pixels are those of the plain camera
    ok = np.isfinite(region).all(1)
    assert np.allclose(region[ok], plain[ok])
    assert np.mean(ok[small]) > 0.95  # a few rays beyond a crossing further in
    assert np.array_equal(cam.valid_mask(rays), ok)
    # pixels: the mask of the image follows the same region
    assert not cam.valid_pixel_mask(plain[large]).any()
    assert cam.valid_pixel_mask(plain[ok]).mean() > 0.99


@pytest.mark.parametrize("kind", KINDS)
def test_no_phantom_observations_with_the_region(kind):
    """Points all around a camera: those the region camera reports as seen (finite pixel
    in the image) are in front of the uncertainty threshold and unproject to their own
    ray; every one of them is also seen by the plain camera."""
    calib = _calibration(kind)
    thr = 0.6
    cam = with_valid_region(calib, thr, n_azimuth=36, n_alpha=30, n_cols=16)
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4000, 3)) * [4.0, 4.0, 4.0]  # all directions, behind too
    uv = cam.project(points)
    seen = np.isfinite(uv).all(1) & cam.valid_pixel_mask(np.nan_to_num(uv, nan=-9.0))
    plain_uv = calib.camera.project(points)
    plain_seen = np.isfinite(plain_uv).all(1)
    assert seen.sum() > 100 and seen.sum() < plain_seen.sum()
    assert not np.any(seen & ~plain_seen)
    rays = points[seen] / np.linalg.norm(points[seen], axis=1, keepdims=True)
    back = cam.unproject(uv[seen])
    assert np.degrees(np.arccos(np.clip(np.sum(back * rays, 1), -1, 1))).max() < 1e-3
    names = calib.statistics["intrinsics_names"]
    cov = np.asarray(calib.statistics["intrinsics_covariance"])
    X = uncertainty_map_of(calib, n_cols=16).motion_per_intrinsic
    assert np.all(ray_sigma_px(calib.camera, rays, cov, names, X) <= 1.1 * thr)
    # no point behind the camera is seen
    assert np.all(points[seen, 2] > 0)


def test_region_round_trips_through_the_calibration_file():
    calib = _calibration("brown")
    cam = with_valid_region(calib, 0.6, n_azimuth=12, n_alpha=20, n_cols=12)
    back = camera_from_dict(camera_to_dict(cam))
    assert back.valid_region_alpha_rad == pytest.approx(cam.valid_region_alpha_rad)
    rays = _rays(500, calib.camera.valid_alpha_rad() - 1e-6)
    assert np.array_equal(np.isnan(back.project(rays)), np.isnan(cam.project(rays)))
    assert "valid_region_alpha_rad" not in camera_to_dict(calib.camera)
    with pytest.raises(OptionsError):
        SphereCamera(W, H, 400.0, 300.0, 300.0, valid_region_alpha_rad=[0.1, 0.2])
    with pytest.raises(OptionsError):
        SphereCamera(W, H, 400.0, 300.0, 300.0, valid_region_alpha_rad=[0.1, 0.2, 4.0, 0.3])
    # the table is interpolated between its azimuths and capped by the valid field
    c = SphereCamera(W, H, 400.0, 300.0, 300.0, valid_region_alpha_rad=[0.2, 0.4, 0.2, 0.4])
    assert c.region_alpha_rad(np.array([0.0, math.pi / 4, -math.pi / 2])) == pytest.approx(
        [0.2, 0.3, 0.4]
    )
