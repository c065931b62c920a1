"""Bands, zero points, sky brightness and the satellite magnitude scaling.

Zero points are AB magnitudes giving 1 e-/s at airmass 1 for LSSTCam, and the dark-sky
brightnesses are zenith values in mag/arcsec^2; both from SMTN-002 v1.9 (Yoachim et al., "LSST
throughputs and sensitivity"). Extinction coefficients are from the same table.
"""
from dataclasses import dataclass

import numpy as np

from inject.errors import InputError
from inject.validate import finite, positive


@dataclass(frozen=True)
class Band:
    """Photometric constants of one LSST filter.

    Parameters
    ----------
    name : str
        Filter name (``u g r i z y``).
    zeropoint : float
        AB magnitude giving 1 e-/s at airmass 1.
    sky_mag : float
        Dark-sky brightness at zenith, mag/arcsec^2.
    extinction : float
        Atmospheric extinction, mag per airmass.
    """

    name: str
    zeropoint: float
    sky_mag: float
    extinction: float


#: SMTN-002 v1.9 values for LSSTCam.
BANDS = {b.name: b for b in (
    Band("u", 26.52, 23.05, 0.47),
    Band("g", 28.51, 22.25, 0.21),
    Band("r", 28.36, 21.20, 0.13),
    Band("i", 28.17, 20.46, 0.10),
    Band("z", 27.78, 19.61, 0.07),
    Band("y", 26.82, 18.60, 0.17),
)}


def band(name):
    """Return the :class:`Band` called ``name`` or raise :class:`InputError`."""
    try:
        return BANDS[name]
    except (KeyError, TypeError):
        raise InputError("band", name, f"unknown band; choose one of {' '.join(BANDS)}") from None


def electron_rate(mag, band_name):
    """Count rate in e-/s of a source of AB magnitude ``mag`` in ``band_name``."""
    m = finite("mag", mag)
    return 10.0 ** (0.4 * (band(band_name).zeropoint - m))


def sky_per_pixel(band_name, exptime_s, pixel_scale_arcsec=0.2, sky_mag=None):
    """Sky background in electrons per pixel over ``exptime_s`` (dark sky at zenith by default).

    As in SMTN-002, the sky is counted with the hardware-only zero point (``zeropoint +
    extinction``): the sky's light is not extinguished by the airmass the way a star's is.
    This gives ~465 e-/px in g for 30 s.
    """
    b = band(band_name)
    mu = b.sky_mag if sky_mag is None else float(finite("sky_mag", sky_mag))
    t = positive("exptime", exptime_s)
    p = positive("pixel_scale_arcsec", pixel_scale_arcsec)
    return 10.0 ** (0.4 * (b.zeropoint + b.extinction - mu)) * t * p ** 2


def apparent_magnitude(mag_ref, range_km, nadir_angle_deg, ref_range_km=550.0):
    """Satellite magnitude seen at ``range_km`` and nadir angle, from a face-on reference.

    The reflected flux scales as ``cos(theta_N) / r^2`` (paper section 2.2), so
    ``m = m_ref + 5 log10(r / r_ref) - 2.5 log10(cos theta_N)``.
    """
    m = finite("mag", mag_ref)
    r = positive("range_km", range_km)
    r_ref = positive("ref_range_km", ref_range_km)
    cos_tn = np.cos(np.radians(finite("nadir_angle_deg", nadir_angle_deg)))
    if np.any(cos_tn <= 0):
        raise InputError("nadir_angle_deg", nadir_angle_deg, "must be < 90")
    return m + 5.0 * np.log10(r / r_ref) - 2.5 * np.log10(cos_tn)
