"""Every celestial WCS of inject, one pointing type, and the sky orientation they share.

Sky orientation (``rotation``, as LSST's ``rotSkyPos``): the position angle of the focal
plane's +y axis, measured from north through east, as afw's ``makeCdMatrix(orientation=
rotSkyPos, flipX=False)`` (obs_lsst's LSSTCam raw formatter keeps ``wcsFlipX = False``). At
rotation 0, +y points north and +x west (east is to the left, as the sky is seen); at
rotation 90 deg, +y points east. A single CCD scene's WCS (:func:`pointing_wcs`) and each
focal-plane CCD's (:func:`ccd_wcs`) use the same convention, and so do the field angles of
:mod:`inject.orbits.passes` (:func:`tangent_to_focal`).
"""
import math
from dataclasses import dataclass

import numpy as np

from inject.camera.layout import (
    DISTORTION_R3,
    DISTORTION_R5,
    PIXEL_MM,
    PLATE_SCALE_ARCSEC_PER_MM,
    field_angle,
)
from inject.errors import InputError, SceneError
from inject.validate import check_pointing


@dataclass(frozen=True)
class Pointing:
    """Telescope boresight (ICRS, deg) and rotator angle ``rotation_deg`` (LSST's rotSkyPos,
    the module's convention)."""

    ra_deg: float
    dec_deg: float
    rotation_deg: float = 0.0

    def __post_init__(self):
        ra, dec, rotation = check_pointing(
            {"ra": self.ra_deg, "dec": self.dec_deg, "rotation": self.rotation_deg})
        object.__setattr__(self, "ra_deg", ra)
        object.__setattr__(self, "dec_deg", dec)
        object.__setattr__(self, "rotation_deg", rotation)

    @classmethod
    def from_mapping(cls, spec):
        """A pointing from ``{ra, dec, rotation}`` (deg; rotation optional, 0)."""
        return cls(*check_pointing(spec))

    def as_mapping(self):
        """``{ra, dec, rotation}``, deg."""
        return {"ra": self.ra_deg, "dec": self.dec_deg, "rotation": self.rotation_deg}

    @property
    def icrs(self):
        """The boresight as an astropy ``SkyCoord`` (ICRS)."""
        from astropy import units as u
        from astropy.coordinates import SkyCoord

        return SkyCoord(self.ra_deg * u.deg, self.dec_deg * u.deg, frame="icrs")


def tangent_to_focal(xi, eta, rotation_deg):
    """Rotate standard coordinates (xi East, eta North) into the focal-plane axes (x, y).

    The matrix of :func:`rotation_matrix` is a reflection, its own inverse, so the same call
    maps focal-plane axes back to (xi, eta).
    """
    (a, b), (c, d) = rotation_matrix(rotation_deg)
    return a * xi + b * eta, c * xi + d * eta


def _tan_wcs(ra, dec, crpix, cd, sip=False):
    """A TAN (optionally TAN-SIP) WCS about (ra, dec) with 0-based ``crpix`` and CD matrix."""
    from astropy.wcs import WCS

    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra, dec]
    wcs.wcs.crpix = [crpix[0] + 1, crpix[1] + 1]  # FITS pixels are 1-based
    wcs.wcs.cd = cd
    wcs.wcs.cunit = ["deg", "deg"]
    # LONPOLE 180 at every dec: WCSLIB's default turns to 0 when CRVAL2 is +90 exactly, which
    # would turn the field by 180 deg against a pointing next to the pole.
    wcs.wcs.lonpole = 180.0
    return wcs


def rotation_matrix(rotation_deg):
    """Field angle (along focal-plane x, y) -> (east, north) tangent-plane offsets.

    +y goes to position angle ``rotation`` (north through east) and +x to ``rotation - 90``
    (west at rotation 0), as afw's ``makeCdMatrix(orientation, flipX=False)``.
    """
    c, s = np.cos(np.radians(rotation_deg)), np.sin(np.radians(rotation_deg))
    return np.array([[-c, s], [s, c]])


def ccd_wcs(ccd_, pointing):
    """The celestial WCS of a CCD: TAN with SIP terms that are the distortion itself.

    The mapping is exact, not fitted: ``CRPIX`` is the boresight's position in the CCD's pixel
    frame (outside the CCD unless it is R22_S11), so that ``u = pixel - CRPIX`` is
    proportional to the focal-plane position. The field angle is ``c u (1 - D3 r^2 - D5
    r^4)`` with ``r = 0.01 |u|`` mm, a polynomial of degree 5 in ``u``: the forward SIP
    polynomials ``A, B`` are its non-linear terms exactly, and the CD matrix is the boresight
    plate scale turned by the rotator. The inverse ``AP, BP`` is the series inverse of the
    radial polynomial fitted to order 9 (:func:`_sip_coefficients`; astropy's
    ``world_to_pixel`` iterates on the forward terms anyway). Tested against an independent
    gnomonic computation in ``tests/test_focalplane.py``.

    Parameters
    ----------
    ccd_ : CCD
    pointing : dict
        ``{ra, dec, rotation}``, deg; ``rotation`` as LSST's rotSkyPos (module docstring).

    Returns
    -------
    astropy.wcs.WCS
        ``to_header(relax=True)`` keeps the SIP terms.
    """
    from astropy.wcs import Sip

    ra, dec, rotation = check_pointing(pointing)
    scale_deg = PLATE_SCALE_ARCSEC_PER_MM * PIXEL_MM / 3600.0
    wcs = _tan_wcs(ra, dec, ccd_.boresight_pixel, scale_deg * rotation_matrix(rotation), sip=True)
    a, b, ap, bp = _sip_coefficients()
    wcs.sip = Sip(a, b, ap, bp, wcs.wcs.crpix)
    ny, nx = ccd_.shape
    wcs.pixel_shape = (nx, ny)
    return wcs


#: Largest focal-plane radius the inverse SIP is fitted to, mm (the science corners are at
#: 368 mm).
_INVERSE_RADIUS_MM = 400.0


def _sip_coefficients():
    """SIP ``A, B`` (forward: exact, order 5) and ``AP, BP`` (inverse: order 9) of the radial
    distortion.

    In pixels ``u, v`` from the boresight, ``rho^2 = (u^2 + v^2) p^2`` (``p = 0.01`` mm), the
    forward terms are ``f(u) = -u (D3 rho^2 + D5 rho^4)``. The inverse is radial too, ``g(U)
    = U h(R^2)`` with ``R`` the radius of ``U = u + f`` in mm; the series of ``h`` converges
    slowly at the corners (to 7th order it is still 2e-4 px off), so ``h`` is a quartic in
    ``R^2`` fitted by least squares to the exact inverse (Newton) out to 400 mm: it is good
    to ~1e-8 px (tested to 1e-6 px through astropy's ``sip_foc2pix``).
    """
    p2 = PIXEL_MM ** 2
    r = np.linspace(1.0, _INVERSE_RADIUS_MM, 2000)
    big_r = r - DISTORTION_R3 * r ** 3 - DISTORTION_R5 * r ** 5
    scaled = big_r / _INVERSE_RADIUS_MM  # columns of comparable size for the fit
    design = np.column_stack([scaled ** (2 * n) for n in range(1, 5)])
    h = np.linalg.lstsq(design, r / big_r - 1.0, rcond=None)[0]
    h = h / _INVERSE_RADIUS_MM ** (2 * np.arange(1, 5))
    a = np.zeros((6, 6))
    ap = np.zeros((10, 10))
    for coeffs, terms in ((a, (-DISTORTION_R3, -DISTORTION_R5)), (ap, tuple(h))):
        for n, c in enumerate(terms, start=1):
            # u (u^2 + v^2)^n = sum_k C(n, k) u^(2n - 2k + 1) v^(2k); A[p, q] multiplies u^p v^q.
            for k in range(n + 1):
                coeffs[2 * (n - k) + 1, 2 * k] = c * p2 ** n * math.comb(n, k)
    return a, a.T.copy(), ap, ap.T.copy()


def focal_to_radec(x_mm, y_mm, pointing):
    """(ra, dec) deg of focal-plane positions: field angle, rotation, gnomonic projection
    (by astropy's TAN about the boresight)."""
    ra, dec, rotation = check_pointing(pointing)
    ax, ay = field_angle(x_mm, y_mm)
    east, north = rotation_matrix(rotation) @ np.vstack([np.ravel(ax), np.ravel(ay)])
    # Pixel (0, 0) at the boresight and one "pixel" a radian: the offsets are the IWC.
    wcs = _tan_wcs(ra, dec, (0, 0), np.degrees(1) * np.eye(2))
    out = wcs.wcs_pix2world(np.column_stack([east, north]), 0)
    return out[:, 0].reshape(np.shape(ax)), out[:, 1].reshape(np.shape(ax))


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
    # East to the left (-x) and north up (+y) at rotation 0: the focal plane's convention.
    return _tan_wcs(ra, dec, crpix, pixel_scale_arcsec / 3600.0 * rotation_matrix(rotation))
