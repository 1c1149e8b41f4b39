"""``gtsam-sphere calibrate``: calibrate a dataset@1 file (or a dataset@2 rig)."""

from __future__ import annotations

import argparse
import logging
import time

from ..core.errors import OptionsError
from ..estimation.optimize import stderr_progress
from .common import add_calibration_options, options_from_args, print_outliers, print_statistics

logger = logging.getLogger("gtsam_sphere.cli")

NAME = "calibrate"
HELP = "calibrate a dataset@1 file (or a dataset@2 rig)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere calibrate``."""
    p.add_argument("dataset")
    p.add_argument("-o", "--output", required=True, help="calibration@1 (@2 for a rig) to write")
    add_calibration_options(p)
    p.add_argument(
        "--camera-model",
        action="append",
        metavar="CAMERA=MODEL",
        help="rigs: the model of one camera (repeat per camera; --model for the others)",
    )
    p.add_argument(
        "--no-joint",
        action="store_true",
        help="rigs: stop at the averaged extrinsics (each camera alone, cam_from_rig "
        "averaged over the shared frames), without the joint rig adjustment",
    )


def run(args) -> int:
    """Run ``gtsam-sphere calibrate``: 0 trusted, 1 not to be trusted (bad input raises)."""
    from ..estimation import rig
    from ..estimation.calibrate import calibrate
    from ..io.dataset import load_dataset

    if rig.is_rig_dataset(args.dataset):  # dataset@2: the rig path (estimation/rig.py)
        return rig.run_cli(args, options_from_args(args), None if args.quiet else stderr_progress)
    if args.camera_model:
        raise OptionsError("--camera-model applies to a rig (dataset@2); use --model")
    if getattr(args, "no_joint", False):
        raise OptionsError("--no-joint applies to a rig (dataset@2)")
    dataset = load_dataset(args.dataset)
    for iid, why in dataset.skipped_images:
        logger.warning("image %r skipped: %s", iid, why)
    if dataset.dropped:
        logger.warning(
            "%d observations outside the image dropped (listed in the output)",
            len(dataset.dropped),
        )
    t0 = time.perf_counter()
    calib = calibrate(dataset, options_from_args(args), None if args.quiet else stderr_progress)
    calib.save(args.output)
    cam = calib.camera
    print(
        f"{args.output}: model {calib.model}, xp {cam.xp:.3f} px, yp {cam.yp:.3f} px, "
        f"c {cam.c:.3f} px ({time.perf_counter() - t0:.1f} s)"
    )
    print_statistics(calib.statistics)
    print_outliers(calib.extra.get("outliers", []))
    # the reasons not to trust the result were logged once by calibrate()
    if args.control_sigma is None and bool((dataset.target_sigma == 0).all()):
        logger.info(
            "hint: every target was held exact (--exact-targets); real boards are rarely "
            "flat or true to scale to 0.1 mm: without --exact-targets their shape is "
            "estimated (README, 'Printed boards')"
        )
    return 0 if calib.statistics.get("trusted", calib.statistics["converged"]) else 1
