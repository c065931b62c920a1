"""Time the focal-plane runner, measured side by side in one run.

* CCDs per second with 1 and 2 worker processes on the same full-size CCDs (half with the
  streak, half without), and the parallel efficiency ``rate(2) / (2 rate(1))``, with the
  workers' start in the clock (cold: each worker is forked from the fork server, which has
  done the imports before any clock, and builds the stars' PSF stamps) and after each worker
  has built them (warm); the same CCDs through a Dask LocalCluster of 2 single-threaded
  workers; peak memory per worker.
* ``--paired N``: in this one process (one thread), N CCDs without the streak and N with it,
  each rendered and written as the runner does, interleaved with the baseline of the same
  CCD (Poisson sky written as IMAGE, MASK, VARIANCE); the per-CCD ratio to the baseline and
  the whole-exposure ratio they predict (the 189 CCDs weighted by how many are crossed).
* The whole 189-CCD exposure (sky, Bahcall-Soneira stars, noise, cosmic rays, the paper's
  satellite across the focal plane: ``sample_fields/focal_paper_550km.yaml``) end to end on 2
  workers, against the baseline of the same workers drawing Poisson sky for the 189 CCDs and
  writing each as IMAGE, MASK and VARIANCE (the CCD-scene benchmark's baseline) and flushing
  it to disk, as the runner must before its manifest says a file is done, run before and
  after the exposure (the ratio is to their mean); and with ``--streak-ccds-only``.
  ``--baseline-no-fsync``: the baseline deletes each file unflushed, so most of its bytes
  never reach the disk (a floor of a job that keeps no file).

Files are written, hashed and deleted as they come (189 full CCDs would take ~49 GB), in a
temporary directory beside ``--out``.

Usage::

    python scripts/bench_focalplane.py [--rate-ccds 8] [--skip-whole] [--skip-dask]
        [--paired N] [--skip-rates] [--baseline-no-fsync] [--out out/bench]
"""
import argparse
import json
import os
import resource
import shutil
import tempfile
import time

import numpy as np

from inject.camera import layout as fp
from inject.exposure import runner as parallel
from inject.exposure.ccd import ccd_scene
from inject.exposure.plan import make_plan
from inject.exposure.scene import parse_focal_scene
from inject.schema import load_scene_file

SCENE = os.path.join(os.path.dirname(__file__), "..", "sample_fields",
                     "focal_paper_550km.yaml")


def baseline_ccd(args):
    """Poisson sky for one CCD written as IMAGE, MASK, VARIANCE (then deleted; with
    ``flush``, first flushed to disk as the runner flushes its files)."""
    from astropy.io import fits

    from inject.config import sky_level
    from inject.io.atomic import fsync_file
    parallel.limit_threads()
    scene, name, outdir, flush = args
    start = time.perf_counter()
    rng = np.random.default_rng(np.random.SeedSequence(1, spawn_key=(fp.ccd(name).id,)))
    sky = sky_level(scene)
    image = rng.poisson(sky, size=scene.detector.shape).astype(np.float32)
    path = os.path.join(outdir, f"{name}.fits")
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(image, name="IMAGE"),
                  fits.ImageHDU(np.zeros(image.shape, np.int32), name="MASK"),
                  fits.ImageHDU(np.full(image.shape, sky, np.float32), name="VARIANCE")]
                 ).writeto(path, overwrite=True)
    if flush:
        fsync_file(path)
    os.remove(path)
    return {"seconds": time.perf_counter() - start,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def paired(plan, crossed, plain, n, outdir, flush=False):
    """Per-CCD seconds of the runner's task and of the baseline, interleaved in this process
    (alternating which goes first), for ``n`` CCDs without and ``n`` with the streak."""
    fscene = plan.fscene
    parallel.limit_threads()
    os.makedirs(outdir, exist_ok=True)
    # Warm-up (imports, the stars' PSF stamps, the profile tables' caches), not timed.
    parallel.render_ccd(parallel.Task(fscene, plain[-1].name, outdir,
                                      tuple(plan.streaks(plain[-1])), keep=False))
    baseline_ccd((ccd_scene(fscene, plain[-1]), plain[-1].name, outdir, flush))
    out = {}
    for kind, ccds in (("plain", plain[:n]), ("streak", crossed[:n])):
        # Wall and CPU (user + system) seconds: on a shared machine the CPU time is the
        # steadier measure of the work done.
        times = {"task": ([], []), "base": ([], [])}

        def timed(name, work):
            wall, cpu = time.perf_counter(), time.process_time()
            work()
            times[name][0].append(time.perf_counter() - wall)
            times[name][1].append(time.process_time() - cpu)

        for k, ccd in enumerate(ccds):
            steps = [("task", lambda: parallel.render_ccd(parallel.Task(
                         fscene, ccd.name, outdir, tuple(plan.streaks(ccd)), keep=False))),
                     ("base", lambda: baseline_ccd((ccd_scene(fscene, ccd), ccd.name,
                                                    outdir, flush)))]
            for name, work in steps if k % 2 == 0 else steps[::-1]:
                timed(name, work)
        (task_s, task_cpu), (base_s, base_cpu) = times["task"], times["base"]
        out[kind] = {"ccds": len(ccds), "task_s_median": float(np.median(task_s)),
                     "baseline_s_median": float(np.median(base_s)),
                     "ratio_median": float(np.median(np.divide(task_s, base_s))),
                     "task_cpu_s_median": float(np.median(task_cpu)),
                     "baseline_cpu_s_median": float(np.median(base_cpu)),
                     "cpu_ratio_median": float(np.median(np.divide(task_cpu, base_cpu)))}
    n_streak, n_plain = len(crossed), len(fp.CCDS) - len(crossed)
    for key, task, base in (("predicted_whole_over_baseline", "task_s_median",
                             "baseline_s_median"),
                            ("predicted_whole_over_baseline_cpu", "task_cpu_s_median",
                             "baseline_cpu_s_median")):
        out[key] = ((n_plain * out["plain"][task] + n_streak * out["streak"][task])
                    / (n_plain * out["plain"][base] + n_streak * out["streak"][base]))
    print(f"paired, predicted whole exposure over the baseline: "
          f"{out['predicted_whole_over_baseline']:.2f} (wall), "
          f"{out['predicted_whole_over_baseline_cpu']:.2f} (CPU) (goal <= 1.2)", flush=True)
    return out


def warm_worker(fscene):
    """Run once in each worker before a warm rate's clock starts: the imports and the stars'
    PSF stamps (cached per worker), then a pause so that each worker takes one of these."""
    from inject.instrument import LSST
    from inject.profile import Seeing
    from inject.stars import psf_stamps

    parallel.limit_threads()
    psf_stamps(Seeing(fscene.scene.seeing).profile(), LSST.pixel_scale_arcsec)
    time.sleep(1.0)
    return os.getpid()


def timed_run(plan, ccds, executor, outdir):
    shutil.rmtree(outdir, ignore_errors=True)
    start = time.perf_counter()
    result = parallel.run(plan, outdir, executor, ccds=ccds, keep=False,
                          progress=_Quiet())
    seconds = time.perf_counter() - start
    assert not result.failed, result.failed
    return seconds, result.rendered


class _Quiet:
    def update(self, row):
        pass

    def close(self):
        pass


def summary(rows):
    sim = np.array([r["simulate_s"] for r in rows])
    write = np.array([r["write_s"] for r in rows])
    streak = np.array([int(r["streaks"]) > 0 for r in rows])
    return {"ccds": len(rows), "simulate_s_mean": float(sim.mean()),
            "write_hash_s_mean": float(write.mean()),
            "simulate_s_streak_ccd": float(sim[streak].mean()) if streak.any() else None,
            "simulate_s_plain_ccd": float(sim[~streak].mean()) if (~streak).any() else None,
            "peak_rss_mib_max": float(max(r["peak_rss_mib"] for r in rows))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rate-ccds", type=int, default=8,
                        help="full-size CCDs for the 1 vs 2 worker rates (half with a streak)")
    parser.add_argument("--skip-whole", action="store_true", help="skip the 189-CCD runs")
    parser.add_argument("--skip-dask", action="store_true")
    parser.add_argument("--paired", type=int, default=0, metavar="N",
                        help="N CCDs without and N with the streak, each against the baseline "
                             "in this process")
    parser.add_argument("--skip-rates", action="store_true", help="skip the 1 vs 2 worker rates")
    parser.add_argument("--baseline-no-fsync", dest="baseline_fsync", action="store_false",
                        help="the baseline deletes each file without flushing it to disk "
                             "first (the runner flushes its files): most of its bytes never "
                             "reach the disk")
    parser.add_argument("--out", default="out/bench")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    work = tempfile.mkdtemp(prefix="bench_focalplane_", dir=args.out)
    fscene = parse_focal_scene(load_scene_file(SCENE))
    plan = make_plan(fscene)
    crossed = list(plan.streak_ccds(fp.CCDS))
    plain = [c for c in fp.CCDS if c not in crossed]
    half = args.rate_ccds // 2
    sample = tuple(sorted(crossed[:half] + plain[:args.rate_ccds - half], key=lambda c: c.id))
    report = {"crossed": len(crossed), "baseline_fsync": args.baseline_fsync,
              "load_average_at_start": os.getloadavg()}
    try:
        if args.paired:
            report["paired"] = paired(plan, crossed, plain, args.paired,
                                      os.path.join(work, "p"), args.baseline_fsync)
            print(json.dumps({"paired": report["paired"]}), flush=True)
        # The fork server (imports done once, workers forked from it) is up before any clock.
        with parallel.process_pool(1) as pool:
            pool.submit(os.getpid).result()
        # Cold: the clock includes starting the workers (a fork of that server, the stars'
        # PSF stamps); warm: each worker has done that first, as in a long run.
        for start in () if args.skip_rates else ("cold", "warm"):
            rates = {}
            for workers in (1, 2):
                with parallel.process_pool(workers) as pool:
                    if start == "warm":
                        pids = set(pool.map(warm_worker, [fscene] * workers))
                        assert len(pids) == workers, pids
                    seconds, rows = timed_run(plan, sample, pool, os.path.join(work, "r"))
                rates[workers] = len(sample) / seconds
                key = f"pool_{workers}" + ("" if start == "cold" else "_warm")
                report[key] = {"seconds": seconds, "ccds_per_s": rates[workers],
                               **summary(rows)}
                print(json.dumps({key: report[key]}), flush=True)
            key = "parallel_efficiency_2" + ("" if start == "cold" else "_warm")
            report[key] = rates[2] / (2 * rates[1])
            print(f"parallel efficiency at 2 workers ({start} workers): {report[key]:.3f} "
                  f"(goal >= 0.85)", flush=True)
        if not args.skip_dask and not args.skip_rates:
            with parallel.dask_executor("local", workers=2) as executor:
                seconds, rows = timed_run(plan, sample, executor, os.path.join(work, "d"))
            report["dask_local_2"] = {"seconds": seconds, "ccds_per_s": len(sample) / seconds,
                                      **summary(rows)}
            print(json.dumps({"dask_local_2": report["dask_local_2"]}), flush=True)
        if not args.skip_whole:
            base_dir = os.path.join(work, "b")
            os.makedirs(base_dir, exist_ok=True)
            def baseline_189(pool):
                start = time.perf_counter()
                rows = list(pool.map(baseline_ccd, [(ccd_scene(fscene, c), c.name, base_dir,
                                                     args.baseline_fsync) for c in fp.CCDS]))
                return time.perf_counter() - start, rows

            # The baseline before and after the exposure: the ratio is to their mean, so a
            # drift of the machine's speed during the run does not favour either side.
            with parallel.process_pool(2) as pool:
                base_before, base_rows = baseline_189(pool)
                whole, rows = timed_run(plan, fp.CCDS, pool, os.path.join(work, "w"))
                base_after, more_rows = baseline_189(pool)
                only, only_rows = timed_run(plan, tuple(crossed), pool,
                                            os.path.join(work, "s"))
            base = (base_before + base_after) / 2
            report["whole_189"] = {"seconds": whole, **summary(rows)}
            report["baseline_poisson_sky_189"] = {
                "seconds": base, "seconds_before": base_before, "seconds_after": base_after,
                "per_ccd_s": float(np.mean([r["seconds"] for r in base_rows + more_rows])),
                # A process's peak RSS is its lifetime's: the first pass, before the exposure.
                "peak_rss_mib_max": float(max(r["peak_rss_mib"] for r in base_rows))}
            report["whole_over_baseline"] = whole / base
            print(f"whole exposure over the baseline: {whole:.0f} s / {base:.0f} s "
                  f"(before {base_before:.0f} s, after {base_after:.0f} s) = "
                  f"{whole / base:.2f} (goal <= 1.2)", flush=True)
            report["streak_ccds_only"] = {"seconds": only, "ccds": len(crossed),
                                          "fraction_of_whole_time": only / whole,
                                          "fraction_of_ccds": len(crossed) / 189}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report["load_average_at_end"] = os.getloadavg()
    print(json.dumps(report, indent=1))
    with open(os.path.join(args.out, "bench_focalplane.json"), "w") as stream:
        json.dump(report, stream, indent=1)


if __name__ == "__main__":
    main()
