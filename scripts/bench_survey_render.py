"""``inject survey --render`` on a sample of a night's streaked visits: planned against
measured, throughput on a process pool and on a Dask LocalCluster, and the CCD files'
compression.

For each constellation: the night is planned once (``inject survey``); its streaked visits go
to a smaller database (the constellation files state their shells' epoch, so the plan of the
sample is the night's), which is rendered with ``--render --cutouts`` on a
process pool and again on a Dask LocalCluster (``--scheduler local``), both with
``--workers``. It prints, per streak, the planned and measured FWHM, mask width and pixels
(on the rendered cut-outs), the medians of their ratios, and the CCDs per second of each
executor. ``--full`` also renders whole CCDs of the first streaked visit (the throughput of
full CCDs), and ``--compression`` writes one full CCD plain, lossless and lossy: sizes, write
times, the noise the lossy file adds (rms difference over the sky's sigma) and, with a
Python >= 3.12 lsst-images venv (``scripts/check_lsst.py`` builds one), lsst-images'
``MaskedImage.read_legacy`` reading the compressed files.

``--paired N`` measures, in this one process and one thread, the seconds per CCD of the
survey's render of each of the first N streaked visits (the visit's plan, shared by its CCDs,
then each CCD's cut-out rendered, written and masked) against ``inject focalplane``'s render of
the same CCDs of the same scene (its plan, then each CCD's task: the same cut-out and
compression, no masker), alternating which goes first, each from empty profile caches (as a
new scene in a worker meets them), the stars' PSF stamps warm in both.

Run::

    python scripts/make_opsim_night.py -o out/night.db
    python scripts/bench_survey_render.py out/night.db --workers 2 --full --compression
    python scripts/bench_survey_render.py out/night.db --paired 2 --rounds 2
"""
import argparse
import contextlib
import csv
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONSTELLATIONS = ("sample_fields/constellation_550km.yaml",
                  "sample_fields/constellation_350km.yaml")


def survey(*argv):
    """``inject survey`` in a child process (its own fork server and pools); seconds."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "inject", "survey", *map(str, argv)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"inject survey {' '.join(map(str, argv))}: {done.stderr}")
    return time.perf_counter() - started


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def sample_database(db, ids, path):
    """The visits ``ids`` of an opsim database, in a database of their own."""
    src = sqlite3.connect(db)
    columns = [r[1] for r in src.execute("PRAGMA table_info(observations)")]
    marks = ",".join("?" * len(ids))
    rows = src.execute(f"SELECT * FROM observations WHERE observationId IN ({marks})",
                       [int(i) for i in ids]).fetchall()
    src.close()
    with contextlib.suppress(FileNotFoundError):
        os.remove(path)
    dst = sqlite3.connect(path)
    types = {r: "REAL" for r in columns}
    dst.execute(f"CREATE TABLE observations ({', '.join(f'{c} {types[c]}' for c in columns)})")
    dst.executemany(f"INSERT INTO observations VALUES ({','.join('?' * len(columns))})", rows)
    dst.commit()
    dst.close()
    return path


def _f(value):
    return float(value) if value not in ("", None) else float("nan")


def compare(rows):
    """Per-streak planned vs measured lines and the medians of the ratios."""
    lines, ratios = [], {"fwhm": [], "width": [], "pixels": []}
    for r in rows:
        pairs = (("fwhm", _f(r["fwhm_arcsec"]), _f(r["measured_fwhm_arcsec"])),
                 ("width", _f(r["mask_width_px"]), _f(r["measured_mask_width_px"])),
                 ("pixels", _f(r["planned_pixels_rendered"]), _f(r["measured_pixels_lost"])))
        for key, a, b in pairs:
            if np.isfinite(a) and np.isfinite(b) and a > 0:
                ratios[key].append(b / a)
        lines.append(f"| {r['observationId']} | {r['satellite']} | {r['found_ccds']}/"
                     f"{r['rendered_ccds']} | {_f(r['fwhm_arcsec']):.2f} | "
                     f"{_f(r['measured_fwhm_arcsec']):.2f} | {_f(r['mask_width_px']):.1f} | "
                     f"{_f(r['measured_mask_width_px']):.1f} | "
                     f"{_f(r['planned_pixels_rendered']):.0f} | "
                     f"{_f(r['measured_pixels_lost']):.0f} |")
    return lines, ratios


def summarise(ratios):
    out = []
    for key, values in ratios.items():
        if values:
            q = np.percentile(values, [0, 50, 100])
            out.append(f"{key} measured/planned: median {q[1]:.3f} (range {q[0]:.3f}-{q[2]:.3f},"
                       f" {len(values)} streaks)")
    return out


def compression_check(folder, lsst_venv):
    """One full CCD of a streak written plain, lossless and lossy."""
    from astropy.io import fits

    from inject.config import parse_scene
    from inject.io.fits import write_exposure
    from inject.scene import simulate

    scene = parse_scene({"seed": 3, "band": "r", "detector": {"type": "e2v"}, "pointing": {
        "ra": 52.5, "dec": -28.1, "rotation": 20.0}, "satellites": [{
            "height": 550.0, "phi": 90.0, "shape": {"type": "box", "length": 7.25,
                                                    "width": 2.65},
            "mag": 5.0, "ref_range": 550.0, "track": {"x0": 300.0, "y0": 200.0,
                                                      "angle": 33.0}}]})
    from inject.camera import layout as fp
    from inject.camera.wcs import ccd_wcs

    result = simulate(scene)
    header = ccd_wcs(fp.ccd("R22_S11"), scene.pointing).to_header(relax=True)
    sizes, times = {}, {}
    for comp in (None, "lossless", "lossy"):
        path = Path(folder) / f"ccd-{comp or 'plain'}.fits"
        started = time.perf_counter()
        write_exposure(path, scene, result, scene.detector.gain, wcs_header=header,
                       overwrite=True, compression=comp)
        times[comp] = time.perf_counter() - started
        sizes[comp] = os.path.getsize(path)
    with fits.open(Path(folder) / "ccd-lossy.fits") as hdus:
        image = np.asarray(hdus["IMAGE"].data)
    with fits.open(Path(folder) / "ccd-lossless.fits") as hdus:
        same = all(np.array_equal(np.asarray(hdus[n].data), getattr(result, a))
                   for n, a in (("IMAGE", "image"), ("MASK", "mask"),
                                ("VARIANCE", "variance")))
    sky = np.asarray(result.streak_model) == 0
    sigma = float(np.sqrt(np.median(result.variance)))
    noise = float(np.sqrt(np.mean((image - result.image)[sky] ** 2)) / sigma)
    print(f"\nCompression of one full e2v CCD (4096 x 4004, a streak, stars), astropy "
          f"{fits.__name__}:")
    print("| file | bytes | ratio to plain | write s |")
    print("|---|---|---|---|")
    for comp in (None, "lossless", "lossy"):
        print(f"| {comp or 'plain'} | {sizes[comp]:,} | {sizes[comp] / sizes[None]:.3f} | "
              f"{times[comp]:.2f} |")
    print(f"lossless reads back equal in astropy: {same}; lossy adds rms {noise:.4f} sigma "
          f"(1/(10 sqrt 12) = {1 / (10 * 12 ** 0.5):.4f})")
    exe = Path(lsst_venv) / "bin" / "python"
    if exe.exists():
        sys.path.insert(0, str(ROOT / "scripts"))
        from check_lsst import READER

        paths = [str(Path(folder) / f"ccd-{c}.fits") for c in ("lossless", "lossy")]
        done = subprocess.run([str(exe), "-c", READER, paths[0], "none", paths[1], "none"],
                              capture_output=True, text=True)
        if done.returncode != 0:
            print(f"lsst-images: failed: {done.stderr.strip().splitlines()[-1:]}")
        else:
            for path, res in json.loads(done.stdout).items():
                print(f"lsst-images read_legacy {Path(path).name}: image equal to astropy's "
                      f"{res['image_equal']}, variance {res['variance_equal']}, planes "
                      f"{len(res['planes'])}, WCS within {res['wcs_max_sep_deg']:.1e} deg")
    else:
        print(f"lsst-images: no venv at {lsst_venv} (scripts/check_lsst.py builds one)")


def _fresh_caches():
    """Empty the per-process caches of streak models and profiles: a new visit's scene meets
    them so in a worker (the stars' PSF stamps stay)."""
    from inject import streak
    from inject.exposure import plan
    from inject.render import PROFILE_CACHE

    PROFILE_CACHE.clear()
    for cached in (plan._reach_px, streak._shared_profile, streak._shared_line_spreads):
        cached.cache_clear()


def paired(db, constellation, n_visits, cutout, compression, rounds, folder):
    """Seconds per CCD (wall and CPU) of the survey's render and of the focal plane's, of the
    same CCDs, alternating; per visit and their ratio."""
    from inject.exposure import runner
    from inject.exposure.plan import make_plan
    from inject.survey.constellation import read_constellation
    from inject.survey.plan import plan_visits
    from inject.survey.render import RenderOptions, model_keys, visit_batches
    from inject.survey.visits import read_visits

    runner.limit_threads()
    night = read_visits(db)
    epoch = night[0].start.utc
    const = read_constellation(str(constellation), epoch)
    plans = [p for p in plan_visits(night, const) if p.streaks][:n_visits]
    options = RenderOptions(cutout=cutout, compression=compression)
    batches = visit_batches(plans, const, model_keys(str(constellation)), str(folder),
                            options, str(constellation), epoch)

    def survey_plan(batch):
        return batch.prepare[0](*batch.prepare[1:])

    def survey(batch):
        plan = survey_plan(batch)
        made = time.perf_counter()
        rows = [runner.render_ccd(batch.make_task(plan, ccd)) for ccd in batch.ccds]
        return made, rows

    def focalplane(batch, fscene):
        plan = make_plan(fscene)
        made = time.perf_counter()
        rows = []
        for ccd in batch.ccds:
            task = batch.make_task(plan, ccd)
            rows.append(runner.render_ccd(runner.Task(
                fscene, ccd.name, task.outdir, task.streaks, keep=False, box=task.box,
                compression=task.compression)))
        return made, rows

    first = next(iter(batches.values()))
    os.makedirs(first.outdir, exist_ok=True)
    runner.render_ccd(first.make_task(survey_plan(first), first.ccds[0]))  # imports, stamps
    print("\n| visit | CCDs | survey s/CCD (plan, simulate, write, mask) | CPU | focalplane s/CCD "
          "(plan, simulate, write) | CPU | ratio | CPU ratio |")
    print("|---|---|---|---|---|---|---|---|")
    ratios = []
    for visit, batch in batches.items():
        os.makedirs(batch.outdir, exist_ok=True)
        fscene = survey_plan(batch).fscene
        times = {"survey": [], "focalplane": []}
        for k in range(rounds):
            steps = [("survey", lambda: survey(batch)),
                     ("focalplane", lambda: focalplane(batch, fscene))]
            for name, work in steps if k % 2 == 0 else steps[::-1]:
                _fresh_caches()
                wall, cpu = time.perf_counter(), time.process_time()
                made, rows = work()
                times[name].append((time.perf_counter() - wall, time.process_time() - cpu,
                                    made - wall, rows))
        n = len(batch.ccds)
        cells = {}
        for name, runs in times.items():
            wall = float(np.median([r[0] for r in runs])) / n
            cpu = float(np.median([r[1] for r in runs])) / n
            plan_s = float(np.median([r[2] for r in runs])) / n
            parts = [float(np.median([sum(row.get(key, 0.0) for row in r[3]) for r in runs])) / n
                     for key in ("simulate_s", "write_s", "measure_s")]
            cells[name] = (wall, cpu, plan_s, parts)
        (sw, sc, sp, sparts), (fw, fc, fpl, fparts) = cells["survey"], cells["focalplane"]
        ratios.append((sw / fw, sc / fc))
        print(f"| {visit} | {n} | {sw:.2f} ({sp:.2f}, {sparts[0]:.2f}, {sparts[1]:.2f}, "
              f"{sparts[2]:.2f}) | {sc:.2f} | {fw:.2f} ({fpl:.2f}, {fparts[0]:.2f}, "
              f"{fparts[1]:.2f}) | {fc:.2f} | {sw / fw:.2f} | {sc / fc:.2f} |", flush=True)
    print(f"survey over focalplane per CCD: median {np.median([r[0] for r in ratios]):.2f} "
          f"(wall), {np.median([r[1] for r in ratios]):.2f} (CPU) (goal <= 1.2)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("visits", help="opsim database of the night")
    parser.add_argument("--constellations", nargs="+", default=list(CONSTELLATIONS))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--cutout", type=int, default=1024)
    parser.add_argument("--max-visits", type=int, default=None,
                        help="render only the first N streaked visits of each")
    parser.add_argument("--no-dask", action="store_true")
    parser.add_argument("--full", action="store_true",
                        help="also render the whole CCDs of the first constellation's first "
                             "streaked visit")
    parser.add_argument("--compression", action="store_true",
                        help="the compression of one full CCD (sizes, times, noise, readers)")
    parser.add_argument("--lsst-venv", default=os.environ.get(
        "INJECT_LSST_VENV", str(Path.home() / ".cache" / "inject" / "lsst-images-venv")))
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--paired", type=int, default=0, metavar="N",
                        help="only the paired seconds per CCD against inject focalplane, on "
                             "the first N streaked visits of the first constellation")
    parser.add_argument("--rounds", type=int, default=2, help="with --paired: rounds per visit")
    args = parser.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-survey-render-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.paired:
        print(f"{args.visits}; {args.constellations[0]}; cut-outs {args.cutout} px, lossless; "
              f"in {work}")
        paired(args.visits, ROOT / args.constellations[0], args.paired, args.cutout,
               "lossless", args.rounds, work / "paired")
        return

    print(f"{args.visits}; --workers {args.workers}, cut-outs {args.cutout} px; in {work}")
    for constellation in args.constellations:
        name = Path(constellation).stem
        folder = work / name
        folder.mkdir(exist_ok=True)
        const = ROOT / constellation
        plan_dir = folder / "plan"
        if not (plan_dir / "streaks.csv").exists():
            survey(args.visits, "-o", plan_dir, "--constellation", const, "--no-plots")
        ids = list(dict.fromkeys(r["observationId"] for r in read_csv(plan_dir / "streaks.csv")))
        ids = ids[:args.max_visits] if args.max_visits else ids
        db = sample_database(args.visits, ids, folder / "sample.db")
        results = {}
        executors = [("process pool", [])] + ([] if args.no_dask else
                                             [("Dask LocalCluster", ["--scheduler", "local"])])
        for label, extra in executors:
            out = folder / ("pool" if not extra else "dask")
            seconds = survey(db, "-o", out, "--constellation", const, "--no-plots",
                             "--render", "--cutouts", "--cutout-size", args.cutout,
                             "--workers", args.workers, "--overwrite", *extra)
            render = json.loads((out / "summary.json").read_text())["render"]
            results[label] = (seconds, render, read_csv(out / "streaks.csv"))
        seconds, render, rows = results["process pool"]
        print(f"\n## {name}: {len(ids)} streaked visits, {len(rows)} streaks, "
              f"{render['ccds']} CCDs ({args.cutout} px cut-outs)")
        print("| visit | satellite | found/CCDs | FWHM planned | measured | mask width planned |"
              " measured | pixels planned (rendered) | measured |")
        print("|---|---|---|---|---|---|---|---|---|")
        lines, ratios = compare(rows)
        print("\n".join(lines))
        print("\n".join(summarise(ratios)))
        for label, (seconds, render, _) in results.items():
            print(f"{label}: {render['ccds_rendered']} CCDs in {render['seconds']:.1f} s of "
                  f"rendering ({render['ccds_per_second']:.3f} CCDs/s; the command "
                  f"{seconds:.1f} s), files {render['size_ratio']:.3f} of plain")
        if args.full and name == Path(args.constellations[0]).stem:
            first = sample_database(args.visits, ids[:1], folder / "first.db")
            out = folder / "full"
            seconds = survey(first, "-o", out, "--constellation", const, "--no-plots",
                             "--render", "--workers", args.workers, "--overwrite")
            render = json.loads((out / "summary.json").read_text())["render"]
            records = [json.loads(p.read_text()) for p in (out / "visits").glob("*/*.json")]
            parts = {k: np.median([r["seconds"][k] for r in records])
                     for k in ("simulate", "write", "mask")}
            print(f"whole CCDs (visit {ids[0]}, process pool): {render['ccds_rendered']} CCDs "
                  f"in {render['seconds']:.1f} s ({render['ccds_per_second']:.3f} CCDs/s); "
                  f"median per CCD: simulate {parts['simulate']:.1f} s, write "
                  f"{parts['write']:.1f} s, mask {parts['mask']:.1f} s; files "
                  f"{render['size_ratio']:.3f} of plain")
            lines, ratios = compare(read_csv(out / "streaks.csv"))
            print("\n".join(lines))
    if args.compression:
        compression_check(work, args.lsst_venv)


if __name__ == "__main__":
    main()
