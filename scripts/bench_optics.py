"""Streak cross-sections with the traced pupil (batoid) against the ideal annulus.

For the paper's two orbits (350 and 550 km at zenith angle 70 deg, ranges from
``inject.geometry``) and field angles 0 to 1.75 deg, with 0.67" Kolmogorov seeing: the FWHM
and the peak (0.2" pixels, the track along the pixel rows) of the cross-section of a point
source's streak, the defocus kernel taken as the annulus (``inject.profile``) or traced
(``inject.optics``), for a track along the field radius and across it. The satellite's own
shape is left out: these are the kernels' effects alone. Also the traced kernel's edges
against the annulus's, its light relative to a star at the same place, and the time to build
one kernel.

Usage::

    python scripts/bench_optics.py [--band g] [--n-rays 1000000]
"""
import argparse
import time

from inject.geometry import slant_range
from inject.instrument import ARCSEC_PER_RAD, LSST
from inject.optics import N_RAYS, traced_kernel
from inject.profile import Seeing, line_spread, stationary_profile

HEIGHTS_KM = (350.0, 550.0)
ZENITH_DEG = 70.0
FIELD_ANGLES_DEG = (0.0, 0.75, 1.25, 1.5, 1.75)
PIXEL_ARCSEC = 0.2


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--band", default="g")
    parser.add_argument("--n-rays", type=int, default=N_RAYS)
    parser.add_argument("--seeing", type=float, default=0.67)
    args = parser.parse_args()
    seeing = Seeing(args.seeing)

    table, kernels, builds = [], [], []
    for height in HEIGHTS_KM:
        r_km = float(slant_range(height, ZENITH_DEG))
        annulus = stationary_profile(None, r_km, seeing, drop=("shape",))
        ann = line_spread(annulus, pixel_scale_arcsec=PIXEL_ARCSEC)
        ann_fwhm, ann_peak = ann.fwhm(), ann.peak()
        for field in FIELD_ANGLES_DEG:
            start = time.perf_counter()
            k = traced_kernel(args.band, r_km, field, 0.0, n_rays=args.n_rays)
            builds.append(time.perf_counter() - start)
            kernels.append((height, r_km, field, k))
            # Field position angle 0: the field radius is the kernel's +x.
            for label, angle in (("along", 0.0), ("across", 90.0)):
                cs = k.cross_section(angle, seeing, pixel_scale_arcsec=PIXEL_ARCSEC)
                fwhm, peak = cs.fwhm(), cs.peak()
                table.append((height, r_km, field, label, ann_fwhm, fwhm,
                              100 * (fwhm / ann_fwhm - 1), 100 * (peak / ann_peak - 1)))
            print(f"  built {height:.0f} km at {field} deg in {builds[-1]:.1f} s", flush=True)

    print(f"\nband {args.band}, zenith {ZENITH_DEG:g} deg, Kolmogorov seeing {args.seeing}\", "
          f"{args.n_rays} rays, point source (no satellite shape)\n")
    print("| height | range | field | track vs radius | FWHM annulus | FWHM rubin | "
          "difference | peak difference |")
    print("|---|---|---|---|---|---|---|---|")
    for height, r_km, field, label, a, b, d, p in table:
        print(f"| {height:.0f} km | {r_km:.1f} km | {field:g} deg | {label} | {a:.3f}\" | "
              f"{b:.3f}\" | {d:+.1f}% | {p:+.1f}% |")

    print("\n| height | field | inner edge (annulus) | outer edge (annulus) | centroid x | "
          "light vs star | star throughput |")
    print("|---|---|---|---|---|---|---|")
    for height, r_km, field, k in kernels:
        a_i = LSST.inner_radius_m / (r_km * 1e3) * ARCSEC_PER_RAD
        a_o = LSST.outer_radius_m / (r_km * 1e3) * ARCSEC_PER_RAD
        print(f"| {height:.0f} km | {field:g} deg | {k.inner_radius:.3f}\" ({a_i:.3f}\") | "
              f"{k.outer_radius:.3f}\" ({a_o:.3f}\") | {k.centroid[0]:+.4f}\" | "
              f"{k.transmitted:.4f} | {k.star_throughput:.4f} |")
    builds.sort()
    print(f"\nkernel build: median {builds[len(builds) // 2]:.1f} s, "
          f"min {builds[0]:.1f} s, max {builds[-1]:.1f} s ({args.n_rays} rays)")


if __name__ == "__main__":
    main()
