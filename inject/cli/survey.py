"""``inject survey``: which visits of a night a constellation streaks, and the pixels their
masks cost (the plan); with ``--render``, the streaked CCDs rendered, masked and measured
(:mod:`inject.survey.render`)."""
import contextlib
import json
import logging
import math
import os
import shutil
import sys
import time
import warnings

from inject.cli.options import add_resume_options, slurm_slice
from inject.errors import InputError
from inject.io.atomic import locks_off

log = logging.getLogger(__name__)

# ``inject --help`` imports this module: the orbits (astropy, SGP4), the streak model and the
# survey engine are imported inside the functions that use them.


def add_survey_parser(sub):
    p = sub.add_parser(
        "survey", help="a night of visits (opsim database or CSV) against a constellation: "
                       "streaks, masks and pixels lost",
        description="For every visit of VISITS (an opsim SQLite database, table "
                    "observations, or a CSV of its columns), the satellites of the "
                    "constellation whose sunlit track crosses a science CCD during the "
                    "exposure: the CCDs, length, magnitude, FWHM, peak surface brightness, "
                    "the mask the masker's rule gives it against the visit's sky, and the "
                    "pixels that mask takes. Plans night by night (each night's tables in "
                    "OUTDIR/nights/ as it finishes: a stopped run rerun as typed goes on "
                    "where it stopped), then writes streaks.csv, visits.csv, summary.json "
                    "and the plots in OUTDIR.")
    p.add_argument("visits", metavar="VISITS", help="opsim SQLite database or CSV of visits")
    p.add_argument("-o", "--output", "--out", dest="output", required=True, metavar="OUTDIR",
                   help="output directory (made if missing; its parent must exist)")
    p.add_argument("--constellation", required=True, metavar="CONST.yaml",
                   help="the satellites' model (shape, mag, ref_range or lumos) and their "
                        "orbits (shells and/or tle)")
    p.add_argument("--mask-width", metavar="PX|ARCSEC",
                   help="also count a fixed-width mask, as studies of constellations did: a "
                        "band of this full width (e.g. 300px or 60arcsec, at 0.2 arcsec/px) "
                        "along every streak on the CCDs, in pixels_fixed_mask columns and a "
                        "fixed_mask block of summary.json (with --rule rubin_sim: the rule's "
                        "own mask, inside the circle)")
    p.add_argument("--rule", choices=("inject", "rubin_sim"), default="inject",
                   help="inject: sunlit tracks on the science CCDs (TAI, light time, "
                        "aberration, the WGS84 penumbra) with the masker's mask; rubin_sim: "
                        "count as rubin_sim's check_pointings, as the literature did (the "
                        "1.75 deg circle, 20 deg, sunlit at the start or end by a sphere's "
                        "shadow, visitTime, observationStartMJD read as UT1 so ~37 s late) "
                        "with a fixed band of --mask-width (300px without it) inside the "
                        "circle")
    p.add_argument("--render", action="store_true",
                   help="render the streaked CCDs (OUTDIR/visits/<observationId>/<CCD>.fits), "
                        "mask them with the masker and add the measured FWHM, mask width "
                        "and pixels lost to streaks.csv")
    p.add_argument("--cutouts", action="store_true",
                   help="with --render: render only a square cut-out around each CCD's "
                        "streaks")
    p.add_argument("--cutout-size", type=int, default=None, metavar="PX",
                   help="side of the cut-outs, px (default: 1024)")
    p.add_argument("--compression", choices=("lossless", "lossy", "none"), default=None,
                   help="with --render: the CCD files' tile compression (lossless: GZIP; "
                        "lossy: IMAGE and VARIANCE quantised to a tenth of the noise with "
                        "dithering, adding 0.029 of it) (default: lossless)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes over the nights, a night a task (default: 1, this "
                        "process); with "
                        "--render, over the CCDs (default: the CPUs this job may use, its "
                        "affinity and control group's quota, and no more than its memory "
                        "holds)")
    p.add_argument("--scheduler", metavar="ADDRESS|local",
                   help="a Dask scheduler address, or 'local' for a Dask LocalCluster of "
                        "--workers processes (default: a process pool)")
    p.add_argument("--job", type=int, metavar="J",
                   help="plan the J-th (0-based) of --njobs interleaved slices of the nights "
                        "(in a SLURM job array, default: the task's place in it)")
    p.add_argument("--njobs", type=int, metavar="N",
                   help="with --job: the number of slices (in a SLURM job array, "
                        "default: its task count)")
    p.add_argument("--csv", choices=("always", "auto", "never"), default="always",
                   help="write the combined visits.csv and streaks.csv: always, never, or "
                        "(auto) for runs of at most 100,000 visits; every night's tables are in "
                        "OUTDIR/nights/ as Parquet files anyway")
    p.add_argument("--no-plots", action="store_true", help="write the tables only")
    p.add_argument("--json", action="store_true", help="print summary.json on stdout")
    p.add_argument("--overwrite", action="store_true", help="replace earlier outputs")
    add_resume_options(p)
    p.set_defaults(func=run_survey)


#: Nights sent to the workers ahead of those being written, per worker (a bound on the
#: visits and plans held in this process).
NIGHTS_AHEAD = 2


def run_survey(args):
    if args.workers is not None and args.workers < 1:  # before the engine's imports
        raise InputError("--workers", args.workers, "must be >= 1")
    options = _render_options(args)
    fixed = _fixed_mask(args)
    if args.rule == "rubin_sim" and options is not None:
        raise InputError("--render", True, "only with --rule inject (the rubin_sim rule has "
                                           "no CCDs)")
    array = slurm_slice(args)
    if array is not None:
        log.info("inject survey: %s", array)
    from inject.survey.visits import select_visits

    select_visits((), args.job, args.njobs)  # --job/--njobs, before the engine's imports
    from inject.exposure.runner import check_outdir
    from inject.orbits.passes import RUBIN
    from inject.survey.nights import VisitSource, select_nights
    from inject.survey.outputs import claim_outdir, output_paths, remove_earlier
    from inject.survey.stream import NightManifest

    source = VisitSource(args.visits, RUBIN.lon_deg)
    nights = select_nights(source.nights, args.job, args.njobs)
    if not len(nights):
        raise InputError("--job", args.job, f"takes none of the {len(source.nights)} nights "
                                            f"(--njobs {args.njobs})")
    constellation = _constellation(args.constellation, (source.first, source.last))
    check_outdir(args.output)
    paths = output_paths(args.output, args.job, args.njobs)
    from inject.io.atomic import check_writable

    made = not os.path.isdir(args.output)
    if not made:  # an output there without --overwrite is refused before any work
        for path in paths.values():
            check_writable(path, args.overwrite)
    if made:
        from inject.exposure.runner import make_outdir

        make_outdir(args.output)
    inputs = _inputs(args, constellation, options, fixed)
    claim = manifest = None
    try:
        key = _run_key(inputs)
        claim = claim_outdir(args.output, key, inputs, args.overwrite)
        if args.overwrite and not claim.same_run:  # another run's nights
            from inject.survey.stream import NIGHTS_DIR

            shutil.rmtree(os.path.join(args.output, NIGHTS_DIR), ignore_errors=True)
        if args.rule == "inject":  # the rubin_sim rule takes no seeing and no sky
            _warn_fallbacks(source)
        manifest = NightManifest(args.output, key, args.job, args.njobs)
        if not args.overwrite:
            manifest.load()
        # --render renders from the plans of every night: they are planned again.
        done = manifest.done(nights) if options is None else set()
        counts = dict(zip(source.nights.tolist(), source.counts.tolist()))
        todo = [int(n) for n in nights if int(n) not in done]
        if done:
            log.info("inject survey: %d of %d nights done already (%s), %d to plan",
                     len(done), len(nights), manifest.path, len(todo))
        started = time.perf_counter()
        plans = _plan(source, todo, counts, constellation, args, fixed, manifest,
                      keep=options is not None)
        if args.rule == "rubin_sim":
            fixed = None  # its band is the rule's mask: recorded under "rule"
        elapsed = time.perf_counter() - started
        rendered = sizing = None
        if options is not None:
            with locks_off(args.no_lock):
                rendered, sizing = _render(plans, constellation, args, source.first, options)
        timings = {"plan_seconds": round(elapsed, 3),
                   "plan_seconds_per_visit": (round(elapsed / sum(counts[n] for n in todo), 4)
                                              if todo else None),
                   "nights_planned": len(todo), "nights_done_before": len(done)}
        written = _write(args, paths, source, nights, manifest, constellation, timings,
                         inputs, plans, rendered, sizing, fixed)
        if args.overwrite:
            remove_earlier(args.output, claim, written.values(),
                           set(rendered.measured) if rendered is not None else set())
        if rendered is not None:
            error = _failed(rendered, args.output)
            if error is not None:
                raise error
    except BaseException as err:
        from inject.errors import RunError

        # Nights written are this run's, kept for its rerun (with its claim).
        kept = manifest is not None and bool(manifest.entries)
        if claim is not None and not isinstance(err, RunError) and not kept:
            claim.release()
        if made and not kept:  # the folder this run made, if nothing else was put there
            with contextlib.suppress(OSError):
                os.rmdir(args.output)
        raise


def _warn_fallbacks(source):
    """One :class:`~inject.errors.InputWarning` per default the plan takes (as
    :func:`inject.survey.plan.warn_fallbacks` says it), naming the first visits."""
    from inject.errors import InputWarning
    from inject.survey.plan import DEFAULT_SEEING

    for missing, column, instead in (
            (source.missing_seeing, "seeingFwhmEff",
             f"the streak model's default seeing, {DEFAULT_SEEING:g} arcsec"),
            (source.missing_sky, "skyBrightness",
             "the band's dark sky at zenith (SMTN-002) times the airmass")):
        if missing.count:
            ids = " ".join(str(i) for i in missing.named)
            more = (f" and {missing.count - len(missing.named)} more"
                    if missing.count > len(missing.named) else "")
            warnings.warn(f"{missing.count} of {source.total} visits have no {column} "
                          f"(visits {ids}{more}): they take {instead}", InputWarning,
                          stacklevel=2)


def _inputs(args, constellation, options, fixed=None):
    """What makes a run: its input files' SHA-256, the constellation's epoch and the options
    that change its outputs (``--job`` left out: a run's slices share its OUTDIR)."""
    from inject.exposure.runner import sha256_file
    from inject.survey.constellation import file_digests

    inputs = {"visits_file": os.path.abspath(args.visits),
              "visits_sha256": sha256_file(args.visits),
              "constellation_sha256": file_digests(constellation),
              "epoch": constellation.epoch_isot,
              "njobs": args.njobs,
              "render": None if options is None else [options.cutout, options.compression]}
    if fixed is not None:  # only then: a run without it keeps its key
        inputs["mask_width_px"] = fixed.width_px
    if args.rule != "inject":
        inputs["rule"] = args.rule
    return inputs


def _fixed_mask(args):
    """The :class:`~inject.survey.fixed_mask.FixedMask` of ``--mask-width`` (None without
    it)."""
    if args.mask_width is None:
        return None
    from inject.survey.fixed_mask import parse_mask_width

    return parse_mask_width(args.mask_width)


def _run_key(inputs):
    import hashlib

    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def _render_options(args):
    """The :class:`~inject.survey.render.RenderOptions` of ``--render`` (None without it);
    the render options refused without it."""
    if not args.render:
        for name, value in (("--cutouts", args.cutouts), ("--cutout-size", args.cutout_size),
                            ("--compression", args.compression), ("--verify", args.verify),
                            ("--no-lock", args.no_lock)):
            if value:
                raise InputError(name, value, "only with --render")
        return None
    if args.cutout_size is not None:
        if not args.cutouts:
            raise InputError("--cutout-size", args.cutout_size, "only with --cutouts")
        if args.cutout_size < 16:
            raise InputError("--cutout-size", args.cutout_size, "must be >= 16 (px)")
    from inject.survey.render import DEFAULT_CUTOUT_PX, RenderOptions

    cutout = (args.cutout_size or DEFAULT_CUTOUT_PX) if args.cutouts else None
    compression = args.compression or "lossless"
    return RenderOptions(cutout=cutout, compression=None if compression == "none"
                         else compression)


def _render(plans, constellation, args, first, options):
    """Render, mask and measure the streaked CCDs (:mod:`inject.survey.render`) on the focal
    plane's runner: a process pool (``--workers``, default the CPUs this job may use, as many
    as its memory holds: :func:`_render_workers`) or Dask (``--scheduler``).

    Returns
    -------
    result : inject.survey.render.RenderResult
    sizing : dict or None
        The process pool's workers, why, and the job's resources (for summary.json).
    """
    from inject.survey.render import model_keys, render_visits, visit_batches

    model = model_keys(args.constellation)
    batches = visit_batches(plans, constellation, model, args.output, options,
                            os.path.abspath(args.constellation), first.start.utc)
    sizing = None
    if args.scheduler:
        from inject.exposure.runner import dask_executor

        with dask_executor(args.scheduler, args.workers) as executor:
            result = render_visits(batches, executor, args.overwrite, verify=args.verify)
    else:
        from inject.exposure.runner import process_pool, stop_fork_server

        sizing = _render_workers(batches, args, options)
        pool = process_pool(sizing["workers"])
        try:
            result = render_visits(batches, pool, args.overwrite, verify=args.verify)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            stop_fork_server()
            raise
        pool.shutdown()
    log.info("inject survey --render: %d CCDs rendered, %d already done, %d failed (%.1f s)",
             len(result.rendered), len(result.skipped), len(result.failed), result.seconds)
    return result, sizing


def _render_workers(batches, args, options):
    """The process pool's workers for the CCDs of ``batches``, said in the log with what
    bounds them (:func:`inject.exposure.sizing.worker_count`: the job's CPUs, the CCDs, and
    the memory for the largest CCD or cut-out).

    Returns
    -------
    dict
        ``workers``, ``why`` and the job's resources (:meth:`~inject.exposure.sizing.
        Resources.record`).
    """
    from inject.exposure import sizing
    from inject.exposure.runner import WORKER_BASE_BYTES, WORKER_BYTES_PER_PIXEL

    ccds = [c for b in batches.values() for c in b.ccds]
    side = options.cutout or float("inf")  # a cut-out is clipped to its CCD
    shape = max(((min(c.shape[0], side), min(c.shape[1], side)) for c in ccds),
                key=lambda s: s[0] * s[1], default=(0, 0))
    need = WORKER_BASE_BYTES + WORKER_BYTES_PER_PIXEL * shape[0] * shape[1]
    resources = sizing.job_resources()
    count, why = sizing.worker_count(resources, need, len(ccds), args.workers,
                                     f"about {{need}} GiB a worker for {shape[1]} x "
                                     f"{shape[0]} px CCDs")
    log.info("inject survey --render: %d worker%s (%s)", count, "s" if count != 1 else "", why)
    return {"workers": count, "why": why, **resources.record()}


def _constellation(path, visits):
    """The constellation of ``path``, its TLEs' epochs checked against ``visits`` (the first
    and the last)."""
    from inject.survey.constellation import read_constellation

    constellation = read_constellation(path)
    constellation.check_epochs(visits)
    return constellation


def _plan(source, todo, counts, constellation, args, fixed, manifest, keep=False):
    """Plan the nights ``todo`` night by night, in this process or on workers (a night a
    task), with their progress (:mod:`inject.progress`): each night's tables written and
    recorded in ``manifest`` as it finishes (:mod:`inject.survey.stream`).

    Returns
    -------
    list of inject.survey.plan.VisitPlan
        With ``keep`` (``--render``), every visit's plan in start order; else empty.
    """
    from concurrent.futures import FIRST_COMPLETED, wait

    import numpy as np

    from inject.progress import Progress
    from inject.survey.nights import night_label
    from inject.survey.plan import fallbacks
    from inject.survey.stream import night_paths, night_tables, plan_night, write_parquet

    width = None if fixed is None else fixed.width_px
    if args.rule == "rubin_sim":  # the band is the rule's own mask, not one beside it
        from inject.survey.rubin_rule import DEFAULT_WIDTH_PX

        options = {"rule": "rubin_sim", "width_px": DEFAULT_WIDTH_PX if width is None else width}
    else:
        options = {"fixed_width_px": width}
    total = sum(counts[n] for n in todo)
    progress = Progress(total, f"planning {len(todo)} night{'s' if len(todo) != 1 else ''}",
                        "visit", log)
    kept, finished, started = {}, [0, 0], time.perf_counter()

    def note():
        done = finished[1]
        left = (time.perf_counter() - started) * (total - done) / done if done else math.nan
        return (f"{finished[0]}/{len(todo)} nights" +
                (f", ~{_duration(left)} left" if math.isfinite(left) else ""))

    def finish(night, visits, plans, sun_alt):
        if len(plans) != counts[night]:  # the file changed since its first pass
            raise InputError("VISITS", args.visits, f"night {night_label(night)} read with "
                                                    f"{len(plans)} visits, counted with "
                                                    f"{counts[night]}: changed while read?")
        visit_table, streak_table = night_tables(night, plans, sun_alt,
                                                 fixed is not None and args.rule == "inject")
        paths = night_paths(args.output, night)
        write_parquet(visit_table, paths["visits"])
        write_parquet(streak_table, paths["streaks"])
        record = fallbacks(visits)
        if args.rule == "rubin_sim":  # which visits lasted their visitTime (summary's rule)
            from inject.survey.rubin_rule import visit_span

            spans = [visit_span(v)[1] for v in visits]
            record["visits_span_from"] = {k: spans.count(k)
                                          for k in ("visitTime", "exposure+readouts")}
        manifest.add(night, len(visits), streak_table.num_rows, paths, record)
        if keep:
            kept[night] = plans
        finished[0] += 1

    def rotators(visits):
        if constellation.pupil == "rubin":  # the vanes need each visit's rotator
            from inject.orbits.passes import RUBIN
            from inject.survey.visits import with_rotators

            return tuple(with_rotators(visits, RUBIN))
        return visits

    workers = args.workers or 1
    nights = source.nights_visits(set(todo)) if todo else iter(())
    try:
        if workers == 1 and not args.scheduler:
            for night, visits in nights:
                visits = rotators(visits)

                def step():
                    finished[1] += 1
                    progress.update(note())

                plans, sun_alt = plan_night(constellation, visits, progress=step, **options)
                finish(night, visits, plans, sun_alt)
                log.debug("night %s done (%s)", night_label(night), note())
        else:
            path = os.path.abspath(args.constellation)
            # Fewer nights than workers (a night alone): each night in as many contiguous
            # parts, each with its own prefilter (a visit's plan is the same in any part).
            parts = -(-workers // len(todo)) if todo else 1
            with _executor(args, workers) as executor:
                pending, done_parts = {}, {}

                def collect():
                    ready, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in sorted(ready, key=lambda f: pending[f][:2]):
                        night, part, visits = pending.pop(future)
                        done_parts[night][part] = future.result()
                        if any(r is None for r in done_parts[night]):
                            continue
                        results = done_parts.pop(night)
                        finish(night, visits, [p for r in results for p in r[0]],
                               np.concatenate([r[1] for r in results]))
                        finished[1] += len(visits)
                        progress.update(f"night {night_label(night)} done ({note()})",
                                        n=len(visits))

                for night, visits in nights:
                    visits = rotators(visits)
                    size = -(-len(visits) // parts)
                    pieces = [visits[k:k + size] for k in range(0, len(visits), size)]
                    done_parts[night] = [None] * len(pieces)
                    for part, piece in enumerate(pieces):
                        pending[executor.submit(plan_night, path, piece, **options)] = \
                            (night, part, visits)
                    while len(pending) >= NIGHTS_AHEAD * workers:
                        collect()
                while pending:
                    collect()
    finally:
        progress.close()
    return [p for night in sorted(kept) for p in kept[night]]


@contextlib.contextmanager
def _executor(args, workers):
    """Dask's executor (``--scheduler``) or a process pool of ``workers``, shut down at the
    end (its queued tasks cancelled after an error)."""
    if args.scheduler:
        from inject.exposure.runner import dask_executor

        with dask_executor(args.scheduler, args.workers) as executor:
            yield executor
        return
    from inject.exposure.runner import process_pool

    pool = process_pool(workers)
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()


def _duration(seconds):
    """``42 s``, ``17 min``, ``3.2 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _write(args, paths, source, nights, manifest, constellation, timings, inputs, plans=(),
           rendered=None, sizing=None, fixed=None):
    """Write the run's files from its nights' tables (:mod:`inject.survey.stream`,
    :func:`inject.survey.outputs.write_run_outputs`) and say so; returns ``{kind: path}`` of
    the files written. ``sizing``: the render's workers and why (:func:`_render_workers`),
    recorded in summary.json."""
    import numpy as np

    from inject import __version__
    from inject.orbits.passes import RUBIN
    from inject.survey.outputs import write_run_outputs
    from inject.survey.plan import TOTAL_PIXELS
    from inject.survey.stream import (
        CSV_AUTO_VISITS,
        SUMMARY_STREAK_COLUMNS,
        SUMMARY_VISIT_COLUMNS,
        add_fallbacks,
        check_nights,
        columns_of,
        read_nights,
        summary_from_tables,
    )
    from inject.survey.visits import local_hours

    check_nights(args.output, manifest, nights)
    about = {"inject_version": __version__,
             "visits_file": inputs["visits_file"], "visits_sha256": inputs["visits_sha256"],
             "constellation_file": os.path.abspath(args.constellation),
             "constellation_sha256": inputs["constellation_sha256"],
             "epoch": inputs["epoch"], "pupil": constellation.pupil,
             "focus_offset_um": constellation.focus_offset_um,
             "satellites": len(constellation),
             "satellites_by_source": dict(constellation.sources),
             "night_visits": source.total, "nights": len(nights),
             "first_night": manifest.entries[int(nights[0])]["night"],
             "last_night": manifest.entries[int(nights[-1])]["night"],
             "job": args.job, "njobs": args.njobs, "site_lon_deg": RUBIN.lon_deg}
    if fixed is not None:
        about["fixed_mask"] = {"width": fixed.given}
    fallback = None
    for night in nights:
        fallback = add_fallbacks(fallback, manifest.entries[int(night)]["fallbacks"])
    about["rule"] = _rule_record(args, (fallback or {}).pop("visits_span_from", None))
    visit_columns = SUMMARY_VISIT_COLUMNS + (("pixels_fixed_mask",) if fixed else ())
    visits = columns_of(read_nights(args.output, nights, "visits", list(visit_columns)))
    streaks = columns_of(read_nights(args.output, nights, "streaks",
                                     list(SUMMARY_STREAK_COLUMNS)))
    measured = extra = None
    if rendered is not None:
        from inject.survey.compare import MEASURED_FIELDS, measured_columns, render_summary

        measured, extra = measured_columns(plans, rendered.measured), MEASURED_FIELDS
        about["render"] = render_summary(plans, measured, rendered, _render_options(args))
        if sizing is not None:
            about["render"]["sizing"] = sizing
    result = summary_from_tables(visits, streaks, about, fallback, RUBIN.lon_deg,
                                 None if fixed is None else fixed.width_px)
    result["timings"] = timings  # the one block a resumed run's summary differs in
    n = len(visits["observationId"])
    tables = None
    if args.csv == "always" or (args.csv == "auto" and n <= CSV_AUTO_VISITS):
        tables = (read_nights(args.output, nights, "visits"),
                  read_nights(args.output, nights, "streaks"))
    plot_data = None
    if not args.no_plots:
        plot_data = {"hours": local_hours(visits["mjd"], RUBIN.lon_deg),
                     "n_streaks": visits["n_streaks"],
                     "fraction": np.asarray(visits["pixels_lost"], float) / TOTAL_PIXELS,
                     "band": visits["band"], "ra": visits["fieldRA"], "dec": visits["fieldDec"]}
    written = write_run_outputs(paths, result, tables, plot_data, args.overwrite,
                                measured=measured, extra_fields=extra or ())
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    log.info("inject survey: %d visits in %d nights, %d streaked, %d streaks, pixel fraction "
             "lost %.3g (%.1f s of plan); wrote %s", n, len(nights), result["streaked_visits"],
             result["streaks"], result["pixel_fraction_lost_total"], timings["plan_seconds"],
             ", ".join(written.values()))
    return written


def _rule_record(args, spans):
    """summary.json's ``rule``: which rule counted the streaks, and for ``rubin_sim`` what it
    takes (the circle, the limit, the time's reading, ``spans``: how many visits lasted their
    ``visitTime`` and how many their exposure and readouts, the band)."""
    if args.rule == "inject":
        return {"name": "inject", "streaks": "sunlit tracks on the science CCDs",
                "time": "observationStartMJD as TAI", "mask": "the masker's width per streak"}
    from inject.survey import rubin_rule
    from inject.survey.fixed_mask import parse_mask_width

    width = (rubin_rule.DEFAULT_WIDTH_PX if args.mask_width is None
             else parse_mask_width(args.mask_width).width_px)
    return {"name": "rubin_sim",
            "streaks": f"rubin_sim's check_pointings: sunlit (sphere of "
                       f"{rubin_rule.SKYFIELD_EARTH_RADIUS_KM} km, the Sun's centre) and above "
                       f"{rubin_rule.ALT_LIMIT_DEG:g} deg at the start or end, the track "
                       f"every ~{rubin_rule.STEP_S:g} s entering the "
                       f"{rubin_rule.RADIUS_DEG} deg circle (gnomonic); no CCDs",
            "time": "observationStartMJD read as UT1 (opsim's TAI: ~37 s late), as rubin_sim "
                    "reads it, to reproduce the literature",
            "radius_deg": rubin_rule.RADIUS_DEG, "alt_limit_deg": rubin_rule.ALT_LIMIT_DEG,
            "step_s": rubin_rule.STEP_S,
            "visits_span_from": spans or {"visitTime": 0, "exposure+readouts": 0},
            "mask": "a fixed band along the track inside the circle",
            "mask_width_px": width,
            "mask_width_given": args.mask_width or f"{rubin_rule.DEFAULT_WIDTH_PX:g}px "
                                                   f"(default)",
            "pixels": "the circle's 0.2 arcsec pixels; pixel fractions are of the 189 CCDs' "
                      "pixels"}


def _failed(rendered, outdir):
    """A :class:`~inject.errors.RunError` naming the CCDs that failed (None if none did): the
    tables are written first, with the CCDs that were measured."""
    if not rendered.failed:
        return None
    from inject.errors import RunError

    rows = rendered.failed
    first = rows[0]
    return RunError(f"{len(rows)} of {len(rows) + len(rendered.rendered) + len(rendered.skipped)}"
                    f" CCDs failed (visit {first['visit']} {first['detector']}: "
                    f"{first['error']}); each one's error is in its visit's manifest.csv under "
                    f"{os.path.join(outdir, 'visits')}; a rerun redoes only the failed ones",
                    [(f"{r['visit']}/{r['detector']}", r["error"]) for r in rows])
