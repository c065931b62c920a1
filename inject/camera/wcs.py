"""Celestial WCS of a CCD from a pointing (TAN projection)."""
from astropy.wcs import WCS

from inject.errors import InputError, SceneError
from inject.camera.layout import rotation_matrix
from inject.validate import check_pointing


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
        ra, dec, rotation = check_pointing(pointing)
    except InputError as err:
        raise SceneError(str(err)) from None
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
