"""Compatibility shims for the oldest supported Python (3.10).

Depends on the standard library only, so every module (the numpy-only core
included) can import it.
"""

from __future__ import annotations

import enum

__all__ = ["StrEnum"]


class StrEnum(str, enum.Enum):
    """An enumeration of strings, as ``enum.StrEnum`` of Python 3.11.

    Members are ``str`` instances equal to their values; ``str()``, ``format()``
    and f-strings give the value (``f"{Model.RADIAL}" == "radial"``), on every
    supported Python, not only from 3.11 on.
    """

    __str__ = str.__str__
    __format__ = str.__format__
