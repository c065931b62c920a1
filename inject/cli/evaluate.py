"""``inject evaluate``: a seeded campaign scoring streak maskers against injected truth.

The paper's satellite (7.25 x 2.65 m box) is simulated on a detector cut-out of the default
field (g band, 30 s, zenith 70 deg, stars, noise) at every height and magnitude, on seeded
random tracks crossing the image, plus streak-free images of the same field (other seeds,
held out from the calibration of the detection threshold) for false positives; every masker
runs on the same images and is scored by :func:`inject.masking.evaluate.evaluate`. Writes
``records.csv`` (one row per image, masker and streak), ``summary.csv`` and ``summary.md``
(per masker, height and magnitude; streak-free images form their own rows) and three PNG
plots; prints the markdown table (or JSON with ``--json``); progress is logged
(:mod:`inject.progress`).
"""
import contextlib
import csv
import io
import json
import logging
import math
import os
import sys

from inject.errors import InputError, OutputError
from inject.io.atomic import atomic_path, output_group
from inject.masking.run import json_safe
from inject.maskplanes import MASK_PLANES
from inject.signals import deferred

log = logging.getLogger(__name__)

# ``inject --help`` imports this module: the simulator, inject.masking.evaluate and the
# maskers (GalSim, SciPy, OpenCV, logging...) are imported inside the functions that use them.

#: Defaults of the campaign: magnitudes spanning peak S/N per pixel ~1.7 to ~0.03 at 550 km.
DEFAULT_MAGS = (11.0, 12.0, 13.0, 13.5, 14.0, 14.5, 15.0, 15.5)
DEFAULT_HEIGHTS = (550.0, 350.0)
DEFAULT_SIZE = 1024
DEFAULT_SEEDS = 5

#: Streak-free images per campaign (false positives), and the seed they start after: seeds
#: 1-100 calibrated :data:`inject.masking.detect.FALSE_ALARM_Z`, so these are held out.
DEFAULT_STREAK_FREE = 20
STREAK_FREE_SEED0 = 1000

#: ``inject evaluate --help``'s description (the module docstring without its markup).
DESCRIPTION = (
    "A seeded campaign scoring streak maskers against injected truth. The paper's satellite "
    "(7.25 x 2.65 m box) is simulated on a detector cut-out of the default field (g band, 30 s, "
    "zenith 70 deg, stars, noise) at every height and magnitude, on seeded random tracks "
    "crossing the image, plus streak-free images of the same field (seeds held out from the "
    "calibration of the detection threshold) for false positives; every masker runs on the "
    "same images. Writes records.csv (one row per image, masker and streak), summary.csv and "
    "summary.md (per masker, height and magnitude; streak-free images have their own rows) "
    "and three PNG plots into the output directory; prints the markdown table (or JSON with "
    "--json) and progress on stderr. If the campaign fails or is stopped, nothing is "
    "written, and a directory made for it is removed.")

#: Pixels of a full LSSTCam ITL CCD, for false positives per CCD from smaller images.
CCD_PIXELS = 4072 * 4000

#: Columns of the summary table, with their markdown headers and formats.
COLUMNS = (("masker", "masker", "{}"), ("height_km", "km", "{:.0f}"), ("mag", "mag", "{:.2f}"),
           ("n", "n", "{}"), ("peak_sb", "peak/σ", "{:.3f}"), ("int_snr", "S/N", "{:.1f}"),
           ("completeness", "compl.", "{:.2f}"), ("line_completeness", "line", "{:.2f}"),
           ("fp_per_ccd", "FP", "{:.2f}"), ("angle_err_deg", "Δangle°", "{:.3f}"),
           ("offset_px", "Δoff px", "{:.2f}"), ("fwhm_bias_pct", "FWHM bias%", "{:+.1f}"),
           ("fwhm_scatter_pct", "FWHM sd%", "{:.1f}"), ("recall", "recall", "{:.3f}"),
           ("overmask", "overmask", "{:.2f}"), ("iou", "IoU", "{:.3f}"),
           ("flux_left", "flux left", "{:.3f}"), ("masked_px", "masked px", "{:.0f}"),
           ("time_s", "time s", "{:.3f}"))


def paper_satellite(height, mag, x0, y0, angle):
    """The paper's satellite (7.25 x 2.65 m box) on a track crossing the image."""
    return {"height": float(height), "shape": {"type": "box", "length": 7.25, "width": 2.65},
            "mag": float(mag), "track": {"x0": float(x0), "y0": float(y0),
                                         "angle": float(angle)}}


def campaign_images(heights, mags, seeds, size, progress=None):
    """Simulated images of the campaign, with labels: ``(SceneResult, {height_km, mag,
    seed})``, generated lazily (one image in memory at a time).

    Seed ``s`` fixes the track (through the central 60% of the image, any angle) and the
    noise, stars and sky, so the same seed gives the same field at every height and magnitude.
    ``progress``: an :class:`inject.progress.Progress` told of each image, or None.
    """
    import numpy as np

    from inject.config import DEFAULT_SCENE, parse_scene
    from inject.scene import simulate
    from inject.schema import apply_overrides
    for height in heights:
        for mag in mags:
            for seed in seeds:
                rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(99,)))
                x0, y0, angle = (rng.uniform(0.2, 0.8) * size, rng.uniform(0.2, 0.8) * size,
                                 rng.uniform(0, 180))
                raw = apply_overrides(DEFAULT_SCENE, [f"seed={seed}", f"detector.nx={size}",
                                                      f"detector.ny={size}"])
                raw["satellites"] = [paper_satellite(height, mag, x0, y0, angle)]
                if progress is not None:
                    progress.update(f"{height:.0f} km mag {mag:.2f} seed {seed}")
                yield simulate(parse_scene(raw)), {"height_km": height, "mag": mag,
                                                   "seed": seed}


def streak_free_images(count, size, progress=None, seed0=STREAK_FREE_SEED0):
    """``count`` streak-free images of the campaign's field (seeds ``seed0 + 1`` on), with
    labels ``{height_km: None, mag: None, seed, streak_free: True}``, generated lazily
    (``progress`` as in :func:`campaign_images`)."""
    from inject.config import DEFAULT_SCENE, parse_scene
    from inject.scene import simulate
    from inject.schema import apply_overrides
    for k in range(1, count + 1):
        seed = seed0 + k
        raw = apply_overrides(DEFAULT_SCENE, [f"seed={seed}", f"detector.nx={size}",
                                              f"detector.ny={size}"])
        raw["satellites"] = []
        if progress is not None:
            progress.update(f"streak-free seed {seed}")
        yield simulate(parse_scene(raw)), {"height_km": None, "mag": None, "seed": seed,
                                           "streak_free": True}


def false_positive_summary(records, size):
    """False positives of each masker on the streak-free images: ``{masker: {images,
    detections, per_image, per_ccd}}`` (``per_ccd`` scaled to a full ITL CCD's area)."""
    out = {}
    for r in records:
        if not r.get("streak_free"):
            continue
        s = out.setdefault(r["masker"], {"images": 0, "detections": 0})
        s["images"] += 1
        s["detections"] += int(r["false_positives"])
    for s in out.values():
        s["per_image"] = s["detections"] / s["images"]
        s["per_ccd"] = s["per_image"] * CCD_PIXELS / float(size * size)
    return out


def bad_pixels(sim):
    """Unusable pixels of a simulated image (the LSST bad planes of its mask)."""
    from inject.masking.detect import BAD_PLANES  # OpenCV, SciPy: not for --help

    bits = sum(1 << MASK_PLANES[p] for p in BAD_PLANES if p in MASK_PLANES)
    return (sim.mask & bits) != 0


def pixel_loss(summary, masker, heights=(550.0, 350.0)):
    """Mean masked pixels per image of ``masker`` at each magnitude for two heights, and
    their ratio (second over first): ``[{mag, px_<h>..., ratio}]``."""
    a, b = heights
    by = {(r["height_km"], r["mag"]): r for r in summary
          if r["masker"] == masker and r["height_km"] is not None}
    rows = []
    for mag in sorted({m for (_, m) in by}):
        if (a, mag) in by and (b, mag) in by:
            pa, pb = by[(a, mag)]["masked_px"], by[(b, mag)]["masked_px"]
            rows.append({"mag": mag, f"px_{a:.0f}": pa, f"px_{b:.0f}": pb,
                         "ratio": pb / pa if pa else float("nan")})
    return rows


def fifty_percent_points(summary):
    """Peak surface brightness (sky sigma) of 50% completeness per masker and height."""
    from inject.masking.evaluate import completeness_point

    out = {}
    for key in sorted({(r["masker"], r["height_km"]) for r in summary
                       if r["height_km"] is not None}):
        rows = [r for r in summary if (r["masker"], r["height_km"]) == key]
        out[key] = completeness_point([r["peak_sb"] for r in rows],
                                      [r["completeness"] for r in rows])
    return out


def _fmt(value, spec):
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return spec.format(value)


def markdown_table(summary):
    """The summary as a markdown table."""
    lines = ["| " + " | ".join(h for _, h, _ in COLUMNS) + " |",
             "|" + "|".join("---" for _ in COLUMNS) + "|"]
    for r in summary:
        lines.append("| " + " | ".join(_fmt(r.get(k), f) for k, _, f in COLUMNS) + " |")
    return "\n".join(lines)


#: What a campaign writes into ``--out`` (pixel_loss.* only with two heights or more).
OUTPUT_FILES = ("records.csv", "summary.csv", "summary.md", "pixel_loss.csv",
                "completeness.png", "fwhm_bias.png", "pixel_loss.png")


def _write_text(path, text, overwrite=False):
    with atomic_path(path, overwrite) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)


def _csv_text(rows):
    keys = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def write_plots(summary, loss, outdir, masker, overwrite=False):
    """Completeness vs peak SB, FWHM bias vs integrated S/N, pixel loss 550 vs 350 km (PNG,
    written atomically); returns the paths."""
    # Figures on their own Agg canvas: no pyplot, so the caller's backend and figures stay.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    paths = []

    def figure():
        fig = Figure(figsize=(6, 4))
        FigureCanvasAgg(fig)
        return fig, fig.subplots()

    def save(fig, name):
        path = os.path.join(outdir, name)
        with atomic_path(path, overwrite) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
        paths.append(path)

    groups = sorted({(r["masker"], r["height_km"]) for r in summary
                     if r["height_km"] is not None})

    def series(key, x, y):
        rows = sorted((r for r in summary if (r["masker"], r["height_km"]) == key),
                      key=lambda r: r[x])
        return [r[x] for r in rows], [r[y] for r in rows]

    fig, ax = figure()
    for key in groups:
        ax.plot(*series(key, "peak_sb", "completeness"), "o-", label=f"{key[0]} {key[1]:.0f} km")
    ax.set(xscale="log", xlabel="peak surface brightness / sky σ per pixel",
           ylabel="completeness", ylim=(-0.03, 1.03))
    ax.axhline(0.5, color="0.7", lw=0.8)
    ax.legend(fontsize=8)
    save(fig, "completeness.png")

    fig, ax = figure()
    for key in groups:
        x, y = series(key, "int_snr", "fwhm_bias_pct")
        if any(math.isfinite(v) for v in y):
            ax.plot(x, y, "o-", label=f"{key[0]} {key[1]:.0f} km")
    ax.set(xscale="log", xlabel="integrated (matched-filter) S/N",
           ylabel="FWHM bias, % (measured / true − 1)")
    ax.axhline(0, color="0.7", lw=0.8)
    ax.legend(fontsize=8)
    save(fig, "fwhm_bias.png")

    if loss:
        fig, ax = figure()
        keys = [k for k in loss[0] if k.startswith("px_")]
        for k in keys:
            ax.plot([r["mag"] for r in loss], [r[k] for r in loss], "o-",
                    label=f"{k[3:]} km")
        ax.set(xlabel="stationary magnitude (550 km, face-on)", ylabel="masked pixels per image",
               title=f"{masker}: pixel loss, same satellite at two heights")
        ax.legend(fontsize=8)
        save(fig, "pixel_loss.png")
    return paths


def run_campaign(maskers, heights=DEFAULT_HEIGHTS, mags=DEFAULT_MAGS, seeds=DEFAULT_SEEDS,
                 size=DEFAULT_SIZE, truth_sigma=None, streak_free=DEFAULT_STREAK_FREE):
    """Run a seeded campaign (with ``streak_free`` streak-free images for false positives);
    returns ``(records, summary)`` (see :func:`inject.masking.evaluate.evaluate` and
    :func:`~inject.masking.evaluate.summarise`). Its progress over the images is this
    module's logger's (:mod:`inject.progress`)."""
    import itertools

    from inject.masking.evaluate import TRUTH_SIGMA, evaluate, load_masker, summarise
    from inject.progress import Progress

    maskers = [load_masker(m) for m in maskers]  # fail on a bad name before simulating
    total = len(heights) * len(mags) * seeds + streak_free
    with Progress(total, "simulating and masking images", "image", log) as progress:
        images = itertools.chain(
            campaign_images(heights, mags, range(1, seeds + 1), size, progress),
            streak_free_images(streak_free, size, progress))
        records = evaluate(images, maskers,
                           TRUTH_SIGMA if truth_sigma is None else truth_sigma, bad=bad_pixels)
    return records, summarise(records)


def add_evaluate_parser(sub):
    """Register ``inject evaluate`` on an argparse sub-parser collection."""
    p = sub.add_parser(
        "evaluate", help="score streak maskers against injected truth (seeded campaign)",
        description=DESCRIPTION)
    p.add_argument("--out", "-o", "--output", dest="out", required=True, metavar="DIR",
                   help="output directory (created if missing)")
    p.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, metavar="N",
                   help="images per height and magnitude")
    p.add_argument("--mags", type=float, nargs="+", default=list(DEFAULT_MAGS), metavar="MAG",
                   help="stationary AB magnitudes at 550 km, face-on")
    p.add_argument("--heights", type=float, nargs="+", default=list(DEFAULT_HEIGHTS),
                   metavar="KM", help="orbit heights")
    p.add_argument("--detector", type=int, default=DEFAULT_SIZE, metavar="PX",
                   help="side of the square detector cut-out (4000 for ~a CCD)")
    p.add_argument("--masker", action="append", metavar="NAME",
                   help="masker to score: inject (ours), findsat_mrt (acstools) or "
                        "module:function taking an image and returning a bool mask; "
                        "repeatable (default: inject)")
    p.add_argument("--streak-free", type=int, default=DEFAULT_STREAK_FREE, metavar="N",
                   help=f"streak-free images for false positives (seeds "
                        f"{STREAK_FREE_SEED0 + 1} on, held out from the threshold's calibration)")
    p.add_argument("--truth-sigma", type=float, default=1.0, metavar="T",
                   help="true region = streak model > T x sky sigma")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files of an earlier campaign in --out")
    p.add_argument("--json", action="store_true",
                   help="print the summary, 50%% points and pixel loss as JSON")
    p.set_defaults(func=run_evaluate)
    return p


def _check(args):
    from inject.validate import check

    if args.seeds < 1:
        raise InputError("--seeds", args.seeds, "must be >= 1")
    if args.seeds > STREAK_FREE_SEED0:
        raise InputError("--seeds", args.seeds, f"must be <= {STREAK_FREE_SEED0} (the "
                         "streak-free images use the seeds after it: they must stay held out)")
    if args.streak_free < 0:
        raise InputError("--streak-free", args.streak_free, "must be >= 0")
    if args.detector < 64:
        raise InputError("--detector", args.detector, "must be >= 64 px")
    check("detector.ny", args.detector, "--detector")  # a cut-out of one CCD
    for h in args.heights:
        if not (math.isfinite(h) and h > 0):
            raise InputError("--heights", h, "must be > 0 km")
        check("height", h, "--heights")
    for m in args.mags:
        if not math.isfinite(m):
            raise InputError("--mags", m, "must be finite")
        check("mag", m, "--mags")
    if not (math.isfinite(args.truth_sigma) and args.truth_sigma > 0):
        raise InputError("--truth-sigma", args.truth_sigma, "must be > 0")


@contextlib.contextmanager
def _output_directory(path):
    """Make ``path`` (and missing parents) for the block; remove the directories it made if
    the block fails or is stopped and they are still empty (the outputs appear only at the
    block's end, so on failure they are)."""
    missing, head = [], os.path.abspath(path)
    while not os.path.isdir(head) and head != os.path.dirname(head):
        missing.append(head)
        head = os.path.dirname(head)
    made = []
    try:
        try:
            for directory in reversed(missing):
                with deferred():  # made and recorded together
                    os.mkdir(directory)
                    made.append(directory)
        except OSError as err:
            raise OutputError(f"{path}: cannot create ({err.strerror or err})") from None
        yield
    except BaseException:
        for directory in reversed(made):  # deepest first; one with files in it stays
            with contextlib.suppress(OSError):
                os.rmdir(directory)
        raise


def run_evaluate(args):
    """The ``inject evaluate`` command (``args`` from :func:`add_evaluate_parser`)."""
    _check(args)  # before the engine's imports
    from inject.masking.evaluate import load_masker

    maskers = args.masker or ["inject"]
    for masker in maskers:  # a bad name or a missing optional package: before any work
        load_masker(masker)
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise OutputError(f"{args.out}: exists and is not a directory")

    # The group checks every target before the campaign's minutes of work, and makes its
    # files appear together at the end, or none of them (a full disk...); the directory is
    # removed again if it was made for a campaign that failed.
    with _output_directory(args.out), output_group(
            [os.path.join(args.out, name) for name in OUTPUT_FILES], args.overwrite):
        records, summary = run_campaign(maskers, args.heights, args.mags, args.seeds,
                                        args.detector, args.truth_sigma, args.streak_free)
        false = false_positive_summary(records, args.detector)
        names = [load_masker(maskers[0]).name]  # pixel loss: the first masker given
        loss = pixel_loss(summary, names[0], tuple(args.heights[:2])) \
            if len(args.heights) >= 2 else []
        points = fifty_percent_points(summary)
        table = markdown_table(summary)
        for name, text in (("records.csv", _csv_text(records)),
                           ("summary.csv", _csv_text(summary)), ("summary.md", table + "\n"),
                           ("pixel_loss.csv", _csv_text(loss) if loss else None)):
            if text is not None:
                _write_text(os.path.join(args.out, name), text, args.overwrite)
        plots = write_plots(summary, loss, args.out, names[0], args.overwrite)
    if args.json:
        out = {"summary": summary,
               "completeness_50": [{"masker": m, "height_km": h, "peak_sb": v}
                                   for (m, h), v in points.items()],
               "pixel_loss": loss, "false_positives": false, "files": plots}
        json.dump(json_safe(out), sys.stdout)
        sys.stdout.write("\n")
        return
    print(table)
    print()
    for (m, h), v in points.items():
        print(f"50% completeness: {m} at {h:.0f} km: peak {_fmt(v, '{:.3f}')} sky sigma per px")
    for r in loss:
        a, b = [k for k in r if k.startswith("px_")]
        print(f"pixel loss ({names[0]}) mag {r['mag']:.2f}: {a[3:]} km {r[a]:.0f} px, "
              f"{b[3:]} km {r[b]:.0f} px, ratio {b[3:]}/{a[3:]} = {_fmt(r['ratio'], '{:.2f}')}")
    for m, f in false.items():
        print(f"false positives ({m}) on {f['images']} streak-free {args.detector} x "
              f"{args.detector} images: {f['detections']} ({f['per_image']:.3f} per image, "
              f"{f['per_ccd']:.3f} per CCD area)")
    log.info("wrote %s/records.csv, summary.csv, summary.md, %s", args.out,
             ", ".join(os.path.basename(p) for p in plots))
