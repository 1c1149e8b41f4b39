"""``gtsam-sphere evaluate``: 3D accuracy against check points, image statistics."""

from __future__ import annotations

import argparse

from .common import print_statistics

NAME = "evaluate"
HELP = "3D accuracy against check points, image statistics"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere evaluate``."""
    p.add_argument("calibration")
    p.add_argument("checkpoints")


def run(args) -> int:
    """Run ``gtsam-sphere evaluate``: 3D accuracy against check points."""
    from ..analysis.evaluate import evaluate_calibration
    from ..io.calibration import load_calibration
    from ..io.dataset import load_checkpoints

    calib = load_calibration(args.calibration)
    ids, xyz, units = load_checkpoints(args.checkpoints)
    rep = evaluate_calibration(calib, ids, xyz, units)
    f = 1000.0 if units == "m" else 1.0
    unit = "mm" if units == "m" else units
    print(f"check points: {len(rep.ids)} used, {len(rep.missing)} not among adjusted targets")
    print(
        f"  RMSE X / Y / Z ({unit}): {rep.rmse_xyz[0] * f:.3f} / {rep.rmse_xyz[1] * f:.3f} / "
        f"{rep.rmse_xyz[2] * f:.3f}   3D: {rep.rmse_3d * f:.3f}"
    )
    print_statistics(calib.statistics)
    return 0
