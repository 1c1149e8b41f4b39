"""``gtsam-sphere demo``: the README's first command, on a small room."""

from __future__ import annotations

import pytest

from gtsam_sphere.cli import main


@pytest.mark.slow  # two small simulated rooms calibrated end to end, ~10 s
def test_demo_exits_as_calibrate_does(tmp_path, capsys):
    """0 and "trusted" for the default model; 1 and the reason for the paper's sphere
    mapping chosen for an equidistant lens it cannot follow (the demo used to exit 0
    whenever the optimiser converged)."""
    common = ["--images", "10", "--no-oracle", "--quiet", "--fov-deg", "150"]
    assert main(["demo", "-o", str(tmp_path / "a"), *common]) == 0
    out = capsys.readouterr().out
    assert "\n  trusted\n" in out and (tmp_path / "a" / "calibration.json").exists()
    args = ["demo", "-o", str(tmp_path / "b"), "--lens", "equidistant", "--model", "sphere"]
    assert main([*args, *common]) == 1
    out = capsys.readouterr().out
    assert "NOT trusted" in out and "does not follow this lens" in out
