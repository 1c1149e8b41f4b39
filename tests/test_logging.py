"""Warnings through logging, progress through callbacks: what the CLI prints where."""

import json
import logging

import pytest
from helpers import bare_calibration

from gtsam_sphere.cli import main
from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.estimation.diagnose import Problem, ProblemCode, raise_if_degenerate
from gtsam_sphere.simulate import SimulationOptions, simulate_room, write_simulation


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    sim = simulate_room(
        SimulationOptions(
            lens="equidistant", fov_deg=180, n_images=4, n_targets=80, n_checkpoints=10,
            width=640, height=480, seed=3,
        )
    )  # fmt: skip
    return write_simulation(sim, tmp_path_factory.mktemp("tiny"))["dataset"]


def _package_logger_state():
    package = logging.getLogger("gtsam_sphere")
    return package.level, list(package.handlers)


@pytest.mark.parametrize("quiet", [False, True])
def test_distrust_is_warned_once_and_quiet_hides_progress_only(
    tiny_dataset, tmp_path, capsys, quiet
):
    before = _package_logger_state()
    out = tmp_path / "c.json"
    argv = ["calibrate", str(tiny_dataset), "-o", str(out), "--model", "sphere"]
    argv += ["--max-iterations", "1"] + (["--quiet"] if quiet else [])
    assert main(argv) == 1  # stopped by the iteration cap: not to be trusted
    captured = capsys.readouterr()
    reasons = json.loads(out.read_text())["statistics"]["distrust"]
    assert any("did not converge" in r for r in reasons)
    err = captured.err.splitlines()
    for reason in reasons:
        assert err.count(f"warning: do not trust this result: {reason}") == 1, captured.err
    assert ("initialising" in captured.err) is not quiet  # a progress line
    assert "warning" not in captured.out  # results only on stdout
    assert _package_logger_state() == before  # the CLI's handler is gone afterwards


def test_export_warns_on_stderr_not_stdout(tmp_path, capsys):
    cam = SphereCamera(640, 480, 319.5, 239.5, 200.0)
    calib = bare_calibration(cam).save(tmp_path / "calib.json")
    out = tmp_path / "cam.yaml"
    argv = ["export", str(calib), "--to", "opencv-fisheye", "-o", str(out), "--samples", "2000"]
    assert main([*argv, "--max-rms-px", "-1"]) == 1  # no fit can be that good
    captured = capsys.readouterr()
    assert "warning" not in captured.out and f"wrote {out}" in captured.out
    assert captured.err.startswith("warning: fit RMS") and captured.err.count("\n") == 1


def test_geometry_warnings_go_to_the_logger_without_a_callback(caplog):
    weak = Problem(ProblemCode.FEW_POINTS, "few", "more", False, ("A",))
    with caplog.at_level(logging.WARNING, logger="gtsam_sphere"):
        assert raise_if_degenerate([weak]) == [weak]
    assert [(r.name, r.levelno, r.getMessage()) for r in caplog.records] == [
        ("gtsam_sphere.estimation.diagnose", logging.WARNING, "[few-points] few -> more")
    ]
