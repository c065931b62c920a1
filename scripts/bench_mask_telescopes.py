#!/usr/bin/env python
"""``inject mask`` on images at other telescopes' settings (the table of the masking guide).

Each row is an :class:`inject.masking.synthetic.Instrument` (pixel scale, seeing, aperture
and the satellite's defocus, sky, read noise, gain, full well; integer images with a
pedestal, Moffat stars with the brightest saturated and bleeding, a bright resolved galaxy).
Per row:

- **completeness** at a peak S/N of 1, 3 and 10 per pixel: ``--images`` images each, one
  streak at a random angle through a random point of the middle half; found (within 0.5 deg
  and 5 px) and located (both ends within 1 px, angle within 0.2 deg);
- **FWHM error**: the median of measured / true - 1 at S/N 10 (3 if none at 10), where
  the true FWHM (of the drawn cross-section, before pixelisation) is at least 2 px; below
  that, the share of streaks flagged ``fwhm_at_pixel_scale``;
- **false positives** on ``--fp-images`` streak-free images (stars, saturated ones with
  bleed trails, and the galaxy);
- **four streaks**: three parallel (100 and 150 px apart, or scaled to fit) and a crossing
  one at S/N 30: how many located within 1 px and 0.2 deg, and how many masked (99% of the
  pixels on the true line under a mask).

Usage::

    python scripts/bench_mask_telescopes.py [--images 10] [--fp-images 20] [--rows 0 1 2]
        [--out out/bench_mask_telescopes.json]
"""
import argparse
import json
import time

import numpy as np

from inject.masking.run import analyse
from inject.masking.synthetic import (
    INSTRUMENTS,
    cross_section,
    four_streaks,
    located,
    make_image,
    masked_fraction,
    match,
)

SNRS = (1.0, 3.0, 10.0)


def random_streak(instrument, snr, rng):
    ny, nx = instrument.shape
    return (float(rng.uniform(-90, 90)), float(rng.uniform(0.25, 0.75) * nx),
            float(rng.uniform(0.25, 0.75) * ny), snr)


def run_row(k, images, fp_images, seed0=100):
    ins = INSTRUMENTS[k]
    truth_fwhm = cross_section(ins)[2]
    row = {"name": ins.name, "shape": list(ins.shape), "pixel_scale": ins.pixel_scale,
           "true_fwhm_px": truth_fwhm, "completeness": {}, "located": {}, "fwhm_rel_err": {},
           "flagged": {}}
    t_mask = []
    for snr in SNRS:
        found = strict = 0
        errs, flags = [], []
        for i in range(images):
            seed = seed0 + 1000 * k + 100 * SNRS.index(snr) + i
            rng = np.random.default_rng(seed)
            img, truths = make_image(ins, [random_streak(ins, snr, rng)], seed=seed)
            t0 = time.perf_counter()
            res = analyse(img, pixel_scale=ins.pixel_scale, n_boot=0)
            t_mask.append(time.perf_counter() - t0)
            j = match(res.streaks, truths)[0]
            if j is None:
                continue
            s = res.streaks[j]
            found += 1
            strict += located(s, truths[0])
            if s["fwhm_measured"]:
                errs.append(s["fwhm_px"] / truth_fwhm - 1)
                flags.append(s["fwhm_at_pixel_scale"])
        row["completeness"][snr] = found / images
        row["located"][snr] = strict / images
        row["fwhm_rel_err"][snr] = float(np.median(errs)) if errs else None
        row["flagged"][snr] = float(np.mean(flags)) if flags else None
    fp = 0
    for i in range(fp_images):
        img, _ = make_image(ins, (), seed=seed0 + 1000 * k + 900 + i)
        fp += len(analyse(img, pixel_scale=ins.pixel_scale, n_boot=0).streaks)
    row["false_positives"] = fp
    row["fp_images"] = fp_images
    img, truths = make_image(ins, four_streaks(ins, snr=30.0, seed=k), seed=seed0 + 1000 * k)
    res = analyse(img, pixel_scale=ins.pixel_scale, n_boot=0)
    idx = match(res.streaks, truths)
    row["four_located"] = sum(j is not None and located(res.streaks[j], t)
                              for j, t in zip(idx, truths))
    row["four_masked"] = sum(masked_fraction(img.shape, res.streaks, t) >= 0.99 for t in truths)
    row["four_found_total"] = len(res.streaks)
    row["mask_seconds_median"] = float(np.median(t_mask))
    return row


def fwhm_cell(row):
    snr = 10.0 if row["fwhm_rel_err"][10.0] is not None else 3.0
    err = row["fwhm_rel_err"][snr]
    if err is None:
        return "n/a"
    if row["true_fwhm_px"] < 2.0:
        return f"{err:+.1%} (flagged {row['flagged'][snr]:.0%})"
    return f"{err:+.1%}"


def table(rows):
    lines = ["| setting | image | true FWHM px | found at S/N 1 / 3 / 10 (located) | FWHM error "
             "| false positives | four streaks located / masked | mask s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        comp = " / ".join(f"{r['completeness'][s]:.0%} ({r['located'][s]:.0%})" for s in SNRS)
        lines.append(f"| {r['name']} | {r['shape'][1]} x {r['shape'][0]} | "
                     f"{r['true_fwhm_px']:.2f} | {comp} | {fwhm_cell(r)} | "
                     f"{r['false_positives']} on {r['fp_images']} | {r['four_located']}/4, "
                     f"{r['four_masked']}/4 (of {r['four_found_total']} found) | "
                     f"{r['mask_seconds_median']:.2f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--images", type=int, default=10, help="images per S/N and row (10)")
    p.add_argument("--fp-images", type=int, default=20, help="streak-free images per row (20)")
    p.add_argument("--rows", type=int, nargs="*", default=list(range(len(INSTRUMENTS))))
    p.add_argument("--out", help="write the rows as JSON")
    args = p.parse_args(argv)
    rows = []
    for k in args.rows:
        t0 = time.perf_counter()
        rows.append(run_row(k, args.images, args.fp_images))
        print(f"row {k} ({INSTRUMENTS[k].name}) {time.perf_counter() - t0:.0f} s", flush=True)
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    print(table(rows))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
