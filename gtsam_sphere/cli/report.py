"""``gtsam-sphere report``: plots and a page for a calibration.

The arguments and the run are :mod:`gtsam_sphere.apps.report`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "report"
HELP = "plots and a page for a calibration"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere report``."""
    from ..apps import report

    report.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere report``."""
    from ..apps import report_rig

    return report_rig.run_cli(args)
