"""``gtsam-sphere undistort``: resample an image to a perspective / panoramic projection.

The arguments and the run are :mod:`gtsam_sphere.apps.undistort`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "undistort"
HELP = "resample an image to a perspective / panoramic projection"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere undistort``."""
    from ..apps import undistort

    undistort.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere undistort``."""
    from ..apps import undistort

    return undistort.run_cli(args)
