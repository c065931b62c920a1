"""The masker's FWHM against the truth when the streaks are drawn through the traced pupil.

For each case (orbit height; the annulus, or ``pupil: rubin`` on the axis and at 1.25 deg with
the track along and across the field radius) and seed: a 1024 px ITL cut-out of the default
field (g, 30 s, zenith 70 deg, sky, stars, noise) with the paper's satellite on a seeded
random track, ``inject mask``'s analysis of the image, and its FWHM against the TRUTH row's.
With the traced pupil it is also set against the FWHM the annulus would have given (the
truth before ``pupil:``), which is what a test against the old truth would have compared.

Usage::

    python scripts/check_mask_pupil.py [--seeds 8] [--mag 12]
"""
import argparse
import sys

import numpy as np

from inject import DEFAULT_SCENE, parse_scene
from inject.masking.run import analyse
from inject.profile import Seeing
from inject.scene import simulate
from inject.streak import StreakModel

CASES = (("annulus", None, None), ("rubin", 0.0, None), ("rubin", 1.25, "along"),
         ("rubin", 1.25, "across"))
SIZE = 1024


def _scene(height, mag, seed, pupil, field, direction):
    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(-80, 80))
    x0, y0 = rng.uniform(0.35, 0.65, 2) * SIZE
    raw = {k: v for k, v in DEFAULT_SCENE.items() if k != "satellites"}
    raw.update(seed=seed, detector={"type": "itl", "nx": SIZE, "ny": SIZE}, pupil=pupil,
               satellites=[dict(DEFAULT_SCENE["satellites"][0], height=height, mag=mag,
                                track={"x0": float(x0), "y0": float(y0), "angle": angle})])
    if field is not None:
        # "along": the outward radius along the track; "across": 90 deg from it.
        raw["field"] = {"angle": field,
                        "position_angle": angle + (90.0 if direction == "across" else 0.0)}
    return parse_scene(raw)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--mag", type=float, default=12.0)
    args = parser.parse_args()
    print("| height | pupil | field | track vs radius | truth FWHM | measured - truth | "
          "scatter | truth - annulus |")
    print("|---|---|---|---|---|---|---|---|")
    for height in (550.0, 350.0):
        for pupil, field, direction in CASES:
            errors, truths, shifts = [], [], []
            for seed in range(1, args.seeds + 1):
                scene = _scene(height, args.mag, 4000 + seed, pupil, field, direction)
                result = simulate(scene)
                row = result.truth[0]
                out = analyse(result.image, pixel_scale=0.2, n_boot=0)
                if not out.streaks:
                    continue
                measured = out.streaks[0]["fwhm_arcsec"]
                errors.append(measured / row["fwhm_arcsec"] - 1)
                truths.append(row["fwhm_arcsec"])
                annulus = StreakModel(height, scene.zenith, band_name=scene.band,
                                      seeing=Seeing(scene.seeing)).fwhm_arcsec
                shifts.append(row["fwhm_arcsec"] / annulus - 1)
            print(f"  {height:.0f} km {pupil} {field} {direction}: {len(errors)} found",
                  file=sys.stderr, flush=True)
            e = 100 * np.array(errors)
            print(f"| {height:.0f} km | {pupil} | {'' if field is None else f'{field:g} deg'} | "
                  f"{direction or ''} | {np.mean(truths):.3f}\" | {e.mean():+.1f}% | "
                  f"{e.std():.1f}% | {100 * np.mean(shifts):+.1f}% |", flush=True)


if __name__ == "__main__":
    main()
