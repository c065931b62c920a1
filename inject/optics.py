"""The defocus kernel traced through Rubin's telescope (batoid), for a point at finite range.

:func:`inject.profile.defocus_kernel` takes the near-field pupil as an ideal annulus (radii
4.18 m and 2.558 m over the range). What the detector really receives from a point a few
hundred kilometres away is what the three mirrors, the camera's lenses and filter, the spider
vanes and the baffles make of it. :func:`traced_kernel` traces a point source at the range and
field position through batoid's LSST model of the band and returns the image it makes, in
arcsec on the sky, relative to a star at the same field position.

The model is batoid's baffled telescope (``LSST_r_baffles.yaml``: the centre cap, the spider
vanes, the top-end-assembly, M1, M2 and M1/M3 baffles) with the camera (L1, L2, filter, L3,
detector) of the band's own model (``LSST_{band}.yaml``), in vacuum as the band's model is;
both files ship with batoid, nothing is downloaded. The telescope is focused at infinity (the
design's detector position). The spider vanes' orientation is that of the model's frame: the
camera rotator and the telescope's rotation about its axis are not followed.

Geometric optics only: each ray lands where the optics send it (no diffraction; at 0.2" pixels
and seeing of 0.5" and more, diffraction's ~0.01" is far below the scales here), at one
wavelength per band (the band's effective wavelength, :data:`BAND_WAVELENGTH_NM`).
"""
import copy
import functools
import os
from dataclasses import dataclass

import galsim
import numpy as np

from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD
from inject.photometry import band as check_band
from inject.profile import GSPARAMS, line_spread
from inject.validate import finite, positive

#: Effective wavelength of each band, nm: the throughput-weighted values of LSST throughputs
#: v1.9 with the fiducial atmosphere at airmass 1.2, as Rubin's wavefront code (ts_wep) uses.
BAND_WAVELENGTH_NM = {"u": 370.9, "g": 476.7, "r": 619.4, "i": 753.9, "z": 866.8, "y": 973.9}

#: Default number of rays over the pupil's square (about 45% of them enter M1's clear annulus,
#: the rest are not traced). The kernel's FWHM with 0.67" seeing moves
#: by less than 0.02% from here to 4 times as many (docs/explanation/physics.md).
N_RAYS = 1_000_000

#: Default sampling of the kernel's image, arcsec.
KERNEL_SCALE_ARCSEC = 0.01

# Rays outside M1's clear annulus (widened by this margin on the stop plane, m) are not traced:
# M1 vignettes them all. The margin covers the beam's walk over M1's 0.44 m sag at 2 deg.
_PUPIL_MARGIN_M = 0.1
# Field offset for the plate-scale Jacobian, rad (10 arcsec): small against the scale's change
# across the field, large against the star centroid's round-off.
_JACOBIAN_STEP_RAD = 10.0 / ARCSEC_PER_RAD
_JACOBIAN_GRID = 128
_PUPIL_SEED = 20240522


def _batoid():
    import batoid

    return batoid


def _model_config(name):
    import yaml

    path = os.path.join(_batoid().datadir, "LSST", name)
    with open(path) as f:
        return yaml.safe_load(f)["opticalSystem"]


@functools.lru_cache(maxsize=6)
def telescope(band):
    """batoid's baffled LSST model with the camera of ``band``.

    Parameters
    ----------
    band : str
        LSST band, ``u g r i z y``.

    Returns
    -------
    batoid.CompoundOptic
    """
    check_band(band)
    config = _model_config("LSST_r_baffles.yaml")
    plain = _model_config(f"LSST_{band}.yaml")
    camera = [item for item in plain["items"] if item["name"] == "LSSTCamera"]
    config["items"] = [item for item in config["items"] if item["name"] != "LSSTCamera"]
    config["items"] += copy.deepcopy(camera)
    # The band's own model is in vacuum; the baffled one in air. Keep the band's, so that the
    # camera's glass constants and the focus are the ones fitted together.
    config["inMedium"] = plain["inMedium"]
    config["medium"] = plain["medium"]
    return _batoid().parse.parse_optic(config)


@dataclass(frozen=True)
class TracedKernel:
    """The image of a point at finite range, in arcsec on the sky, relative to a star.

    The frame is batoid's field angles (x, y) with the star at the same field position at the
    origin: a field position angle of 0 puts the field radius along +x.

    Attributes
    ----------
    image : ndarray
        Surface density per arcsec^2, indexed ``[iy, ix]``, odd-sized, pixel
        ``[n // 2, n // 2]`` centred on the star's centroid. Its integral
        (``image.sum() * scale**2``) is :attr:`transmitted`.
    scale : float
        Pixel size of ``image``, arcsec.
    centroid : tuple of float
        The kernel's centroid relative to the star's, arcsec (x, y).
    inner_radius, outer_radius : float
        Where the azimuthally averaged surface density around the centroid crosses half of its
        plateau, arcsec: the traced counterparts of the annulus's ``R_i / r`` and ``R_o / r``
        (NaN when the kernel has no hole, at very large range).
    transmitted : float
        Light reaching the detector relative to a star at the same field position (the flat
        field divides the star's vignetting out, so this is what the image keeps).
    star_throughput : float
        The star's rays reaching the detector over those entering M1's clear annulus (what the
        spider vanes, baffles and vignetting take).
    band : str
    range_km : float
    field_angle_deg, field_position_angle_deg : float
    n_traced : int
        Rays traced (those entering M1's clear annulus, widened by a margin).
    """

    image: np.ndarray
    scale: float
    centroid: tuple
    inner_radius: float
    outer_radius: float
    transmitted: float
    star_throughput: float
    band: str
    range_km: float
    field_angle_deg: float
    field_position_angle_deg: float
    n_traced: int

    def profile(self, gsparams=GSPARAMS):
        """The kernel as a GalSim profile (arcsec) with flux :attr:`transmitted`."""
        image = galsim.Image(np.ascontiguousarray(self.image * self.scale ** 2),
                             scale=self.scale)
        return galsim.InterpolatedImage(image, flux=self.transmitted, gsparams=gsparams)

    def cross_section(self, track_angle_deg=0.0, seeing=None, pixel_scale_arcsec=None,
                      gsparams=GSPARAMS):
        """Line-spread function across a track, kernel (x) seeing.

        Parameters
        ----------
        track_angle_deg : float
            Direction of the track in the kernel's frame, deg from +x (0 is along the field
            radius when the field position angle is 0).
        seeing : inject.profile.Seeing, optional
            Atmosphere to convolve with; None for the kernel alone.
        pixel_scale_arcsec : float, optional
            Include the response of square pixels of this size, aligned with the track.

        Returns
        -------
        inject.profile.CrossSection
            Flux ``transmitted`` (not renormalised).
        """
        parts = [self.profile(gsparams).rotate(-float(track_angle_deg) * galsim.degrees)]
        atmosphere = None if seeing is None else seeing.profile(gsparams)
        if atmosphere is not None:
            parts.append(atmosphere)
        profile = parts[0] if len(parts) == 1 else galsim.Convolve(parts, gsparams=gsparams)
        return line_spread(profile, pixel_scale_arcsec=pixel_scale_arcsec)


def _field_direction(theta_x, theta_y):
    """Unit propagation direction of light from field angle (theta_x, theta_y), rad."""
    return np.asarray(_batoid().utils.fieldToDirCos(theta_x, theta_y), dtype=float)


def _pupil_points(optic, n_rays):
    """Stratified points over M1's clear annulus (widened by a margin) on the stop plane, m.

    One point drawn uniformly in each cell of a square grid of ``sqrt(n_rays)`` cells across
    the pupil (a fixed seed: the same points every time). A plain grid aliases with the 5 cm
    spider vanes at 45 deg: it saw them block 1.81% of the annulus instead of 1.91%.
    """
    nx = max(int(np.sqrt(n_rays)), 8)
    size = optic.pupilSize
    cell = size / nx
    centres = (np.arange(nx) + 0.5) * cell - size / 2
    x, y = np.meshgrid(centres, centres)
    rng = np.random.default_rng(_PUPIL_SEED)
    x = x.ravel() + rng.uniform(-0.5, 0.5, x.size) * cell
    y = y.ravel() + rng.uniform(-0.5, 0.5, y.size) * cell
    m1 = optic["M1"].obscuration.original  # the clear annulus is the negation of an annulus
    r = np.hypot(x, y)
    keep = (r > m1.inner - _PUPIL_MARGIN_M) & (r < m1.outer + _PUPIL_MARGIN_M)
    return x[keep], y[keep], int(np.count_nonzero((r >= m1.inner) & (r <= m1.outer)))


def _pupil_rays(optic, wavelength_m, points, theta, source_km=None):
    """Rays through the stop-plane ``points`` from a star (``source_km`` None) or a point.

    From a star the rays are parallel along the field direction; from a point ``source_km``
    away in that direction they diverge from it. Each starts ``optic.backDist`` before the
    stop plane, ahead of every baffle.
    """
    batoid = _batoid()
    x, y = points
    stop = optic.stopSurface.coordSys.origin
    z = np.full_like(x, stop[2])
    dircos = _field_direction(*theta)
    if source_km is None:
        u = np.broadcast_to(dircos[:, None], (3, x.size))
    else:
        source = stop - float(source_km) * 1e3 * dircos
        u = np.vstack([x - source[0], y - source[1], z - source[2]])
        u = u / np.sqrt(np.sum(u * u, axis=0))
    n = optic.inMedium.getN(wavelength_m)
    back = optic.backDist
    return batoid.RayVector(x - back * u[0], y - back * u[1], z - back * u[2],
                            u[0] / n, u[1] / n, u[2] / n, wavelength=wavelength_m)


def _landed(optic, rays):
    """Trace; focal-plane x, y (m) of the rays that reach the detector."""
    out = optic.trace(rays)
    ok = ~(out.vignetted | out.failed)
    return out.x[ok], out.y[ok]


def _jacobian(optic, wavelength_m, theta):
    """d(focal-plane centroid)/d(field angle), m/rad, from stars a few arcsec apart."""
    points = _pupil_points(optic, _JACOBIAN_GRID ** 2)[:2]
    columns = []
    for axis in (0, 1):
        ends = []
        for sign in (-1, 1):
            t = np.array(theta, dtype=float)
            t[axis] += sign * _JACOBIAN_STEP_RAD
            x, y = _landed(optic, _pupil_rays(optic, wavelength_m, points, t))
            ends.append(np.array([x.mean(), y.mean()]))
        columns.append((ends[1] - ends[0]) / (2 * _JACOBIAN_STEP_RAD))
    return np.column_stack(columns)


def _edges(dx, dy, centre, scale):
    """Inner and outer half-plateau radii of the rays' azimuthally averaged surface density."""
    r = np.hypot(dx - centre[0], dy - centre[1])
    step = scale
    edges = np.arange(0.0, r.max() + 2 * step, step)
    counts, _ = np.histogram(r, edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    density = counts / (2 * np.pi * mid * step)
    # The plateau: the median over the radii holding the middle half of the light.
    lo, hi = np.quantile(r, [0.25, 0.75])
    plateau = np.median(density[(mid >= lo) & (mid <= hi)])
    above = np.flatnonzero(density >= 0.5 * plateau)
    if len(above) == 0:
        return np.nan, np.nan
    half = 0.5 * plateau

    def crossing(i, j):
        return mid[i] + (half - density[i]) * (mid[j] - mid[i]) / (density[j] - density[i])

    first, last = above[0], above[-1]
    outer = crossing(last, last + 1) if last + 1 < len(mid) else mid[last]
    inner = crossing(first - 1, first) if first > 0 else np.nan
    # A hole narrower than two bins is not resolved: call it no hole.
    if not inner > 2 * step:
        inner = np.nan
    return inner, outer


def traced_kernel(band, range_km, field_angle_deg=0.0, field_position_angle_deg=0.0,
                  n_rays=N_RAYS, pixel_scale=KERNEL_SCALE_ARCSEC):
    """Trace a point at ``range_km`` through Rubin's telescope: the real defocus kernel.

    Parameters
    ----------
    band : str
        LSST band (``u g r i z y``): its camera (filter) model and effective wavelength.
    range_km : float
        Distance from the telescope's entrance pupil to the point, km.
    field_angle_deg : float
        Angle of the point from the optical axis, deg (LSSTCam's field reaches ~1.75).
    field_position_angle_deg : float
        Direction of the field position in the focal plane, deg from batoid's +x.
    n_rays : int
        Rays over the pupil's square, one in each cell of a ``sqrt(n_rays)`` grid (those
        outside M1's clear annulus are not traced); the star used for the normalisation goes
        through the same pupil points.
    pixel_scale : float
        Sampling of the returned image, arcsec.

    Returns
    -------
    TracedKernel

    Notes
    -----
    The rays fill the entrance pupil uniformly (stratified), so each carries the same flux
    (the 8.4 m pupil seen from hundreds of km is a uniform beam to 1e-10). Their landing points
    are mapped back to the sky through the local Jacobian of the star's centroid with field
    angle (plate scale and distortion at that field position) and measured from the star's
    centroid, so the kernel says how the point's image differs from a star's, not where the
    star is.
    """
    check_band(band)
    range_km = positive("range_km", range_km, scalar=True)
    field = finite("field_angle_deg", field_angle_deg, scalar=True)
    if not 0 <= field <= 2.0:
        raise InputError("field_angle_deg", field_angle_deg, "must be within [0, 2] deg")
    pa = finite("field_position_angle_deg", field_position_angle_deg, scalar=True)
    n_rays = int(positive("n_rays", n_rays, scalar=True))
    scale = positive("pixel_scale", pixel_scale, scalar=True)

    optic = telescope(band)
    wavelength_m = BAND_WAVELENGTH_NM[band] * 1e-9
    theta = np.radians(field) * np.array([np.cos(np.radians(pa)), np.sin(np.radians(pa))])

    *points, n_clear = _pupil_points(optic, n_rays)
    sx, sy = _landed(optic, _pupil_rays(optic, wavelength_m, points, theta))
    px, py = _landed(optic, _pupil_rays(optic, wavelength_m, points, theta, source_km=range_km))
    if len(sx) == 0 or len(px) == 0:
        raise InputError("field_angle_deg", field_angle_deg, "no light reaches the detector")

    # Focal plane -> field angle (arcsec) about the star's centroid.
    inverse = np.linalg.inv(_jacobian(optic, wavelength_m, theta)) * ARCSEC_PER_RAD
    dx, dy = inverse @ np.vstack([px - sx.mean(), py - sy.mean()])

    transmitted = len(px) / len(sx)
    centroid = (float(dx.mean()), float(dy.mean()))
    half = int(np.ceil((np.abs(np.concatenate([dx, dy])).max() + 4 * scale) / scale))
    n = 2 * half + 1
    bins = (np.arange(n + 1) - n / 2) * scale
    counts, _, _ = np.histogram2d(dy, dx, bins=(bins, bins))
    image = counts * (transmitted / len(px)) / scale ** 2
    inner, outer = _edges(dx, dy, centroid, scale)
    return TracedKernel(image=image, scale=scale, centroid=centroid,
                        inner_radius=float(inner), outer_radius=float(outer),
                        transmitted=float(transmitted), star_throughput=len(sx) / n_clear,
                        band=band, range_km=range_km, field_angle_deg=field,
                        field_position_angle_deg=pa, n_traced=len(points[0]))
