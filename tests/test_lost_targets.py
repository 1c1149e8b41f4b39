"""Free targets whose second ray is a blunder (estimation.calibrate.targets_lost_to_outliers)
and the trimmed S-transform of a free network (core.geometry.fit_similarity_trimmed).

Found on zoo stress 214 s32 (a free room of 8 images, 5 % blunders): six targets seen
in two images, one ray a blunder, drifted 0.5-6 km along the other; the least-squares
S-transform onto the approximate coordinates then shrank the whole network 2000 times,
and the calibration was trusted."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import dataset_doc, small_free_room, three_view_problem

from gtsam_sphere.core.geometry import (
    MISFIT_LIMIT,
    fit_similarity,
    fit_similarity_trimmed,
)
from gtsam_sphere.estimation.calibrate import (
    LOST_TO_OUTLIERS_REASON,
    targets_lost_to_outliers,
)
from gtsam_sphere.io.dataset import parse_dataset


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_trimmed_similarity_ignores_points_that_flew_off():
    rng = np.random.default_rng(3)
    dst = rng.uniform([0, 0, 0], [7, 6, 3], size=(200, 3))
    R, scale, t = _rotation(rng), 0.37, np.array([1.0, -2.0, 0.5])
    src = (dst - t) @ R / scale  # dst = scale * R @ src + t exactly
    src[:6] += rng.normal(size=(6, 3)) * 3000.0  # six targets kilometres away
    plain = fit_similarity(src, dst)
    assert plain.scale < 0.01 * scale  # what the least-squares fit does
    sim, kept = fit_similarity_trimmed(src, dst)
    assert kept.tolist() == [False] * 6 + [True] * 194
    assert sim.scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(sim.R, R, atol=1e-9)
    np.testing.assert_allclose(sim.apply(src[6:]), dst[6:], atol=1e-9)


def test_trimmed_similarity_drops_gross_misfits_and_keeps_the_noise():
    rng = np.random.default_rng(4)
    dst = rng.uniform(-2, 2, size=(100, 3))
    src = dst + rng.normal(scale=0.01, size=dst.shape)  # approximate coordinates: 1 cm
    src[10] += [0.5, 0.0, 0.0]  # a misfit 50 sigma, not far enough to be a spread outlier
    sim, kept = fit_similarity_trimmed(src, dst)
    assert not kept[10]
    misfit = np.linalg.norm(sim.apply(src) - dst, axis=1)
    assert np.all(misfit[kept] <= MISFIT_LIMIT * np.median(misfit[kept]))
    assert kept.sum() >= 95  # 1 cm Gaussian noise is not trimmed away
    assert sim.scale == pytest.approx(1.0, abs=0.01)


def test_trimmed_similarity_equals_least_squares_on_clean_points():
    rng = np.random.default_rng(5)
    dst = rng.normal(size=(30, 3))
    src = dst + rng.normal(scale=1e-3, size=dst.shape)
    sim, kept = fit_similarity_trimmed(src, dst)
    ref = fit_similarity(src[kept], dst[kept])
    assert kept.sum() >= 29
    assert sim.scale == pytest.approx(ref.scale, rel=1e-12)


@pytest.mark.parametrize("shape", [(5, 2), (5,), (2, 3)])
def test_trimmed_similarity_rejects_bad_shapes(shape):
    bad = np.zeros(shape)
    with pytest.raises(ValueError, match=r"shape|at least 3"):
        fit_similarity_trimmed(bad, bad)


def _two_view_doc(sigma=None):
    """Two images see T0-T5; observation 0 of B (of T0) will be the blunder."""
    targets = []
    for k in range(6):
        t = {"id": f"T{k}", "xyz": [float(k), 0.5 * k, 3.0]}
        if sigma is not None:
            t["sigma"] = sigma
        targets.append(t)
    obs = [{"target": f"T{k}", "uv": [100.0 + 20 * k, 200.0 + 3 * k]} for k in range(6)]
    return dataset_doc(
        targets, [{"id": "A", "observations": obs}, {"id": "B", "observations": obs}]
    )


def test_a_free_target_whose_second_ray_is_an_outlier_is_lost():
    ds = parse_dataset(_two_view_doc())
    outlier = np.zeros(ds.n_observations, bool)
    blunder = np.flatnonzero((ds.obs_image == 1) & (ds.obs_target == 0))
    outlier[blunder] = True
    lost = targets_lost_to_outliers(ds, outlier)
    assert [ds.target_ids[j] for j in np.flatnonzero(lost)] == ["T0"]
    assert not targets_lost_to_outliers(ds, np.zeros(ds.n_observations, bool)).any()


@pytest.mark.parametrize("sigma", [0.0, 0.01])
def test_targets_with_a_sigma_are_never_lost(sigma):
    ds = parse_dataset(_two_view_doc(sigma))
    outlier = ds.obs_image == 1  # every ray of B an outlier
    assert not targets_lost_to_outliers(ds, outlier).any()


@pytest.mark.slow
def test_free_room_with_a_blunder_keeps_its_scale_and_lists_the_lost_target():
    """End to end: a free room where one target seen in two images gets a 300 px blunder
    in one of them. The target is listed as undetermined (not adjusted), the rest of the
    network keeps its size (camera centres within centimetres of the truth after the
    datum transform) and the file round-trips the list."""
    from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate

    sim = small_free_room(21)
    doc = sim.dataset
    seen: dict[str, list] = {}
    for im in doc["images"]:
        for ob in im["observations"]:
            seen.setdefault(ob["target"], []).append(ob)
    victim = next(t for t, obs in sorted(seen.items()) if len(obs) == 2)
    seen[victim][1]["uv"] = [seen[victim][1]["uv"][0] + 300.0, seen[victim][1]["uv"][1]]
    ds = parse_dataset(doc, "room.json")
    calib = calibrate(ds, CalibrationOptions())
    lost = calib.extra["undetermined_targets"]
    assert [e["id"] for e in lost] == [victim]
    assert lost[0]["reason"] == LOST_TO_OUTLIERS_REASON and lost[0]["n_observations"] == 2
    assert calib.statistics["n_targets_undetermined"] == 1
    assert victim not in calib.target_ids
    truth = {im["id"]: np.asarray(im["centre_world"]) for im in sim.truth["images"]}
    R, t = calib.cam_from_world_R, calib.cam_from_world_t
    centres = -np.einsum("kji,kj->ki", R, t)
    expected = np.array([truth[i] for i in calib.image_ids])
    # the datum is the approximate coordinates (1 cm noise): same size, same place
    assert np.max(np.linalg.norm(centres - expected, axis=1)) < 0.1
    doc_out = calib.to_dict()
    assert [e["id"] for e in doc_out["undetermined_targets"]] == [victim]
    precision = doc_out["target_precision"]
    assert precision["target"] == calib.target_ids
    assert np.all(np.isfinite(precision["intersection_sigma"]))
    assert np.all(np.asarray(precision["intersection_sigma"]) > 0)


def _bearing_jacobian(ray, f_px, d):
    """Jacobian (2, 3) of an ideal tangent-plane projection of a point at distance ``d``
    along ``ray`` (unit), ``f_px`` px per radian: rows span the plane normal to the ray."""
    ray = np.asarray(ray, float) / np.linalg.norm(ray)
    a = np.cross(ray, [0.0, 0.0, 1.0] if abs(ray[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(ray, a)
    return (f_px / d) * np.stack([a, b])


@pytest.mark.parametrize("angle_deg", [0.5, 5.0, 30.0, 90.0])
def test_intersection_sigma_of_two_rays_matches_the_closed_form(angle_deg):
    from gtsam_sphere.estimation.graph import intersection_sigma

    f_px, d, s_px = 500.0, 4.0, 0.7
    g = np.radians(angle_deg)
    rays = [[0.0, 0.0, 1.0], [np.sin(g), 0.0, np.cos(g)]]
    J = np.stack([_bearing_jacobian(r, f_px, d) for r in rays])
    out = intersection_sigma(J, np.array([0, 0]), np.full(2, 1 / s_px**2), np.array([np.nan]))
    assert out[0] == pytest.approx((d / f_px) * s_px / np.sqrt(1 - np.cos(g)), rel=1e-6)


def test_intersection_sigma_one_ray_prior_and_exact_targets():
    from gtsam_sphere.estimation.graph import intersection_sigma

    J = np.stack([_bearing_jacobian([0, 0, 1], 500.0, 4.0)] * 3)
    obs_target = np.array([0, 1, 2])
    sigma = np.array([np.nan, 0.01, 0.0, np.nan])  # free, prior, exact, unobserved
    J[2] = 0.0  # exact targets have no Jacobian (not variables)
    out = intersection_sigma(J, obs_target, np.ones(3), sigma)
    assert np.isposinf(out[0])  # one ray: no depth
    assert out[1] == pytest.approx(0.01)  # the prior holds the depth
    assert np.isnan(out[2]) and np.isnan(out[3])


def test_weak_targets_are_measured_against_the_network_extent():
    from gtsam_sphere.estimation.calibrate import WEAK_TARGET_FRACTION, weak_targets

    rng = np.random.default_rng(0)
    xyz = rng.uniform([0, 0, 0], [7, 6, 3], size=(500, 3))
    extent = np.linalg.norm(np.percentile(xyz, 95, 0) - np.percentile(xyz, 5, 0))
    sig = np.full(500, 0.01)
    sig[:3] = [np.inf, 2 * WEAK_TARGET_FRACTION * extent, np.nan]
    limit, weak = weak_targets(xyz, sig)
    assert limit == pytest.approx(WEAK_TARGET_FRACTION * extent)
    assert weak.tolist()[:3] == [True, True, False] and weak.sum() == 2


def test_rig_joint_adjustment_leaves_out_a_target_a_blunder_left_on_one_ray():
    """The joint rig graph applies the same rule: a free target kept in two images of the
    rig, one of its rays 200 px off, is not in the joint result's targets but listed;
    the free rig's S-transform keeps its scale (frames within millimetres)."""
    from test_rig_joint import _in_model_rig

    from gtsam_sphere.estimation.rig_joint import adjust_rig_jointly

    rig, truth, calibs, ext0, frames0, xyz0 = _in_model_rig(0, n_surveyed=0)
    victim = "T007"
    kept = 0
    for cal in calibs.values():
        obs = cal.extra["observations"]
        keep = []
        for k, tg in enumerate(obs["target"]):
            if tg != victim:
                keep.append(k)
            elif kept < 2:
                keep.append(k)
                kept += 1
                if kept == 2:
                    obs["uv_px"][k] = obs["uv_px"][k] + [200.0, 0.0]
        cal.extra["observations"] = {
            "image": [obs["image"][k] for k in keep],
            "target": [obs["target"][k] for k in keep],
            "uv_px": np.asarray(obs["uv_px"])[keep],
        }
    assert kept == 2
    jr = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    assert jr.undetermined_targets == [victim]
    assert victim not in jr.target_xyz and len(jr.target_xyz) > 100
    assert any("not determined" in note for note in jr.notes)
    # free rig: S-transformed onto the approximate coordinates (2 cm noise)
    for f, (R, t) in jr.rig_from_world.items():
        R0, t0 = truth["frames"][f]
        assert np.linalg.norm(-R.T @ t - (-R0.T @ t0)) < 0.02


def _target_rmse(jr, truth):
    ids = sorted(jr.target_xyz)
    got = np.array([jr.target_xyz[i] for i in ids])
    want = np.array([truth["xyz"][int(i[1:])] for i in ids])
    return float(np.sqrt(np.mean(np.sum((got - want) ** 2, axis=1))))


def test_rig_joint_adjustment_ends_with_cauchy_when_blunders_remain():
    """3 % of the rig's observations 100-300 px off: Huber alone keeps part of their
    pull on the targets; the joint adjustment's last stage is then Cauchy's (as a single
    camera's), and the targets come back to within 1.1x the blunder-free RMSE (Huber
    alone: 1.36x)."""
    from test_rig_joint import _in_model_rig

    from gtsam_sphere.estimation.rig_joint import adjust_rig_jointly

    rig, truth, calibs, ext0, frames0, xyz0 = _in_model_rig(0)
    clean = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    assert clean.loss == "huber"
    rng = np.random.default_rng(7)
    for cal in calibs.values():
        uv = np.array(cal.extra["observations"]["uv_px"], float)
        hit = rng.random(len(uv)) < 0.03
        angle = rng.uniform(0, 2 * np.pi, hit.sum())
        uv[hit] += rng.uniform(100, 300, hit.sum())[:, None] * np.c_[np.cos(angle), np.sin(angle)]
        cal.extra["observations"] = dict(cal.extra["observations"], uv_px=uv)
    jr = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    assert jr.loss == "cauchy"
    assert _target_rmse(jr, truth) < 1.1 * _target_rmse(clean, truth)


def test_rays_that_meet_beyond_the_network_do_not_fix_a_target():
    from gtsam_sphere.estimation.calibrate import targets_extent, unfixed_targets

    rng = np.random.default_rng(8)
    xyz = rng.uniform([0, 0, 0], [7, 6, 3], size=(50, 3))
    xyz[0] = [53_000.0, 0.0, 0.0]  # flew off: the extent ignores it
    extent = targets_extent(xyz)
    assert 6.0 < extent < 10.0
    sigma = np.full(50, 0.01)
    sigma[0] = 4000.0  # rays meeting 53 km away
    sigma[1] = np.inf  # one ray
    sigma[2] = 0.5 * extent  # weak, but fixed
    sigma[3] = np.nan  # exact
    judge = np.ones(50, bool)
    judge[4] = False  # a target with a sigma is not judged
    sigma[4] = 1e6
    out = unfixed_targets(sigma, judge, extent)
    assert np.flatnonzero(out).tolist() == [0, 1]


def test_a_stage_holds_out_a_free_target_only_a_blunder_ties_to_a_second_image():
    """``held_out_targets`` (zoo stress 3201 s32): T0, seen in images 0 and 1 with a
    200 px blunder in 1, is held out; T1, seen in three images with one blunder, and
    T2, seen in two images with a sigma, are not."""
    from gtsam_sphere.estimation.calibrate import held_out_targets

    gross = {0: ((0, 1), (1,)), 1: ((0, 1, 2), (2,)), 2: ((0, 1), (1,))}
    surveyed = {2: 0.01, 10: 0.01, 20: 0.01, 30: 0.01}  # a datum of targets with a sigma
    problem, values = three_view_problem(gross, surveyed)
    hold = held_out_targets(problem, values)
    assert np.unique(problem.obs_target[hold]).tolist() == [0]
    assert hold.sum() == 2  # both of its observations
    # a scale that makes the blunder look ordinary: nothing is held out
    problem_wide, values = three_view_problem(gross, surveyed, noise_px=30.0)
    assert not held_out_targets(problem_wide, values).any()


def test_a_held_out_target_keeps_its_place_on_its_good_ray():
    """A robust stage with T0 held out: the rest is adjusted, T0 follows image 0's pose
    and its ray there, at the depth it had, and the stage converges."""
    import gtsam

    from gtsam_sphere.estimation.calibrate import _robust_stage
    from gtsam_sphere.estimation.graph import point_key, pose_key
    from gtsam_sphere.estimation.optimize import OptimizerOptions

    problem, truth = three_view_problem({0: ((0, 1), (1,))})
    start = gtsam.Values(truth)
    start.update(pose_key(2), truth.atPose3(pose_key(2)).retract(np.full(6, 0.01)))
    lines: list[str] = []
    out = _robust_stage(problem, problem.build(), start, OptimizerOptions(), None, lines.append, "")
    assert out.converged, out.describe()
    assert any("1 targets without a sigma" in ln and "held out" in ln for ln in lines)
    before = start.atPose3(pose_key(0)).transformTo(start.atPoint3(point_key(0)))
    after = out.values.atPose3(pose_key(0)).transformTo(out.values.atPoint3(point_key(0)))
    # on the ray of its observation in image 0 (to the noise's 0.01 px), at the same depth
    assert np.linalg.norm(after) == pytest.approx(np.linalg.norm(before), rel=1e-6)
    good = np.flatnonzero((problem.obs_target == 0) & (problem.obs_image == 0))
    e_px = problem.residuals_px(out.values)[good]
    assert np.linalg.norm(e_px) < 1e-6
    moved = start.atPose3(pose_key(0)).localCoordinates(out.values.atPose3(pose_key(0)))
    assert np.abs(moved).max() > 1e-6  # the pose it follows was adjusted
