"""Accuracy and speed of :func:`inject.stars.draw_stars` against GalSim drawing each star.

Accuracy: single stars at random sub-pixel positions, drawn by ``draw_stars`` and by
``psf.drawImage(method="auto", offset=...)`` with the same (project) GSParams; reported are
the largest pixel difference relative to the star's peak and the flux difference relative to
the star's flux, over the image (128^2 for faint stars, 401^2 for bright ones, both larger
than the stamps, so the flux difference includes the wings cut off at the stamp edge).

Speed: ~20,000 stars (Bahcall & Soneira magnitudes at l = 90, b = 30 scaled to that density,
r band, 30 s) on an ITL CCD (4072 x 4000), against GalSim drawing each star into a stamp of
the same size as the core stamp (timed on the first ``--galsim-stars`` and scaled).

Usage::

    python scripts/bench_stars.py [--seeing 0.67] [--oversample 16]
"""
import argparse
import time

import galsim
import numpy as np

from inject import stars
from inject.photometry import electron_rate
from inject.scene import rng

PIXEL = 0.2


def accuracy(st, n_stars, flux, size, gen):
    worst_pixel, worst_flux, lost = 0.0, 0.0, []
    for _ in range(n_stars):
        x, y = gen.uniform(size / 2 - 4, size / 2 + 4, 2)
        image = np.zeros((size, size))
        drawn = stars.draw_stars(image, [x], [y], [flux], st, PIXEL)
        ref = galsim.ImageD(size, size, scale=PIXEL)
        st.psf.drawImage(image=ref, offset=(x - (size - 1) / 2, y - (size - 1) / 2),
                         method="auto")
        ref = ref.array * flux
        worst_pixel = max(worst_pixel, np.abs(image - ref).max() / ref.max())
        worst_flux = max(worst_flux, abs(image.sum() - ref.sum()) / flux)
        lost.append(1 - drawn[0] / flux)
    return worst_pixel, worst_flux, max(lost)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeing", type=float, default=0.67, help="Kolmogorov FWHM, arcsec")
    parser.add_argument("--oversample", type=int, default=16)
    parser.add_argument("--stars", type=int, default=20000)
    parser.add_argument("--galsim-stars", type=int, default=300)
    args = parser.parse_args()

    psf = galsim.Kolmogorov(fwhm=args.seeing)
    t0 = time.perf_counter()
    st = stars.PsfStamps(psf, PIXEL, oversample=args.oversample)
    t_build = time.perf_counter() - t0
    print(f"PSF Kolmogorov {args.seeing}\", {args.oversample} phases/px: stamps built in "
          f"{t_build:.2f} s; core {2 * st.core_half + 1}^2 px (lost <= {st.core_lost:.1e}), "
          f"bright {2 * st.bright_half + 1}^2 px (lost <= {st.bright_lost:.1e})")

    gen = np.random.default_rng(1)
    for label, flux, size in (("faint (core stamp)", 1e4, 128), ("bright (with ring)", 1e7, 401)):
        pixel, flux_err, lost = accuracy(st, 30, flux, size, gen)
        print(f"{label:20s} max |pixel error| / peak {pixel:.2e}, |flux difference| / flux "
              f"{flux_err:.2e} in {size}^2, flux outside stamp <= {lost:.1e}")

    shape = (4000, 4072)
    area = shape[0] * shape[1] * (PIXEL / 3600) ** 2
    spec = stars.StarFieldSpec(galactic_l=90, galactic_b=30,
                               density_per_deg2=args.stars / area)
    field = stars.star_field(spec, shape, PIXEL, "r", rng(1, "stars"))
    flux = electron_rate(field["mag"], "r") * 30.0
    image = np.zeros(shape)
    image += 0.0  # touch the pages first
    t0 = time.perf_counter()
    drawn = stars.draw_stars(image, field["x"], field["y"], flux, st, PIXEL)
    t_draw = time.perf_counter() - t0
    n = flux.size
    print(f"{n} stars ({(flux >= 1e6).sum()} bright) on {shape[1]} x {shape[0]}: "
          f"draw_stars {t_draw:.2f} s (+{t_build:.2f} s stamps once); "
          f"charge landed / flux {drawn.sum() / flux.sum():.5f}")

    h = st.core_half
    size = 2 * h + 1
    for label, profile in (("GalSim default GSParams", psf), ("GalSim project GSParams", st.psf)):
        other = np.zeros(shape)
        m = min(args.galsim_stars, n)
        t0 = time.perf_counter()
        for k in range(m):
            ix, iy = int(np.floor(field["x"][k])), int(np.floor(field["y"][k]))
            stamp = profile.drawImage(nx=size, ny=size, scale=PIXEL, method="auto",
                                      offset=(field["x"][k] - ix, field["y"][k] - iy)).array
            y0, x0 = iy - h, ix - h
            ys, xs = max(y0, 0), max(x0, 0)
            ye, xe = min(y0 + size, shape[0]), min(x0 + size, shape[1])
            if ye > ys and xe > xs:
                other[ys:ye, xs:xe] += flux[k] * stamp[ys - y0:ye - y0, xs - x0:xe - x0]
        per_star = (time.perf_counter() - t0) / m
        print(f"{label}: {per_star * 1e3:.2f} ms per star -> {per_star * n:.1f} s for {n} "
              f"stars ({per_star * n / t_draw:.0f}x slower)")


if __name__ == "__main__":
    main()
