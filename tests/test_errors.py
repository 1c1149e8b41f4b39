"""The exception hierarchy (gtsam_sphere.core.errors) and the one exit-code table of the CLI."""

import argparse
import json

import pytest

import gtsam_sphere.cli as cli
from gtsam_sphere.core.errors import (
    DatasetError,
    DegenerateGeometryError,
    GtsamSphereError,
    InitialisationError,
    InputError,
    OptionsError,
)
from gtsam_sphere.estimation import diagnose
from gtsam_sphere.io import dataset
from gtsam_sphere.simulate import SimulationOptions, simulate_room, write_simulation


def test_hierarchy():
    for cls in (DatasetError, DegenerateGeometryError, InitialisationError, OptionsError):
        assert issubclass(cls, InputError)
    assert issubclass(InputError, GtsamSphereError)
    assert issubclass(InputError, ValueError)  # `except ValueError` callers keep working
    assert issubclass(DegenerateGeometryError, DatasetError)  # as before errors.py
    # one class each, wherever it is imported from
    assert dataset.DatasetError is DatasetError
    assert diagnose.DegenerateGeometryError is DegenerateGeometryError


def test_degenerate_geometry_error_keeps_its_problems_through_pickle():
    import pickle

    problem = diagnose.Problem(
        code=diagnose.ProblemCode.SINGLE_IMAGE,
        message="only one usable image",
        advice="capture more images",
        fatal=True,
        items=("A",),
    )
    exc = pickle.loads(pickle.dumps(DegenerateGeometryError([problem])))
    assert exc.problems == [problem] and "only one usable image" in str(exc)


@pytest.mark.parametrize(
    ("exc", "code"),
    [
        (InputError("x"), 2),
        (DatasetError("x"), 2),
        (DegenerateGeometryError([]), 2),
        (InitialisationError("x"), 2),
        (OptionsError("x"), 2),
        (FileNotFoundError(2, "No such file or directory", "out.json"), 2),
        (PermissionError(13, "Permission denied", "out.json"), 2),
        (BrokenPipeError(32, "Broken pipe"), 141),
        (KeyboardInterrupt(), 130),
        (ValueError("inside numpy"), None),  # a bug, not bad input: keeps its traceback
        (RuntimeError("x"), None),
        (SystemExit(3), None),
    ],
)
def test_exit_code_table(exc, code):
    assert cli.exit_code(exc) == code


def test_table_lists_subclasses_before_their_bases():
    classes = [cls for cls, _ in cli.EXIT_CODES]
    for i, cls in enumerate(classes):
        assert not any(issubclass(cls, earlier) for earlier in classes[:i]), cls


@pytest.fixture
def raising_command(monkeypatch, tmp_path):
    """``main(["evaluate", ...])`` with the command replaced by one raising ``exc``."""

    def run(exc):
        def command(args):
            raise exc

        monkeypatch.setattr(cli.evaluate, "run", command)
        return cli.main(["evaluate", str(tmp_path / "c.json"), str(tmp_path / "cp.json")])

    return run


@pytest.mark.parametrize(
    ("exc", "code", "message"),
    [
        (DatasetError("d.json: targets[3] has no\n  string 'id'"), 2,
         "error: d.json: targets[3] has no string 'id'"),
        (OptionsError("unknown additional parameter 'k9'"), 2,
         "error: unknown additional parameter 'k9'"),
        (InitialisationError("no image can be initialised"), 2,
         "error: no image can be initialised"),
        (PermissionError(13, "Permission denied", "out.json"), 2,
         "error: out.json: Permission denied"),
        (KeyboardInterrupt(), 130, "interrupted: no output file was written or changed"),
    ],
)  # fmt: skip
def test_main_maps_exceptions_to_codes_and_one_line(raising_command, capsys, exc, code, message):
    assert raising_command(exc) == code
    captured = capsys.readouterr()
    assert captured.err.strip() == message and captured.out == ""


def test_main_lets_bugs_through(raising_command):
    with pytest.raises(ValueError, match="operands could not be broadcast"):
        raising_command(ValueError("operands could not be broadcast"))
    with pytest.raises(ZeroDivisionError):
        raising_command(ZeroDivisionError())


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    sim = simulate_room(
        SimulationOptions(
            lens="equidistant", fov_deg=180, n_images=4, n_targets=80, n_checkpoints=10,
            width=640, height=480, sigma_mode="free", seed=3,
        )
    )  # fmt: skip
    return write_simulation(sim, tmp_path_factory.mktemp("tiny"))["dataset"]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--ap", "k1,k9"], "unknown additional parameter 'k9'"),
        (["--radial-terms", "9"], "the radial mapping has 0 to 6 terms"),
        (["--control-sigma", "-1"], "control_sigma must be a positive number"),
    ],
)
def test_calibrate_bad_options_exit_2(tiny_dataset, tmp_path, capsys, options, message):
    out = tmp_path / "c.json"
    assert cli.main(["calibrate", str(tiny_dataset), "-o", str(out), "--quiet", *options]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].startswith("error: ") and message in lines[-1]
    assert all(line.startswith("warning: ") for line in lines[:-1]), lines  # no traceback
    assert not out.exists()


def test_calibrate_degenerate_geometry_exits_2(tiny_dataset, tmp_path, capsys):
    doc = json.loads(tiny_dataset.read_text())
    doc["images"] = doc["images"][:1]
    one = tmp_path / "one.json"
    one.write_text(json.dumps(doc))
    out = tmp_path / "c.json"
    assert cli.main(["calibrate", str(one), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "degenerate calibration geometry" in err and "only one usable image" in err
    assert not out.exists()


def test_detect_and_simulate_refuse_options_but_not_bugs(monkeypatch, tmp_path):
    from gtsam_sphere import simulate
    from gtsam_sphere.apps import detect

    parser = argparse.ArgumentParser()
    detect.add_cli_arguments(parser)
    args = parser.parse_args(["x.png", "--board", "chessboard:4x6:0.02", "-o", str(tmp_path / "d")])

    def bug(*a, **k):
        raise ValueError("a bug in the detector")

    monkeypatch.setattr(detect, "detect_images", bug)
    with pytest.raises(ValueError, match="a bug in the detector"):
        detect.run_cli(args)
    bad = parser.parse_args(["x.png", "--board", "chessboard:4by6:0.02", "-o", str(tmp_path / "d")])
    assert detect.run_cli(bad) == 2

    parser = argparse.ArgumentParser()
    simulate.add_cli_arguments(parser)
    monkeypatch.setattr(simulate, "simulate_room", lambda options: bug())
    args = parser.parse_args(["--preset", "gopro", "-o", str(tmp_path / "s")])
    with pytest.raises(ValueError, match="a bug"):
        simulate.run_cli(args)
    bad = parser.parse_args(["--lens", "pinhole", "--fov-deg", "190", "-o", str(tmp_path / "s")])
    assert simulate.run_cli(bad) == 2
