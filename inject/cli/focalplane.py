"""``inject focalplane``: a focal-plane scene rendered CCD by CCD."""
import gc
import json
import logging
import os
import sys

from inject.cli.options import add_resume_options, slurm_slice
from inject.errors import InputError, OutputError
from inject.io.atomic import atomic_path, locks_off

log = logging.getLogger(__name__)

# ``inject --help`` imports this module: the scene parser, the plan, the runner (multiprocessing,
# Dask) and the camera layout are imported inside the functions that use them.


def add_focalplane_parser(sub):
    p = sub.add_parser(
        "focalplane", help="simulate the LSSTCam focal plane (189 CCDs) from a scene file",
        description="Simulate the CCDs of a focal-plane scene (tracks in focal-plane mm) on a "
                    "process pool or a Dask cluster, resumably; one FITS per CCD, "
                    "manifest.csv and mosaic.png in OUTDIR.")
    p.add_argument("scene", help="YAML focal-plane scene (an example: the repository's "
                                         "sample_fields/focal_paper_550km.yaml)")
    p.add_argument("-o", "--output", "--out", metavar="OUTDIR", help="output directory (not needed "
                                                             "with --plan)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes (default: the CPUs this job may use, its affinity "
                        "and control group's quota, and no more than its memory holds)")
    p.add_argument("--scheduler", metavar="ADDRESS|local",
                   help="a Dask scheduler address, or 'local' for a Dask LocalCluster of "
                        "--workers single-threaded processes (default: a process pool)")
    p.add_argument("--memory-limit", default=None, metavar="SIZE",
                   help="memory limit per LocalCluster worker (default: 3GiB)")
    p.add_argument("--detectors", metavar="LIST",
                   help="comma-separated CCD names or ids (default: the scene's, or all 189)")
    p.add_argument("--streak-ccds-only", action="store_true",
                   help="render only the CCDs a streak reaches")
    p.add_argument("--job", type=int, metavar="J",
                   help="render the J-th (0-based) of --njobs interleaved slices (in a SLURM job "
                        "array, default: the task's place in it)")
    p.add_argument("--njobs", type=int, metavar="N",
                   help="with --job: the number of slices (in a SLURM job array, "
                        "default: its task count)")
    p.add_argument("--retries", type=int, default=2, metavar="N",
                   help="resubmissions of a failed CCD")
    p.add_argument("--plan", action="store_true", help="print what would be rendered; render "
                                                       "nothing")
    p.add_argument("--json", action="store_true", help="with --plan: one JSON object")
    p.add_argument("--no-mosaic", action="store_true", help="do not write mosaic.png")
    p.add_argument("--overwrite", action="store_true",
                   help="replace files of an earlier run of another scene")
    add_resume_options(p)
    p.add_argument("overrides", nargs="*", default=[], metavar="key.path=value",
                   help="override scene keys, e.g. satellites.0.mag=6 cutout.nx=512")
    p.set_defaults(func=run_focalplane)


def _selected(plan, args):
    from inject.camera import layout as fp
    from inject.exposure.runner import slice_ccds

    ccds = plan.fscene.ccds
    if args.detectors is not None:
        wanted = set(fp.select(args.detectors))
        outside = sorted(wanted - set(ccds), key=lambda c: c.id)
        if outside:
            raise InputError("--detectors", args.detectors,
                             f"{outside[0].name} is not among the scene's detectors")
        ccds = tuple(c for c in ccds if c in wanted)
    why = f"the {len(ccds)} CCDs selected"
    if args.streak_ccds_only:
        ccds, before = plan.streak_ccds(ccds), len(ccds)
        why = f"--streak-ccds-only: no streak reaches the {before} CCDs selected"
    sliced = slice_ccds(ccds, args.job, args.njobs)
    if ccds and not sliced:
        why = f"--job {args.job} of --njobs {args.njobs} takes none of the {len(ccds)} CCDs"
    return sliced, why


def run_focalplane(args):
    # The options alone first: a bad one is answered before the engine is imported.
    if args.workers is not None and args.workers < 1:
        raise InputError("--workers", args.workers, "must be >= 1")
    if args.retries < 0:
        raise InputError("--retries", args.retries, "must be >= 0")
    if args.json and not args.plan:
        raise InputError("--json", True, "only with --plan")
    from inject.exposure.runner import slice_ccds

    slice_ccds((), args.job, args.njobs)  # --job/--njobs
    from inject.exposure.plan import make_plan
    from inject.exposure.scene import parse_focal_scene
    from inject.schema import apply_overrides, load_scene_file

    fscene = parse_focal_scene(apply_overrides(load_scene_file(args.scene), args.overrides))
    plan = make_plan(fscene)
    array = slurm_slice(args)
    if array is not None:
        log.info("inject focalplane: %s", array)
    ccds, why = _selected(plan, args)
    if args.plan:
        result = plan.summary(ccds)
        if args.json:
            json.dump(result, sys.stdout)
            sys.stdout.write("\n")
        else:
            for d in result["detectors"]:
                ends = "; ".join(f"({s['x0']:.1f}, {s['y0']:.1f}) -> ({s['x1']:.1f}, "
                                 f"{s['y1']:.1f})" for s in d["streaks"])
                print(f"{d['name']:8s} {d['id']:3d} {d['vendor']:3s}  {ends}")
            log.info("%d of %d CCDs reached by a streak", len(result["detectors"]), len(ccds))
        return
    from inject.exposure.runner import check_outdir

    if not args.output:
        raise InputError("-o", None, "give an output directory (or --plan)")
    check_outdir(args.output)
    limit = _memory_limit(plan.fscene, ccds, args)
    records = _check_satellites_file(plan, args)
    with locks_off(args.no_lock):
        if not ccds:
            _nothing_to_render(plan, args, records, why)
            return
        workers = _workers(plan.fscene, ccds, args)
        mosaic = os.path.join(args.output, "mosaic.png")
        if not args.no_mosaic and os.path.exists(mosaic) and not args.overwrite:
            from inject.exposure.runner import read_manifest

            rows = read_manifest(args.output).values()
            if not any(r.get("scene_sha256") == fscene.digest for r in rows):
                raise OutputError(f"{mosaic}: exists (not this scene's); pass --overwrite to "
                                  "replace it")
        _render(plan, ccds, args, records, workers, limit)


def _nothing_to_render(plan, args, records, why):
    """No CCD in this run (an empty --job slice, --streak-ccds-only on a pass in shadow): not
    a failure (a batch array may have more slices than CCDs). The directory is checked and
    its manifest made as for a run (another scene's run is refused without --overwrite,
    replaced with it), and satellites.csv says where each satellite went."""
    from inject.exposure.runner import run

    run(plan, args.output, None, ccds=(), overwrite=args.overwrite)
    path = write_satellites(args.output, records)
    log.info("inject focalplane: no CCD to render (%s); wrote %s", why, path)


def _workers(fscene, ccds, args):
    """The worker processes of the run, said in the log with what bounds them
    (:func:`inject.exposure.sizing.worker_count`): ``--workers`` (default the CPUs this job
    may use), never more than the CCDs, and only as many as the job's memory holds, each
    about :func:`inject.exposure.runner.worker_bytes`: without ``--workers`` the count is
    capped at what fits, with it a count that does not fit is refused (as ``inject simulate``
    refuses a CCD too large). A remote Dask cluster's memory is its own."""
    from inject.exposure import sizing
    from inject.exposure.runner import worker_bytes

    if args.scheduler not in (None, "local"):
        return args.workers
    need, (ny, nx) = worker_bytes(fscene, ccds)
    count, why = sizing.worker_count(sizing.job_resources(), need, len(ccds), args.workers,
                                     f"about {{need}} GiB a worker for {nx} x {ny} px CCDs")
    log.info("inject focalplane: %d worker%s (%s)", count, "s" if count != 1 else "", why)
    return count


#: The exposure-level record of every satellite, next to manifest.csv.
SATELLITES_CSV = "satellites.csv"


def _check_satellites_file(plan, args):
    """The satellite records of the run; refuse (before any work) to replace another scene's
    satellites.csv without --overwrite."""
    import csv

    from inject.exposure.plan import satellite_records

    fscene = plan.fscene
    path = os.path.join(args.output, SATELLITES_CSV)
    if os.path.exists(path) and not args.overwrite:
        with open(path, newline="") as stream:
            digests = {row.get("scene_sha256") for row in csv.DictReader(stream)}
        if digests - {fscene.digest}:
            raise OutputError(f"{path}: exists (not this scene's); pass --overwrite to "
                              "replace it")
    return satellite_records(plan)


def write_satellites(outdir, records):
    """Write OUTDIR/satellites.csv atomically: one row per satellite of the scene (see
    :func:`inject.exposure.plan.satellite_records`), so a satellite that renders nowhere still
    says why. Its content depends on the scene alone (every ``--job`` slice writes the same)."""
    import csv
    import io

    from inject.exposure.plan import SATELLITE_FIELDS

    text = io.StringIO()
    writer = csv.DictWriter(text, SATELLITE_FIELDS)
    writer.writeheader()
    for row in records:
        writer.writerow({k: ("" if row[k] is None else str(row[k]).lower()
                             if isinstance(row[k], bool) else row[k]) for k in SATELLITE_FIELDS})
    path = os.path.join(outdir, SATELLITES_CSV)
    with atomic_path(path, overwrite=True) as tmp:
        with open(tmp, "w", newline="") as stream:
            stream.write(text.getvalue())
    return path


def _run_on_pool(plan, ccds, args, workers):
    """The run on a process pool. A stop (or an error) does not wait for the CCDs under way:
    the runner has stopped the workers, and the fork server is ended too."""
    from inject.exposure.runner import process_pool, run, stop_fork_server

    pool = None
    try:
        pool = process_pool(workers)
        result = run(plan, args.output, pool, ccds, overwrite=args.overwrite,
                     retries=args.retries, verify=args.verify)
    except BaseException as err:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        if isinstance(err, KeyboardInterrupt):  # a stop signal too (inject.signals.Stopped)
            stop_fork_server()
            # The interpreter's last collection walks every object of the libraries and the
            # scene (0.5-1 s); the process is about to exit: leave them to it.
            gc.freeze()
        raise
    pool.shutdown()
    return result


def _memory_limit(fscene, ccds, args):
    """``--memory-limit`` checked: only with ``--scheduler local``, in Dask's size syntax, and
    enough for one CCD (Dask would restart a worker over its limit again and again); the
    default :data:`~inject.exposure.runner.DASK_MEMORY_LIMIT` without it."""
    from inject.exposure.runner import DASK_MEMORY_LIMIT, worker_bytes

    if args.memory_limit is None:
        return DASK_MEMORY_LIMIT
    if args.scheduler != "local":
        raise InputError("--memory-limit", args.memory_limit,
                         "only with --scheduler local (a cluster's workers have their own)")
    try:
        from dask.utils import parse_bytes
    except ImportError:
        return args.memory_limit  # dask_executor says that Dask is needed
    try:
        limit = parse_bytes(args.memory_limit)
    except (ValueError, TypeError):
        raise InputError("--memory-limit", args.memory_limit,
                         "must be a size such as 3GiB, 2500MB or 4e9") from None
    if ccds:
        need, (ny, nx) = worker_bytes(fscene, ccds)
        if limit < need:
            raise InputError("--memory-limit", args.memory_limit,
                             f"less than one worker needs (about {need / 2**30:.2g} GiB for a "
                             f"{nx} x {ny} px CCD)")
    return args.memory_limit


def _render(plan, ccds, args, records, workers, memory_limit):
    from inject.exposure.runner import dask_executor, run

    if args.scheduler:
        with dask_executor(args.scheduler, workers, memory_limit, args.retries) as executor:
            result = run(plan, args.output, executor, ccds, overwrite=args.overwrite,
                         retries=args.retries, verify=args.verify)
    else:
        result = _run_on_pool(plan, ccds, args, workers)
    log.info("%s: %d CCDs rendered, %d already done, %d failed", args.output,
             len(result.rendered), len(result.skipped), len(result.failed))
    write_satellites(args.output, records)
    for row in records:
        if not row["n_ccds"]:
            log.warning("satellites[%s]: renders on no CCD (why: %s)", row["satellite"],
                        os.path.join(args.output, SATELLITES_CSV))
    if not args.no_mosaic:
        from inject.exposure.mosaic import write_mosaic

        path = os.path.join(args.output, "mosaic.png")
        write_mosaic(path, plan.fscene, args.output)
        log.info("wrote %s", path)
    error = result.error(args.output)  # which CCDs failed, with their messages
    if error is not None:
        raise error  # a RunError: one line, exit status 2
