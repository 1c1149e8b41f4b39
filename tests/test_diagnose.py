"""Degeneracy checks (estimation.diagnose): each failure is named, a healthy room is not."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.estimation.diagnose import (
    DegenerateGeometryError,
    Problem,
    ProblemCode,
    check_geometry,
    image_groups,
    raise_if_degenerate,
)
from gtsam_sphere.io.dataset import DatasetError, parse_dataset
from gtsam_sphere.simulate import SimulationOptions, simulate_room

SMALL_ROOM = dict(
    lens="sphere",
    fov_deg=200,
    noise_px=0.3,
    n_images=12,
    n_targets=120,
    n_checkpoints=10,
    width=800,
    height=600,
    seed=11,
)


def _room(**overrides):
    sim = simulate_room(SimulationOptions(**{**SMALL_ROOM, **overrides}))
    return sim, parse_dataset(sim.dataset, "room.json")


def _true_poses(sim, dataset):
    """Truth cam_from_world (M,3,3), (M,3) in the dataset's image order."""
    by_id = {im["id"]: im["cam_from_world"] for im in sim.truth["images"]}
    R = np.array([by_id[i]["R"] for i in dataset.image_ids])
    t = np.array([by_id[i]["t"] for i in dataset.image_ids])
    return R, t


def _codes(problems, fatal=None):
    return {p.code for p in problems if fatal is None or p.fatal == fatal}


@pytest.fixture(scope="module")
def room():
    return _room()


@pytest.mark.slow  # end-to-end
def test_healthy_room_has_no_fatal_problem_before_or_after_initialisation(room):
    from gtsam_sphere.estimation.calibrate import initialise

    sim, ds = room
    assert _codes(check_geometry(ds), fatal=True) == set()
    assert _codes(check_geometry(ds, _true_poses(sim, ds)), fatal=True) == set()
    init = initialise(ds, seed=0)  # the real pipeline's initial poses, as calibrate.py has them
    problems = check_geometry(init.dataset, init)
    assert _codes(problems, fatal=True) == set()
    assert raise_if_degenerate(problems) == [p for p in problems if not p.fatal]


def test_single_usable_image():
    sim, ds = _room(sigma_mode="free")
    doc = copy.deepcopy(sim.dataset)
    doc["images"] = doc["images"][:1]
    one = parse_dataset(doc, "one.json")
    problems = check_geometry(one)
    (p,) = [p for p in problems if p.code is ProblemCode.SINGLE_IMAGE]
    assert p.fatal and "IMG_0001" in p.message and "no sigma" in p.message
    assert p.items == ("IMG_0001",)
    with pytest.raises(DegenerateGeometryError, match="only one usable image") as info:
        raise_if_degenerate(problems)
    assert isinstance(info.value, DatasetError)  # the CLI exits 2 on it
    assert "capture more images" in str(info.value)
    # with every target weighted and a 3D target field, one image is a weak resection only
    sim_w, _ = _room(sigma_mode="weighted")
    doc_w = copy.deepcopy(sim_w.dataset)
    doc_w["images"] = doc_w["images"][:1]
    (pw,) = [p for p in check_geometry(parse_dataset(doc_w)) if p.code is ProblemCode.SINGLE_IMAGE]
    assert not pw.fatal and "one resection" in pw.message


def test_all_images_from_one_position():
    # stations confined to a 1 cm box in the middle of a 6 x 6 x 3 m room
    kwargs = dict(room_size_m=(6.0, 6.0, 3.0), wall_clearance_m=2.995, station_height_m=(1.5, 1.51))
    sim, ds = _room(sigma_mode="free", **kwargs)
    assert ProblemCode.NO_BASELINE not in _codes(check_geometry(ds))  # needs poses
    problems = check_geometry(ds, _true_poses(sim, ds))
    (p,) = [p for p in problems if p.code is ProblemCode.NO_BASELINE]
    assert p.fatal and "one position" in p.message and "cannot be triangulated" in p.message
    assert set(p.items) == set(ds.image_ids)
    with pytest.raises(DegenerateGeometryError, match="move the camera between images"):
        raise_if_degenerate(problems)
    # the same stations with every target weighted: a warning, not fatal
    sim_w, ds_w = _room(sigma_mode="weighted", **kwargs)
    (pw,) = [
        p
        for p in check_geometry(ds_w, _true_poses(sim_w, ds_w))
        if p.code is ProblemCode.NO_BASELINE
    ]
    assert not pw.fatal
    # the healthy room has a baseline
    sim_h, ds_h = _room(sigma_mode="free")
    assert ProblemCode.NO_BASELINE not in _codes(check_geometry(ds_h, _true_poses(sim_h, ds_h)))


def _look_at(centre, target, up=(0.0, 1.0, 0.0)):
    """cam_from_world R (3,3), t (3,) of a camera at ``centre`` looking at ``target``."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


def _board_dataset(tilt_deg, c_px=2000.0, distance_m=1.0, n_images=8, seed=0):
    """A planar 9 x 7 board (z = 0, 0.4 x 0.3 m) seen from ``distance_m``, views tilted by
    up to ``tilt_deg``; ``c_px`` 2000 is a long lens at 1 m (largest incidence ~14 deg)."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(9) * 0.05, np.arange(7) * 0.05), -1).reshape(-1, 2)
    xyz = np.column_stack([g - g.mean(0), np.zeros(len(g))])
    cam = SphereCamera(1000, 800, 499.5, 399.5, c_px)
    targets = [{"id": f"B{k:02d}", "xyz": p.tolist(), "sigma": 0.0} for k, p in enumerate(xyz)]
    images, Rs, ts = [], [], []
    for i in range(n_images):
        azim = 2 * np.pi * i / n_images
        tilt = np.radians(tilt_deg) * rng.uniform(0.5, 1.0)
        centre = distance_m * np.array(
            [np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), -np.cos(tilt)]
        )
        R, t = _look_at(centre, rng.normal(0, 0.01, 3))
        uv = cam.project(xyz @ R.T + t) + rng.normal(0, 0.2, (len(xyz), 2))
        obs = [{"target": f"B{k:02d}", "uv": p.tolist()} for k, p in enumerate(uv)]
        images.append({"id": f"V{i}", "observations": obs})
        Rs.append(R)
        ts.append(t)
    doc = {
        "format": "gtsam-sphere/dataset@1",
        "camera": {"width": 1000, "height": 800},
        "targets": targets,
        "images": images,
    }
    ds = parse_dataset(doc, "board.json")
    assert ds.n_observations == n_images * len(xyz)  # every corner inside the frame
    return ds, (np.array(Rs), np.array(ts))


def test_planar_targets_narrow_field_little_tilt():
    ds, poses = _board_dataset(tilt_deg=5.0)
    assert ProblemCode.PLANAR_NARROW not in _codes(check_geometry(ds))  # needs poses
    problems = check_geometry(ds, poses)
    (p,) = [p for p in problems if p.code is ProblemCode.PLANAR_NARROW]
    assert p.fatal and "principal distance" in p.message and "tilt the camera" in p.advice
    # exact control: every image is its own group, and that is fine
    assert len(image_groups(ds)) == len(ds.image_ids)
    assert ProblemCode.DISCONNECTED not in _codes(problems)
    # tilted views of the same board separate c from the distance
    ds_t, poses_t = _board_dataset(tilt_deg=40.0)
    assert ProblemCode.PLANAR_NARROW not in _codes(check_geometry(ds_t, poses_t))
    # a wide lens close to the board too (largest incidence ~55 deg)
    ds_w, poses_w = _board_dataset(tilt_deg=5.0, c_px=300.0, distance_m=0.15)
    assert ProblemCode.PLANAR_NARROW not in _codes(check_geometry(ds_w, poses_w))


def test_images_with_too_few_points_are_reported_from_the_loader(room):
    sim, _ = room
    doc = copy.deepcopy(sim.dataset)
    doc["images"][3]["observations"] = doc["images"][3]["observations"][:2]
    doc["images"][5]["observations"] = doc["images"][5]["observations"][:5]
    ds = parse_dataset(doc, "few.json")
    assert [i for i, _ in ds.skipped_images] == ["IMG_0004"]
    problems = check_geometry(ds)
    (p,) = [p for p in problems if p.code is ProblemCode.FEW_POINTS]
    assert not p.fatal
    assert p.items == ("IMG_0004", "IMG_0006")  # skipped by the loader; kept with 5 < 6
    assert "skipped by the loader" in p.message and "'IMG_0006'" in p.message
    # images left out for another reason are listed separately
    ds2 = ds.subset_images(np.arange(len(ds.image_ids)) != 0, {0: "initialisation failed: x"})
    (q,) = [p for p in check_geometry(ds2) if p.code is ProblemCode.SKIPPED_IMAGES]
    assert q.items == ("IMG_0001",) and "initialisation failed" in q.message
    # no image with enough points at all: fatal
    for im in doc["images"]:
        im["observations"] = im["observations"][:4]
    (f,) = [p for p in check_geometry(parse_dataset(doc)) if p.code is ProblemCode.FEW_POINTS]
    assert f.fatal


def _split_network(sim, sigma_mode):
    """The room's images in two halves that share no target (the second half's targets renamed)."""
    ds, first, second = _split_at(sim, len(sim.dataset["images"]) // 2)
    assert sigma_mode == "free" or np.isfinite(ds.target_sigma).all()
    return ds, first, second


def test_disconnected_free_network_is_fatal_and_names_the_groups():
    sim, ds0 = _room(sigma_mode="free")
    assert len(image_groups(ds0)) == 1
    assert ProblemCode.DISCONNECTED not in _codes(check_geometry(ds0))
    ds, first, second = _split_network(sim, "free")
    groups = image_groups(ds)
    assert sorted(sorted(ds.image_ids[i] for i in g) for g in groups) == sorted([first, second])
    (p,) = [p for p in check_geometry(ds) if p.code is ProblemCode.DISCONNECTED]
    assert p.fatal and "2 groups" in p.message and "free network" in p.message
    assert repr(first[0]) in p.message and repr(second[0]) in p.message
    assert set(p.items) == set(first + second)
    with pytest.raises(DegenerateGeometryError, match="share no target"):
        raise_if_degenerate(check_geometry(ds))


def test_disconnected_weighted_network_is_a_warning_and_exact_control_is_fine():
    sim_w, _ = _room(sigma_mode="weighted")
    ds_w, _, _ = _split_network(sim_w, "weighted")
    (p,) = [p for p in check_geometry(ds_w) if p.code is ProblemCode.DISCONNECTED]
    assert not p.fatal and "approximate coordinates" in p.message
    strict = check_geometry(ds_w, weighted_anchor=False)
    assert ProblemCode.DISCONNECTED in _codes(strict, fatal=True)
    sim_x, _ = _room(sigma_mode="fixed")
    ds_x, _, _ = _split_network(sim_x, "fixed")
    assert ProblemCode.DISCONNECTED not in _codes(check_geometry(ds_x))


def test_coincident_or_collinear_targets_are_fatal(room):
    sim, _ = room
    for kind, place in (("coincide", lambda k: [1.0, 2.0, 3.0]), ("one line", lambda k: [k, 0, 0])):
        doc = copy.deepcopy(sim.dataset)
        for k, t in enumerate(doc["targets"]):
            t["xyz"] = [float(v) for v in place(k)]
        (p,) = [
            p
            for p in check_geometry(parse_dataset(doc))
            if p.code is ProblemCode.DEGENERATE_TARGETS
        ]
        assert p.fatal and kind in p.message


def test_free_targets_seen_once_are_a_warning():
    sim, ds = _room(sigma_mode="free")
    problems = check_geometry(ds)
    once = [p for p in problems if p.code is ProblemCode.UNDETERMINED_TARGETS]
    n_views = {}
    for im in sim.dataset["images"]:
        for o in im["observations"]:
            n_views[o["target"]] = n_views.get(o["target"], 0) + 1
    expected = sorted(t for t, n in n_views.items() if n < 2)
    if expected:
        (p,) = once
        assert not p.fatal and sorted(p.items) == expected
    else:
        assert once == []


def test_poses_are_validated_and_nan_rows_ignored(room):
    sim, ds = room
    R, t = _true_poses(sim, ds)
    with pytest.raises(ValueError, match=r"\(12, 3, 3\)"):
        check_geometry(ds, (R[:3], t[:3]))
    with pytest.raises(ValueError, match="cam_from_world"):
        check_geometry(ds, np.zeros((12, 3, 3)))
    Rt = np.concatenate([R, t[:, :, None]], axis=2)
    assert check_geometry(ds, Rt) == check_geometry(ds, (R, t))
    R2 = R.copy()
    R2[:6] = np.nan  # images that failed to initialise
    assert _codes(check_geometry(ds, (R2, t)), fatal=True) == set()


def test_raise_if_degenerate_passes_warnings_on():
    warning = Problem(ProblemCode.FEW_POINTS, "few", "more", False, ("A",))
    lines: list[str] = []
    assert raise_if_degenerate([warning], warn=lines.append) == [warning]
    assert lines == ["warning: [few-points] few -> more"]
    fatal = Problem(ProblemCode.NO_BASELINE, "one spot", "move", True)
    with pytest.raises(DegenerateGeometryError) as info:
        raise_if_degenerate([warning, fatal], warn=lines.append)
    assert info.value.problems == [fatal]
    assert "\n" not in str(info.value) and "one spot" in str(info.value)
    assert "move" in str(info.value) and "few" not in str(info.value)


@st.composite
def _random_networks(draw):
    """Small valid datasets: any target layout (coincident, collinear, planar, 3D), any sigma
    mix, images seeing random subsets; with random poses (some NaN) or none."""
    n_t = draw(st.integers(1, 12))
    layout = draw(st.sampled_from(["3d", "plane", "line", "point"]))
    coords = draw(
        st.lists(st.tuples(*[st.floats(-5, 5)] * 3), min_size=n_t, max_size=n_t, unique=True)
    )
    xyz = np.array(coords, float)
    if layout == "plane":
        xyz[:, 2] = 1.0
    elif layout == "line":
        xyz[:, 1:] = 0.0
    elif layout == "point":
        xyz[:] = xyz[0]
    sigma = draw(st.lists(st.sampled_from([None, 0.0, 0.01]), min_size=n_t, max_size=n_t))
    targets = []
    for k in range(n_t):
        t = {"id": f"T{k}", "xyz": xyz[k].tolist()}
        if sigma[k] is not None:
            t["sigma"] = sigma[k]
        targets.append(t)
    images = []
    for i in range(draw(st.integers(1, 6))):
        seen = draw(st.lists(st.integers(0, n_t - 1), unique=True, max_size=n_t))
        obs = [{"target": f"T{k}", "uv": [10.0 + k, 20.0 + i]} for k in seen]
        images.append({"id": f"I{i}", "observations": obs})
    doc = {
        "format": "gtsam-sphere/dataset@1",
        "camera": {"width": 100, "height": 100},
        "targets": targets,
        "images": images,
    }
    try:
        ds = parse_dataset(doc, "random.json", min_observations_per_image=1)
    except DatasetError:
        assume(False)
    poses = None
    if draw(st.booleans()):
        m = len(ds.image_ids)
        R = np.stack([np.eye(3)] * m)
        t = np.array(draw(st.lists(st.tuples(*[st.floats(-3, 3)] * 3), min_size=m, max_size=m)))
        if draw(st.booleans()):
            R[0] = np.nan
        poses = (R, t)
    return ds, poses


@settings(max_examples=120, deadline=None, derandomize=True, database=None)
@given(network=_random_networks())
def test_check_geometry_never_fails_on_a_valid_dataset(network):
    ds, poses = network
    problems = check_geometry(ds, poses)
    assert all(isinstance(p, Problem) and p.message and p.advice for p in problems)
    assert [p.fatal for p in problems] == sorted((p.fatal for p in problems), reverse=True)
    if any(p.fatal for p in problems):
        with pytest.raises(DegenerateGeometryError):
            raise_if_degenerate(problems)
    else:
        assert raise_if_degenerate(problems) == problems


def _split_at(sim, n_first):
    """The room with the images after the first ``n_first`` seeing renamed targets only
    (two groups that share no target): (dataset, first ids, other ids)."""
    doc = copy.deepcopy(sim.dataset)
    extra = {}
    for im in doc["images"][n_first:]:
        for o in im["observations"]:
            o["target"] = "B_" + o["target"]
            extra[o["target"]] = o["target"][2:]
    xyz = {t["id"]: t for t in doc["targets"]}
    doc["targets"] += [dict(xyz[old], id=new) for new, old in sorted(extra.items())]
    ids = [im["id"] for im in doc["images"]]
    return parse_dataset(doc, "split.json"), ids[:n_first], ids[n_first:]


def test_connected_images_keeps_the_largest_free_group_and_names_the_rest():
    from dataclasses import replace

    from gtsam_sphere.estimation.calibrate import DISCONNECTED_REASON, connected_images

    sim, _ = _room(sigma_mode="free")
    ds, _, rest = _split_at(sim, 8)
    with pytest.raises(DegenerateGeometryError) as err:
        raise_if_degenerate(check_geometry(ds))
    part = connected_images(ds, err.value)
    assert part.image_ids == [i for i in ds.image_ids if i not in rest]
    assert part.skipped_images == [(i, DISCONNECTED_REASON) for i in rest]
    # another fatal problem beside it: no way out
    other = replace(err.value.problems[0], code=ProblemCode.FEW_POINTS)
    assert connected_images(ds, DegenerateGeometryError([*err.value.problems, other])) is None


@pytest.mark.slow  # one small room, ~4 s
def test_calibrate_leaves_out_a_group_of_images_a_free_network_cannot_hold():
    """A free room whose last 4 images see only targets no other image sees: refused
    whole before; now the 8 connected images are calibrated (trusted) and the 4 others
    are listed in skipped_images with the reason, and counted in the input."""
    from gtsam_sphere.estimation.calibrate import DISCONNECTED_REASON, calibrate

    sim, _ = _room(sigma_mode="free")
    ds, _, rest = _split_at(sim, 8)
    calib = calibrate(ds)
    assert calib.statistics["trusted"], calib.statistics["distrust"]
    assert sorted(calib.image_ids) == sorted(i for i in ds.image_ids if i not in rest)
    skipped = calib.to_dict()["skipped_images"]
    assert [(s["id"], s["reason"]) for s in skipped] == [(i, DISCONNECTED_REASON) for i in rest]
    assert calib.statistics["n_images_input"] == 12
    assert calib.statistics["n_images_skipped"] == 4
    with pytest.raises(DegenerateGeometryError, match="share no target"):
        calibrate(ds, keep_connected=False)
