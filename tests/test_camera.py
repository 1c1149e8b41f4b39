"""The camera models' project/unproject over the whole sphere."""

import numpy as np
import pytest

from gtsam_sphere.camera import SphereCamera, radial_g


def _directions(rng, n, max_alpha_deg):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    alpha = np.degrees(np.arccos(d[:, 2]))
    d = d[alpha < max_alpha_deg]
    return np.vstack([d, [[0, 0, 1.0]], [[1.0, 0, 0]], [[0.0, -1, 1e-9]]])


@pytest.mark.parametrize("brown", [{}, {"p1": 2e-4, "p2": -1e-4, "a1": 1e-4}])
def test_radial_round_trip_past_90_degrees(brown):
    radial = {"g3": -0.04, "g5": 0.01}
    cam = SphereCamera(1600, 1200, 801.3, 598.2, 420.0, brown=brown, radial=radial)
    rays = _directions(np.random.default_rng(0), 4000, 175.0)
    uv = cam.project(3.7 * rays)
    back = cam.unproject(uv)
    assert np.isfinite(back).all()
    np.testing.assert_allclose(back, rays, atol=1e-9)


def test_radial_unproject_is_unique_where_sphere_needs_a_hemisphere():
    """A ray at 120 deg: the radial mapping finds it from the pixel alone."""
    ray = np.array([[np.sin(np.radians(120)), 0.0, np.cos(np.radians(120))]])
    radial = SphereCamera(1000, 1000, 500, 500, 300, radial={})
    np.testing.assert_allclose(radial.unproject(radial.project(ray)), ray, atol=1e-12)
    sphere = SphereCamera(1000, 1000, 500, 500, 300)
    uv = sphere.project(ray)
    np.testing.assert_allclose(sphere.unproject(uv, hemisphere=-1), ray, atol=1e-12)
    assert sphere.unproject(uv)[0, 2] > 0  # default: the front half


def test_radial_outside_image_and_fold_are_nan():
    cam = SphereCamera(1000, 1000, 500, 500, 300, radial={"g3": -0.3})
    a_max = cam.max_alpha_rad()
    _, dg, _ = radial_g(np.array([a_max * 0.999, a_max * 1.01]), np.array([-0.3]), True)
    assert dg[0] > 0 and dg[1] <= 0
    g_max = radial_g(np.array([a_max]), np.array([-0.3]))[0]
    uv = np.array([[500 + 300 * g_max * 1.01, 500.0], [500 + 300 * g_max * 0.99, 500.0]])
    rays = cam.unproject(uv)
    assert np.isnan(rays[0]).all() and np.isfinite(rays[1]).all()


@pytest.mark.parametrize("radial", [None, {"g3": 0.02}])
def test_ideal_from_points_matches_pixels(radial):
    cam = SphereCamera(1000, 800, 490, 410, 350, brown={"k1": 0.01, "p1": 1e-4}, radial=radial)
    pts = 2.0 * _directions(np.random.default_rng(1), 300, 85.0)
    ideal, J = cam.ideal_from_points(pts, jacobians=True)
    np.testing.assert_allclose(ideal, cam.ideal_from_pixels(cam.project(pts)), atol=1e-7)
    h = 1e-7
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        num = (cam.ideal_from_points(pts + dp) - cam.ideal_from_points(pts - dp)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, atol=1e-5 * np.abs(num).max())


def test_bad_shapes_name_the_shape():
    cam = SphereCamera(1000, 800, 490, 410, 350, radial={})
    with pytest.raises(ValueError, match=r"\(4,\)"):
        cam.project(np.zeros(4))
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        cam.unproject(np.zeros((3, 3)))
