"""Checks of the pure-Python functions' arguments, raising the package's
:class:`InputError` named by the argument (the compiled module checks its
own)."""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from ._core import InputError


def real(field: str, value: Any) -> float:
    """``value`` (a number or a 0-d array of one) as a float, refusing what
    is not a real number (a bool, a string, an array of several)."""
    if isinstance(value, np.ndarray):
        if value.ndim != 0 or value.dtype.kind not in "iuf":
            raise InputError(f"{field}: {value!r} is not a real number")
        return float(value)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise InputError(f"{field}: {value!r} is not a real number")
    return float(value)


def count(field: str, value: Any, least: int) -> int:
    """``value`` as a whole number ``>= least``, refusing fractions, bools
    and strings."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{field}: {value!r} is not an integer")
    if value < least:
        raise InputError(f"{field}: {value} must be >= {least}")
    return int(value)
