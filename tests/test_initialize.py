"""Tests of gtsam_sphere.estimation.initialize on a tiny local "inside-out room" simulator."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import initialise_simulation

from gtsam_sphere.estimation.initialize import (
    InitialisationError,
    InitialisationResult,
    bearings_from_pixels,
    initialize_poses,
    observed_disc,
)
from gtsam_sphere.simulate.lenses import (
    Equidistant,
    Equisolid,
    FieldOfView,
    KannalaBrandt,
    PinholeBrown,
    SphereLens,
    Stereographic,
    Unified,
    incidence_angle,
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def _room_targets(rng: np.random.Generator, n: int) -> np.ndarray:
    """Targets on the walls, floor and ceiling of a 6 x 5 x 3 m room (metres)."""
    half = np.array([3.0, 2.5, 1.5])
    pts = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    side = rng.choice([-1.0, 1.0], size=n)
    pts[np.arange(n), axis] = side * half[axis]
    return pts


def _project(p_cam: np.ndarray, mapping: str, f_px: float, pp: np.ndarray, max_alpha: float):
    """Pixels of camera-frame points and a visibility mask."""
    rho = np.hypot(p_cam[:, 0], p_cam[:, 1])
    alpha = np.arctan2(rho, p_cam[:, 2])
    if mapping == "equidistant":
        r = f_px * alpha
    elif mapping == "pinhole":
        r = f_px * np.tan(np.minimum(alpha, 1.5))
    else:  # sphere
        r = f_px * np.sin(alpha)
    safe = np.where(rho > 0, rho, 1.0)
    uv = pp + r[:, None] * p_cam[:, :2] / safe[:, None]
    return uv, alpha <= max_alpha


def _cube_corner_targets(rng: np.random.Generator, n: int) -> np.ndarray:
    """A 3D calibration object: grids on three orthogonal 0.6 m faces meeting at the origin."""
    side = int(np.ceil(np.sqrt(n / 3)))
    g = (np.arange(side) + 0.5) * 0.6 / side
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    z = np.zeros_like(a)
    return np.concatenate([np.column_stack(c) for c in ((a, b, z), (a, z, b), (z, a, b))])


def _look_at(centre: np.ndarray, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """cam_from_world rotation with +z from ``centre`` towards ``target``, random roll."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, rng.normal(size=3))
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def simulate(
    seed: int,
    mapping: str,
    f_px: float,
    fov_deg: float,
    width: int,
    height: int,
    n_images: int,
    n_targets: int,
    target_noise_m: float = 0.01,
    pixel_noise_px: float = 0.3,
    blunder_fraction: float = 0.03,
    lens=None,
    scene: str = "room",
):
    """Synthetic dataset: random poses inside a room, targets on its surfaces.

    ``lens`` (a :mod:`gtsam_sphere.simulate.lenses` object) replaces ``mapping``/``f_px``
    (its own field cap applies); ``scene="object"`` puts the targets on a cube corner
    (:func:`_cube_corner_targets`) seen from outside.
    """
    rng = np.random.default_rng(seed)
    if scene == "object":
        xyz_true = _cube_corner_targets(rng, n_targets)
    else:
        xyz_true = _room_targets(rng, n_targets)
    pp = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    rots, trans, uv_all, img_all, tgt_all = [], [], [], [], []
    for i in range(n_images):
        if scene == "object":  # outside the object's octant, looking roughly at it
            centre = rng.uniform(0.8, 1.6, 3) * rng.choice([1.0, 1.0, 1.0, -0.3], 3)
            centre = np.abs(centre) + 0.3
            rot = _look_at(centre, rng.uniform(0.0, 0.4, 3), rng)
        else:
            rot = _random_rotation(rng)
            centre = rng.uniform([-1.0, -1.0, -0.5], [1.0, 1.0, 0.5])
        t = -rot @ centre
        p_cam = xyz_true @ rot.T + t
        if lens is None:
            uv, vis = _project(p_cam, mapping, f_px, pp, np.radians(fov_deg) / 2)
        else:
            uv = lens.project(p_cam)
            vis = np.all(np.isfinite(uv), axis=1)
            uv = np.where(vis[:, None], uv, -1e9)
        if scene == "object":  # a face is seen from the side its normal points to
            normals = np.eye(3)[np.argmax(xyz_true == 0, axis=1)]
            vis &= np.einsum("ij,ij->i", normals, centre - xyz_true) > 0.05
        vis &= (uv[:, 0] > -0.5) & (uv[:, 0] < width - 0.5)
        vis &= (uv[:, 1] > -0.5) & (uv[:, 1] < height - 0.5)
        idx = np.flatnonzero(vis)
        rots.append(rot)
        trans.append(t)
        uv_all.append(uv[idx] + rng.normal(scale=pixel_noise_px, size=(idx.size, 2)))
        img_all.append(np.full(idx.size, i))
        tgt_all.append(idx)
    uv = np.concatenate(uv_all)
    n_obs = uv.shape[0]
    blunder = rng.random(n_obs) < blunder_fraction
    offset = rng.normal(size=(n_obs, 2))
    offset *= rng.uniform(20, 60, size=n_obs)[:, None] / np.linalg.norm(offset, axis=1)[:, None]
    uv[blunder] += offset[blunder]
    xyz_approx = xyz_true + rng.normal(scale=target_noise_m, size=xyz_true.shape)
    return dict(
        uv_px=uv,
        obs_image=np.concatenate(img_all),
        obs_target=np.concatenate(tgt_all),
        target_xyz=xyz_approx,
        width=width,
        height=height,
        n_images=n_images,
        R=np.array(rots),
        t=np.array(trans),
    )


def _pose_errors(res: InitialisationResult, data: dict, images) -> tuple[float, float]:
    """Worst rotation error (deg) and camera-centre error (m) over ``images``."""
    worst_rot, worst_pos = 0.0, 0.0
    for i in images:
        r_est, t_est = res.cam_from_world_R[i], res.cam_from_world_t[i]
        r_true, t_true = data["R"][i], data["t"][i]
        cos = (np.trace(r_est.T @ r_true) - 1) / 2
        worst_rot = max(worst_rot, np.degrees(np.arccos(np.clip(cos, -1, 1))))
        c_est, c_true = -r_est.T @ t_est, -r_true.T @ t_true
        worst_pos = max(worst_pos, float(np.linalg.norm(c_est - c_true)))
    return worst_rot, worst_pos


def _inputs(data: dict) -> dict:
    keys = ("uv_px", "obs_image", "obs_target", "target_xyz", "width", "height", "n_images")
    return {k: data[k] for k in keys}


@pytest.mark.parametrize("mapping", ["pinhole", "equidistant", "sphere"])
def test_bearings_from_pixels_round_trip(mapping):
    rng = np.random.default_rng(3)
    f_px, pp = 300.0, np.array([400.0, 300.0])
    max_alpha = {"pinhole": 1.4, "equidistant": 3.0, "sphere": np.pi / 2}[mapping]
    alpha = rng.uniform(0, max_alpha, 200)
    phi = rng.uniform(-np.pi, np.pi, 200)
    rays = np.stack([np.sin(alpha) * np.cos(phi), np.sin(alpha) * np.sin(phi), np.cos(alpha)], 1)
    uv, _ = _project(rays, mapping, f_px, pp, np.pi)
    back = bearings_from_pixels(uv, mapping, f_px, pp)
    np.testing.assert_allclose(back, rays, atol=1e-9)
    np.testing.assert_allclose(bearings_from_pixels(pp[None], mapping, f_px, pp), [[0, 0, 1.0]])


def test_bearings_outside_domain_are_nan():
    pp = np.zeros(2)
    rays = bearings_from_pixels(np.array([[150.0, 0.0], [50.0, 0.0]]), "sphere", 100.0, pp)
    assert np.all(np.isnan(rays[0])) and np.all(np.isfinite(rays[1]))
    rays = bearings_from_pixels(np.array([[400.0, 0.0]]), "equidistant", 100.0, pp)
    assert np.all(np.isnan(rays))
    with pytest.raises(ValueError, match="unknown mapping"):
        bearings_from_pixels(np.zeros((1, 2)), "fisheye??", 100.0, pp)


def _check_case(data, res, expect_mapping, f_true, tol_deg=1.0, tol_m=0.05):
    assert res.mapping == expect_mapping
    assert abs(res.f_px / f_true - 1) < 0.03
    good = [i for i in range(data["n_images"]) if i not in res.failures]
    assert res.ok[good].all()
    # well-observed images (>= 50 targets): within ~1 deg / 5 cm; all: within 3 deg / 10 cm
    counts = np.bincount(data["obs_image"], minlength=data["n_images"])
    rot_err, pos_err = _pose_errors(res, data, [i for i in good if counts[i] >= 50])
    assert rot_err < tol_deg, rot_err
    assert pos_err < tol_m, pos_err
    rot_err, pos_err = _pose_errors(res, data, good)
    assert rot_err < 3 * tol_deg and pos_err < 2 * tol_m, (rot_err, pos_err)
    # most observations of initialised images are inliers
    mask = res.ok[data["obs_image"]]
    assert res.inlier_mask[mask].mean() > 0.85
    assert not res.inlier_mask[~mask].any()


@pytest.mark.slow  # end-to-end
def test_equidistant_200deg_lens_with_two_observation_image():
    data = simulate(
        seed=10,
        mapping="equidistant",
        f_px=300.0,
        fov_deg=200.0,
        width=1200,
        height=1000,
        n_images=10,
        n_targets=200,
    )
    # image 3 keeps only 2 observations
    keep = (data["obs_image"] != 3) | (np.cumsum(data["obs_image"] == 3) <= 2)
    for key in ("uv_px", "obs_image", "obs_target"):
        data[key] = data[key][keep]
    messages: list[str] = []
    res = initialize_poses(**_inputs(data), rng=np.random.default_rng(0), progress=messages.append)
    assert messages
    assert 3 in res.failures and "only 2 observations" in res.failures[3]
    assert not res.ok[3] and np.isnan(res.cam_from_world_R[3]).all()
    assert len(res.failures) == 1
    # there really are points behind the camera in this data
    _check_case(data, res, "equidistant", 300.0)


@pytest.mark.slow  # end-to-end
def test_pinhole_70deg_lens():
    f_px = 500.0 / np.tan(np.radians(35.0))
    data = simulate(
        seed=11,
        mapping="pinhole",
        f_px=f_px,
        fov_deg=120.0,  # clipped by the 1000 x 750 frame: ~70 deg horizontally
        width=1000,
        height=750,
        n_images=8,
        n_targets=1500,
    )
    res = initialize_poses(**_inputs(data), rng=np.random.default_rng(1))
    assert not res.failures
    _check_case(data, res, "pinhole", f_px)


def test_no_image_can_be_initialised_raises():
    data = simulate(1, "pinhole", 500.0, 90.0, 800, 600, 3, 300)
    keep = np.zeros(data["obs_image"].size, bool)
    for i in range(3):
        keep[np.flatnonzero(data["obs_image"] == i)[:2]] = True
    for key in ("uv_px", "obs_image", "obs_target"):
        data[key] = data[key][keep]
    with pytest.raises(ValueError, match="no image can be initialised"):
        initialize_poses(**_inputs(data))


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="uv_px"):
        initialize_poses(
            np.zeros((4, 3)), np.zeros(4, int), np.zeros(4, int), np.zeros((1, 3)), 100, 100, 1
        )
    with pytest.raises(ValueError, match="obs_target"):
        initialize_poses(
            np.zeros((4, 2)), np.zeros(4, int), np.full(4, 5), np.zeros((1, 3)), 100, 100, 1
        )


def _radius_error(res: InitialisationResult, lens, uv_px: np.ndarray) -> float:
    """Largest error (px) of the initial lens' radius over the observed field."""
    rays = lens.unproject(uv_px)
    alpha = incidence_angle(rays)
    alpha = alpha[np.isfinite(alpha)]
    grid = np.linspace(0.02, np.percentile(alpha, 99), 40)
    p = np.column_stack([np.sin(grid), np.zeros_like(grid), np.cos(grid)])
    true_r = lens.project(p)[:, 0] - lens.cx
    return float(np.max(np.abs(res.lens.radius_px(grid) - true_r)))


# (lens, image size): image circles from 0.25x the short side to 1.3x the half diagonal,
# principal points off the centre, five families and two lenses between them
_CIRCLE_CASES = {
    "equisolid250-circle0.25": (
        Equisolid,
        dict(f=0.25 * 2000 / 1.7740, max_angle_deg=125.0),
        2000,
        2000,
        (0.0, 0.0),
    ),
    "stereo200-circle0.45-offset": (
        Stereographic,
        dict(f=0.45 * 1600 / 2.3835, max_angle_deg=100.0),
        1600,
        1600,
        (0.06, -0.05),
    ),
    "unified220-circle0.33": (
        Unified,
        dict(f=0.33 * 2400 / np.tan(np.radians(55)), xi=1.0, max_angle_deg=110.0),
        2400,
        2400,
        (0.0, 0.03),
    ),
    "kb190-circle0.5": (
        KannalaBrandt,
        dict(f=700 / 1.58, k1=-0.02, k2=0.003, max_angle_deg=95.0),
        1600,
        1400,
        (0.0, 0.0),
    ),
    "equidistant180-fullframe1.3": (
        Equidistant,
        dict(f=1.3 * 1000.0 / (np.pi / 2), max_angle_deg=90.0),
        1600,
        1200,
        (0.08, 0.0),
    ),
    "fov260-circle0.35": (  # a lens that squeezes its rim: 90-130 deg in 13 % of the radius
        FieldOfView,
        dict(f=0.35 * 1600 / 0.8094, omega=2.2, max_angle_deg=130.0),
        1600,
        1600,
        (0.02, 0.0),
    ),
    "pinhole-brown-offset": (
        PinholeBrown,
        dict(f=900.0, k1=-0.05, max_angle_deg=60.0),
        1600,
        1200,
        (-0.1, 0.1),
    ),
}


#: the fast loop keeps one circle (each takes 7-25 s on 2 cores); CI runs them all
_FAST_CIRCLES = {"unified220-circle0.33"}


@pytest.mark.parametrize(
    "case",
    [
        c if c in _FAST_CIRCLES else pytest.param(c, marks=pytest.mark.slow)
        for c in sorted(_CIRCLE_CASES)
    ],
)
def test_focal_scale_and_principal_point_from_the_pixels(case):
    """The initial lens matches the truth over the observed field, whatever the circle."""
    cls, params, width, height, (ox, oy) = _CIRCLE_CASES[case]
    cx, cy = (width - 1) / 2 + ox * width, (height - 1) / 2 + oy * height
    lens = cls(cx=cx, cy=cy, **params)
    data = simulate(3, "", 0.0, 0.0, width, height, 12, 900, lens=lens)
    messages: list[str] = []
    res = initialize_poses(**_inputs(data), rng=np.random.default_rng(0), progress=messages.append)
    short = min(width, height)
    # the radius of the initial lens is right to 3 % of the observed radius ...
    r_obs = np.percentile(np.hypot(*(data["uv_px"] - [cx, cy]).T), 99)
    assert _radius_error(res, lens, data["uv_px"]) < 0.03 * r_obs, messages
    # ... the principal point to 2 % of the short side, the poses to ~1-2 deg
    assert np.hypot(*(res.principal_point_px - [cx, cy])) < 0.02 * short, messages
    good = [i for i in range(data["n_images"]) if res.ok[i]]
    assert len(good) == data["n_images"]
    rot_err, _ = _pose_errors(res, data, good)
    assert rot_err < 2.0, rot_err
    mask = res.ok[data["obs_image"]]
    assert res.inlier_mask[mask].mean() > 0.9


def test_small_circle_is_found_as_a_disc():
    lens = Equisolid(f=300.0, cx=1100.0, cy=1000.0, max_angle_deg=125.0)
    data = simulate(4, "", 0.0, 0.0, 2000, 2000, 12, 900, lens=lens)
    centre, radius = observed_disc(data["uv_px"], 2000, 2000)
    assert np.hypot(*(centre - [1100.0, 1000.0])) < 15.0
    assert abs(radius - 300.0 * 2 * np.sin(np.radians(62.5))) < 20.0
    # a full-frame image (a circle beyond the sensor's corners) is not a disc ...
    wide = Equidistant(f=700.0, cx=799.5, cy=599.5, max_angle_deg=89.0)
    data = simulate(4, "", 0.0, 0.0, 1600, 1200, 12, 900, lens=wide)
    assert observed_disc(data["uv_px"], 1600, 1200) is None
    # ... while a circle (r = 777 px) that only the top and bottom edges crop is one
    wide = Equidistant(f=500.0, cx=799.5, cy=599.5, max_angle_deg=89.0)
    data = simulate(4, "", 0.0, 0.0, 1600, 1200, 12, 900, lens=wide)
    centre, _ = observed_disc(data["uv_px"], 1600, 1200)
    assert np.hypot(*(centre - [799.5, 599.5])) < 10.0, centre


def test_circle_cropped_by_the_sensor_is_found_from_its_arcs():
    """A 260 deg lens whose circle (r = 400 px) the bottom of a 1280x800 sensor crops by
    80 px: the circle is fitted to the hull's arcs, not to the sensor's edge (without the
    disc, only the image centre, 150 px off, was tried and every hypothesis failed)."""
    lens = FieldOfView(f=400.0 / 0.8094, cx=511.5, cy=479.5, omega=2.2, max_angle_deg=130.0)
    data = simulate(4, "", 0.0, 0.0, 1280, 800, 12, 900, lens=lens)
    assert data["uv_px"][:, 1].max() > 790  # the sensor does crop the circle
    centre, radius = observed_disc(data["uv_px"], 1280, 800)
    assert np.hypot(*(centre - [511.5, 479.5])) < 10.0, centre
    assert abs(radius - 400.0) < 20.0, radius


@pytest.mark.slow  # 12 s: a full initialisation of a 3D-object set (CI runs it)
def test_3d_object_picks_the_right_focal_scale():
    """A cube corner of three tag grids seen by a 1280x800 fisheye (real case of issue 12)."""
    lens = KannalaBrandt(f=330.0, cx=640.0, cy=400.0, k1=-0.01, k2=0.002, max_angle_deg=98.0)
    data = simulate(
        5,
        "",
        0.0,
        0.0,
        1280,
        800,
        15,
        300,
        lens=lens,
        scene="object",
        target_noise_m=0.0,
        blunder_fraction=0.0,
    )
    res = initialize_poses(**_inputs(data), rng=np.random.default_rng(0))
    assert abs(res.lens.f_px / 330.0 - 1) < 0.05, res.lens.describe()
    good = np.flatnonzero(res.ok)
    assert good.size >= 13
    rot_err, pos_err = _pose_errors(res, data, good)
    assert rot_err < 2.0 and pos_err < 0.05, (rot_err, pos_err)


@pytest.mark.slow  # a full initialisation (CI runs it)
def test_orthographic_lens_within_90_deg_is_not_folded():
    """The folded sphere hypothesis (tests/test_lens_zoo.py) does not take an ordinary
    orthographic lens: every pixel is then the image of its front ray only."""
    lens = SphereLens(f=480.0, cx=799.5, cy=599.5, max_angle_deg=75.0)
    data = simulate(6, "", 0.0, 0.0, 1600, 1200, 12, 400, lens=lens, scene="object")
    res = initialize_poses(**_inputs(data), rng=np.random.default_rng(0))
    assert not res.lens.folded, res.lens.describe()
    good = np.flatnonzero(res.ok)
    assert good.size == data["n_images"]
    rot_err, pos_err = _pose_errors(res, data, good)
    assert rot_err < 2.0 and pos_err < 0.1, (rot_err, pos_err)


@pytest.mark.slow  # 18 s on 2 cores: every hypothesis is scanned before it fails (CI runs it)
def test_unexplainable_data_fails_fast_with_the_hypotheses_tried():
    """Pixels unrelated to the targets: no hypothesis explains them -> a clear error."""
    data = simulate(6, "equidistant", 300.0, 180.0, 1200, 1000, 8, 400)
    rng = np.random.default_rng(1)
    data["obs_target"] = rng.permutation(data["obs_target"])
    with pytest.raises(InitialisationError, match="no lens hypothesis explains"):
        initialize_poses(**_inputs(data), rng=np.random.default_rng(0))


def test_pruned_costs_keep_the_best_hypotheses_exact():
    """``_Problem.costs(keep=k)`` scores losers only until they pass the k-th best total:
    the k lowest entries (per group) and their order equal the full evaluation's, and
    every pruned entry is a partial sum above that bound (never below the true total)."""
    from gtsam_sphere.estimation.initialize import _family, _Problem

    data = simulate(3, "equidistant", 300.0, 180.0, 1000, 800, 6, 300)
    problem = _Problem(data["uv_px"], data["obs_image"], data["obs_target"], data["target_xyz"], 6)
    pp = np.array([499.5, 399.5])
    hyps = [_family(m, f, pp) for m in ("equidistant", "equisolid") for f in (240, 280, 300, 330)]
    groups = np.repeat([0, 1], 4)
    images, seeds = [0, 1, 2, 3], [5, 6, 7, 8]
    full = problem.costs(hyps, images, seeds, 6.0, 64, False)
    for keep, grp in [(1, None), (3, None), (1, groups), (2, groups)]:
        pruned = problem.costs(hyps, images, seeds, 6.0, 64, False, keep=keep, groups=grp)
        labels = np.zeros(len(hyps), int) if grp is None else grp
        for g in np.unique(labels):
            members = np.flatnonzero(labels == g)
            best = members[np.argsort(full[members], kind="stable")[:keep]]
            np.testing.assert_array_equal(
                members[np.argsort(pruned[members], kind="stable")[:keep]], best
            )
            np.testing.assert_allclose(pruned[best], full[best], rtol=1e-12)
            rest = np.setdiff1d(members, best)
            assert np.all(pruned[rest] <= full[rest] + 1e-9)
            assert np.all(pruned[rest] > full[best].max())
    assert np.argmin(full) == 2  # the true lens wins


@pytest.mark.parametrize("warp_w", [0.0, float(np.log(4.0)), float(np.log(0.25))])
def test_joint_refine_jacobian_matches_finite_differences(warp_w):
    """The joint refit's analytic Jacobian (principal point, odd polynomial in the warped
    incidence, poses on SO(3) x R3) against scipy's central differences of its residuals,
    at the start and at a perturbed point with rotated poses; its normal equations are
    ``J^T W J`` and the gradient of its Huber cost (some observations past the
    threshold there); the arrow solve gives the dense solve's LM run."""
    from scipy.optimize._numdiff import approx_derivative

    from gtsam_sphere.core.least_squares import Damping, arrow_solve, levenberg_marquardt
    from gtsam_sphere.estimation.initialize import _family, _joint_refine, _JointRefit, _Problem

    data = simulate(4, "equidistant", 300.0, 200.0, 1000, 800, 4, 300, blunder_fraction=0.0)
    problem = _Problem(data["uv_px"], data["obs_image"], data["obs_target"], data["target_xyz"], 4)
    problem.all_observations = True
    hyp = replace(_family("equidistant", 300.0, np.array([499.5, 399.5])), warp_w=warp_w)
    rot = np.asarray(data["R"], float)
    trans = np.asarray(data["t"], float)
    mask = np.ones(data["uv_px"].shape[0], bool)
    refit = _JointRefit.build(problem, [0, 1, 2, 3], hyp, rot, trans, mask, 3.0)
    n_lens, n_x = refit.n_lens, refit.x0.size
    assert n_x == 2 + 4 + 24
    rng = np.random.default_rng(0)
    for x in (refit.x0, refit.x0 + rng.normal(scale=1e-2, size=n_x)):
        res, J = refit.jacobian(x)
        np.testing.assert_array_equal(res, refit.residuals(x))
        dense = np.zeros((2 * res.shape[0], n_x))
        for i, k in enumerate(refit.owner):
            dense[2 * i : 2 * i + 2, :n_lens] = J[i, :, :n_lens]
            dense[2 * i : 2 * i + 2, refit.pose_idx[k]] = J[i, :, n_lens:]
        numeric = approx_derivative(lambda z: refit.residuals(z).ravel(), x, method="3-point")
        scale = np.abs(numeric).max(axis=0) + 1.0
        assert np.abs((dense - numeric) / scale).max() < 1e-5
        H, g = refit.linearize(x)
        e = np.linalg.norm(res, axis=1) / 3.0
        w = np.minimum(1.0, 1.0 / np.maximum(e, 1e-300))
        if x is not refit.x0:
            assert (w < 1.0).any()  # the Huber weights are exercised
        Wd = dense * np.repeat(w, 2)[:, None] / 9.0
        np.testing.assert_allclose(H, Wd.T @ dense, rtol=1e-10, atol=1e-8 * np.abs(H).max())
        # steps of 1e-6 max(1, |x|): the default (6e-6 on b near 0) straddles Huber kinks
        # of the steep alpha^7 coefficient
        step = 1e-6 * np.maximum(1.0, np.abs(x))
        grad = approx_derivative(refit.cost, x, method="3-point", abs_step=step)
        np.testing.assert_allclose(g, grad, rtol=1e-4, atol=1e-6 * np.abs(g).max())
    start = refit.x0 + rng.normal(scale=1e-3, size=n_x)
    runs = [
        levenberg_marquardt(
            start,
            refit.cost,
            refit.linearize,
            damping=Damping(max_tries=12),
            max_iterations=8,
            solve=solve,
        )
        for solve in (None, arrow_solve(n_lens, 6))
    ]
    np.testing.assert_allclose(runs[1].x, runs[0].x, rtol=1e-7, atol=1e-9)
    assert runs[1].cost < refit.cost(start)
    out = _joint_refine(problem, [0, 1, 2, 3], hyp, rot, trans, mask, 3.0)
    assert (out is not None) or warp_w != 0.0  # the lens's own shape refits
    if warp_w == 0.0:
        np.testing.assert_allclose(out[0].principal_point_px, [499.5, 399.5], atol=0.5)


def test_refit_covers_a_family_of_another_warp():
    """``_to_refit``: the best zoomed hypothesis, then the best of another warp (the
    pinhole ranked third behind two families of warp 0 is refitted), else the second."""
    from gtsam_sphere.estimation.initialize import _family, _to_refit

    pp = np.array([999.5, 999.5])
    stereo, equi, pin = (_family(m, 100.0, pp) for m in ("stereographic", "equidistant", "pinhole"))
    zoomed = [(510.0, stereo, 1.0), (524.0, equi, 1.0), (560.0, pin, 1.0)]
    assert [z[1] for z in _to_refit(zoomed)] == [stereo, pin]
    assert [z[1] for z in _to_refit(zoomed[:2])] == [stereo, equi]
    fov = _family("fov", 100.0, pp)
    assert [z[1] for z in _to_refit([(1.0, pin, 1.0), (2.0, fov, 1.0), (3.0, stereo, 1.0)])] == [
        pin,
        fov,
    ]
    same = [(1.0, stereo, 1.0), (2.0, equi, 1.0), (3.0, _family("equisolid", 90.0, pp), 1.0)]
    assert [z[1] for z in _to_refit(same)] == [stereo, equi]


@pytest.mark.slow  # a full initialisation of a 3D-object set (CI runs it)
def test_a_lens_no_family_matches_is_tried_with_other_warps():
    """Seed 4 case 05 of the lens zoo: a 150 deg pinhole with strong Brown terms in a
    circle of 200 px (f = 15 px; 65-75 deg of incidence fill 168 px of the radius), on a
    3D object. No family matches it: the best refit left 58 % of the observations
    consistent and the calibration failed. Re-expressed with other warps, the lens
    explains over 85 % of them, around the right principal point."""
    from gtsam_sphere.estimation.calibrate import (
        initialise,
        resolve_control_sigma,
        with_control_sigma,
    )
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import SimulationOptions, simulate_room

    options = SimulationOptions(
        lens="pinhole",
        fov_deg=150.0,
        width=1280,
        height=800,
        circle_radius_px=200.0,
        lens_options={"k1": -0.1, "k2": 0.02, "cx": 767.5, "cy": 447.5},
        n_images=20,
        n_targets=370,
        n_checkpoints=191,
        seed=4005,
        scene="object3d",
    )
    dataset = parse_dataset(simulate_room(options).dataset)
    dataset = with_control_sigma(dataset, resolve_control_sigma(dataset, None), lambda _: None)
    lines = []
    init = initialise(dataset, 0, lines.append)
    assert any("trying the lens with other warps" in ln for ln in lines), lines
    assert init.inlier_mask.mean() > 0.85, lines
    assert np.hypot(*(np.asarray(init.principal_point_px) - [767.5, 447.5])) < 10.0, lines


def test_another_warp_replaces_the_lens_only_with_a_clear_gain(monkeypatch):
    """``_other_warps`` keeps the chosen lens unless another warp explains
    ``_OTHER_WARP_GAIN`` of the observations more: seed 9 case 05 of the zoo swapped
    its lens on a re-posing gain of 6 of 1,668 (0.4 %) and then failed."""
    import gtsam_sphere.estimation.initialize as ini

    n_obs, n_kept = 1000, 600
    lens = ini._family("stereographic", 150.0, np.array([640.0, 400.0]))
    rng = np.random.default_rng(0)
    points = rng.normal(size=(n_obs, 3)) + [0.0, 0.0, 4.0]
    problem = ini._Problem(
        rng.uniform(0, 800, size=(n_obs, 2)),
        np.repeat(np.arange(10), n_obs // 10),
        np.arange(n_obs),
        points,
        10,
    )
    rot = np.broadcast_to(np.eye(3), (10, 3, 3)).copy()
    mask = np.zeros(n_obs, bool)
    mask[:n_kept] = True
    posed = (rot, np.zeros((10, 3)), np.ones(10, bool), mask, {}, lens)

    def fake_pose_all(problem, images, hyp, thr, seeds, min_inliers):
        gain = gains[round(hyp.warp_w, 1)]
        m = np.zeros(n_obs, bool)
        m[: n_kept + gain] = True
        return rot, np.zeros((10, 3)), np.ones(10, bool), m, {}, hyp

    monkeypatch.setattr(ini, "_pose_all", fake_pose_all)
    monkeypatch.setattr(ini, "_final_refit", lambda *args: args[-2])
    lines = []
    margin = int(np.ceil(ini._OTHER_WARP_GAIN * n_obs))
    gains = {w: margin - 1 for w in ini._OTHER_WARPS}
    kept, others = ini._other_warps(
        problem, np.arange(10), 4.0, np.arange(10), 6, posed, lines.append
    )
    assert kept is posed, lines
    assert "keeping the lens" in lines[-1]
    # the other warps are the alternatives, most consistent first
    assert [round(o[5].warp_w, 1) for o in others] == list(ini._OTHER_WARPS)
    gains[-1.0] = margin
    swapped, others = ini._other_warps(
        problem, np.arange(10), 4.0, np.arange(10), 6, posed, lines.append
    )
    assert swapped[5].warp_w == pytest.approx(-1.0) and swapped[3].sum() == n_kept + margin
    assert others[0] is posed and all(o is not swapped for o in others)
    # a warp that explains the data (85 %), then one that falls away from it by the margin:
    # the rest are not tried (zoo seed 10 case 05: 3 s of 9 s, the same lens)
    tried = []
    gains.update({-1.6: 250, -1.0: 250 - margin - 1, -0.5: 300})
    monkeypatch.setattr(
        ini, "_final_refit", lambda *args: tried.append(round(args[2].warp_w, 1)) or args[-2]
    )
    peak, others = ini._other_warps(
        problem, np.arange(10), 4.0, np.arange(10), 6, posed, lines.append
    )
    assert tried == [-1.6, -1.0], lines
    assert peak[5].warp_w == pytest.approx(-1.6) and any("not tried" in ln for ln in lines)
    # falling by less than the margin, or below the 80 % that explain the data: on
    tried.clear()
    gains.update({w: 250 for w in ini._OTHER_WARPS})
    gains[-1.0] = 250 - margin
    ini._other_warps(problem, np.arange(10), 4.0, np.arange(10), 6, posed, lines.append)
    assert tried == list(ini._OTHER_WARPS)
    tried.clear()
    gains.update({w: 0 for w in ini._OTHER_WARPS})
    gains[-1.6] = 150
    ini._other_warps(problem, np.arange(10), 4.0, np.arange(10), 6, posed, lines.append)
    assert tried == list(ini._OTHER_WARPS)


def _stress_options(**kw):
    """A zoo stress draw's simulation options (``bench_lens_zoo --stress``), rebuilt."""
    from gtsam_sphere.simulate import SimulationOptions

    base = dict(
        n_targets=370,
        tilt_deg=45.0,
        error_field_terms=6,
        n_checkpoints=191,
        min_targets_per_image=8,
        preferred_targets_per_image=20,
    )
    return SimulationOptions(**{**base, **kw})


def test_disc_whose_outermost_observations_roughen_the_hull_is_still_a_disc():
    """Zoo stress 219 s33: a 295 deg field-of-view lens (circle r = 252 px, principal
    point 9 % and 5 % off centre) on a 3D object. The hull of every observation is a
    disc; without its outermost 0.5 % it was not (found no disc, only the image centre
    was tried, f came out 53 % off: 22x the oracle's 3D error, not trusted)."""
    from gtsam_sphere.simulate import simulate_room

    sim = simulate_room(
        _stress_options(
            lens="fov",
            fov_deg=295.0,
            width=1280,
            height=720,
            circle_radius_px=252.0,
            lens_options=dict(
                omega=2.2,
                a1=-0.013658,
                a2=0.002348,
                p1=-0.000472,
                p2=0.000115,
                cx=753.42,
                cy=398.38,
            ),
            pupil_shift_m=0.0022,
            error_field_px=1.6,
            n_images=40,
            noise_px=0.5,
            target_sigma_m=0.0005,
            sigma_mode="free",
            seed=554590497,
            scene="object3d",
        )
    )
    uv = np.array([ob["uv"] for im in sim.dataset["images"] for ob in im["observations"]])
    disc = observed_disc(uv, 1280, 720)
    assert disc is not None
    assert np.hypot(*(disc[0] - [753.42, 398.38])) < 10.0, disc
    assert abs(disc[1] - 252.0) < 15.0, disc


@pytest.mark.slow  # a full initialisation with the folded lens's rescue (CI runs it)
def test_folded_lens_is_searched_in_focal_scale_and_principal_point_together():
    """Zoo stress 220 s15: a 327 deg orthographic (sphere) lens, circle r = 384 px cropped
    by a 752x480 sensor, principal point 6 % and 8 % off centre, a free room of 10
    images. The folded lens was found at f 7 % and the principal point 14 px off, one
    after the other: 40 % of the observations consistent and the dataset refused."""
    from gtsam_sphere.simulate import simulate_room

    sim = simulate_room(
        _stress_options(
            lens="sphere",
            fov_deg=327.0,
            width=752,
            height=480,
            circle_radius_px=384.0,
            lens_options=dict(cx=328.876, cy=200.14),
            n_images=10,
            noise_px=0.5,
            target_sigma_m=0.01,
            sigma_mode="free",
            seed=821145187,
            scene="room",
        )
    )
    _, res, messages = initialise_simulation(sim)
    assert res.lens.folded, res.lens.describe()
    assert abs(res.lens.f_px / 384.0 - 1) < 0.02, res.lens.describe()
    assert np.hypot(*(res.principal_point_px - [328.876, 200.14])) < 4.0, messages
    assert res.inlier_mask.mean() > 0.9


@pytest.mark.slow  # an initialisation of a 10-image board, ~3 s
def test_the_second_refit_starts_without_a_principal_point_grid(monkeypatch):
    """Zoo stress seed 227 s20 (`--defects`): a 219 deg stereographic board of 10 images,
    1.5 px noise and 5 % blunders, refits two hypotheses. Only the first (or a folded
    one) searches a principal point grid: the second refit starts from the first refit's
    principal point (or its own) and moves it anyway; a grid there changed no result of
    zoo seed 0 or stress seed 227 and cost up to 5 s of 10. The lens still lands within
    a few pixels of the true principal point."""
    import gtsam_sphere.estimation.initialize as ini
    from gtsam_sphere.estimation.calibrate import initialise
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    options = _stress_options(
        lens="stereographic",
        fov_deg=219.0,
        width=640,
        height=480,
        circle_radius_px=384.0,
        lens_options={"a1": -0.029471, "a2": 7e-06, "p1": 2.2e-05, "p2": 3.2e-05,
                      "cx": 365.58, "cy": 268.78},
        n_images=10,
        noise_px=1.5,
        target_sigma_m=0.0005,
        sigma_mode="free",
        blunder_rate=0.05,
        seed=820398270,
        scene="board",
    )  # fmt: skip
    dataset = parse_dataset(simulate_room(options).dataset)
    searched, refitted = [], []
    search, refit = ini._pp_search, ini._refit

    def counted_search(*args, **kw):
        searched.append(args[3].mapping)
        return search(*args, **kw)

    def counted_refit(*args, **kw):
        refitted.append(args[3].mapping)
        return refit(*args, **kw)

    monkeypatch.setattr(ini, "_pp_search", counted_search)
    monkeypatch.setattr(ini, "_refit", counted_refit)
    lines = []
    init = initialise(dataset, 0, lines.append)
    assert len(refitted) == 2, lines
    assert len(searched) == 1, lines
    assert np.hypot(*(np.asarray(init.principal_point_px) - [365.58, 268.78])) < 5.0, lines
