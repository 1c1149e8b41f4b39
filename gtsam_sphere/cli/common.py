"""Arguments and printouts shared by the commands that calibrate (``calibrate``, ``demo``).

The calibration options (``--model``, ``--ap``, ``--loss``, ...) and their
:class:`~gtsam_sphere.estimation.calibrate.CalibrationOptions`; the statistics and
outlier tables printed on standard output.
"""

from __future__ import annotations

import argparse

from ..core.camera import DEFAULT_MODEL, Model, parse_brown_terms
from ..core.errors import OptionsError
from ..core.robust import Loss
from ..estimation.optimize import OptimizerKind


def add_calibration_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        choices=[m.value for m in Model],
        default=DEFAULT_MODEL.value,
        help=f"camera model (default {DEFAULT_MODEL.value}; the paper's method is sphere+knn)",
    )
    p.add_argument(
        "--ap",
        default=None,
        help="Brown additional parameters, e.g. k1,k2,p1,p2 or all; default: k1,k2,k3,p1,p2 "
        "for brown, p1,p2,a1,a2 (decentering, affinity) for radial",
    )
    p.add_argument(
        "--radial-terms",
        type=int,
        default=6,
        help="coefficients g3, g5, ... of the radial mapping (radial models, 0-6): the most "
        "that may be used; those the data cannot support are dropped unless --all-terms",
    )
    p.add_argument(
        "--all-terms",
        action="store_true",
        help="keep every radial and --ap term even where the data cannot support it "
        "(default: dropped by a Wald test with a BIC penalty, docs/conventions.md)",
    )
    p.add_argument("--optimizer", choices=[o.value for o in OptimizerKind], default="lm")
    # the truncated quadratic ranks solutions (calibrate's first stage); its 0/1 weights
    # can strand a target whose every observation is beyond the threshold: not offered
    losses = [x.value for x in Loss if x is not Loss.TRUNCATED]
    p.add_argument("--loss", choices=losses, default="huber")
    p.add_argument("--loss-threshold", type=float, default=2.45, help="robust threshold in sigmas")
    p.add_argument(
        "--sigma-px",
        type=float,
        default=None,
        help="image noise sigma (px); default: estimated from the residuals",
    )
    targets = p.add_mutually_exclusive_group()
    targets.add_argument(
        "--control-sigma",
        type=_control_sigma_arg,
        default="auto",
        metavar="SIGMA|auto",
        help="the targets marked exact (sigma 0, printed boards, machined objects) are "
        "estimated around their nominal coordinates with this standard deviation in the "
        "dataset's units (e.g. 0.0005 for 0.5 mm): recovers a curled or misprinted board; "
        "default 'auto': 1e-3 of the exact targets' extent",
    )
    targets.add_argument(
        "--exact-targets",
        dest="control_sigma",
        action="store_const",
        const=None,
        help="hold the targets marked exact (sigma 0) at their nominal coordinates",
    )
    p.add_argument("--max-iterations", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _control_sigma_arg(text: str):
    """``auto`` or a number; anything else is left to the options' own check (exit 2)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        return text


def options_from_args(args):
    """:class:`~gtsam_sphere.estimation.calibrate.CalibrationOptions` from the parsed arguments.

    A value the options refuse raises :class:`~gtsam_sphere.core.errors.OptionsError`.
    """
    from ..estimation.calibrate import CalibrationOptions

    brown_terms = None if args.ap is None else parse_brown_terms(args.ap)
    try:
        return CalibrationOptions(
            model=Model(args.model),
            brown_terms=brown_terms,
            radial_terms=args.radial_terms,
            select_terms=not getattr(args, "all_terms", False),
            optimizer=OptimizerKind(args.optimizer),
            loss=Loss(args.loss),
            loss_threshold=args.loss_threshold,
            sigma_px=args.sigma_px,
            max_iterations=args.max_iterations,
            seed=args.seed,
            control_sigma=args.control_sigma,
        )
    except ValueError as exc:  # the checks of CalibrationOptions: the values given
        raise OptionsError(str(exc)) from exc


def print_statistics(stats: dict) -> None:
    rows = [
        ("RMS (px)", f"{stats['rms_px']:.4f}"),
        ("RMS without outliers (px)", f"{stats['rms_px_without_outliers']:.4f}"),
        ("observations used / rejected", f"{stats['n_observations']} / {stats['n_rejected']}"),
        ("images used / skipped", f"{stats['n_images']} / {stats['n_images_skipped']}"),
        (
            "down-weighted / outliers (>5 sigma, unlike neighbours)",
            f"{stats['n_downweighted']} / {stats['n_outliers']}",
        ),
        ("systematic (>5 sigma, like neighbours)", f"{stats.get('n_systematic', 0)}"),
        ("sigma (px)", f"{stats['sigma_px']:.4f}"),
        ("weighted sum of squares", f"{stats['weighted_sum_squares']:.4e}"),
        (
            "redundancy (mean redundancy number)",
            f"{stats['redundancy']}"
            + (f" ({stats['mean_redundancy']:.2f})" if "mean_redundancy" in stats else ""),
        ),
        ("a-posteriori variance factor", f"{stats['variance_factor']:.4f}"),
        ("largest incidence angle (deg)", f"{stats['max_incidence_deg']:.1f}"),
    ]
    if "n_targets" in stats:
        rows.append(
            (
                "targets adjusted / undetermined (of them unreliable) / weak",
                f"{stats['n_targets']} / {stats.get('n_targets_undetermined', 0)} "
                f"({stats.get('n_targets_unreliable', 0)}) / {stats.get('n_targets_weak', 0)}",
            )
        )
    if "n_targets_off_prior" in stats:
        rows.append(
            (
                "targets beyond 5 sigma of their priors (largest shift)",
                f"{stats['n_targets_off_prior']} ({stats['target_shift_max_sigma']:.1f} sigma)",
            )
        )
    rows += [
        ("status", f"{stats['status']} after {stats['iterations']} iterations"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")


def print_outliers(outliers: list[dict], limit: int = 10) -> None:
    if not outliers:
        return
    print(f"\n  outliers (> 5 sigma): {len(outliers)}, all listed in the file; largest:")
    for o in outliers[:limit]:
        cause = o["cause"]
        if cause == "mislabelled":
            cause += f" (looks like target {o['matches_target']!r}, {o['distance_px']:.1f} px)"
        print(
            f"    image {o['image']!r} target {o['target']!r}: "
            f"{o['residual_norm_px']:.1f} px, {cause}"
        )
