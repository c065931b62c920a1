"""The visits of a night: an opsim database (SQLite) or a CSV with the same columns.

The columns read are those LSST's scheduler (rubin_scheduler, formerly opsim) writes in its
``observations`` table:

==========================  =============================================================
``observationId``           the visit's id (integer)
``observationStartMJD``     the start of the first exposure, MJD in **TAI**
``fieldRA``, ``fieldDec``   the boresight, ICRS, deg
``rotSkyPos``               the sky's orientation on the focal plane, deg (below)
``band`` or ``filter``      the filter, ``u g r i z y`` (``band`` first: newer databases put the
                            physical filter's name, such as ``r_57``, in ``filter``)
``visitExposureTime``       the open-shutter time of the whole visit, s
``numExposures``            optional (default 1): snaps in the visit
``seeingFwhmEff``           optional: the effective PSF FWHM, arcsec
``skyBrightness``           optional: the sky, mag/arcsec^2
``rotTelPos``               optional: the camera rotator's angle, deg (``pupil: rubin``)
``paraAngle``               optional: the parallactic angle, deg (for rotTelPos, below)
==========================  =============================================================

Times. ``observationStartMJD`` is TAI (the scheduler's convention); it becomes an astropy
:class:`~astropy.time.Time` with ``scale="tai"``, which the orbits read in UTC (37 s
earlier on the clock).

Rotation. ``rotSkyPos`` is taken as the angle LSST's camera and pipelines call rotSkyPos, the
position angle of the focal plane's +y axis measured from north through east: the
``rotation`` of :class:`inject.camera.wcs.Pointing` (afw's ``makeCdMatrix(orientation=
rotSkyPos, flipX=False)``). rubin_scheduler writes this angle (its ``RotationConverter``:
rotSkyPos = parallactic angle - rotTelPos - 90 deg); databases of the older rubin_sim schema
described it as rotTelPos - parallactic angle, which turns the focal plane about the boresight
(the streak counts are unchanged on average, the CCDs each one crosses are not).
``rotTelPos`` turns the focal plane against the spider vanes of the traced pupil
(:func:`inject.optics.telescope_position_angle`). Without the column (or NULL) it is taken
from the same relation: from ``paraAngle`` when the file has it, else from the parallactic
angle computed for the visit's start (:func:`with_rotators`, with ``pupil: rubin`` only).

Snaps. A visit of ``numExposures`` = n snaps is n exposures of ``visitExposureTime / n``
seconds, each after the previous one's readout (:data:`READOUT_S`): a satellite that crosses
the field during a readout leaves no streak.

Seeing. ``seeingFwhmEff`` is the FWHM of the single Gaussian with the PSF's effective number of
pixels; the streak model's seeing is the PSF's own FWHM, ``FWHMgeom = 0.822 FWHMeff + 0.052``
(arcsec; SMTN-002, Ivezic et al. 2019). Without the column the model's default is used.
"""
import csv
import math
import os
import sqlite3
from dataclasses import dataclass, replace

import numpy as np

from inject.errors import FileFormatError, InputError
from inject.photometry import BANDS

#: Readout between two snaps of a visit, s (LSSTCam reads out in 2 s).
READOUT_S = 2.0

#: Columns every visit needs (``band`` may be given as ``filter``).
REQUIRED = ("observationId", "observationStartMJD", "fieldRA", "fieldDec", "rotSkyPos", "band",
            "visitExposureTime")
#: Columns read when present.
OPTIONAL = ("numExposures", "seeingFwhmEff", "skyBrightness", "rotTelPos", "paraAngle",
            "visitTime")

#: Where a visit's rotator angle came from: its ``rotTelPos``, its ``paraAngle`` and
#: ``rotSkyPos``, or the parallactic angle computed for its start (:func:`with_rotators`).
ROTATOR_SOURCES = ("rotTelPos", "paraAngle", "computed")

#: The MJDs of 1900-01-01 and 2100-01-01: a time of a survey outside is a mistake (a JD given
#: as an MJD is year ~8600).
MJD_RANGE = (15020.0, 88069.0)

#: FWHMgeom = a FWHMeff + b (arcsec), SMTN-002.
FWHM_GEOM_PER_EFF = 0.822
FWHM_GEOM_OFFSET = 0.052


@dataclass(frozen=True)
class Visit:
    """One visit of the survey.

    Attributes
    ----------
    observation_id : int
    mjd_tai : float
        Start of the first exposure, MJD (TAI).
    ra_deg, dec_deg : float
        Boresight, ICRS.
    rotation_deg : float
        rotSkyPos (module notes), deg.
    band : str
    exptime_s : float
        Open-shutter time of the whole visit (all snaps), s.
    n_exposures : int
        Snaps.
    seeing_fwhm_eff : float or None
        ``seeingFwhmEff``, arcsec.
    sky_brightness : float or None
        ``skyBrightness``, mag/arcsec^2.
    rotator_deg : float or None
        ``rotTelPos``, the camera rotator's angle, deg (None when not known).
    rotator_source : str or None
        Where ``rotator_deg`` came from (:data:`ROTATOR_SOURCES`).
    visit_time_s : float or None
        ``visitTime``, the visit's span from its first shutter opening to its last closing,
        s (read by ``--rule rubin_sim`` only: :mod:`inject.survey.rubin_rule`).
    """

    observation_id: int
    mjd_tai: float
    ra_deg: float
    dec_deg: float
    rotation_deg: float
    band: str
    exptime_s: float
    n_exposures: int = 1
    seeing_fwhm_eff: float | None = None
    sky_brightness: float | None = None
    rotator_deg: float | None = None
    rotator_source: str | None = None
    visit_time_s: float | None = None

    @property
    def start(self):
        """The start as an astropy Time (TAI)."""
        from astropy.time import Time

        return Time(self.mjd_tai, format="mjd", scale="tai")

    @property
    def seeing_arcsec(self):
        """The PSF's FWHM for the streak model (``FWHMgeom``, module notes), or None."""
        if self.seeing_fwhm_eff is None:
            return None
        return FWHM_GEOM_PER_EFF * self.seeing_fwhm_eff + FWHM_GEOM_OFFSET

    def snaps(self):
        """``(start, duration)`` of each snap, s from the visit's start."""
        n = self.n_exposures
        each = self.exptime_s / n
        return tuple(((each + READOUT_S) * k, each) for k in range(n))


def read_visits(path):
    """The visits of an opsim SQLite database or a CSV, in start order.

    Parameters
    ----------
    path : str or os.PathLike
        A SQLite file (table ``observations``) or a ``.csv`` with a header line.

    Returns
    -------
    tuple of Visit

    Raises
    ------
    FileFormatError
        The file cannot be read, is not a SQLite database or CSV, has no ``observations``
        table or lacks a column.
    InputError
        It holds no visit, or a value is out of its domain (named by row and column).
    """
    path = os.fspath(path)
    columns, rows = (_read_sqlite if visits_kind(path) == "sqlite" else _read_csv)(path)
    names = column_names(path, columns)
    if not rows:
        raise InputError("VISITS", path, "holds no visit (an empty night)")
    visits = [visit_from_row(path, k, dict(zip(columns, row)), names) for k, row in enumerate(rows)]
    ids = [v.observation_id for v in visits]
    if len(set(ids)) != len(ids):
        seen = set()
        twice = next(i for i in ids if i in seen or seen.add(i))
        raise InputError(f"{path} observationId", twice, "given to two visits")
    return tuple(sorted(visits, key=lambda v: (v.mjd_tai, v.observation_id)))


def visits_kind(path):
    """``"sqlite"`` or ``"csv"``: what the visits file ``path`` is, by its first bytes (a
    SQLite database) or its name (``.csv``); FileFormatError if it is missing, unreadable or
    neither."""
    if not os.path.isfile(path):
        raise FileFormatError(f"{path}: no such file (an opsim database or a CSV of visits)")
    try:
        with open(path, "rb") as stream:
            head = stream.read(16)
    except OSError as err:
        raise FileFormatError(f"{path}: cannot be read ({err.strerror or err})") from None
    if head.startswith(b"SQLite format 3"):
        return "sqlite"
    if path.lower().endswith(".csv"):
        return "csv"
    raise FileFormatError(f"{path}: neither a SQLite database nor a .csv file")


def open_observations(path, ordered=False):
    """An opsim database's ``observations`` table, opened read-only (a database given by
    mistake is never changed, nor created).

    Returns
    -------
    connection, columns, cursor
        The columns inject reads (:data:`REQUIRED`, :data:`OPTIONAL`, ``filter``) in the
        table's order, checked (:func:`column_names`), and a cursor over them, ``ordered`` by
        start time and id. The caller closes the connection.
    """
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise FileFormatError(f"{path}: cannot be opened as SQLite ({err})") from None
    try:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type IN "
                                            "('table', 'view')")}
        if "observations" not in tables:
            raise FileFormatError(f"{path}: has no 'observations' table (tables: "
                                  f"{', '.join(sorted(tables)) or 'none'}): not an opsim "
                                  f"database")
        cursor = con.execute("SELECT * FROM observations LIMIT 0")
        columns = [d[0] for d in cursor.description]
        wanted = [c for c in columns if c in REQUIRED + OPTIONAL + ("filter",)]
        column_names(path, wanted)
        order = " ORDER BY observationStartMJD, observationId" if ordered else ""
        cursor = con.execute(f"SELECT {', '.join(quote_column(c) for c in wanted)} "
                             f"FROM observations{order}")
    except sqlite3.Error as err:
        con.close()
        raise FileFormatError(f"{path}: not a readable SQLite database ({err})") from None
    except BaseException:
        con.close()
        raise
    return con, wanted, cursor


def _read_sqlite(path):
    con, wanted, cursor = open_observations(path)
    try:
        return wanted, cursor.fetchall()
    except sqlite3.Error as err:
        raise FileFormatError(f"{path}: not a readable SQLite database ({err})") from None
    finally:
        con.close()


def quote_column(name):
    """``name`` quoted as an SQL identifier."""
    return '"' + name.replace('"', '""') + '"'


def csv_rows(path):
    """A CSV of visits read as it is iterated: ``(header, iterator of rows)``, blank rows
    left out; FileFormatError for an unreadable or empty file and, as it is reached, a row
    whose fields are not the header's."""
    try:
        stream = open(path, newline="", encoding="utf-8")
    except OSError as err:
        raise FileFormatError(f"{path}: not a readable CSV ({err})") from None
    try:
        reader = csv.reader(stream)
        header = next(reader, None)
    except (UnicodeDecodeError, csv.Error) as err:
        stream.close()
        raise FileFormatError(f"{path}: not a readable CSV ({err})") from None
    if header is None:
        stream.close()
        raise FileFormatError(f"{path}: empty (a CSV of visits needs a header line)")
    header = [h.strip() for h in header]

    def rows():
        try:
            k = 0
            for row in reader:
                if not any(cell.strip() for cell in row):
                    continue
                k += 1
                if len(row) != len(header):
                    raise FileFormatError(f"{path}: row {k} has {len(row)} fields, the "
                                          f"header {len(header)}")
                yield row
        except (OSError, UnicodeDecodeError, csv.Error) as err:
            raise FileFormatError(f"{path}: not a readable CSV ({err})") from None
        finally:
            stream.close()

    return header, rows()


def _read_csv(path):
    header, rows = csv_rows(path)
    return header, list(rows)


def column_names(path, columns):
    """Which column gives each field (``band`` may come from ``filter``)."""
    names = {}
    for key in REQUIRED:
        if key in columns:
            names[key] = key
        elif key == "band" and "filter" in columns:
            names[key] = "filter"
        else:
            also = " (or filter)" if key == "band" else ""
            raise FileFormatError(f"{path}: no column {key}{also}; an opsim table needs "
                                  f"{', '.join(REQUIRED)}")
    for key in OPTIONAL:
        if key in columns:
            names[key] = key
    return names


def _number(path, k, column, value, kind=float):
    where = f"{path} row {k + 1} {column}"
    if isinstance(value, str):
        value = value.strip()
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(where, value, "must be a number") from None
    if not math.isfinite(number):
        raise InputError(where, value, "must be finite")
    if kind is int:
        if number != int(number):
            raise InputError(where, value, "must be an integer")
        return int(number)
    return number


def visit_from_row(path, k, row, names):
    """The :class:`Visit` of row ``k`` of ``path`` (``row``: column -> value; ``names``:
    :func:`column_names`'s), its values checked."""
    def get(key, kind=float):
        return _number(path, k, names[key], row[names[key]], kind)

    def optional(key):
        if key not in names:
            return None
        value = row[names[key]]
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        return get(key)

    band = row[names["band"]]
    band = band.strip() if isinstance(band, str) else band
    # A physical filter name (r_57) in the 'filter' column: its band is the first letter.
    if isinstance(band, str) and band not in BANDS and band[:1] in BANDS and band[1:2] in "_-":
        band = band[0]
    if band not in BANDS:
        raise InputError(f"{path} row {k + 1} {names['band']}", band,
                         f"not an LSST band ({' '.join(BANDS)})")
    dec = get("fieldDec")
    if abs(dec) > 90:
        raise InputError(f"{path} row {k + 1} fieldDec", dec, "must be within [-90, 90] deg")
    exptime = get("visitExposureTime")
    if not exptime > 0:
        raise InputError(f"{path} row {k + 1} visitExposureTime", exptime, "must be > 0 s")
    n_exp = optional("numExposures")
    n_exp = 1 if n_exp is None else _number(path, k, "numExposures", n_exp, int)
    if n_exp < 1:
        raise InputError(f"{path} row {k + 1} numExposures", n_exp, "must be >= 1")
    seeing = optional("seeingFwhmEff")
    if seeing is not None and not seeing > 0:
        raise InputError(f"{path} row {k + 1} seeingFwhmEff", seeing, "must be > 0 arcsec")
    visit_time = optional("visitTime")
    if visit_time is not None and not visit_time > 0:
        raise InputError(f"{path} row {k + 1} visitTime", visit_time, "must be > 0 s")
    mjd = get("observationStartMJD")
    check_mjd(f"{path} row {k + 1} observationStartMJD (visit {row[names['observationId']]})",
              mjd)
    rotation = get("rotSkyPos") % 360.0
    rotator, source = optional("rotTelPos"), "rotTelPos"
    if rotator is None:
        parallactic, source = optional("paraAngle"), "paraAngle"
        rotator = None if parallactic is None else rotator_angle(rotation, parallactic)
    return Visit(observation_id=get("observationId", int), mjd_tai=mjd,
                 ra_deg=get("fieldRA") % 360.0, dec_deg=dec, rotation_deg=rotation, band=band,
                 exptime_s=exptime, n_exposures=n_exp, seeing_fwhm_eff=seeing,
                 sky_brightness=optional("skyBrightness"), rotator_deg=rotator,
                 rotator_source=None if rotator is None else source,
                 visit_time_s=visit_time)


def rotator_angle(rot_sky_pos_deg, parallactic_deg):
    """rotTelPos from rotSkyPos and the parallactic angle, deg in [-180, 180).

    LSST's relation rotSkyPos = parallactic angle - rotTelPos - 90 deg, where the
    parallactic angle is the position angle of the zenith at the boresight, from north
    through east.
    """
    return float((parallactic_deg - rot_sky_pos_deg - 90.0 + 180.0) % 360.0 - 180.0)


def with_rotators(visits, site):
    """``visits`` with a rotator angle for each: those without one (no ``rotTelPos`` or
    ``paraAngle``) take it from the parallactic angle computed for their start
    (:func:`inject.orbits.passes.parallactic_angles`, :func:`rotator_angle`)."""
    out = list(visits)
    missing = [k for k, v in enumerate(out) if v.rotator_deg is None]
    if missing:
        from astropy.time import Time

        from inject.orbits.passes import parallactic_angles

        starts = Time([out[k].mjd_tai for k in missing], format="mjd", scale="tai")
        angles = parallactic_angles([out[k].ra_deg for k in missing],
                                    [out[k].dec_deg for k in missing], starts, site)
        for k, angle in zip(missing, angles):
            out[k] = replace(out[k], rotator_deg=rotator_angle(out[k].rotation_deg, angle),
                             rotator_source="computed")
    return out


def check_mjd(name, mjd):
    """Refuse (InputError) an MJD outside :data:`MJD_RANGE` (1900-2100)."""
    if not MJD_RANGE[0] <= mjd < MJD_RANGE[1]:
        year = 1858.87 + mjd / 365.25
        hint = " (a JD instead of an MJD?)" if mjd > 2400000.5 else ""
        raise InputError(name, mjd, f"is the year {year:.0f}, outside 1900-2100{hint}")


def select_visits(visits, job=None, njobs=None):
    """The ``job``-th of ``njobs`` interleaved slices of the visits (all without a job).

    Raises
    ------
    InputError
        ``job`` without ``njobs`` (or the reverse), ``njobs`` < 1, ``job`` outside
        ``0 .. njobs - 1``.
    """
    if job is None and njobs is None:
        return tuple(visits)
    if job is None or njobs is None:
        raise InputError("--job/--njobs", (job, njobs), "give both, or neither")
    if njobs < 1:
        raise InputError("--njobs", njobs, "must be >= 1")
    if not 0 <= job < njobs:
        raise InputError("--job", job, f"must be in 0 .. {njobs - 1}")
    return tuple(visits[job::njobs])


def local_hours(mjd_tai, site_lon_deg):
    """Hours of local mean solar time at start MJDs (TAI) (0-24, wrapping past midnight into
    24-36 for a night that starts in the evening): UTC plus the site's east longitude over 15
    deg an hour."""
    import warnings

    from astropy.time import Time
    from erfa import ErfaWarning

    mjd_tai = np.asarray(mjd_tai, float)
    if not mjd_tai.size:
        return np.array([])
    with warnings.catch_warnings():
        # A year past the leap-second table's: UTC is taken as TAI - 37 s.
        warnings.simplefilter("ignore", ErfaWarning)
        mjd = Time(mjd_tai, format="mjd", scale="tai").utc.mjd
    local = (np.asarray(mjd, float) + site_lon_deg / 360.0) % 1.0 * 24.0
    # Evening hours stay as they are; the morning after midnight continues past 24.
    return np.where(local < 12.0, local + 24.0, local)
