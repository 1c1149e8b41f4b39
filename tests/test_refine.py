"""Map refinement with a frozen calibration: global, partitioned (in process and on Ray), CLI."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest
from helpers import bare_calibration, bare_rig_calibration

from gtsam_sphere.cli import main
from gtsam_sphere.core.errors import InputError, OptionsError
from gtsam_sphere.estimation.map_problem import refine_global
from gtsam_sphere.estimation.partition import covisibility_partition
from gtsam_sphere.estimation.partitioned import PartitionedOptions, make_submaps, refine_map
from gtsam_sphere.simulate.building import (
    building_map_problem,
    room_aligned_rms_m,
    simulate_building,
)


@pytest.fixture(scope="module")
def small_map():
    """A 4-room building, ~6,000 observations, perturbed start, prior and odometry."""
    scene = simulate_building(n_images=100, obs_per_image=60.0, seed=3)
    return scene, building_map_problem(scene, seed=4)


@pytest.fixture(scope="module")
def global_result(small_map):
    return refine_global(small_map[1])


def test_partitioned_solve_equals_the_global_solve_and_the_truth(small_map, global_result):
    scene, problem = small_map
    start = room_aligned_rms_m(scene, problem.points_world)
    result = refine_map(problem, 3)
    assert result.converged and global_result.converged
    assert result.stats["separator_dim"] > 0  # the submaps do share variables
    assert abs(result.error - global_result.error) <= 1e-9 * global_result.error
    np.testing.assert_allclose(result.points_world, global_result.points_world, atol=1e-8)
    np.testing.assert_allclose(result.world_from_cam_t, global_result.world_from_cam_t, atol=1e-8)
    # round trip against the truth: 8 cm start error (after a similarity per room) down to 1 cm
    final = room_aligned_rms_m(scene, result.points_world)
    assert final < 0.15 * start


@pytest.mark.slow
def test_host_keeping_one_submap_alive_gives_the_same_answer_bit_for_bit(small_map):
    """A host of 3 submaps that keeps 1 worker alive makes the others again from their data
    at each call: the same steps, to the last bit, and never more than 1 alive."""
    from gtsam_sphere.estimation.partitioned import LocalExecutor

    problem = small_map[1]
    hosts = []

    def one_resident(submaps, separator):
        hosts.append(LocalExecutor(submaps, separator, resident=1))
        return hosts[-1]

    reference = refine_map(problem, 3)
    result = refine_map(problem, 3, executor_factory=one_resident)
    assert result.error == reference.error and result.iterations == reference.iterations
    np.testing.assert_array_equal(result.points_world, reference.points_world)
    np.testing.assert_array_equal(result.world_from_cam_R, reference.world_from_cam_R)
    host = hosts[0].host
    assert len(host.workers) == 1
    assert host.workers_made >= 3 * 2 * result.iterations  # reduce and step each make one
    assert reference.stats["workers"][0]["workers_made"] == 3


def test_partition_balances_observations_and_cuts_at_doors(small_map):
    scene, problem = small_map
    part = covisibility_partition(problem.obs_image, problem.obs_point, 4, problem.n_images)
    counts = np.bincount(part[problem.obs_image], minlength=4)
    share = problem.n_observations / 4
    assert np.all(np.abs(counts - share) <= 0.15 * share)
    submaps, _ = make_submaps(problem, 4)
    # rooms of 25 images: each cut falls at a door, only the odometry's pose is shared
    keys = [set(np.r_[s.pose_keys(), s.point_keys()].tolist()) for s in submaps]
    shared = set.union(*[a & b for i, a in enumerate(keys) for b in keys[i + 1 :]])
    assert len(shared) <= 3
    assert sum(s.n_observations for s in submaps) == problem.n_observations


@pytest.mark.slow
def test_interrupted_run_resumes_from_its_checkpoint(small_map, global_result, tmp_path):
    problem = small_map[1]
    checkpoint = tmp_path / "run.checkpoint.npz"
    options = PartitionedOptions(checkpoint=checkpoint)

    def interrupt(iteration, info):
        if iteration == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        refine_map(problem, 2, options=options, on_iteration=interrupt)
    assert checkpoint.is_file()
    lines = []
    result = refine_map(problem, 2, options=options, progress=lines.append)
    assert result.stats["resumed_from"] == 2
    assert "resumed" in lines[0]
    assert abs(result.error - global_result.error) <= 1e-9 * global_result.error
    assert not checkpoint.exists()  # removed once the run finished
    # a checkpoint of other submaps is ignored, not used
    with pytest.raises(KeyboardInterrupt):
        refine_map(problem, 2, options=options, on_iteration=interrupt)
    result = refine_map(problem, 3, options=options)
    assert result.stats["resumed_from"] is None


def test_parts_generated_alone_refine_to_the_whole_maps_solution():
    from gtsam_sphere.estimation.graph import pose_key
    from gtsam_sphere.estimation.partitioned import refine_submaps
    from gtsam_sphere.simulate.building import BuildingOptions, building_parts

    options = BuildingOptions(n_images=100, obs_per_image=40.0, seed=3)
    parts, shared = building_parts(options, 3)
    whole = building_parts(options, 1)[0][0].build()  # the same building in one process
    assert sum(p.build().n_observations for p in parts) == whole.n_observations
    reference = refine_global(whole)
    separator = np.array([pose_key(int(i)) for i in shared], np.uint64)
    states, info, _ = refine_submaps(parts, separator)  # recipes: built by the workers
    assert info["separator_dim"] == 6 * len(shared)
    assert abs(info["error"] - reference.error) <= 1e-9 * reference.error
    truth, _ = parts[1].truth()
    assert np.sqrt(np.mean((states[1]["P"] - truth) ** 2)) < 0.05  # 5 cm start noise, drift


def test_bad_map_input_names_the_item(small_map):
    problem = small_map[1]
    from dataclasses import replace

    bad = replace(problem, obs_point=problem.obs_point.copy())
    bad.obs_point[7] = problem.n_points + 5
    with pytest.raises(InputError, match="observation 7"):
        refine_global(bad)
    bad = replace(problem, uv_px=problem.uv_px.copy())
    bad.uv_px[11, 0] = np.nan
    with pytest.raises(InputError, match="observation 11"):
        refine_map(bad, 2)
    with pytest.raises(InputError, match="partitions"):
        refine_map(problem, problem.n_images + 1)


def test_ray_missing_names_the_extra(monkeypatch):
    import sys

    from gtsam_sphere.estimation.ray_executor import import_ray

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(OptionsError, match=r"gtsam-sphere\[distributed\]"):
        import_ray()


# --------------------------------------------------------------------------- command line


def _write_map(scene, problem, path, with_poses: slice):
    """dataset@1 of the building; images in ``with_poses`` carry a start cam_from_world."""
    targets = [
        {"id": f"L{j}", "xyz": problem.points_world[j].tolist()}
        for j in range(len(problem.points_world))
    ]
    images = []
    for i in range(scene.n_images):
        sel = np.flatnonzero(scene.obs_image == i)
        im = {
            "id": f"I{i:04d}",
            "observations": [
                {"target": f"L{scene.obs_point[k]}", "uv": scene.uv_px[k].tolist()} for k in sel
            ],
        }
        if i in range(scene.n_images)[with_poses]:
            R = problem.world_from_cam_R[i].T
            im["cam_from_world"] = {
                "R": R.tolist(),
                "t": (-R @ problem.world_from_cam_t[i]).tolist(),
            }
        images.append(im)
    doc = {
        "format": "gtsam-sphere/dataset@1",
        "units": "m",
        "camera": {"width": scene.camera.width, "height": scene.camera.height},
        "targets": targets,
        "images": images,
    }
    path.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def cli_map(tmp_path_factory):
    d = tmp_path_factory.mktemp("refine")
    scene = simulate_building(n_images=50, obs_per_image=50.0, seed=5)
    problem = building_map_problem(scene, seed=6)
    _write_map(scene, problem, d / "map.json", slice(0, 40))  # the last 10 are resected
    bare_calibration(scene.camera).save(d / "calib.json")
    return scene, d


def _refine_cli(d, out, *extra):
    """``gtsam-sphere refine`` of ``d``'s map and calibration to ``d / out`` (sigma 0.5 px)."""
    return main(
        ["refine", str(d / "map.json"), "--calibration", str(d / "calib.json"),
         "-o", str(d / out), "--sigma-px", "0.5", *extra]
    )  # fmt: skip


@pytest.mark.slow  # the rig test runs the same two paths in the fast loop
def test_cli_refine_local_and_partitioned_agree(cli_map, capsys):
    scene, d = cli_map
    assert _refine_cli(d, "g.json", "--quiet") == 0
    assert _refine_cli(d, "p.json", "--partitions", "2") == 0
    err = capsys.readouterr().err
    assert "iteration" in err  # progress without --quiet
    from gtsam_sphere import load_calibration

    g, p = load_calibration(d / "g.json"), load_calibration(d / "p.json")
    assert g.image_ids == p.image_ids and len(g.image_ids) == scene.n_images
    np.testing.assert_allclose(p.target_xyz, g.target_xyz, atol=1e-7)
    np.testing.assert_allclose(p.cam_from_world_t, g.cam_from_world_t, atol=1e-7)
    assert g.statistics["rms_px"] < 1.0 and p.statistics["partitions"] == 2
    assert not (d / "p.json.checkpoint.npz").exists()


def test_cli_refine_bad_input_exits_2(cli_map, tmp_path, capsys):
    _, d = cli_map
    doc = json.loads((d / "map.json").read_text())
    doc["images"][3]["observations"][0]["target"] = "NOPE"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    args = ["--calibration", str(d / "calib.json"), "-o", str(tmp_path / "o.json")]
    assert main(["refine", str(tmp_path / "bad.json"), *args]) == 2
    assert "'NOPE'" in capsys.readouterr().err
    assert main(["refine", str(d / "map.json"), *args, "--address", "auto"]) == 2
    assert "--engine ray" in capsys.readouterr().err
    assert main(["refine", str(d / "map.json"), *args, "--partitions", "0"]) == 2
    assert not (tmp_path / "o.json").exists()


# --------------------------------------------------------------------------- Ray


@pytest.mark.slow
def test_ray_worker_killed_mid_run_converges_to_the_same_answer(small_map, global_result):
    ray = pytest.importorskip(
        "ray", reason="Ray not installed (pip install 'gtsam-sphere[distributed]')"
    )
    from gtsam_sphere.estimation.ray_executor import RayExecutor

    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    try:
        made = {}

        def factory(submaps, separator):
            made["executor"] = RayExecutor(submaps, separator, n_workers=2)
            return made["executor"]

        killed = []

        def kill(iteration, info):
            if iteration == 2:
                pid = made["executor"].infos()[0]["pid"]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)

        result = refine_map(small_map[1], 3, executor_factory=factory, on_iteration=kill)
        assert killed
        pids = [w["pid"] for w in result.stats["workers"]]
        assert killed[0] not in pids  # the actor was restarted in a new process
        assert result.converged
        assert result.iterations == global_result.iterations  # no iteration lost or repeated
        assert abs(result.error - global_result.error) <= 1e-9 * global_result.error
        np.testing.assert_allclose(result.points_world, global_result.points_world, atol=1e-8)
    finally:
        ray.shutdown()


@pytest.mark.slow
def test_cli_refine_on_ray(cli_map, capsys):
    pytest.importorskip("ray", reason="Ray not installed (pip install 'gtsam-sphere[distributed]')")
    _, d = cli_map
    ray_args = ("--engine", "ray", "--workers", "2", "--partitions", "2", "--quiet")
    assert _refine_cli(d, "r.json", *ray_args) == 0
    assert _refine_cli(d, "g2.json", "--quiet") == 0
    from gtsam_sphere import load_calibration

    r, g = load_calibration(d / "r.json"), load_calibration(d / "g2.json")
    np.testing.assert_allclose(r.target_xyz, g.target_xyz, atol=1e-7)
    assert r.statistics["engine"] == "ray"


def _rig_map(d):
    """A back-to-back rig (cam1 turned 180 deg, 10 cm aside) along the building's path."""
    from gtsam_sphere.simulate.building import rotation_exp

    scene = simulate_building(n_images=50, obs_per_image=40.0, seed=7)
    problem = building_map_problem(scene, seed=8)
    cam = scene.camera
    c1_from_rig = (rotation_exp(np.array([0.0, np.pi, 0.0])), np.array([0.1, 0.0, 0.0]))
    rng = np.random.default_rng(9)
    images, truth_cw = [], []
    for i in range(scene.n_images):
        Rwc, twc = scene.world_from_cam_R[i], scene.world_from_cam_t[i]
        R0, t0 = Rwc.T, -Rwc.T @ twc  # cam0_from_world = rig_from_world
        for cid, (Rc, tc) in (("cam0", (np.eye(3), np.zeros(3))), ("cam1", c1_from_rig)):
            R, t = Rc @ R0, Rc @ t0 + tc
            room = scene.room_of_image[i]
            idx = np.flatnonzero(scene.room_of_point == room)
            pc = scene.points_world[idx] @ R.T + t
            alpha = np.arctan2(np.hypot(pc[:, 0], pc[:, 1]), pc[:, 2])
            ok = (alpha < np.radians(90.0)) & (np.linalg.norm(pc, axis=1) > 0.3)
            uv = cam.project(pc[ok]) + rng.normal(scale=0.5, size=(int(ok.sum()), 2))
            inside = np.all((uv > 2) & (uv < cam.width - 3), axis=1)
            idx, uv = idx[ok][inside], uv[inside]
            if len(idx) < 6:
                continue
            start = problem.world_from_cam_R[i].T  # the perturbed start, cam0
            entry = {
                "id": f"{cid}_{i:03d}",
                "camera": cid,
                "frame": f"{i:03d}",
                "observations": [{"target": f"L{j}", "uv": p.tolist()} for j, p in zip(idx, uv)],
            }
            if cid == "cam0":
                entry["cam_from_world"] = {
                    "R": start.tolist(),
                    "t": (-start @ problem.world_from_cam_t[i]).tolist(),
                }
            images.append(entry)
            truth_cw.append((entry["id"], R, t))
    doc = {
        "format": "gtsam-sphere/dataset@2",
        "units": "m",
        "cameras": [{"id": c, "width": cam.width, "height": cam.height} for c in ("cam0", "cam1")],
        "targets": [
            {"id": f"L{j}", "xyz": problem.points_world[j].tolist()} for j in range(scene.n_points)
        ],
        "images": images,
    }
    (d / "rig_map.json").write_text(json.dumps(doc))
    rig = bare_rig_calibration(
        {"cam0": cam, "cam1": cam},
        {"cam0": (np.eye(3), np.zeros(3)), "cam1": c1_from_rig},
        rms_px=0.5,
    )
    rig.save(d / "rig_calib.json")
    return scene, dict((k, (R, t)) for k, R, t in truth_cw)


def test_cli_refine_rig_map_keeps_the_rig_rigid(tmp_path):
    from gtsam_sphere import load_calibration

    scene, _ = _rig_map(tmp_path)
    args = ["--calibration", str(tmp_path / "rig_calib.json"), "--sigma-px", "0.5", "--quiet"]
    assert (
        main(["refine", str(tmp_path / "rig_map.json"), *args, "-o", str(tmp_path / "g.json")]) == 0
    )
    out = ["-o", str(tmp_path / "p.json"), "--partitions", "3"]
    assert main(["refine", str(tmp_path / "rig_map.json"), *args, *out]) == 0
    g, p = load_calibration(tmp_path / "g.json"), load_calibration(tmp_path / "p.json")
    np.testing.assert_allclose(p.target_xyz, g.target_xyz, atol=1e-7)
    assert len(g.frame_ids) == scene.n_images
    # every frame's two images keep the calibrated cam1_from_cam0 (ties of 1e-4 rad / m)
    Rc, tc = g.cam_from_rig["cam1"]
    k = {iid: q for q, iid in enumerate(g.image_ids)}
    for i in range(0, scene.n_images, 7):
        a, b = k.get(f"cam0_{i:03d}"), k.get(f"cam1_{i:03d}")
        if a is None or b is None:
            continue
        R_rel = g.cam_from_world_R[b] @ g.cam_from_world_R[a].T  # cam1_from_cam0
        t_rel = g.cam_from_world_t[b] - R_rel @ g.cam_from_world_t[a]
        np.testing.assert_allclose(R_rel, Rc, atol=3e-4)
        np.testing.assert_allclose(t_rel, tc, atol=3e-4)
    # the targets' shape (after a similarity per room) goes from the 5 cm start to < 1 cm
    j = np.array([int(t[1:]) for t in g.target_ids])
    for room in np.unique(scene.room_of_point[j]):
        sel = scene.room_of_point[j] == room
        if sel.sum() < 10:
            continue
        from gtsam_sphere.core.geometry import fit_similarity

        est = g.target_xyz[sel]
        aligned = fit_similarity(est, scene.points_world[j[sel]]).apply(est)
        assert np.sqrt(np.mean(np.sum((aligned - scene.points_world[j[sel]]) ** 2, 1))) < 0.01


def test_cli_interrupted_refine_says_it_resumes(cli_map, tmp_path, capsys, monkeypatch):
    import gtsam_sphere.estimation.partitioned as partitioned

    _, d = cli_map
    real = partitioned._save_checkpoint
    calls = []

    def save_then_interrupt(*args, **kwargs):
        real(*args, **kwargs)
        calls.append(1)
        raise KeyboardInterrupt

    monkeypatch.setattr(partitioned, "_save_checkpoint", save_then_interrupt)
    out = tmp_path / "r.json"
    args = ["refine", str(d / "map.json"), "--calibration", str(d / "calib.json"), "-o", str(out)]
    assert main([*args, "--partitions", "2", "--sigma-px", "0.5", "--quiet"]) == 130
    err = capsys.readouterr().err
    assert "resume from its checkpoint" in err and not out.exists()
    monkeypatch.setattr(partitioned, "_save_checkpoint", real)
    assert main([*args, "--partitions", "2", "--sigma-px", "0.5"]) == 0
    assert "resumed from" in capsys.readouterr().err
    assert not (tmp_path / "r.json.checkpoint.npz").exists()
