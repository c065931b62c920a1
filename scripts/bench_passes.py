"""Passes per second: which satellites of a 5,000-satellite catalog cross the field in one exposure.

The catalog: a Walker-delta shell (550 km, 53 deg; 5000/50/1 by default) with epoch at the
exposure, plus a few example TLEs aimed at the field (so some passes do cross). One 30 s exposure
from Rubin, the pointing at alt 55, az 290 at mid-exposure (2026-06-15, ~1.6 h after sunset).

Two ways, timed in this run:

* ``prefilter + exact``: :func:`inject.orbits.passes.find_passes`: SGP4 ``SatrecArray`` at every
  5 s with numpy geometry for the whole catalog, then the exact astropy frames
  (:func:`compute_pass`, 1 s samples, light time, shadow) for the candidates only;
* ``exact for all``: :func:`compute_pass` with the exposure's shared :class:`FieldFrame` on a
  random sample of the catalog (``--exact-sample``), scaled to the catalog: the brute force.

``--check`` also runs the exact pass on every satellite above the horizon during the exposure and
verifies that the prefilter dropped none that crosses the field (slow: minutes).

Usage::

    python scripts/bench_passes.py [--satellites 5000] [--planes 50] [--exact-sample 100] [--check]
"""
import argparse
import time
import warnings

import numpy as np
from astropy import units as u
from astropy.coordinates import ICRS, AltAz, SkyCoord

from inject.camera.wcs import Pointing
from inject.orbits.passes import (
    RUBIN,
    Exposure,
    FieldFrame,
    aimed_orbit,
    compute_pass,
    crossing_candidates,
    find_passes,
    walker_shell,
)

START = "2026-06-15T23:30:00"


def build_catalog(n, planes, exposure):
    shell = walker_shell(n - 4, planes, 1, 550.0, 53.0, exposure.start) if (n - 4) % planes == 0 \
        else walker_shell(n, planes, 1, 550.0, 53.0, exposure.start)[:n - 4]
    aimed = [aimed_orbit(exposure.middle, 55.0 + d_alt, 290.0 + d_az, ascending=k % 2 == 0,
                         name=f"EXAMPLE-{k}", satnum=90001 + k)
             for k, (d_alt, d_az) in enumerate(((0, 0), (1.0, 0.5), (-1.2, 1.5), (0.3, -4.0)))]
    return aimed + shell


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--satellites", type=int, default=5000)
    parser.add_argument("--planes", type=int, default=50)
    parser.add_argument("--exact-sample", type=int, default=100)
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args()

    exposure = Exposure(START, 30.0)
    mid = exposure.middle
    c = SkyCoord(az=290 * u.deg, alt=55 * u.deg,
                 frame=AltAz(obstime=mid, location=RUBIN.location)).transform_to(ICRS())
    pointing = Pointing(c.ra.deg, c.dec.deg, 0.0)

    t0 = time.perf_counter()
    catalog = build_catalog(args.satellites, args.planes, exposure)
    t_build = time.perf_counter() - t0
    print(f"catalog: {len(catalog)} satellites (Walker shell 550 km 53 deg + 4 aimed example "
          f"TLEs), built in {t_build:.2f} s")
    print(f"exposure {START} UTC, 30 s; pointing ra {pointing.ra_deg:.4f} dec "
          f"{pointing.dec_deg:.4f} (alt 55 az 290 at mid-exposure)")

    # Warm up astropy's caches (IERS table, ERFA) so neither way pays for them.
    compute_pass(catalog[0], exposure, pointing)

    t0 = time.perf_counter()
    idx = crossing_candidates(catalog, exposure, pointing)
    t_pre = time.perf_counter() - t0
    t0 = time.perf_counter()
    passes = find_passes(catalog, exposure, pointing)
    t_find = time.perf_counter() - t0
    print(f"\nprefilter alone: {t_pre:.3f} s -> {len(idx)} candidates "
          f"({len(catalog) / t_pre:,.0f} satellites/s)")
    print(f"prefilter + exact (find_passes): {t_find:.3f} s -> {len(passes)} crossing the field: "
          f"{len(catalog) / t_find:,.0f} satellites/s")
    for p in passes:
        mid_i = len(p.t_s) // 2
        print(f"  {p.orbit.name}: {p.message}; range {p.range_km[mid_i]:.0f} km, "
              f"{np.degrees(p.angular_speed_rad_s[mid_i]):.3f} deg/s")

    rng = np.random.default_rng(1)
    sample = rng.choice(len(catalog), size=min(args.exact_sample, len(catalog)), replace=False)
    t0 = time.perf_counter()
    frame = FieldFrame.build(exposure.start + exposure.sample_times(1.0) * u.s, pointing, RUBIN)
    t_frame = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in sample:
        compute_pass(catalog[i], exposure, pointing, frame=frame)
    t_exact = (time.perf_counter() - t0) / len(sample)
    t_all = t_frame + t_exact * len(catalog)
    print(f"\nexact for all (brute force, shared frame, timed on {len(sample)}): frame "
          f"{t_frame * 1e3:.0f} ms once, then {t_exact * 1e3:.2f} ms per satellite -> "
          f"{len(catalog) / t_all:,.0f} satellites/s, {t_all:.1f} s for the catalog")
    print(f"ratio (exact for all / prefilter + exact): {t_all / t_find:.1f}x")
    t0 = time.perf_counter()
    for i in sample[:10]:
        compute_pass(catalog[i], exposure, pointing)
    t_own = (time.perf_counter() - t0) / 10
    print(f"(one compute_pass that builds its own frame: {t_own * 1e3:.0f} ms)")

    if args.check:
        times = exposure.start + exposure.sample_times(5.0) * u.s
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # Every satellite above the horizon and < 87 deg from the boresight at some coarse
            # sample (one farther cannot reach the field in 30 s at < 1 deg/s).
            up = crossing_candidates(catalog, exposure, pointing, field_radius_deg=1e9,
                                     margin_deg=0.0)
        exact = {int(i) for i in up if compute_pass(catalog[i], exposure, pointing).in_field}
        missed = exact - set(idx.tolist())
        print(f"\ncheck: exact pass on the {len(up)} satellites in front of the boresight and "
              f"above the horizon ({len(times)} coarse samples) in {time.perf_counter() - t0:.0f}"
              f" s: {len(exact)} cross the field, {len(missed)} missed by the prefilter")


if __name__ == "__main__":
    main()
