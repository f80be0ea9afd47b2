"""Checks of arguments at sim2d's public boundary.

Each check returns the value in its canonical type or raises a ``ValueError`` that names
the argument, its value and what was expected.
"""

from __future__ import annotations

import operator

import numpy as np

__all__ = ["as_int", "check_index", "check_vector"]


def as_int(value, name: str) -> int:
    """``value`` as an int; bools and non-integers are refused."""
    if isinstance(value, bool):
        raise ValueError(f"{name}={value!r} is a bool; expected an int")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name}={value!r} is a {type(value).__name__}; expected an int") from None


def check_index(value, name: str, size: int, what: str) -> int:
    """``value`` as an int in ``0..size - 1``; ``what`` says what the index counts."""
    i = as_int(value, name)
    if not 0 <= i < size:
        raise ValueError(f"{name}={value!r} is out of range; expected {what} in 0..{size - 1}")
    return i


def check_vector(value, name: str) -> np.ndarray:
    """``value`` as a finite ``(2,)`` float array ``(x, z)``."""
    try:
        vec = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not numeric; expected (x, z) in SI units") from None
    if vec.shape != (2,):
        raise ValueError(f"{name}={value!r} has shape {vec.shape}; expected shape (2,): (x, z)")
    if not np.all(np.isfinite(vec)):
        raise ValueError(f"{name}={value!r} is not finite; expected two finite numbers")
    return vec
