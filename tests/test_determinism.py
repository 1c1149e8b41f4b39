"""Determinism: the same dataset and seed give a byte-identical calibration file.

Two ``gtsam-sphere calibrate`` runs in this process (state left behind by the first
run must not change the second), and one in a fresh interpreter with another
``PYTHONHASHSEED`` (set iteration order must not leak into the result). On failure
the message lists the JSON fields that differ.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys

import pytest

from gtsam_sphere.cli import main
from gtsam_sphere.simulate import SimulationOptions, simulate_room, write_simulation

SEED = "5"


def _differences(a, b, path: str = "") -> list[str]:
    """JSON paths where two parsed documents differ (``/history[3]/cost: 1.0 != 1.5``)."""
    if type(a) is not type(b):
        return [f"{path}: {type(a).__name__} != {type(b).__name__}"]
    if isinstance(a, dict):
        out = [f"{path}/{k}: only in one file" for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += _differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for k, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{k}]")]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def _assert_same_bytes(first, second) -> None:
    x, y = first.read_bytes(), second.read_bytes()
    if x != y:
        diffs = _differences(json.loads(x), json.loads(y))
        pytest.fail(
            f"{first.name} and {second.name} differ in {len(diffs)} fields: "
            + "; ".join(diffs[:15])
            + ("" if diffs else " (same JSON content, different bytes: key order or format)")
        )


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A small simulated room (12 images, 40 targets, 2% blunders), calibrated with --seed 5."""
    out = tmp_path_factory.mktemp("determinism")
    sim = simulate_room(
        SimulationOptions(
            lens="sphere",
            fov_deg=200,
            noise_px=0.3,
            blunder_rate=0.02,
            n_images=12,
            n_targets=40,
            n_checkpoints=10,
            width=800,
            height=600,
            seed=3,
        )
    )
    dataset = write_simulation(sim, out)["dataset"]
    calib = out / "first.json"
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["calibrate", str(dataset), "-o", str(calib), "--seed", SEED, "--quiet"])
    assert rc in (0, 1) and calib.exists()
    return dataset, calib, rc


@pytest.mark.slow
def test_calibrate_twice_in_one_process_gives_identical_bytes(first_run):
    dataset, first, rc_first = first_run
    second = first.with_name("second.json")
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["calibrate", str(dataset), "-o", str(second), "--seed", SEED, "--quiet"])
    assert rc == rc_first
    _assert_same_bytes(first, second)


@pytest.mark.slow  # end-to-end
def test_calibrate_in_a_fresh_process_with_another_hash_seed_gives_identical_bytes(first_run):
    dataset, first, rc_first = first_run
    third = first.with_name("third.json")
    env = dict(os.environ, PYTHONHASHSEED="12345")
    argv = ["calibrate", str(dataset), "-o", str(third), "--seed", SEED, "--quiet"]
    proc = subprocess.run(
        [sys.executable, "-m", "gtsam_sphere", *argv],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == rc_first, proc.stderr[-2000:]
    _assert_same_bytes(first, third)
