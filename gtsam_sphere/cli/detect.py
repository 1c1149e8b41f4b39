"""``gtsam-sphere detect``: detect board corners / markers in images.

The arguments and the run are :mod:`gtsam_sphere.apps.detect`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "detect"
HELP = "detect board corners / markers in images"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere detect``."""
    from ..apps import detect

    detect.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere detect``."""
    if getattr(args, "bag", None):  # images from a ROS bag: a folder per topic
        from ..apps import rosbag_images

        return rosbag_images.run_cli(args)
    if getattr(args, "camera", None):  # a folder per camera: a rig, dataset@2
        from ..apps import detect_rig

        return detect_rig.run_cli(args)
    from ..apps import detect

    return detect.run_cli(args)
