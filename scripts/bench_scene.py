"""Time a full LSSTCam CCD scene against drawing Poisson sky alone, measured in one run.

The scene: one ITL CCD (4072 x 4000) in g with dark sky, Bahcall-Soneira stars to 24 mag at
galactic latitude 30 deg, noise, and two streaks (the paper's satellite at 550 and 350 km),
written to FITS. The baseline: Poisson sky for the same CCD written to FITS. Each is timed
best-of-N in this process, alternating, so machine load hits both alike; the scene's stages
are timed too, to name what dominates.

Usage::

    python scripts/bench_scene.py [--repeat 3] [--out out/bench]
"""
import argparse
import os
import tempfile
import time

import numpy as np
from astropy.io import fits

from inject import scene as scene_mod
from inject.config import DEFAULT_SCENE, parse_scene
from inject.io.fits import write_exposure
from inject.schema import apply_overrides

SCENE = apply_overrides(DEFAULT_SCENE, [
    "stars={galactic_b: 30, galactic_l: 90, mag_limit: 24}",
    "satellites=[{height: 550, shape: {type: box, length: 7.25, width: 2.65}, mag: 5.0, "
    "track: {x0: 0, y0: 300, angle: 33}}, {height: 350, shape: {type: box, length: 7.25, "
    "width: 2.65}, mag: 5.0, track: {x0: 4000, y0: 200, angle: 118}}]"])


def baseline(scene, path):
    """Poisson sky alone for the CCD, written to FITS."""
    rng = np.random.default_rng(1)
    sky = scene_mod.sky_level(scene)
    image = rng.poisson(sky, size=scene.detector.shape).astype(np.float32)
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(image, name="IMAGE")]).writeto(
        path, overwrite=True)


class Stages:
    """Wrap the scene's stage functions to time them."""

    def __init__(self):
        self.seconds = {}

    def wrap(self, module, name, label):
        original = getattr(module, name)

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - start
        setattr(module, name, timed)


def full_scene(scene, path, stages):
    from inject import stars

    stars.psf_stamps.cache_clear()  # every run pays for its PSF stamps, as a fresh process would
    result = scene_mod.simulate(scene)
    start = time.perf_counter()
    write_exposure(path, scene, result, scene.detector.gain, overwrite=True)
    stages.seconds["write FITS"] = stages.seconds.get("write FITS", 0) + time.perf_counter() - start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    scene = parse_scene(SCENE)
    from inject import stars

    stages = Stages()
    stages.wrap(scene_mod, "render_streaks", "streaks")
    stages.wrap(stars, "add_star_field", "stars")
    stages.wrap(scene_mod, "bleed_saturation", "saturation")
    best = {"scene": np.inf, "baseline": np.inf}
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "ccd.fits")
        for _ in range(args.repeat):
            for name, run in (("baseline", lambda: baseline(scene, path)),
                              ("scene", lambda: full_scene(scene, path, stages))):
                start = time.perf_counter()
                run()
                best[name] = min(best[name], time.perf_counter() - start)
    ratio = best["scene"] / best["baseline"]
    print(f"Poisson sky + write:             {best['baseline']:.2f} s")
    print(f"full scene (sky, stars, noise, 2 streaks) + write: {best['scene']:.2f} s")
    print(f"ratio: {ratio:.2f}x (target <= 3x)")
    print("scene stages (mean per run):")
    for label, seconds in sorted(stages.seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {label:<12s} {seconds / args.repeat:.2f} s")


if __name__ == "__main__":
    main()
