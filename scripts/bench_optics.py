"""The traced pupil (``pupil: rubin``) against the ideal annulus: streaks, grid accuracy, cost.

Sections (all by default, or name some with ``--sections``):

``table``
    The paper's satellite (7.25 m x 2.65 m box, g = 5 at 550 km) at 350 and 550 km, zenith
    angle 70 deg, 0.67" Kolmogorov seeing, 0.2" pixels: streak FWHM and peak surface
    brightness with the annulus and with the traced kernel at field angles 0 to 1.75 deg, the
    track along the field radius and across it; and the paper's 350/550 peak ratio.
``kernels``
    A point source's kernel alone: its edges against the annulus's, its light relative to a
    star at the same place, and the time to trace one.
``grid``
    The kernel grid (:func:`inject.optics.kernel`) against exact traces between its nodes.
``focus``
    The paper's satellite at 350 and 550 km (zenith 70 deg), on the axis: streak FWHM and peak
    against the detector's shift from the design's focus, and where a star is sharpest.
``rotator``
    The paper's satellite at 350 and 550 km (zenith 70 deg) at 1.5 deg, the field radius along
    the focal plane's +x: streak FWHM and peak against the camera rotator's angle (rotTelPos),
    the track along the field radius and across it, and without a rotator (22.5 deg).
``cost``
    ``inject focalplane`` on the paper's focal-plane sample (``--streak-ccds-only``), with
    ``pupil=annulus`` and ``pupil=rubin`` alternated in one run: the first rubin run with an
    empty kernel cache, then warm runs.

Usage::

    python scripts/bench_optics.py [--sections table kernels grid focus rotator cost] [--band g]
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from inject.geometry import slant_range
from inject.instrument import ARCSEC_PER_RAD, LSST
from inject.optics import (
    GRID_RAYS,
    N_RAYS,
    VANE_OFFSET_DEG,
    kernel,
    telescope_position_angle,
    traced_kernel,
)
from inject.profile import Seeing
from inject.streak import StreakModel

HEIGHTS_KM = (350.0, 550.0)
ZENITH_DEG = 70.0
FIELD_ANGLES_DEG = (0.0, 0.75, 1.25, 1.5, 1.75)
PIXEL_ARCSEC = 0.2
SECTIONS = ("table", "kernels", "grid", "focus", "rotator", "cost")
ROTATORS_DEG = (None, 0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
FOCUS_UM = (-10.0, -5.0, -2.0, -1.0, 0.0, 1.0, 2.0, 5.0, 10.0)


def table(band, seeing):
    """FWHM and peak, annulus vs rubin, and the 350/550 peak ratio."""
    rows, peaks = [], {}
    for height in HEIGHTS_KM:
        kw = dict(height_km=height, zenith_deg=ZENITH_DEG, band_name=band, seeing=seeing)
        annulus = StreakModel(**kw)
        peaks[(height, "annulus", None, None)] = annulus.peak_e_per_px
        for field in FIELD_ANGLES_DEG:
            for label, pa in (("along", 0.0), ("across", 90.0)):
                rubin = StreakModel(pupil="rubin", field_angle_deg=field,
                                    field_position_angle_deg=pa, **kw)
                peaks[(height, "rubin", field, label)] = rubin.peak_e_per_px
                rows.append((height, field, label, annulus, rubin))
                print(f"  {height:.0f} km, {field} deg, {label}", file=sys.stderr, flush=True)
    print(f"\nband {band}, zenith {ZENITH_DEG:g} deg, Kolmogorov seeing "
          f"{seeing.fwhm_arcsec}\", the paper's box satellite, {PIXEL_ARCSEC}\" pixels\n")
    print("| height | field | track vs radius | FWHM annulus | FWHM rubin | difference | "
          "peak annulus | peak rubin | difference |")
    print("|---|---|---|---|---|---|---|---|---|")
    for height, field, label, a, r in rows:
        print(f"| {height:.0f} km | {field:g} deg | {label} | {a.fwhm_arcsec:.3f}\" | "
              f"{r.fwhm_arcsec:.3f}\" | {100 * (r.fwhm_arcsec / a.fwhm_arcsec - 1):+.1f}% | "
              f"{a.peak_e_per_px:.0f} e- | {r.peak_e_per_px:.0f} e- | "
              f"{100 * (r.peak_e_per_px / a.peak_e_per_px - 1):+.1f}% |")
    print("\nPeak surface brightness ratio, 350 km / 550 km (zenith 70 deg):\n")
    print("| kernel | field | track vs radius | ratio |")
    print("|---|---|---|---|")
    low, high = HEIGHTS_KM
    print(f"| annulus | any | any | {peaks[(low, 'annulus', None, None)] / peaks[(high, 'annulus', None, None)]:.4f} |")  # noqa: E501
    for field in (0.0, 1.5):
        for label in ("along", "across"):
            ratio = peaks[(low, "rubin", field, label)] / peaks[(high, "rubin", field, label)]
            print(f"| rubin | {field:g} deg | {label} | {ratio:.4f} |")


def kernels(band, n_rays):
    """Edges and light of a point source's kernel, and the time to trace one."""
    builds, out = [], []
    for height in HEIGHTS_KM:
        r_km = float(slant_range(height, ZENITH_DEG))
        for field in FIELD_ANGLES_DEG:
            start = time.perf_counter()
            k = traced_kernel(band, r_km, field, 0.0, n_rays=n_rays)
            builds.append(time.perf_counter() - start)
            out.append((height, r_km, field, k))
    print("\n| height | field | inner edge (annulus) | outer edge (annulus) | centroid x | "
          "light vs star | star throughput |")
    print("|---|---|---|---|---|---|---|")
    for height, r_km, field, k in out:
        a_i = LSST.inner_radius_m / (r_km * 1e3) * ARCSEC_PER_RAD
        a_o = LSST.outer_radius_m / (r_km * 1e3) * ARCSEC_PER_RAD
        print(f"| {height:.0f} km | {field:g} deg | {k.inner_radius:.3f}\" ({a_i:.3f}\") | "
              f"{k.outer_radius:.3f}\" ({a_o:.3f}\") | {k.centroid[0]:+.4f}\" | "
              f"{k.transmitted:.4f} | {k.star_throughput:.4f} |")
    builds.sort()
    print(f"\nkernel trace: median {builds[len(builds) // 2]:.1f} s, "
          f"min {builds[0]:.1f} s, max {builds[-1]:.1f} s ({n_rays} rays)")


def _fwhm_peak(k, track_angle, seeing):
    cs = k.cross_section(track_angle, seeing, pixel_scale_arcsec=PIXEL_ARCSEC)
    return np.array([cs.fwhm(), cs.peak()])


def grid(band, seeing):
    """The grid's kernel against an exact trace, between nodes in range and field."""
    print("\n| range | field | track vs radius | FWHM | peak |")
    print("|---|---|---|---|---|")
    worst = np.zeros(2)
    for r_km in (358.0, 612.0, 1013.0, 1390.0):
        for field in (0.025, 0.725, 1.275, 1.475, 1.605, 1.745, 1.855, 2.005):
            exact = traced_kernel(band, r_km, field, VANE_OFFSET_DEG, n_rays=GRID_RAYS)
            grid_kernel = kernel(band, r_km, field)
            for label, turn in (("along", 0.0), ("across", 90.0)):
                angle = VANE_OFFSET_DEG + turn
                error = _fwhm_peak(grid_kernel, angle, seeing) / _fwhm_peak(exact, angle,
                                                                            seeing) - 1
                worst = np.maximum(worst, np.abs(error))
                print(f"| {r_km:.0f} km | {field} deg | {label} | {100 * error[0]:+.3f}% | "
                      f"{100 * error[1]:+.3f}% |", flush=True)
    print(f"\nlargest: FWHM {100 * worst[0]:.3f}%, peak {100 * worst[1]:.3f}%")


def _rms_radius(k):
    """rms radius of a kernel's image about its centroid, arcsec (its pixels' scale^2/6 out)."""
    n = k.image.shape[0]
    c = (np.arange(n) - n // 2) * k.scale
    x, y = np.meshgrid(c, c)
    w = k.image / k.image.sum()
    r2 = np.sum(w * ((x - k.centroid[0]) ** 2 + (y - k.centroid[1]) ** 2)) - k.scale ** 2 / 6
    return float(np.sqrt(r2))


def focus(band, seeing):
    """Streak FWHM and peak on the axis against the focus offset; the star's sharpest focus."""
    print("\n| focus offset | 350 km FWHM | 350 km peak | 550 km FWHM | 550 km peak | "
          "kernel rms radius at 1293.8 km | star rms radius |")
    print("|---|---|---|---|---|---|---|")
    stars = []
    r550 = float(slant_range(550.0, ZENITH_DEG))
    for dz in FOCUS_UM:
        cells = []
        for height in HEIGHTS_KM:
            m = StreakModel(height_km=height, zenith_deg=ZENITH_DEG, band_name=band,
                            seeing=seeing, pupil="rubin", focus_offset_um=dz)
            cells += [f"{m.fwhm_arcsec:.3f}\"", f"{m.peak_e_per_px:.0f} e-"]
        ring = _rms_radius(traced_kernel(band, r550, 0.0, n_rays=GRID_RAYS, focus_offset_um=dz))
        star = _rms_radius(traced_kernel(band, 1e9, 0.0, n_rays=GRID_RAYS, focus_offset_um=dz))
        stars.append(star)
        print(f"| {dz:+g} um | " + " | ".join(cells) + f" | {ring:.4f}\" | {star:.4f}\" |",
              flush=True)
    # The star's sharpest focus: a parabola through the three smallest rms radii squared.
    i = int(np.clip(np.argmin(stars), 1, len(stars) - 2))
    z, r2 = np.array(FOCUS_UM[i - 1:i + 2]), np.array(stars[i - 1:i + 2]) ** 2
    a, b, c = np.polyfit(z, r2, 2)
    best = -b / (2 * a)
    print(f"\nan on-axis star (band-integrated) is sharpest at {best:+.2f} um: rms radius "
          f"{np.sqrt(c - b * b / (4 * a)):.4f}\"")


def rotator(band, seeing):
    """Streak FWHM and peak at 1.5 deg against the camera rotator's angle."""
    print("\n| rotator | telescope PA | " + " | ".join(
        f"{h:.0f} km {label} FWHM | {h:.0f} km {label} peak" for h in HEIGHTS_KM
        for label in ("along", "across")) + " |")
    print("|---|---|" + "---|---|" * 2 * len(HEIGHTS_KM))
    for rot in ROTATORS_DEG:
        # The field radius along the focal plane's +x: its kernel is traced at -rotator.
        pa = None if rot is None else telescope_position_angle(rot, 0.0)
        cells = []
        for height in HEIGHTS_KM:
            for track_pa in (0.0, 90.0):
                m = StreakModel(height_km=height, zenith_deg=ZENITH_DEG, band_name=band,
                                seeing=seeing, pupil="rubin", field_angle_deg=1.5,
                                field_position_angle_deg=track_pa,
                                telescope_position_angle_deg=pa)
                cells += [f"{m.fwhm_arcsec:.3f}\"", f"{m.peak_e_per_px:.0f} e-"]
        label = "none" if rot is None else f"{rot:g} deg"
        node = VANE_OFFSET_DEG if pa is None else pa
        print(f"| {label} | {node:g} deg | " + " | ".join(cells) + " |", flush=True)


def _run(pupil, outdir, cache):
    env = dict(os.environ, INJECT_CACHE_DIR=cache)
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "inject", "focalplane",
                    "sample_fields/focal_paper_550km.yaml", "-o", outdir, "--streak-ccds-only",
                    "--no-mosaic", "--overwrite", f"pupil={pupil}"],
                   check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def cost(repeat):
    """A focal-plane exposure with each pupil, alternated; the first rubin run cold."""
    with tempfile.TemporaryDirectory() as tmp:
        cache, out = os.path.join(tmp, "cache"), os.path.join(tmp, "out")
        cold = _run("rubin", out, cache)
        files = sum(len(f) for _, _, f in os.walk(cache))
        times = {"annulus": [], "rubin": []}
        for _ in range(repeat):
            for pupil in ("annulus", "rubin"):
                times[pupil].append(_run(pupil, out, cache))
    a, r = np.median(times["annulus"]), np.median(times["rubin"])
    print(f"\ninject focalplane sample_fields/focal_paper_550km.yaml --streak-ccds-only "
          f"(median of {repeat}, alternated)")
    print(f"annulus {a:.1f} s, rubin warm {r:.1f} s: ratio {r / a:.2f}; "
          f"rubin cold (empty cache, {files} kernels traced) {cold:.1f} s")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument("--band", default="g")
    parser.add_argument("--n-rays", type=int, default=N_RAYS, help="rays of 'kernels'")
    parser.add_argument("--seeing", type=float, default=0.67)
    parser.add_argument("--repeat", type=int, default=3, help="runs of each pupil in 'cost'")
    args = parser.parse_args()
    seeing = Seeing(args.seeing)
    if "table" in args.sections:
        table(args.band, seeing)
    if "kernels" in args.sections:
        kernels(args.band, args.n_rays)
    if "grid" in args.sections:
        grid(args.band, seeing)
    if "focus" in args.sections:
        focus(args.band, seeing)
    if "rotator" in args.sections:
        rotator(args.band, seeing)
    if "cost" in args.sections:
        cost(args.repeat)


if __name__ == "__main__":
    main()
