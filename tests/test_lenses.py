"""Tests of the simulator's lens families (gtsam_sphere.simulate.lenses)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gtsam_sphere.simulate.lenses import (
    LENS_KINDS,
    DoubleSphere,
    ErrorField,
    FieldOfView,
    NonCentral,
    PinholeBrown,
    SphereLens,
    incidence_angle,
    lens_from_dict,
    make_lens,
)

W, H = 4000, 3000

# (kind, fov_deg, options): every family, with distortion where it has some
CASES = [
    ("pinhole", 75.0, {"k1": -0.1, "k2": 0.05, "k3": 0.01, "p1": 1e-3, "p2": -5e-4}),
    ("pinhole", 150.0, {"a1": 1e-4, "a2": -2e-4}),
    ("equidistant", 150.0, {}),
    ("equidistant", 250.0, {"p1": 2e-4, "p2": -1e-4, "a1": 3e-4}),
    ("equisolid", 180.0, {}),
    ("equisolid", 300.0, {"p2": 1e-4}),
    ("stereographic", 200.0, {}),
    ("sphere", 120.0, {"p1": 1e-4, "a2": 1e-4}),
    ("sphere", 300.0, {}),
    ("kannala-brandt", 150.0, {"k1": 0.03, "k2": -0.008, "k3": 0.001, "p1": 2e-4}),
    ("kannala-brandt", 220.0, {"k1": -0.01, "k2": 0.001}),
    ("unified", 160.0, {"xi": 0.8, "k1": -0.05, "k2": 0.01, "p1": 1e-4, "p2": 1e-4}),
    ("unified", 250.0, {"xi": 1.6}),
    ("double-sphere", 150.0, {"xi": -0.2, "alpha": 0.6, "p1": 2e-4, "a1": 1e-4}),
    ("double-sphere", 240.0, {}),
    ("double-sphere", 330.0, {"xi": 0.1, "alpha": 0.5}),
    ("double-sphere", 170.0, {"xi": 0.3, "alpha": 0.3}),
    ("fov", 100.0, {"omega": 1.0, "p2": 1e-4}),
    ("fov", 170.0, {"omega": 0.5}),
    ("fov", 300.0, {"omega": 2.2, "a2": 1e-4}),
]


def _without_decentering(opts: dict) -> dict:
    return {k: v for k, v in opts.items() if k not in ("p1", "p2", "a1", "a2")}


def _directions(alpha: np.ndarray, seed: int = 0) -> np.ndarray:
    phi = np.random.default_rng(seed).uniform(-math.pi, math.pi, alpha.size)
    return np.stack(
        [np.sin(alpha) * np.cos(phi), np.sin(alpha) * np.sin(phi), np.cos(alpha)], axis=1
    )


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


def _test_angles(lens) -> np.ndarray:
    amax = math.radians(lens.max_incidence_deg)
    special = [0.0, min(amax, math.pi / 2), 0.98 * amax]
    grid = np.linspace(0.0, 0.98 * amax, 400)
    return np.concatenate([special, grid])


@pytest.mark.parametrize(("kind", "fov", "opts"), CASES)
def test_round_trip(kind, fov, opts):
    lens = make_lens(kind, fov, W, H, **opts)
    alpha = _test_angles(lens)
    rays = _directions(alpha)
    uv = lens.project(3.7 * rays)
    assert np.isfinite(uv).all()
    if isinstance(lens, SphereLens):
        back = lens.unproject(uv, hemisphere=np.where(rays[:, 2] < 0, -1, 1))
    else:
        back = lens.unproject(uv)
    assert np.allclose(np.linalg.norm(back, axis=1), 1.0)
    assert _angle(back, rays).max() < 1e-9
    # and the other way round: pixels -> rays -> pixels (relative: the unified lens
    # with xi < 1 sends its valid range far outside the image)
    scale = np.maximum(1.0, np.abs(uv - [lens.cx, lens.cy]).max(axis=1))
    assert (np.abs(lens.project(back) - uv).max(axis=1) / scale).max() < 1e-9


@pytest.mark.parametrize(("kind", "fov", "opts"), CASES)
def test_fov_on_border(kind, fov, opts):
    lens = make_lens(kind, fov, W, H, **opts)
    half = math.radians(fov / 2)
    if kind == "sphere" and fov > 180:
        # disc radius is f at 90 degrees, the back hemisphere folds inside it
        assert lens.f == pytest.approx(0.98 * min(W, H) / 2)
        assert lens.max_incidence_deg == pytest.approx(fov / 2)
        return
    radius = min(W, H) / 2 if fov >= 180 else math.hypot(W, H) / 2
    # along the axis where decentering/affinity vanish for the ideal lens
    ideal = make_lens(kind, fov, W, H, **_without_decentering(opts))
    uv = ideal.project(_directions(np.array([half, half]), seed=3))
    r = np.hypot(uv[:, 0] - ideal.cx, uv[:, 1] - ideal.cy)
    assert r == pytest.approx([radius, radius], rel=1e-9)


def test_optical_axis_maps_to_principal_point():
    for kind in LENS_KINDS:
        lens = make_lens(kind, 120.0, W, H)
        uv = lens.project([[0.0, 0.0, 2.0]])
        assert uv[0] == pytest.approx([(W - 1) / 2, (H - 1) / 2])
        assert lens.unproject(uv)[0] == pytest.approx([0.0, 0.0, 1.0])


def test_axes_conventions():
    lens = make_lens("equidistant", 180.0, W, H)
    uv = lens.project([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    assert uv[0, 0] > lens.cx and uv[0, 1] == pytest.approx(lens.cy)  # x right -> u right
    assert uv[1, 1] > lens.cy and uv[1, 0] == pytest.approx(lens.cx)  # y down -> v down


def test_pinhole_matches_opencv():
    lens = make_lens("pinhole", 75, W, H, k1=-0.1, k2=0.05, k3=0.01, p1=1e-3, p2=-5e-4)
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3)) + [0, 0, 3]
    k = np.array([[lens.f, 0, lens.cx], [0, lens.f, lens.cy], [0, 0, 1]])
    dist = np.array([lens.k1, lens.k2, lens.p1, lens.p2, lens.k3])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, dist)
    assert np.abs(lens.project(pts) - ref[:, 0]).max() < 1e-8


def test_kannala_brandt_matches_opencv_fisheye():
    lens = make_lens("kannala-brandt", 150, W, H, k1=0.03, k2=-0.008, k3=0.001, k4=1e-4)
    pts = np.random.default_rng(1).uniform(-2, 2, (50, 3)) + [0, 0, 1]
    pts = pts[pts[:, 2] > 0.2]
    k = np.array([[lens.f, 0, lens.cx], [0, lens.f, lens.cy], [0, 0, 1]])
    dist = np.array([lens.k1, lens.k2, lens.k3, lens.k4])
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), k, dist)
    assert np.abs(lens.project(pts) - ref[:, 0]).max() < 1e-8


def test_invalid_points_are_nan():
    pin = make_lens("pinhole", 90, W, H)
    uv = pin.project([[0, 0, -1.0], [1.0, 0, 0.0], [0, 0, 0], [0.1, 0, 1]])
    assert np.isnan(uv[:3]).all() and np.isfinite(uv[3]).all()
    fish = make_lens("equidistant", 200, W, H)  # capped at 100 degrees (circle)
    uv = fish.project(_directions(np.radians([95.0, 120.0])))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    assert np.isnan(fish.unproject([[fish.cx + 0.99 * W, fish.cy]])).all()


def test_sphere_is_the_spherical_model_and_folds():
    lens = SphereLens(cx=100.0, cy=50.0, f=80.0)
    p = np.array([[0.3, -0.2, 0.5], [0.3, -0.2, -0.5]])
    expected = np.array([100.0, 50.0]) + 80.0 * p[:, :2] / np.linalg.norm(p, axis=1)[:, None]
    uv = lens.project(p)
    assert np.allclose(uv, expected)
    assert np.allclose(uv[0], uv[1])  # front and back share a pixel
    front = lens.unproject(uv[:1])
    back = lens.unproject(uv[:1], hemisphere=-1)
    assert front[0, 2] > 0 and back[0, 2] < 0
    assert _angle(back, p[1:]).max() < 1e-12
    # alpha = 90 degrees and straight behind
    edge = lens.project([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    assert edge[0] == pytest.approx([180.0, 50.0]) and edge[1] == pytest.approx([100.0, 50.0])


def test_max_incidence_reflects_monotonicity():
    kb = make_lens("kannala-brandt", 150, W, H, k1=0.02, k2=-0.01)
    alpha = np.linspace(0, 0.999 * math.radians(kb.max_incidence_deg), 500)
    uv = kb.project(np.stack([np.sin(alpha), 0 * alpha, np.cos(alpha)], axis=1))
    assert np.all(np.diff(uv[:, 0]) > 0)
    beyond = math.radians(kb.max_incidence_deg + 1.0)
    assert np.isnan(kb.project([[math.sin(beyond), 0.0, math.cos(beyond)]])).all()
    assert kb.max_incidence_deg < 180
    assert make_lens("unified", 200, W, H, xi=2.0).max_incidence_deg == pytest.approx(100)
    assert PinholeBrown(0, 0, 1).max_incidence_deg == 85.0


def test_make_lens_errors():
    with pytest.raises(ValueError, match="fisheye"):
        make_lens("fisheye", 150, W, H)
    with pytest.raises(ValueError, match="pinhole"):
        make_lens("pinhole", 180, W, H)
    with pytest.raises(ValueError, match="stereographic"):
        make_lens("stereographic", 360, W, H)
    with pytest.raises(ValueError, match="bogus"):
        make_lens("equidistant", 150, W, H, bogus=1.0)
    with pytest.raises(ValueError):
        make_lens("equidistant", 150, W, H, fill="square")


def test_non_central_round_trip_and_distance_dependence():
    base = make_lens("equidistant", 200, W, H)
    lens = NonCentral(base, pupil_shift_m=0.01)
    rays = _directions(np.radians([0.0, 30.0, 90.0, 95.0]), seed=4)
    near, far = lens.project(0.5 * rays), lens.project(50.0 * rays)
    assert np.abs(near - far).max() > 0.5  # not a central camera
    assert near[0] == pytest.approx(far[0])  # the axis ray is unaffected
    origins, dirs = lens.unproject_with_origin(near)
    assert np.allclose(origins[:, :2], 0.0)
    assert np.abs(lens.project(origins + 2.0 * dirs) - near).max() < 1e-6
    assert np.abs(lens.project(origins + 0.5 * rays) - near).max() > 0  # sanity


def test_error_field_bounded_smooth_and_invertible():
    base = make_lens("kannala-brandt", 150, W, H, k1=0.03)
    lens = ErrorField(base, amplitude_px=3.0, n_terms=5, seed=11)
    rays = _directions(np.linspace(0, math.radians(74), 300), seed=5)
    uv0, uv = base.project(rays), lens.project(rays)
    disp = np.linalg.norm(uv - uv0, axis=1)
    assert disp.max() <= 3.0 + 1e-9 and disp.max() > 0.3
    assert _angle(lens.unproject(uv), rays).max() < 1e-9
    same = ErrorField(base, amplitude_px=3.0, n_terms=5, seed=11)
    assert np.array_equal(same.project(rays), uv)
    other = ErrorField(base, amplitude_px=3.0, n_terms=5, seed=12)
    assert not np.allclose(other.project(rays), uv)


def test_to_dict_round_trip():
    lens = ErrorField(
        NonCentral(make_lens("unified", 200, W, H, xi=1.3, k1=-0.02), 0.003), 2.0, seed=3
    )
    again = lens_from_dict(lens.to_dict())
    pts = _directions(np.radians([10.0, 60.0, 95.0]))
    assert np.array_equal(again.project(pts), lens.project(pts))


def test_incidence_angle():
    a = incidence_angle([[0, 0, 1.0], [1, 0, 0.0], [0, 0, -2.0], [0, 1, -1.0]])
    assert a == pytest.approx([0, math.pi / 2, math.pi, 0.75 * math.pi])


# -- double sphere and FOV (field-of-view) lenses ------------------------------------


def _paper_double_sphere(p: np.ndarray, fx: float, cx: float, cy: float, xi: float, a: float):
    """Usenko et al. 2018, Eq. 40-45 for points of any distance (fx = fy, no distortion)."""
    x, y, z = p.T
    d1 = np.linalg.norm(p, axis=1)
    d2 = np.sqrt(x * x + y * y + (xi * d1 + z) ** 2)
    den = a * d2 + (1.0 - a) * (xi * d1 + z)
    return np.stack([fx * x / den + cx, fx * y / den + cy], axis=1)


def test_double_sphere_is_the_papers_model_and_validity_bound():
    lens = make_lens("double-sphere", 200.0, W, H, xi=-0.25, alpha=0.62, cx=2100.0, cy=1400.0)
    pts = _directions(np.radians(np.linspace(0.0, 99.0, 60)), seed=7)
    pts = pts * np.random.default_rng(2).uniform(0.2, 40.0, (60, 1))  # distance is irrelevant
    ref = _paper_double_sphere(pts, lens.f, lens.cx, lens.cy, lens.xi, lens.alpha)
    assert np.abs(lens.project(pts) - ref).max() < 1e-8
    # the paper's validity: z > -w2 |p| with w1 = (1 - alpha) / alpha for alpha > 1/2
    w1 = (1 - 0.62) / 0.62
    w2 = (w1 - 0.25) / math.sqrt(2 * w1 * -0.25 + 0.25**2 + 1)
    free = DoubleSphere(cx=0.0, cy=0.0, f=1.0, xi=-0.25, alpha=0.62)
    assert free.max_incidence_deg == pytest.approx(math.degrees(math.acos(-w2)), abs=0.05)
    # alpha = 1/2, xi = 0 sees (almost) the whole sphere
    assert DoubleSphere(0.0, 0.0, 1.0, xi=0.0, alpha=0.5).max_incidence_deg > 179.9
    with pytest.raises(ValueError, match="alpha"):
        DoubleSphere(0.0, 0.0, 1.0, alpha=1.0)


def test_fov_model_is_devernay_faugeras_below_90_deg():
    omega = 1.3
    lens = make_lens("fov", 150.0, W, H, omega=omega)
    pts = _directions(np.radians(np.linspace(0.5, 89.5, 50)), seed=8) * 3.0
    r_u = np.hypot(pts[:, 0], pts[:, 1]) / pts[:, 2]  # pinhole radius
    r_d = np.arctan(2.0 * r_u * math.tan(omega / 2)) / omega
    uv = lens.project(pts)
    r = np.hypot(uv[:, 0] - lens.cx, uv[:, 1] - lens.cy) / lens.f
    assert np.abs(r - r_d).max() < 1e-12
    # past 90 degrees the incidence form continues smoothly: pi / (2 omega) at 90 degrees
    edge = lens.project([[1.0, 0.0, 0.0]])[0]
    assert (edge[0] - lens.cx) / lens.f == pytest.approx(math.pi / (2 * omega))
    with pytest.raises(ValueError, match="omega"):
        FieldOfView(0.0, 0.0, 1.0, omega=math.pi)


@pytest.mark.parametrize(
    ("kind", "fov", "opts"), [c for c in CASES if c[0] in ("double-sphere", "fov")]
)
def test_new_lenses_monotonic_and_edges(kind, fov, opts):
    lens = make_lens(kind, fov, W, H, fill="circle", **opts)
    half = fov / 2
    assert lens.max_incidence_deg == pytest.approx(half)  # a circular image sees fov / 2
    alpha = np.linspace(0.0, math.radians(half), 2000)
    ideal = make_lens(kind, fov, W, H, fill="circle", **_without_decentering(opts))
    uv = ideal.project(np.stack([np.sin(alpha), 0 * alpha, np.cos(alpha)], axis=1))
    assert np.isfinite(uv).all() and np.all(np.diff(uv[:, 0]) > 0)  # radius increases
    # the optical axis is the principal point, in both directions
    assert lens.project([[0.0, 0.0, 5.0]])[0] == pytest.approx([lens.cx, lens.cy])
    assert lens.unproject([[lens.cx, lens.cy]])[0] == pytest.approx([0.0, 0.0, 1.0])
    # 90 degrees is an ordinary point when the field reaches it
    if half >= 90.0:
        side = lens.unproject(lens.project([[0.0, 1.0, 0.0]]))[0]
        assert side == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)
    # beyond the field: NaN both ways
    beyond = math.radians(half + 1.0)
    if beyond < math.pi:
        assert np.isnan(lens.project([[math.sin(beyond), 0.0, math.cos(beyond)]])).all()
    r_edge = ideal.project([[math.sin(math.radians(half)), 0.0, math.cos(math.radians(half))]])
    far = [[lens.cx + 1.05 * (r_edge[0, 0] - ideal.cx), lens.cy]]
    assert np.isnan(lens.unproject(far)).all()


def test_double_sphere_cannot_reach_past_its_validity():
    assert make_lens("double-sphere", 240.0, W, H).max_incidence_deg == pytest.approx(120.0)
    with pytest.raises(ValueError, match="double-sphere"):
        make_lens("double-sphere", 250.0, W, H)  # xi = -0.2, alpha = 0.6: 244 degrees
    with pytest.raises(ValueError, match="bogus"):
        make_lens("fov", 120.0, W, H, bogus=1.0)


def test_new_lenses_to_dict_round_trip():
    for lens in (
        make_lens("double-sphere", 220.0, W, H, xi=-0.1, alpha=0.57, p1=1e-4, cx=2050.0),
        make_lens("fov", 200.0, W, H, omega=1.7, cy=1600.0),
    ):
        again = lens_from_dict(lens.to_dict())
        assert again == lens
        pts = _directions(np.radians([0.0, 45.0, 99.0]))
        assert np.array_equal(again.project(pts), lens.project(pts))


# -- image circle size and principal point -------------------------------------------


@pytest.mark.parametrize("kind", ["equidistant", "double-sphere", "fov", "pinhole", "sphere"])
@pytest.mark.parametrize(
    ("fov", "radius", "pp"),
    [
        (100.0, 0.25 * min(W, H), (0.0, 0.0)),
        (170.0, 1.3 * math.hypot(W, H) / 2, (0.1 * W, -0.1 * H)),
        (150.0, 1000.0, (-0.07 * W, 0.05 * H)),
    ],
)
def test_circle_radius_and_principal_point_honoured(kind, fov, radius, pp):
    if kind == "pinhole" and fov > 160:
        fov = 160.0
    cx, cy = (W - 1) / 2 + pp[0], (H - 1) / 2 + pp[1]
    lens = make_lens(kind, fov, W, H, circle_radius_px=radius, cx=cx, cy=cy)
    assert (lens.cx, lens.cy) == (cx, cy)
    assert lens.max_incidence_deg == pytest.approx(fov / 2)
    half = math.radians(fov / 2)
    uv = lens.project(_directions(np.array([half, half, half]), seed=9))
    assert np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) == pytest.approx([radius] * 3, rel=1e-9)
    # circle_radius_px overrides fill
    same = make_lens(kind, fov, W, H, fill="diagonal", circle_radius_px=radius, cx=cx, cy=cy)
    assert same == lens


def test_circle_radius_for_sphere_past_180_is_the_disc():
    lens = make_lens("sphere", 250.0, W, H, circle_radius_px=600.0)
    assert lens.f == 600.0 and lens.max_incidence_deg == pytest.approx(125.0)
    with pytest.raises(ValueError, match="circle_radius_px"):
        make_lens("equidistant", 180.0, W, H, circle_radius_px=0.0)


def test_sphere_oracle_undoes_sensor_defects_in_the_image_plane():
    """A sphere lens with affinity, shear and decentering: ``ideal_pixels`` are the
    pixels of the same lens without them (front and back hemisphere alike), which is
    what the oracle maps the measurements to (the sphere lens cannot be unprojected)."""
    from dataclasses import dataclass
    from dataclasses import replace as dc_replace

    from gtsam_sphere.simulate.oracle import oracle_dataset

    @dataclass
    class _Measurements:  # the one field oracle_dataset reads and replaces
        uv_px: np.ndarray

    lens = make_lens("sphere", 250.0, W, H, a1=0.02, a2=-0.004, p1=4e-4, p2=-3e-4)
    clean = dc_replace(lens, a1=0.0, a2=0.0, p1=0.0, p2=0.0)
    rng = np.random.default_rng(2)
    rays = rng.normal(size=(500, 3))
    rays = rays[np.degrees(np.arccos(rays[:, 2] / np.linalg.norm(rays, axis=1))) < 124.0]
    assert (rays[:, 2] < 0).sum() > 50  # behind the camera too
    uv = lens.project(rays)
    assert np.abs(uv - clean.project(rays)).max() > 1.0  # the defects move pixels
    np.testing.assert_allclose(lens.ideal_pixels(uv), clean.project(rays), atol=1e-8)
    ideal, model, fixed = oracle_dataset(_Measurements(uv), lens, lens.to_dict())
    assert str(model) == "sphere" and fixed == (lens.cx, lens.cy, lens.f)
    np.testing.assert_allclose(ideal.uv_px, clean.project(rays), atol=1e-8)
