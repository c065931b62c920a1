"""Time a CCD with 200 short streaks against the same CCD with one, measured in one run.

Each scene is the default one (an ITL CCD in g with dark sky, stars, Poisson and read noise,
z = 70 deg) with the paper's satellite at 550 km on 40 px tracks scattered over the CCD:

* ``one``: a single track;
* ``train``: 200 tracks at one angle and magnitude (a constellation train: same shell, same
  direction), which share one swept profile;
* ``mixed``: 200 tracks at one angle with magnitudes 1-9, whose noise-tightened budgets fall
  on a few steps of the tolerance grid (:func:`inject.render.snap_tolerance`);
* ``random``: 200 tracks at 200 random angles (0-360 deg) and one magnitude, which share
  tables on the profile's grid of pixel orientations (:func:`inject.render.orientation_step`);
* ``angles`` (``--angles N``): N tracks at N different angles, as ``random`` but fewer, for
  the cost per extra angle.

Every run starts with empty caches (profiles, tables, PSF stamps), as a fresh process would,
and runs :func:`inject.scene.simulate`; best of ``--repeat``, the scenes alternating so
machine load hits them alike. ``--check`` also renders the train without reuse and reports
the largest difference (it must be float rounding).

Usage::

    python scripts/bench_many_streaks.py [--repeat 3] [--angles 20] [--check]

``--check`` also renders the random-angle scene with every streak at its own exact angle
(``MAX_ORIENTATION_STEPS = 0``: no snapping) and reports the largest difference, against
the budget's tolerance and the plans' predicted snapping error.
"""
import argparse
import time

import numpy as np

from inject import render, stars, streak
from inject import scene as scene_mod
from inject.config import DEFAULT_SCENE, parse_scene

SATELLITE = {"height": 550.0, "shape": {"type": "box", "length": 7.25, "width": 2.65}}


def tracks_scene(n, angles, mags, seed=3):
    """The default scene with ``n`` 40 px tracks at random places on the CCD."""
    rng = np.random.default_rng(seed)
    sats = [dict(SATELLITE, mag=float(m), track={
        "x0": float(rng.uniform(100, 3900)), "y0": float(rng.uniform(100, 3900)),
        "angle": float(a), "length": 40.0}) for a, m in zip(angles, mags)][:n]
    return parse_scene(dict(DEFAULT_SCENE, satellites=sats))


def fresh_caches():
    render.PROFILE_CACHE.clear()
    streak._shared_profile.cache_clear()
    streak._shared_line_spreads.cache_clear()
    stars.psf_stamps.cache_clear()


def run(scene):
    fresh_caches()
    start = time.perf_counter()
    scene_mod.simulate(scene)
    return time.perf_counter() - start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--streaks", type=int, default=200)
    parser.add_argument("--angles", type=int, default=20,
                        help="tracks at distinct angles in the worst case (0 to skip)")
    parser.add_argument("--check", action="store_true",
                        help="also compare the train with and without reuse")
    args = parser.parse_args(argv)
    n = args.streaks
    rng = np.random.default_rng(7)
    scenes = {
        "one": tracks_scene(1, [33.0], [8.0]),
        "train": tracks_scene(n, [33.0] * n, [8.0] * n),
        "mixed": tracks_scene(n, [33.0] * n, rng.uniform(1, 9, n)),
        "random": tracks_scene(n, rng.uniform(0, 360, n), [8.0] * n),
    }
    if args.angles:
        scenes["angles"] = tracks_scene(args.angles, rng.uniform(0, 180, args.angles),
                                        [8.0] * args.angles)
    best = {name: np.inf for name in scenes}
    for _ in range(args.repeat):
        for name, scene in scenes.items():
            best[name] = min(best[name], run(scene))
    one = best["one"]
    print(f"one 40 px streak on an ITL CCD (sky, stars, noise): {one:.2f} s")
    for name, label in (("train", f"{n} streaks, one angle and magnitude (a train)"),
                        ("mixed", f"{n} streaks, one angle, magnitudes 1-9"),
                        ("random", f"{n} streaks at {n} random angles")):
        print(f"{label}: {best[name]:.2f} s ({best[name] / one:.2f}x; "
              f"{(best[name] - one) / (n - 1) * 1e3:.1f} ms per extra streak)")
    if args.angles:
        k = args.angles
        print(f"{k} streaks at {k} distinct angles: {best['angles']:.2f} s "
              f"({best['angles'] / one:.2f}x; "
              f"{(best['angles'] - one) / (k - 1) * 1e3:.0f} ms per extra streak)")
    for name in ("mixed", "random"):
        fresh_caches()
        scene_mod.render_streaks(scenes[name])
        swept = [k for k in render.PROFILE_CACHE._items if k[0] == "swept"]
        print(f"{name} scene: {len(swept)} swept profiles kept ({render.PROFILE_CACHE.misses} "
              f"cache misses in all), {render.PROFILE_CACHE.nbytes / 2 ** 20:.0f} MiB")
    if args.check:
        shared, _ = scene_mod.render_streaks(scenes["train"])
        alone, _ = scene_mod.render_tracks(
            scenes["train"].detector.shape, scene_mod.streak_models(scenes["train"]),
            [s.track for s in scenes["train"].satellites], noise_sigma=scene_mod.pixel_noise(
                scenes["train"]), cache=None)
        print(f"train with and without reuse: max |difference| "
              f"{np.abs(shared - alone).max() / shared.max():.1e} of the peak")
        fresh_caches()
        snapped, _ = scene_mod.render_streaks(scenes["random"])
        built = [entry[0] for k, entry in render.PROFILE_CACHE._items.items() if k[0] == "swept"]
        predicted = max(swept.plan.predicted_error.get("orientation", 0.0) for swept in built)
        tolerance = min(swept.budget.tolerance for swept in built)
        fresh_caches()
        steps, render.MAX_ORIENTATION_STEPS = render.MAX_ORIENTATION_STEPS, 0
        try:
            exact, _ = scene_mod.render_streaks(scenes["random"])
        finally:
            render.MAX_ORIENTATION_STEPS = steps
        # Each build also has its own end-cap approximations (<= tol / 2 each, e.g. where a
        # table ends across the track): the two may differ by more than the snapping alone.
        print(f"random angles, snapped against exact: max |difference| "
              f"{np.abs(snapped - exact).max() / exact.max():.1e} of the peak (tolerance "
              f"{tolerance:.0e}; snapping predicted at most {predicted:.1e})")


if __name__ == "__main__":
    main()
