"""``gtsam-sphere simulate``: simulate a calibration: the paper's room, a board, a 3D object.

The arguments and the run are :mod:`gtsam_sphere.simulate`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "simulate"
HELP = "simulate a calibration: the paper's room, a board, a 3D object"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere simulate``."""
    from .. import simulate

    simulate.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere simulate``."""
    from .. import simulate

    return simulate.run_cli(args)
