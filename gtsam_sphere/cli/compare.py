"""``gtsam-sphere compare``: the paper's Table 1/2 rows on one dataset.

The arguments and the run are :mod:`gtsam_sphere.analysis.compare`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "compare"
HELP = "the paper's Table 1/2 rows on one dataset"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere compare``."""
    from ..analysis import compare

    compare.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere compare``."""
    from ..analysis import compare

    return compare.run_cli(args)
