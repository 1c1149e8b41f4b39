"""``gtsam-sphere compare``: the paper's Table 1/2 rows on one dataset.

The arguments and the run are :mod:`gtsam_sphere.analysis.compare`'s own (``add_cli_arguments``,
``run_cli``), imported when the parser is built, as before the split.
"""

from __future__ import annotations

import argparse

NAME = "compare"
HELP = "the paper's Table 1/2 rows on one dataset; a calibration against Kalibr's camchain"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere compare``."""
    from ..analysis import compare
    from ..apps import kalibr_compare

    compare.add_cli_arguments(p)
    p.add_argument(
        "--with",
        dest="with_",
        metavar="CAMCHAIN.yaml|MODEL.cameramodel",
        default=None,
        help="compare CALIB.json with a Kalibr camchain (pinhole-equi, omni-radtan, ds-none, "
        "eucm-none) "
        "or an mrcal .cameramodel: projection differences over the observed field",
    )
    kalibr_compare.add_cli_arguments(p)


def run(args) -> int:
    """Run ``gtsam-sphere compare``."""
    if getattr(args, "with_", None):
        from ..apps import kalibr_compare

        return kalibr_compare.run_cli(args)
    from ..analysis import compare

    return compare.run_cli(args)
