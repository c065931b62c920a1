"""The visits of a survey of any length, read night by night (:class:`VisitSource`).

A survey's *night* is the local date at the site at the evening, noon to noon in local mean
solar time: :func:`night_of` of a visit's ``observationStartMJD`` (as given, TAI) and the
site's east longitude, ``floor(mjd + lon / 360 - 0.5)``, the MJD of that evening's date. At
Rubin (70.75 deg W) a night runs from 16:43 to 16:43 UTC; TAI's 37 s on UTC only move the
noon by 37 s. Every part of ``inject survey`` takes the night from this one function: the
grouping, the ``--job`` slices, the files under ``nights/`` and ``summary.json``'s years.
An opsim database's own ``night`` column (nights since the survey's start, by the scheduler's
own rule) is not read.

Reading is in two passes, neither holding the survey. The first (:class:`VisitSource`'s
constructor) checks every row as :func:`inject.survey.visits.read_visits` does, so that a bad
value anywhere is a one-line error before any work, and keeps the night of each visit only as
counts per night (while it reads, each visit's night and id, 16 bytes a visit, for the counts
and the check that no id is given twice). The
second (:meth:`VisitSource.nights`) yields one night's visits at a time: from SQLite through
one cursor ordered by start time, from a CSV in one pass over its lines when they are in night
order (the scheduler's order). A CSV whose nights are out of order is read whole instead (a
log line says so: such a file is a hand-made one, small).
"""
import logging
import math
import os
import sqlite3
from dataclasses import dataclass

import numpy as np

from inject.errors import FileFormatError, InputError
from inject.survey.visits import (
    column_names,
    csv_rows,
    open_observations,
    visit_from_row,
    visits_kind,
)

log = logging.getLogger(__name__)

#: Rows fetched from SQLite at a time.
FETCH_ROWS = 20_000
#: Visits named in a fallback warning.
NAMED = 5


def night_of(mjd, lon_deg):
    """The night of visits starting at ``mjd`` (MJD as given, TAI): the MJD of the local
    date at the evening, noon to noon in local mean solar time at east longitude
    ``lon_deg`` (module notes).

    Parameters
    ----------
    mjd : float or array_like
    lon_deg : float

    Returns
    -------
    int or ndarray of int64
    """
    if isinstance(mjd, (float, int)):  # a visit's: math's floor, the same arithmetic
        return math.floor(mjd + lon_deg / 360.0 - 0.5)
    value = np.floor(np.asarray(mjd, float) + lon_deg / 360.0 - 0.5).astype(np.int64)
    return int(value) if value.ndim == 0 else value


def night_label(night):
    """A night's date, ``YYYY-MM-DD`` (the evening's)."""
    from datetime import date, timedelta

    return (date(1858, 11, 17) + timedelta(days=int(night))).isoformat()


def year_of(night):
    """The calendar year of a night's evening."""
    return int(night_label(night)[:4])


@dataclass
class _Fallback:
    """Visits of the first pass without a column the plan can default (for the warning)."""

    count: int = 0
    named: tuple = ()

    def add(self, visit_id):
        self.count += 1
        if len(self.named) < NAMED:
            self.named = self.named + (visit_id,)


class VisitSource:
    """The visits of an opsim database (SQLite) or CSV, by night (module notes).

    Parameters
    ----------
    path : str or os.PathLike
    lon_deg : float
        The site's east longitude, deg (:func:`night_of`).

    Attributes
    ----------
    path : str
    nights : ndarray of int64
        The nights with visits, in order.
    counts : ndarray of int64
        Visits of each night.
    first, last : inject.survey.visits.Visit
        The first and the last visit (start time, then id).
    missing_seeing, missing_sky : _Fallback
        Visits without ``seeingFwhmEff`` / ``skyBrightness`` (count, the first ids).

    Raises
    ------
    FileFormatError, InputError
        As :func:`inject.survey.visits.read_visits`.
    """

    def __init__(self, path, lon_deg):
        path = os.fspath(path)
        self.path, self.lon_deg = path, float(lon_deg)
        self.kind = visits_kind(path)
        self.missing_seeing, self.missing_sky = _Fallback(), _Fallback()
        self._index()

    # --- the first pass ---------------------------------------------------------------------

    def _index(self):
        nights, ids = [], []  # chunks as arrays: 16 bytes a visit
        chunk_nights, chunk_ids = [], []
        first = last = None
        self.ordered, previous = True, None
        for visit in self._checked():
            night = night_of(visit.mjd_tai, self.lon_deg)
            if previous is not None and night < previous:
                self.ordered = False
            previous = night
            chunk_nights.append(night)
            chunk_ids.append(visit.observation_id)
            key = (visit.mjd_tai, visit.observation_id)
            if first is None or key < (first.mjd_tai, first.observation_id):
                first = visit
            if last is None or key > (last.mjd_tai, last.observation_id):
                last = visit
            if visit.seeing_fwhm_eff is None:
                self.missing_seeing.add(visit.observation_id)
            if visit.sky_brightness is None:
                self.missing_sky.add(visit.observation_id)
            if len(chunk_nights) >= FETCH_ROWS:
                nights.append(np.array(chunk_nights, np.int64))
                ids.append(np.array(chunk_ids, np.int64))
                chunk_nights, chunk_ids = [], []
        nights.append(np.array(chunk_nights, np.int64))
        ids.append(np.array(chunk_ids, np.int64))
        nights, ids = np.concatenate(nights), np.concatenate(ids)
        if not nights.size:
            raise InputError("VISITS", self.path, "holds no visit (an empty night)")
        order = np.argsort(ids, kind="stable")
        twice = np.flatnonzero(ids[order][1:] == ids[order][:-1])
        if twice.size:  # the id whose second use comes first in the file
            raise InputError(f"{self.path} observationId", int(ids[order[twice + 1].min()]),
                             "given to two visits")
        self.nights, self.counts = np.unique(nights, return_counts=True)
        self.first, self.last = first, last
        self.total = int(self.counts.sum())

    def _checked(self):
        """Every row as a Visit, in the file's order (checked as read_visits checks them)."""
        columns, rows = self._rows(ordered=False)
        names = column_names(self.path, columns)
        for k, row in enumerate(rows):
            yield visit_from_row(self.path, k, dict(zip(columns, row)), names)

    # --- the rows -------------------------------------------------------------------------------

    def _rows(self, ordered):
        """``(columns, iterator of rows)``; SQLite ``ordered`` by start time and id."""
        if self.kind == "sqlite":
            return self._sqlite_rows(ordered)
        return self._csv_rows()

    def _sqlite_rows(self, ordered):
        path = self.path
        con, wanted, cursor = open_observations(path, ordered)

        def rows():
            try:
                while True:
                    batch = cursor.fetchmany(FETCH_ROWS)
                    if not batch:
                        return
                    yield from batch
            except sqlite3.Error as err:
                raise FileFormatError(f"{path}: not a readable SQLite database ({err})") \
                    from None
            finally:
                con.close()

        return wanted, rows()

    def _csv_rows(self):
        return csv_rows(self.path)

    # --- the second pass ------------------------------------------------------------------------

    def nights_visits(self, wanted=None):
        """Yield ``(night, visits)`` for each night in order (only those in ``wanted``, a set
        of nights, if given), the visits in start order (then id); no other night's visits
        are made."""
        columns, rows = self._rows(ordered=True)
        names = column_names(self.path, columns)
        at = columns.index(names["observationStartMJD"])
        if self.kind == "csv" and not self.ordered:
            log.info("%s: its nights are not in order; read whole (sort it by "
                     "observationStartMJD to read it night by night)", self.path)
            groups = {}
            for k, row in enumerate(rows):
                night = night_of(float(row[at]), self.lon_deg)
                if wanted is None or night in wanted:
                    groups.setdefault(night, []).append(
                        visit_from_row(self.path, k, dict(zip(columns, row)), names))
            for night in sorted(groups):
                yield night, _in_order(groups[night])
            return
        current, group = None, []
        for k, row in enumerate(rows):
            night = night_of(float(row[at]), self.lon_deg)
            if night != current:
                if group:
                    yield current, _in_order(group)
                current, group = night, []
            if wanted is None or night in wanted:
                group.append(visit_from_row(self.path, k, dict(zip(columns, row)), names))
        if group:
            yield current, _in_order(group)


def _in_order(visits):
    return tuple(sorted(visits, key=lambda v: (v.mjd_tai, v.observation_id)))


def select_nights(nights, job=None, njobs=None):
    """The ``job``-th of ``njobs`` interleaved slices of the ``nights`` (all without a job):
    every ``njobs``-th night from the ``job``-th.

    Raises
    ------
    InputError
        As :func:`inject.survey.visits.select_visits`.
    """
    from inject.survey.visits import select_visits

    return np.asarray(select_visits(list(nights), job, njobs), np.int64)


def sun_altitudes(visits, site):
    """The Sun's altitude at each visit's start, deg (astropy, geometric: no refraction),
    one vectorised call for the visits (a night's). Beyond the bundled IERS table the Earth's
    orientation is extrapolated, as the orbits' frames take it (a warning said there)."""
    if not len(visits):
        return np.zeros(0)
    import warnings

    from astropy.coordinates import AltAz, get_sun
    from astropy.time import Time
    from erfa import ErfaWarning

    from inject.orbits.passes import earth_orientation

    times = Time([v.mjd_tai for v in visits], format="mjd", scale="tai")
    with earth_orientation(times), warnings.catch_warnings():
        # A year past the leap-second table's: UTC is taken as TAI - 37 s (a second at most).
        warnings.simplefilter("ignore", ErfaWarning)
        sun = get_sun(times).transform_to(AltAz(obstime=times, location=site.location))
    return np.asarray(sun.alt.deg, float)


#: Sun-altitude bins of summary.json's ``by_sun_alt``: name, lower and upper bound (deg).
SUN_ALT_BINS = (("above_-12", -12.0, math.inf), ("-18_to_-12", -18.0, -12.0),
                ("below_-18", -math.inf, -18.0))


def sun_alt_bins(alt_deg):
    """The index in :data:`SUN_ALT_BINS` of each Sun altitude (a bin holds its lower bound;
    NaN is above every bound)."""
    alt = np.asarray(alt_deg, float)
    return (alt < SUN_ALT_BINS[1][2]).astype(int) + (alt < SUN_ALT_BINS[2][2])
