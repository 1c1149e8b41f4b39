"""A frozen calibration in users' GTSAM graphs: pixel factors, bearings, the map paths."""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative21, numericalDerivative22
from helpers import perturbed_values, scene_pose

from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.core.least_squares import LMStatus
from gtsam_sphere.estimation.external import (
    ProjectionBlocks,
    bearing_sigma_rad,
    bearing_sqrt_information,
    bearings,
    levenberg_marquardt,
    make_bearing_factors,
    make_projection_block,
    make_projection_factor,
    model_scale_px_per_rad,
)
from gtsam_sphere.estimation.graph import point_key, pose_key
from gtsam_sphere.estimation.optimize import (
    OptimizerOptions,
    lm_driver,
    make_ordering,
    optimize,
)
from gtsam_sphere.io.calibration import Calibration
from gtsam_sphere.simulate.building import fisheye_camera, simulate_building

ROOT = Path(__file__).resolve().parents[1]
M = gtsam.noiseModel
HUBER = M.mEstimator.Huber.Create(1.0)


class _Field:
    """A smooth learned correction: ``predict(uv) -> (N, 2)`` px."""

    def predict(self, uv_px):
        uv = np.asarray(uv_px, float)
        return np.column_stack(
            [0.8 * np.sin(uv[:, 1] / 150.0), 0.5 * np.cos(uv[:, 0] / 210.0 + 0.3)]
        )


def _cameras():
    """The two mappings, with Brown terms and a learned correction on the measurement side."""
    sphere = SphereCamera(
        width=1000,
        height=1000,
        xp=500.3,
        yp=498.2,
        c=400.0,
        brown={"k1": 0.01, "p1": 1e-3},
        correction=_Field(),
    )
    radial = fisheye_camera(200.0)
    radial.brown = {"p2": 2e-4, "a1": 1e-3}
    radial.correction = _Field()
    return {"sphere": sphere, "radial": radial}


CAMERAS = _cameras()
DIRECTIONS = {
    "ordinary": [0.3, -0.2, 1.0],
    "optical axis": [0.0, 0.0, 1.0],
    "90 degrees": [1.0, 0.4, 0.0],
    "behind camera": [0.2, -0.5, -1.0],
}
NOISE = {
    "isotropic": M.Isotropic.Sigma(2, 0.5),
    "diagonal": M.Diagonal.Sigmas(np.array([0.5, 0.8])),
    "huber": M.Robust.Create(HUBER, M.Isotropic.Sigma(2, 0.5)),
    "cauchy-full": M.Robust.Create(
        M.mEstimator.Cauchy.Create(1.5),
        M.Gaussian.SqrtInformation(np.array([[2.0, 0.3], [0.0, 1.5]])),
    ),
    "tukey": M.Robust.Create(M.mEstimator.Tukey.Create(4.685), M.Isotropic.Sigma(2, 0.5)),
    "geman-mcclure": M.Robust.Create(
        M.mEstimator.GemanMcClure.Create(1.0), M.Isotropic.Sigma(2, 0.5)
    ),
    "welsch (per observation)": M.Robust.Create(
        M.mEstimator.Welsch.Create(2.0), M.Isotropic.Sigma(2, 0.5)
    ),
}


def _one(camera, direction, seed=0, offset=(1.5, -2.0)):
    """A pose and a point seen along ``direction``; the pixel is off by ``offset`` px."""
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose3(gtsam.Rot3.Rodrigues(*rng.normal(size=3)), rng.normal(size=3))
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    point = pose.transformFrom(2.5 * d)
    uv = camera.project(d[None])[0] + np.asarray(offset)
    values = gtsam.Values()
    values.insert(pose_key(0), pose)
    values.insert(point_key(0), point)
    return pose, point, uv, values


# ----------------------------------------------------------------------------- Jacobians


@pytest.mark.parametrize("direction", list(DIRECTIONS))
@pytest.mark.parametrize("mapping", list(CAMERAS))
def test_projection_factor_jacobians_match_numerical(mapping, direction):
    camera = CAMERAS[mapping]
    pose, point, uv, values = _one(camera, DIRECTIONS[direction])
    factor = make_projection_factor(camera, uv, pose_key(0), point_key(0), NOISE["isotropic"])

    def err(P, X):
        v = gtsam.Values()
        v.insert(pose_key(0), P)
        v.insert(point_key(0), X)
        return factor.whitenedError(v)

    A = factor.linearize(values).jacobian()[0]
    n_pose = numericalDerivative21(err, pose, point, delta=1e-6)
    n_point = numericalDerivative22(err, pose, point, delta=1e-6)
    scale = np.abs(A).max()
    np.testing.assert_allclose(A[:, :6], n_pose, atol=1e-6 * scale)
    np.testing.assert_allclose(A[:, 6:], n_point, atol=1e-6 * scale)
    # residual: corrected measurement minus the model, px, in the adjustment's metric
    pc = pose.transformTo(point)
    e = camera.ideal_from_pixels(uv)[0] - camera.ideal_from_points(pc[None])[0]
    M_ = camera.measurement_metric(uv)[0]
    np.testing.assert_allclose(factor.unwhitenedError(values), M_ @ e, atol=1e-9)


def test_frozen_residual_is_in_raw_pixels_under_a_strong_affinity():
    """The frozen factor weighs as the adjustment: raw pixels, not the affinity's metric.

    With ``a1 = 0.3`` the corrected coordinates shrink x by 0.7; a 0.5 px offset of
    the raw pixel must come back as 0.5 px (to first order), so that the calibration's
    ``sigma_px`` means the same in a user's graph.
    """
    camera = _affine_radial()
    offset = np.array([0.5, -0.4])
    pose, point, uv, values = _one(camera, [0.4, -0.3, 1.0], offset=offset)
    factor = make_projection_factor(camera, uv, pose_key(0), point_key(0), NOISE["isotropic"])
    np.testing.assert_allclose(factor.unwhitenedError(values), offset, atol=5e-3)
    old = (
        camera.ideal_from_pixels(uv)[0] - camera.ideal_from_points(pose.transformTo(point)[None])[0]
    )
    assert abs(old[0] - offset[0]) > 0.1  # the corrected coordinates are off by ~30 %
    block = ProjectionBlocks(camera, uv, [pose_key(0)], [point_key(0)], NOISE["isotropic"])
    np.testing.assert_allclose(
        block.residuals_px(values)[0], factor.unwhitenedError(values), atol=1e-12
    )


@pytest.mark.parametrize("direction", list(DIRECTIONS))
@pytest.mark.parametrize("mapping", list(CAMERAS))
def test_block_equals_gtsam_noise_model(mapping, direction):
    """The vectorised block whitens and weights per observation exactly like GTSAM does
    with the same noise model on single-observation factors (cost and normal equations)."""
    camera = CAMERAS[mapping]
    rng = np.random.default_rng(4)
    pose, point, _, values = _one(camera, DIRECTIONS[direction])
    # several images of one landmark, pixels off by 0.3 to 6 px (some in the robust tails)
    uvs, pks = [], []
    for i in range(1, 5):
        p = pose.compose(
            gtsam.Pose3(
                gtsam.Rot3.Rodrigues(*(0.05 * rng.normal(size=3))), 0.1 * rng.normal(size=3)
            )
        )
        values.insert(pose_key(i), p)
        d = p.transformTo(point)
        uvs.append(camera.project(d[None])[0] + rng.normal(scale=2.0, size=2))
        pks.append(pose_key(i))
    uv = np.array(uvs)
    for name, noise in NOISE.items():
        block = gtsam.NonlinearFactorGraph()
        block.add(make_projection_block(camera, uv, pks, point_key(0), noise))
        single = gtsam.NonlinearFactorGraph()
        for k in range(len(uv)):
            single.add(make_projection_factor(camera, uv[k], pks[k], point_key(0), noise))
        assert block.error(values) == pytest.approx(single.error(values), rel=1e-10), name
        Hb, gb = block.linearize(values).hessian()
        Hs, gs = single.linearize(values).hessian()
        np.testing.assert_allclose(Hb, Hs, rtol=1e-9, atol=1e-9 * np.abs(Hs).max(), err_msg=name)
        np.testing.assert_allclose(gb, gs, rtol=1e-9, atol=1e-9 * np.abs(gs).max(), err_msg=name)


def test_cache_never_serves_stale_results():
    """Alternating between two estimates, partial Values and every evaluation mode: the
    shared cache of ProjectionBlocks always equals independent single-observation factors."""
    scene = simulate_building(n_images=30, obs_per_image=25, images_per_room=15, seed=5)
    pk = np.array([pose_key(i) for i in scene.obs_image], np.uint64)
    lk = np.array([point_key(j) for j in scene.obs_point], np.uint64)
    noise = M.Robust.Create(M.mEstimator.Huber.Create(2.0), M.Isotropic.Sigma(2, 0.5))
    blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, noise, max_obs=3)
    graph = gtsam.NonlinearFactorGraph()
    for f in blocks.factors():
        graph.add(f)
    single = gtsam.NonlinearFactorGraph()
    for k in range(scene.n_observations):
        single.add(make_projection_factor(scene.camera, scene.uv_px[k], pk[k], lk[k], noise))
    estimates = [perturbed_values(scene, seed) for seed in (1, 2)]
    for values in estimates + estimates[::-1]:
        assert graph.error(values) == pytest.approx(single.error(values), rel=1e-12)
        np.testing.assert_allclose(
            graph.linearize(values).hessian()[1],
            single.linearize(values).hessian()[1],
            rtol=1e-8,
            atol=1e-6,
        )
        # one variable nudged in its last digits: only its blocks may change
        nudged = gtsam.Values(values)
        nudged.update(point_key(0), values.atPoint3(point_key(0)) * (1 + 1e-15) + 1e-12)
        assert graph.error(nudged) == pytest.approx(single.error(nudged), rel=1e-12)
    # the same through the trusted passes of levenberg_marquardt (one step)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(1)
    out, info = levenberg_marquardt(graph, estimates[0], params)
    assert info["error"] == pytest.approx(single.error(out), rel=1e-12)
    assert blocks.stats["hits"] > 0 and blocks.stats["full_passes"] > 0


def test_any_grouping_linearises_like_single_factors():
    """Blocks mixing landmarks, seeing a pose twice, and blocks sharing one sparsity pattern
    (they share the zero-padded C++ Jacobian they are handed over in): cost, gradient and
    normal equations equal those of single-observation factors, in GTSAM's linearisation
    and in the passes of levenberg_marquardt, in any order of evaluation."""
    scene = simulate_building(n_images=24, obs_per_image=30, images_per_room=12, seed=8)
    pk = np.array([pose_key(i) for i in scene.obs_image], np.uint64)
    lk = np.array([point_key(j) for j in scene.obs_point], np.uint64)
    noise = M.Robust.Create(M.mEstimator.Huber.Create(1.5), M.Isotropic.Sigma(2, 0.5))
    rng = np.random.default_rng(3)
    order = rng.permutation(scene.n_observations)
    cuts = np.cumsum(rng.integers(1, 7, size=scene.n_observations))
    groups = [g for g in np.split(order, cuts[cuts < scene.n_observations]) if len(g)]
    # the same image twice in one block (observations of two landmarks)
    two = [np.flatnonzero(scene.obs_image == i)[:2] for i in (3, 7)]
    groups = [np.setdiff1d(g, np.concatenate(two)) for g in groups] + two
    groups = [g for g in groups if len(g)]
    blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, noise, groups=groups)
    engine = blocks.engine
    keys = [engine.block_keys(g) for g in range(engine.n_blocks)]  # poses, landmarks
    patterns = [b.shape for b in engine._blocks]
    assert any(len(k[1]) > 1 for k in keys)  # several landmarks in a block
    assert any(len(k[0]) < len(g) for k, g in zip(keys, blocks.groups))  # a pose seen twice
    assert len(set(patterns)) < len(patterns)  # shared patterns
    graph = gtsam.NonlinearFactorGraph()
    factors = blocks.factors()
    for f in factors:
        graph.add(f)
    single = gtsam.NonlinearFactorGraph()
    for k in range(scene.n_observations):
        single.add(make_projection_factor(scene.camera, scene.uv_px[k], pk[k], lk[k], noise))
    for seed in (1, 2, 1):
        values = perturbed_values(scene, seed)
        Hs, gs = single.linearize(values).hessian()
        Hb, gb = graph.linearize(values).hessian()
        np.testing.assert_allclose(Hb, Hs, rtol=1e-9, atol=1e-9 * np.abs(Hs).max())
        np.testing.assert_allclose(gb, gs, rtol=1e-9, atol=1e-9 * np.abs(gs).max())
        # factor by factor, out of order: each hands over its own Jacobian blocks
        lin_single = single.linearize(values)
        for g in (len(factors) - 1, 0, len(factors) // 2, len(factors) - 2):
            ordering = gtsam.Ordering()
            for key in factors[g].keys():
                ordering.push_back(key)
            mine = gtsam.GaussianFactorGraph()
            mine.push_back(factors[g].linearize(values))
            ref = gtsam.GaussianFactorGraph()
            for k in blocks.groups[g]:
                ref.push_back(lin_single.at(int(k)))
            A, B = mine.augmentedHessian(ordering), ref.augmentedHessian(ordering)
            np.testing.assert_allclose(A, B, rtol=1e-9, atol=1e-9 * np.abs(B).max())
    # a datum (a pose and a landmark under priors, in both graphs): without one the
    # normal equations are singular, and the solver's handling of the gauge (Cholesky
    # refusing them, or QR steps of rounding / lambda along it), not the factors,
    # would set the last digits compared below
    start = perturbed_values(scene, 4)
    first_pose, first_point = int(pk[0]), int(lk[0])
    for g in (graph, single):
        g.add(
            gtsam.PriorFactorPose3(
                first_pose, start.atPose3(first_pose), M.Isotropic.Sigma(6, 1e-3)
            )
        )
        g.add(
            gtsam.PriorFactorPoint3(
                first_point, start.atPoint3(first_point), M.Isotropic.Sigma(3, 1e-2)
            )
        )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(2)
    out, info = levenberg_marquardt(graph, start, params)
    ref, _ = levenberg_marquardt(single, perturbed_values(scene, 4), params)
    assert info["error"] == pytest.approx(single.error(out), rel=1e-12)
    assert info["error"] == pytest.approx(single.error(ref), rel=1e-9)


# ----------------------------------------------------------------------------- robust


def test_robust_downweights_an_injected_outlier():
    """Resection of one image with one gross observation (80 px): Huber lands on the
    outlier-free solution, L2 is pulled away; the outlier's weight is small."""
    scene = simulate_building(
        n_images=25, obs_per_image=60, images_per_room=25, seed=2, noise_px=0.3
    )
    sel = np.flatnonzero(scene.obs_image == 10)[:20]
    points = scene.obs_point[sel]
    truth = scene_pose(scene, 10)
    init = truth.retract(np.array([0.02, -0.01, 0.015, 0.05, -0.04, 0.03]))
    l2 = M.Isotropic.Sigma(2, 0.3)
    huber = M.Robust.Create(M.mEstimator.Huber.Create(2.45), l2)

    def resect(uv, noise):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(pose_key(10), init)
        for j in points:
            values.insert(point_key(j), scene.points_world[j])
            graph.add(gtsam.NonlinearEqualityPoint3(point_key(j), scene.points_world[j]))
        blocks = ProjectionBlocks(
            scene.camera, uv, pose_key(10), [point_key(j) for j in points], noise
        )
        for f in blocks.factors():
            graph.add(f)
        out = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        return out.atPose3(pose_key(10)), blocks.robust_weights(out)

    clean, _ = resect(scene.uv_px[sel], l2)
    uv = scene.uv_px[sel].copy()
    uv[0] += [64.0, -48.0]
    pose_l2, _ = resect(uv, l2)
    pose_huber, w = resect(uv, huber)
    off_l2 = np.linalg.norm(clean.localCoordinates(pose_l2))
    off_huber = np.linalg.norm(clean.localCoordinates(pose_huber))
    assert w[0] < 0.05 and np.all(w[1:] > 0.5)
    assert off_huber < 0.1 * off_l2
    assert np.linalg.norm(truth.localCoordinates(pose_huber)) < 5e-3


# ----------------------------------------------------------------------------- bearings


@pytest.mark.parametrize("mapping", list(CAMERAS))
def test_bearings_round_trip_with_project(mapping):
    camera = CAMERAS[mapping]
    rng = np.random.default_rng(7)
    limit = np.radians(150.0) if mapping == "sphere" else camera.max_alpha_rad() - 0.05
    alpha = rng.uniform(0.0, min(limit, np.radians(100.0)), 400)
    phi = rng.uniform(0, 2 * np.pi, 400)
    rays = np.column_stack(
        [np.sin(alpha) * np.cos(phi), np.sin(alpha) * np.sin(phi), np.cos(alpha)]
    )
    uv = camera.project(rays)
    hemisphere = np.sign(rays[:, 2])
    back = bearings(camera, uv, hemisphere)
    np.testing.assert_allclose(back, rays, atol=1e-7)
    np.testing.assert_allclose(camera.project(back), uv, atol=1e-6)
    calib = Calibration(
        "x", camera, [], np.zeros((0, 3, 3)), np.zeros((0, 3)), [], np.zeros((0, 3)), {}
    )
    units = calib.bearing(uv[:5], hemisphere[:5])
    assert all(isinstance(u, gtsam.Unit3) for u in units)
    np.testing.assert_allclose([u.point3() for u in units], rays[:5], atol=1e-7)
    with pytest.raises(ValueError, match="no ray"):
        calib.bearing(np.array([[camera.xp + 5 * camera.c, camera.yp]]))


def test_sphere_mapping_needs_the_hemisphere():
    """Past 90 degrees the sphere mapping is two-to-one: the same pixel, two rays."""
    camera = SphereCamera(width=1000, height=1000, xp=500.0, yp=500.0, c=400.0)
    ray = np.array([[0.6, 0.0, -0.8]])
    uv = camera.project(ray)
    np.testing.assert_allclose(camera.project(ray * [1, 1, -1]), uv)
    np.testing.assert_allclose(bearings(camera, uv, -1.0), ray, atol=1e-12)
    np.testing.assert_allclose(bearings(camera, uv, 1.0), ray * [1, 1, -1], atol=1e-12)


def test_bearing_noise_from_pixel_noise():
    c = 300.0
    equidistant = SphereCamera(width=1000, height=1000, xp=500.0, yp=500.0, c=c, radial={})
    sphere = SphereCamera(width=1000, height=1000, xp=500.0, yp=500.0, c=c)
    alpha = np.radians([0.0, 30.0, 60.0, 85.0])
    rays = np.column_stack([np.sin(alpha), 0 * alpha, np.cos(alpha)])
    # equidistant: radial c, tangential c alpha / sin(alpha); sphere: c cos(alpha) and c
    s = model_scale_px_per_rad(equidistant, rays)
    tang = c * np.where(alpha > 0, alpha / np.where(alpha > 0, np.sin(alpha), 1), 1.0)
    np.testing.assert_allclose(
        np.sort(s, 1), np.sort(np.column_stack([tang, 0 * alpha + c]), 1), rtol=1e-9
    )
    s = model_scale_px_per_rad(sphere, rays)
    np.testing.assert_allclose(s[:, 0] * s[:, 1], c * c * np.cos(alpha), rtol=1e-9)
    uv = equidistant.project(rays)
    sig = bearing_sigma_rad(equidistant, uv, 0.6)
    assert sig[0] == pytest.approx(0.6 / c)
    np.testing.assert_allclose(sig, 0.6 / np.sqrt(tang * c), rtol=1e-9)
    # an affinity stretches the pixel path's metric by 1 / (1 - a1) in x (on the axis)
    equidistant.brown = {"a1": 0.36}
    sig = bearing_sigma_rad(equidistant, equidistant.project(rays[:1]), 0.6)
    assert sig[0] == pytest.approx(0.6 * np.sqrt(1 - 0.36) / c)


def _affine_radial():
    camera = fisheye_camera(200.0)
    camera.brown = {"a1": 0.3, "a2": -0.05, "p1": 0.01, "p2": -0.02}
    return camera


@pytest.mark.parametrize("mapping", ["radial", "radial, strong affinity"])
def test_sqrt_information_reproduces_pixel_weighting(mapping):
    """GeneralSFMFactorSphericalCamera with bearing_sqrt_information: whitened error equals
    the pixel residual / sigma to first order, anisotropy included (fisheye at 80 deg), and
    with the frozen factor's metric under a strong affinity."""
    camera = CAMERAS["radial"] if mapping == "radial" else _affine_radial()
    rng = np.random.default_rng(3)
    for direction in ([0.1, 0.05, 1.0], [1.0, 0.3, 0.2], [0.5, -1.0, -0.4]):
        pose, point, uv, values = _one(camera, direction, offset=rng.normal(scale=0.5, size=2))
        R = bearing_sqrt_information(camera, uv[None], 0.5)[0]
        ray = bearings(camera, uv[None])[0]
        f = gtsam.GeneralSFMFactorSphericalCamera(
            gtsam.Unit3(ray), M.Gaussian.SqrtInformation(R), 1, 2
        )
        v = gtsam.Values()
        v.insert(1, gtsam.SphericalCamera(pose))
        v.insert(2, point)
        pixel = make_projection_factor(camera, uv, 1, 2, M.Isotropic.Sigma(2, 0.5))
        vp = gtsam.Values()
        vp.insert(1, pose)
        vp.insert(2, point)
        e_bearing = f.whitenedError(v)
        e_pixel = pixel.whitenedError(vp)
        assert np.linalg.norm(e_bearing) == pytest.approx(np.linalg.norm(e_pixel), rel=0.02)


# ----------------------------------------------------------------------------- bundle adjustment


def _gauge(scene, graph):
    """Prior on the first pose and noisy-free odometry (fixes the 7-DoF gauge and scale)."""
    graph.add(gtsam.PriorFactorPose3(pose_key(0), scene_pose(scene, 0), M.Isotropic.Sigma(6, 1e-4)))
    odo = M.Diagonal.Sigmas(np.r_[[0.01] * 3, [0.02] * 3])
    for i in range(scene.n_images - 1):
        rel = scene_pose(scene, i).between(scene_pose(scene, i + 1))
        graph.add(gtsam.BetweenFactorPose3(pose_key(i), pose_key(i + 1), rel, odo))


def _errors(scene, values):
    rot = max(
        np.linalg.norm(
            gtsam.Rot3.Logmap(
                scene_pose(scene, i).rotation().between(values.atPose3(pose_key(i)).rotation())
            )
        )
        for i in range(scene.n_images)
    )
    trans = max(
        np.linalg.norm(
            scene_pose(scene, i).translation() - values.atPose3(pose_key(i)).translation()
        )
        for i in range(scene.n_images)
    )
    pts = np.array([values.atPoint3(point_key(j)) for j in range(scene.n_points)])
    return rot, trans, np.sqrt(np.mean(np.sum((pts - scene.points_world) ** 2, 1)))


@pytest.fixture(scope="module")
def small_scene():
    return simulate_building(
        n_images=20, obs_per_image=40, images_per_room=10, seed=11, noise_px=0.3
    )


@pytest.mark.parametrize(
    "path",
    [
        "bearing",
        "pixel-blocks",
        pytest.param("pixel-single", marks=pytest.mark.slow),  # one factor per observation
        "spherical-sqrtinfo",
        "isam2-blocks",
    ],
)
def test_small_bundle_adjustment_recovers_truth(small_scene, path):
    """From a perturbed start (0.6 deg, 5 cm, landmarks 8 cm) every path reaches the
    optimum it reaches from the truth, and that optimum is within the noise of the truth."""
    scene = small_scene
    initial = perturbed_values(scene, seed=3)
    start = _errors(scene, initial)
    result = _solve(scene, path, initial)
    optimum = _solve(scene, path, perturbed_values(scene, seed=0, rot=0, trans=0, pts=0))
    rot, trans, pts = _errors(scene, result)
    assert rot < 5e-3 and trans < 0.02 and pts < 0.02, (path, start, (rot, trans, pts))
    assert pts < 0.2 * start[2] and trans < 0.2 * start[1]
    for i in range(scene.n_images):
        d = optimum.atPose3(pose_key(i)).localCoordinates(result.atPose3(pose_key(i)))
        assert np.linalg.norm(d) < 1e-4, (path, i, d)
    P = np.array([result.atPoint3(point_key(j)) for j in range(scene.n_points)])
    Q = np.array([optimum.atPoint3(point_key(j)) for j in range(scene.n_points)])
    assert np.abs(P - Q).max() < 1e-4, path


def _tight() -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(100)
    return params


def _solve(scene, path, initial):
    """Refine ``initial`` with one of the paths; returns Pose3/Point3 Values."""
    pk = np.array([pose_key(i) for i in scene.obs_image], np.uint64)
    lk = np.array([point_key(j) for j in scene.obs_point], np.uint64)
    graph = gtsam.NonlinearFactorGraph()
    pixel_noise = M.Robust.Create(M.mEstimator.Huber.Create(2.45), M.Isotropic.Sigma(2, 0.3))
    if path == "spherical-sqrtinfo":
        # GeneralSFMFactorSphericalCamera needs SphericalCamera variables (no odometry)
        R = bearing_sqrt_information(scene.camera, scene.uv_px, 0.3)
        rays = bearings(scene.camera, scene.uv_px)
        for k in range(scene.n_observations):
            graph.add(
                gtsam.GeneralSFMFactorSphericalCamera(
                    gtsam.Unit3(rays[k]), M.Gaussian.SqrtInformation(R[k]), int(pk[k]), int(lk[k])
                )
            )
        # bearings fix no scale and the walls hide one room from the next: two cameras
        # held in every room
        held = np.r_[
            [
                np.flatnonzero(scene.room_of_image == r)[[0, -1]]
                for r in np.unique(scene.room_of_image)
            ]
        ].ravel()
        for i in held:
            graph.add(
                gtsam.PriorFactorSphericalCamera(
                    pose_key(i),
                    gtsam.SphericalCamera(scene_pose(scene, i)),
                    M.Isotropic.Sigma(6, 1e-4),
                )
            )
        values = gtsam.Values()
        for i in range(scene.n_images):
            values.insert(pose_key(i), gtsam.SphericalCamera(initial.atPose3(pose_key(i))))
        for j in range(scene.n_points):
            values.insert(point_key(j), initial.atPoint3(point_key(j)))
        out = gtsam.LevenbergMarquardtOptimizer(graph, values, _tight()).optimize()
        result = gtsam.Values()
        for i in range(scene.n_images):
            result.insert(pose_key(i), out.atSphericalCamera(pose_key(i)).pose())
        for j in range(scene.n_points):
            result.insert(point_key(j), out.atPoint3(point_key(j)))
    else:
        _gauge(scene, graph)
        if path == "bearing":
            for f in make_bearing_factors(
                scene.camera, scene.uv_px, pk, lk, 0.3, robust=M.mEstimator.Huber.Create(2.45)
            ):
                graph.add(f)
            result = gtsam.LevenbergMarquardtOptimizer(graph, initial, _tight()).optimize()
        elif path == "pixel-single":
            for k in range(scene.n_observations):
                graph.add(
                    make_projection_factor(
                        scene.camera, scene.uv_px[k], int(pk[k]), int(lk[k]), pixel_noise
                    )
                )
            result = gtsam.LevenbergMarquardtOptimizer(graph, initial, _tight()).optimize()
        elif path == "pixel-blocks":
            blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, pixel_noise)
            for f in blocks.factors():
                graph.add(f)
            result, info = levenberg_marquardt(graph, initial, _tight())
            assert info["converged"]
            ref = gtsam.LevenbergMarquardtOptimizer(graph, initial, _tight()).optimize()
            assert graph.error(result) == pytest.approx(graph.error(ref), rel=1e-9)
        else:  # ISAM2, images in trajectory order, landmarks once seen twice
            result = _isam2(scene, initial, pk, lk, pixel_noise)
    return result


def _isam2(scene, initial, pk, lk, noise):
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-6)  # relinearise everything that moves: exact optimum
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    theta = isam.getLinearizationPoint()  # held: callbacks get it without a copy
    blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, noise)
    factors = blocks.factors()
    added_point = np.zeros(scene.n_points, bool)
    added_block = np.zeros(len(factors), bool)
    last_image = np.array([scene.obs_image[idx].max() for idx in blocks.groups])
    odo = M.Diagonal.Sigmas(np.r_[[0.01] * 3, [0.02] * 3])
    for i in range(scene.n_images):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(pose_key(i), initial.atPose3(pose_key(i)))
        if i == 0:
            graph.add(
                gtsam.PriorFactorPose3(
                    pose_key(0), scene_pose(scene, 0), M.Isotropic.Sigma(6, 1e-4)
                )
            )
        else:
            rel = scene_pose(scene, i - 1).between(scene_pose(scene, i))
            graph.add(gtsam.BetweenFactorPose3(pose_key(i - 1), pose_key(i), rel, odo))
        # a block goes in once all its images are in; its landmark with its first block
        for g in np.flatnonzero((last_image == i) & ~added_block):
            j = scene.obs_point[blocks.groups[g][0]]
            if not added_point[j]:
                values.insert(point_key(j), initial.atPoint3(point_key(j)))
                added_point[j] = True
            graph.add(factors[g])
            added_block[g] = True
        isam.update(graph, values)
    assert added_block.all() and theta.size() == scene.n_images + scene.n_points
    for _ in range(5):
        isam.update()
    return isam.calculateEstimate()


def _far_start_graph(scene):
    """The Huber pixel blocks of ``scene`` with its gauge, and a far start (landmarks
    0.5 m off): LM rejects many trial steps from there. Returns (graph, initial, blocks)."""
    pk = np.array([pose_key(i) for i in scene.obs_image], np.uint64)
    lk = np.array([point_key(j) for j in scene.obs_point], np.uint64)
    noise = M.Robust.Create(M.mEstimator.Huber.Create(1.0), M.Isotropic.Sigma(2, 0.3))
    graph = gtsam.NonlinearFactorGraph()
    _gauge(scene, graph)
    blocks = ProjectionBlocks(scene.camera, scene.uv_px, pk, lk, noise)
    for f in blocks.factors():
        graph.add(f)
    return graph, perturbed_values(scene, 3, rot=0.1, trans=0.2, pts=0.5), blocks


def test_levenberg_marquardt_with_rejected_steps_matches_gtsam(small_scene):
    """A far start (landmarks 0.5 m off): many trial steps are rejected, so the Jacobians
    computed ahead with a rejected trial's cost must never serve a later linearisation.
    The Python-driven LM takes GTSAM's own LM path on the same blocks."""
    scene = small_scene
    graph, initial, blocks = _far_start_graph(scene)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    ours, info = levenberg_marquardt(graph, initial, params)
    # one full evaluation per trial step and one initially: more than that means rejections
    # (each rejection is one more trial) and a linearisation after them
    assert blocks.stats["full_passes"] > info["iterations"] + 3
    assert info["converged"]
    ref = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert info["error"] == pytest.approx(graph.error(ref), rel=1e-9)
    assert info["error"] == pytest.approx(graph.error(ours), rel=1e-12)
    for i in range(scene.n_images):
        d = ref.atPose3(pose_key(i)).localCoordinates(ours.atPose3(pose_key(i)))
        assert np.linalg.norm(d) < 1e-7, (i, d)


def test_levenberg_marquardt_matches_gtsam_on_cpp_factors(small_scene):
    scene = small_scene
    pk = np.array([pose_key(i) for i in scene.obs_image], np.uint64)
    lk = np.array([point_key(j) for j in scene.obs_point], np.uint64)
    graph = gtsam.NonlinearFactorGraph()
    _gauge(scene, graph)
    for f in make_bearing_factors(scene.camera, scene.uv_px, pk, lk, 0.3):
        graph.add(f)
    initial = perturbed_values(scene, seed=4)
    ours, info = levenberg_marquardt(graph, initial)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    assert info["converged"] and info["iterations"] >= 2
    assert graph.error(ours) == pytest.approx(graph.error(ref), rel=1e-6)


def test_levenberg_marquardt_status_means_what_optimize_means():
    """One status enum (LMStatus) and optimize()'s meaning: converged on a small decrease,
    stalled when no step lowers the cost before lambda passes its upper bound."""
    key = gtsam.symbol("x", 0)
    target = gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(key, target, gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    start = gtsam.Values()
    start.insert(key, gtsam.Pose3(gtsam.Rot3.Rz(0.5), np.array([1.5, 2.0, 2.0])))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(1)
    _, info = levenberg_marquardt(graph, start, params)
    assert info["status"] is LMStatus.MAX_ITERATIONS and not info["converged"]
    out, info = levenberg_marquardt(graph, start)
    assert info["status"] is LMStatus.CONVERGED and info["converged"]
    at_optimum = gtsam.Values()
    at_optimum.insert(key, target)
    _, info = levenberg_marquardt(graph, at_optimum)
    assert info["status"] is LMStatus.STALLED and not info["converged"]
    assert info["iterations"] == 1


def _cubic_graph(sigma):
    """One unknown x, residual ``(x^3 - 1) / sigma``: from x = 0.05 the Gauss-Newton
    step overshoots by thousands, and the damping that makes it a descent step grows
    as ``1 / sigma^2`` (whitened curvature)."""
    key = gtsam.symbol("x", 0)

    def residual(this, values, H):
        x = values.atVector(key)[0]
        if H is not None:
            H[0] = np.asfortranarray([[3.0 * x * x]])
        return np.array([x**3 - 1.0])

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), [key], residual))
    start = gtsam.Values()
    start.insert(key, np.array([0.05]))
    return graph, start, key


def test_optimize_damps_as_far_as_the_whitened_curvature_needs():
    """GTSAM's default lambdaUpperBound (1e5) is below the damping a precise residual
    needs (zoo stress 2912 s15: every robust stage stalled at 0.1 px); optimize() gives
    up at OptimizerOptions.lambda_upper_bound (1e10) instead."""
    graph, start, key = _cubic_graph(1e-5)
    stalled = optimize(graph, start, OptimizerOptions(lambda_upper_bound=1e5))
    assert stalled.status is LMStatus.STALLED and not stalled.converged
    assert stalled.values.atVector(key)[0] == 0.05  # no step was taken
    assert OptimizerOptions().lambda_upper_bound == 1e10
    result = optimize(graph, start, OptimizerOptions(max_iterations=500))
    assert result.converged and result.values.atVector(key)[0] == pytest.approx(1.0, abs=1e-6)


def test_levenberg_marquardt_solves_what_cholesky_finds_indeterminate():
    """A radial mapping of six terms fitted over 0-58 and 122-131 deg of incidence (the
    rays a 262 deg sphere lens shows on a sensor smaller than its fold): the Jacobian's
    condition number is about 3e5, the normal equations' about 1e11, and Cholesky finds
    the damped system indeterminate below lambda = 1e-3. Raising lambda instead took all
    100 iterations to a cost of 7.6e-3 (5e-14 at the optimum); QR of the same system
    reaches the least-squares solution in a few."""
    from gtsam_sphere.estimation.optimize import GraphBackend

    a0, c_px, sigma_px = np.pi / 2, 3000.0, 0.3
    t = np.concatenate([np.linspace(0.0, 58 / 90, 300), np.linspace(122 / 90, 131 / 90, 60)])
    alpha = a0 * t
    powers = c_px * a0 * np.stack([t ** (2 * i + 3) for i in range(6)], axis=1)
    r_px = c_px * np.sin(alpha)  # the sphere lens
    key = gtsam.symbol("g", 0)

    def residual(this, values, H):
        if H is not None:
            H[0] = np.asfortranarray(powers)
        return c_px * alpha + powers @ values.atVector(key) - r_px

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(M.Isotropic.Sigma(len(t), sigma_px), [key], residual))
    start = gtsam.Values()
    start.insert(key, np.zeros(6))
    backend = GraphBackend(graph, start)
    backend.linearize()
    assert backend.solve(1e-6) is not None and backend.use_qr  # Cholesky refused it
    out, info = levenberg_marquardt(graph, start)
    assert info["status"] is LMStatus.CONVERGED and info["iterations"] <= 5
    best = np.linalg.lstsq(powers, r_px - c_px * alpha, rcond=None)[0]
    np.testing.assert_allclose(out.atVector(key), best, rtol=1e-6, atol=1e-9)
    assert info["error"] < 1e-9


class _ExpBackend:
    """LMBackend of the residual ``exp(x) - 2`` (Gauss-Newton); its first solve is indeterminate."""

    def __init__(self, x: float):
        self.x, self.lams, self.delta, self.trial = x, [], 0.0, x

    @staticmethod
    def cost(x: float) -> float:
        return 0.5 * (np.exp(x) - 2.0) ** 2

    def linearize(self) -> None:
        self.J, self.r = np.exp(self.x), np.exp(self.x) - 2.0
        self.model_cost = 0.5 * self.r**2

    def solve(self, lam: float):
        self.lams.append(lam)
        if len(self.lams) == 1:
            return None
        self.delta = -self.J * self.r / (self.J**2 + lam)
        return 0.5 * self.r**2 - 0.5 * (self.r + self.J * self.delta) ** 2

    def evaluate(self) -> float:
        self.trial = self.x + self.delta
        return self.cost(self.trial)

    def accept(self) -> None:
        self.x = self.trial


def test_lm_driver_damping_schedule_status_and_resumed_count():
    """The one LM loop: an indeterminate system and rejected steps multiply lambda by 10,
    an accepted step divides it; a resumed run counts its earlier iterations; it ends
    converged at the optimum, the hook told so only after the last iteration."""
    backend = _ExpBackend(-3.0)
    seen = []
    params = gtsam.LevenbergMarquardtParams()
    info = lm_driver(backend, params, backend.cost(-3.0), iteration=3, on_iteration=seen.append)
    # 1e-5 indeterminate, 1e-4 .. 1e-2 overshoot (exp(x) - 2 is nearly flat at -3), 1e-1 lowers
    # the cost; the next iteration starts at 1e-2
    assert backend.lams[:6] == pytest.approx([1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1e-2], rel=1e-12)
    assert seen[0].iteration == 4 and seen[0].lam == pytest.approx(1e-2, rel=1e-12)
    assert info["status"] is LMStatus.CONVERGED and info["converged"]
    assert [it.converged for it in seen] == [False] * (len(seen) - 1) + [True]
    assert info["iterations"] == seen[-1].iteration == 3 + len(info["iteration_s"])
    assert backend.x == pytest.approx(np.log(2.0), abs=1e-3)
    assert info["error"] == backend.cost(backend.x)
    params.setMaxIterations(5)
    done = lm_driver(_ExpBackend(0.0), params, 1.0, iteration=5)
    assert done["iterations"] == 5 and done["status"] is LMStatus.MAX_ITERATIONS


def test_optimize_lm_takes_gtsams_steps_with_the_given_ordering(small_scene):
    """optimize() runs LM from Python (no copy of the Values per callback): with the same
    elimination ordering it takes GTSAM's steps (same iterations, costs and state), from
    a far start where steps are rejected, and reports one LMStatus."""
    scene = small_scene
    graph, initial, blocks = _far_start_graph(scene)
    ordering = make_ordering(
        [point_key(j) for j in range(scene.n_points)],
        [pose_key(i) for i in range(scene.n_images)],
        [],
    )
    options = OptimizerOptions(max_iterations=100)
    ours = optimize(graph, initial, options, ordering)
    params = gtsam.LevenbergMarquardtParams()
    params.setOrdering(ordering)
    params.setMaxIterations(100)
    params.setRelativeErrorTol(options.relative_tolerance)
    params.setAbsoluteErrorTol(options.absolute_tolerance)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    costs = [ref.error()]
    for _ in range(len(ours.history) - 1):
        ref.iterate()
        costs.append(ref.error())
    assert ours.status is LMStatus.CONVERGED and ours.converged and ours.message == ""
    assert len(ours.history) > 3
    np.testing.assert_allclose([h["cost"] for h in ours.history], costs, rtol=1e-12)
    for i in range(scene.n_images):
        d = ref.values().atPose3(pose_key(i)).localCoordinates(ours.values.atPose3(pose_key(i)))
        assert np.linalg.norm(d) < 1e-10, (i, d)
    capped = optimize(graph, initial, OptimizerOptions(max_iterations=2), ordering)
    assert capped.status is LMStatus.MAX_ITERATIONS and len(capped.history) == 3
    # from its own optimum: one more (negligible) step, GTSAM's, and converged
    again = optimize(graph, ours.values, options, ordering)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, ours.values, params)
    ref.iterate()
    assert again.status is LMStatus.CONVERGED and len(again.history) == 2
    assert again.history[1]["cost"] == pytest.approx(ref.error(), rel=1e-12)


# ----------------------------------------------------------------------------- simulator, bench


def test_building_simulator_is_seeded_and_consistent():
    a = simulate_building(n_images=60, obs_per_image=50, images_per_room=20, seed=9)
    b = simulate_building(n_images=60, obs_per_image=50, images_per_room=20, seed=9)
    np.testing.assert_array_equal(a.uv_px, b.uv_px)
    assert abs(a.n_observations / (60 * 50) - 1) < 0.15
    assert np.all(np.diff(a.obs_image) >= 0)
    assert np.bincount(a.obs_point).min() >= 2
    np.testing.assert_allclose(a.camera.project(a.points_cam()), a.uv_true_px, atol=1e-9)
    alpha = np.degrees(np.arccos(a.true_bearings()[:, 2]))
    assert alpha.max() > 90.0  # the fisheye sees past 90 degrees
    assert a.camera.mapping == "radial"


def _bench_map_module():
    """``benchmarks/bench_map.py`` imported as a module (the folder is not a package)."""
    spec = importlib.util.spec_from_file_location("bench_map", ROOT / "benchmarks" / "bench_map.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_map_paths_refine_the_map_like_the_cpp_reference(tmp_path, capsys):
    """The map benchmark's paths, in this process on a small trajectory (no timing).

    Every path (C++ bearing factors, the Python frozen-calibration blocks, the pure C++
    reference) in batch LM and in iSAM2 must refine the perturbed map to a fraction of
    its start error and within 1.5x of the C++ reference's; the benchmark's table and
    summary are then printed from these rows by its ``--report`` entry.
    """
    bench = _bench_map_module()
    n_obs = 3000
    rows = []
    for mode in ("lm", "isam2"):
        for path in ("bearing", "python", "cpp-ref"):
            args = argparse.Namespace(
                seed=0,
                n_obs=n_obs,
                n_images=bench.images_for(n_obs, quick=True),
                path=path,
                mode=mode,
                max_obs=8,
                lm_iterations=20,
            )
            row = bench.worker(args)
            rows.append(dict(row, status="ok", n_obs_requested=n_obs, peak_mb=0.0))
    for row in rows:
        ref = next(r for r in rows if r["path"] == "cpp-ref" and r["mode"] == row["mode"])
        what = f"{row['path']} {row['mode']}"
        assert row["n_obs"] == ref["n_obs"] > 0.9 * n_obs, what
        assert row["point_rms_m"] < 0.25 * row["start_point_rms_m"], what
        assert row["point_rms_m"] < 1.5 * ref["point_rms_m"], what
        assert row["rot_rms_deg"] < 2.0 * ref["rot_rms_deg"] + 0.05, what
    report = tmp_path / "rows.json"
    report.write_text(json.dumps(rows))
    assert bench.main(["--report", str(report)]) == 0
    text = capsys.readouterr().out
    for path in ("bearing", "python", "cpp-ref"):
        assert f"| {path} |" in text
    assert "growth exponent" in text and "peak MB" in text and "ratios against cpp-ref" in text
