"""``gtsam-sphere``: the command line.

Subcommands: ``demo``, ``simulate``, ``calibrate``, ``evaluate``, ``detect``
(and those added by later stages), one module each in this package
(``NAME``, ``HELP``, ``add_arguments``, ``run``; :data:`COMMANDS`). Every subcommand
exits 0 on success, 1 when the result should not be trusted, 2 on bad input
(:data:`EXIT_CODES`).

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
from pathlib import Path

from ..core.errors import InputError
from . import (
    calibrate,
    compare,
    demo,
    detect,
    evaluate,
    export,
    refine,
    report,
    simulate,
    undistort,
)

logger = logging.getLogger(__name__)

#: the subcommands, in the order ``--help`` lists them
COMMANDS = (
    demo,
    calibrate,
    evaluate,
    compare,
    report,
    simulate,
    detect,
    export,
    undistort,
    refine,
)


def build_parser() -> argparse.ArgumentParser:
    """The ``gtsam-sphere`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="gtsam-sphere",
        description="Calibrate any central camera on a virtual sphere, in a GTSAM factor graph.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        p = sub.add_parser(command.NAME, help=command.HELP)
        command.add_arguments(p)
        p.set_defaults(func=command.run)
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
        checkpoint = getattr(args, "checkpoint", None)
        if checkpoint is not None and Path(checkpoint).is_file():
            where += f"; run it again to resume from its checkpoint {checkpoint}"
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
            status = int(args.func(args) or EXIT_OK)
            # a block-buffered stdout (a pipe, without PYTHONUNBUFFERED) is written out
            # here, where a closed pipe is caught, not at exit (where Python exits 120)
            sys.stdout.flush()
            return status
    except BaseException as exc:  # only the classes of EXIT_CODES are handled
        code = exit_code(exc)
        if code is None:
            raise
        _say_why(exc, args)
        return code
