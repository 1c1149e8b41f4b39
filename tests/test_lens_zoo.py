"""A fast subset of the lens zoo (benchmarks/bench_lens_zoo.py): default options, no
prior knowledge of the lens, a trusted result within 1.15x of the oracle.

The cases are the zoo's own (same builder, same seeds), chosen to span the scenes and the
image circles: a 250 deg equidistant lens on a circle of 0.4 x the short side with its
principal point 10 % / 6 % off the centre (the room), a 340 deg equisolid lens on a
cropped circle and a 200 deg orthographic (sphere) lens on a 3D object, a 250 deg
orthographic lens whose image folds (the radial model folds with it: the sphere model
takes over, ``statistics.model_fallback``), and a 220 deg catadioptric (unified) lens in
the room.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_lens_zoo.py"


def _zoo():
    spec = importlib.util.spec_from_file_location("bench_lens_zoo", _BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


ZOO = _zoo()
CASES = {c.id: c for c in ZOO.build_cases()}
SUBSET = (
    "11-equidistant-250-room-r0.4s",
    "20-equisolid-340-object3d-r1.3d",
    "32-sphere-200-object3d-r1.3d",
    "33-sphere-250-room-r0.25s",
    "46-unified-220-room-r1.3d",
    "35-sphere-360-object3d-r0.4s-imp",
)
FOLDED = "35-sphere-360-object3d-r0.4s-imp"
#: cases of the second case list (``--seed 1``), which nothing was tuned on, that failed
#: there: a 260 deg lens whose circle the sensor crops (no disc was found, every
#: hypothesis at the image centre failed), a 360 deg orthographic lens off the centre
#: (the folded lens was only tried at the centre), a 300 deg lens on a 3D object
#: (GTSAM's Marginals refused the ill-conditioned system: "singular", untrusted)
SEED1 = {c.id: c for c in ZOO.build_cases(1)}
SEED1_SUBSET = (
    "59-fov-260-room-r0.5s-imp",
    "35-sphere-360-object3d-r0.4s",
    "26-stereographic-300-object3d-r0.4s-imp",
)
#: cases of the sixth list (``--seed 5``, first run in session 12) that were trusted at
#: 327x and 50x the oracle's 3D error: a 170 deg orthographic lens on a board (13 of 20
#: boards posed mirrored behind the camera, which the folded lens images the same) and
#: a 150 deg pinhole lens with an error field on an object (a wild initial polynomial,
#: then a term selection that multiplied sigma by 19)
SEED5 = {c.id: c for c in ZOO.build_cases(5)}
SEED5_SUBSET = (
    "31-sphere-170-board-diag-imp",
    "05-pinhole-150-object3d-r0.4s-imp",
)


def test_the_zoo_has_every_family_scene_and_circle():
    """The benchmark's case list covers what issue 12 asks for (at least 60 cases)."""
    cases = list(CASES.values())
    assert len(cases) >= 60
    assert {c.family for c in cases} >= {
        "pinhole",
        "equidistant",
        "equisolid",
        "stereographic",
        "sphere",
        "kannala-brandt",
        "unified",
        "double-sphere",
        "fov",
    }
    assert {c.scene for c in cases} == {"room", "board", "object3d"}
    radii = [c.radius_over_short for c in cases]
    assert min(radii) <= 0.25 + 1e-9 and max(radii) >= 1.0
    assert max(c.fov_deg for c in cases) >= 340 and min(c.fov_deg for c in cases) <= 60
    assert max(max(abs(o) for o in c.pp_offset) for c in cases) >= 0.1
    assert set(SUBSET) <= set(CASES)


@pytest.mark.slow
@pytest.mark.parametrize(
    "cases, case_id",
    [(CASES, c) for c in SUBSET]
    + [(SEED1, c) for c in SEED1_SUBSET]
    + [(SEED5, c) for c in SEED5_SUBSET],
    ids=[
        *SUBSET,
        *(f"seed1-{c}" for c in SEED1_SUBSET),
        *(f"seed5-{c}" for c in SEED5_SUBSET),
    ],
)
def test_zoo_case_default_calibration_matches_the_oracle(cases, case_id, tmp_path):
    row = ZOO.run_case(cases[case_id], tmp_path)
    assert "error" not in row, row.get("error")
    assert row["success"], row.get("distrust")
    assert row["ratio"] <= 1.15, row
    assert row["pp_error_px"] < 1.0


def _initialise_case(case):
    """Simulate a zoo case and initialise it; returns (simulation, result, progress
    lines, the worst initial rotation error in degrees over the images)."""
    import numpy as np
    from helpers import initialise_simulation

    from gtsam_sphere.simulate import simulate_room

    sim = simulate_room(case.options())
    data, res, messages = initialise_simulation(sim)
    truth = {im["id"]: im["cam_from_world"] for im in sim.truth["images"]}
    worst = 0.0
    for k, image_id in enumerate(data.image_ids):
        if not res.ok[k]:
            continue
        R_true = np.asarray(truth[image_id]["R"], float)
        cos = (np.trace(res.cam_from_world_R[k].T @ R_true) - 1) / 2
        worst = max(worst, float(np.degrees(np.arccos(np.clip(cos, -1, 1)))))
    return sim, res, messages, worst


@pytest.mark.slow
def test_a_folded_lens_is_initialised_on_both_hemispheres():
    """A 360 deg orthographic lens (r = f sin(alpha)) images two rays on every pixel; the
    object is seen behind the camera in some views. The folded hypothesis lets RANSAC
    take the ray each pose predicts: every view is posed right (7 of 15 were 19-116 deg
    wrong before, and the calibration was not trusted)."""
    _, res, _, worst_deg = _initialise_case(CASES[FOLDED])
    assert res.lens.folded and res.mapping == "sphere", res.lens.describe()
    assert res.ok.all()
    assert worst_deg < 2.0, worst_deg
    assert res.inlier_mask.mean() > 0.95


@pytest.mark.slow
def test_a_board_seen_by_a_folded_lens_is_posed_in_front_of_it():
    """Seed 5 case 31: a 170 deg orthographic lens on a board. The folded hypothesis
    (chosen by 2 %) images a ray and its mirror behind the camera at the same pixel, so
    every board has a mirror pose with the same image; RANSAC returned it for 13 of 20.
    They are turned back to the front, where the lens sees: every initial rotation within
    7.1 deg of the truth (the mirrored ones were 41-131 deg off)."""
    _, res, messages, worst_deg = _initialise_case(SEED5["31-sphere-170-board-diag-imp"])
    assert res.lens.folded, res.lens.describe()
    assert any(m.endswith("taken in front") for m in messages), messages
    assert res.ok.all()
    assert worst_deg < 10.0, worst_deg


@pytest.mark.slow
def test_a_wide_perspective_lens_is_refitted_with_its_own_warp():
    """Seed 1 case 05: a 150 deg pinhole lens with strong Brown terms filling the
    diagonal, seen on a 3D object. The pinhole family was zoomed third, behind two
    families of warp 0 that were the only ones refitted: the stereographic polynomial
    left 40 % of the observations inconsistent, and the calibration spent two full
    robust adjustments (3.3x the zoo's median time) finding the warp. Refitting the
    best family of another warp finds the perspective lens at once."""
    _, res, messages, worst_deg = _initialise_case(SEED1["05-pinhole-150-object3d-diag-imp"])
    assert res.mapping == "pinhole" and res.lens.warp_w < 0, messages
    assert res.ok.all()
    assert res.inlier_mask.mean() > 0.95, messages
    assert worst_deg < 2.0, worst_deg


@pytest.mark.slow
def test_a_refit_far_below_the_other_hypothesis_is_not_followed_by_a_second():
    """Seed 0 case 05: a 150 deg pinhole lens on a 3D object. Its first refit costs 0.10
    times the second hypothesis' zoomed cost, whose refit lost (488 against 63): the
    second refit is skipped (``_BEATEN_REFIT``) and the lens found is the same. The
    other side, a second refit that wins (0.70), is seed 1 case 05 above."""
    _, res, messages, worst_deg = _initialise_case(CASES["05-pinhole-150-object3d-diag"])
    skipped = [m for m in messages if m.endswith("no second refit")]
    assert len(skipped) == 1 and "times the" in skipped[0], messages
    assert sum(m.startswith("refit:") for m in messages) == 1, messages
    assert res.mapping == "pinhole" and res.ok.all()
    assert res.inlier_mask.mean() > 0.95, messages
    assert worst_deg < 2.0, worst_deg


SEED3 = {c.id: c for c in ZOO.build_cases(3)}


@pytest.mark.slow
@pytest.mark.parametrize(
    "case, trigger, skipped",
    [
        # the initial lens is the folded orthographic one: no radial adjustment at all
        (CASES["33-sphere-250-room-r0.25s"], "initial lens is the folded", "adjusting:"),
        # the initial lens is a polynomial; its first adjustment folds at 89.5 deg after
        # its first robust stage: no more stages (each crawled 100 iterations), no warp
        # or term selection, no kNN round of the radial model (seed 3 case 33 ran both
        # models in full: 5.7x the list's median time)
        (
            SEED3["33-sphere-250-room-r1.3d"],
            "a first-adjustment stage's mapping folds",
            "kNN round",
        ),
    ],
    ids=["folded-initial-lens", "folds-in-first-adjustment"],
)
def test_a_lens_that_folds_goes_to_the_sphere_model_early(case, trigger, skipped):
    """A 250 deg orthographic lens: the radial model cannot follow its fold, so the
    sphere model runs as soon as the fold shows, and is kept."""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    early = [i for i, line in enumerate(lines) if "cannot follow this lens" in line]
    assert len(early) == 1 and trigger in lines[early[0]], lines
    assert not any(line.startswith(skipped) for line in lines[: early[0]]), lines
    assert not any("terms the data do not support" in line for line in lines[: early[0]])
    # at most the least-squares stage and one robust stage before the fold is seen
    scales = [line for line in lines[: early[0]] if line.startswith("robust scale estimate")]
    assert len(scales) <= 2, scales
    assert calib.statistics["trusted"]
    assert str(calib.model) == "sphere+knn"
    assert calib.statistics["model_fallback"].startswith("radial+knn -> sphere+knn")


def test_the_stress_draws_are_seeded_and_reach_beyond_the_lists():
    """``--stress``: the same seed draws the same cases; they reach the sizes, noise,
    blunders, image counts and narrow pinholes the lists leave out; the lists' cases keep
    the simulator's noise and no blunders (their simulations are unchanged)."""
    a, b = ZOO.build_stress_cases(3, 200), ZOO.build_stress_cases(3, 200)
    assert a == b and a != ZOO.build_stress_cases(4, 200)
    assert len({c.id for c in a}) == 200
    assert {c.family for c in a} == set(ZOO.FAMILIES)
    assert {c.scene for c in a} == set(ZOO.SCENES)
    assert {(c.width, c.height) for c in a} == set(ZOO.STRESS_SIZES)
    assert {c.noise_px for c in a} == set(ZOO.STRESS_NOISE_PX)
    assert {c.blunder_rate for c in a} == set(ZOO.STRESS_BLUNDERS)
    assert {c.n_images for c in a} == set(ZOO.STRESS_IMAGES)
    pinholes = [c.fov_deg for c in a if c.family == "pinhole"]
    assert min(pinholes) < 60.0 and all(40.0 <= f <= 150.0 for f in pinholes)
    for c in a:
        fovs = ZOO.FAMILIES[c.family]
        assert c.fov_deg <= max(fovs) and (c.circle is not None or c.fov_deg < 180.0)
        assert max(abs(o) for o in c.pp_offset) <= 0.1
        opts = c.options()
        assert (opts.noise_px, opts.blunder_rate) == (c.noise_px, c.blunder_rate)
    listed = next(iter(CASES.values())).options()
    assert (listed.noise_px, listed.blunder_rate) == (0.3, 0.0)


#: found by random draws beyond the lists (session 17): a 215 deg catadioptric lens
#: (unified, xi 2.17: its rim squeezed toward a fold at 117.5 deg) on a 240 px circle
#: of a 752x480 sensor, a 3D object, 1 px noise and 2 % blunders. An early radial stage
#: folded at 82.5 deg, the sphere model took over at 2.65 px robust sigma against the
#: radial stage's 1.01 px, its kNN rounds learned the misfit as a 2 px "field", and the
#: result was trusted at 20x the oracle's 3D error with c 36 % off.
SILENT_UNIFIED = ZOO.Case(
    id="found-unified-215-object3d-752x480-n1-b0.02",
    family="unified",
    fov_deg=215.0,
    width=752,
    height=480,
    circle=0.5,
    pp_offset=(-0.029064192557019405, 0.030394603892081012),
    scene="object3d",
    n_images=15,
    pupil_shift_m=0.0,
    error_field_px=0.0,
    seed=372618933,
    lens_options={"xi": 2.1657},
    noise_px=1.0,
    blunder_rate=0.02,
)


#: ``--stress 40 --seed 201`` case s09: a 98 deg double-sphere lens on a board, 5 %
#: blunders. The first adjustment's second stage saw rays at 96 deg and folded at 88;
#: the sphere model fit about as well (1.19 against 0.98 px) and its kNN loop learned the
#: misfit over 13 rounds: trusted at 48x the oracle's 3D error, c 15 % off.
SILENT_DOUBLE_SPHERE = next(
    c for c in ZOO.build_stress_cases(201, 40) if c.id.startswith("s09-double-sphere-98-board")
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "case", [SILENT_UNIFIED, SILENT_DOUBLE_SPHERE], ids=["unified-215", "double-sphere-98"]
)
def test_a_lens_that_does_not_fold_is_no_silent_sphere_answer(case):
    """The cases above: no sphere model stands in for them, and the result is either
    right or untrusted. (Since the first stage's starts are ranked by a truncated cost,
    neither radial run folds early any more; the rules that refused the sphere model
    for them, :func:`~gtsam_sphere.estimation.calibrate.sphere_fits_worse` and
    :func:`~gtsam_sphere.estimation.calibrate.sphere_learns_a_misfit`, are tested in
    ``test_calibrate.py``.)"""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    sim = simulate_room(case.options())
    calib = calibrate(parse_dataset(sim.dataset), None)
    assert "model_fallback" not in calib.statistics
    c_true = ZOO._axis_scale_px(sim.lens)
    assert not calib.statistics["trusted"] or abs(calib.camera.c / c_true - 1.0) < 0.05


def test_the_summary_counts_trusted_results_far_from_every_reference():
    def row(i, success, ratio, family, blind=None):
        r = {"id": f"c{i}", "success": success, "ratio": ratio, "family_ratio": family}
        if blind is not None:
            r["field_blind_ratio"] = blind
        return r

    rows = [
        row(0, True, 1.0, 1.0),
        row(1, True, 48.0, 46.0),  # silent
        row(2, False, 48.0, 46.0),  # wrong, but not trusted
        row(3, True, 2.5, 2.6, 0.85),  # an error field the poses absorb
        row(4, True, 3.0, 1.1),  # estimating pp and c costs this much here
        row(5, True, 5.0, 4.0, 3.0),  # silent, error field or not
    ]
    line = next(ln for ln in ZOO.summary_lines(rows) if ln.startswith("trusted but over"))
    assert line.endswith(": 2 (c1, c5)"), line


#: ``--stress`` draws with blunders on a board that ended not trusted (c 80 % and 350 %
#: off) when the first stage's start with every observation won on Huber's cost: the
#: poses and the mapping had bent toward the blunders
BLUNDER_BOARDS = {
    "s30-pinhole-114": (202, "s30-pinhole-114-board-1024x1024-n0.5-b0.02"),
    "s12-equisolid-85": (204, "s12-equisolid-85-board-640x480-n0.1-b0.05"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BLUNDER_BOARDS))
def test_a_board_with_blunders_starts_from_the_clean_first_stage(name):
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    seed, case_id = BLUNDER_BOARDS[name]
    case = next(c for c in ZOO.build_stress_cases(seed, 40) if c.id == case_id)
    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    first = next(ln for ln in lines if ln.startswith("truncated cost of stage 1"))
    with_all, without = (float(v) for v in first.split(": ")[1].split(" / "))
    assert without < with_all, first
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    assert abs(calib.camera.c / ZOO._axis_scale_px(sim.lens) - 1.0) < 0.01


@pytest.mark.slow
def test_an_affinity_pulled_by_blunders_does_not_win_the_first_stage():
    """``--stress 40 --seed 203`` s18: a 105 deg field-of-view object, 640x480, 2 %
    blunders. Least squares on every observation inflated the affinity ``a1`` to 0.59
    and moved the principal point 500 px; in corrected coordinates that start fitted
    better than the clean one (median 0.43 against 0.59 px) and won, and the
    calibration ended untrusted at 45x the oracle's 3D error after 290 s. Ranked in raw
    pixels it lost by 4x; with the residual's decentering and affinity undone
    (``sphere_residual``) it no longer gets that far and loses by 1.9x. The
    re-adjustments no longer run it."""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    case = next(c for c in ZOO.build_stress_cases(203, 40) if c.id.startswith("s18-"))
    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    ranked = [ln for ln in lines if ln.startswith("truncated cost of stage 1")]
    assert len(ranked) == 1, ranked  # only the first adjustment ranks two starts
    with_all, without = (float(v) for v in ranked[0].split(": ")[1].split(" / "))
    assert without < with_all, ranked[0]
    assert any(ln.startswith("stage 1 without") for ln in lines)  # the re-adjustments
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    assert abs(calib.camera.c / ZOO._axis_scale_px(sim.lens) - 1.0) < 0.01
    xp, yp = calib.camera.principal_point_px
    assert np.hypot(xp - sim.lens.cx, yp - sim.lens.cy) < 2.0


@pytest.mark.slow
def test_a_folding_lens_the_search_took_for_a_polynomial_is_not_a_silent_answer():
    """``--stress 40 --seed 209 --defects`` s38: a 322 deg orthographic object, 640x480,
    1 px noise, a sensor with ``a1 = 0.016``. The affinity made the fitted (odd
    polynomial) lens win the search over the folded one; seen through a fold the
    radial geometry is wrong: 18 % of the observations beyond 5 sigma (20 % was the
    limit), trusted at 69x the oracle's 3D error. Now such a share is not trusted
    (10 %), and the sphere model with the decentering and affinity terms, started from
    the folded lens the search scored, is trusted instead, its principal distance and
    principal point right."""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    case = next(c for c in ZOO.build_stress_cases(209, 40, defects=True) if c.id.startswith("s38-"))
    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    assert any("observations are beyond 5 sigma) and the lens may fold" in ln for ln in lines)
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    assert "the lens may fold" in calib.statistics["model_fallback"]
    assert calib.model == "brown+knn" and calib.camera.radial is None
    assert calib.camera.brown["a1"] == pytest.approx(case.lens_options["a1"], abs=2e-3)
    xp, yp = calib.camera.principal_point_px
    assert np.hypot(xp - sim.lens.cx, yp - sim.lens.cy) < 2.0
    # the sphere model's c is the lens's f (the affinity scales x only)
    assert calib.camera.c == pytest.approx(sim.lens.f, rel=5e-3)


@pytest.mark.slow
def test_a_knn_loop_caught_in_a_cycle_of_two_rounds_is_stable():
    """``--stress 40 --seed 210`` s04: a 46 deg pinhole room, 161 observations, 2 %
    blunders. The kNN training set flipped between 145 and 142 observations (CV RMS
    0.0969 and 0.0902 px) for all 25 rounds and the calibration was not trusted at
    1.00x the oracle's 3D error; a round back within tolerance of the one before the
    previous one ends the loop."""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    case = next(c for c in ZOO.build_stress_cases(210, 40) if c.id.startswith("s04-"))
    sim = simulate_room(case.options())
    lines: list[str] = []
    calib = calibrate(parse_dataset(sim.dataset), None, lines.append)
    assert any(ln.endswith("(a cycle of two rounds)") for ln in lines)
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    assert calib.statistics["knn_rounds"] == 3


@pytest.mark.slow  # 6,326 observations, and the fallbacks an untrusted result tries: ~2 min
def test_a_first_adjustment_that_drifts_from_its_first_stage_is_not_trusted():
    """``--stress 40 --seed 3201 --targets --defects --shapes`` s06: a 332 deg sphere
    lens on a 3D object (752x480, 0.1 px). The first stage fitted the 78 % of the
    observations the initialisation explained at a robust scale of 0.17 px; the Huber
    stages then let the other 22 % pull the lens to c = 4,714 px (true 528) and a 7 deg
    field at 9.9 px, trusted at 10.9x the known-family adjustment's 3D error. A final
    scale above ``SIGMA_GROWTH`` times the smallest a first-adjustment stage reached is
    not trusted."""
    from gtsam_sphere.estimation.calibrate import Distrust, calibrate
    from gtsam_sphere.io.dataset import parse_dataset
    from gtsam_sphere.simulate import simulate_room

    cases = ZOO.build_stress_cases(3201, 40, defects=True, targets=True, shapes=True)
    case = next(c for c in cases if c.id.startswith("s06-"))
    assert case.id.startswith("s06-sphere-332-object3d-752x480")
    sim = simulate_room(case.options())
    st = calibrate(parse_dataset(sim.dataset), None).statistics
    assert not st["trusted"]
    assert Distrust.SIGMA_GROWTH in st["distrust_codes"]
    assert st["sigma_px"] > 10 * st["first_stage_sigma_px"]


@pytest.mark.slow  # 1,156 observations and the oracles: ~15 s
def test_a_free_target_a_blunder_pulls_onto_a_camera_centre_does_not_stall(tmp_path, capsys):
    """``--stress 40 --seed 3201 --targets --defects --shapes`` s32: a 289 deg
    field-of-view room with free targets and 2 % blunders. Target T0068, seen in two
    images, one through a blunder, crept along its good ray into that camera's centre
    during the final Cauchy stage; LM then found no step (any step crossed the centre)
    and the calibration was not trusted (stalled) at 1.22x the oracle's 3D error. The
    robust stages now hold such targets out."""
    cases = ZOO.build_stress_cases(3201, 40, defects=True, targets=True, shapes=True)
    case = next(c for c in cases if c.id.startswith("s32-"))
    assert case.id.startswith("s32-fov-289-room-1024x1024")
    row = ZOO.run_case(case, tmp_path, verbose=True)
    out = capsys.readouterr().err  # the progress lines
    assert "held out of this stage" in out
    assert "stalled" not in out
    assert row["success"], row.get("distrust")
    assert row["ratio"] <= 1.15, row
