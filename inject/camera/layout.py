"""The LSSTCam focal plane: 189 science CCDs, their pixels in focal-plane millimetres, the
field-angle distortion (each CCD's celestial WCS is :mod:`inject.camera.wcs`'s).

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
import re
from dataclasses import dataclass

import numpy as np

from inject.camera.detector import E2V, ITL
from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD
from inject.trajectory import clip_path_boxes

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
        grown by ``margin_px``; ``shape`` (ny, nx) for a cut-out from pixel (0, 0)
        (:func:`boxes_mm` of this CCD)."""
        return tuple(float(v) for v in boxes_mm((self,), margin_px, shape)[0])

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
# Tracks against the layout

def extent_mm():
    """``(xmin, xmax, ymin, ymax)`` of the science CCDs' pixel areas, mm."""
    boxes = np.array([c.bounds_mm() for c in CCDS])
    return (float(boxes[:, 0].min()), float(boxes[:, 1].max()),
            float(boxes[:, 2].min()), float(boxes[:, 3].max()))


def boxes_mm(ccds=CCDS, margin_px=0.0, shape=None):
    """``(xmin, xmax, ymin, ymax)`` mm of several CCDs' pixel areas (edges at -0.5 and
    n - 0.5 px, :meth:`CCD.pixel_to_focal`'s arithmetic term by term) as an ``(n, 4)`` array.

    Parameters
    ----------
    ccds : sequence of CCD
    margin_px : float
        Pixels added on every side.
    shape : tuple of int, optional
        ``(ny, nx)`` of a cut-out from pixel (0, 0) (each CCD's own shape if None).
    """
    centre = np.array([c.centre_mm for c in ccds], float).reshape(-1, 2)
    refpos = np.array([c.refpos for c in ccds], float).reshape(-1, 2)
    size = np.array([c.shape if shape is None else shape for c in ccds], float).reshape(-1, 2)
    low = -0.5 - margin_px
    x0 = centre[:, 0] + (low - refpos[:, 0]) * PIXEL_MM
    y0 = centre[:, 1] + (low - refpos[:, 1]) * PIXEL_MM
    x1 = centre[:, 0] + (size[:, 1] - 0.5 + margin_px - refpos[:, 0]) * PIXEL_MM
    y1 = centre[:, 1] + (size[:, 0] - 0.5 + margin_px - refpos[:, 1]) * PIXEL_MM
    return np.stack([x0, x1, y0, y1], axis=1)


def ccds_reached(xs, ys, margin_px=0.0, ccds=CCDS, shape=None):
    """CCDs whose pixel area grown by ``margin_px`` a polyline (mm) reaches, in the order of
    ``ccds`` (id order by default)."""
    ccds = tuple(ccds)
    if not ccds:
        return ()
    box, _, _, _ = clip_path_boxes(xs, ys, boxes_mm(ccds, margin_px, shape))
    return tuple(ccds[i] for i in np.unique(box))
