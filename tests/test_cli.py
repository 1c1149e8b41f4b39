"""The command line: calibrate writes calibration@1, load_calibration reproduces it."""

import json

import numpy as np
import pytest
from helpers import shared_data_file

from gtsam_sphere import load_calibration
from gtsam_sphere.cli import main
from gtsam_sphere.simulate import SimulationOptions, simulate_room, write_simulation


@pytest.fixture(scope="module")
def small_room(tmp_path_factory):
    out = tmp_path_factory.mktemp("room")
    sim = simulate_room(
        SimulationOptions(
            lens="sphere",
            fov_deg=200,
            noise_px=0.3,
            n_images=16,
            n_targets=150,
            n_checkpoints=60,
            width=1600,
            height=1200,
            seed=5,
        )
    )
    return sim, write_simulation(sim, out)


@pytest.mark.slow  # end-to-end
def test_calibrate_evaluate_and_reload(small_room, tmp_path, capsys):
    sim, paths = small_room
    calib_path = tmp_path / "calib.json"
    rc = main(
        ["calibrate", str(paths["dataset"]), "-o", str(calib_path), "--model", "sphere", "--quiet"]
    )
    assert rc == 0
    doc = json.loads(calib_path.read_text())
    assert doc["format"] == "gtsam-sphere/calibration@1"
    assert doc["statistics"]["n_observations"] == sum(
        len(im["observations"]) for im in sim.dataset["images"]
    )
    calib = load_calibration(calib_path)
    # project with the adjusted poses reproduces the observations to the reported RMS
    im = sim.dataset["images"][0]
    i = calib.image_ids.index(im["id"])
    xyz = np.array([calib.target(o["target"]) for o in im["observations"]])
    uv = np.array([o["uv"] for o in im["observations"]])
    pc = xyz @ calib.cam_from_world_R[i].T + calib.cam_from_world_t[i]
    assert np.sqrt(np.mean(np.sum((calib.camera.project(pc) - uv) ** 2, 1))) < 1.0
    rays = calib.camera.unproject(uv, hemisphere=np.sign(pc[:, 2]))
    # no ray only for pixels past the sphere's rim (noise at ~90 deg incidence)
    rim = np.linalg.norm(calib.camera.ideal_from_pixels(uv), axis=1) > calib.camera.c
    assert np.array_equal(np.isnan(rays[:, 0]), rim)
    # rays agree with the points to within the pixel noise: the sphere mapping's slope is
    # c * |cos(incidence)| px/rad, so an angle error times that slope is a pixel error
    cosang = np.sum(rays * pc / np.linalg.norm(pc, axis=1)[:, None], axis=1)
    angle_rad = np.arccos(np.clip(cosang, -1, 1))
    slope = calib.camera.c * np.abs(pc[:, 2]) / np.linalg.norm(pc, axis=1)
    ok = ~rim
    assert np.max(angle_rad[ok] * slope[ok]) < 1.5  # 5 sigma of the 0.3 px noise
    rc = main(["evaluate", str(calib_path), str(paths["checkpoints"])])
    assert rc == 0
    assert "RMSE X / Y / Z (mm)" in capsys.readouterr().out


@pytest.mark.slow  # end-to-end
def test_default_model_unprojects_past_90_degrees_without_a_hemisphere(tmp_path):
    """The default (radial + kNN) on a 200 deg fisheye: unproject(uv) alone finds every ray."""
    from gtsam_sphere.simulate import gopro_like

    sim = simulate_room(
        gopro_like(
            fov_deg=200.0, fill="circle", n_images=16, n_targets=150, n_checkpoints=60, seed=5
        )
    )
    paths = write_simulation(sim, tmp_path / "sim")
    out = tmp_path / "c.json"
    assert main(["calibrate", str(paths["dataset"]), "-o", str(out), "--quiet"]) == 0
    calib = load_calibration(out)
    assert calib.model == "radial+knn" and calib.camera.mapping == "radial"
    obs = calib.extra["observations"]
    uv = np.asarray(obs["uv_px"], float)
    index = {t: k for k, t in enumerate(calib.target_ids)}
    xyz = calib.target_xyz[[index[t] for t in obs["target"]]]
    img = [calib.image_ids.index(i) for i in obs["image"]]
    pc = np.einsum("nij,nj->ni", calib.cam_from_world_R[img], xyz) + calib.cam_from_world_t[img]
    assert np.max(obs["incidence_deg"]) > 95.0
    rays = calib.camera.unproject(uv)
    assert np.isfinite(rays).all()
    cosang = np.sum(rays * pc / np.linalg.norm(pc, axis=1)[:, None], axis=1)
    angle_px = np.arccos(np.clip(cosang, -1, 1)) * calib.camera.c  # ~ px for an equidistant lens
    back = np.asarray(obs["incidence_deg"]) > 90
    assert back.sum() > 20
    # 2 mm pupil shift and 2 px error field included: rays within a few noise sigmas
    assert np.median(angle_px) < 0.5 and np.percentile(angle_px[back], 95) < 2.0


def test_bad_dataset_exits_2_with_message(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "gtsam-sphere/dataset@9"}')
    assert main(["calibrate", str(bad), "-o", str(tmp_path / "c.json")]) == 2
    assert "unsupported version" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize(
    "name", ["opencv_fisheye_left.dataset.json", "ov_plane_train.dataset.json"]
)
@pytest.mark.slow  # end-to-end
def test_real_data_calibrates_with_every_corner(name, tmp_path):
    path = shared_data_file(name)
    doc = json.loads(path.read_text())
    n_input = sum(len(im["observations"]) for im in doc["images"])
    out = tmp_path / "c.json"
    assert main(["calibrate", str(path), "-o", str(out), "--quiet"]) == 0
    stats = json.loads(out.read_text())["statistics"]
    assert stats["n_observations"] == n_input and stats["n_rejected"] == 0
    assert stats["n_images_skipped"] == 0


@pytest.mark.slow  # end-to-end
def test_ctrl_c_leaves_the_previous_file_and_says_so(small_room, tmp_path, capsys, monkeypatch):
    """Issue 6: an interrupted run writes nothing and names the last good state."""
    import gtsam_sphere.estimation.calibrate as calibrate_module

    _, paths = small_room
    out = tmp_path / "c.json"
    out.write_text('{"previous": true}')

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate_module, "optimize", interrupted)
    rc = main(["calibrate", str(paths["dataset"]), "-o", str(out), "--quiet"])
    assert rc == 130
    assert out.read_text() == '{"previous": true}'
    err = capsys.readouterr().err
    assert "interrupted" in err and "previous" in err and str(out) in err
    assert [p.name for p in tmp_path.iterdir()] == ["c.json"]  # no temporary left behind


@pytest.mark.slow
@pytest.mark.parametrize("unbuffered", [False, True])
def test_closed_stdout_ends_quietly(tmp_path, unbuffered):
    """``gtsam-sphere ... | head``: exit 141, no "error: Broken pipe", no traceback.

    Block-buffered (a pipe, no ``PYTHONUNBUFFERED``: what a fresh machine has) the
    closed pipe shows only when stdout is flushed; at exit Python would return 120."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gtsam_sphere",
            "simulate",
            "--preset",
            "gopro",
            "-o",
            str(tmp_path / "sim"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    proc.stdout.close()  # the reader goes away before the first line
    err = proc.stderr.read().decode()
    assert proc.wait() == 141
    assert "Broken pipe" not in err and "Traceback" not in err, err
    # the files written before the pipe closed are complete
    assert (tmp_path / "sim" / "dataset.json").is_file()
