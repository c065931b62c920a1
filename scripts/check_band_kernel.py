"""The band-integrated traced kernel (``pupil: rubin``) against an independent trace.

The reference here does not call ``inject.optics``' tracing: it builds batoid's baffled LSST
telescope with the band's camera itself, traces random rays (batoid's own ray generator) from
a point at the range and from a star at each of ``--n-ref`` wavelengths spread evenly over the
band, weights each wavelength by the band's throughput (GalSim's ``LSST_{band}.dat``) times a
5772 K blackbody counted in photons by GalSim's ``SED``, and projects the rays across the
track about the star's centroid. The streak's line-spread function is then the rays'
histogram convolved, in Fourier space, with the projections of a 0.5 m disk at the range and
of 0.67" Kolmogorov seeing (GalSim's transform). Its FWHM and peak are compared with inject's:
the grid kernel scenes use (:func:`inject.optics.kernel`), and traces with 1 to 12
wavelengths (:func:`inject.optics.traced_kernel`), on axis and at 1.5 deg, at 350 and 550 km
(zenith angle 70 deg), the track along and across the field radius.

Usage::

    python scripts/check_band_kernel.py [--bands g r] [--n-ref 60] [--rays 100000]
        [--baseline OLD_OPTICS_PY] [--no-check | --no-timing]

``--baseline`` times an earlier ``inject/optics.py`` (``git show REV:inject/optics.py >
old.py``) against this one, tracing the same kernel alternately.
"""
import argparse
import copy
import importlib.util
import os
import sys
import time

import batoid
import galsim
import numpy as np
import yaml
from scipy.special import j1

from inject.geometry import slant_range
from inject.optics import (
    BAND_WAVELENGTH_NM,
    GRID_RAYS,
    N_WAVELENGTHS,
    VANE_OFFSET_DEG,
    kernel,
    traced_kernel,
)
from inject.profile import line_spread

ARCSEC = np.degrees(1.0) * 3600.0
HEIGHTS_KM = (350.0, 550.0)
ZENITH_DEG = 70.0
FIELDS_DEG = (0.0, 1.5)
DISK_RADIUS_M = 0.5
SEEING_FWHM = 0.67
STEP = 0.005  # arcsec, the reference's sampling across the track
NODES = (1, 3, 5, 8, 12)


def optic(band):
    """batoid's baffled telescope with ``band``'s camera, in the camera model's (vacuum)
    media: built here from the two model files."""
    def load(name):
        with open(os.path.join(batoid.datadir, "LSST", name)) as f:
            return yaml.safe_load(f)["opticalSystem"]

    baffled, own = load("LSST_r_baffles.yaml"), load(f"LSST_{band}.yaml")
    items = [i for i in baffled["items"] if i["name"] != "LSSTCamera"]
    items += [copy.deepcopy(i) for i in own["items"] if i["name"] == "LSSTCamera"]
    baffled.update(items=items, inMedium=own["inMedium"], medium=own["medium"])
    return batoid.parse.parse_optic(baffled)


def reference_wavelengths(band, n):
    """``n`` wavelengths at the centres of equal bins over the band, nm, and their photon
    weights (throughput x GalSim's photon SED of a 5772 K blackbody x bin width)."""
    bandpass = galsim.Bandpass(f"LSST_{band}.dat", "nm")
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23

    def planck(w_nm):
        w = w_nm * 1e-9
        return 1.0 / (w ** 5 * np.expm1(h * c / (w * k * 5772.0)))

    sed = galsim.SED(planck, "nm", "flambda")
    edges = np.linspace(bandpass.blue_limit, bandpass.red_limit, n + 1)
    waves = 0.5 * (edges[1:] + edges[:-1])
    fine = np.linspace(bandpass.blue_limit, bandpass.red_limit, 20 * n + 1)
    photons = bandpass(fine) * sed(fine)
    # Each bin's photons: the fine samples' trapezoid sums within it.
    weights = np.array([np.trapezoid(photons[20 * i:20 * i + 21], fine[20 * i:20 * i + 21])
                        for i in range(n)])
    return waves, weights / weights.sum()


def _direction(theta):
    return np.array(batoid.utils.fieldToDirCos(*theta))


def _star(tel, wave_nm, theta, rays, seed):
    out = tel.trace(batoid.RayVector.asPolar(optic=tel, wavelength=wave_nm * 1e-9,
                                             dirCos=_direction(theta), nrandom=rays, rng=seed))
    ok = ~out.vignetted
    return out.x[ok], out.y[ok], ok.mean()


def reference(band, range_km, field_deg, pa_deg, n_ref, rays):
    """Rays' offsets from the star's centroid (arcsec, batoid's frame), their weights, and
    the point's light relative to the star's."""
    tel = optic(band)
    waves, weights = reference_wavelengths(band, n_ref)
    pa = np.radians(pa_deg)
    theta = np.radians(field_deg) * np.array([np.cos(pa), np.sin(pa)])
    stop = np.array(tel.stopSurface.coordSys.origin)
    source = stop - range_km * 1e3 * _direction(theta)
    star_x, star_y, star_w, pts, point_light, star_light = [], [], [], [], 0.0, 0.0
    for i, (wave, weight) in enumerate(zip(waves, weights)):
        sx, sy, kept = _star(tel, wave, theta, rays, 2 * i)
        star_x.append(sx)
        star_y.append(sy)
        star_w.append(np.full(len(sx), weight / rays))
        out = tel.trace(batoid.RayVector.asPolar(optic=tel, wavelength=wave * 1e-9,
                                                 source=source, nrandom=rays, rng=2 * i + 1))
        ok = ~out.vignetted
        pts.append((out.x[ok], out.y[ok], np.full(ok.sum(), weight / rays)))
        point_light += weight * ok.mean()
        star_light += weight * kept
    sw = np.concatenate(star_w)
    centre = np.array([np.average(np.concatenate(star_x), weights=sw),
                       np.average(np.concatenate(star_y), weights=sw)])
    # Plate scale and distortion: star centroids 10" either side, at the mean wavelength.
    mean_wave = np.dot(waves, weights)
    step = 10.0 / ARCSEC
    jac = np.zeros((2, 2))
    for axis in (0, 1):
        ends = []
        for sign in (-1, 1):
            t = theta.copy()
            t[axis] += sign * step
            x, y, _ = _star(tel, mean_wave, t, 40_000, 99)
            ends.append([x.mean(), y.mean()])
        jac[:, axis] = (np.array(ends[1]) - np.array(ends[0])) / (2 * step)
    px, py, pw = (np.concatenate(a) for a in zip(*pts))
    d = np.linalg.inv(jac) @ (np.vstack([px, py]) - centre[:, None]) * ARCSEC
    return d, pw, point_light / star_light


def reference_lsf(d, w, track_deg, range_km):
    """FWHM (arcsec) and peak (per arcsec, unit flux) across a track at ``track_deg`` from
    batoid's +x: the rays' histogram x the disk's and the seeing's projections, in Fourier
    space."""
    a = np.radians(track_deg)
    across = -d[0] * np.sin(a) + d[1] * np.cos(a)
    n = 2 ** 15
    y = (np.arange(n) - n // 2) * STEP
    hist, _ = np.histogram(across, np.append(y - STEP / 2, y[-1] + STEP / 2), weights=w)
    k = 2 * np.pi * np.fft.rfftfreq(n, STEP)
    spectrum = np.fft.rfft(np.fft.ifftshift(hist / hist.sum()))
    spectrum /= np.sinc(k * STEP / (2 * np.pi))  # undo the histogram's bins
    ka = k * DISK_RADIUS_M / (range_km * 1e3) * ARCSEC
    disk = np.ones_like(ka)
    disk[1:] = 2 * j1(ka[1:]) / ka[1:]
    seeing = galsim.Kolmogorov(fwhm=SEEING_FWHM)
    mtf = np.array([seeing.kValue(0.0, kk).real for kk in k])
    lsf = np.fft.fftshift(np.fft.irfft(spectrum * disk * mtf, n)) / STEP
    i = int(np.argmax(lsf))
    p, q, r = lsf[i - 1:i + 2]
    peak = q - 0.125 * (p - r) ** 2 / (p - 2 * q + r)
    above = np.flatnonzero(lsf >= peak / 2)
    lo, hi = above[0], above[-1]
    half = peak / 2
    left = y[lo - 1] + (half - lsf[lo - 1]) * STEP / (lsf[lo] - lsf[lo - 1])
    right = y[hi] + (half - lsf[hi]) * STEP / (lsf[hi + 1] - lsf[hi])
    return np.array([right - left, peak])


def inject_lsf(k, track_deg, range_km):
    """The same from an inject kernel, through GalSim (inject's renderer's way)."""
    disk = galsim.TopHat(radius=DISK_RADIUS_M / (range_km * 1e3) * ARCSEC)
    profile = galsim.Convolve([k.profile().withFlux(1.0).rotate(-track_deg * galsim.degrees),
                               disk, galsim.Kolmogorov(fwhm=SEEING_FWHM)])
    cs = line_spread(profile)
    return np.array([cs.fwhm(), cs.peak()])


def check(bands, n_ref, rays):
    rows, worst = [], {}
    for band in bands:
        for height in HEIGHTS_KM:
            r_km = float(slant_range(height, ZENITH_DEG))
            for field in FIELDS_DEG:
                start = time.perf_counter()
                d, w, light = reference(band, r_km, field, VANE_OFFSET_DEG, n_ref, rays)
                grid = kernel(band, r_km, field)
                traces = {K: traced_kernel(band, r_km, field, VANE_OFFSET_DEG, n_rays=GRID_RAYS,
                                           n_wavelengths=K) for K in NODES}
                mono = traced_kernel(band, r_km, field, VANE_OFFSET_DEG, n_rays=GRID_RAYS,
                                     wavelength_nm=BAND_WAVELENGTH_NM[band])
                for label, turn in (("along", 0.0), ("across", 90.0)):
                    track = VANE_OFFSET_DEG + turn
                    ref = reference_lsf(d, w, track, r_km)
                    got = {"grid": inject_lsf(grid, track, r_km),
                           "mono": inject_lsf(mono, track, r_km)}
                    got.update({K: inject_lsf(t, track, r_km) for K, t in traces.items()})
                    errors = {key: value / ref - 1 for key, value in got.items()}
                    for key, e in errors.items():
                        worst[key] = np.maximum(worst.get(key, 0.0), np.abs(e))
                    rows.append((band, height, field, label, ref, got["grid"], errors,
                                 light, grid.transmitted))
                print(f"  {band} {height:.0f} km {field} deg: {time.perf_counter() - start:.0f} s",
                      file=sys.stderr, flush=True)
    print(f"\nreference: {n_ref} wavelengths x {rays} rays (point and star each); inject: "
          f"{GRID_RAYS} rays; 0.5 m disk, {SEEING_FWHM}\" Kolmogorov\n")
    print("| band | height | field | track vs radius | FWHM reference | FWHM inject | "
          "difference | peak reference | peak inject | difference | light ref / inject |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for band, height, field, label, ref, got, errors, light, transmitted in rows:
        e = errors["grid"]
        print(f"| {band} | {height:.0f} km | {field:g} deg | {label} | {ref[0]:.4f}\" | "
              f"{got[0]:.4f}\" | {100 * e[0]:+.2f}% | {ref[1]:.4f} | {got[1]:.4f} | "
              f"{100 * e[1]:+.2f}% | {light:.4f} / {transmitted:.4f} |")
    print(f"\nWavelength nodes (traced_kernel, {GRID_RAYS} rays) against the reference: "
          "largest |error| over the rows above, FWHM / peak\n")
    print("| wavelengths | FWHM | peak |")
    print("|---|---|---|")
    effective = "/".join(str(BAND_WAVELENGTH_NM[b]) for b in bands)
    label = {"mono": f"1, the band's effective ({effective} nm)",
             "grid": f"{N_WAVELENGTHS}, the grid (scenes)"}
    for key in ("mono", *NODES, "grid"):
        print(f"| {label.get(key, key)} | {100 * worst[key][0]:.2f}% | "
              f"{100 * worst[key][1]:.2f}% |")


def timing(band, baseline, repeat=3):
    """Seconds to trace one grid kernel (550 km, zenith 70, on axis and at 1.5 deg): one
    wavelength and the band, and an earlier optics module, alternated."""
    r_km = float(slant_range(550.0, ZENITH_DEG))

    def trace(module=None, **kw):
        return lambda f: (module or sys.modules[__name__]).traced_kernel(
            band, r_km, f, VANE_OFFSET_DEG, n_rays=GRID_RAYS, **kw)

    runs = {"one wavelength": trace(wavelength_nm=BAND_WAVELENGTH_NM[band]),
            f"{N_WAVELENGTHS} wavelengths": trace()}
    if baseline:
        spec = importlib.util.spec_from_file_location("baseline_optics", baseline)
        old = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(old)
        runs["baseline module"] = trace(old)
    times = {name: [] for name in runs}
    for field in FIELDS_DEG:
        for run in runs.values():
            run(field)  # the optics model parsed and cached
    for _ in range(repeat):
        for field in FIELDS_DEG:
            for name, run in runs.items():
                start = time.perf_counter()
                run(field)
                times[name].append(time.perf_counter() - start)
    print(f"\nTime to trace one kernel ({GRID_RAYS} rays, {band}, 550 km, on axis and 1.5 deg, "
          f"{repeat} rounds alternated): median")
    for name, t in times.items():
        print(f"  {name}: {np.median(t):.2f} s (min {min(t):.2f}, max {max(t):.2f})")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bands", nargs="+", default=["g", "r"])
    parser.add_argument("--n-ref", type=int, default=60, help="reference wavelengths")
    parser.add_argument("--rays", type=int, default=100_000,
                        help="reference rays per wavelength (point and star each)")
    parser.add_argument("--baseline", help="an earlier inject/optics.py to time against")
    parser.add_argument("--no-check", action="store_true", help="only the timing")
    parser.add_argument("--no-timing", action="store_true", help="only the check")
    args = parser.parse_args()
    if not args.no_check:
        check(args.bands, args.n_ref, args.rays)
    if not args.no_timing:
        timing(args.bands[0], args.baseline)


if __name__ == "__main__":
    main()
