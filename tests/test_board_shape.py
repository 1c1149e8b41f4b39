"""Estimating a printed board's real shape (``control_sigma``) on a simulated curled board.

A 9x12 chessboard whose real corners bow out of the plane by up to 0.8 mm and whose rows
are printed 0.3% too far apart is seen through an equidistant fisheye. Calibrating with
the nominal (flat, exact) board leaves the warp in the residuals and biases the
intrinsics; ``control_sigma`` lets the adjustment estimate the corners around their
nominal coordinates, which must recover both the lens and the board's shape.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate
from gtsam_sphere.io.dataset import parse_dataset
from gtsam_sphere.simulate.building import rotation_exp
from gtsam_sphere.simulate.lenses import Equidistant

LENS = Equidistant(cx=401.3, cy=298.6, f=260.0)
WIDTH, HEIGHT = 800, 600
SQUARE_M = 0.03
COLS, ROWS = 9, 12
NOISE_PX = 0.05


def _boards() -> tuple[np.ndarray, np.ndarray]:
    """Nominal (flat) and true (curled, stretched) corners, (T, 3) metres each."""
    i, j = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    nominal = np.stack([j.ravel() * SQUARE_M, i.ravel() * SQUARE_M, 0 * i.ravel()], axis=1)
    u = (nominal[:, 0] / nominal[:, 0].max()) * 2 - 1  # -1..1 across the board
    v = (nominal[:, 1] / nominal[:, 1].max()) * 2 - 1
    true = nominal.copy()
    true[:, 1] *= 1.003  # rows printed 0.3% too far apart
    true[:, 2] = 0.0008 * (1.0 - v**2) + 0.0003 * u * v  # curled along y, a little twist
    return nominal, true


@functools.cache
def _dataset() -> tuple[dict, np.ndarray, np.ndarray]:
    nominal, true = _boards()
    rng = np.random.default_rng(7)
    centre = true.mean(axis=0)
    images = []
    for k in range(16):
        # the board fills a different part of the field each time, tilted up to ~45 deg
        R = rotation_exp(rng.uniform(-0.7, 0.7, 3))
        look = rotation_exp(np.array([rng.uniform(-0.9, 0.9), rng.uniform(-0.9, 0.9), 0.0]))
        distance = rng.uniform(0.35, 0.6)
        t = look @ np.array([0.0, 0.0, distance]) - R @ centre
        uv = LENS.project((R @ true.T).T + t)
        uv = uv + rng.normal(0.0, NOISE_PX, uv.shape)
        inside = np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] > 0) & (uv[:, 0] < WIDTH - 1) & (uv[:, 1] > 0) & (uv[:, 1] < HEIGHT - 1)
        if inside.sum() < 20:
            continue
        images.append(
            {
                "id": f"view{k:02d}",
                "observations": [
                    {"target": f"C{n:03d}", "uv": uv[n].tolist()} for n in np.flatnonzero(inside)
                ],
            }
        )
    doc = {
        "format": "gtsam-sphere/dataset@1",
        "camera": {"width": WIDTH, "height": HEIGHT},
        "targets": [
            {"id": f"C{n:03d}", "xyz": p.tolist(), "sigma": 0} for n, p in enumerate(nominal)
        ],
        "images": images,
    }
    return doc, nominal, true


@functools.cache
def _calibrate(control_sigma: float | None):
    doc, _, _ = _dataset()
    # the lens is equidistant: the radial mapping with no extra terms is exact
    options = CalibrationOptions(
        model="radial", radial_terms=0, brown_terms=(), control_sigma=control_sigma
    )
    return calibrate(parse_dataset(doc, "curled board"), options)


def _shape_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` (N, 3) moved by the best similarity onto ``b``, minus ``b`` (N, 3).

    The board's scale trades exactly against the camera distances, so only the shape
    up to a similarity is observable (the priors hold the nominal scale).
    """
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    R = u @ d @ vt
    scale = float(np.sum(sv * np.diag(d)) / np.sum((a - ma) ** 2))
    return scale * (R @ (a - ma).T).T + mb - b


@pytest.mark.slow  # end-to-end
def test_the_warp_shows_when_the_board_is_taken_as_exact():
    calib = _calibrate(None)
    assert calib.statistics["rms_px"] > 1.5 * NOISE_PX * np.sqrt(2)
    assert "target_shift_rms" not in calib.statistics


@pytest.mark.slow  # end-to-end
def test_control_sigma_recovers_the_lens_and_the_board_shape():
    exact, free = _calibrate(None), _calibrate(0.002)
    # residuals down to the simulated noise (2D RMS of N(0, 0.05) per axis = 0.071 px)
    assert free.statistics["rms_px"] < 1.2 * NOISE_PX * np.sqrt(2)
    sig = free.statistics["intrinsics_sigma"]
    cam = free.camera
    for est, true, s in (
        (cam.xp, LENS.cx, sig["xp_px"]),
        (cam.yp, LENS.cy, sig["yp_px"]),
        (cam.c, LENS.f, sig["c_px"]),
    ):
        assert abs(est - true) < 4 * s, (est, true, s)
    # the nominal board biases the principal distance by many of its sigmas
    assert abs(exact.camera.c - LENS.f) > 4 * sig["c_px"]
    # the estimated board has the true shape (up to a similarity) to a fraction of the warp
    _, nominal, true = _dataset()
    order = [free.target_ids.index(f"C{n:03d}") for n in range(len(nominal))]
    est = free.target_xyz[order]
    shape_error = np.sqrt(np.mean(np.sum(_shape_residual(est, true) ** 2, axis=1)))
    warp = np.sqrt(np.mean(np.sum(_shape_residual(nominal, true) ** 2, axis=1)))
    assert shape_error < 0.15 * warp, (shape_error, warp)
    assert free.statistics["control_sigma"] == 0.002
    assert 0 < free.statistics["target_shift_rms"] <= free.statistics["target_shift_max"]
    shifts = free.extra["target_shifts"]
    assert len(shifts["target"]) == len(nominal) == len(shifts["shift"])


@pytest.mark.parametrize("bad", [0.0, -1e-3, float("nan"), float("inf")])
def test_bad_control_sigma_is_refused_with_its_value(bad):
    with pytest.raises(ValueError, match="control_sigma"):
        CalibrationOptions(control_sigma=bad)


@pytest.mark.slow  # end-to-end
def test_report_shows_the_board_shape(tmp_path):
    from gtsam_sphere.apps.report import target_shifts_of, write_report

    paths = write_report(_calibrate(0.002), tmp_path / "free")
    md = paths["markdown"].read_text()
    assert paths["target_shifts"].stat().st_size > 1000
    assert "## Target shape" in md and "sigma of 2 mm" in md and "(target_shifts.png)" in md
    # the figure's data: the out-of-plane shifts follow the true curl, the in-plane ones
    # the stretch of the rows
    nominal, shift = target_shifts_of(_calibrate(0.002))
    _, _, true = _dataset()
    assert nominal.shape == shift.shape == true.shape
    assert np.corrcoef(shift[:, 2], true[:, 2])[0, 1] > 0.95
    assert np.corrcoef(shift[:, 1], true[:, 1] - nominal[:, 1])[0, 1] > 0.95
    # an exact board has nothing to show
    paths = write_report(_calibrate(None), tmp_path / "exact")
    assert "target_shifts" not in paths
    assert "## Target shape" not in paths["markdown"].read_text()
