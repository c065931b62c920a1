"""What ``inject survey`` writes: ``streaks.csv``, ``visits.csv``, ``summary.json`` and the
plots, all or none of them (:func:`inject.io.atomic.output_group`); a run of many nights
writes them from its nights' files (:mod:`inject.survey.stream`, :func:`write_run_outputs`).

``streaks.csv`` has one row per visit and satellite whose sunlit streak crosses a science CCD
(:data:`inject.survey.plan.STREAK_FIELDS`), ``visits.csv`` one row per visit, streaked or not
(:data:`inject.survey.plan.VISIT_FIELDS`). ``summary.json`` holds the totals, the
distributions of FWHM and mask width over the streaks, and the same per band and per hour of
the night (local mean solar time at the site), and for a run of nights per year and per
altitude of the Sun. The plots: streaks per visit through the night
(``streaks_per_visit.png``), the pixel fraction lost per visit (``pixel_fraction.png``), a
sky map of it (``sky_map.png``, a HEALPix map with healpy), and per year and Sun altitude
(``by_year.png``, ``by_sun_alt.png``).

A ``--job J --njobs N`` slice writes the same files with ``-jobJ-of-N`` before the extension,
so that the slices of a night can share one folder. A run claims its folder before any work
(:func:`claim_outdir`, the file :data:`CLAIM`, keyed on the run's inputs and options): the
slices of one run share the claim, another run is refused unless it overwrites, and then
the earlier run's files that this run does not write are removed (:func:`remove_earlier`).

Numbers are written as Python's ``repr`` of the float, the shortest text that reads back as
the same float.
"""
import contextlib
import csv
import io
import json
import math
import os
import re
import shutil

import numpy as np

from inject.errors import OutputError
from inject.io.atomic import atomic_path, output_group

#: Files of a run, by kind (the plots last).
NAMES = {"streaks": "streaks.csv", "visits": "visits.csv", "summary": "summary.json",
         "night": "streaks_per_visit.png", "fraction": "pixel_fraction.png",
         "sky": "sky_map.png", "year": "by_year.png", "sun": "by_sun_alt.png"}
#: The tables among :data:`NAMES` (``--csv``) and the plots.
TABLES = ("streaks", "visits")
PLOTS = ("night", "fraction", "sky", "year", "sun")


def output_paths(outdir, job=None, njobs=None):
    """``{kind: path}`` of a run's files (a job's carry its slice in their names)."""
    out = {}
    for kind, name in NAMES.items():
        if job is not None:
            stem, ext = os.path.splitext(name)
            name = f"{stem}-job{job}-of-{njobs}{ext}"
        out[kind] = os.path.join(outdir, name)
    return out


def _cell(value):
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return "" if not math.isfinite(value) else repr(value)
    return value


def csv_text(rows, fields):
    """CSV text of ``rows`` (dicts) with the columns ``fields``; NaN and None as empty."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fields, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row[k]) for k in fields})
    return text.getvalue()


def write_run_outputs(paths, summary_map, tables=None, plot_data=None, overwrite=False,
                      measured=None, extra_fields=()):
    """Write a night-by-night run's files together (or none: an output group): its
    summary.json; with ``tables`` (``(visits, streaks)``, pyarrow Tables), visits.csv and
    streaks.csv; with ``plot_data`` (:func:`write_visit_plots`'s), the plots, the per-year and
    per-Sun-altitude ones from ``summary_map``.

    ``measured`` (``--render``): ``{(observationId, satellite): {column: value}}`` of the
    measured columns ``extra_fields``, added to the streaks' rows after the planned ones.
    Returns ``{kind: path}`` of the files written.
    """
    from inject.survey.stream import plot_bins

    wanted = {"summary": paths["summary"]}
    if tables is not None:
        wanted.update({k: paths[k] for k in TABLES})
    if plot_data is not None:
        wanted.update({k: paths[k] for k in PLOTS})
    with output_group(list(wanted.values()), overwrite):
        if tables is not None:
            visits, streaks = tables
            rows = streaks.to_pylist()
            if measured is not None:
                rows = [{**row, **dict.fromkeys(extra_fields),
                         **measured.get((row["observationId"], row["satellite"]), {})}
                        for row in rows]
            _write_text(paths["streaks"], csv_text(rows, streaks.column_names +
                                                   list(extra_fields)), overwrite)
            _write_text(paths["visits"], csv_text(visits.to_pylist(), visits.column_names),
                        overwrite)
        _write_text(paths["summary"], json.dumps(summary_map, indent=1) + "\n", overwrite)
        if plot_data is not None:
            write_visit_plots(paths, plot_data, overwrite)
            plot_bins(paths["year"], summary_map, "by_year", "per year (of the night's "
                      "evening)", overwrite)
            plot_bins(paths["sun"], summary_map, "by_sun_alt", "per altitude of the Sun at "
                      "the visit's start (deg)", overwrite)
    return wanted


def _write_text(path, text, overwrite):
    with atomic_path(path, overwrite) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as stream:
            stream.write(text)


def write_visit_plots(paths, data, overwrite=False):
    """Streaks per visit against the hour of the night, the pixel fraction lost per visit,
    and the sky map of the pixel fraction lost (a HEALPix map,
    :func:`inject.survey.stream.healpix_fraction`, or without healpy the visits coloured by
    it).

    Parameters
    ----------
    paths : dict
        :func:`output_paths`.
    data : dict
        Per visit: ``hours`` (:func:`inject.survey.visits.local_hours`), ``n_streaks``,
        ``fraction`` (of the pixels lost), ``band``, ``ra`` and ``dec`` (deg).
    overwrite : bool
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    hours = np.asarray(data["hours"], float)
    counts = np.asarray(data["n_streaks"])
    fraction = np.asarray(data["fraction"], float)
    bands = np.asarray(data["band"], object)
    colours = dict(zip("ugrizy", ("#56b4e9", "#009e73", "#e69f00", "#d55e00", "#cc79a7",
                                  "#000000")))

    def figure():
        fig = Figure(figsize=(8, 4))
        FigureCanvasAgg(fig)
        # The legend goes right of the axes, where it covers no visit.
        return fig, fig.add_axes([0.1, 0.14, 0.8, 0.78])

    def hour_axis(ax):
        ticks = np.arange(np.floor(hours.min()), np.ceil(hours.max()) + 1) if len(hours) \
            else np.arange(18, 31)
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{int(t) % 24:02d}" for t in ticks], fontsize=7)
        ax.set_xlabel("local mean solar time at the site (h)")

    for kind, values, label in (("night", counts, "streaks per visit"),
                                ("fraction", fraction, "pixel fraction lost per visit")):
        fig, ax = figure()
        for b in "ugrizy":
            sel = bands == b
            if sel.any():
                ax.plot(hours[sel], values[sel], "o", ms=3, color=colours[b], label=b)
        hour_axis(ax)
        ax.set_ylabel(label)
        ax.set_title(f"{len(counts)} visits, {int(np.count_nonzero(counts))} streaked",
                     fontsize=9)
        if len(counts):
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                      title="band", title_fontsize=7)
        _save(fig, paths[kind], overwrite)

    # RA and Dec on plain axes, the labels outside them (a Mollweide's RA labels sit on the
    # equator, among the fields).
    from inject.survey.stream import SKY_NSIDE, healpix_fraction

    fig = Figure(figsize=(8, 4.6))
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0.08, 0.11, 0.76, 0.8])
    ra, dec = np.asarray(data["ra"], float), np.asarray(data["dec"], float)
    vmax = max(float(fraction.max(initial=0.0)), 1e-6)
    sky = healpix_fraction(ra, dec, fraction)
    if sky is not None:
        import healpy as hp

        # The map sampled on a 0.25 deg grid of RA and Dec, its pixels without a visit blank.
        grid_ra, grid_dec = np.meshgrid(np.linspace(359.875, 0.125, 1440),
                                        np.linspace(89.875, -89.875, 720))
        image = sky[hp.ang2pix(SKY_NSIDE, grid_ra, grid_dec, lonlat=True)]
        vmax = max(float(np.nanmax(sky, initial=0.0)), 1e-6)
        points = ax.imshow(image, extent=(360.0, 0.0, -90.0, 90.0), origin="upper",
                           aspect="auto", cmap="viridis", vmin=0.0, vmax=vmax,
                           interpolation="nearest")
        title = (f"pixel fraction lost: mean over the visits in each HEALPix pixel "
                 f"(nside {SKY_NSIDE})")
    else:
        order = np.argsort(fraction)
        points = ax.scatter(ra[order], dec[order], c=fraction[order], s=8, cmap="viridis",
                            vmin=0.0, vmax=vmax)
        title = "visits (RA, Dec), coloured by the pixel fraction lost"
    ax.set_xlim(360.0, 0.0)  # RA increasing to the left, as the sky is seen
    ax.set_ylim(-90.0, 90.0)
    ax.set_xticks(np.arange(0, 361, 30))
    ax.set_yticks(np.arange(-90, 91, 30))
    ax.tick_params(labelsize=7)
    ax.set_xlabel("RA (deg)", fontsize=8)
    ax.set_ylabel("Dec (deg)", fontsize=8)
    ax.grid(True, lw=0.3)
    ax.set_title(title, fontsize=9)
    bar = fig.colorbar(points, cax=fig.add_axes([0.87, 0.11, 0.02, 0.8]))
    bar.ax.tick_params(labelsize=6)
    _save(fig, paths["sky"], overwrite)


def _save(fig, path, overwrite):
    with atomic_path(path, overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


# --- the folder's claim ---------------------------------------------------------------------

#: The claim of a run on its OUTDIR: the key of its inputs and options.
CLAIM = "survey_claim.json"
#: A plan file of any run or slice (:data:`NAMES`, with or without ``-jobJ-of-N``).
_PLAN_FILE = re.compile(r"(%s)(-job\d+-of-\d+)?\.(csv|json|png)$" % "|".join(
    re.escape(os.path.splitext(n)[0]) for n in NAMES.values()))


class Claim:
    """A run's claim on its OUTDIR (:func:`claim_outdir`).

    Attributes
    ----------
    path : str
        The claim file.
    same_run : bool
        The folder was claimed by a run of the same key (a slice of this run, or this run
        again): the other slices' files are left alone.
    previous : str or None
        The claim file's earlier text, put back if this run fails.
    """

    def __init__(self, path, same_run, previous):
        self.path, self.same_run, self.previous = path, same_run, previous

    def release(self):
        """Undo the claim (a failed run): the earlier claim back, or none."""
        if self.same_run:
            return
        if self.previous is None:
            with contextlib.suppress(OSError):
                os.remove(self.path)
        else:
            _write_text(self.path, self.previous, True)


def claim_outdir(outdir, key, inputs, overwrite=False):
    """Claim ``outdir`` (an existing folder) for a run whose inputs and options hash to
    ``key``, before any work.

    Parameters
    ----------
    outdir : str
    key : str
        The run's key: equal for the ``--job`` slices of one run.
    inputs : dict
        What the key was made of, written beside it for the record.
    overwrite : bool
        Whether another run's claim may be replaced.

    Returns
    -------
    Claim

    Raises
    ------
    OutputError
        The folder holds another run's claim, or plan files and no claim, without
        ``overwrite``.
    """
    path = os.path.join(outdir, CLAIM)
    try:
        with open(path, encoding="utf-8") as stream:
            previous = stream.read()
    except FileNotFoundError:
        previous = None
    except OSError as err:
        raise OutputError(f"{path}: cannot be read ({err.strerror or err})") from None
    try:
        earlier = json.loads(previous).get("key") if previous is not None else None
    except (ValueError, AttributeError):
        earlier = None
    if earlier == key:
        return Claim(path, True, previous)
    if not overwrite:
        if previous is not None:
            raise OutputError(f"{outdir}: holds the outputs of another survey run ({CLAIM}: "
                              f"other VISITS, constellation or options); give another OUTDIR, "
                              f"or pass --overwrite to replace them")
        plan_files = sorted(n for n in os.listdir(outdir) if _PLAN_FILE.fullmatch(n))
        if plan_files:
            raise OutputError(f"{os.path.join(outdir, plan_files[0])}: exists (an earlier "
                              f"run's); give another OUTDIR, or pass --overwrite to replace it")
    _write_text(path, json.dumps({"key": key, **inputs}, indent=1) + "\n", True)
    return Claim(path, False, previous)


def remove_earlier(outdir, claim, written, visit_ids):
    """With ``--overwrite``: remove the earlier outputs in ``outdir`` that this run did not
    write. Of another run (``claim.same_run`` false) every plan file of any slice and every
    ``visits/<id>`` folder whose visit ``visit_ids`` (the visits this run rendered) leaves out;
    of this run, the plan files of its own slice that it did not write (the plots after
    ``--no-plots``).

    Parameters
    ----------
    outdir : str
    claim : Claim
    written : sequence of str
        The files this run wrote.
    visit_ids : set of int
        The visits this run rendered (their folders are kept).
    """
    from inject.survey.render import VISITS_DIR

    keep = {os.path.abspath(p) for p in written}
    slices = {_PLAN_FILE.fullmatch(os.path.basename(p)).group(2) for p in keep}
    for name in os.listdir(outdir):
        match = _PLAN_FILE.fullmatch(name)
        path = os.path.abspath(os.path.join(outdir, name))
        if match and path not in keep and (not claim.same_run or match.group(2) in slices):
            os.remove(path)
    folder = os.path.join(outdir, VISITS_DIR)
    if claim.same_run or not os.path.isdir(folder):
        return
    kept = {str(i) for i in visit_ids}
    for name in os.listdir(folder):
        if name not in kept:
            shutil.rmtree(os.path.join(folder, name))
