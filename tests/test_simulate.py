"""Tests of the seeded room simulator (gtsam_sphere.simulate)."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from gtsam_sphere.simulate import (
    SimulationOptions,
    add_cli_arguments,
    gopro_like,
    lens_from_dict,
    nikon_like,
    run_cli,
    simulate_room,
    write_simulation,
)

SMALL = {"n_images": 12, "width": 1600, "height": 1200}


def _check_dataset(ds: dict) -> None:
    assert ds["format"] == "gtsam-sphere/dataset@1"
    assert ds["units"] == "m"
    w, h = ds["camera"]["width"], ds["camera"]["height"]
    target_ids = [t["id"] for t in ds["targets"]]
    assert len(set(target_ids)) == len(target_ids)
    image_ids = [im["id"] for im in ds["images"]]
    assert len(set(image_ids)) == len(image_ids)
    known = set(target_ids)
    for t in ds["targets"]:
        assert len(t["xyz"]) == 3 and np.isfinite(t["xyz"]).all()
    for im in ds["images"]:
        obs = im["observations"]
        assert len(obs) >= 8
        names = [o["target"] for o in obs]
        assert len(set(names)) == len(names), im["id"]
        assert set(names) <= known
        uv = np.array([o["uv"] for o in obs])
        assert np.isfinite(uv).all()
        assert (uv[:, 0] >= -0.5).all() and (uv[:, 0] <= w - 0.5).all()
        assert (uv[:, 1] >= -0.5).all() and (uv[:, 1] <= h - 0.5).all()


def test_determinism_and_seed_dependence():
    opts = SimulationOptions(lens="kannala-brandt", fov_deg=150, blunder_rate=0.02, **SMALL)
    a, b = simulate_room(opts), simulate_room(opts)
    for key in ("dataset", "checkpoints", "truth"):
        assert json.dumps(getattr(a, key)) == json.dumps(getattr(b, key))
    c = simulate_room(opts, rng=np.random.default_rng(opts.seed))
    assert json.dumps(c.dataset) == json.dumps(a.dataset)
    d = simulate_room(SimulationOptions(lens="kannala-brandt", fov_deg=150, seed=1, **SMALL))
    assert json.dumps(d.dataset) != json.dumps(a.dataset)


@pytest.mark.parametrize(
    "opts",
    [
        SimulationOptions(**SMALL),
        nikon_like(n_images=10),
        gopro_like(n_images=10, blunder_rate=0.05),
        SimulationOptions(lens="unified", fov_deg=200, lens_options={"xi": 1.2}, **SMALL),
    ],
    ids=["default", "nikon", "gopro", "unified200"],
)
def test_dataset_format(opts):
    sim = simulate_room(opts)
    _check_dataset(sim.dataset)
    assert len(sim.dataset["images"]) == opts.n_images
    cp = sim.checkpoints
    assert cp["format"] == "gtsam-sphere/checkpoints@1" and cp["units"] == "m"
    ds_ids = {t["id"] for t in sim.dataset["targets"]}
    assert {t["id"] for t in cp["targets"]} <= ds_ids
    assert len(cp["targets"]) == min(opts.n_checkpoints, len(ds_ids))
    assert sim.truth["format"] == "gtsam-sphere/truth@1"
    json.dumps(sim.truth)  # JSON-ready


def test_observations_match_truth_without_noise():
    opts = SimulationOptions(lens="equisolid", fov_deg=190, noise_px=0.0, **SMALL)
    sim = simulate_room(opts)
    truth = sim.truth
    xyz = {t["id"]: np.array(t["xyz"]) for t in truth["targets"]}
    lens = lens_from_dict(truth["lens"])
    for im, pose in zip(sim.dataset["images"], truth["images"], strict=True):
        assert im["id"] == pose["id"]
        r = np.array(pose["cam_from_world"]["R"])
        t = np.array(pose["cam_from_world"]["t"])
        assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
        pts = np.array([xyz[o["target"]] for o in im["observations"]])
        uv = np.array([o["uv"] for o in im["observations"]])
        assert np.abs(lens.project(pts @ r.T + t) - uv).max() < 1e-9
        # the camera centre is inside the room
        centre = -r.T @ t
        assert (centre > 0).all() and (centre < opts.room_size_m).all()


def test_checkpoints_are_true_coordinates():
    sim = simulate_room(SimulationOptions(n_checkpoints=191, **SMALL))
    xyz = {t["id"]: t["xyz"] for t in sim.truth["targets"]}
    for t in sim.checkpoints["targets"]:
        assert t["xyz"] == xyz[t["id"]]


@pytest.mark.parametrize(("rate", "seed"), [(0.0, 0), (0.05, 1), (0.1, 2), (0.013, 3)])
def test_blunders_counted(rate, seed):
    opts = SimulationOptions(blunder_rate=rate, seed=seed, noise_px=0.0, **SMALL)
    sim = simulate_room(opts)
    n_obs = sum(len(im["observations"]) for im in sim.dataset["images"])
    blunders = sim.truth["blunders"]
    assert len(blunders) == round(rate * n_obs)
    kinds = [b["kind"] for b in blunders]
    assert set(kinds) <= {"mislabel", "offset"}
    if rate >= 0.05:
        assert 0.3 < kinds.count("mislabel") / len(kinds) < 0.7
    # blunders really are gross: they disagree with the true projection by > 5 px
    lens = sim.lens
    xyz = {t["id"]: np.array(t["xyz"]) for t in sim.truth["targets"]}
    poses = {p["id"]: p["cam_from_world"] for p in sim.truth["images"]}
    obs = {
        (im["id"], o["target"]): o["uv"] for im in sim.dataset["images"] for o in im["observations"]
    }
    for b in blunders:
        pose = poses[b["image"]]
        p = np.array(pose["R"]) @ xyz[b["target"]] + pose["t"]
        err = np.linalg.norm(lens.project(p[None])[0] - obs[(b["image"], b["target"])])
        assert err > 5.0 or not np.isfinite(err)
    # and the others are exact (noise_px = 0)
    bad = {(b["image"], b["target"]) for b in blunders}
    good = [k for k in obs if k not in bad][:200]
    for image, target in good:
        pose = poses[image]
        p = np.array(pose["R"]) @ xyz[target] + pose["t"]
        assert np.abs(lens.project(p[None])[0] - obs[(image, target)]).max() < 1e-9


def test_portrait_and_landscape():
    sim = simulate_room(SimulationOptions(**SMALL))
    kinds = [im["orientation"] for im in sim.truth["images"]]
    assert kinds.count("portrait") == kinds.count("landscape") == 6
    for im in sim.truth["images"]:
        r = np.array(im["cam_from_world"]["R"])
        up_in_cam = r @ [0.0, 0.0, 1.0]  # world up seen from the camera
        if im["orientation"] == "landscape":
            assert abs(up_in_cam[1]) > abs(up_in_cam[0])  # up is along -v
        else:
            assert abs(up_in_cam[0]) > abs(up_in_cam[1])  # up is along u


def test_sigma_modes():
    base = dict(target_sigma_m=0.02, **SMALL)
    weighted = simulate_room(SimulationOptions(sigma_mode="weighted", **base)).dataset
    free = simulate_room(SimulationOptions(sigma_mode="free", **base)).dataset
    fixed = simulate_room(SimulationOptions(sigma_mode="fixed", **base))
    assert all(t["sigma"] == 0.02 for t in weighted["targets"])
    assert all("sigma" not in t for t in free["targets"])
    assert all(t["sigma"] == 0.0 for t in fixed.dataset["targets"])
    true = {t["id"]: t["xyz"] for t in fixed.truth["targets"]}
    assert all(t["xyz"] == true[t["id"]] for t in fixed.dataset["targets"])
    diffs = np.array([np.subtract(t["xyz"], true[t["id"]]) for t in weighted["targets"]])
    assert 0.015 < diffs.std() < 0.025
    with pytest.raises(ValueError, match="sigma_mode"):
        simulate_room(SimulationOptions(sigma_mode="loose", **SMALL))


@pytest.mark.parametrize("fov", [200.0, 300.0])
def test_sphere_lens_sees_behind(fov):
    sim = simulate_room(SimulationOptions(lens="sphere", fov_deg=fov, **SMALL))
    stats = sim.truth["statistics"]
    assert stats["n_observations_beyond_90deg"] > 0
    assert 90.0 < stats["max_incidence_deg"] <= fov / 2 + 1e-9
    _check_dataset(sim.dataset)


def test_imperfections_and_presets():
    nikon, gopro = nikon_like(), gopro_like()
    assert (nikon.n_images, nikon.fov_deg, nikon.lens) == (44, 75.0, "pinhole")
    assert gopro.n_images == 52 and gopro.fov_deg == 150.0
    sim = simulate_room(gopro_like(n_images=6))
    assert sim.truth["lens"]["kind"] == "error-field"
    assert sim.truth["lens"]["lens"]["kind"] == "non-central"


def test_targets_on_room_surfaces():
    opts = SimulationOptions(**SMALL)
    sim = simulate_room(opts)
    xyz = np.array([t["xyz"] for t in sim.truth["targets"]])
    assert len(xyz) == opts.n_targets
    size = np.array(opts.room_size_m)
    on_face = np.isclose(xyz, 0.0).any(axis=1) | np.isclose(xyz, size).any(axis=1)
    assert on_face.all()
    faces = {t["face"] for t in sim.truth["targets"]}
    assert len(faces) == 6


def test_write_simulation_and_cli(tmp_path, capsys):
    sim = simulate_room(SimulationOptions(**SMALL))
    paths = write_simulation(sim, tmp_path / "a")
    for key, path in paths.items():
        assert json.loads(path.read_text()) == json.loads(json.dumps(getattr(sim, key)))
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [
        "checkpoints.json",
        "dataset.json",
        "truth.json",
    ]
    parser = add_cli_arguments(argparse.ArgumentParser())
    args = parser.parse_args(
        ["--lens", "sphere", "--fov-deg", "220", "--n-images", "8", "--width", "800"]
        + ["--height", "600", "--blunder-rate", "0.02", "--sigma-mode", "free"]
        + ["--seed", "5", "-o", str(tmp_path / "b")]
    )
    assert run_cli(args) == 0
    out = capsys.readouterr().out
    assert "images 8" in out and "max incidence" in out
    ds = json.loads((tmp_path / "b" / "dataset.json").read_text())
    _check_dataset(ds)
    assert all("sigma" not in t for t in ds["targets"])
    bad = parser.parse_args(["--lens", "pinhole", "--fov-deg", "190", "-o", str(tmp_path / "c")])
    assert run_cli(bad) == 2


# -- scenes, image circle, principal point ---------------------------------------------

OBJECTS = {"n_images": 12, "width": 1280, "height": 800}


def _observed_geometry(sim):
    """Per observation: camera-frame point, pixel, target normal and view vector."""
    xyz = {t["id"]: np.array(t["xyz"]) for t in sim.truth["targets"]}
    nrm = {t["id"]: np.array(t["normal"]) for t in sim.truth["targets"]}
    rows = []
    for im, pose in zip(sim.dataset["images"], sim.truth["images"], strict=True):
        r = np.array(pose["cam_from_world"]["R"])
        t = np.array(pose["cam_from_world"]["t"])
        centre = np.array(pose["centre_world"])
        for o in im["observations"]:
            p = xyz[o["target"]]
            rows.append((r @ p + t, o["uv"], nrm[o["target"]], p - centre))
    p_cam, uv, normals, view = (np.array(c) for c in zip(*rows, strict=True))
    return p_cam, uv, normals, view


@pytest.mark.parametrize("scene", ["board", "object3d"])
def test_scenes_deterministic_valid_and_exact(scene):
    from gtsam_sphere.io.dataset import parse_dataset

    opts = SimulationOptions(scene=scene, lens="equidistant", fov_deg=190, **OBJECTS)
    a, b = simulate_room(opts), simulate_room(opts)
    for key in ("dataset", "checkpoints", "truth"):
        assert json.dumps(getattr(a, key)) == json.dumps(getattr(b, key))
    c = simulate_room(SimulationOptions(scene=scene, seed=4, fov_deg=190, **OBJECTS))
    assert json.dumps(c.dataset) != json.dumps(a.dataset)
    _check_dataset(a.dataset)
    ds = parse_dataset(a.dataset)
    assert ds.n_observations == a.truth["statistics"]["n_observations"]
    assert len(a.dataset["images"]) == opts.n_images
    assert a.truth["scene"] == scene
    # exact control by default: sigma 0 and the true coordinates
    true = {t["id"]: t["xyz"] for t in a.truth["targets"]}
    assert all(t["sigma"] == 0.0 and t["xyz"] == true[t["id"]] for t in a.dataset["targets"])
    assert all(t["xyz"] == true[t["id"]] for t in a.checkpoints["targets"])
    faces = {t["face"] for t in a.truth["targets"]}
    assert faces == ({"board"} if scene == "board" else {"plane_xy", "plane_xz", "plane_yz"})


@pytest.mark.parametrize("scene", ["board", "object3d"])
def test_scene_targets_seen_from_the_front_and_exactly_projected(scene):
    opts = SimulationOptions(scene=scene, lens="fov", fov_deg=200, noise_px=0.0, **OBJECTS)
    sim = simulate_room(opts)
    p_cam, uv, normals, view = _observed_geometry(sim)
    assert np.all(np.sum(normals * view, axis=1) < 0.0)  # the front side only
    assert np.abs(sim.lens.project(p_cam) - uv).max() < 1e-9
    if scene == "board":
        xyz = np.array([t["xyz"] for t in sim.truth["targets"]])
        assert np.allclose(xyz[:, 2], 0.0) and len(xyz) == 12 * 9
        assert np.diff(np.unique(xyz[:, 0]))[0] == pytest.approx(0.04)


def test_board_reaches_behind_a_250_degree_lens_and_fills_a_narrow_one():
    wide = simulate_room(
        SimulationOptions(scene="board", lens="equidistant", fov_deg=250, **OBJECTS)
    )
    stats = wide.truth["statistics"]
    assert 115.0 < stats["max_incidence_deg"] <= 125.0 + 1e-9
    assert stats["n_observations_beyond_90deg"] > 0.1 * stats["n_observations"]
    narrow = simulate_room(SimulationOptions(scene="board", lens="pinhole", fov_deg=60, **OBJECTS))
    for im in narrow.dataset["images"]:
        uv = np.array([o["uv"] for o in im["observations"]])
        extent = np.ptp(uv, axis=0).max() / max(OBJECTS["width"], OBJECTS["height"])
        assert extent > 0.15  # the board is a good part of the image, not a speck
    # all images together cover the image: every cell of a 4 x 4 grid holds observations
    uv = np.array([o["uv"] for im in narrow.dataset["images"] for o in im["observations"]])
    cells = set(map(tuple, np.floor(uv / [OBJECTS["width"] / 4, OBJECTS["height"] / 4])))
    assert len(cells) == 16


@pytest.mark.parametrize("scene", ["room", "board"])
@pytest.mark.parametrize(
    ("fov", "radius_factor", "pp"),
    [(180.0, 0.25, (0.0, 0.0)), (200.0, 1.3, (0.1, -0.1)), (120.0, 0.45, (-0.1, 0.08))],
)
def test_circle_radius_and_principal_point_honoured(scene, fov, radius_factor, pp):
    w, h = 1600, 1200
    short, half_diag = min(w, h), math.hypot(w, h) / 2
    radius = radius_factor * (short if radius_factor < 1 else half_diag)
    cx, cy = (w - 1) / 2 + pp[0] * w, (h - 1) / 2 + pp[1] * h
    opts = SimulationOptions(
        scene=scene,
        lens="equisolid",
        fov_deg=fov,
        width=w,
        height=h,
        circle_radius_px=radius,
        lens_options={"cx": cx, "cy": cy},
        noise_px=0.0,
        n_images=10,
    )
    sim = simulate_room(opts)
    assert (sim.truth["lens"]["cx"], sim.truth["lens"]["cy"]) == (cx, cy)
    p_cam, uv, _, _ = _observed_geometry(sim)
    alpha = np.degrees(np.arctan2(np.hypot(p_cam[:, 0], p_cam[:, 1]), p_cam[:, 2]))
    r = np.hypot(uv[:, 0] - cx, uv[:, 1] - cy)
    assert alpha.max() <= fov / 2 + 1e-9 and r.max() <= radius * (1 + 1e-9)
    m = opts.margin_px
    assert uv.min() >= -0.5 + m and (uv.max(axis=0) <= [w - 0.5 - m, h - 0.5 - m]).all()
    if radius_factor < 1:  # a small circle: the periphery of the circle is used
        assert r.max() > 0.9 * radius
    else:  # a cropped circle: the image border limits the incidence, corners are used
        assert alpha.max() < fov / 2 - 5.0
        corner_r = np.hypot(np.array([-0.5, w - 0.5]) - cx, np.array([-0.5, h - 0.5])[:, None] - cy)
        assert r.max() > 0.85 * corner_r.max()


def test_scene_noise_blunders_and_imperfections():
    opts = SimulationOptions(
        scene="object3d",
        lens="double-sphere",
        fov_deg=220,
        blunder_rate=0.05,
        pupil_shift_m=0.002,
        error_field_px=1.5,
        sigma_mode="weighted",
        **OBJECTS,
    )
    sim = simulate_room(opts)
    n_obs = sim.truth["statistics"]["n_observations"]
    assert len(sim.truth["blunders"]) == round(0.05 * n_obs)
    assert sim.truth["lens"]["kind"] == "error-field"
    assert all(t["sigma"] == opts.target_sigma_m for t in sim.dataset["targets"])
    _check_dataset(sim.dataset)


def test_scene_validation():
    with pytest.raises(ValueError, match="scene"):
        simulate_room(SimulationOptions(scene="cave", **OBJECTS))
    with pytest.raises(ValueError, match="board"):
        simulate_room(SimulationOptions(scene="board", board_shape=(1, 9), **OBJECTS))


def test_cli_scene_circle_and_principal_point(tmp_path, capsys):
    parser = add_cli_arguments(argparse.ArgumentParser())
    args = parser.parse_args(
        ["--scene", "board", "--lens", "double-sphere", "--fov-deg", "230"]
        + ["--lens-option", "xi=-0.1", "--lens-option", "alpha=0.6", "--n-images", "8"]
        + ["--width", "1600", "--height", "1200", "--cx", "900", "--cy", "650"]
        + ["--circle-radius-px", "700", "-o", str(tmp_path / "b")]
    )
    assert run_cli(args) == 0
    assert "scene board" in capsys.readouterr().out
    truth = json.loads((tmp_path / "b" / "truth.json").read_text())
    lens = truth["lens"]
    assert (lens["kind"], lens["cx"], lens["cy"], lens["xi"]) == ("double-sphere", 900, 650, -0.1)
    assert truth["options"]["circle_radius_px"] == 700.0
    _check_dataset(json.loads((tmp_path / "b" / "dataset.json").read_text()))
    bad = parser.parse_args(["--lens-option", "xi", "-o", str(tmp_path / "c")])
    assert run_cli(bad) == 2


def test_offset_principal_point_with_filled_diagonal_caps_incidence_at_half_fov():
    # fov/2 lands on the half diagonal from the principal point; moved by 10%, the far
    # corner would show more than fov/2 without the visibility cap
    w, h, fov = 1600, 1200, 120.0
    cx, cy = (w - 1) / 2 + 0.1 * w, (h - 1) / 2 + 0.1 * h
    opts = SimulationOptions(
        lens="equidistant",
        fov_deg=fov,
        width=w,
        height=h,
        fill="diagonal",
        lens_options={"cx": cx, "cy": cy},
        noise_px=0.0,
        n_images=16,
    )
    sim = simulate_room(opts)
    assert sim.lens.max_incidence_deg > fov / 2  # the lens itself would see further
    p_cam, uv, _, _ = _observed_geometry(sim)
    alpha = np.degrees(np.arctan2(np.hypot(p_cam[:, 0], p_cam[:, 1]), p_cam[:, 2]))
    assert fov / 2 - 3.0 < alpha.max() <= fov / 2 + 1e-9
    # the far corner (top left) is not reached, the near ones are
    assert np.hypot(uv[:, 0] - cx, uv[:, 1] - cy).max() <= math.hypot(w, h) / 2 + 1e-6


def test_lens_zoo_case_list_builds(monkeypatch):
    import importlib.util
    import os
    import sys
    from pathlib import Path

    from gtsam_sphere.simulate import build_lens

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_lens_zoo.py"
    spec = importlib.util.spec_from_file_location("bench_lens_zoo", path)
    zoo = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_lens_zoo", zoo)  # its dataclass needs the module
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        # the script pins its threads with os.environ.setdefault: restored after the test
        monkeypatch.setenv(var, os.environ.get(var, "1"))
    spec.loader.exec_module(zoo)
    cases = zoo.build_cases(0)
    assert len(cases) >= 60 and len({c.id for c in cases}) == len(cases)
    assert [c.id for c in zoo.build_cases(0)] == [c.id for c in cases]
    assert {c.scene for c in cases} == {"room", "board", "object3d"}
    assert len({c.family for c in cases}) == 9
    assert min(c.fov_deg for c in cases) <= 60 and max(c.fov_deg for c in cases) == 360
    assert {0.25, 1.3} <= {c.circle for c in cases}
    assert max(max(abs(v) for v in c.pp_offset) for c in cases) == pytest.approx(0.1)
    assert any(c.pupil_shift_m and c.error_field_px for c in cases)
    for c in cases:  # every family reaches the field of view it is given
        build_lens(c.options())
    quick = zoo.quick_cases(cases)
    assert 6 <= len(quick) <= 10 and {c.scene for c in quick} == {"room", "board", "object3d"}
    # stress draws with sensor defects: the same draws otherwise, defects within bounds
    plain, bent = zoo.build_stress_cases(205, 12), zoo.build_stress_cases(205, 12, defects=True)
    assert [c.id + "-d" for c in plain] == [c.id for c in bent]
    for p, b in zip(plain, bent):
        extra = {k: v for k, v in b.lens_options.items() if k not in p.lens_options}
        assert set(extra) == set(zoo.STRESS_DEFECTS)
        assert all(abs(v) <= zoo.STRESS_DEFECTS[k] for k, v in extra.items())
        assert (p.seed, p.noise_px, p.fov_deg) == (b.seed, b.noise_px, b.fov_deg)
        build_lens(b.options())
    # drawn shape parameters: the same draws otherwise, within their ranges, reaching
    # the field (the fixed ones where no draw did, without the "-s")
    drawn = zoo.build_stress_cases(205, 80, shapes=True)
    fixed = zoo.build_stress_cases(205, 80)
    assert [c.id.removesuffix("-s") for c in drawn] == [c.id for c in fixed]
    seen: dict[str, set] = {}
    for d, f in zip(drawn, fixed):
        assert (d.seed, d.noise_px, d.fov_deg, d.family) == (
            f.seed,
            f.noise_px,
            f.fov_deg,
            f.family,
        )
        build_lens(d.options())
        ranges = zoo.SHAPE_RANGES.get(d.family)
        if not ranges or not d.id.endswith("-s"):
            assert d.lens_options == f.lens_options
            continue
        assert set(d.lens_options) == set(ranges)
        for k, (lo, hi) in ranges.items():
            if d.family == "unified" and d.fov_deg > 180.0:
                # past 180 deg xi is set by how far past the half field the lens sees
                reach = math.degrees(math.acos(-1.0 / d.lens_options["xi"]))
                assert d.fov_deg / 2 + 5.0 <= reach + 1e-6 <= d.fov_deg / 2 + 20.0 + 1e-6
            else:
                assert lo <= d.lens_options[k] <= hi
        seen.setdefault(d.family, set()).add(tuple(sorted(d.lens_options.items())))
    assert set(seen) == set(zoo.SHAPE_RANGES) and all(len(v) >= 2 for v in seen.values())


@pytest.mark.slow  # three end-to-end adjustments
def test_oracle_references_know_less_and_do_worse():
    """The zoo's three references on one board with a 2 px error field: the oracle
    (lens and field known), the family oracle (principal point and distance estimated)
    and the field-blind oracle (the field left in the measurements)."""
    from gtsam_sphere.simulate.oracle import oracle_calibration

    sim = simulate_room(
        SimulationOptions(
            scene="board", lens="equidistant", fov_deg=120, error_field_px=2.0, **OBJECTS
        )
    )
    lens = sim.truth["lens"]["lens"]
    assert sim.truth["lens"]["kind"] == "error-field"
    known = oracle_calibration(sim)
    family = oracle_calibration(sim, known_lens=False)
    blind = oracle_calibration(sim, known_field=False)
    cam = known.camera
    assert (cam.xp, cam.yp, cam.c) == (lens["cx"], lens["cy"], lens["f"])
    fam = family.camera
    assert 0 < math.hypot(fam.xp - lens["cx"], fam.yp - lens["cy"]) < 2.0
    assert 0 < abs(fam.c - lens["f"]) < 0.01 * lens["f"]
    assert (blind.camera.xp, blind.camera.c) == (lens["cx"], lens["f"])
    # what the poses absorb of the field moves the camera stations
    from gtsam_sphere.analysis.evaluate import evaluate_checkpoints

    ids = [im["id"] for im in sim.truth["images"]]
    xyz = np.array([im["centre_world"] for im in sim.truth["images"]], float)

    def stations_rmse_m(calib):
        R, t = np.asarray(calib.cam_from_world_R), np.asarray(calib.cam_from_world_t)
        centres = -np.einsum("kji,kj->ki", R, t)
        return evaluate_checkpoints(list(calib.image_ids), centres, ids, xyz).rmse_3d

    assert stations_rmse_m(blind) > 1.5 * stations_rmse_m(known)
    assert blind.statistics["rms_px"] > known.statistics["rms_px"]
