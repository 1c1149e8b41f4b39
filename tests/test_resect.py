"""Tests of gtsam_sphere.estimation.resect: one image's pose with the calibration held fixed."""

from __future__ import annotations

import numpy as np
import pytest

from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.estimation.resect import resect


def rot(rx, ry, rz):
    """Rotation matrix (3, 3) of a rotation vector (rad)."""
    w = np.array([rx, ry, rz], float)
    th = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(th, 1e-300)
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def board(nx=9, ny=7, square=0.05):
    """Planar grid (nx * ny, 3) in metres, board frame (z = 0)."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    return np.column_stack([i.ravel() * square, j.ravel() * square, np.zeros(i.size)])


RADIAL = SphereCamera(
    width=1280, height=960, xp=645.3, yp=478.1, c=330.0, radial={"g3": -0.04, "g5": 0.01}
)
BROWN = SphereCamera(
    width=1280,
    height=960,
    xp=641.0,
    yp=482.5,
    c=600.0,
    brown={"k1": 0.05, "p1": 1e-3},
)
SPHERE = SphereCamera(width=1280, height=960, xp=640.0, yp=480.0, c=400.0)


def simulate(camera, R, t, xyz, noise_px, seed=0):
    """Noisy pixels (N, 2) of world points (N, 3) seen with ``cam_from_world = R, t``."""
    uv = camera.project(xyz @ R.T + t)
    return uv + np.random.default_rng(seed).normal(0.0, noise_px, uv.shape)


def pose_errors(res, R, t):
    """Rotation error (deg) and translation error (world units)."""
    dR = res.R @ R.T
    sin = np.linalg.norm([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2
    ang = np.degrees(np.arctan2(sin, (np.trace(dR) - 1) / 2))
    return ang, np.linalg.norm(res.t - t)


@pytest.mark.parametrize("camera", [RADIAL, BROWN, SPHERE], ids=["radial", "brown", "sphere"])
def test_known_pose_recovered(camera):
    xyz = board()
    R, t = rot(0.3, -0.25, 0.1), np.array([-0.2, -0.12, 0.45])
    uv = simulate(camera, R, t, xyz, noise_px=0.2)
    res = resect(camera, uv, xyz, np.random.default_rng(1))
    assert res.success and res.status == "ok"
    ang, dt = pose_errors(res, R, t)
    print(f"{camera.mapping}: {ang:.4f} deg, {dt * 1e3:.3f} mm, RMS {res.rms_px:.3f} px")
    assert ang < 0.3 and dt < 1e-3  # 0.2 px noise: about 0.1 deg, 0.1 mm
    assert res.residuals_px.shape == (len(xyz), 2)
    assert res.inlier_mask.all()
    # 0.2 px per coordinate: RMS of the 2-D error about 0.28 px (less the 6 fitted dof)
    assert 0.2 < res.rms_px < 0.35
    np.testing.assert_allclose(res.rms_px, res.rms_px_all)
    # residuals are raw pixels: measured minus camera.project of the returned pose
    pred = camera.project(xyz @ res.R.T + res.t)
    np.testing.assert_allclose(res.residuals_px, uv - pred, atol=1e-9)


def test_noise_free_is_exact():
    xyz = board()
    R, t = rot(-0.2, 0.4, -0.3), np.array([-0.1, -0.2, 0.5])
    uv = simulate(RADIAL, R, t, xyz, noise_px=0.0)
    res = resect(RADIAL, uv, xyz, np.random.default_rng(0))
    ang, dt = pose_errors(res, R, t)
    assert ang < 1e-7 and dt < 1e-9 and res.rms_px < 1e-6


def test_outlier_handled():
    xyz = board()
    R, t = rot(0.1, 0.2, 0.05), np.array([-0.2, -0.15, 0.5])
    uv = simulate(RADIAL, R, t, xyz, noise_px=0.2, seed=3)
    bad = [5, 40]
    clean = resect(RADIAL, uv, xyz, np.random.default_rng(2))
    uv[bad[1]] += [-6.0, 4.0]
    uv[bad[0]] += [25.0, -18.0]
    res = resect(RADIAL, uv, xyz, np.random.default_rng(2))
    assert res.success
    assert not res.inlier_mask[bad].any()
    assert res.inlier_mask.sum() == len(xyz) - len(bad)
    ang, dt = pose_errors(res, R, t)
    assert ang < 0.3 and dt < 1e-3
    # the outliers barely move the pose: Huber weights, then rejected at 5 sigma
    ang, dt = pose_errors(res, clean.R, clean.t)
    assert ang < 0.02 and dt < 5e-5
    assert res.rms_px < 0.35 < res.rms_px_all
    np.testing.assert_allclose(np.linalg.norm(res.residuals_px[bad[0]]), 30.9, atol=0.5)


def wide_view():
    """A board seen edge-on from above its middle: half of it lies past 90 deg (behind)."""
    xyz = board(12, 8, 0.05)
    centre = np.array([0.3, 0.17, 0.12])  # camera 12 cm above the board
    z = np.array([np.cos(0.3), np.sin(0.3), -0.2])  # optical axis nearly along the board
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return xyz, R, -R @ centre


def test_points_past_90_deg_radial():
    xyz, R, t = wide_view()
    inc = np.degrees(np.arccos((xyz @ R.T + t)[:, 2] / np.linalg.norm(xyz @ R.T + t, axis=1)))
    assert (inc > 90).sum() >= 20 and (inc < 90).sum() >= 20 and inc.max() < 170
    uv = simulate(RADIAL, R, t, xyz, noise_px=0.2, seed=5)
    res = resect(RADIAL, uv, xyz, np.random.default_rng(0))
    assert res.success, res.status
    ang, dt = pose_errors(res, R, t)
    print(f"radial, {inc.min():.0f}-{inc.max():.0f} deg: {ang:.4f} deg, {dt * 1e3:.3f} mm")
    assert ang < 0.3 and dt < 1e-3
    assert res.inlier_mask.all()
    np.testing.assert_allclose(res.incidence_deg, inc, atol=0.05)


def test_points_past_90_deg_sphere_hemispheres():
    # the sphere mapping is two-to-one past 90 deg: the resection finds the right half
    xyz, R, t = wide_view()
    uv = simulate(SPHERE, R, t, xyz, noise_px=0.2, seed=6)
    res = resect(SPHERE, uv, xyz, np.random.default_rng(0))
    assert res.success, res.status
    ang, dt = pose_errors(res, R, t)
    assert ang < 0.3 and dt < 1e-3
    assert res.inlier_mask.all()
    assert ((res.incidence_deg > 90) == ((xyz @ R.T + t)[:, 2] < 0)).all()


def test_initial_pose_skips_ransac():
    xyz = board()
    R, t = rot(0.3, -0.25, 0.1), np.array([-0.2, -0.12, 0.45])
    uv = simulate(RADIAL, R, t, xyz, noise_px=0.1)
    res = resect(RADIAL, uv, xyz, initial_pose=(rot(0.32, -0.2, 0.1), t + 0.01))
    ang, dt = pose_errors(res, R, t)
    assert res.success and ang < 0.3 and dt < 1e-3


def test_failure_is_reported_not_raised():
    xyz = board()[:3]
    res = resect(RADIAL, np.zeros((3, 2)) + 600, xyz)
    assert not res.success and "3 usable" in res.status
    assert np.isnan(res.R).all() and res.residuals_px.shape == (3, 2)


@pytest.mark.parametrize(
    "uv_shape, xyz_shape, message",
    [
        ((10, 3), (10, 3), r"uv_px must have shape \(N, 2\), got \(10, 3\)"),
        ((10,), (10, 3), r"uv_px must have shape \(N, 2\), got \(10,\)"),
        ((10, 2), (10, 2), r"xyz_world must have shape \(N, 3\), got \(10, 2\)"),
        ((10, 2), (9, 3), r"\(10, 2\) and \(9, 3\)"),
    ],
)
def test_bad_shapes_raise(uv_shape, xyz_shape, message):
    with pytest.raises(ValueError, match=message):
        resect(RADIAL, np.zeros(uv_shape), np.ones(xyz_shape))


def test_sigma_is_in_raw_pixels_under_a_strong_affinity():
    """The resection weighs as the adjustment (``measurement_metric``): with ``a1 = 0.5``
    the corrected coordinates halve x, and a sigma taken there is ~27 % low (0.36 px
    for 0.5 px of noise, mean of these 8 draws before the metric)."""
    camera = SphereCamera(
        width=1280,
        height=960,
        xp=645.3,
        yp=478.1,
        c=330.0,
        radial={"g3": -0.04},
        brown={"a1": 0.5, "p2": 0.01},
    )
    R, t = rot(0.1, -0.2, 0.05), np.array([-0.3, -0.25, 0.6])
    xyz = board(20, 15, 0.035)
    sigma, ang, dt = [], [], []
    for seed in range(8):
        res = resect(camera, simulate(camera, R, t, xyz, 0.5, seed=seed), xyz)
        assert res.success
        sigma.append(res.sigma_px)
        a, d = pose_errors(res, R, t)
        ang.append(a)
        dt.append(d)
    assert np.mean(sigma) == pytest.approx(0.5, rel=0.05)
    assert np.sqrt(np.mean(np.square(ang))) < 0.1  # deg
    assert np.sqrt(np.mean(np.square(dt))) < 1e-3  # m
