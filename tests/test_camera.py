"""The camera models' project/unproject over the whole sphere."""

import numpy as np
import pytest

from gtsam_sphere.core.camera import BROWN_TERMS, SphereCamera, radial_g, sphere_residual


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


@pytest.mark.parametrize("w", [-1.2, 0.7, 1.4])
def test_warped_radial_round_trip_to_175_degrees(w):
    """The warp (a field that grows like tan, or squeezes its rim like the FOV model):
    pixel -> ray -> pixel over the whole sphere, and its series at the optical axis."""
    cam = SphereCamera(1600, 1200, 801.3, 598.2, 420.0, radial={"w": w, "g3": 0.01})
    rays = _directions(np.random.default_rng(3), 4000, 175.0)
    uv = cam.project(3.7 * rays)
    np.testing.assert_allclose(cam.unproject(uv), rays, atol=1e-9)
    assert cam.max_alpha_rad() == pytest.approx(np.pi)
    # either side of the series branch at the axis (alpha < 1e-4) agrees with g itself
    x = np.array([1e-6, 0.99e-4, 1.01e-4, 1e-3])
    near = np.column_stack([x, np.zeros(4), np.ones(4)])
    g = radial_g(np.arctan(x), np.array([0.01]), warp=w)
    np.testing.assert_allclose(cam.ideal_from_points(near)[:, 0] / 420.0, g, rtol=1e-9)


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


# -- the sphere mapping with Brown terms on a lens past 180 degrees ----------------------------


class SmoothCorrection:
    """A smooth learned correction (px), Lipschitz constant 0.01 px/px."""

    def predict(self, uv_px):
        uv = np.asarray(uv_px, float)
        return np.column_stack([0.8 * np.sin(uv[:, 1] / 90.0), -0.6 * np.cos(uv[:, 0] / 70.0)])


def brown_210(p1=4e-6, p2=-3e-6, a1=2e-5, a2=1e-5, correction=None):
    """A sphere + Brown camera standing for a 210 deg equidistant lens (image radius 330 alpha).

    ``c`` and ``k1-k3`` are what the adjustment fits to that lens without noise: the
    residual ``r - brown(r) - c sin(alpha)`` is linear in them (least squares up to
    105 deg). The small decentering and affinity terms stand for noise-level values
    of a real fit; they tilt the fold's ideal radius around ``c`` (the 90 deg gap).
    """
    width, height, f = 1600, 1200, 330.0
    s = 0.5 * max(width, height)
    alpha = np.linspace(0.0, np.radians(105.0), 400)
    r = f * alpha
    u = r / s
    A = np.column_stack([np.sin(alpha), r * u**2, r * u**4, r * u**6])
    c, k1, k2, k3 = np.linalg.lstsq(A, r, rcond=None)[0]
    brown = {"k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2, "a1": a1, "a2": a2}
    return SphereCamera(
        width, height, 802.5, 597.0, c, brown=brown, brown_scale_px=s, correction=correction
    )


def _theta(cam):
    names = tuple(t for t in BROWN_TERMS if t in cam.brown)
    theta = np.array([cam.xp, cam.yp, cam.c] + [cam.brown[t] for t in names])
    return theta, names


def _observed_pixels(cam, max_deg=105.0, step=6.0):
    """A pixel grid over the image within ``max_deg`` of the axis (equidistant radius)."""
    gu, gv = np.meshgrid(np.arange(0.0, cam.width, step), np.arange(0.0, cam.height, step))
    uv = np.column_stack([gu.ravel(), gv.ravel()]) + 0.25
    r = np.linalg.norm(uv - cam.principal_point_px, axis=1)
    return uv[r < 330.0 * np.radians(max_deg)]


@pytest.mark.parametrize("correction", [None, SmoothCorrection()])
def test_brown_past_180_pixel_ray_pixel_round_trip(correction):
    """Every pixel of a 210 deg image, on either side of the fold, comes back from its ray.

    Before the fix ``project`` put the rays behind the camera on the front-side pixel
    (173 px off on this camera) and the rays in the 90 deg gap got wrong pixels.
    """
    cam = brown_210(correction=correction)
    uv = _observed_pixels(cam)
    hemisphere = cam.pixel_hemisphere(uv)
    rays = cam.unproject(uv, hemisphere=hemisphere)
    has_ray = np.all(np.isfinite(rays), axis=1)
    # no ray only where the corrected point leaves the sphere's disc, a band at the fold
    outside = np.linalg.norm(cam.ideal_from_pixels(uv), axis=1) > cam.c * (1 + 1e-12)
    np.testing.assert_array_equal(~has_ray, outside)
    assert np.mean(outside) < 0.01
    uv, rays, hemisphere = uv[has_ray], rays[has_ray], hemisphere[has_ray]
    back = rays[:, 2] < 0
    np.testing.assert_array_equal(back, hemisphere < 0)
    assert back.sum() > 5000 and (~back).sum() > 5000
    incidence = np.degrees(np.arccos(rays[:, 2]))
    assert incidence.max() > 104.0
    points = rays * np.linspace(0.1, 50.0, len(rays))[:, None]
    projected = cam.project(points)
    err = np.linalg.norm(projected - uv, axis=1)
    assert np.all(err < 1e-6), (err.max(), incidence[np.argmax(err)])
    assert np.median(err) < 1e-9
    # the projection satisfies the adjustment's residual: exactly with the correction
    # itself (exact=True), and with the correction's table on the default path
    theta, names = _theta(cam)
    for exact in (True, False):
        projected = cam.project(points, exact=exact)
        if correction is None:
            corrected = projected
        elif exact:
            corrected = projected - correction.predict(projected)
        else:
            corrected = projected - cam.correction_table().predict(projected)
        e = sphere_residual(theta, names, cam.brown_scale_px, corrected, points)
        assert np.abs(e).max() < 1e-9
        assert np.abs(cam.pixel_residuals(projected, e, exact=exact)).max() < 1e-6


def test_brown_past_180_ray_pixel_ray_and_the_sides_of_the_fold():
    cam = brown_210()
    rays = _directions(np.random.default_rng(3), 6000, 105.0)
    uv = cam.project(rays)
    profile = cam.fold_profile(np.arctan2(rays[:, 1], rays[:, 0]))
    sin_alpha = np.hypot(rays[:, 0], rays[:, 1])
    in_gap = sin_alpha > profile["ideal_max"] * (1 - 1e-12)
    # NaN exactly for the rays in the 90 deg gap (none of these directions is on the axis)
    np.testing.assert_array_equal(np.isnan(uv).any(axis=1), in_gap)
    ok = ~in_gap
    assert in_gap.sum() < 0.01 * len(rays)
    radius = np.linalg.norm(uv[ok] - cam.principal_point_px, axis=1)
    fold = cam.fold_profile(np.arctan2(*(uv[ok] - cam.principal_point_px)[:, ::-1].T))
    back = rays[ok, 2] < 0
    assert np.all((radius > fold["radius_px"]) == back)  # behind the camera: beyond the fold
    np.testing.assert_array_equal(cam.pixel_hemisphere(uv[ok]), np.where(back, -1.0, 1.0))
    again = cam.unproject(uv[ok], hemisphere=cam.pixel_hemisphere(uv[ok]))
    # the sphere mapping's slope vanishes at 90 deg: the ray of a pixel rounded to 1e-13 px
    # is good to 1e-13 / (c |cos(alpha)|) rad
    lever = 1.0 / np.maximum(np.abs(rays[ok, 2]), 1e-6)
    assert np.all(np.linalg.norm(again - rays[ok], axis=1) <= 1e-11 * lever)
    np.testing.assert_allclose(cam.ideal_from_pixels(uv[ok]), cam.c * rays[ok, :2], atol=1e-9)


def test_brown_past_180_gap_and_jump_at_90_degrees():
    """The fold's ideal radius is not tied to ``c``: a gap of rays or a band of pixels."""
    cam = brown_210()
    phi = np.radians(np.arange(0.0, 360.0, 1.0))
    profile = cam.fold_profile(phi)
    assert np.all(np.abs(profile["radius_px"] - 330.0 * np.pi / 2) < 10.0)  # 90 deg
    assert profile["ideal_max"].min() < 1 < profile["ideal_max"].max()
    # an azimuth with a gap: the rays within gap_deg of 90 deg have no pixel
    i = int(np.argmin(profile["ideal_max"]))
    gap = profile["gap_deg"][i]
    assert 0.2 < gap < 2.0 and profile["no_ray_px"][i] == 0
    alpha = np.radians(90.0 + np.array([-1.02, -0.98, 0.0, 0.98, 1.02]) * gap)
    rays = np.column_stack(
        [np.sin(alpha) * np.cos(phi[i]), np.sin(alpha) * np.sin(phi[i]), np.cos(alpha)]
    )
    uv = cam.project(rays)
    np.testing.assert_array_equal(np.isnan(uv).any(axis=1), [False, True, True, True, False])
    # an azimuth without a gap: project jumps over no_ray_px of pixels that have no ray
    j = int(np.argmax(profile["ideal_max"]))
    assert profile["gap_deg"][j] == 0 and profile["no_ray_px"][j] > 0.5
    alpha = np.radians([90.0 - 1e-7, 90.0, 90.0 + 1e-7])
    rays = np.column_stack(
        [np.sin(alpha) * np.cos(phi[j]), np.sin(alpha) * np.sin(phi[j]), np.cos(alpha)]
    )
    uv = cam.project(rays)
    r = np.linalg.norm(uv - cam.principal_point_px, axis=1)
    assert abs(r[1] - r[0]) < 1e-3  # exactly 90 deg counts as the front
    assert abs((r[2] - r[0]) - profile["no_ray_px"][j]) < 0.05
    between = cam.principal_point_px + np.linspace(r[0] + 0.05, r[2] - 0.05, 9)[:, None] * [
        np.cos(phi[j]),
        np.sin(phi[j]),
    ]
    assert np.isnan(cam.unproject(between, hemisphere=cam.pixel_hemisphere(between))).all()


def test_brown_back_rays_without_a_fold_share_the_mirror_pixel():
    """Brown terms that fold nowhere keep the sphere's two-to-one, as without Brown terms."""
    cam = SphereCamera(1000, 800, 490, 410, 350, brown={"k1": -0.02, "a1": 1e-3})
    ray = np.array([[np.sin(np.radians(120)), 0.3, np.cos(np.radians(120))]])
    mirror = ray * [1, 1, -1]
    np.testing.assert_allclose(cam.project(ray), cam.project(mirror), atol=1e-9)
    assert cam.pixel_hemisphere(cam.project(ray))[0] == 1.0
    np.testing.assert_allclose(
        cam.unproject(cam.project(ray), hemisphere=-1), ray / np.linalg.norm(ray), atol=1e-12
    )
    # the antipode of the axis: the mirror of the principal point without a fold, NaN with one
    np.testing.assert_allclose(cam.project([0.0, 0.0, -2.0]), [[490.0, 410.0]], atol=1e-12)
    assert np.isnan(brown_210().project([0.0, 0.0, -2.0])).all()


def test_brown_narrow_lens_puts_rays_behind_it_outside_the_image():
    """A compressing k1 folds far outside a narrow image: rays behind land beyond the fold."""
    cam = SphereCamera(1200, 1000, 601.0, 498.0, 450.0, brown={"k1": 0.01, "p1": 1e-4})
    rays = _directions(np.random.default_rng(5), 500, 150.0)[:-2]  # not at 90 deg
    uv = cam.project(rays)
    assert np.isfinite(uv).all()
    back = rays[:, 2] < 0
    radius = np.linalg.norm(uv - cam.principal_point_px, axis=1)
    assert radius[back].min() > 3000 and radius[~back].max() < 1000
    again = cam.unproject(uv, hemisphere=cam.pixel_hemisphere(uv))
    np.testing.assert_allclose(again, rays, atol=1e-9)


@pytest.mark.parametrize("radial", [None, ("g3", "g5")])
def test_sphere_residual_jacobians_with_strong_decentering_and_affinity(radial):
    """Decentering and affinity are undone in the residual (``A^-1 e``): the extra
    derivative terms against central differences, far from zero (p1 0.01, p2 -0.02,
    a1 0.3, a2 -0.1)."""
    rng = np.random.default_rng(11)
    names = ("p1", "p2", "a1", "a2")
    g = [] if radial is None else [-0.05, 0.01]
    theta = np.array([640.0, 400.0, 350.0, *g, 0.01, -0.02, 0.3, -0.1])
    uv = rng.uniform(100.0, 1200.0, (20, 2))
    pc = rng.normal(size=(20, 3)) + [0.0, 0.0, 2.0]
    e, J_theta, J_pc = sphere_residual(theta, names, 500.0, uv, pc, True, radial_names=radial)
    np.testing.assert_allclose(e, sphere_residual(theta, names, 500.0, uv, pc, radial_names=radial))
    h = 1e-6
    for k in range(len(theta)):
        d = np.zeros_like(theta)
        d[k] = h * max(1.0, abs(theta[k]))
        num = (
            sphere_residual(theta + d, names, 500.0, uv, pc, radial_names=radial)
            - sphere_residual(theta - d, names, 500.0, uv, pc, radial_names=radial)
        ) / (2 * d[k])
        np.testing.assert_allclose(J_theta[:, :, k], num, rtol=1e-5, atol=1e-5, err_msg=str(k))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        num = (
            sphere_residual(theta, names, 500.0, uv, pc + d, radial_names=radial)
            - sphere_residual(theta, names, 500.0, uv, pc - d, radial_names=radial)
        ) / (2 * h)
        np.testing.assert_allclose(J_pc[:, :, k], num, rtol=1e-5, atol=1e-5)
    # the corrected-coordinate residual mapped by A^-1; with a1, a2 alone (a linear
    # map) x is scaled by 1 / (1 - a1) and y is untouched
    from gtsam_sphere.core.camera import brown_distortion, decentering_affinity_matrix

    n_g = len(g)
    e0 = sphere_residual(theta[: 3 + n_g], (), 500.0, uv, pc, radial_names=radial)  # xbar - c m
    xbar = uv - theta[:2]
    coeffs = dict(zip(names, theta[3 + n_g :]))
    corrected = e0 - brown_distortion(xbar, coeffs, 500.0)
    A = decentering_affinity_matrix(xbar, coeffs, 500.0)
    np.testing.assert_allclose(e, np.linalg.solve(A, corrected[..., None])[..., 0], rtol=1e-12)
    aff = {"a1": 0.3, "a2": -0.1}
    theta_aff = np.concatenate([theta[: 3 + n_g], [0.3, -0.1]])
    e_aff = sphere_residual(theta_aff, ("a1", "a2"), 500.0, uv, pc, radial_names=radial)
    corrected = e0 - brown_distortion(xbar, aff, 500.0)
    np.testing.assert_allclose(e_aff[:, 1], corrected[:, 1], rtol=1e-12)
    np.testing.assert_allclose(e_aff[:, 0], (corrected[:, 0] - 0.1 * corrected[:, 1]) / 0.7)


class _Smooth:
    """A smooth learned correction (px) for the metric test."""

    def predict(self, uv_px):
        uv = np.asarray(uv_px, float)
        return np.column_stack([0.6 * np.sin(uv[:, 1] / 170.0), 0.4 * np.cos(uv[:, 0] / 230.0)])


def test_measurement_metric_reproduces_the_adjustments_residual():
    """``M (ideal_from_pixels(uv) - ideal(P))`` (the frozen factors' and resection's
    residual) equals the adjustment's :func:`sphere_residual` on the learned-corrected
    pixels; None without decentering and affinity terms, NaN where ``A`` is singular."""
    rng = np.random.default_rng(5)
    cam = SphereCamera(
        width=1280,
        height=960,
        xp=652.0,
        yp=471.0,
        c=340.0,
        brown={"k1": 0.02, "p1": 0.01, "p2": -0.02, "a1": 0.3, "a2": -0.1},
    )
    cam.correction = _Smooth()
    uv = rng.uniform(50.0, 1230.0, (40, 2))
    pc = rng.normal(size=(40, 3)) + [0.0, 0.0, 2.0]
    theta, names = _theta(cam)
    corrected = uv - cam.correction.predict(uv)
    expected = sphere_residual(theta, names, cam.brown_scale_px, corrected, pc)
    M = cam.measurement_metric(uv, exact=True)
    assert M.shape == (40, 2, 2)
    e = cam.ideal_from_pixels(uv, exact=True) - cam.ideal_from_points(pc)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", M, e), expected, rtol=1e-10, atol=1e-10)
    assert (
        SphereCamera(
            width=100, height=100, xp=50, yp=50, c=40.0, brown={"k1": 0.1}
        ).measurement_metric(uv)
        is None
    )
    folded = SphereCamera(width=100, height=100, xp=50, yp=50, c=40.0, brown={"a1": 1.0})
    assert np.isnan(folded.measurement_metric(uv)).all()


def test_inside_image_is_the_sensor_s_outer_edges():
    """Pixel centres run 0..width-1, so the edges are -0.5 and width - 0.5 (inclusive);
    NaN is outside."""
    cam = SphereCamera(640, 480, 319.5, 239.5, 300.0)
    uv = np.array(
        [[-0.5, -0.5], [639.5, 479.5], [-0.51, 10.0], [10.0, 479.51], [np.nan, 5.0], [320, 240]]
    )
    assert cam.inside_image(uv).tolist() == [True, True, False, False, False, True]
