"""Other ways to draw a streak, kept to compare the renderer against (benchmarks and tests).

* :func:`render_galsim_box` is the idiom of LSST ``source_injection`` and imSim: a thin
  ``galsim.Box(L, w)`` convolved with the profile and drawn by FFT. Exact up to GalSim's
  ``GSParams`` but its FFT grows with the square of the streak length.
* :func:`render_gaussian` is the Tyson et al. (2020) / Bektesevic et al. (2018) approximation:
  a Gaussian cross-section of FWHM ``sqrt(theta_atm^2 + (D_sat^2 + D_mirror^2) / r^2)``.
  Cheap, but 6-8% too wide and the wrong shape for defocused profiles.
"""
import galsim
import numpy as np
from scipy import special

from inject.instrument import ARCSEC_PER_RAD

#: Width (arcsec) of the thin box in the GalSim idiom.
BOX_WIDTH_ARCSEC = 1e-6


def render_galsim_box(shape, profile, pixel_scale, segment, flux_per_px, gsparams=None):
    """Draw ``Box(L) x profile`` rotated to the track, by FFT, into a new float64 image.

    Parameters
    ----------
    shape : tuple
        ``(ny, nx)`` of the image.
    profile : galsim.GSObject
        Unit-flux stationary profile in the track frame (arcsec).
    pixel_scale : float
        Arcsec per pixel.
    segment : Segment
    flux_per_px : float
        Charge per pixel of track length.
    gsparams : galsim.GSParams, optional
        Accuracy (and the FFT size allowed).
    """
    length = segment.length * pixel_scale
    streak = galsim.Convolve([galsim.Box(length, BOX_WIDTH_ARCSEC), profile], gsparams=gsparams)
    streak = streak.rotate(segment.angle_deg * galsim.degrees).withFlux(
        flux_per_px * segment.length)
    image = galsim.ImageD(shape[1], shape[0], xmin=0, ymin=0, scale=pixel_scale)
    centre = galsim.PositionD(0.5 * (segment.x0 + segment.x1), 0.5 * (segment.y0 + segment.y1))
    streak.drawImage(image=image, center=centre, method="auto")
    return image.array


def gaussian_fwhm(model):
    """Tyson/Bektesevic effective FWHM (arcsec) of a :class:`~inject.streak.StreakModel`."""
    r_m = model.geometry.range_km * 1e3
    d_mirror = 2 * model.telescope.outer_radius_m
    return float(np.sqrt(model.seeing.fwhm_arcsec ** 2
                         + (model.shape.size_m ** 2 + d_mirror ** 2) / r_m ** 2
                         * ARCSEC_PER_RAD ** 2))


def render_gaussian(shape, model, segment):
    """Sweep a Gaussian of :func:`gaussian_fwhm` along a segment (pixel-integrated across the
    track, error-function ends along it) into a new float64 image."""
    p = model.pixel_scale
    sigma = gaussian_fwhm(model) / p / (2 * np.sqrt(2 * np.log(2)))
    y, x = np.indices(shape, dtype=float)
    c, s = segment.direction
    t = (x - segment.x0) * c + (y - segment.y0) * s
    d = -(x - segment.x0) * s + (y - segment.y0) * c
    root2 = np.sqrt(2) * sigma
    across = 0.5 * (special.erf((d + 0.5) / root2) - special.erf((d - 0.5) / root2))
    along = 0.5 * (special.erf(t / root2) - special.erf((t - segment.length) / root2))
    return model.flux_per_px * across * along
