"""Rigs: dataset@2 reading, the first rig calibration (per camera + averaged extrinsics),
calibration@2 writing and reading, the command line."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from helpers import shared_data_file

from gtsam_sphere import load_calibration
from gtsam_sphere.cli import main
from gtsam_sphere.core.camera import Model, SphereCamera
from gtsam_sphere.estimation.calibrate import CalibrationOptions
from gtsam_sphere.estimation.rig import (
    RIG_ADJUSTMENT,
    calibrate_rig,
    camera_options,
    check_rig_connected,
    compose,
    parse_camera_models,
    place_cameras,
    robust_pose_mean,
    rotation_angle,
)
from gtsam_sphere.io.calibration import RigCalibration
from gtsam_sphere.io.dataset import (
    DatasetError,
    dataset_version,
    parse_dataset,
    parse_rig_dataset,
    split_rig,
)
from gtsam_sphere.simulate import SimulationOptions, make_lens, simulate_room


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Axis times angle (rad) of a rotation (3, 3)."""
    import gtsam

    return np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(np.asarray(R, float))))


def rotation(axis, deg: float) -> np.ndarray:
    """Rotation (3, 3) by ``deg`` degrees about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


# -- dataset@2 validation ----------------------------------------------------------


def small_rig_doc() -> dict:
    """A valid two-camera dataset@2 document (6 targets, 2 frames, 4 images)."""
    targets = [{"id": f"T{k}", "xyz": [float(k), float(k % 2), 2.0]} for k in range(6)]

    def obs(shift):
        return [
            {"target": f"T{k}", "uv": [100.0 + 10 * k + shift, 200.0 + shift]} for k in range(6)
        ]

    return {
        "format": "gtsam-sphere/dataset@2",
        "units": "m",
        "cameras": [
            {"id": "cam0", "width": 640, "height": 480},
            {"id": "cam1", "width": 800, "height": 600},
        ],
        "targets": targets,
        "images": [
            {"id": "L0", "camera": "cam0", "frame": "0", "observations": obs(0)},
            {"id": "R0", "camera": "cam1", "frame": "0", "observations": obs(1)},
            {"id": "L1", "camera": "cam0", "frame": "1", "observations": obs(2)},
            {"id": "R1", "camera": "cam1", "frame": "1", "observations": obs(3)},
            {"id": "X", "camera": "cam1", "observations": obs(4)},
        ],
    }


def test_rig_dataset_reads_and_splits():
    rig = parse_rig_dataset(small_rig_doc(), "rig.json")
    assert rig.camera_ids == ["cam0", "cam1"]
    assert rig.camera_sizes == [(640, 480), (800, 600)]
    assert rig.frame_ids == ["0", "1"]
    assert rig.image_frame == ["0", "0", "1", "1", None]
    parts = split_rig(rig)
    assert list(parts) == ["cam0", "cam1"]
    assert parts["cam0"].image_ids == ["L0", "L1"]
    assert parts["cam1"].image_ids == ["R0", "R1", "X"]
    assert (parts["cam1"].width, parts["cam1"].height) == (800, 600)
    assert parts["cam0"].target_ids is parts["cam1"].target_ids  # shared targets
    assert parts["cam1"].n_observations == 18
    assert np.allclose(parts["cam1"].uv_px[0], [101.0, 201.0])
    assert dataset_version(small_rig_doc()) == 2


def test_dataset_v1_still_reads():
    doc = small_rig_doc()
    v1 = {
        "format": "gtsam-sphere/dataset@1",
        "camera": {"width": 640, "height": 480},
        "targets": doc["targets"],
        "images": [{"id": "A", "observations": doc["images"][0]["observations"]}],
    }
    assert dataset_version(v1) == 1
    assert parse_dataset(v1).image_ids == ["A"]
    with pytest.raises(DatasetError, match="dataset@3"):
        dataset_version({"format": "gtsam-sphere/dataset@3"})
    # a dataset@2 handed to the dataset@1 reader says which version it is
    with pytest.raises(DatasetError, match="unsupported version"):
        parse_dataset(doc)


def _bad(edit):
    doc = small_rig_doc()
    edit(doc)
    return doc


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["images"][1].update(camera="cam7"), r"image 'R0': unknown camera 'cam7'"),
        (lambda d: d["images"][1].pop("camera"), r"image 'R0': 'camera' must name one of"),
        (
            lambda d: d["cameras"][1].update(id="cam0"),
            r"duplicate camera id 'cam0' \(cameras\[1\]\)",
        ),
        (
            lambda d: d["images"][2].update(frame="0"),
            r"frame '0' holds two images of camera 'cam0' \('L0' and 'L1'\)",
        ),
        (
            lambda d: (
                [im.update(observations=im["observations"][:2]) for im in d["images"][1::2]]
                + [d["images"].pop()]
            ),
            r"camera 'cam1' has no usable image \(R0: only 2 usable",
        ),
        (
            lambda d: d.update(images=[im for im in d["images"] if im["camera"] == "cam0"]),
            r"camera 'cam1' has no usable image \(no image names it\)",
        ),
        (lambda d: d.pop("cameras"), r"'cameras' must be a non-empty list"),
        (lambda d: d.update(camera={"width": 1, "height": 1}), r"not 'camera'"),
        (lambda d: d["cameras"][0].pop("id"), r"cameras\[0\] has no string 'id'"),
        (lambda d: d["cameras"][1].update(width=0), r"camera 'cam1'.width must be a positive"),
        (lambda d: d["images"][3].update(frame=3), r"image 'R1': 'frame' must be a non-empty str"),
        (lambda d: d["images"][3].update(id="L0"), r"duplicate image id 'L0' \(images\[3\]\)"),
        (
            lambda d: d["images"][0]["observations"][0].update(target="T99"),
            r"image 'L0' observation 0: unknown target id 'T99'",
        ),
    ],
)
def test_rig_dataset_errors_name_the_item(edit, message):
    with pytest.raises(DatasetError, match=message):
        parse_rig_dataset(_bad(edit), "rig.json")


def test_rig_dataset_skips_and_drops_per_camera():
    doc = small_rig_doc()
    doc["images"][3]["observations"] = doc["images"][3]["observations"][:3]  # R1: too few
    doc["images"][0]["observations"][0]["uv"] = [700.0, 10.0]  # outside cam0's 640 px
    rig = parse_rig_dataset(doc, "rig.json")
    assert rig.skipped_images == [("R1", "only 3 usable observations (< 4)")]
    assert [d[:2] for d in rig.dropped] == [("L0", "T0")]
    parts = split_rig(rig)
    assert parts["cam1"].skipped_images == rig.skipped_images
    assert parts["cam0"].skipped_images == []
    assert len(parts["cam0"].dropped) == 1 and not parts["cam1"].dropped
    assert parts["cam0"].n_input_observations == 12
    # 700 px is inside cam1's 800 px image: each image is checked against its own camera
    doc["images"][1]["observations"][0]["uv"] = [700.0, 10.0]
    assert len(parse_rig_dataset(doc).dropped) == 1


_JUNK = [None, 0, -1, 1.5, True, "", "x", [], {}, [1, 2], {"a": 1}, float("nan"), 10**400]


def _mutations(doc):
    """Every (container, key) of a document, for replacing one item by junk."""
    stack = [doc]
    while stack:
        node = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node)
        for key, value in list(items):
            yield node, key
            if isinstance(value, (dict, list)):
                stack.append(value)


def test_rig_dataset_junk_anywhere_is_a_dataset_error_or_accepted():
    base = small_rig_doc()
    n = 0
    for k in range(len(list(_mutations(copy.deepcopy(base))))):
        for junk in _JUNK[k % 3 :: 3]:
            doc = copy.deepcopy(base)
            target = next(x for i, x in enumerate(_mutations(doc)) if i == k)
            target[0][target[1]] = junk
            try:
                rig = parse_rig_dataset(doc, "fuzz.json")
            except DatasetError as exc:
                assert "fuzz.json" in str(exc)
            else:
                split_rig(rig)
            n += 1
    assert n > 100


# -- robust averaging, the spanning tree ------------------------------------------


def test_robust_pose_mean_ignores_a_gross_sample():
    rng = np.random.default_rng(3)
    R0, t0 = rotation([1, 2, 3], 40.0), np.array([0.1, -0.2, 0.3])
    Rs, ts = [], []
    for _ in range(12):
        Rs.append(rotation(rng.normal(size=3), 0.05) @ R0)
        ts.append(t0 + rng.normal(0, 1e-3, 3))
    Rs.append(rotation([0, 0, 1], 20.0) @ R0)  # a frame whose pose is wrong
    ts.append(t0 + [0.5, 0.0, 0.0])
    mean = robust_pose_mean(np.array(Rs), np.array(ts))
    assert np.degrees(rotation_angle(mean.R.T @ R0)) < 0.05
    assert np.linalg.norm(mean.t - t0) < 1.5e-3
    assert mean.weights[-1] < 0.01 and mean.downweighted[-1]
    spread = mean.spread()
    assert spread["n_frames"] == 13
    assert spread["rotation_spread_deg"] < 0.2  # the outlier barely counts
    assert spread["rotation_max_deg"] == pytest.approx(20.0, abs=0.2)
    single = robust_pose_mean(R0[None], t0[None])
    assert np.allclose(single.R, R0) and np.allclose(single.t, t0)
    assert single.spread()["rotation_spread_deg"] is None


def test_rotation_angle_is_accurate_near_zero_and_pi():
    assert rotation_angle(rotation([0, 1, 0], 1e-6)) == pytest.approx(np.radians(1e-6), rel=1e-6)
    assert rotation_angle(rotation([0, 1, 1], 179.9999)) == pytest.approx(
        np.radians(179.9999), rel=1e-9
    )


def test_place_cameras_follows_shared_frames_and_names_the_unlinked():
    rng = np.random.default_rng(0)
    truth = {
        "a": (np.eye(3), np.zeros(3)),
        "b": (rotation([0, 1, 0], 180.0), np.array([0.0, 0.0, -0.1])),
        "c": (rotation([1, 0, 0], 90.0), np.array([0.05, 0.0, 0.0])),
    }
    poses = {c: {} for c in truth}
    for f in range(6):
        rig_from_world = (rotation(rng.normal(size=3), 30.0), rng.normal(size=3))
        for c, frames in (("a", range(0, 4)), ("b", range(2, 6)), ("c", range(4, 6))):
            if f in frames:  # c shares frames with b only
                poses[c][str(f)] = compose(truth[c], rig_from_world)
    cam_from_rig, precision = place_cameras(["a", "b", "c"], poses, lambda _s: None)
    for c in truth:
        assert np.allclose(cam_from_rig[c][0], truth[c][0], atol=1e-9)
        assert np.allclose(cam_from_rig[c][1], truth[c][1], atol=1e-9)
    assert precision["c"]["parent"] == "b" and precision["b"]["parent"] == "a"
    assert precision["c"]["n_frames"] == 2
    with pytest.raises(DatasetError, match=r"camera\(s\) \['c'\] share no frame with") as err:
        check_rig_connected(["a", "b", "c"], {"a": {"0"}, "b": {"0", "1"}, "c": {"2"}})
    assert "Capture rig frames" in str(err.value)
    check_rig_connected(["a", "b", "c"], {"a": {"0"}, "b": {"0", "1"}, "c": {"1"}})


def test_camera_models_option():
    ids = ["cam0", "cam1"]
    models = parse_camera_models(["cam1=brown"], ids)
    assert models == {"cam1": Model.BROWN}
    opts = camera_options(CalibrationOptions(), ids, models)
    assert opts["cam0"].model == Model("radial+knn")
    assert opts["cam1"].model == Model.BROWN
    assert opts["cam1"].brown_terms == ("k1", "k2", "k3", "p1", "p2")  # brown's own default
    for spec, message in (
        ("cam9=radial", "unknown camera 'cam9'"),
        ("cam1=fancy", "unknown model 'fancy'"),
        ("cam1", "expected CAMERA=MODEL"),
    ):
        with pytest.raises(DatasetError, match=message):
            parse_camera_models([spec], ids)
    with pytest.raises(DatasetError, match="given a model twice"):
        parse_camera_models(["cam1=radial", "cam1=sphere"], ids)


# -- calibration@2 writing and reading ---------------------------------------------


def _two_cameras():
    cam0 = SphereCamera(
        width=640, height=480, xp=320.5, yp=240.2, c=300.0, radial={"g3": 0.01, "g5": -0.002}
    )
    cam1 = SphereCamera(
        width=800,
        height=600,
        xp=400.0,
        yp=299.0,
        c=420.0,
        brown={"k1": 0.01, "p1": 1e-4},
        brown_scale_px=400.0,
    )
    return cam0, cam1


def test_calibration_v2_round_trip(tmp_path):
    cam0, cam1 = _two_cameras()
    R1, t1 = rotation([0.1, 1, 0], 7.9), np.array([-0.16, 0.002, 0.001])
    rig_R, rig_t = rotation([1, 1, 0], 20.0), np.array([0.3, -0.1, 2.0])
    img1 = compose((R1, t1), (rig_R, rig_t))
    calib = RigCalibration(
        camera_ids=["cam0", "cam1"],
        cameras={"cam0": cam0, "cam1": cam1},
        models={"cam0": "radial", "cam1": "brown"},
        cam_from_rig={"cam0": (np.eye(3), np.zeros(3)), "cam1": (R1, t1)},
        frame_ids=["00"],
        rig_from_world_R=rig_R[None],
        rig_from_world_t=rig_t[None],
        image_ids=["L_00", "R_00"],
        image_camera=["cam0", "cam1"],
        image_frame=["00", "00"],
        cam_from_world_R=np.array([rig_R, img1[0]]),
        cam_from_world_t=np.array([rig_t, img1[1]]),
        target_ids=["T0"],
        target_xyz=np.array([[0.1, 0.2, 0.3]]),
        statistics={
            "rms_px": 0.4,
            "n_observations": 10,
            "n_rejected": 0,
            "rig_adjustment": RIG_ADJUSTMENT,
            "cameras": {"cam0": {"rms_px": 0.41}, "cam1": {"rms_px": 0.39}},
        },
    )
    path = calib.save(tmp_path / "rig.calib.json")
    doc = json.loads(path.read_text())
    assert doc["format"] == "gtsam-sphere/calibration@2"
    assert doc["model"] == "cam0=radial,cam1=brown"
    cam_doc = doc["cameras"][1]
    assert {"id", "model", "width", "height", "cam_from_rig", "xp_px", "c_px", "brown"} <= set(
        cam_doc
    )
    assert doc["frames"] == [
        {"id": "00", "rig_from_world": {"R": rig_R.tolist(), "t": rig_t.tolist()}}
    ]
    assert doc["images"][1]["camera"] == "cam1" and doc["images"][1]["frame"] == "00"

    back = load_calibration(path)
    assert isinstance(back, RigCalibration)
    assert back.camera_ids == ["cam0", "cam1"]
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(20, 3)) + [0, 0, 3.0]
    for cid, cam in (("cam0", cam0), ("cam1", cam1)):
        uv = back.cameras[cid].project(pts)
        assert np.allclose(uv, cam.project(pts), atol=1e-9)
        rays = back.cameras[cid].unproject(uv)
        assert np.allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-7)
    assert np.allclose(back.cam_from_rig["cam1"][0], R1)
    assert np.allclose(back.cam_from_rig["cam1"][1], t1)
    assert back.cam_from_rig["cam1"][1].shape == (3,)
    assert np.allclose(back.cam_from_world_R[1], img1[0])
    assert back.statistics["cameras"]["cam1"]["rms_px"] == 0.39
    assert not hasattr(back, "camera")
    with pytest.raises(DatasetError, match=r"rig calibration .* use \.cameras\[id\]"):
        _ = back.camera
    one = back.camera_calibration("cam1")
    assert one.image_ids == ["R_00"] and one.statistics["rms_px"] == 0.39
    assert one.camera.c == pytest.approx(420.0)

    bad = copy.deepcopy(doc)
    del bad["statistics"]["cameras"]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match="statistics.cameras"):
        load_calibration(tmp_path / "bad.json")
    bad = copy.deepcopy(doc)
    bad["cameras"][1]["cam_from_rig"]["t"] = [0, 0]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"camera 'cam1' cam_from_rig t must have shape"):
        load_calibration(tmp_path / "bad.json")


def test_cli_refuses_an_unlinked_rig_before_calibrating(tmp_path, capsys):
    doc = small_rig_doc()
    for im in doc["images"]:
        if im["camera"] == "cam1":
            im.pop("frame", None)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(path), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "camera(s) ['cam1'] share no frame with camera(s) ['cam0']" in err
    assert "Capture rig frames" in err and not out.exists()
    bad = small_rig_doc()
    bad["images"][1]["camera"] = "nope"
    path.write_text(json.dumps(bad))
    assert main(["calibrate", str(path), "-o", str(out), "--quiet"]) == 2
    assert "unknown camera 'nope'" in capsys.readouterr().err
    path.write_text(json.dumps(small_rig_doc()))
    assert main(["calibrate", str(path), "-o", str(out), "--camera-model", "cam5=radial"]) == 2
    assert "unknown camera 'cam5'" in capsys.readouterr().err


# -- simulated rigs ----------------------------------------------------------------


def simulate_rig(cam1_from_cam0, seed=0, n_frames=14, noise_px=0.3, disjoint=False) -> dict:
    """A two-camera dataset@2 from the simulator: the room seen by camera 0 (a 180 deg
    equidistant fisheye, 1000 px) and, at each of its poses, by camera 1 (a 170 deg
    equisolid fisheye, 900 px) at ``cam_from_rig = cam1_from_cam0`` (R (3, 3), t (3,) m).

    ``disjoint``: camera 1 does not observe a target that camera 0 observes in the same
    frame (no stereo overlap at all). Approximate targets seen only by camera 1 get the
    simulator's 1 cm noise and sigma.
    """
    opts = SimulationOptions(
        lens="equidistant",
        fov_deg=180.0,
        width=1000,
        height=1000,
        fill="circle",
        n_images=n_frames,
        noise_px=noise_px,
        seed=seed,
    )
    sim = simulate_room(opts)
    lens1 = make_lens("equisolid", 170.0, 900, 900, fill="circle")
    rng = np.random.default_rng(seed + 1)
    ids = [t["id"] for t in sim.truth["targets"]]
    xyz = np.array([t["xyz"] for t in sim.truth["targets"]])
    normals = np.array([t["normal"] for t in sim.truth["targets"]])
    R1, t1 = cam1_from_cam0
    images, seen1 = [], set()
    for k, (im0, true0) in enumerate(zip(sim.dataset["images"], sim.truth["images"])):
        frame = f"{k:03d}"
        images.append(
            {
                "id": f"A_{frame}",
                "camera": "cam0",
                "frame": frame,
                "observations": im0["observations"],
            }
        )
        pose0 = (np.array(true0["cam_from_world"]["R"]), np.array(true0["cam_from_world"]["t"]))
        R, t = compose((R1, t1), pose0)
        centre = -R.T @ t
        view = xyz - centre
        dist = np.linalg.norm(view, axis=1)
        uv = lens1.project(xyz @ R.T + t)
        ok = np.isfinite(uv).all(axis=1)
        ok[ok] &= ((uv[ok] > 5.0) & (uv[ok] < 895.0)).all(axis=1)
        ok &= (np.sum(normals * view, axis=1) / dist < -0.1) & (dist > 0.3)
        if disjoint:
            ok &= ~np.isin(ids, [o["target"] for o in im0["observations"]])
        keep = np.flatnonzero(ok)
        uv_obs = uv[keep] + rng.normal(0.0, noise_px, (len(keep), 2))
        seen1.update(ids[j] for j in keep)
        images.append(
            {
                "id": f"B_{frame}",
                "camera": "cam1",
                "frame": frame,
                "observations": [
                    {"target": ids[j], "uv": p.tolist()} for j, p in zip(keep, uv_obs)
                ],
            }
        )
    targets = list(sim.dataset["targets"])
    known = {t["id"] for t in targets}
    for tid in sorted(seen1 - known):
        p = xyz[ids.index(tid)] + rng.normal(0.0, opts.target_sigma_m, 3)
        targets.append({"id": tid, "xyz": p.tolist(), "sigma": opts.target_sigma_m})
    return {
        "format": "gtsam-sphere/dataset@2",
        "units": "m",
        "cameras": [
            {"id": "cam0", "width": 1000, "height": 1000},
            {"id": "cam1", "width": 900, "height": 900},
        ],
        "targets": targets,
        "images": images,
    }


def _check_rig_result(calib: RigCalibration, truth, rot_deg: float, t_m: float) -> None:
    R, t = calib.cam_from_rig["cam1"]
    assert np.degrees(rotation_angle(R.T @ truth[0])) < rot_deg
    assert np.linalg.norm(t - truth[1]) < t_m
    assert np.allclose(calib.cam_from_rig["cam0"][0], np.eye(3))
    st = calib.statistics
    assert st["rig_adjustment"] == RIG_ADJUSTMENT
    assert st["trusted"] and not st["distrust"]
    assert st["n_frames"] == len(calib.frame_ids)
    for cid in calib.camera_ids:
        cs = st["cameras"][cid]
        assert 0.2 < cs["rms_px"] < 0.5
        # the rig-composed poses fit nearly as well as each camera's own
        assert cs["rms_px_rig"] < 1.3 * cs["rms_px"]
    pr = st["cameras"]["cam1"]["cam_from_rig_precision"]
    assert pr["parent"] == "cam0" and pr["n_frames"] == len(calib.frame_ids)
    assert 0 < pr["rotation_spread_deg"] < 0.2 and 0 < pr["translation_spread_norm"] < 0.01
    # the joint adjustment's precision: the true error within 3 sigma, per axis
    phi = rotation_vector(R @ truth[0].T)
    sigma_rot = np.radians(np.asarray(pr["rotation_sigma_deg_axes"]))
    assert np.all(np.abs(phi) < 3.0 * sigma_rot), (phi, sigma_rot)
    assert np.all(np.abs(t - truth[1]) < 3.0 * np.asarray(pr["translation_sigma"]))
    assert st["joint"]["converged"] and 0.7 < st["joint"]["variance_factor"] < 1.5
    # every framed image's pose is cam_from_rig * rig_from_world
    frame_index = {f: k for k, f in enumerate(calib.frame_ids)}
    for k, (cid, f) in enumerate(zip(calib.image_camera, calib.image_frame)):
        rig = (calib.rig_from_world_R[frame_index[f]], calib.rig_from_world_t[frame_index[f]])
        R_k, t_k = compose(calib.cam_from_rig[cid], rig)
        assert np.allclose(calib.cam_from_world_R[k], R_k, atol=1e-12)
        assert np.allclose(calib.cam_from_world_t[k], t_k, atol=1e-12)


@pytest.mark.slow
def test_simulated_stereo_rig_cli_and_round_trip(tmp_path, capsys):
    truth = (rotation([0.2, 1.0, 0.1], 8.0), np.array([-0.16, 0.01, 0.005]))
    doc = simulate_rig(truth)
    path = tmp_path / "rig.dataset.json"
    path.write_text(json.dumps(doc))
    out = tmp_path / "rig.calib.json"
    code = main(["calibrate", str(path), "-o", str(out), "--model", "radial", "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "(joint (per-camera initialisation" in printed and "(joint adjustment)" in printed
    calib = load_calibration(out)
    assert isinstance(calib, RigCalibration)
    _check_rig_result(calib, truth, rot_deg=0.1, t_m=0.003)
    # project / unproject per camera: a target seen by camera 1 lands on its pixel
    rig = parse_rig_dataset(doc)
    cam1 = calib.cameras["cam1"]
    k = calib.image_ids.index("B_003")
    obs = next(im for im in doc["images"] if im["id"] == "B_003")["observations"]
    xyz = np.array([calib.target_xyz[calib.target_ids.index(o["target"])] for o in obs])
    uv = np.array([o["uv"] for o in obs])
    pc = xyz @ calib.cam_from_world_R[k].T + calib.cam_from_world_t[k]
    assert np.sqrt(np.mean(np.sum((cam1.project(pc) - uv) ** 2, axis=1))) < 1.0
    rays = cam1.unproject(uv)
    cos = np.sum(rays * pc / np.linalg.norm(pc, axis=1, keepdims=True), axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    assert len(calib.image_ids) == len(rig.image_ids)


@pytest.mark.slow
def test_simulated_rig_back_to_back_without_shared_targets():
    # cameras looking in opposite directions, not one target in common within a frame:
    # the surveyed targets (1 cm sigma) tie them
    truth = (rotation([0, 1, 0], 180.0) @ rotation([1, 0, 0], 3.0), np.array([0.02, -0.01, -0.05]))
    doc = simulate_rig(truth, seed=2, disjoint=True)
    by_frame = {}
    for im in doc["images"]:
        by_frame.setdefault(im["frame"], []).append({o["target"] for o in im["observations"]})
    assert all(not (a & b) for a, b in by_frame.values())
    rig = parse_rig_dataset(doc, "back-to-back")
    calib = calibrate_rig(rig, CalibrationOptions(model=Model.RADIAL))
    _check_rig_result(calib, truth, rot_deg=0.1, t_m=0.003)


# -- real data: OpenCV's omnidirectional stereo pair --------------------------------


@pytest.mark.slow
def test_opencv_omnidir_stereo_rig(tmp_path, capsys):
    """Calibrate the real stereo pair as a rig; OpenCV's references (../shared/data/README.md):
    per-camera omnidir RMS 0.439 / 0.407 px, baseline 160.5 mm, rotation 7.93 deg."""
    path = shared_data_file("opencv_omnidir_stereo.dataset.json")
    out = tmp_path / "omnidir.calib.json"
    code = main(["calibrate", str(path), "-o", str(out), "--quiet"])
    captured = capsys.readouterr()
    print(captured.out)
    print(captured.err)
    if code not in (0, 1):  # the file is valid: never bad input, never a crash
        pytest.fail(f"exit {code}: {captured.err}")
    calib = load_calibration(out)
    R, t = calib.cam_from_rig["cam1"]
    rms = {c: calib.statistics["cameras"][c]["rms_px"] for c in calib.camera_ids}
    rms_rig = {c: calib.statistics["cameras"][c]["rms_px_rig"] for c in calib.camera_ids}
    pr = calib.statistics["cameras"]["cam1"]["cam_from_rig_precision"]
    R0, t0 = (np.asarray(pr["cam_from_rig_averaged"][k]) for k in ("R", "t"))
    print(
        f"exit {code}; RMS per camera {rms}, with the rig {rms_rig}; baseline "
        f"{np.linalg.norm(t) * 1e3:.2f} +- {pr['baseline_sigma'] * 1e3:.3f} mm (averaged "
        f"{np.linalg.norm(t0) * 1e3:.2f}); rotation {np.degrees(rotation_angle(R)):.3f} +- "
        f"{pr['rotation_sigma_deg']:.4f} deg (averaged {np.degrees(rotation_angle(R0)):.3f}); "
        f"distrust {calib.statistics['distrust']}"
    )
    assert calib.statistics["n_frames"] == 39
    assert calib.statistics["rig_adjustment"] == RIG_ADJUSTMENT
    assert code == 0, calib.statistics["distrust"]
    assert rms["cam0"] < 0.439 and rms["cam1"] < 0.407
    assert np.linalg.norm(t) == pytest.approx(0.1605, abs=0.003)
    assert np.degrees(rotation_angle(R)) == pytest.approx(7.93, abs=0.3)
    # the joint adjustment: the rig's poses fit better than the averaged ones did
    assert all(rms_rig[c] < 0.4 for c in rms_rig)
    assert 0 < pr["rotation_sigma_deg"] < 0.1 and 0 < pr["baseline_sigma"] < 0.001
