"""Projection uncertainty maps (gtsam_sphere.analysis.uncertainty) and their report figure."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from gtsam_sphere import SphereCamera
from gtsam_sphere.analysis.uncertainty import (
    cell_weights,
    compensate_jacobian,
    intrinsic_value,
    intrinsics_covariance,
    knn_sigma_px,
    motion_jacobian,
    uncertainty_map,
    uncertainty_map_of,
    with_intrinsic,
)
from gtsam_sphere.apps.export import pixel_rays
from gtsam_sphere.apps.report import PLOTS, write_report
from gtsam_sphere.estimation.correct import KNNCorrection
from gtsam_sphere.io.calibration import Calibration
from gtsam_sphere.io.dataset import DatasetError

W, H = 800, 600
NAMES = ["xp_px", "yp_px", "c_px", "k1", "k2", "p1"]


def brown_camera() -> SphereCamera:
    return SphereCamera(
        W, H, xp=402.0, yp=297.0, c=330.0, brown={"k1": 0.2, "k2": -0.02, "p1": 5e-4}
    )


def covariance(scale: float = 1.0) -> np.ndarray:
    sig = np.array([0.3, 0.25, 0.5, 1e-3, 5e-4, 2e-5])
    corr = np.eye(6)
    corr[2, 3] = corr[3, 2] = 0.6  # c and k1 are correlated in a real adjustment
    corr[3, 4] = corr[4, 3] = -0.8
    return scale * corr * np.outer(sig, sig)


def test_adapter_maps_names_to_camera_attributes():
    cam = brown_camera()
    assert intrinsic_value(cam, "xp_px") == 402.0 and intrinsic_value(cam, "c") == 330.0
    assert intrinsic_value(cam, "k3") == 0.0  # a Brown term the model does not carry
    moved = with_intrinsic(cam, "k1", 0.25)
    assert moved.brown["k1"] == 0.25 and cam.brown["k1"] == 0.2  # a copy
    assert with_intrinsic(cam, "yp_px", 1.0).yp == 1.0 and cam.yp == 297.0
    assert with_intrinsic(cam, "k3", 1e-3).brown["k3"] == 1e-3 and "k3" not in cam.brown
    with pytest.raises(ValueError, match="'g9'"):
        with_intrinsic(cam, "g9", 0.1)
    if any(f.name == "radial" for f in dataclasses.fields(SphereCamera)):
        rad = dataclasses.replace(cam, radial={"g3": 0.01})
        assert with_intrinsic(rad, "g3", 0.02).radial["g3"] == 0.02 and rad.radial["g3"] == 0.01


def test_zero_covariance_gives_a_zero_map():
    m = uncertainty_map(brown_camera(), np.zeros((6, 6)), NAMES, n_cols=16)
    ok = np.isfinite(m.sigma_px)
    assert ok.mean() > 0.9
    assert np.all(m.sigma_px[ok] == 0.0) and np.all(m.sigma_knn_px[ok] == 0.0)


def test_map_grows_with_the_covariance():
    cam = brown_camera()
    a = uncertainty_map(cam, covariance(1.0), NAMES, n_cols=16)
    b = uncertainty_map(cam, covariance(4.0), NAMES, n_cols=16)
    ok = np.isfinite(a.sigma_px)
    assert np.all(a.sigma_px[ok] > 0)
    assert np.allclose(b.sigma_px[ok] / a.sigma_px[ok], 2.0, rtol=0.03)
    # a principal-point-only covariance shifts every pixel by the same amount
    pp = np.zeros((6, 6))
    pp[0, 0], pp[1, 1] = 0.3**2, 0.4**2
    m = uncertainty_map(cam, pp, NAMES, n_cols=16)
    assert np.allclose(m.sigma_px[ok], 0.5, atol=1e-6)
    # c and the radial terms matter more away from the principal point
    cc = np.zeros((6, 6))
    cc[2, 2] = 1.0
    m = uncertainty_map(cam, cc, NAMES, n_cols=16)
    r = np.hypot(*np.meshgrid(m.u_px - cam.xp, m.v_px - cam.yp))
    inner, outer = ok & (r < 80), ok & (r > 250)
    assert m.sigma_px[outer].min() > 2 * m.sigma_px[inner].max()


def test_map_matches_monte_carlo():
    cam = brown_camera()
    cov = covariance()
    m = uncertainty_map(cam, cov, NAMES, n_cols=8)
    rows, cols = np.nonzero(np.isfinite(m.sigma_px))
    uv = np.column_stack([m.u_px[cols], m.v_px[rows]])
    rays = pixel_rays(cam, uv)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(np.zeros(6), cov, size=300)
    theta0 = np.array([intrinsic_value(cam, n) for n in NAMES])
    pix = []
    for d in draws:
        c = cam
        for name, value in zip(NAMES, theta0 + d):
            c = with_intrinsic(c, name, value)
        pix.append(c.project(rays))
    pix = np.array(pix)
    mc = np.sqrt(np.sum(pix.var(axis=0), axis=1))
    full_err = np.abs(m.sigma_px[rows, cols] / mc - 1)
    assert full_err.max() < 0.15
    # the diagonal-only map ignores the correlations: farther from the truth
    diag = uncertainty_map(cam, np.diag(np.diag(cov)), NAMES, n_cols=8)
    diag_err = np.abs(diag.sigma_px[rows, cols] / mc - 1)
    assert diag_err.mean() > 2 * full_err.mean()


def test_covariance_from_statistics():
    cov = covariance()
    names, got, note = intrinsics_covariance(
        {"intrinsics_covariance": cov.tolist(), "intrinsics_names": NAMES}
    )
    assert names == NAMES and np.allclose(got, cov) and note.startswith("full")
    names, got, note = intrinsics_covariance({"intrinsics_sigma": {"xp_px": 0.3, "c_px": 0.5}})
    assert names == ["xp_px", "c_px"] and np.allclose(got, np.diag([0.09, 0.25]))
    assert "diagonal only" in note
    with pytest.raises(DatasetError, match="neither"):
        intrinsics_covariance({"rms_px": 1.0}, "c.json")
    with pytest.raises(DatasetError, match=r"shape \(2, 2\)"):
        intrinsics_covariance(
            {"intrinsics_covariance": [[1, 0], [0, 1]], "intrinsics_names": NAMES}
        )
    with pytest.raises(DatasetError, match="intrinsics_names"):
        intrinsics_covariance({"intrinsics_covariance": [[1.0]]})
    with pytest.raises(DatasetError, match="negative"):
        intrinsics_covariance({"intrinsics_covariance": [[-1.0]], "intrinsics_names": ["c_px"]})


def _knn(noise_px: float, k: int = 16, n: int = 3000, seed: int = 0) -> KNNCorrection:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [W, H], size=(n, 2))
    smooth = 0.5 * np.column_stack([np.sin(uv[:, 0] / 200), np.cos(uv[:, 1] / 150)])
    y = smooth + rng.normal(0, noise_px, size=(n, 2))
    return KNNCorrection(n_neighbors=k, weights="uniform", cv_folds=2).fit(uv, y)


def test_knn_term_is_the_standard_error_of_the_local_mean():
    model = _knn(0.3, k=16)
    uv = np.random.default_rng(1).uniform([100, 100], [W - 100, H - 100], size=(400, 2))
    s = knn_sigma_px(model, uv)
    # per point: sqrt(2) * noise / sqrt(k) (both coordinates); the smooth part adds a little
    assert np.median(s) == pytest.approx(np.sqrt(2) * 0.3 / 4, rel=0.15)
    assert knn_sigma_px(object(), uv) is None
    cam = brown_camera()
    cam.correction = model
    m = uncertainty_map(cam, covariance(), NAMES, n_cols=10)
    ok = np.isfinite(m.sigma_px)
    assert np.all(m.sigma_knn_px[ok] > 0) and "kNN" in m.note
    assert np.allclose(
        m.sigma_px[ok] ** 2, m.sigma_intrinsics_px[ok] ** 2 + m.sigma_knn_px[ok] ** 2
    )
    quieter = _knn(0.1, k=16)
    cam.correction = quieter
    m2 = uncertainty_map(cam, covariance(), NAMES, n_cols=10)
    assert np.nanmedian(m2.sigma_knn_px) < 0.5 * np.nanmedian(m.sigma_knn_px)


def _calibration(stats: dict) -> Calibration:
    rng = np.random.default_rng(0)
    uv = rng.uniform([150, 100], [650, 500], size=(300, 2))
    return Calibration(
        model="brown",
        camera=brown_camera(),
        image_ids=[],
        cam_from_world_R=np.zeros((0, 3, 3)),
        cam_from_world_t=np.zeros((0, 3)),
        target_ids=[],
        target_xyz=np.zeros((0, 3)),
        statistics={"rms_px": 0.3, "n_observations": 300, "n_rejected": 0, **stats},
        extra={"observations": {"uv_px": uv, "residual_px": rng.normal(0, 0.3, (300, 2))}},
    )


@pytest.mark.slow  # end-to-end
def test_uncertainty_of_a_calibration_and_its_report_section(tmp_path):
    calib = _calibration(
        {"intrinsics_covariance": covariance().tolist(), "intrinsics_names": NAMES}
    )
    m = uncertainty_map_of(calib, n_cols=12)
    assert m.note.startswith("full") and np.nanmax(m.sigma_px) > 0
    paths = write_report(calib, tmp_path / "rep")
    assert "uncertainty" in PLOTS and paths["uncertainty"].stat().st_size > 1000
    md = paths["markdown"].read_text()
    assert "## Projection uncertainty" in md and "How to read it" in md
    assert "(uncertainty.png)" in md and "full covariance" in md
    # sigmas only: the page says the correlations are missing
    sig = dict(zip(NAMES, np.sqrt(np.diag(covariance()))))
    md = write_report(_calibration({"intrinsics_sigma": sig}), tmp_path / "b")["markdown"]
    assert "diagonal only" in md.read_text()
    # nothing: a placeholder image and a sentence, no failure
    paths = write_report(_calibration({}), tmp_path / "c")
    assert paths["uncertainty"].exists() and "No map" in paths["markdown"].read_text()
    with pytest.raises(DatasetError, match="neither"):
        uncertainty_map_of(_calibration({}))


# --------------------------------------------------------------- compensated camera frame


def _observations(n: int = 1500, seed: int = 5) -> np.ndarray:
    """Observed pixels over part of the image only (the fit region), (n, 2) px."""
    return np.random.default_rng(seed).uniform([100, 80], [560, 480], size=(n, 2))


def _monte_carlo_compensated(cam, cov, names, m, range_m, fit_ranges, n_draws, seed=0):
    """Per-cell RMS projection change (px) after the best motion fitted numerically.

    For each draw of the intrinsics, the rotation (and, with ``fit_ranges``,
    the translation, over the grid's points at each of those ranges) that
    minimises the weighted squared pixel differences over the map's fit
    region is found by nonlinear least squares on the perturbed camera's
    exact projection; the change is then measured on every cell, at
    ``range_m`` (``None``: infinity).
    """
    rows, cols = np.nonzero(np.isfinite(m.sigma_px))
    uv = np.column_stack([m.u_px[cols], m.v_px[rows]])
    rays = pixel_rays(cam, uv)
    w = m.fit_weight[rows, cols]
    fit = w > 0
    shells = list(fit_ranges or [])
    n_motion = 6 if shells else 3
    sw = np.sqrt(np.tile(w[fit], max(len(shells), 1)))[:, None]

    def moved(c, x, idx, ranges):
        """Pixels of the cells ``idx`` moved by ``x``, one block per range (one projection)."""
        rot = Rotation.from_rotvec(x[:3])
        p = [
            rot.apply(rays[idx]) if r is None else rot.apply(r * rays[idx]) + x[3:] for r in ranges
        ]
        return c.project(np.concatenate(p))

    def residual(x, c):
        q = moved(c, x, fit, shells or [None]) - np.tile(uv[fit], (max(len(shells), 1), 1))
        return (q * sw).ravel()

    scale = np.r_[np.full(3, 1e-3), np.full(n_motion - 3, 1e-3 * max(shells or [1.0]))]
    theta0 = np.array([intrinsic_value(cam, n) for n in names])
    rng = np.random.default_rng(seed)
    diffs = []
    for d in rng.multivariate_normal(np.zeros(len(names)), cov, size=n_draws):
        c = cam
        for name, value in zip(names, theta0 + d):
            c = with_intrinsic(c, name, value)
        x = least_squares(residual, np.zeros(n_motion), x_scale=scale, args=(c,), method="lm").x
        diffs.append(moved(c, x, slice(None), [range_m]) - uv)
    diffs = np.array(diffs)
    return rows, cols, np.sqrt(diffs.var(axis=0).sum(axis=1))


@pytest.mark.parametrize(
    "range_m, fit_ranges",
    [(None, None), (1.5, [1.0, 2.0, 4.0])],
    ids=["rotation", "three-shells"],
)
@pytest.mark.slow  # end-to-end
def test_compensated_map_matches_monte_carlo_with_a_fitted_motion(range_m, fit_ranges):
    cam, cov = brown_camera(), covariance()
    m = uncertainty_map(
        cam,
        cov,
        NAMES,
        n_cols=8,
        compensate_rotation=True,
        fit_uv_px=_observations(),
        range_m=range_m,
        fit_ranges_m=fit_ranges,
    )
    translated = range_m is not None or fit_ranges is not None
    assert m.compensation == ("rotation+translation" if translated else "rotation")
    shells = fit_ranges or ([range_m] if range_m is not None else None)
    rows, cols, mc = _monte_carlo_compensated(cam, cov, NAMES, m, range_m, shells, n_draws=200)
    err = np.abs(m.sigma_intrinsics_px[rows, cols] / mc - 1)
    assert err.max() < 0.15
    # the fixed-ray map is not the same quantity: several times the fitted answer somewhere
    fixed_err = np.abs(m.sigma_fixed_ray_px[rows, cols] / mc - 1)
    assert fixed_err.max() > 1.0 and np.mean(fixed_err > 0.15) > 0.3


def test_one_shell_is_range_invariant_and_several_shells_are_not():
    cam, cov, obs = brown_camera(), covariance(), _observations()
    kw = dict(n_cols=10, compensate_rotation=True, fit_uv_px=obs)
    near = uncertainty_map(cam, cov, NAMES, range_m=0.5, **kw)
    far = uncertainty_map(cam, cov, NAMES, range_m=50.0, **kw)
    assert np.allclose(near.sigma_px, far.sigma_px, rtol=1e-6, equal_nan=True)
    shells = [1.0, 2.0, 4.0]
    at = {
        r: uncertainty_map(cam, cov, NAMES, range_m=r, fit_ranges_m=shells, **kw)
        for r in (2.0, 20.0, None)
    }
    med = {r: np.nanmedian(mm.sigma_px) for r, mm in at.items()}
    # smallest among the fitted depths, growing towards infinity
    assert med[2.0] < med[20.0] < med[None] * 1.001
    assert at[None].fit_ranges_m == (1.0, 2.0, 4.0) and "range 1, 2, 4" in at[None].fit_note
    rot = uncertainty_map(cam, cov, NAMES, **kw)
    assert med[None] == pytest.approx(np.nanmedian(rot.sigma_px), rel=0.3)


def test_principal_point_alone_is_almost_a_rotation_on_an_ideal_lens():
    cam = SphereCamera(W, H, xp=402.0, yp=297.0, c=330.0, radial={})  # equidistant
    names = ["xp_px", "yp_px", "c_px"]
    cov = np.diag([0.3**2, 0.3**2, 0.0])
    sigma_pp = np.hypot(0.3, 0.3)
    fixed = uncertainty_map(cam, cov, names, n_cols=20)
    comp = uncertainty_map(
        cam, cov, names, n_cols=20, compensate_rotation=True, fit_uv_px=_observations(2000)
    )
    ok = np.isfinite(fixed.sigma_px)
    assert ok.all() and np.allclose(fixed.sigma_px, sigma_pp, rtol=1e-6)
    assert np.allclose(comp.sigma_fixed_ray_px, fixed.sigma_px)
    r = np.hypot(*np.meshgrid(comp.u_px - cam.xp, comp.v_px - cam.yp))
    assert comp.sigma_px[r < 100].max() < 0.05 * sigma_pp
    # what is left grows towards the rim, where a rotation is no longer a shift
    assert comp.sigma_px[r > 350].min() > 3 * comp.sigma_px[r < 100].max()
    assert comp.sigma_px.max() < sigma_pp
    # the fitted rotation is the shift over the principal distance (rad)
    assert comp.motion_sigma[:2] == pytest.approx(0.3 / cam.c, rel=0.15)
    # (a rotation about the axis helps only because the fit region is off-centre)
    assert comp.motion_sigma[2] < 0.2 * comp.motion_sigma[0]
    # without observations the fit is uniform over the image: still small at the centre
    uniform = uncertainty_map(cam, cov, names, n_cols=20, compensate_rotation=True)
    assert np.all(uniform.fit_weight == 1.0) and "uniform" in uniform.fit_note
    assert uniform.sigma_px[r < 100].max() < 0.15 * sigma_pp


def test_compensation_never_increases_the_weighted_variance_over_the_fit_region():
    cam = brown_camera()
    rng = np.random.default_rng(3)
    sig = np.sqrt(np.diag(covariance()))
    obs = _observations()
    for _ in range(4):
        a = rng.normal(size=(6, 6))
        cov = np.outer(sig, sig) * (a @ a.T) / 6  # random correlations, the same scales
        for range_m in (None, 1.5):
            m = uncertainty_map(
                cam,
                cov,
                NAMES,
                n_cols=12,
                compensate_rotation=True,
                fit_uv_px=obs,
                range_m=range_m,
            )
            w = m.fit_weight
            fixed = np.nansum(w * m.sigma_fixed_ray_px**2)
            comp = np.nansum(w * m.sigma_intrinsics_px**2)
            assert comp <= fixed * (1 + 1e-9)
            assert comp < 0.9 * fixed  # and the principal point's share is gone
    # pointwise it need not hold (the module docstring says so): the cells right of
    # the fit region, and a few on its border, grow by a few percent here
    m = uncertainty_map(
        cam, covariance(), NAMES, n_cols=12, compensate_rotation=True, fit_uv_px=obs
    )
    ratio = m.sigma_intrinsics_px / m.sigma_fixed_ray_px
    assert np.nanmax(ratio) > 1.0 and np.nanmax(ratio) < 1.1
    assert np.median(ratio[m.fit_weight > 0]) < 0.8
    # more freedom (a translation too) fits at least as well
    m6 = uncertainty_map(
        cam, covariance(), NAMES, n_cols=12, compensate_rotation=True, fit_uv_px=obs, range_m=1.5
    )
    w = m.fit_weight
    assert np.nansum(w * m6.sigma_intrinsics_px**2) <= np.nansum(w * m.sigma_intrinsics_px**2)


def test_compensated_map_shapes_and_bad_inputs():
    cam, cov = brown_camera(), covariance()
    obs = _observations()
    m = uncertainty_map(cam, cov, NAMES, n_cols=10, compensate_rotation=True, fit_uv_px=obs)
    shape = m.sigma_px.shape
    assert shape == (8, 10) and m.cov_px.shape == shape + (2, 2)
    for a in (m.sigma_intrinsics_px, m.sigma_fixed_ray_px, m.fit_weight):
        assert a.shape == shape
    assert m.motion_sigma.shape == (3,) and m.range_m is None
    assert m.fit_weight.sum() == pytest.approx(len(obs)) and "observations" in m.fit_note
    assert "rotation" in m.describe() and "infinity" in m.describe()
    m6 = uncertainty_map(
        cam, cov, NAMES, n_cols=10, compensate_rotation=True, fit_uv_px=obs, range_m=3.0
    )
    assert m6.motion_sigma.shape == (6,) and "translation" in m6.describe()
    # the default keeps the fixed-ray map, identical to the stored fixed-ray term
    plain = uncertainty_map(cam, cov, NAMES, n_cols=10)
    assert plain.compensation == "none" and plain.fit_weight is None
    assert plain.motion_sigma is None and "fixed" in plain.describe()
    assert np.array_equal(plain.sigma_intrinsics_px, plain.sigma_fixed_ray_px, equal_nan=True)
    assert np.allclose(m.sigma_fixed_ray_px, plain.sigma_px, equal_nan=True)
    # linear in the covariance, zero without one
    m4 = uncertainty_map(cam, 4 * cov, NAMES, n_cols=10, compensate_rotation=True, fit_uv_px=obs)
    ok = np.isfinite(m.sigma_px)
    assert np.allclose(m4.sigma_px[ok], 2 * m.sigma_px[ok], rtol=0.03)
    zero = uncertainty_map(
        cam, np.zeros((6, 6)), NAMES, n_cols=10, compensate_rotation=True, fit_uv_px=obs
    )
    assert np.all(zero.sigma_px[ok] == 0.0)
    # a robust weight of 0 removes an observation from the fit
    half = uncertainty_map(
        cam,
        cov,
        NAMES,
        n_cols=10,
        compensate_rotation=True,
        fit_uv_px=obs,
        fit_weight=np.r_[np.ones(750), np.zeros(750)],
    )
    assert half.fit_weight.sum() == pytest.approx(750)
    bad = [
        (dict(range_m=2.0), "compensate_rotation"),
        (dict(fit_ranges_m=[2.0]), "compensate_rotation"),
        (dict(compensate_rotation=True, fit_ranges_m=[1.0, 0.0]), "fit_ranges_m"),
        (dict(compensate_rotation=True, fit_ranges_m=[]), "empty"),
        (dict(compensate_rotation=True, range_m=-1.0), "range_m"),
        (dict(compensate_rotation=True, range_m=float("nan")), "range_m"),
        (dict(compensate_rotation=True, fit_uv_px=obs[:, :1]), r"\(M, 2\)"),
        (dict(compensate_rotation=True, fit_uv_px=obs, fit_weight=-np.ones(len(obs))), ">= 0"),
        (dict(compensate_rotation=True, fit_uv_px=obs, fit_weight=np.ones(3)), "fit_weight"),
        (dict(compensate_rotation=True, fit_weight=np.ones(3)), "fit_uv_px"),
        (dict(compensate_rotation=True, fit_uv_px=obs + 5000.0), "no observation"),
    ]
    for kwargs, match in bad:
        with pytest.raises(ValueError, match=match):
            uncertainty_map(cam, cov, NAMES, n_cols=10, **kwargs)
    with pytest.raises(ValueError, match="NaN"):
        uncertainty_map(cam, np.full((6, 6), np.nan), NAMES, n_cols=10)
    # the building blocks
    J = np.ones((5, 2, 4))
    with pytest.raises(ValueError, match=r"\(N, 2, K\)"):
        compensate_jacobian(J, np.ones((4, 2, 3)), np.ones(5))
    with pytest.raises(ValueError, match="weights"):
        compensate_jacobian(J, np.ones((5, 2, 3)), np.ones(4))
    with pytest.raises(ValueError, match="no cell"):
        compensate_jacobian(J, np.ones((5, 2, 3)), np.zeros(5))
    counts = cell_weights(np.array([0.5, 1.5]), np.array([0.5]), np.array([[0.2, 0.4], [9, 9]]))
    assert counts.tolist() == [[1.0, 0.0]]
    rays = pixel_rays(cam, np.array([[402.0, 297.0], [700.0, 100.0]]))
    G = motion_jacobian(cam, rays)
    assert G.shape == (2, 2, 3)
    # on the axis a rotation about x moves v, about y moves u, about z nothing
    assert G[0, 1, 0] == pytest.approx(-cam.c, rel=1e-3) and abs(G[0, 0, 0]) < 1e-3
    assert G[0, 0, 1] == pytest.approx(cam.c, rel=1e-3) and np.abs(G[0, :, 2]).max() < 1e-3
    assert motion_jacobian(cam, rays, range_m=2.0).shape == (2, 2, 6)
    with pytest.raises(ValueError, match="range_m"):
        motion_jacobian(cam, rays, range_m=0.0)


def test_map_of_a_calibration_is_compensated_over_its_observations():
    calib = _calibration(
        {"intrinsics_covariance": covariance().tolist(), "intrinsics_names": NAMES}
    )
    m = uncertainty_map_of(calib, n_cols=12)
    assert m.compensation == "rotation" and "observations" in m.fit_note
    assert m.fit_weight.sum() == pytest.approx(300)
    fixed = uncertainty_map_of(calib, n_cols=12, compensate_rotation=False)
    assert fixed.compensation == "none"
    assert np.nanmedian(m.sigma_px) < np.nanmedian(fixed.sigma_px)
    assert uncertainty_map_of(calib, n_cols=12, range_m=2.0).motion_sigma.shape == (6,)
    with pytest.raises(DatasetError, match="range_m"):
        uncertainty_map_of(calib, n_cols=12, range_m=-2.0)
    # no stored observations, or none on the image: a uniform fit, and the note says so
    del calib.extra["observations"]
    assert "uniform" in uncertainty_map_of(calib, n_cols=12).fit_note
    calib.extra["observations"] = {"uv_px": np.full((4, 2), 9000.0)}
    assert "no stored observation" in uncertainty_map_of(calib, n_cols=12).fit_note


@pytest.mark.slow
def test_report_says_which_map_it_shows(tmp_path):
    calib = _calibration(
        {"intrinsics_covariance": covariance().tolist(), "intrinsics_names": NAMES}
    )
    paths = write_report(calib, tmp_path / "rep")
    md = paths["markdown"].read_text()
    assert "Shown: points at infinity, after the camera rotation" in md
    assert "for a fixed camera-frame ray (no compensation" in md
    assert "fitted rotation's sigma" in md and "camera rotation" in PLOTS["uncertainty"]
    html = paths["html"].read_text()
    assert "<code>uncertainty_map_of(..., compensate_rotation=False)</code>" in html
