"""``gtsam-sphere export``: fit OpenCV / Kalibr camera models to a calibration.

The arguments and the run are :mod:`gtsam_sphere.apps.export`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "export"
HELP = "fit OpenCV / Kalibr / ROS / mrcal / basalt camera models to a calibration"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere export``."""
    from ..apps import export

    export.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere export``."""
    from ..apps import export

    if args.target in export.RIG_TARGETS:  # kalibr camchain, OpenCV stereo: a rig
        from ..apps import export_rig

        return export_rig.run_cli(args)
    if args.target in export.FORMAT_TARGETS:  # ROS CameraInfo, mrcal, basalt
        from ..apps import export_formats

        return export_formats.run_cli(args)
    return export.run_cli(args)
