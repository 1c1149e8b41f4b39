"""``gtsam-sphere``: the command line.

Subcommands: ``demo``, ``simulate``, ``calibrate``, ``evaluate``, ``detect``
(and those added by later stages). Every subcommand exits 0 on success,
1 when the result should not be trusted, 2 on bad input (:data:`EXIT_CODES`).

Standard error carries two streams: progress lines (the ``progress``
callbacks; ``--quiet`` hides them) and the ``gtsam_sphere`` logger's records
(warnings as ``warning: ...``, hints; never hidden), through a handler that
:func:`main` installs for the duration of a command. Standard output carries
results only.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
from pathlib import Path

from .core.camera import DEFAULT_MODEL, Model, parse_brown_terms
from .core.errors import InputError, OptionsError
from .estimation.graph import Loss
from .estimation.optimize import OptimizerKind, stderr_progress

logger = logging.getLogger(__name__)


def _add_calibration_options(p: argparse.ArgumentParser) -> None:
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
    p.add_argument("--loss", choices=[x.value for x in Loss], default="huber")
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


def _options_from_args(args):
    """:class:`~gtsam_sphere.estimation.calibrate.CalibrationOptions` from the parsed arguments.

    A value the options refuse raises :class:`~gtsam_sphere.core.errors.OptionsError`.
    """
    from .estimation.calibrate import CalibrationOptions

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


def _print_statistics(stats: dict) -> None:
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
        ("redundancy", f"{stats['redundancy']}"),
        ("a-posteriori variance factor", f"{stats['variance_factor']:.4f}"),
        ("largest incidence angle (deg)", f"{stats['max_incidence_deg']:.1f}"),
        ("status", f"{stats['status']} after {stats['iterations']} iterations"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")


def cmd_calibrate(args) -> int:
    from .estimation import rig
    from .estimation.calibrate import calibrate
    from .io.dataset import load_dataset

    if rig.is_rig_dataset(args.dataset):  # dataset@2: the rig path (gtsam_sphere/rig.py)
        return rig.run_cli(args, _options_from_args(args), None if args.quiet else stderr_progress)
    if args.camera_model:
        raise OptionsError("--camera-model applies to a rig (dataset@2); use --model")
    dataset = load_dataset(args.dataset)
    for iid, why in dataset.skipped_images:
        logger.warning("image %r skipped: %s", iid, why)
    if dataset.dropped:
        logger.warning(
            "%d observations outside the image dropped (listed in the output)",
            len(dataset.dropped),
        )
    t0 = time.perf_counter()
    calib = calibrate(dataset, _options_from_args(args), None if args.quiet else stderr_progress)
    calib.save(args.output)
    cam = calib.camera
    print(
        f"{args.output}: model {calib.model}, xp {cam.xp:.3f} px, yp {cam.yp:.3f} px, "
        f"c {cam.c:.3f} px ({time.perf_counter() - t0:.1f} s)"
    )
    _print_statistics(calib.statistics)
    _print_outliers(calib.extra.get("outliers", []))
    # the reasons not to trust the result were logged once by calibrate()
    if args.control_sigma is None and bool((dataset.target_sigma == 0).all()):
        logger.info(
            "hint: every target was held exact (--exact-targets); real boards are rarely "
            "flat or true to scale to 0.1 mm: without --exact-targets their shape is "
            "estimated (README, 'Printed boards')"
        )
    return 0 if calib.statistics.get("trusted", calib.statistics["converged"]) else 1


def _print_outliers(outliers: list[dict], limit: int = 10) -> None:
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


def cmd_evaluate(args) -> int:
    from .analysis.evaluate import evaluate_calibration
    from .io.calibration import load_calibration
    from .io.dataset import load_checkpoints

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
    _print_statistics(calib.statistics)
    return 0


def cmd_demo(args) -> int:
    import numpy as np

    from .analysis.evaluate import evaluate_calibration
    from .estimation.calibrate import CalibrationOptions, calibrate
    from .io.dataset import parse_dataset
    from .simulate import gopro_like, simulate_room, write_simulation
    from .simulate.oracle import oracle_calibration

    out = Path(args.output)
    say = None if args.quiet else stderr_progress
    sim_options = gopro_like(
        lens=args.lens,
        fov_deg=args.fov_deg,
        fill="circle" if args.fov_deg >= 180 else "diagonal",
        lens_options=gopro_like().lens_options if args.lens == "kannala-brandt" else {},
        noise_px=args.noise_px,
        n_images=args.images,
        seed=args.seed,
    )
    print(
        f"simulating the paper's room: {args.lens} lens, {args.fov_deg:.0f} deg field of view, "
        f"decentering, {sim_options.pupil_shift_m * 1e3:.0f} mm pupil shift, "
        f"{sim_options.error_field_px:.0f} px smooth error field, noise {args.noise_px} px, "
        f"{args.images} images, seed {args.seed}"
    )
    sim = simulate_room(sim_options)
    paths = write_simulation(sim, out)
    dataset = parse_dataset(sim.dataset, str(paths["dataset"]))
    calib = calibrate(dataset, CalibrationOptions(model=Model(args.model), seed=args.seed), say)
    calib.save(out / "calibration.json")
    ids = [t["id"] for t in sim.checkpoints["targets"]]
    xyz = np.array([t["xyz"] for t in sim.checkpoints["targets"]], float)
    rep = evaluate_calibration(calib, ids, xyz)
    print(f"\nwrote {out / 'calibration.json'} (dataset, check points and truth beside it)\n")
    lens = sim.lens
    print(f"  {'':22}{'estimated':>12}{'truth':>12}")
    for name, est, true in (
        ("xp (px)", calib.camera.xp, lens.cx),
        ("yp (px)", calib.camera.yp, lens.cy),
        ("c (px)", calib.camera.c, lens.f),
    ):
        print(f"  {name:<22}{est:>12.3f}{true:>12.3f}")
    rows = [(f"{args.model} (estimated lens)", calib.statistics["rms_px"], rep)]
    if not args.no_oracle:
        if say:
            say("oracle: the same data with the true lens held fixed")
        oracle = oracle_calibration(sim, args.seed)
        rows.append(
            (
                "oracle (true lens)",
                oracle.statistics["rms_px"],
                evaluate_calibration(oracle, ids, xyz),
            )
        )
    print(f"\n  check points ({len(rep.ids)}), RMSE after a 7-parameter similarity:")
    print(f"  {'':30}{'RMS px':>8}{'X mm':>8}{'Y mm':>8}{'Z mm':>8}{'3D mm':>8}")
    for label, rms, r in rows:
        x, y, z = (v * 1e3 for v in r.rmse_xyz)
        print(f"  {label:<30}{rms:>8.3f}{x:>8.3f}{y:>8.3f}{z:>8.3f}{r.rmse_3d * 1e3:>8.3f}")
    if len(rows) == 2:
        print(f"  3D RMSE / oracle: {rep.rmse_3d / rows[1][2].rmse_3d:.2f}")
    print()
    _print_statistics(calib.statistics)
    return 0 if calib.statistics["converged"] else 1


def build_parser() -> argparse.ArgumentParser:
    """The ``gtsam-sphere`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="gtsam-sphere",
        description="Calibrate any central camera on a virtual sphere, in a GTSAM factor graph.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulate a room and calibrate it, printing a result table")
    p.add_argument("-o", "--output", default="gtsam_sphere_demo")
    p.add_argument("--lens", default="kannala-brandt", help="simulated lens family")
    p.add_argument("--fov-deg", type=float, default=200.0)
    p.add_argument("--noise-px", type=float, default=0.3)
    p.add_argument("--images", type=int, default=52)
    p.add_argument("--model", choices=[m.value for m in Model], default=DEFAULT_MODEL.value)
    p.add_argument("--no-oracle", action="store_true", help="skip the true-lens adjustment")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("calibrate", help="calibrate a dataset@1 file (or a dataset@2 rig)")
    p.add_argument("dataset")
    p.add_argument("-o", "--output", required=True, help="calibration@1 (@2 for a rig) to write")
    _add_calibration_options(p)
    p.add_argument(
        "--camera-model",
        action="append",
        metavar="CAMERA=MODEL",
        help="rigs: the model of one camera (repeat per camera; --model for the others)",
    )
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("evaluate", help="3D accuracy against check points, image statistics")
    p.add_argument("calibration")
    p.add_argument("checkpoints")
    p.set_defaults(func=cmd_evaluate)

    from . import simulate
    from .analysis import compare
    from .apps import detect, export, report, undistort

    # subcommands whose module owns its arguments (add_cli_arguments / run_cli)
    for name, module, help_text in (
        ("compare", compare, "the paper's Table 1/2 rows on one dataset"),
        ("report", report, "plots and a page for a calibration"),
        ("simulate", simulate, "simulate a calibration: the paper's room, a board, a 3D object"),
        ("detect", detect, "detect board corners / markers in images"),
        ("export", export, "fit OpenCV / Kalibr camera models to a calibration"),
        ("undistort", undistort, "resample an image to a perspective / panoramic projection"),
    ):
        p = sub.add_parser(name, help=help_text)
        module.add_cli_arguments(p)
        p.set_defaults(func=module.run_cli)
    return parser


#: exit code of a run that went through and whose result can be trusted
EXIT_OK = 0
#: exit code of a run that wrote its result but says not to trust it (``calibrate``:
#: ``statistics.distrust`` says why; ``demo``: not converged)
EXIT_UNTRUSTED = 1

#: Exit code of each exception class, the one table of them: the first row whose class
#: matches wins (so a subclass comes before its base). An exception in no row is a bug
#: and keeps its traceback: a ``ValueError`` that is not an :class:`InputError` (raised
#: inside numpy, GTSAM or by a missing check of ours) is not bad input.
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    # bad input: a file that violates its contract (DatasetError), degenerate geometry
    # (DegenerateGeometryError), no image initialised, a bad option (OptionsError)
    (InputError, 2),
    # standard output closed by its reader (``| head``): before OSError, its base
    (BrokenPipeError, 141),
    # an output that cannot be written (a directory, permissions, disc full)
    (OSError, 2),
    # Ctrl-C: nothing written
    (KeyboardInterrupt, 130),
)


def exit_code(exc: BaseException) -> int | None:
    """The exit code of ``exc`` by :data:`EXIT_CODES`, None for one to re-raise.

    Parameters
    ----------
    exc : BaseException

    Returns
    -------
    int or None
    """
    for cls, code in EXIT_CODES:
        if isinstance(exc, cls):
            return code
    return None


def _say_why(exc: BaseException, args: argparse.Namespace) -> None:
    """Tell on standard error why the run stops (one line; nothing for a closed pipe)."""
    if isinstance(exc, BrokenPipeError):
        # no message, and no traceback at exit when Python flushes stdout again
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):  # no real file behind sys.stdout
            pass
    elif isinstance(exc, KeyboardInterrupt):
        out = getattr(args, "output", None)
        where = ""
        if out is not None and Path(out).is_file():
            where = f"; the last good result is the previous {out}, unchanged"
        elif out is not None:
            where = f"; {out} was not created"
        print(f"interrupted: no output file was written or changed{where}", file=sys.stderr)
    elif isinstance(exc, OSError) and not isinstance(exc, InputError):
        filename = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {filename}{exc.strerror or exc}", file=sys.stderr)
    else:
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"error: {message}", file=sys.stderr)


class StderrLogHandler(logging.Handler):
    """One line per log record on the *current* ``sys.stderr``.

    Warnings and errors are prefixed with their level (``warning: ...``);
    information (hints) is printed as it is. Looking up ``sys.stderr`` at each
    record keeps redirections made after installation (tests, callers) working.
    """

    def emit(self, record: logging.LogRecord) -> None:
        """Print ``record`` on standard error."""
        try:
            text = self.format(record)
            if record.levelno >= logging.WARNING:
                text = f"{record.levelname.lower()}: {text}"
            print(text, file=sys.stderr, flush=True)
        except Exception:  # logging must never break the command
            self.handleError(record)


@contextlib.contextmanager
def log_to_stderr(level: int = logging.INFO):
    """Show the ``gtsam_sphere`` logger's records on standard error while inside.

    Parameters
    ----------
    level : int
        Lowest level shown (default INFO: hints and warnings).
    """
    package = logging.getLogger("gtsam_sphere")
    handler = StderrLogHandler(level)
    previous = package.level
    package.addHandler(handler)
    if not package.isEnabledFor(level):
        package.setLevel(level)
    try:
        yield handler
    finally:
        package.removeHandler(handler)
        package.setLevel(previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gtsam-sphere`` console script.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 success, 1 result not to be trusted, 2 bad input or degenerate
        geometry (one ``error: ...`` line on standard error, no output file
        written), 130 interrupted, 141 standard output closed by its reader
        (e.g. piped to ``head``; files already written are complete, the work
        after the closed pipe was not done). :data:`EXIT_CODES` maps exceptions
        to these codes; any other exception propagates with its traceback.
    """
    args = build_parser().parse_args(argv)
    try:
        with log_to_stderr():
            return int(args.func(args) or EXIT_OK)
    except BaseException as exc:  # only the classes of EXIT_CODES are handled
        code = exit_code(exc)
        if code is None:
            raise
        _say_why(exc, args)
        return code


if __name__ == "__main__":
    sys.exit(main())
