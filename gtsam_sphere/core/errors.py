"""The package's exceptions, in one place.

::

    GtsamSphereError                      anything gtsam_sphere raises on purpose
    +-- InputError (also a ValueError)    the input cannot give a result; exit 2
        +-- DatasetError                  a file violates its data contract
        |   +-- DegenerateGeometryError   the images cannot calibrate the camera
        +-- InitialisationError           no image could be initialised
        +-- OptionsError                  a bad option or argument
        +-- TargetMismatchError           the images show a target other than the one described

The command line maps these classes to exit codes in one table
(:data:`gtsam_sphere.cli.EXIT_CODES`). A ``ValueError`` that is not an
:class:`InputError` (raised inside numpy, GTSAM or by a missing check of
ours) is a bug: it keeps its traceback.

``InputError`` derives from ``ValueError`` so that callers catching
``ValueError`` keep working. ``DegenerateGeometryError`` stays a
``DatasetError`` (as it was before this module existed), so code that
catches ``DatasetError`` still sees it.

Depends on the standard library only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = [
    "DatasetError",
    "DegenerateGeometryError",
    "GtsamSphereError",
    "InitialisationError",
    "InputError",
    "OptionsError",
    "TargetMismatchError",
]


class GtsamSphereError(Exception):
    """Base class of every exception gtsam_sphere raises on purpose."""


class InputError(GtsamSphereError, ValueError):
    """The input (a file, the images' geometry, an option) cannot give a result.

    The command line exits 2 with the message on one ``error: ...`` line.
    """


class DatasetError(InputError):
    """An input file violates the data contract; the message names the item."""


class DegenerateGeometryError(DatasetError):
    """The dataset's geometry cannot calibrate the camera; ``problems`` lists why.

    Parameters
    ----------
    problems : sequence of Problem
        The fatal findings of :func:`gtsam_sphere.estimation.diagnose.check_geometry`
        (each with ``message``, ``code`` and ``advice``).

    Attributes
    ----------
    problems : list of Problem
        The fatal problems (message and advice of each are in the text).
    """

    def __init__(self, problems: Sequence[Any]):
        self.problems = list(problems)
        text = "; ".join(f"{p.message} ({p.code}; advice: {p.advice})" for p in self.problems)
        super().__init__(f"degenerate calibration geometry: {text}")

    def __reduce__(self):
        """Pickle with the problems (the default would pass the message as ``problems``)."""
        return (type(self), (self.problems,))


class InitialisationError(InputError):
    """No image could be initialised (too few observations, no lens hypothesis fits)."""


class OptionsError(InputError):
    """An option or argument is invalid (command line or options object)."""


class TargetMismatchError(InputError):
    """The images contradict the target description (e.g. the board is larger than described).

    Raised by detection when, say, a chessboard's pattern continues beyond the
    described grid or tags carry ids the described layout does not have: the corners
    would otherwise be labelled wrongly. The message names the image and what was seen.
    """
