"""A survey planned night by night: each night's tables as Parquet files as it finishes, a
manifest of the nights done, and the run's combined outputs made from those files.

Under OUTDIR/:data:`NIGHTS_DIR`, every night planned leaves ``visits-YYYY-MM-DD.parquet``
and ``streaks-YYYY-MM-DD.parquet`` (the night's rows of ``visits.csv`` and ``streaks.csv``,
:func:`night_tables`; the visits' rows with the night and the Sun's altitude at the start),
each written whole or not at all (:func:`inject.io.atomic.atomic_path`), and then an entry in
the slice's manifest (:class:`NightManifest`, ``manifest.json`` or
``manifest-jobJ-of-N.json``): the night, its visits and streaks, and each file's name and
SHA-256. A night is done when its entry is there and its files still have those digests; a
stopped run rerun as typed plans only the nights not done.

The run's ``visits.csv``, ``streaks.csv`` (:data:`CSV_AUTO_VISITS`), ``summary.json`` and
plots are then made from the nights' files alone (:func:`summary_from_tables`), never from
what this process happened to plan, so that a run stopped and resumed writes the same bytes
as one that was not. The times a run took are the one thing that differs:
``summary.json``'s ``timings``.
"""
import json
import logging
import math
import os

import numpy as np

from inject.errors import OutputError
from inject.io.atomic import atomic_path
from inject.survey.nights import SUN_ALT_BINS, night_label, sun_altitudes
from inject.survey.visits import local_hours

log = logging.getLogger(__name__)

#: Folder of the nights' files under OUTDIR.
NIGHTS_DIR = "nights"
#: ``--csv auto`` writes the combined CSV files for runs of at most this many visits (about
#: three months of LSST; a year's visits.csv would be ~80 MB).
CSV_AUTO_VISITS = 100_000
#: Columns the nights' visit tables add to :data:`inject.survey.plan.VISIT_FIELDS`.
NIGHT_VISIT_FIELDS = ("night", "sun_alt_deg")
#: HEALPix resolution of the sky map (``nside`` 16: pixels of 3.7 deg, about a field's
#: width, so that a survey's visits tile it).
SKY_NSIDE = 16

#: Columns of the tables that are not floats.
_INTEGERS = {"observationId", "n_streaks", "n_ccds_streaked", "pixels_lost", "n_candidates",
             "pixels_fixed_mask", "n_ccds", "sunlit_parts"}
_STRINGS = {"band", "satellite", "ccds", "night", "rule"}


def _schema(fields):
    import pyarrow as pa

    return pa.schema([(f, pa.int64() if f in _INTEGERS else pa.string() if f in _STRINGS
                       else pa.float64()) for f in fields])


def _table(rows, fields):
    """A pyarrow Table of ``rows`` (dicts) with the columns ``fields``, None as null."""
    import pyarrow as pa

    schema = _schema(fields)
    return pa.Table.from_arrays(
        [pa.array([r[f] for r in rows], type=schema.field(f).type) for f in fields],
        schema=schema)


def fields(fixed):
    """The columns of the visits' and the streaks' tables (``fixed``: with ``--mask-width``)."""
    from inject.survey.plan import (
        FIXED_STREAK_FIELDS,
        FIXED_VISIT_FIELDS,
        STREAK_FIELDS,
        VISIT_FIELDS,
    )

    visits = VISIT_FIELDS + (FIXED_VISIT_FIELDS if fixed else ()) + NIGHT_VISIT_FIELDS
    return visits, STREAK_FIELDS + (FIXED_STREAK_FIELDS if fixed else ())


def plan_night(constellation, visits, site=None, progress=None, **options):
    """Plan one night's visits (:func:`inject.survey.plan.plan_visits`, one prefilter for the
    night) and the Sun's altitude at each start.

    Parameters
    ----------
    constellation : inject.survey.constellation.Constellation or str
        Or its file, read once per process (a worker's task).
    visits : sequence of inject.survey.visits.Visit
        The night's, in start order.
    site : inject.orbits.passes.Site, optional
        Rubin by default.
    progress : callable, optional
        Called after each visit.
    **options
        Passed to :func:`~inject.survey.plan.plan_visits` (``fixed_width_px``); with
        ``rule="rubin_sim"``, to :func:`inject.survey.rubin_rule.plan_visits` (``width_px``).

    Returns
    -------
    plans : list of inject.survey.plan.VisitPlan
    sun_alt_deg : ndarray
    """
    import warnings

    from inject.errors import OrbitWarning
    from inject.orbits.passes import RUBIN
    from inject.survey import plan, rubin_rule

    rule = options.pop("rule", "inject")
    plan_visits = rubin_rule.plan_visits if rule == "rubin_sim" else plan.plan_visits
    site = RUBIN if site is None else site
    if isinstance(constellation, str):
        from inject.survey.constellation import read_constellation_once

        constellation = read_constellation_once(constellation)
    with warnings.catch_warnings():
        # An epoch's warning is said once, for the survey (check_epochs).
        warnings.simplefilter("ignore", OrbitWarning)
        plans = plan_visits(visits, constellation, site, progress=progress, **options)
        return plans, sun_altitudes(visits, site)


def night_tables(night, plans, sun_alt_deg, fixed):
    """The night's visits and streaks as pyarrow Tables (:func:`fields`)."""
    visit_fields, streak_fields = fields(fixed)
    label = night_label(night)
    visits = [{**p.visit_row(), "night": label, "sun_alt_deg": float(alt)}
              for p, alt in zip(plans, sun_alt_deg)]
    streaks = [row for p in plans for row in p.streak_rows()]
    return _table(visits, visit_fields), _table(streaks, streak_fields)


def night_paths(outdir, night):
    """``{kind: path}`` of a night's Parquet files."""
    label = night_label(night)
    return {kind: os.path.join(outdir, NIGHTS_DIR, f"{kind}-{label}.parquet")
            for kind in ("visits", "streaks")}


def write_parquet(table, path):
    """``table`` to ``path``, whole or not at all (replacing a file there)."""
    import pyarrow.parquet as pq

    os.makedirs(os.path.dirname(path), exist_ok=True)
    with atomic_path(path, True) as tmp:
        pq.write_table(table, tmp)


class NightManifest:
    """The nights a run's slice has done (module notes): ``nights/manifest.json`` (or
    ``manifest-jobJ-of-N.json``), rewritten whole after each night.

    Parameters
    ----------
    outdir : str
    key : str
        The run's key (:func:`inject.survey.outputs.claim_outdir`): the entries of a manifest
        with another key are not this run's.
    job, njobs : int or None
    version : str, optional
        inject's version (default: this one's): nights planned by another version are
        planned again, never mixed with this one's.
    """

    def __init__(self, outdir, key, job=None, njobs=None, version=None):
        if version is None:
            from inject import __version__ as version
        self.outdir, self.key, self.version = outdir, key, version
        name = "manifest.json" if job is None else f"manifest-job{job}-of-{njobs}.json"
        self.path = os.path.join(outdir, NIGHTS_DIR, name)
        self.entries = {}

    def load(self):
        """The entries recorded by this run (none from another run's or an unreadable
        manifest)."""
        try:
            with open(self.path, encoding="utf-8") as stream:
                data = json.load(stream)
        except (OSError, ValueError):
            return self
        if not isinstance(data, dict) or data.get("key") != self.key:
            return self
        if data.get("inject_version") != self.version:
            log.info("%s: its nights were planned by inject %s, not %s: planned again",
                     self.path, data.get("inject_version"), self.version)
            return self
        self.entries = {int(e["mjd"]): e for e in data.get("nights", [])}
        return self

    def done(self, nights):
        """Those of ``nights`` whose entry is here and whose files have its SHA-256."""
        from inject.exposure.runner import sha256_file

        out = set()
        for night in nights:
            entry = self.entries.get(int(night))
            if entry is None:
                continue
            try:
                same = all(sha256_file(os.path.join(self.outdir, f["path"])) == f["sha256"]
                           for f in entry["files"].values())
            except OSError:
                same = False
            if same:
                out.add(int(night))
        return out

    def add(self, night, visits, streaks, paths, fallbacks):
        """Record a night whose files ``paths`` (``{kind: path}``) are written, with its
        visits' count, its streaks' and its visits' :func:`inject.survey.plan.fallbacks`, and
        write the manifest."""
        from inject.exposure.runner import sha256_file

        files = {kind: {"path": os.path.relpath(path, self.outdir),
                        "sha256": sha256_file(path)} for kind, path in paths.items()}
        self.entries[int(night)] = {"night": night_label(night), "mjd": int(night),
                                    "visits": int(visits), "streaks": int(streaks),
                                    "files": files, "fallbacks": fallbacks}
        lines = ",\n".join(json.dumps(self.entries[n], sort_keys=True)
                           for n in sorted(self.entries))
        text = (f'{{"key": {json.dumps(self.key)}, "inject_version": '
                f'{json.dumps(self.version)}, "nights": [\n{lines}\n]}}\n')
        with atomic_path(self.path, True) as tmp:
            with open(tmp, "w", encoding="utf-8") as stream:
                stream.write(text)


def read_nights(outdir, nights, kind, columns=None):
    """The ``kind`` (``visits`` or ``streaks``) tables of ``nights`` as one pyarrow Table, in
    night order (only ``columns``, if given)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    tables = [pq.read_table(night_paths(outdir, n)[kind], columns=columns) for n in nights]
    return pa.concat_tables(tables) if tables else None


# --- the summary from the tables ------------------------------------------------------------

def _distribution(values):
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    q = np.percentile(values, [0, 10, 50, 90, 100])
    return {"min": float(q[0]), "p10": float(q[1]), "median": float(q[2]),
            "p90": float(q[3]), "max": float(q[4]), "mean": float(values.mean())}


def _totals(visits, streaks, total_pixels):
    """Counts, pixel fractions and the streaks' distributions of the visits' and streaks'
    columns (dicts of arrays, the rows chosen)."""
    counts = np.asarray(visits["n_streaks"], float)
    lost = np.asarray(visits["pixels_lost"], float)
    n = counts.size
    fraction = lost / total_pixels
    return {
        "visits": n,
        "streaked_visits": int(np.count_nonzero(counts)),
        "streaked_fraction": float(np.count_nonzero(counts) / n) if n else None,
        "streaks": int(len(streaks["fwhm_arcsec"])),
        "streaks_per_visit": float(counts.mean()) if n else None,
        "pixels_lost": int(lost.sum()),
        "pixel_fraction_lost_total": float(lost.sum() / (n * total_pixels)) if n else None,
        "pixel_fraction_lost_median": float(np.median(fraction)) if n else None,
        "pixel_fraction_lost_max": float(fraction.max()) if n else None,
        "pixel_fraction_lost_median_streaked": (float(np.median(fraction[counts > 0]))
                                                if counts.any() else None),
        **{key: _distribution(streaks[key]) for key in
           ("fwhm_arcsec", "mask_width_px", "peak_e_per_px", "mag", "length_deg")},
    }


#: The visits' and streaks' columns the summary and the plots read.
SUMMARY_VISIT_COLUMNS = ("observationId", "mjd", "band", "n_streaks", "pixels_lost", "night",
                         "sun_alt_deg", "fieldRA", "fieldDec")
SUMMARY_STREAK_COLUMNS = ("observationId", "fwhm_arcsec", "mask_width_px", "peak_e_per_px",
                          "mag", "length_deg")


def columns_of(table):
    """``{column: ndarray}`` of a pyarrow Table (null as NaN in a number column); the
    ``night`` column (``YYYY-MM-DD``) as ``year`` (int), a string a visit being 60 bytes."""
    import pyarrow as pa
    import pyarrow.compute as pc

    out = {}
    for name in table.column_names:
        column = table.column(name)
        if name == "night":
            out["year"] = pc.cast(pc.utf8_slice_codeunits(column, 0, 4),
                                  pa.int64()).to_numpy(zero_copy_only=False)
        elif column.type in ("string", "large_string"):
            out[name] = np.asarray(column.to_pylist(), object)
        else:
            out[name] = column.to_numpy(zero_copy_only=False)
    return out


def summary_from_tables(visits, streaks, about, fallbacks, site_lon_deg, fixed_width_px=None):
    """The ``summary.json`` mapping of a run's tables (``{column: ndarray}``, visits in
    start order): ``about`` (the inputs, for the record), the totals and distributions of
    :func:`_totals`, the visits whose seeing or sky came from a default (``fallbacks``), with
    a fixed width its ``fixed_mask`` block, and the same totals ``by_band``, ``by_hour``
    (local mean solar time, :func:`inject.survey.visits.local_hours`), ``by_year`` (the
    calendar year of the visit's night's evening) and ``by_sun_alt`` (the Sun's altitude at
    the visit's start: :data:`~inject.survey.nights.SUN_ALT_BINS`).

    Parameters
    ----------
    visits, streaks : dict of ndarray
        :data:`SUMMARY_VISIT_COLUMNS` and :data:`SUMMARY_STREAK_COLUMNS` as
        :func:`columns_of` gives them (the night as its ``year``; and ``pixels_fixed_mask``
        of the visits with a fixed width).
    about : dict
        The inputs, first in the mapping.
    fallbacks : dict
        :func:`inject.survey.plan.fallbacks` of the visits.
    site_lon_deg : float
    fixed_width_px : float or None
        ``--mask-width``'s width, px.
    """
    from inject.survey.nights import sun_alt_bins
    from inject.survey.plan import TOTAL_PIXELS

    ids = np.asarray(visits["observationId"])
    order = np.argsort(ids, kind="stable")
    # Each streak's visit (its row in the visits' table).
    row = order[np.searchsorted(ids, np.asarray(streaks["observationId"]), sorter=order)] \
        if len(streaks["observationId"]) else np.zeros(0, int)

    def chosen(mask):
        mask = np.asarray(mask, bool)
        return ({k: v[mask] for k, v in visits.items()},
                {k: v[mask[row]] for k, v in streaks.items()})

    out = {**about, "total_pixels_per_visit": TOTAL_PIXELS,
           **_totals(visits, streaks, TOTAL_PIXELS), "fallbacks": fallbacks}
    if fixed_width_px is not None:
        from inject.instrument import LSST

        band = np.asarray(visits["pixels_fixed_mask"], float)
        physical = np.asarray(visits["pixels_lost"], float)
        streaked = np.asarray(visits["n_streaks"]) > 0
        out["fixed_mask"] = {
            **about.get("fixed_mask", {}),
            "width_px": fixed_width_px,
            "width_arcsec": fixed_width_px * LSST.pixel_scale_arcsec,
            "pixels_lost": int(band.sum()),
            "pixel_fraction_lost_total": float(band.sum() / (band.size * TOTAL_PIXELS)),
            "pixel_fraction_lost_median_streaked": (
                float(np.median(band[streaked]) / TOTAL_PIXELS) if streaked.any() else None),
            "pixels_lost_physical": int(physical.sum()),
            "ratio_to_physical": (float(band.sum() / physical.sum()) if physical.sum()
                                  else None)}
    bands = visits["band"]
    out["by_band"] = {b: _totals(*chosen(bands == b), TOTAL_PIXELS)
                      for b in sorted(set(bands), key="ugrizy".index)}
    hours = local_hours(visits["mjd"], site_lon_deg).astype(int)
    out["by_hour"] = {f"{h % 24:02d}": _totals(*chosen(hours == h), TOTAL_PIXELS)
                      for h in sorted(set(hours.tolist()))}
    years = np.asarray(visits["year"], int)
    out["by_year"] = {str(y): _totals(*chosen(years == y), TOTAL_PIXELS)
                      for y in sorted(set(years.tolist()))}
    bins = sun_alt_bins(visits["sun_alt_deg"])
    out["by_sun_alt"] = {name: _totals(*chosen(bins == k), TOTAL_PIXELS)
                         for k, (name, _, _) in enumerate(SUN_ALT_BINS) if (bins == k).any()}
    return out


def add_fallbacks(total, night):
    """``total`` (:func:`inject.survey.plan.fallbacks`, or None) plus a night's."""
    if total is None:
        return json.loads(json.dumps(night))
    for key in ("visits_default_seeing", "visits_model_sky"):
        total[key] += night[key]
    for key in ("visits_rotator_from", "visits_span_from"):  # the latter: the rubin_sim rule's
        for source, count in night.get(key, {}).items():
            total.setdefault(key, {})
            total[key][source] = total[key].get(source, 0) + count
    return total


def check_nights(outdir, manifest, nights):
    """Refuse (OutputError) to make the run's outputs from a night not recorded as done."""
    missing = [n for n in nights if int(n) not in manifest.entries]
    if missing:
        raise OutputError(f"{os.path.join(outdir, NIGHTS_DIR)}: night "
                          f"{night_label(missing[0])} is not done ({len(missing)} missing)")


def plot_bins(path, summary_map, key, title, overwrite=True):
    """A bar plot of ``summary_map[key]``'s bins (``by_year``, ``by_sun_alt``): the fraction
    of visits streaked and the pixel fraction lost in each."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    bins = summary_map[key]
    names = list(bins)
    fig = Figure(figsize=(8, 4))
    FigureCanvasAgg(fig)
    left = fig.add_axes([0.09, 0.2, 0.36, 0.68])
    right = fig.add_axes([0.6, 0.2, 0.36, 0.68])
    x = np.arange(len(names))
    for ax, field, label in ((left, "streaked_fraction", "fraction of visits streaked"),
                             (right, "pixel_fraction_lost_total", "pixel fraction lost")):
        values = [bins[n][field] or 0.0 for n in names]
        ax.bar(x, values, color="#0072b2")
        ax.set_xticks(x)
        ax.set_xticklabels(names, fontsize=7, rotation=30 if len(names) > 4 else 0)
        ax.set_ylabel(label, fontsize=8)
        ax.tick_params(labelsize=7)
        for k, n in enumerate(names):  # above each bar, however short
            ax.annotate(f"{bins[n]['visits']:,}", (k, values[k]), xytext=(0, 2),
                        textcoords="offset points", ha="center", fontsize=6)
        ax.margins(y=0.1)
    fig.suptitle(f"{title} (visits above each bar)", fontsize=9)
    with atomic_path(path, overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def healpix_fraction(ra_deg, dec_deg, fraction, nside=SKY_NSIDE):
    """The pixel fraction lost on a HEALPix map (healpy, RING order): in each HEALPix pixel,
    the mean over the visits whose boresight falls in it; NaN where none does. None without
    healpy."""
    try:
        import healpy as hp
    except ImportError:
        return None
    pixel = hp.ang2pix(nside, np.asarray(ra_deg, float), np.asarray(dec_deg, float),
                       lonlat=True)
    npix = hp.nside2npix(nside)
    visits = np.bincount(pixel, minlength=npix).astype(float)
    lost = np.bincount(pixel, weights=np.asarray(fraction, float), minlength=npix)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(visits > 0, lost / visits, math.nan)
