"""``inject survey``: which visits of a night a constellation streaks, and the pixels their
masks cost (the plan); with ``--render``, the streaked CCDs rendered, masked and measured
(:mod:`inject.survey.render`)."""
import contextlib
import json
import logging
import os
import sys
import time
import warnings

from inject.cli.options import add_resume_options, slurm_slice
from inject.errors import InputError, OrbitWarning
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
                    "pixels that mask takes. Writes streaks.csv, visits.csv, summary.json "
                    "and three plots in OUTDIR.")
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
                   help="worker processes over the visits (default: 1, this process); with "
                        "--render, over the CCDs (default: the CPUs this job may use, its "
                        "affinity and control group's quota, and no more than its memory "
                        "holds)")
    p.add_argument("--scheduler", metavar="ADDRESS|local",
                   help="a Dask scheduler address, or 'local' for a Dask LocalCluster of "
                        "--workers processes (default: a process pool)")
    p.add_argument("--job", type=int, metavar="J",
                   help="plan the J-th (0-based) of --njobs interleaved slices of the visits "
                        "(in a SLURM job array, default: the task's place in it)")
    p.add_argument("--njobs", type=int, metavar="N",
                   help="with --job: the number of slices (in a SLURM job array, "
                        "default: its task count)")
    p.add_argument("--no-plots", action="store_true", help="write the tables only")
    p.add_argument("--json", action="store_true", help="print summary.json on stdout")
    p.add_argument("--overwrite", action="store_true", help="replace earlier outputs")
    add_resume_options(p)
    p.set_defaults(func=run_survey)


#: Visits sent to a worker at a time.
CHUNK_VISITS = 8


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
    from inject.survey.outputs import claim_outdir, output_paths, remove_earlier
    from inject.survey.plan import warn_fallbacks
    from inject.survey.visits import read_visits

    night = read_visits(args.visits)
    visits = select_visits(night, args.job, args.njobs)
    if not visits:
        raise InputError("--job", args.job, f"takes none of the {len(night)} visits "
                                            f"(--njobs {args.njobs})")
    constellation = _constellation(args.constellation, night)
    if constellation.pupil == "rubin":  # the vanes need each visit's rotator
        from inject.orbits.passes import RUBIN
        from inject.survey.visits import with_rotators

        visits = with_rotators(visits, RUBIN)
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
    claim = None
    try:
        claim = claim_outdir(args.output, _run_key(inputs), inputs, args.overwrite)
        if args.rule == "inject":  # the rubin_sim rule takes no seeing and no sky
            warn_fallbacks(visits)
        started = time.perf_counter()
        plans = _plan(visits, constellation, args, fixed)
        if args.rule == "rubin_sim":
            fixed = None  # its band is the rule's mask: recorded under "rule"
        elapsed = time.perf_counter() - started
        rendered = sizing = None
        if options is not None:
            with locks_off(args.no_lock):
                rendered, sizing = _render(plans, constellation, args, night[0], options)
        written = _write(args, paths, plans, night, visits, constellation, elapsed, inputs,
                         rendered, sizing, fixed)
        if args.overwrite:
            remove_earlier(args.output, claim, written.values(),
                           set(rendered.measured) if rendered is not None else set())
        if rendered is not None:
            error = _failed(rendered, args.output)
            if error is not None:
                raise error
    except BaseException as err:
        from inject.errors import RunError

        if claim is not None and not isinstance(err, RunError):  # a RunError has written
            claim.release()
        if made:  # the folder this run made, if nothing else was put there meanwhile
            with contextlib.suppress(OSError):
                os.rmdir(args.output)
        raise


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


def _constellation(path, night):
    from inject.survey.constellation import read_constellation

    constellation = read_constellation(path)
    constellation.check_epochs(night)
    return constellation


def _plan(visits, constellation, args, fixed=None):
    """Every visit's plan, in this process or on workers, with its progress
    (:mod:`inject.progress`)."""
    from functools import partial

    from inject.progress import Progress
    from inject.survey.plan import plan_chunk, plan_visits

    width = None if fixed is None else fixed.width_px
    if args.rule == "rubin_sim":  # the band is the rule's own mask, not one beside it
        from inject.survey import rubin_rule

        band = rubin_rule.DEFAULT_WIDTH_PX if width is None else width
        plan_visits = partial(rubin_rule.plan_visits, width_px=band)
        plan_chunk = partial(rubin_rule.plan_chunk, width_px=band)
        width = None
    else:
        plan_visits = partial(plan_visits, fixed_width_px=width)
        plan_chunk = partial(plan_chunk, fixed_width_px=width)
    progress = Progress(len(visits), "planning visits", "visit", log)
    workers = args.workers or 1
    try:
        if workers == 1 and not args.scheduler:
            with warnings.catch_warnings():
                # An epoch's warning is said once, for the night (check_epochs).
                warnings.simplefilter("ignore", OrbitWarning)
                return plan_visits(visits, constellation, progress=progress.update)
        chunks = [visits[k:k + CHUNK_VISITS] for k in range(0, len(visits), CHUNK_VISITS)]
        path = os.path.abspath(args.constellation)
        task = plan_chunk
        if args.scheduler:
            from inject.exposure.runner import dask_executor

            with dask_executor(args.scheduler, args.workers) as executor:
                return _gather(executor, task, path, chunks, progress)
        from inject.exposure.runner import process_pool

        pool = process_pool(workers)
        try:
            result = _gather(pool, task, path, chunks, progress)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
        return result
    finally:
        progress.close()


def _gather(executor, function, path, chunks, progress):
    from concurrent.futures import as_completed

    futures = {executor.submit(function, path, chunk): k for k, chunk in enumerate(chunks)}
    out = [None] * len(chunks)
    for future in as_completed(futures):
        out[futures[future]] = future.result()
        for _ in out[futures[future]]:
            progress.update()
    return [plan for chunk in out for plan in chunk]


def _write(args, paths, plans, night, visits, constellation, elapsed, inputs, rendered=None,
           sizing=None, fixed=None):
    """Write the run's files (:func:`inject.survey.outputs.write_outputs`) and say so;
    returns ``{kind: path}`` of the files written. ``sizing``: the render's workers and why
    (:func:`_render_workers`), recorded in summary.json."""
    from inject import __version__
    from inject.orbits.passes import RUBIN
    from inject.survey.outputs import summary, write_outputs

    about = {"inject_version": __version__,
             "visits_file": inputs["visits_file"], "visits_sha256": inputs["visits_sha256"],
             "constellation_file": os.path.abspath(args.constellation),
             "constellation_sha256": inputs["constellation_sha256"],
             "epoch": inputs["epoch"], "pupil": constellation.pupil,
             "focus_offset_um": constellation.focus_offset_um,
             "satellites": len(constellation),
             "satellites_by_source": dict(constellation.sources),
             "night_visits": len(night), "job": args.job, "njobs": args.njobs,
             "site_lon_deg": RUBIN.lon_deg, "plan_seconds": round(elapsed, 3),
             "plan_seconds_per_visit": round(elapsed / len(visits), 4)}
    if fixed is not None:
        about["fixed_mask"] = {"width": fixed.given}
    about["rule"] = _rule_record(args, visits)
    measured = None
    if rendered is not None:
        from inject.survey.compare import measured_columns, render_summary

        measured = measured_columns(plans, rendered.measured)
        about["render"] = render_summary(plans, measured, rendered, _render_options(args))
        if sizing is not None:
            about["render"]["sizing"] = sizing
    result = summary(plans, about, RUBIN.lon_deg)
    written = write_outputs(paths, plans, result, args.overwrite, plots=not args.no_plots,
                            measured=measured)
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    log.info("inject survey: %d visits, %d streaked, %d streaks, pixel fraction lost %.3g "
             "(%.3f s a visit); wrote %s", len(visits), result["streaked_visits"],
             result["streaks"], result["pixel_fraction_lost_total"], elapsed / len(visits),
             ", ".join(written.values()))
    return written


def _rule_record(args, visits):
    """summary.json's ``rule``: which rule counted the streaks, and for ``rubin_sim`` what it
    takes (the circle, the limit, the time's reading, the spans' source, the band)."""
    if args.rule == "inject":
        return {"name": "inject", "streaks": "sunlit tracks on the science CCDs",
                "time": "observationStartMJD as TAI", "mask": "the masker's width per streak"}
    from inject.survey import rubin_rule
    from inject.survey.fixed_mask import parse_mask_width

    width = (rubin_rule.DEFAULT_WIDTH_PX if args.mask_width is None
             else parse_mask_width(args.mask_width).width_px)
    sources = [rubin_rule.visit_span(v)[1] for v in visits]
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
            "visits_span_from": {s: sources.count(s) for s in ("visitTime",
                                                               "exposure+readouts")},
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
