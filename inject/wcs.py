"""Celestial WCS of a CCD from a pointing (TAN projection)."""
from astropy.wcs import WCS

from .errors import SceneError
from .focalplane import rotation_matrix


def pointing_wcs(pointing, shape, pixel_scale_arcsec, crpix=None):
    """A TAN WCS for a CCD.

    Parameters
    ----------
    pointing : dict
        ``{ra: deg, dec: deg, rotation: deg}``: the sky position of the reference pixel and the
        angle from +y (columns) to north, counter-clockwise (east of north for a camera looking
        at the sky: RA increases to the left, as displayed with origin lower).
    shape : tuple
        ``(ny, nx)``.
    pixel_scale_arcsec : float
    crpix : tuple, optional
        0-based ``(x, y)`` pixel at the pointing; the image centre by default (a CCD away from
        the boresight passes its own offset here).
    """
    try:
        ra, dec = float(pointing["ra"]), float(pointing["dec"])
        rotation = float(pointing.get("rotation", 0.0))
    except (KeyError, TypeError, ValueError):
        raise SceneError(f"pointing={pointing!r}: needs numeric ra and dec (deg), "
                         "optional rotation") from None
    if not (0 <= ra < 360 and -90 <= dec <= 90):
        raise SceneError(f"pointing={pointing!r}: ra must be in [0, 360), dec in [-90, 90]")
    ny, nx = shape
    if crpix is None:
        crpix = ((nx - 1) / 2, (ny - 1) / 2)
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra, dec]
    wcs.wcs.crpix = [crpix[0] + 1, crpix[1] + 1]  # FITS pixels are 1-based
    scale = pixel_scale_arcsec / 3600.0
    # East to the left (-x) and north up (+y) at rotation 0: the focal plane's convention.
    wcs.wcs.cd = scale * rotation_matrix(rotation)
    wcs.wcs.cunit = ["deg", "deg"]
    return wcs
