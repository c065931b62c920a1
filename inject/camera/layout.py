"""The LSSTCam focal plane: 189 science CCDs, their pixels in focal-plane millimetres, the
field-angle distortion and each CCD's celestial WCS (DESIGN.md section 8).

Geometry is obs_lsst's nominal one (``policy/rafts.yaml``, ``policy/lsstCam/R*.yaml``,
``generateCamera.py``; afw ``cameraGeom/Orientation.cc``): raft ``Rij`` is centred at
``(127 (j - 2), 127 (i - 2))`` mm and its CCD ``Sij`` at ``(42.25 (j - 1), 42.25 (i - 1))`` mm
from the raft centre, with no yaw anywhere, so a CCD's pixel ``(x, y)`` lies at::

    FP = centre + (pixel - refpos) * 0.010 mm

with ``refpos = (2047.5, 2001.5)`` for e2v (4096 x 4004) and ``(2036.5, 2000.5)`` for ITL
(4072 x 4000). The focal-plane frame's origin is the centre of R22_S11 and its axes run along
every CCD's pixel x and y. The corner rafts R00, R04, R40, R44 hold guiders and wavefront
sensors (ids 189-204) and are not science CCDs: they are not part of this layout.

Field angles follow obs_lsst's ``FocalPlane -> FieldAngle`` radial polynomial
(``cameraTransforms.yaml``): a point at radius ``r`` mm is seen at the field angle
``PLATE_SCALE * (r - 8.33713991e-9 r^3 - 1.41389858e-15 r^5)`` arcsec from the boresight,
in the direction of the point. As in afw's ``makeSkyWcs(pixelsToFieldAngle, orientation,
flipX, boresight)``, the field angle (in radians) is the intermediate world coordinate of a
gnomonic (TAN) projection about the boresight, turned on the sky by the rotator angle.

Sky orientation (``rotation``, as LSST's ``rotSkyPos``): the position angle of the focal
plane's +y axis, measured from north through east, as afw's ``makeCdMatrix(orientation=
rotSkyPos, flipX=False)`` (obs_lsst's LSSTCam raw formatter keeps ``wcsFlipX = False``). At
rotation 0, +y points north and +x west (east is to the left, as the sky is seen); at
rotation 90 deg, +y points east. :mod:`inject.camera.wcs` uses the same convention for single CCDs.
"""
import math
import re
from dataclasses import dataclass

import numpy as np

from inject.camera.detector import E2V, ITL
from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD
from inject.trajectory import _clip_line
from inject.validate import check_pointing

#: Pixel pitch, mm.
PIXEL_MM = 0.010
#: Raft pitch and CCD pitch inside a raft, mm.
RAFT_PITCH_MM = 127.0
CCD_PITCH_MM = 42.25
#: obs_lsst's plate scale at the boresight, arcsec per mm (0.20006"/px).
PLATE_SCALE_ARCSEC_PER_MM = 20.005867576692737
#: Radial distortion: angle = plate scale x (r - D3 r^3 - D5 r^5), r in mm.
DISTORTION_R3 = 8.33713991e-9
DISTORTION_R5 = 1.41389858e-15

#: Rafts holding ITL sensors; the other 13 science rafts hold e2v sensors.
ITL_RAFTS = ("R01", "R02", "R03", "R10", "R20", "R41", "R42", "R43")
#: The 21 science rafts in detector-id order.
SCIENCE_RAFTS = tuple(f"R{i}{j}" for i in range(5) for j in range(5)
                      if (i, j) not in ((0, 0), (0, 4), (4, 0), (4, 4)))
#: Reference pixel (x, y) at the CCD's nominal position, per vendor.
REFPOS = {"e2v": (2047.5, 2001.5), "itl": (2036.5, 2000.5)}
SENSORS = {"e2v": E2V, "itl": ITL}

_NAME = re.compile(r"^R([0-4])([0-4])_S([0-2])([0-2])$")


@dataclass(frozen=True)
class CCD:
    """One science CCD of the focal plane.

    Attributes
    ----------
    name : str
        ``Rij_Skl``.
    id : int
        obs_lsst detector id, 0-188.
    vendor : str
        ``"itl"`` or ``"e2v"``.
    centre_mm : tuple of float
        Focal-plane position of the reference pixel, mm.
    refpos : tuple of float
        Reference pixel ``(x, y)``.
    """

    name: str
    id: int
    vendor: str
    centre_mm: tuple
    refpos: tuple

    @property
    def raft(self):
        return self.name[:3]

    @property
    def sensor(self):
        return self.name[4:]

    @property
    def detector(self):
        """The full-size :class:`~inject.camera.detector.Detector` of this CCD's vendor."""
        return SENSORS[self.vendor]

    @property
    def shape(self):
        """``(ny, nx)`` of the full CCD."""
        return self.detector.shape

    def pixel_to_focal(self, x, y):
        """Focal-plane mm of pixel coordinates (pixel (0, 0) is the first pixel's centre)."""
        return (self.centre_mm[0] + (np.asarray(x, float) - self.refpos[0]) * PIXEL_MM,
                self.centre_mm[1] + (np.asarray(y, float) - self.refpos[1]) * PIXEL_MM)

    def focal_to_pixel(self, x_mm, y_mm):
        """Pixel coordinates of focal-plane mm (the inverse of :meth:`pixel_to_focal`)."""
        return (self.refpos[0] + (np.asarray(x_mm, float) - self.centre_mm[0]) / PIXEL_MM,
                self.refpos[1] + (np.asarray(y_mm, float) - self.centre_mm[1]) / PIXEL_MM)

    def bounds_mm(self, margin_px=0.0, shape=None):
        """``(xmin, xmax, ymin, ymax)`` mm of the pixel area (edges at -0.5 and n - 0.5 px)
        grown by ``margin_px``; ``shape`` (ny, nx) for a cut-out from pixel (0, 0)."""
        ny, nx = self.shape if shape is None else shape
        x0, y0 = self.pixel_to_focal(-0.5 - margin_px, -0.5 - margin_px)
        x1, y1 = self.pixel_to_focal(nx - 0.5 + margin_px, ny - 0.5 + margin_px)
        return float(x0), float(x1), float(y0), float(y1)

    @property
    def boresight_pixel(self):
        """Pixel coordinates of the focal-plane origin (the boresight) in this CCD's frame."""
        x, y = self.focal_to_pixel(0.0, 0.0)
        return float(x), float(y)


def _build_ccds():
    ccds = []
    for k, raft in enumerate(SCIENCE_RAFTS):
        ri, rj = int(raft[1]), int(raft[2])
        vendor = "itl" if raft in ITL_RAFTS else "e2v"
        for i in range(3):
            for j in range(3):
                centre = (RAFT_PITCH_MM * (rj - 2) + CCD_PITCH_MM * (j - 1),
                          RAFT_PITCH_MM * (ri - 2) + CCD_PITCH_MM * (i - 1))
                ccds.append(CCD(f"{raft}_S{i}{j}", 9 * k + 3 * i + j, vendor, centre,
                                REFPOS[vendor]))
    return tuple(ccds)


#: The 189 science CCDs, in detector-id order.
CCDS = _build_ccds()
BY_NAME = {c.name: c for c in CCDS}


def ccd(key):
    """The :class:`CCD` named ``key`` (``"R22_S11"``) or with detector id ``key``.

    Raises
    ------
    InputError
        Not a science CCD (a corner raft, a malformed name, an id outside 0-188).
    """
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        if 0 <= key < len(CCDS):
            return CCDS[int(key)]
        raise InputError("detector", key, f"ids run from 0 to {len(CCDS) - 1}")
    if isinstance(key, str):
        name = key.strip().upper()
        if name in BY_NAME:
            return BY_NAME[name]
        if name.isdigit():
            return ccd(int(name))
        match = _NAME.match(name)
        if match and f"R{match[1]}{match[2]}" not in SCIENCE_RAFTS:
            raise InputError("detector", key, "corner rafts hold guiders and wavefront sensors, "
                                              "not science CCDs")
    raise InputError("detector", key, "not a science CCD name (R01_S00 ... R43_S22) or id")


def select(keys):
    """CCDs for a list of names or ids (or one comma-separated string), in id order, each
    once; every CCD when ``keys`` is None."""
    if keys is None:
        return CCDS
    if isinstance(keys, str):
        keys = [k for k in keys.split(",") if k.strip()]
    if not keys:
        raise InputError("detectors", keys, "needs at least one CCD")
    return tuple(sorted({ccd(k) for k in keys}, key=lambda c: c.id))


# -------------------------------------------------------------------------------------------
# Field angles and plate scale

def field_angle(x_mm, y_mm):
    """Field angle (radians, along focal-plane x and y) of a focal-plane position."""
    x, y = np.asarray(x_mm, float), np.asarray(y_mm, float)
    r2 = x * x + y * y
    factor = (1.0 - DISTORTION_R3 * r2 - DISTORTION_R5 * r2 * r2) * (
        PLATE_SCALE_ARCSEC_PER_MM / ARCSEC_PER_RAD)
    return x * factor, y * factor


def radius_of_angle(theta_rad):
    """Focal-plane radius (mm) seen at field angle ``theta_rad`` (Newton on the polynomial,
    to 1e-12 mm)."""
    target = np.asarray(theta_rad, float) * ARCSEC_PER_RAD / PLATE_SCALE_ARCSEC_PER_MM
    r = target.copy()
    for _ in range(8):
        f = r - DISTORTION_R3 * r ** 3 - DISTORTION_R5 * r ** 5 - target
        r = r - f / (1.0 - 3 * DISTORTION_R3 * r ** 2 - 5 * DISTORTION_R5 * r ** 4)
    return r


def focal_of_field_angle(ax, ay):
    """Focal-plane mm of a field angle (radians): the inverse of :func:`field_angle`."""
    ax, ay = np.asarray(ax, float), np.asarray(ay, float)
    theta = np.hypot(ax, ay)
    r = radius_of_angle(theta)
    scale = np.divide(r, theta, out=np.full(theta.shape, ARCSEC_PER_RAD
                                            / PLATE_SCALE_ARCSEC_PER_MM), where=theta > 0)
    return ax * scale, ay * scale


def plate_scales(x_mm, y_mm):
    """Radial and tangential plate scale (arcsec per mm) at a focal-plane position.

    Radial: ``d angle / d r = s (1 - 3 D3 r^2 - 5 D5 r^4)``; tangential: ``angle / r = s (1 -
    D3 r^2 - D5 r^4)``. At the corners of the science area (r ~ 310 mm) they are 0.25% and
    0.08% below the boresight's 20.0059"/mm.
    """
    r2 = np.asarray(x_mm, float) ** 2 + np.asarray(y_mm, float) ** 2
    s = PLATE_SCALE_ARCSEC_PER_MM
    return (s * (1 - 3 * DISTORTION_R3 * r2 - 5 * DISTORTION_R5 * r2 * r2),
            s * (1 - DISTORTION_R3 * r2 - DISTORTION_R5 * r2 * r2))


def pixel_scale_along(x_mm, y_mm, angle_deg):
    """Sky length (arcsec) of one pixel step along direction ``angle_deg`` at a position.

    A streak's effective exposure per pixel is this length over its angular speed, so its
    charge per pixel of track scales with it (the width in pixels scales inversely).
    """
    x, y = float(x_mm), float(y_mm)
    radial, tangential = plate_scales(x, y)
    r = np.hypot(x, y)
    a = np.radians(angle_deg)
    if r == 0:
        return float(radial * PIXEL_MM)
    cos_rel = (np.cos(a) * x + np.sin(a) * y) / r  # direction against the radius
    sin_rel = np.sqrt(max(0.0, 1 - cos_rel ** 2))
    return float(PIXEL_MM * np.hypot(radial * cos_rel, tangential * sin_rel))


# -------------------------------------------------------------------------------------------
# Celestial WCS

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
    ``world_to_pixel`` iterates on the forward terms anyway). Tested against an independent gnomonic computation in ``tests/test_focalplane.py``.

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
    from astropy.wcs import Sip, WCS

    ra, dec, rotation = check_pointing(pointing)
    crpix = ccd_.boresight_pixel
    scale_deg = PLATE_SCALE_ARCSEC_PER_MM * PIXEL_MM / 3600.0
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = [ra, dec]
    wcs.wcs.crpix = [crpix[0] + 1, crpix[1] + 1]  # FITS pixels are 1-based
    wcs.wcs.cd = scale_deg * rotation_matrix(rotation)
    wcs.wcs.cunit = ["deg", "deg"]
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


def focal_to_sky(x_mm, y_mm, pointing):
    """(ra, dec) deg of focal-plane positions: field angle, rotation, gnomonic projection
    (by astropy's TAN about the boresight)."""
    from astropy.wcs import WCS

    ra, dec, rotation = check_pointing(pointing)
    ax, ay = field_angle(x_mm, y_mm)
    east, north = rotation_matrix(rotation) @ np.vstack([np.ravel(ax), np.ravel(ay)])
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra, dec]
    wcs.wcs.crpix = [1, 1]  # 0-based pixel (0, 0) below: the offsets are the IWC
    wcs.wcs.cdelt = [np.degrees(1), np.degrees(1)]  # IWC in radians -> degrees
    out = wcs.wcs_pix2world(np.column_stack([east, north]), 0)
    return out[:, 0].reshape(np.shape(ax)), out[:, 1].reshape(np.shape(ax))


# -------------------------------------------------------------------------------------------
# Tracks against the layout

def clip_path(xs, ys, box):
    """The parts of a polyline (focal-plane mm) inside a box ``(xmin, xmax, ymin, ymax)``.

    Returns
    -------
    list of tuple
        ``(piece, t0, t1)``: the index of the polyline piece and the fractions ``0 <= t0 <
        t1 <= 1`` along it that lie inside, in order along the path.
    """
    xmin, xmax, ymin, ymax = box
    out = []
    for k in range(len(xs) - 1):
        dx, dy = xs[k + 1] - xs[k], ys[k + 1] - ys[k]
        length = float(np.hypot(dx, dy))
        if length == 0:
            continue
        angle = float(np.degrees(np.arctan2(dy, dx)))
        chord = _clip_line(xs[k], ys[k], angle, (xmin, xmax), (ymin, ymax))
        if chord is None:
            continue
        t0, t1 = max(chord[0] / length, 0.0), min(chord[1] / length, 1.0)
        if t1 > t0:
            out.append((k, t0, t1))
    return out


def extent_mm():
    """``(xmin, xmax, ymin, ymax)`` of the science CCDs' pixel areas, mm."""
    boxes = np.array([c.bounds_mm() for c in CCDS])
    return (float(boxes[:, 0].min()), float(boxes[:, 1].max()),
            float(boxes[:, 2].min()), float(boxes[:, 3].max()))


def ccds_reached(xs, ys, margin_px=0.0, ccds=CCDS, shape=None):
    """CCDs whose pixel area grown by ``margin_px`` a polyline (mm) reaches, in id order."""
    return tuple(c for c in ccds if clip_path(xs, ys, c.bounds_mm(margin_px, shape)))
