"""Real passes: a satellite on a TLE or circular orbit seen from a site during one exposure.

The engine behind issue 13 (the part that does not need the focal plane). A satellite is an SGP4
element set (:class:`Orbit`, from a TLE or from circular-orbit elements); the site, the exposure
and the sidereally tracked pointing are :class:`Site`, :class:`Exposure` and
:class:`~inject.camera.wcs.Pointing`.
:func:`compute_pass` samples the exposure and returns a :class:`Pass`: where the satellite is
(geometric alt/az, range), how the paper sees it (nadir angle, phi), how fast it crosses the tracked
star field, whether it is sunlit, and where it appears on the sky as gnomonic field angles in the
focal-plane frame. The focal-plane module maps those field angles to mm (with the distortion).

Frames. The satellite goes TEME -> ITRS -> AltAz (astropy, purely geometric: no aberration, as for
any body computed in the Earth's frame); the pointing goes ICRS -> AltAz (astropy applies
aberration to stars). Both are compared in the same AltAz frame at the same instant, so the streak
sits at its place among the stars; mixing ICRS star positions with the satellite's astrometric
RA/Dec would put it ~20" off. No refraction (pressure 0) for either.

Times. A sample's ``alt_deg``/``az_deg``/``range_km`` are where the satellite *is* at that instant;
its field angles are where it *appears*: the position one light time earlier seen from the site at
the sample time (~2-5" at LEO). Taking the retarded position in the Earth-fixed frame also applies
the diurnal aberration of a nearby body to first order (the neglected rotation over the light time
is 0.03").

Offline. Nothing is downloaded: astropy's bundled IERS table (astropy-iers-data) is used, and a
time beyond it gives an :class:`~inject.errors.OrbitWarning` (astropy then extrapolates UT1 and
uses mean polar motion) instead of an error.
"""
import math
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from astropy import units as u
from astropy.constants import R_sun
from astropy.constants import c as _c
from astropy.coordinates import (
    ITRS,
    TEME,
    AltAz,
    CartesianRepresentation,
    EarthLocation,
    SkyCoord,
    get_sun,
)
from astropy.time import Time
from astropy.utils import iers
from astropy.utils.exceptions import AstropyWarning
from sgp4.api import SGP4_ERRORS, WGS72, Satrec, SatrecArray
from sgp4.earth_gravity import wgs72
from sgp4.exporter import export_tle
from sgp4.io import compute_checksum

from inject.camera.layout import focal_of_field_angle
from inject.camera.wcs import Pointing, tangent_to_focal
from inject.errors import InputError, OrbitError, OrbitWarning
from inject.geometry import R_EARTH_KM
from inject.photometry import apparent_magnitude
from inject.validate import RANGES, finite, in_range, parse_time, positive

# Offline: never download Earth-orientation data; past the bundled table, warn and extrapolate.
iers.conf.auto_download = False
iers.conf.auto_max_age = None

#: Speed of light, km/s.
C_KM_S = _c.to_value("km/s")
#: Earth's rotation rate, rad/s (the rate of GMST 1982, the angle of TEME -> ITRS).
EARTH_ROTATION_RAD_S = 7.292115855e-5
#: Solar radius, km (astropy's IAU 2015 nominal value).
R_SUN_KM = R_sun.to_value("km")
#: A TLE epoch this many days from the exposure gives an OrbitWarning: SGP4's along-track error
#: grows to km after a week or two for LEO (drag), i.e. the streak lands far from its true place
#: (RANGES' ``orbit.epoch_days`` row).
EPOCH_WARN_DAYS = RANGES["orbit.epoch_days"].warn_hi
#: Beyond this many days the TLE is refused (OrbitError): the predicted position is meaningless
#: for a given exposure (tens to hundreds of km along track, i.e. degrees on the sky).
EPOCH_REFUSE_DAYS = RANGES["orbit.epoch_days"].hi
#: Radius of the disc that counts as "the field", degrees of field angle. It encloses every
#: LSSTCam science CCD (the outer corner of R01 is at 370 mm, ~2.06 deg); the focal-plane module
#: decides which CCDs are actually crossed.
FIELD_RADIUS_DEG = 2.1


# --- site, exposure, pointing ------------------------------------------------------------------

@dataclass(frozen=True)
class Site:
    """An observatory: geodetic latitude and longitude (deg, WGS84) and height (m)."""

    lat_deg: float = -30.2446
    lon_deg: float = -70.7494
    height_m: float = 2647.0

    def __post_init__(self):
        for key, value in (("lat", self.lat_deg), ("lon", self.lon_deg),
                           ("height", self.height_m)):
            RANGES[f"site.{key}"].check(value)

    @cached_property
    def location(self):
        """The site as an astropy :class:`~astropy.coordinates.EarthLocation`."""
        return EarthLocation.from_geodetic(self.lon_deg * u.deg, self.lat_deg * u.deg,
                                           self.height_m * u.m)

    @cached_property
    def itrs_km(self):
        """Geocentric ITRS position of the site, km, shape (3,)."""
        return np.array([q.to_value(u.km) for q in self.location.geocentric])


#: Rubin Observatory on Cerro Pachon (the default site).
RUBIN = Site()


@dataclass(frozen=True)
class Exposure:
    """An exposure: start time (UTC) and duration (s)."""

    start: Time
    exptime_s: float = 30.0

    def __post_init__(self):
        object.__setattr__(self, "start", parse_time(self.start, "time"))
        RANGES["exptime"].check(self.exptime_s)

    def sample_times(self, step_s=1.0):
        """Seconds from the start: 0 to ``exptime_s``, at most ``step_s`` apart, with the middle.

        An even number of equal intervals, so the middle of the exposure is a sample.
        """
        step = positive("step_s", step_s, scalar=True)
        n_half = max(1, math.ceil(self.exptime_s / (2.0 * step)))
        return np.linspace(0.0, self.exptime_s, 2 * n_half + 1)

    @property
    def middle(self):
        return self.start + self.exptime_s / 2.0 * u.s


# --- orbits --------------------------------------------------------------------------------------

#: Keys of a circular orbit (:meth:`Orbit.circular`'s elements; ``epoch`` optional), as the
#: ``orbit:`` scene key and ``inject pass --orbit`` take them.
CIRCULAR_ORBIT_KEYS = ("height", "inclination", "raan", "mean_anomaly", "epoch")

def orbit_from_spec(spec, time, where="orbit"):
    """The one parser of an orbit given as a mapping: a scene's ``orbit:`` and ``inject
    pass``'s ``--tle``/``--orbit``.

    Parameters
    ----------
    spec : mapping
        ``{tle: FILE}``, ``{tle: [line1, line2]}`` or the circular-orbit keys
        :data:`CIRCULAR_ORBIT_KEYS` (``epoch`` optional, default ``time``); numbers may be
        strings (from a command line). Each is checked against :data:`~inject.validate.RANGES`
        (``orbit.height`` etc.).
    time : Time or str
        The exposure start (the default epoch).
    where : str
        How the user wrote it, for messages (``satellites[0].orbit``, ``--orbit``).

    Raises
    ------
    InputError, OrbitError
    """
    if not isinstance(spec, dict):
        raise InputError(where, spec, "must be {tle: FILE or [line1, line2]} or "
                                      "{height, inclination, raan, mean_anomaly[, epoch]}")
    unknown = sorted(set(spec) - {"tle", *CIRCULAR_ORBIT_KEYS})
    if unknown:
        raise InputError(f"{where}.{unknown[0]}", spec[unknown[0]],
                         f"unknown key (known: tle, {', '.join(CIRCULAR_ORBIT_KEYS)})")
    if "tle" in spec:
        if set(spec) != {"tle"}:
            raise InputError(where, sorted(spec), "'tle' takes no other key")
        tle = spec["tle"]
        if isinstance(tle, str):
            return Orbit.read_tle(tle)
        if isinstance(tle, (list, tuple)) and len(tle) == 2:
            return Orbit.from_tle(*tle)
        raise InputError(f"{where}.tle", tle, "a TLE file name or [line1, line2]")
    missing = [k for k in CIRCULAR_ORBIT_KEYS[:4] if k not in spec]
    if missing:
        raise InputError(where, sorted(spec), f"needs {', '.join(missing)} (or tle)")
    numbers = []
    for k in CIRCULAR_ORBIT_KEYS[:4]:
        value = spec[k]
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                raise InputError(f"{where}.{k}", value, "must be a number") from None
        numbers.append(value)
    epoch = parse_time(spec.get("epoch", time), f"{where}.epoch")
    return Orbit.circular(*numbers, epoch, name="orbit", where=where)


def site_from_spec(spec, where="site"):
    """The one parser of a site: None (Rubin), ``{lat, lon, height}``, ``[lat, lon, height]``
    or ``"LAT,LON,M"`` (deg, deg, m; checked against RANGES' ``site.*`` rows)."""
    if spec is None:
        return RUBIN
    given = spec
    if isinstance(spec, str):
        spec = [v.strip() for v in spec.split(",")]
    if isinstance(spec, dict):
        if set(spec) != {"lat", "lon", "height"}:
            raise InputError(where, spec, "needs exactly lat, lon, height (deg, deg, m)")
        spec = [spec["lat"], spec["lon"], spec["height"]]
    if not isinstance(spec, (list, tuple)) or len(spec) != 3:
        raise InputError(where, given, "must be LAT,LON,M or {lat, lon, height} (deg, deg, m)")
    values = []
    for key, value in zip(("lat", "lon", "height"), spec):
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                raise InputError(where, given, "must be LAT,LON,M (deg, deg, m)") from None
        values.append(RANGES[f"site.{key}"].check(value, f"{where} {key}"))
    return Site(*values)


def _tle_checksum_ok(line):
    return len(line) >= 69 and line[68].isdigit() and int(line[68]) == compute_checksum(line)


@dataclass(frozen=True, eq=False)
class Orbit:
    """One satellite as an SGP4 element set.

    Build it with :meth:`from_tle`, :meth:`read_tle` or :meth:`circular`. ``kind`` is ``"tle"`` or
    ``"circular"``.
    """

    satrec: Satrec
    name: str = "satellite"
    kind: str = "tle"

    @classmethod
    def from_tle(cls, line1, line2, name=None, where=("TLE line 1", "TLE line 2")):
        """An orbit from the two lines of a TLE (checksums verified); ``where`` names the two
        lines in errors (e.g. by their line numbers in a file).

        Raises
        ------
        OrbitError
            If a line is malformed or its checksum is wrong.
        """
        return cls._from_lines(line1, line2, name, where)

    @classmethod
    def _from_lines(cls, line1, line2, name, where):
        """:meth:`from_tle`, its errors naming the lines as ``where`` says (e.g. by their
        line numbers in a file)."""
        lines = []
        for k, line, label in ((1, line1, where[0]), (2, line2, where[1])):
            if not isinstance(line, str):
                raise OrbitError(f"{label}={line!r}: must be a string")
            line = line.rstrip()
            if len(line) != 69 or line[0] != str(k):
                raise OrbitError(f"{label}={line!r}: must be 69 characters starting with "
                                 f"'{k} '")
            if not _tle_checksum_ok(line):
                raise OrbitError(f"{label}={line!r}: bad checksum (last digit "
                                 f"{line[68]}, expected {compute_checksum(line)})")
            lines.append(line)
        if lines[0][2:7] != lines[1][2:7]:
            raise OrbitError(f"{where[0]} and {where[1]}: different catalog numbers "
                             f"({lines[0][2:7]!r} and {lines[1][2:7]!r})")
        try:
            sat = Satrec.twoline2rv(lines[0], lines[1], WGS72)
        except (ValueError, IndexError) as err:
            raise OrbitError(f"{where[0]}={lines[0][:20]!r}...: unreadable ({err})") from None
        orbit = cls(sat, (name or lines[0][2:7]).strip(), "tle")
        orbit._check_elements()
        return orbit

    @classmethod
    def from_text(cls, text, source="TLE text"):
        """An orbit from TLE text: two lines, optionally after a name line.

        Errors name ``source`` and the text's own line numbers (``TLE file 'x.tle' line 3``).
        """
        numbered = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip()]
        if len(numbered) not in (2, 3):
            raise OrbitError(f"{source}: holds {len(numbered)} non-empty lines, expected 2 TLE "
                             f"lines, optionally after a name line")
        name = numbered[0][1].strip().removeprefix("0 ") if len(numbered) == 3 else None
        (n1, l1), (n2, l2) = numbered[-2:]
        return cls._from_lines(l1, l2, name, (f"{source} line {n1}", f"{source} line {n2}"))

    @classmethod
    def read_tle(cls, path):
        """An orbit from a TLE file (two lines, optionally after a name line)."""
        try:
            with open(path, encoding="ascii") as f:
                text = f.read()
        except (OSError, UnicodeDecodeError) as err:
            raise OrbitError(f"TLE file {str(path)!r}: cannot be read ({err})") from None
        return cls.from_text(text, f"TLE file {str(path)!r}")

    @classmethod
    def circular(cls, height_km, inclination_deg, raan_deg, mean_anomaly_deg, epoch,
                 name="circular", satnum=99999, where="orbit"):
        """A circular orbit as SGP4 mean elements (eccentricity 0, no drag).

        ``height_km`` is the height of the Brouwer mean semi-major axis above
        :data:`~inject.geometry.R_EARTH_KM`; SGP4 adds the J2 secular drift (nodal precession) and
        the short-period terms (the radius oscillates by a few km about it). ``mean_anomaly_deg``
        is the argument of latitude at ``epoch`` (deg from the ascending node). The elements
        are checked against :data:`~inject.validate.RANGES` (``orbit.*``; messages name them
        ``<where>.<key>``).
        """
        h, inc, raan, ma = (RANGES[f"orbit.{k}"].check(v, f"{where}.{k}") for k, v in (
            ("height", height_km), ("inclination", inclination_deg), ("raan", raan_deg),
            ("mean_anomaly", mean_anomaly_deg)))
        raan, ma = raan % 360.0, ma % 360.0
        epoch = parse_time(epoch, "epoch")
        a_er = (R_EARTH_KM + h) / _wgs72_radius_km()
        # sgp4init takes the Kozai mean motion and derives the Brouwer one (and Satrec.a) from
        # it: solve for the Kozai value that gives the wanted Brouwer semi-major axis.
        no_kozai = _mean_motion_rad_min(a_er)
        epoch_days = epoch.utc.jd - 2433281.5  # days since 1949 December 31 00:00 UT
        for _ in range(6):
            sat = _sgp4init(satnum, epoch_days, inc, raan, ma, no_kozai)
            no_kozai *= (sat.a / a_er) ** 1.5
        sat = _sgp4init(satnum, epoch_days, inc, raan, ma, no_kozai)
        orbit = cls(sat, name, "circular")
        orbit._check_elements()
        return orbit

    @property
    def epoch(self):
        """The element set's epoch (UTC)."""
        return Time(self.satrec.jdsatepoch, self.satrec.jdsatepochF, format="jd", scale="utc")

    @property
    def mean_height_km(self):
        """Height of the mean semi-major axis above :data:`~inject.geometry.R_EARTH_KM`."""
        return self.satrec.a * _wgs72_radius_km() - R_EARTH_KM

    def tle_lines(self):
        """The element set as two TLE lines (valid checksums), e.g. to write a TLE file."""
        return export_tle(self.satrec)

    def as_tle(self):
        """This orbit rounded to what its TLE lines hold (so a TLE file written from it and
        the orbit propagate the same; the rounding moves a LEO satellite by ~10 m)."""
        return Orbit.from_tle(*self.tle_lines(), name=self.name)

    def _check_elements(self):
        """Refuse element sets SGP4 cannot propagate, or whose perigee is below 80 km."""
        err, _, _ = self.satrec.sgp4_tsince(0.0)
        if err:
            raise OrbitError(f"orbit {self.name!r}: SGP4 error {err} at epoch "
                             f"({SGP4_ERRORS.get(err, 'unknown')})")
        perigee = self.satrec.altp * _wgs72_radius_km()
        if perigee < 80.0:
            raise OrbitError(f"orbit {self.name!r}: perigee height {perigee:.0f} km: decayed "
                             f"(must be >= 80 km)")

    def check_epoch(self, time):
        """Warn (OrbitWarning) or refuse (OrbitError) an epoch far from ``time``."""
        days = abs((parse_time(time) - self.epoch).to_value(u.day))
        if days > EPOCH_REFUSE_DAYS:
            raise OrbitError(f"orbit {self.name!r}: epoch {self.epoch.isot} is {days:.1f} days "
                             f"from the exposure (more than {EPOCH_REFUSE_DAYS:g} is refused)")
        if days > EPOCH_WARN_DAYS:
            warnings.warn(f"orbit {self.name!r}: epoch {self.epoch.isot} is {days:.1f} days from "
                          f"the exposure (> {EPOCH_WARN_DAYS:g}): position may be km off",
                          OrbitWarning, stacklevel=2)


def _wgs72_radius_km():
    return wgs72.radiusearthkm  # SGP4's Earth radius, the unit of Satrec.a and altp


def _mean_motion_rad_min(a_er):
    """Keplerian mean motion (rad/min) for a semi-major axis in WGS72 Earth radii."""
    return wgs72.xke / a_er ** 1.5


def _sgp4init(satnum, epoch_days, inc, raan, ma, no_kozai):
    sat = Satrec()
    sat.sgp4init(WGS72, "i", satnum, epoch_days, 0.0, 0.0, 0.0, 0.0, np.radians(0.0),
                 np.radians(inc), np.radians(ma), no_kozai, np.radians(raan))
    return sat


def walker_shell(total, planes, phasing, height_km, inclination_deg, epoch, raan0_deg=0.0,
                 name="shell"):
    """A Walker-delta constellation ``i: total/planes/phasing`` of circular orbits.

    Plane ``j`` has RAAN ``raan0 + 360 j / planes``; satellite ``k`` in it has argument of
    latitude ``360 k / S + 360 phasing j / total`` (``S = total / planes``).
    """
    total, planes = int(total), int(planes)
    if planes < 1 or total < planes or total % planes:
        raise InputError("walker total/planes", f"{total}/{planes}",
                         "total must be a positive multiple of planes")
    per_plane = total // planes
    epoch = parse_time(epoch, "epoch")  # once for the shell, not once per satellite
    orbits = []
    for j in range(planes):
        for k in range(per_plane):
            orbits.append(Orbit.circular(
                height_km, inclination_deg, raan0_deg + 360.0 * j / planes,
                360.0 * k / per_plane + 360.0 * phasing * j / total, epoch,
                name=f"{name}-{j:03d}-{k:03d}", satnum=(j * per_plane + k) % 100000))
    return orbits


def aimed_orbit(time, alt_deg, az_deg, site=RUBIN, height_km=550.0, inclination_deg=53.0,
                ascending=True, name="EXAMPLE-SAT", satnum=90001):
    """A circular orbit (epoch ``time``) that is at (alt, az) seen from ``site`` at ``time``.

    Example data: builds Starlink-like shell orbits timed to cross a chosen pointing, for tests
    and sample fields; returned as the TLE it writes (:meth:`Orbit.as_tle`). The orbit's
    geocentric direction is aimed at the point of the line of sight at the orbit's radius,
    refined against SGP4 itself (a few iterations); the TLE's rounding leaves it ~0.01 deg off.
    ``ascending`` picks the northbound or southbound pass through that point.

    Raises
    ------
    InputError
        If the point's geocentric latitude exceeds the inclination (no such orbit).
    """
    time = parse_time(time)
    alt = in_range("alt", alt_deg, 0.0, 90.0, hi_open=False, scalar=True)
    az = finite("az", az_deg, scalar=True)
    inc = in_range("inclination", inclination_deg, 0.0, 180.0, scalar=True)
    north, east, up = altaz_basis(site)
    a, z = math.radians(alt), math.radians(az)
    s_itrs = math.cos(a) * (math.cos(z) * north + math.sin(z) * east) + math.sin(a) * up
    teme = TEME(obstime=time)

    def target(radius):
        # Point of the line of sight at geocentric distance ``radius``, in TEME.
        o = site.itrs_km
        b = o @ s_itrs
        rho = -b + math.sqrt(b * b - (o @ o - radius ** 2))
        p = o + rho * s_itrs
        c = SkyCoord(CartesianRepresentation(*p, unit=u.km), frame=ITRS(obstime=time))
        return c.transform_to(teme).cartesian.xyz.to_value(u.km)

    def u_raan(p):
        dec = math.asin(np.clip(p[2] / np.linalg.norm(p), -1, 1))
        sin_u = math.sin(dec) / math.sin(math.radians(inc))
        if abs(sin_u) > 1.0:
            raise InputError("alt/az", (alt_deg, az_deg),
                             f"that point is at latitude {math.degrees(dec):.1f} deg, beyond "
                             f"inclination {inc:g} deg")
        arg = math.asin(sin_u) if ascending else math.pi - math.asin(sin_u)
        ra = math.atan2(p[1], p[0])
        return arg, ra - math.atan2(math.cos(math.radians(inc)) * math.sin(arg), math.cos(arg))

    radius = R_EARTH_KM + height_km
    goal = target(radius)
    arg, raan = u_raan(goal)
    arg_set, raan_set = arg, raan
    jd1, jd2 = time.utc.jd1, time.utc.jd2
    for _ in range(8):
        orbit = Orbit.circular(height_km, inc, math.degrees(raan_set), math.degrees(arg_set),
                               time, name=name, satnum=satnum)
        _, r, _ = orbit.satrec.sgp4(jd1, jd2)
        r = np.asarray(r)
        goal = target(np.linalg.norm(r))
        arg_goal, raan_goal = u_raan(goal)
        arg_now, raan_now = u_raan(r)
        arg_set += arg_goal - arg_now
        raan_set += _wrap_pi(raan_goal - raan_now)
        if np.linalg.norm(np.asarray(r) - goal) < 1e-3:
            break
    return Orbit.circular(height_km, inc, math.degrees(raan_set), math.degrees(arg_set), time,
                          name=name, satnum=satnum).as_tle()


def _wrap_pi(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


# --- propagation and frames ----------------------------------------------------------------------

def propagate_teme(orbits, times):
    """TEME positions (km) and velocities (km/s) of ``orbits`` at ``times``.

    Vectorised with SGP4's ``SatrecArray``. Returns arrays of shape (n_orbits, n_times, 3).

    Raises
    ------
    OrbitError
        If SGP4 fails for any orbit at any time (decayed, eccentricity out of range).
    """
    times = Time(times)
    return _sgp4(orbits, np.atleast_1d(times.utc.jd1).astype(float),
                 np.atleast_1d(times.utc.jd2).astype(float))


def _sgp4(orbits, jd1, jd2):
    """:func:`propagate_teme` at UTC Julian dates ``jd1 + jd2`` (avoids astropy Time overhead)."""
    if len(orbits) == 1:
        err, r, v = orbits[0].satrec.sgp4_array(jd1, jd2)
        err, r, v = err[None], r[None], v[None]
    else:
        err, r, v = SatrecArray([o.satrec for o in orbits]).sgp4(jd1, jd2)
    if np.any(err):
        i, k = np.argwhere(err)[0]
        raise OrbitError(f"orbit {orbits[i].name!r}: SGP4 error {err[i, k]} at "
                         f"{Time(jd1[k], jd2[k], format='jd').utc.isot} "
                         f"({SGP4_ERRORS.get(int(err[i, k]), 'unknown')})")
    return r, v


def teme_to_itrs(r_teme_km, times):
    """Rotate TEME position vectors (km, shape (n_times, 3)) at ``times`` into ITRS (astropy)."""
    c = SkyCoord(CartesianRepresentation(r_teme_km.T, unit=u.km), frame=TEME(obstime=times))
    return c.transform_to(ITRS(obstime=times)).cartesian.xyz.to_value(u.km).T


def altaz_basis(site):
    """The site's North, East and Up unit vectors in ITRS (geodetic latitude and longitude).

    The axes of astropy's AltAz cartesian representation in its topocentric ITRS -> AltAz (a
    test checks them against :attr:`FieldFrame.itrs_to_altaz`). Note that astropy must be given
    *topocentric* ITRS (site subtracted, ``location`` set): from geocentric ITRS it goes through
    ITRS -> CIRS -> ITRS, which treats the satellite as a celestial source, ~100" off at LEO.
    """
    lat, lon = np.radians(site.lat_deg), np.radians(site.lon_deg)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    return np.cross(up, east), east, up


def _check_iers(times):
    """One OrbitWarning if a time lies beyond the bundled IERS table; whether one does."""
    table = iers.earth_orientation_table.get()
    last = table["MJD"].max().to_value(u.d)
    if np.max(np.atleast_1d(times.utc.mjd)) > last:
        end = Time(last, format="mjd").utc.isot[:10]
        warnings.warn(f"time {Time(np.max(times.utc.mjd), format='mjd').utc.isot} is beyond the "
                      f"bundled IERS table (ends {end}): UT1 and polar motion extrapolated, "
                      f"positions may be off by arcseconds", OrbitWarning, stacklevel=6)
        return True
    return False


@contextmanager
def earth_orientation(times):
    """Warn once (:func:`_check_iers`) if ``times`` lie beyond the bundled IERS table, and
    within the block silence astropy's own warnings of the same (a repeat of it, with advice
    to download a table, which this offline package never does)."""
    beyond = _check_iers(times)
    with warnings.catch_warnings():
        if beyond:
            for text in ("Tried to get polar motions", r"\(some\) times are outside of range"):
                warnings.filterwarnings("ignore", message=text, category=AstropyWarning)
        yield


def parallactic_angles(ra_deg, dec_deg, times, site):
    """The parallactic angle of each boresight at its time, deg in [0, 360).

    The position angle, from the ICRS north through east, of the direction to the zenith:
    the boresight's place seen from ``site`` (no refraction) moved 10 arcsec up, back in
    ICRS. North is the ICRS pole rather than the true pole of the date, as LSST's rotation
    angles take it (the two differ by the precession since J2000, ~0.3 deg by 2026).

    Parameters
    ----------
    ra_deg, dec_deg : array_like
        Boresights, ICRS, deg.
    times : astropy.time.Time
        One time per boresight.
    site : Site

    Returns
    -------
    ndarray
    """
    frame = AltAz(obstime=times, location=site.location)
    boresight = SkyCoord(np.asarray(ra_deg, float) * u.deg, np.asarray(dec_deg, float) * u.deg,
                         frame="icrs")
    with earth_orientation(times):
        horizontal = boresight.transform_to(frame)
        up = SkyCoord(az=horizontal.az, alt=horizontal.alt + 10 * u.arcsec, frame=frame)
        return boresight.position_angle(up.transform_to("icrs")).to_value(u.deg)


def _rot_z(angle):
    """Matrices (n, 3, 3) turning vectors by ``angle`` (rad, shape (n,)) about z."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(np.shape(angle) + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1], m[..., 2, 2] = c, -s, s, c, 1.0
    return m


@dataclass(frozen=True, eq=False)
class FieldFrame:
    """Everything one exposure's satellites share, from astropy, at each sample time.

    Built once per (times, pointing, site) by :meth:`build` with one astropy call per frame
    chain (many exposures' in the same calls by :meth:`build_many`); each satellite then needs
    SGP4 and matrix products only.

    Attributes
    ----------
    centre, east, north : ndarray (n_times, 3)
        The boresight and its local East and North, unit vectors in astropy's AltAz cartesian
        axes (North, East, Up), from the ICRS pointing transformed to AltAz: with the stars'
        aberration, so the tracked star field.
    alt_deg, az_deg : ndarray (n_times,)
        The boresight's (unrefracted) altitude and azimuth.
    teme_to_itrs : ndarray (n_times, 3, 3)
        astropy's TEME -> ITRS rotation of geocentric vectors (GMST 1982 and polar motion from
        the IERS table), obtained by rotating the axes.
    itrs_to_altaz : ndarray (3, 3)
        astropy's topocentric ITRS -> AltAz rotation at the site.
    sun_itrs : ndarray (n_times, 3)
        Geocentric Sun (astropy ``get_sun``) in ITRS, km.
    to_icrs : ndarray (n_times, 2, 2)
        Apparent (AltAz) gnomonic offsets from the boresight -> ICRS ones: the differential
        aberration (a linear map to 1e-4 x the field angle, ~0.5" at the field's edge), so
        that field angles are those of the ICRS star a CCD's WCS puts at the same pixel.
    """

    times: Time
    site: Site
    pointing: Pointing
    centre: np.ndarray
    east: np.ndarray
    north: np.ndarray
    alt_deg: np.ndarray
    az_deg: np.ndarray
    teme_to_itrs: np.ndarray
    itrs_to_altaz: np.ndarray
    sun_itrs: np.ndarray
    to_icrs: np.ndarray | None = None

    @cached_property
    def jd_utc(self):
        """UTC Julian dates of the samples as two float arrays (SGP4's input)."""
        return (np.atleast_1d(self.times.utc.jd1).astype(float),
                np.atleast_1d(self.times.utc.jd2).astype(float))

    def t_from(self, start):
        """Seconds of the samples from ``start`` (UTC Time)."""
        jd1, jd2 = self.jd_utc
        return ((jd1 - start.utc.jd1) + (jd2 - start.utc.jd2)) * 86400.0

    @classmethod
    def build(cls, times, pointing, site=RUBIN):
        """Compute the frames at ``times`` (warns once if they lie beyond the IERS table)."""
        times = Time(times)
        with earth_orientation(times):
            return cls._build_many([times], [pointing], site)[0]

    @classmethod
    def build_many(cls, times, pointings, site=RUBIN):
        """The frames of several exposures, each at its own times and pointing, in one astropy
        call per frame chain for them all.

        The same numbers, bit for bit, as ``[FieldFrame.build(t, p, site) for t, p in
        zip(times, pointings)]`` (ERFA and numpy compute each time apart), at a fraction of
        the cost: astropy's is mostly per call, not per time.

        Parameters
        ----------
        times : sequence of astropy.time.Time
            Each exposure's sample times (1-D); those of one time scale are computed together.
        pointings : sequence of inject.camera.wcs.Pointing
            One per exposure.
        site : Site

        Returns
        -------
        list of FieldFrame
            In the order of ``times`` (warns once per time scale if some lie beyond the IERS
            table).
        """
        times = [Time(t) for t in times]
        if len(times) != len(pointings):
            raise InputError("pointings", len(pointings), f"need one per exposure ({len(times)})")
        by_scale = {}
        for k, t in enumerate(times):
            by_scale.setdefault(t.scale, []).append(k)
        frames = [None] * len(times)
        for ks in by_scale.values():
            # Concatenated in their own scale: a conversion would change the last bits.
            together = np.concatenate([times[k] for k in ks])
            with earth_orientation(together):
                built = cls._build_many([times[k] for k in ks], [pointings[k] for k in ks],
                                        site, together)
            for k, frame in zip(ks, built):
                frames[k] = frame
        return frames

    @classmethod
    def _build_many(cls, times, pointings, site, together=None):
        """:meth:`build_many` for times of one scale (``together``: them concatenated)."""
        sizes = [t.size for t in times]
        if together is None:
            together = times[0] if len(times) == 1 else np.concatenate(times)
        n = together.size
        loc = site.location
        frame = AltAz(obstime=together, location=loc)
        centre = SkyCoord([p.ra_deg for p in pointings] * u.deg,
                          [p.dec_deg for p in pointings] * u.deg, frame="icrs")
        # Offsets of 1 arcmin: the tangent directions of North and East at the boresight; the
        # aberration's change over 1' (1e-4 x 60" = 6 mas) is negligible. One (3, n) transform,
        # each exposure's points repeated at each of its times.
        pts = [centre, centre.directional_offset_by(0 * u.deg, 1 * u.arcmin),
               centre.directional_offset_by(90 * u.deg, 1 * u.arcmin)]
        owner = np.repeat(np.arange(len(pointings)), sizes)
        radec = SkyCoord(np.stack([p.ra.deg[owner] for p in pts]) * u.deg,
                         np.stack([p.dec.deg[owner] for p in pts]) * u.deg, frame="icrs")
        aa = radec.transform_to(frame)
        vec = np.moveaxis(aa.cartesian.xyz.value, 0, -1)  # (3 points, n, 3)
        c, nn, e = (_unit(v) for v in vec)
        n_off, e_off = nn, e  # the offset points' apparent directions
        nn = _unit(nn - _dot(nn, c)[:, None] * c)
        e_perp = _unit(np.cross(c, nn))
        # AltAz cartesian axes are left-handed on the sky: take East's sign from the offset point.
        e = e_perp * np.sign(_dot(e, e_perp))[:, None]
        # TEME -> ITRS: rotate the three axes (1e4 km long, for round-off) in one call.
        axes = np.broadcast_to(np.eye(3)[:, None, :] * 1e4, (3, n, 3))
        rep = CartesianRepresentation(np.moveaxis(axes, -1, 0), unit=u.km)
        rot = SkyCoord(rep, frame=TEME(obstime=together)).transform_to(ITRS(obstime=together))
        cols = np.moveaxis(rot.cartesian.xyz.to_value(u.km), 0, -1) / 1e4  # (axis, n, 3)
        m_teme = np.stack([cols[0], cols[1], cols[2]], axis=-1)  # M @ r_teme = r_itrs
        # Topocentric ITRS -> AltAz: a rotation set by the site alone, the same at every time.
        t0 = together[:1] if together.shape else together
        topo = SkyCoord(CartesianRepresentation(np.eye(3) * 1e4, unit=u.km),
                        frame=ITRS(obstime=t0, location=loc))
        m_aa = topo.transform_to(AltAz(obstime=t0, location=loc)).cartesian.xyz.to_value(
            u.km) / 1e4  # columns: images of the ITRS axes
        sun = get_sun(together).transform_to(ITRS(obstime=together)).cartesian.xyz.to_value(
            u.km).T
        # The offset points are at ICRS gnomonic (0, tan 1') and (tan 1', 0); their apparent
        # gnomonic offsets give the linear map ICRS -> apparent, inverted here.
        t1 = math.tan(math.radians(1 / 60))
        cols = [np.stack([_dot(v, e) / _dot(v, c), _dot(v, nn) / _dot(v, c)], axis=-1) / t1
                for v in (e_off, n_off)]
        to_icrs = np.linalg.inv(np.stack(cols, axis=-1))  # (n, 2, 2)
        alt, az = aa[0].alt.to_value(u.deg), aa[0].az.to_value(u.deg)
        if len(times) == 1:  # whole, whatever the times' shape
            return [cls(times[0], site, pointings[0], c, e, nn, alt, az, m_teme, m_aa, sun,
                        to_icrs)]
        frames = []
        for t, pointing, lo, hi in zip(times, pointings, np.cumsum([0] + sizes[:-1]),
                                       np.cumsum(sizes)):
            s = slice(lo, hi)
            frames.append(cls(t, site, pointing, c[s], e[s], nn[s], alt[s], az[s], m_teme[s],
                              m_aa, sun[s], to_icrs[s]))
        return frames

    def to_altaz(self, r_itrs_km):
        """Topocentric unit vectors (AltAz axes), range (km), alt and az (deg) of ITRS points."""
        top = (r_itrs_km - self.site.itrs_km) @ self.itrs_to_altaz.T
        rng = np.linalg.norm(top, axis=-1)
        unit = top / rng[..., None]
        alt = np.degrees(np.arcsin(np.clip(unit[..., 2], -1.0, 1.0)))
        az = np.degrees(np.arctan2(unit[..., 1], unit[..., 0])) % 360.0
        return unit, rng, alt, az

    def field_angles(self, unit):
        """Gnomonic field angles (deg) of unit vectors (n_times, 3) in this frame.

        Returns ``xi, eta, x, y, front``: standard coordinates (xi East, eta North) and the same
        rotated into the focal-plane axes by :func:`inject.camera.wcs.tangent_to_focal`;
        tangent-plane coordinates in radians (as afw's FIELD_ANGLE) expressed in degrees. They
        are ICRS offsets: those of the star that appears where the direction points
        (:attr:`to_icrs`), so that a CCD's WCS (TAN about the ICRS boresight) maps them to the
        same pixel as that star. ``front`` is False where the direction is 90 deg or more from
        the boresight (the projection is then undefined: NaN).
        """
        cz = _dot(unit, self.centre)
        front = cz > 1e-6
        safe = np.where(front, cz, 1.0)
        xi = np.where(front, np.degrees(_dot(unit, self.east) / safe), np.nan)
        eta = np.where(front, np.degrees(_dot(unit, self.north) / safe), np.nan)
        if self.to_icrs is not None:  # apparent -> ICRS offsets (differential aberration)
            m = self.to_icrs
            xi, eta = (m[..., 0, 0] * xi + m[..., 0, 1] * eta,
                       m[..., 1, 0] * xi + m[..., 1, 1] * eta)
        x, y = tangent_to_focal(xi, eta, self.pointing.rotation_deg)
        return xi, eta, x, y, front


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --- shadow --------------------------------------------------------------------------------------

def sun_itrs(times):
    """Geocentric ITRS position of the Sun (km, (n, 3)) from astropy's ``get_sun``."""
    return get_sun(times).transform_to(ITRS(obstime=times)).cartesian.xyz.to_value(u.km).T


#: WGS84 equatorial and polar radii, km.
WGS84_A_KM, WGS84_B_KM = 6378.137, 6356.752314245
#: Default height of the grazing atmosphere that blocks sunlight, km: 0, the solid Earth's
#: geometric shadow. Sunlight grazing the limb below ~10-20 km is mostly absorbed and
#: refracted away, so a satellite there is far dimmer than the geometric penumbra says; the
#: height is a scene key (``shadow_atmosphere_km``) for those who want that margin.
SHADOW_ATMOSPHERE_KM = 0.0


def illumination(r_sat_km, r_sun_km, earth_radius_km=None, atmosphere_km=SHADOW_ATMOSPHERE_KM):
    """Fraction of the Sun's disc visible from the satellite (conical umbra/penumbra).

    Both positions geocentric in an Earth-fixed frame (z along the rotation axis), km, shape
    (..., 3). The Earth is the WGS84 ellipsoid grown by ``atmosphere_km`` (the height below
    which the grazing atmosphere is taken to block the Sun): scaling z by a/b makes it a
    sphere of radius a, and lines, hence the shadow's geometry, stay lines. ``earth_radius_km``
    instead takes a sphere of that radius (no scaling). The discs are flat circles of angular
    radii ``asin(R_sun / d_sun)`` and ``asin(R / |r|)`` (Montenbruck & Gill 2000, 3.4.2).

    Returns
    -------
    fraction : ndarray
        1 sunlit, 0 in the umbra, in between in the penumbra (or annular phase).
    state : ndarray of str
        ``"sunlit"``, ``"penumbra"`` or ``"umbra"``.
    """
    r_sat = np.asarray(r_sat_km, dtype=float)
    r_sun = np.asarray(r_sun_km, dtype=float)
    if earth_radius_km is None:
        squash = np.array([1.0, 1.0, (WGS84_A_KM + atmosphere_km) / (WGS84_B_KM + atmosphere_km)])
        r_sat, r_sun = r_sat * squash, r_sun * squash
        earth_radius_km = WGS84_A_KM + atmosphere_km
    to_sun = r_sun - r_sat
    d_sun = np.linalg.norm(to_sun, axis=-1)
    d_sat = np.linalg.norm(r_sat, axis=-1)
    a = np.arcsin(R_SUN_KM / d_sun)
    b = np.arcsin(np.minimum(earth_radius_km / d_sat, 1.0))
    cos_c = -_dot(r_sat, to_sun) / (d_sat * d_sun)
    c = np.arccos(np.clip(cos_c, -1.0, 1.0))
    # Overlap area of two discs of radii a, b at distance c (lens formula), where partial.
    partial = (c < a + b) & (c > np.abs(a - b))
    cs = np.where(partial, c, a + b)  # placeholder where not partial: keeps arccos in range
    x = (cs ** 2 + a ** 2 - b ** 2) / (2 * cs)
    y = np.sqrt(np.maximum(a ** 2 - x ** 2, 0.0))
    lens = (a ** 2 * np.arccos(np.clip(x / a, -1, 1)) + b ** 2 * np.arccos(
        np.clip((cs - x) / b, -1, 1)) - cs * y)
    full = np.where(b >= a, np.pi * a ** 2, np.pi * b ** 2)  # one disc inside the other
    overlap = np.where(c >= a + b, 0.0, np.where(partial, lens, full))
    fraction = np.clip(1.0 - overlap / (np.pi * a ** 2), 0.0, 1.0)
    state = np.where(fraction >= 1.0, "sunlit", np.where(fraction <= 0.0, "umbra", "penumbra"))
    return fraction, state


def sunlight(orbit, times, atmosphere_km=SHADOW_ATMOSPHERE_KM):
    """Visible fraction of the Sun's disc and shadow state of ``orbit`` at ``times``.

    See :func:`illumination`; the Sun from astropy's ``get_sun``, both in ITRS.
    """
    times = Time(times)
    r_teme, _ = propagate_teme([orbit], times)
    return illumination(teme_to_itrs(r_teme[0], times), sun_itrs(times),
                        atmosphere_km=atmosphere_km)


# --- the pass ------------------------------------------------------------------------------------

@dataclass(eq=False)
class Pass:
    """A satellite through one exposure, sampled (see :func:`compute_pass`).

    Per-sample arrays (length n): ``t_s`` (from the exposure start), ``utc``; geometric
    ``alt_deg``, ``az_deg``, ``range_km`` (where it is at that instant); ``nadir_angle_deg`` and
    ``phi_deg`` (the paper's eq. 1 and 8 angles: at the satellite, between its geocentric nadir
    and the line to the site; and the azimuth of its inertial velocity in the paper's frame, z to
    nadir, the site in the yz-plane at +y, x = y cross z, so phi = 90 deg is motion towards the
    site along constant azimuth); ``angular_speed_rad_s`` across the tracked star field;
    ``sun_fraction``, ``shadow``, ``sunlit`` (fraction > 0); ``light_time_s``; where it appears:
    ``apparent_alt_deg``, ``apparent_az_deg`` and the field angles ``xi_deg``, ``eta_deg``
    (standard coordinates, East/North) and ``field_x_deg``, ``field_y_deg`` (focal-plane axes
    after the rotator, the input of the focal-plane mapping to mm).

    ``in_field`` is True when the apparent track, above the horizon, enters the disc of radius
    ``field_radius_deg``; ``visible`` also needs the Sun on it there; ``message`` says why not.
    """

    orbit: Orbit
    exposure: Exposure
    pointing: Pointing
    site: Site
    t_s: np.ndarray
    utc: Time
    alt_deg: np.ndarray
    az_deg: np.ndarray
    range_km: np.ndarray
    nadir_angle_deg: np.ndarray
    phi_deg: np.ndarray
    angular_speed_rad_s: np.ndarray
    sun_fraction: np.ndarray
    shadow: np.ndarray
    light_time_s: np.ndarray
    apparent_alt_deg: np.ndarray
    apparent_az_deg: np.ndarray
    xi_deg: np.ndarray
    eta_deg: np.ndarray
    field_x_deg: np.ndarray
    field_y_deg: np.ndarray
    field_radius_deg: float
    in_field: bool = False
    visible: bool = False
    message: str = ""
    inside: np.ndarray | None = field(default=None, repr=False)
    #: Height above :data:`~inject.geometry.R_EARTH_KM` (the geocentric distance less the
    #: paper's spherical Earth), km: what the streak model's ``height`` means.
    height_km: np.ndarray | None = field(default=None, repr=False)

    @property
    def sunlit(self):
        return self.sun_fraction > 0.0

    def magnitude(self, mag_ref, ref_range_km=550.0):
        """Apparent magnitude per sample from the paper's scaling, dimmed by the penumbra.

        ``mag_ref`` is the stationary magnitude at ``ref_range_km``, face-on
        (:func:`~inject.photometry.apparent_magnitude`: flux ~ cos(theta_N) / r^2), plus
        ``-2.5 log10(sun_fraction)``; ``inf`` in the umbra (no light).
        """
        m = apparent_magnitude(mag_ref, self.range_km, self.nadir_angle_deg, ref_range_km)
        lit = self.sun_fraction > 0
        dim = -2.5 * np.log10(np.where(lit, self.sun_fraction, 1.0))
        return np.where(lit, m + dim, np.inf)

    def focal_mm(self):
        """Focal-plane position (mm) where the satellite appears, per sample: the field angles
        through :func:`inject.camera.layout.focal_of_field_angle` (the distortion), the mapping
        every CCD's WCS uses. NaN where the field angle is undefined (behind the boresight) or
        beyond :data:`TRACK_RADIUS_DEG` (outside the camera, where the distortion polynomial
        does not apply)."""
        ax, ay = np.radians(self.field_x_deg), np.radians(self.field_y_deg)
        ok = np.isfinite(ax) & np.isfinite(ay)
        ok[ok] = np.hypot(self.field_x_deg[ok], self.field_y_deg[ok]) <= TRACK_RADIUS_DEG
        x, y = focal_of_field_angle(np.where(ok, ax, 0.0), np.where(ok, ay, 0.0))
        return np.where(ok, x, np.nan), np.where(ok, y, np.nan)

    def samples(self):
        """The samples as a list of JSON-ready dicts (the keys of ``inject pass --json``
        except the focal-plane ``x_mm``/``y_mm``, plus the field angles)."""
        keys = ("t_s", "alt_deg", "az_deg", "range_km", "nadir_angle_deg", "phi_deg",
                "angular_speed_rad_s", "sun_fraction", "light_time_s", "apparent_alt_deg",
                "apparent_az_deg", "xi_deg", "eta_deg", "field_x_deg", "field_y_deg")
        out = []
        for i in range(len(self.t_s)):
            row = {"t_s": float(self.t_s[i]), "utc": self.utc[i].isot}
            for k in keys[1:]:
                val = float(getattr(self, k)[i])
                row[k] = val if math.isfinite(val) else None
            row["sunlit"] = bool(self.sunlit[i])
            row["shadow"] = str(self.shadow[i])
            out.append(row)
        return out

    def to_dict(self):
        """JSON-ready summary: ``in_field``, ``visible``, ``message``, the orbit and samples."""
        return {"in_field": bool(self.in_field), "visible": bool(self.visible),
                "message": self.message, "satellite": self.orbit.name,
                "orbit_kind": self.orbit.kind, "tle": list(self.orbit.tle_lines()),
                "time": self.exposure.start.isot, "exptime_s": self.exposure.exptime_s,
                "ra_deg": self.pointing.ra_deg, "dec_deg": self.pointing.dec_deg,
                "rotation_deg": self.pointing.rotation_deg,
                "site": [self.site.lat_deg, self.site.lon_deg, self.site.height_m],
                "field_radius_deg": self.field_radius_deg, "samples": self.samples()}


def segment_distances(x, y):
    """Per segment between consecutive points: its closest distance to the origin."""
    x0, y0, x1, y1 = x[..., :-1], y[..., :-1], x[..., 1:], y[..., 1:]
    dx, dy = x1 - x0, y1 - y0
    len2 = dx * dx + dy * dy
    t = np.clip(-(x0 * dx + y0 * dy) / np.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    return np.hypot(x0 + t * dx, y0 + t * dy)


def compute_pass(orbit, exposure, pointing, site=RUBIN, step_s=1.0, t_s=None,
                 field_radius_deg=FIELD_RADIUS_DEG, frame=None, check_epoch=True,
                 atmosphere_km=SHADOW_ATMOSPHERE_KM):
    """The satellite through one exposure, sampled at least every ``step_s`` and at the middle.

    Parameters
    ----------
    orbit : Orbit
    exposure : Exposure
    pointing : Pointing
    site : Site
    step_s : float
        Largest sample spacing, s (used when ``t_s`` is None).
    t_s : array_like, optional
        Explicit sample times, s from the exposure start (e.g. denser vertices for the renderer).
    field_radius_deg : float
        Radius of the field disc for ``in_field``.
    frame : FieldFrame, optional
        The tracked field at the sample times, when already built (shared across satellites).
    check_epoch : bool
        Apply :meth:`Orbit.check_epoch` (warn past 14 days, refuse past 60).
    atmosphere_km : float
        Height of the grazing atmosphere that blocks sunlight (:func:`illumination`).

    Returns
    -------
    Pass
    """
    if check_epoch:
        orbit.check_epoch(exposure.start)
    ts = exposure.sample_times(step_s) if t_s is None else np.sort(finite("t_s", t_s))
    if frame is None:
        frame = FieldFrame.build(exposure.start + ts * u.s, pointing, site)
    elif (frame.times.shape != ts.shape or frame.pointing != pointing or frame.site != site
          or np.any(np.abs(frame.t_from(exposure.start) - ts) > 1e-6)):
        raise InputError("frame", "FieldFrame", "was built for other times, pointing or site")
    times = frame.times
    jd1, jd2 = frame.jd_utc
    m = frame.teme_to_itrs
    r_teme, v_teme = (a[0] for a in _sgp4([orbit], jd1, jd2))
    r_itrs = np.einsum("tij,tj->ti", m, r_teme)
    v_in = np.einsum("tij,tj->ti", m, v_teme)  # inertial velocity in ITRS axes
    _, rng, alt, az = frame.to_altaz(r_itrs)

    # Light time: the retarded position (one iteration is exact to < 1 mm at LEO) in the
    # Earth-fixed frame of its own time, seen from the site at the sample time. The ITRS of
    # t - tau is that of t turned back by the Earth's rotation over tau (GMST 1982's rate; polar
    # motion's share of it is 1e-13 rad): a vector fixed in TEME appears turned by +w tau.
    tau = rng / C_KM_S
    r_ret_teme, _ = (a[0] for a in _sgp4([orbit], jd1, jd2 - tau / 86400.0))
    r_ret = np.einsum("tij,tj->ti", _rot_z(EARTH_ROTATION_RAD_S * tau) @ m, r_ret_teme)
    app_unit, app_rng, app_alt, app_az = frame.to_altaz(r_ret)
    tau = app_rng / C_KM_S
    xi, eta, fx, fy, front = frame.field_angles(app_unit)

    # Paper geometry at the satellite (rotation-invariant, computed in ITRS axes).
    obs = site.itrs_km
    z_hat = -_unit(r_itrs)  # geocentric nadir
    los = _unit(obs - r_itrs)  # satellite -> site
    nadir = np.degrees(np.arccos(np.clip(_dot(z_hat, los), -1.0, 1.0)))
    y_raw = los - _dot(los, z_hat)[:, None] * z_hat
    y_norm = np.linalg.norm(y_raw, axis=-1)
    y_hat = y_raw / np.where(y_norm > 0, y_norm, 1.0)[:, None]
    x_hat = np.cross(y_hat, z_hat)
    phi = np.degrees(np.arctan2(_dot(v_in, y_hat), _dot(v_in, x_hat)))
    phi = np.where(y_norm > 1e-12, phi, np.nan)  # at the zenith phi is undefined

    # Speed across the tracked star field: the inertial relative velocity perpendicular to the
    # line of sight over the range (stars are fixed in inertial axes; Earth's spin axis is ITRS z
    # to within polar motion, 0.3").
    omega = np.array([0.0, 0.0, EARTH_ROTATION_RAD_S])
    v_rel = v_in - np.cross(omega, obs)
    s = _unit(r_itrs - obs)
    v_perp = v_rel - _dot(v_rel, s)[:, None] * s
    ang_speed = np.linalg.norm(v_perp, axis=-1) / rng

    frac, state = illumination(r_itrs, frame.sun_itrs, atmosphere_km=atmosphere_km)

    above = app_alt > 0.0
    ok = front & above
    inside_pts = ok & (np.hypot(xi, eta) <= field_radius_deg)
    # Gnomonic: great circles are straight, so a segment between samples is the track's chord.
    seg_d = np.where(ok[:-1] & ok[1:], segment_distances(np.nan_to_num(xi),
                                                          np.nan_to_num(eta)), np.inf)
    in_field = bool(inside_pts.any() or (seg_d <= field_radius_deg).any())
    lit_inside = inside_pts & (frac > 0)
    visible = bool(lit_inside.any()) if inside_pts.any() else bool(
        in_field and (frac > 0).any())
    if not above.any():
        msg = f"below the horizon (altitude {alt.max():.1f} deg at most)"
    elif not in_field:
        near = min(np.min(np.hypot(xi, eta)[ok], initial=np.inf), np.min(seg_d, initial=np.inf))
        # The true angle from the boresight of a tangent-plane distance (deg of tan).
        closest = (f"{np.degrees(np.arctan(np.radians(near))):.2f} deg" if np.isfinite(near)
                   else "more than 90 deg")
        msg = f"misses the field (closest {closest} from the boresight, field radius " \
              f"{field_radius_deg:g} deg)"
    elif not visible:
        msg = "crosses the field in Earth's shadow"
    elif (frac[inside_pts] < 1).any():
        msg = "crosses the field, partly in Earth's shadow (penumbra or umbra)"
    else:
        msg = "crosses the field, sunlit"
    return Pass(orbit, exposure, pointing, site, ts, times, alt, az, rng, nadir, phi, ang_speed,
                frac, state, tau, app_alt, app_az, xi, eta, fx, fy, float(field_radius_deg),
                in_field, visible, msg, inside_pts,
                np.linalg.norm(r_itrs, axis=-1) - R_EARTH_KM)


# --- many satellites -----------------------------------------------------------------------------

def crossing_candidates(orbits, exposure, pointing, site=RUBIN, step_s=5.0, margin_deg=1.0,
                        field_radius_deg=FIELD_RADIUS_DEG):
    """Indices of the orbits that may cross the field: a coarse vectorised prefilter.

    SGP4 (``SatrecArray``) for the whole catalog at every ``step_s``, with the shared
    :class:`FieldFrame` of those times; no light time, no shadow.
    An orbit is a candidate when, above the horizon, a straight segment between consecutive
    coarse samples passes within ``field_radius_deg + margin_deg`` of the boresight in the tangent
    plane (the margin covers the track's curvature between samples and the light time).
    """
    ts = exposure.sample_times(step_s)
    times = exposure.start + ts * u.s
    frame = FieldFrame.build(times, pointing, site)
    r_teme, _ = propagate_teme(orbits, times)
    r_itrs = np.einsum("tij,stj->sti", frame.teme_to_itrs, r_teme)
    unit, _, _, _ = frame.to_altaz(r_itrs)
    above = unit[..., 2] > 0
    cz = np.einsum("sti,ti->st", unit, frame.centre)
    front = cz > 0.05
    safe = np.where(front, cz, 1.0)
    xi = np.degrees(np.einsum("sti,ti->st", unit, frame.east) / safe)
    eta = np.degrees(np.einsum("sti,ti->st", unit, frame.north) / safe)
    ok = above & front
    radius = field_radius_deg + margin_deg
    near = segment_distances(xi, eta) <= radius
    hit = (near & ok[:, :-1] & ok[:, 1:]).any(axis=1) | (ok & (np.hypot(xi, eta) <= radius)).any(
        axis=1)
    return np.flatnonzero(hit)


def find_passes(orbits, exposure, pointing, site=RUBIN, step_s=1.0, **prefilter):
    """The passes of ``orbits`` that cross the field during ``exposure``.

    Prefilters with :func:`crossing_candidates`, then runs :func:`compute_pass` (exact astropy
    frames) on the candidates only. Returns the list of :class:`Pass` with ``in_field`` True.
    """
    idx = crossing_candidates(orbits, exposure, pointing, site, **prefilter)
    if not len(idx):
        return []
    times = exposure.start + exposure.sample_times(step_s) * u.s
    frame = FieldFrame.build(times, pointing, site)
    out = []
    for i in idx:
        p = compute_pass(orbits[i], exposure, pointing, site, step_s, frame=frame)
        if p.in_field:
            out.append(p)
    return out


# --- the track on the focal plane ----------------------------------------------------------------

#: Field-angle radius (deg) beyond which no focal-plane position is given: past the science
#: CCDs (2.06 deg) with room for a footprint, well inside the distortion polynomial's range.
TRACK_RADIUS_DEG = 3.0
#: Sample step (s) of the pass a focal-plane track is built from. Between two samples 0.1 s
#: apart the track is straight in field angle to far better than a pixel, and the
#: distortion bends the chord (<= 9 mm at LEO rates) by less than 0.02 px.
TRACK_STEP_S = 0.1


def track_runs(p, tol_px=0.05, max_gap_s=1.0, lit_only=False,
               radius_deg=TRACK_RADIUS_DEG):
    """The apparent track of a (densely sampled) pass as focal-plane polylines.

    Keeps the samples above the horizon, within ``radius_deg`` of the boresight (and sunlit, if
    ``lit_only``), split into runs of consecutive samples, and in each run the fewest samples
    such that consecutive vertices are at most ``max_gap_s`` apart and every dropped sample lies
    within ``tol_px`` pixels of the chord between its neighbours (so the distortion's bend and
    the changes of width and brightness along the track are followed).

    Parameters
    ----------
    p : Pass
        Typically computed with ``step_s=TRACK_STEP_S``.

    Returns
    -------
    x_mm, y_mm : ndarray
        Focal-plane position of every sample (NaN where not kept).
    runs : list of ndarray
        Sample indices of each run's vertices, in time order.
    """
    from inject.camera.layout import PIXEL_MM
    x, y = p.focal_mm()
    keep = np.isfinite(x) & (p.apparent_alt_deg > 0.0) & (
        np.hypot(p.field_x_deg, p.field_y_deg) <= radius_deg)
    if lit_only:
        keep &= p.sun_fraction > 0.0
    x, y = np.where(keep, x, np.nan), np.where(keep, y, np.nan)
    tol = tol_px * PIXEL_MM
    runs = []
    idx = np.flatnonzero(keep)
    for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
        if len(run) < 2:
            continue
        chosen = [run[0]]
        a = 0
        while a < len(run) - 1:
            b = a + 1
            while b + 1 < len(run) and p.t_s[run[b + 1]] - p.t_s[run[a]] <= max_gap_s + 1e-9 \
                    and _chord_deviation(x[run[a:b + 2]], y[run[a:b + 2]]) <= tol:
                b += 1
            chosen.append(run[b])
            a = b
        runs.append(np.array(chosen))
    return x, y, runs


def _chord_deviation(x, y):
    """Largest distance of the inner points from the chord between the first and last."""
    dx, dy = x[-1] - x[0], y[-1] - y[0]
    length = math.hypot(dx, dy)
    if length == 0:
        return float(np.max(np.hypot(x - x[0], y - y[0])))
    return float(np.max(np.abs((x[1:-1] - x[0]) * dy - (y[1:-1] - y[0]) * dx)) / length)
