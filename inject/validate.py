"""Domain checks shared by the engine's entry points; each raises :class:`InputError`.

:data:`RANGES` is the one table of the accepted and plausible ranges of every quantity a
scene file or a command line sets; the scene parser and the CLI check through it.
"""
import math
import numbers
import os
import warnings
from dataclasses import dataclass

from inject.errors import InputError, InputWarning, ResourceError

# NumPy is imported by the checks that use it: the command line's parser imports this module
# (through the options' defaults) and answers --help or a bad option without NumPy.


def _has_none(value):
    """True if ``value`` is None or holds a None (which numpy would turn into NaN)."""
    import numpy as np

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
    import numpy as np

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
    import numpy as np

    arr = finite(name, value, scalar=scalar)
    if np.any(arr <= 0):
        raise InputError(name, value, "must be > 0")
    return arr


def in_range(name, value, lo, hi, *, hi_open=True, scalar=False):
    """Return ``value`` as a float array, raising unless ``lo <= value < hi`` (or ``<= hi``).

    ``scalar`` is as in :func:`finite`.
    """
    import numpy as np

    arr = finite(name, value, scalar=scalar)
    upper_ok = arr < hi if hi_open else arr <= hi
    if np.any(arr < lo) or not np.all(upper_ok):
        bound = f"< {hi}" if hi_open else f"<= {hi}"
        raise InputError(name, value, f"must be >= {lo} and {bound}")
    return arr


# --- The ranges of every user-facing quantity ---------------------------------------------

@dataclass(frozen=True)
class Range:
    """The accepted range of one quantity, and the narrower range where it is plausible.

    A value outside ``[lo, hi]`` (``lo_open``/``hi_open``: the bound itself excluded) is refused
    with an :class:`InputError`; a value inside it but outside ``[warn_lo, warn_hi]`` is used,
    with an :class:`InputWarning`.

    Attributes
    ----------
    name : str
        The quantity, as the scene file and the README name it.
    unit : str
    lo, hi : float
        Hard bounds (``-inf``/``inf`` for none).
    why : str
        Why the hard bounds are where they are (said in the error message).
    warn_lo, warn_hi : float
        Plausible bounds (``-inf``/``inf`` for none).
    warn_why : str
        What is implausible beyond them (said in the warning).
    integer : bool
        The value must be a whole number.
    options : str
        The command-line options checked against this range (for the README).
    """

    name: str
    unit: str
    lo: float
    hi: float
    why: str
    lo_open: bool = False
    hi_open: bool = False
    warn_lo: float = -math.inf
    warn_hi: float = math.inf
    warn_why: str = ""
    integer: bool = False
    options: str = ""

    def bounds(self):
        """The hard bounds as text, e.g. ``"> 0 and <= 3600"``."""
        lo = None if self.lo == -math.inf else f"{'>' if self.lo_open else '>='} {_num(self.lo)}"
        hi = None if self.hi == math.inf else f"{'<' if self.hi_open else '<='} {_num(self.hi)}"
        return " and ".join(b for b in (lo, hi) if b) or "finite"

    def plausible(self):
        """Where a value is warned about, as text (empty if never)."""
        if not self.warn_why:
            return ""
        if self.warn_lo == -math.inf:
            return f"above {_num(self.warn_hi)}"
        if self.warn_hi == math.inf:
            return f"below {_num(self.warn_lo)}"
        return f"outside {_num(self.warn_lo)} to {_num(self.warn_hi)}"

    def check(self, value, name=None):
        """Return ``value`` as a float (an int for integer quantities) if it is inside the hard
        bounds; warn if it is outside the plausible ones.

        Parameters
        ----------
        value : float
        name : str, optional
            How the user wrote the quantity (``--height``, ``satellites[0].height``); default
            :attr:`name`.

        Raises
        ------
        InputError
            ``value`` is not a finite number, not whole where it must be, or out of bounds.
        """
        name = name or self.name
        if isinstance(value, bool):  # a YAML "yes" is not a number
            raise InputError(name, value, "must be a number")
        if self.integer and isinstance(value, numbers.Integral):
            x = int(value)  # exactly: a float would round 2**63 - 1 up
        else:
            x = finite(name, value, scalar=True)
        if self.integer and x != int(x):
            raise InputError(name, value, "must be a whole number")
        below = x <= self.lo if self.lo_open else x < self.lo
        above = x >= self.hi if self.hi_open else x > self.hi
        if below or above:
            unit = f" {self.unit}" if self.unit else ""
            raise InputError(name, value, f"must be {self.bounds()}{unit} ({self.why})")
        if not self.warn_lo <= x <= self.warn_hi:
            warnings.warn(f"{name}={value!r}: {self.warn_why}; used as given", InputWarning,
                          stacklevel=3)
        return int(x) if self.integer else x


def _num(x):
    return "2^63 - 1" if x == 2 ** 63 - 1 else f"{x:g}"


_INF = math.inf
#: Every numeric quantity a scene file or a command line can set, with its accepted range
#: (refused outside) and plausible range (warned outside). The README's "Input ranges" table
#: is :func:`ranges_markdown` of this.
RANGES = {r.name: r for r in (
    Range("seed", "", 1, 2 ** 63 - 1, "0 means 'random' to GalSim; the FITS header keeps a "
          "64-bit integer", integer=True, options="add-streak --seed"),
    Range("exptime", "s", 0, 3600, "LSSTCam visits are 15-30 s; an hour is beyond any CCD "
          "exposure", lo_open=True),
    Range("seeing", "arcsec", 0, 30, "0 turns the atmosphere off", hi_open=True,
          warn_hi=3, warn_why="Rubin's seeing is 0.4-2 arcsec", options="--seeing"),
    Range("zenith", "deg", 0, 90, "90 deg is the horizon", hi_open=True, options="--zenith"),
    Range("dark_current", "e-/s/px", 0, 1e4, "1e4 e-/s fills a 170 ke- full well in 17 s",
          warn_hi=1, warn_why="LSSTCam's cooled CCDs have well under 1 e-/s/px"),
    Range("cosmic_rays", "per s per CCD", 0, 100, "drawn over the whole CCD, also for a "
          "cut-out: 100 per s for an hour is 360 000 rays",
          warn_hi=10, warn_why="imSim uses ~0.2 per s per CCD"),
    Range("detector.nx", "px", 1, 4096, "a cut-out of one sensor, as a focal-plane scene's "
          "cutout.nx (clipped to each CCD): at most ITL 4072 x 4000 or e2v 4096 x 4004",
          integer=True),
    Range("detector.ny", "px", 1, 4004, "a cut-out of one sensor, as a focal-plane scene's "
          "cutout.ny (clipped to each CCD): at most ITL 4072 x 4000 or e2v 4096 x 4004",
          integer=True, options="evaluate --detector"),
    Range("detector.gains", "e-/ADU", 0, 1000, "a gain is positive", lo_open=True,
          warn_lo=0.5, warn_hi=5, warn_why="LSSTCam's amplifiers have 1.4-1.8 e-/ADU"),
    Range("detector.read_noise", "e-", 0, 1000, "read noise is positive", lo_open=True,
          warn_hi=20, warn_why="LSSTCam's amplifiers have 5-7 e-"),
    Range("detector.full_well", "e-", 0, 1e7, "LSSTCam's CCDs hold ~170 000 e-",
          lo_open=True),
    Range("detector.bias", "ADU", 0, 65535, "a 16-bit ADC"),
    Range("sky.level", "e-/px", 0, 1e9, "1e9 e- is ~6000 full wells"),
    Range("sky.mag", "mag/arcsec^2", 0, 40, "0 is brighter than the daytime sky",
          warn_lo=15, warn_hi=25, warn_why="the night sky is 17-23 mag/arcsec^2 (moonlit to "
          "dark, y to u)"),
    Range("stars.galactic_l", "deg", -360, 360, "a longitude"),
    Range("stars.galactic_b", "deg", -90, 90, "a latitude"),
    Range("stars.mag_limit", "AB mag", -2, 30, "fainter stars are invisible to LSST and "
          "multiply the star count"),
    Range("stars.mag_bright", "AB mag", -2, 30, "Sirius, the brightest star, is -1.5"),
    Range("stars.density_per_deg2", "per deg^2", 0, 1e8, "1e8 per deg^2 is a star every 3 px",
          lo_open=True),
    Range("pointing.ra", "deg", 0, 360, "right ascension", hi_open=True,
          options="add-streak --ra0, pass --ra"),
    Range("pointing.dec", "deg", -90, 90, "declination", options="add-streak --dec0, pass --dec"),
    Range("pointing.rotation", "deg", -_INF, _INF, "any angle", options="pass --rotation"),
    Range("orbit.height", "km", 80, 1e6, "a perigee below 80 km has decayed; at 1e6 km the "
          "Sun's pull matters more than the Earth's", warn_hi=4e5,
          warn_why="beyond the Moon (384 400 km) nothing is an Earth satellite",
          options="pass --orbit height"),
    Range("orbit.inclination", "deg", 0, 180, "0 prograde equatorial, 180 retrograde",
          options="pass --orbit inclination"),
    Range("orbit.raan", "deg", -_INF, _INF, "any angle (taken modulo 360)",
          options="pass --orbit raan"),
    Range("orbit.mean_anomaly", "deg", -_INF, _INF, "any angle (the argument of latitude at "
          "the epoch, taken modulo 360)", options="pass --orbit mean_anomaly"),
    Range("orbit.epoch_days", "days", 0, 60, "|epoch - exposure start| of a TLE or orbit: "
          "SGP4's along-track error for LEO reaches tens to hundreds of km (degrees on the "
          "sky) in two months", warn_hi=14, warn_why="after a week or two the position may be "
          "km off (drag)", options="pass --tle, pass --orbit epoch"),
    Range("shadow_atmosphere_km", "km", 0, 200, "height of the grazing atmosphere taken to block "
          "the Sun in Earth's shadow (0: the solid WGS84 Earth); above ~100 km the air is too "
          "thin to matter", options="pass --shadow-atmosphere"),
    Range("site.lat", "deg", -90, 90, "geodetic latitude", options="pass --site"),
    Range("site.lon", "deg", -360, 360, "geodetic longitude (east positive)",
          options="pass --site"),
    Range("site.height", "m", -500, 10000, "above the WGS84 ellipsoid: the Dead Sea shore to "
          "above Everest", options="pass --site"),
    Range("height", "km", 100, _INF, "nothing orbits below ~100 km, and the speed is a "
          "circular orbit's", warn_hi=4e5,
          warn_why="beyond the Moon (384 400 km) nothing is an Earth satellite, and the "
          "effective exposure per pixel exceeds any exposure",
          options="--height, evaluate --heights"),
    Range("mag", "AB mag", -30, 100, "-30 is brighter than the Sun, at -26.7", warn_lo=-10,
          warn_why="brighter than any satellite seen (Iridium flares reached -9.5)",
          options="--mag, evaluate --mags"),
    Range("phi", "deg", -_INF, _INF, "any angle (the velocity's direction)", options="--phi"),
    Range("range", "km", 0, 1e6, "a polyline vertex's exact range (an orbit's vertices carry "
          "it), in place of the spherical-Earth one", lo_open=True),
    Range("angular_speed", "rad/s", 0, 1, "a polyline vertex's exact angular speed across the "
          "star field (an orbit's vertices carry it); LEO at zenith is ~0.014", lo_open=True),
    Range("ref_range", "km", 1, 1e6, "magnitudes are quoted at 550 or 1000 km",
          options="--ref-range"),
    Range("size", "m", 0, 200, "the shape's largest extent, box diagonal, disk diameter or "
          "composite span; the ISS, the largest satellite, is 109 m", lo_open=True,
          options="--length, --width, --radius"),
    Range("reflectance", "", 0, 1e6, "a composite part's flux per unit area relative to the "
          "other parts", lo_open=True),
    Range("track.x0", "px", -1e6, 1e6, "1e6 px is 55 deg away at 0.2 arcsec/px",
          options="add-streak --x0"),
    Range("track.y0", "px", -1e6, 1e6, "1e6 px is 55 deg away at 0.2 arcsec/px",
          options="add-streak --y0"),
    Range("track.angle", "deg", -_INF, _INF, "any angle", options="add-streak --angle"),
    Range("track.length", "px", 0, 1e6, "1e6 px is 55 deg at 0.2 arcsec/px; omit it to "
          "cross the image", options="add-streak --track-length"),
    Range("pixel_scale", "arcsec/px", 0.01, 10, "LSSTCam has 0.2; the profile is sampled per "
          "pixel", options="--pixel-scale, or the image's WCS"),
    Range("gain", "e-/ADU", 0, 1000, "a gain is positive", lo_open=True,
          options="add-streak --gain, or the GAIN header"),
    Range("charge_per_px", "e-", 0, 1e15, "the expected charge of the brightest pixel; "
          "numpy's Poisson draw fails above 9e18, and 1e15 e- is already 6e9 full wells"),
)}


def check(quantity, value, name=None):
    """Check ``value`` against :data:`RANGES` ``[quantity]`` (see :meth:`Range.check`)."""
    return RANGES[quantity].check(value, name)


def check_pointing(pointing, names=None):
    """The one check of a pointing ``{ra, dec[, rotation]}`` (deg): :data:`RANGES`' rows
    ``pointing.ra``, ``pointing.dec``, ``pointing.rotation``.

    Parameters
    ----------
    pointing : mapping or inject.camera.wcs.Pointing
    names : mapping, optional
        How the user wrote each key (``{"ra": "--ra", ...}``); default ``pointing.<key>``.

    Returns
    -------
    ra, dec, rotation : float

    Raises
    ------
    InputError
        Not a mapping with numeric ``ra`` and ``dec``, or a value out of its range.
    """
    names = names or {}
    if hasattr(pointing, "ra_deg"):  # an inject.camera.wcs.Pointing
        pointing = {"ra": pointing.ra_deg, "dec": pointing.dec_deg,
                    "rotation": pointing.rotation_deg}
    if not hasattr(pointing, "get") or pointing.get("ra") is None or \
            pointing.get("dec") is None:
        raise InputError("pointing", pointing, "needs numeric ra and dec (deg), optional "
                                               "rotation")
    out = []
    for k in ("ra", "dec", "rotation"):
        value = pointing.get(k, 0.0)
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            value = float(value)  # named as a float, as every scene number
        out.append(RANGES[f"pointing.{k}"].check(value, names.get(k, f"pointing.{k}")))
    return tuple(out)


def ranges_markdown():
    """The table of :data:`RANGES` as Markdown (the docs' input-ranges page is built from it)."""
    def cell(text):
        return str(text).replace("|", "\\|").replace("\n", " ")

    def options(r):
        commands = ("add-streak", "evaluate", "pass", "simulate", "profile", "mask")
        return ", ".join(f"`{o}`" if o.startswith("-") or o.split(" ")[0] in commands else o
                         for o in (o.strip() for o in r.options.split(","))) if r.options else ""

    lines = ["| scene key | options | unit | accepted | warned | why |",
             "|---|---|---|---|---|---|"]
    for r in RANGES.values():
        accepted = r.bounds() + (" (whole number)" if r.integer else "")
        why = r.why + (f". Warned: {r.warn_why}" if r.warn_why else "")
        lines.append("| " + " | ".join(cell(c) for c in (
            f"`{r.name}`", options(r), r.unit, accepted, r.plausible(), why)) + " |")
    return "\n".join(lines)


# --- Memory -------------------------------------------------------------------------------

def available_memory():
    """Bytes of memory available to a new allocation (``MemAvailable`` of /proc/meminfo,
    else free physical pages), or None where neither can be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None


def check_memory(needed, what):
    """Raise :class:`ResourceError` if ``needed`` bytes exceed the memory available.

    Parameters
    ----------
    needed : float
        Estimated peak bytes of the work.
    what : str
        The work, for the message (``"detector 4072 x 4000"``).
    """
    free = available_memory()
    if free is not None and needed > free:
        raise ResourceError(f"{what}: needs about {needed / 2**30:.3g} GiB of memory, "
                            f"{free / 2**30:.3g} GiB available")


def parse_time(value, name="time"):
    """An astropy :class:`~astropy.time.Time` (UTC) from an ISO 8601 string, a ``datetime``
    or a Time.

    A UTC offset (``2026-06-15T20:30:00-03:00``, or a YAML timestamp with one) is converted
    to UTC, whether the time comes as a string (the command line, a quoted YAML value) or as
    a YAML timestamp; a time without one is UTC.

    Raises
    ------
    InputError
        If ``value`` is not a readable time.
    """
    from datetime import datetime, timezone

    from astropy.time import Time

    if isinstance(value, Time):
        return value.utc
    try:
        return Time(value, scale="utc")
    except (ValueError, TypeError):
        pass
    if isinstance(value, str):
        # astropy reads no offsets; Python's ISO 8601 parser does (leap seconds aside, which
        # astropy already read above when there is no offset).
        try:
            stamp = datetime.fromisoformat(value.strip())
        except ValueError:
            stamp = None
        if stamp is not None and stamp.tzinfo is not None:
            return Time(stamp.astimezone(timezone.utc).replace(tzinfo=None), scale="utc")
    raise InputError(name, value, "must be an ISO 8601 time, UTC or with a UTC offset, e.g. "
                                  "2026-06-15T23:30:00 or 2026-06-15T20:30:00-03:00")
