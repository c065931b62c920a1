"""Reproduce the four figures of Snyder & Tyson (sections 2-3) with the ``inject`` engine.

Writes, into ``--out`` (default ``out/figures``):

``fig1_range.png``
    Range vs orbit height at several zenith angles.
``fig2_teff.png``
    Effective pixel exposure time vs orbit height (motion along constant azimuth).
``fig3_profiles.png``
    Geometric profile, defocus kernel and stationary profile at 550 and 350 km.
``fig4_cross_sections.png``
    Streak cross-sections (e-/px) at 550 and 350 km.

It prints one line per file, the 350/550 km peak surface-brightness ratio (the paper quotes
~4 %) and the two FWHMs.

Examples
--------
>>> main(["--out", "out/figures"])  # doctest: +SKIP
"""
import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from inject.geometry import effective_exposure, slant_range  # noqa: E402
from inject.profile import defocus_kernel  # noqa: E402
from inject.streak import StreakModel  # noqa: E402

HEIGHTS_KM = np.linspace(200.0, 1200.0, 201)
ZENITHS_DEG = (0, 20, 40, 60, 70, 80)
PAPER_HEIGHTS_KM = (550.0, 350.0)
PAPER_ZENITH_DEG = 70.0
GRID_SCALE_ARCSEC = 0.02
GRID_PIXELS = 300  # 6" field


def _save(fig, path):
    """Write ``fig`` to ``path``, close it and report the file."""
    fig.savefig(path, dpi=150)
    plt.close(fig)
    print(f"wrote {path}")


def height_plot(path, quantity, ylabel, title):
    """Plot ``quantity(height_km, zenith_deg)`` vs orbit height, one line per zenith angle."""
    values = quantity(HEIGHTS_KM[:, None], np.asarray(ZENITHS_DEG, dtype=float)[None, :])
    fig, ax = plt.subplots(figsize=(6, 4.5), layout="constrained")
    lines = ax.plot(HEIGHTS_KM, values)
    ax.legend(lines, [f"z = {z}°" for z in ZENITHS_DEG], title="zenith angle")
    ax.set(xlabel="orbit height (km)", ylabel=ylabel, title=title, xlim=HEIGHTS_KM[[0, -1]])
    ax.grid(alpha=0.3)
    _save(fig, path)


def draw(profile):
    """Surface brightness (arcsec^-2) of a unit-flux GalSim profile on the common grid."""
    image = profile.drawImage(nx=GRID_PIXELS, ny=GRID_PIXELS, scale=GRID_SCALE_ARCSEC,
                              method="no_pixel")
    return image.array / GRID_SCALE_ARCSEC ** 2


def profiles_figure(path, models):
    """2x3 grid: geometric profile, defocus kernel, stationary profile; one row per model."""
    titles = ("geometric profile", "defocus kernel", "stationary profile")
    images = []
    for m in models:
        g = m.geometry
        images.append([draw(m.shape.profile(g.range_km, g.nadir_angle_deg, g.phi_deg)),
                       draw(defocus_kernel(g.range_km, m.telescope)), draw(m.profile)])
    half = GRID_PIXELS * GRID_SCALE_ARCSEC / 2
    fig, axes = plt.subplots(len(models), 3, figsize=(12, 3.6 * len(models) + 0.6),
                             layout="constrained", sharex=True, sharey=True)
    for col, title in enumerate(titles):
        vmax = max(row[col].max() for row in images)
        for row, m in enumerate(models):
            ax = axes[row, col]
            im = ax.imshow(images[row][col], origin="lower", cmap="magma", vmin=0, vmax=vmax,
                           extent=(-half, half, -half, half))
            ax.set_title(f"{title}, h = {m.height_km:.0f} km", fontsize=10)
            ax.set_xlabel("along track (arcsec)")
            ax.set_ylabel("across track (arcsec)")
            ax.label_outer()
        fig.colorbar(im, ax=axes[:, col], shrink=0.9, label="flux fraction / arcsec²")
    fig.suptitle(f"7.25 m x 2.65 m box, z = {PAPER_ZENITH_DEG:.0f}°, φ = 90°, "
                 f"Kolmogorov {models[0].seeing.fwhm_arcsec}\"")
    _save(fig, path)


def cross_section_figure(path, models):
    """Streak cross-sections (e-/px vs offset across the track) with FWHM and peak."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5), layout="constrained")
    for m in models:
        offset, e_per_px = m.cross_section(half_width_arcsec=4.0)
        ax.plot(offset, e_per_px, label=f"h = {m.height_km:.0f} km: FWHM {m.fwhm_arcsec:.2f}\", "
                                       f"peak {m.peak_e_per_px:,.0f} e-/px")
    ref = models[0]
    ax.set(xlabel="offset across track (arcsec)", ylabel="charge per pixel (e-/px)",
           title=f"streak cross-sections, z = {PAPER_ZENITH_DEG:.0f}°, stationary "
                 f"{ref.band_name} = {ref.mag:g} at {ref.ref_range_km:.0f} km")
    ax.set_ylim(0, 1.3 * ax.get_ylim()[1])
    ax.legend(loc="upper center")
    ax.grid(alpha=0.3)
    _save(fig, path)


def main(argv=None):
    """Parse ``--out``, write the four figures and print the peak ratio and FWHMs."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/figures"),
                        help="output directory (created if needed)")
    out = parser.parse_args(argv).out
    out.mkdir(parents=True, exist_ok=True)
    height_plot(out / "fig1_range.png", slant_range, "range (km)",
                "distance to the satellite")
    height_plot(out / "fig2_teff.png", lambda h, z: 1e3 * effective_exposure(h, z, 90.0),
                "effective pixel exposure $t_\\mathrm{eff}$ (ms)",
                "effective pixel exposure, φ = 90° (constant azimuth)")
    models = [StreakModel(h, PAPER_ZENITH_DEG) for h in PAPER_HEIGHTS_KM]
    profiles_figure(out / "fig3_profiles.png", models)
    cross_section_figure(out / "fig4_cross_sections.png", models)
    high, low = models
    print(f"peak surface brightness 350/550 km: {low.peak_e_per_px / high.peak_e_per_px:.3f}")
    for m in models:
        print(f"FWHM at {m.height_km:.0f} km: {m.fwhm_arcsec:.3f} arcsec")


if __name__ == "__main__":
    main()
