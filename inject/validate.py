"""Domain checks shared by the engine's entry points; each raises :class:`InputError`."""
import numpy as np

from .errors import InputError


def _has_none(value):
    """True if ``value`` is None or holds a None (which numpy would turn into NaN)."""
    return value is None or any(v is None for v in np.asarray(value, dtype=object).ravel())


def finite(name, value, *, scalar=False):
    """Return ``value`` as a float array, raising if any element is NaN or infinite.

    Parameters
    ----------
    name : str
        The parameter's name, for the error message.
    value : float or array_like
        The value to check.
    scalar : bool
        Require a single number (a Python or numpy scalar, or a 0-d array) and return it as a
        Python float.

    Returns
    -------
    ndarray or float

    Raises
    ------
    InputError
        If ``value`` is not numeric (a None, a string where ``scalar``, an array where
        ``scalar``) or not finite.
    """
    if scalar and isinstance(value, (str, bytes)):
        raise InputError(name, value, "must be a number")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(name, value, "must be a number") from None
    if scalar and arr.ndim != 0:
        raise InputError(name, value, "must be a single number, not an array")
    if not np.all(np.isfinite(arr)):
        # numpy turns None into NaN: name the real problem.
        none = np.any(np.isnan(arr)) and _has_none(value)
        raise InputError(name, value, "must be a number" if none else "must be finite")
    return float(arr) if scalar else arr


def positive(name, value, *, scalar=False):
    """Return ``value`` as a float array, raising unless every element is finite and > 0.

    ``scalar`` is as in :func:`finite`.
    """
    arr = finite(name, value, scalar=scalar)
    if np.any(arr <= 0):
        raise InputError(name, value, "must be > 0")
    return arr


def in_range(name, value, lo, hi, *, hi_open=True, scalar=False):
    """Return ``value`` as a float array, raising unless ``lo <= value < hi`` (or ``<= hi``).

    ``scalar`` is as in :func:`finite`.
    """
    arr = finite(name, value, scalar=scalar)
    upper_ok = arr < hi if hi_open else arr <= hi
    if np.any(arr < lo) or not np.all(upper_ok):
        bound = f"< {hi}" if hi_open else f"<= {hi}"
        raise InputError(name, value, f"must be >= {lo} and {bound}")
    return arr
