"""Re-resection of images left at a wrong pose (estimation.calibrate.repair_poses) and the
second ray a folding lens images at a pixel (estimation.calibrate.folded_rays).

Found on ``bench_lens_zoo.py --stress 40 --seed 3301 --targets --defects --shapes`` s34:
a 321 deg sphere lens (its image folds at 90 deg) whose four images kept poses 7-9 m off
with every ray within 47 deg; the repair posed them on the front rays alone and never
found them, and the calibration was not trusted (198 of 861 observations beyond 5
sigma)."""

from __future__ import annotations

import numpy as np
import pytest

from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.estimation.calibrate import folded_rays


def _rays(alpha_deg, phi_deg):
    a, p = np.radians(alpha_deg), np.radians(phi_deg)
    return np.stack([np.sin(a) * np.cos(p), np.sin(a) * np.sin(p), np.cos(a)], axis=-1)


def test_the_sphere_mapping_images_a_second_ray_mirrored_about_90_deg():
    cam = SphereCamera(width=2000, height=2000, xp=1000.0, yp=990.0, c=800.0)
    alpha = np.array([20.0, 60.0, 85.0, 110.0, 150.0])
    phi = np.array([0.0, 45.0, 170.0, -90.0, -30.0])
    P = _rays(alpha, phi)
    uv = cam.project(P, valid_only=False)
    front = cam.unproject(uv)
    back = folded_rays(cam, uv, front, tolerance_px=1.0)
    got = np.degrees(np.arccos(np.clip(back[:, 2], -1, 1)))
    expected = 180.0 - np.degrees(np.arccos(np.clip(front[:, 2], -1, 1)))
    # within the search step, on the same azimuth
    np.testing.assert_allclose(got, expected, atol=0.3)
    np.testing.assert_allclose(
        np.arctan2(back[:, 1], back[:, 0]), np.arctan2(front[:, 1], front[:, 0]), atol=1e-9
    )
    # the true ray is the front or the other one
    best = np.maximum(np.sum(front * P, 1), np.sum(back * P, 1))
    assert np.all(np.degrees(np.arccos(np.clip(best, -1, 1))) < 0.3)


def test_a_lens_that_does_not_fold_has_no_second_ray():
    cam = SphereCamera(
        width=2000,
        height=2000,
        xp=1000.0,
        yp=1000.0,
        c=600.0,
        radial={},  # equidistant
    )
    P = _rays(np.array([10.0, 80.0, 120.0]), np.array([0.0, 90.0, 200.0]))
    uv = cam.project(P, valid_only=False)
    back = folded_rays(cam, uv, cam.unproject(uv), tolerance_px=1.0)
    assert np.isnan(back).all()


def test_no_pixels_no_rays():
    cam = SphereCamera(width=100, height=100, xp=50.0, yp=50.0, c=40.0)
    assert folded_rays(cam, np.zeros((0, 2)), np.zeros((0, 3)), 1.0).shape == (0, 3)


@pytest.mark.slow  # 861 observations, ~10 s
def test_images_posed_on_the_wrong_side_of_a_fold_are_repaired():
    """Stress 3301 s34 end to end: the four images are re-resected with both rays of
    each pixel competing, and the calibration is trusted with the lens and the
    stations right."""
    from helpers import stress_case

    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    case = stress_case(3301, "s34-")
    assert case.id.startswith("s34-sphere-321-room-1920x1080")
    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    repaired = [ln for ln in lines if "re-resected" in ln]
    assert {ln.split()[1].rstrip(":") for ln in repaired} >= {
        "IMG_0004",
        "IMG_0005",
        "IMG_0010",
        "IMG_0012",
    }
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    truth = {im["id"]: np.asarray(im["centre_world"]) for im in sim.truth["images"]}
    R, t = calib.cam_from_world_R, calib.cam_from_world_t
    centres = -np.einsum("kji,kj->ki", R, t)
    expected = np.array([truth[i] for i in calib.image_ids])
    assert np.max(np.linalg.norm(centres - expected, axis=1)) < 0.01  # metres
    assert calib.camera.c == pytest.approx(sim.lens.f, rel=0.02)
