"""Domain checks shared by the engine's entry points; each raises :class:`InputError`."""
import numpy as np

from .errors import InputError


def finite(name, value):
    """Return ``value`` as a float array, raising if any element is NaN or infinite."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(name, value, "must be a number") from None
    if not np.all(np.isfinite(arr)):
        raise InputError(name, value, "must be finite")
    return arr


def positive(name, value):
    """Return ``value`` as a float array, raising unless every element is finite and > 0."""
    arr = finite(name, value)
    if np.any(arr <= 0):
        raise InputError(name, value, "must be > 0")
    return arr


def in_range(name, value, lo, hi, *, hi_open=True):
    """Return ``value`` as a float array, raising unless ``lo <= value < hi`` (or ``<= hi``)."""
    arr = finite(name, value)
    upper_ok = arr < hi if hi_open else arr <= hi
    if np.any(arr < lo) or not np.all(upper_ok):
        bound = f"< {hi}" if hi_open else f"<= {hi}"
        raise InputError(name, value, f"must be >= {lo} and {bound}")
    return arr
