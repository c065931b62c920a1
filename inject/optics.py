"""The defocus kernel traced through Rubin's telescope (batoid), for a point at finite range.

:func:`inject.profile.defocus_kernel` takes the near-field pupil as an ideal annulus (radii
4.18 m and 2.558 m over the range). What the detector really receives from a point a few
hundred kilometres away is what the three mirrors, the camera's lenses and filter, the spider
vanes and the baffles make of it. :func:`traced_kernel` traces a point source at the range and
field position through batoid's LSST model of the band and returns the image it makes, in
arcsec on the sky, relative to a star at the same field position. Scenes (``pupil: rubin``)
take it from :func:`kernel`: a grid of traced kernels over range and field angle, kept in
memory and in a cache folder between runs.

The model is batoid's baffled telescope (``LSST_r_baffles.yaml``: the centre cap, the spider
vanes, the top-end-assembly, M1, M2 and M1/M3 baffles) with the camera (L1, L2, filter, L3,
detector) of the band's own model (``LSST_{band}.yaml``), in vacuum as the band's model is;
both files ship with batoid, nothing is downloaded. The telescope is focused at infinity (the
design's detector position) unless a focus offset moves the detector. The spider vanes'
orientation is that of the model's frame, fixed to the telescope; the camera rotator turns the
focal plane against them (:func:`telescope_position_angle`; without a rotator the field radius
is taken 22.5 deg from a vane).

Geometric optics only: each ray lands where the optics send it (no diffraction; at 0.2" pixels
and seeing of 0.5" and more, diffraction's ~0.01" is far below the scales here). The kernel is
integrated over the band: the camera's focus moves with wavelength, and a defocused ring
magnifies it (in g at 1294 km the streak's FWHM with seeing goes from 1.70" at 420 nm to 1.32"
at 540 nm). The rays are split among :data:`N_WAVELENGTHS` wavelengths, slices of equal
photons of what the detector counts from the satellite (:func:`band_wavelengths`: the band's
throughput times the Sun's spectrum).
"""
import copy
import functools
import hashlib
import json
import os
import warnings
import zipfile
from dataclasses import dataclass

import galsim
import numpy as np

from inject.errors import InputError, InputWarning
from inject.instrument import ARCSEC_PER_RAD
from inject.photometry import band as check_band
from inject.profile import GSPARAMS, line_spread
from inject.validate import finite, positive

#: Effective wavelength of each band, nm: the throughput-weighted values of LSST throughputs
#: v1.9 with the fiducial atmosphere at airmass 1.2, as Rubin's wavefront code (ts_wep) uses.
#: A monochromatic trace (``traced_kernel(..., wavelength_nm=...)``) for comparisons; scenes
#: trace over the band.
BAND_WAVELENGTH_NM = {"u": 370.9, "g": 476.7, "r": 619.4, "i": 753.9, "z": 866.8, "y": 973.9}

#: The satellite's default spectrum: sunlight reflected without colour, the Sun as a blackbody
#: of its effective temperature, K (IAU 2015 nominal value).
SUN_TEMPERATURE_K = 5772.0

#: Wavelengths a kernel is traced at, the rays divided equally among them. The streak's FWHM and
#: peak with seeing are within 0.3% of a fine integration over the band from here
#: (docs/explanation/physics.md).
N_WAVELENGTHS = 8

# h c / k, nm K: Planck's law in nm.
_HC_OVER_K_NM_K = 1.438776877e7

# Sampling of the band's photon spectrum for its quantiles, nm.
_SPECTRUM_STEP_NM = 0.1

#: Largest field angle traced, deg: the science CCDs' outer corners are at 2.048 deg, where the
#: baffles leave a star 1% of its light (none reaches the detector from 2.06 deg).
FIELD_MAX_DEG = 2.05

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
_DETECTOR = "LSST.LSSTCamera.Detector"


def check_field_angle(value):
    """``value`` checked as a field angle, deg: a finite number within [0,
    :data:`FIELD_MAX_DEG`] (InputError otherwise)."""
    field = finite("field_angle_deg", value, scalar=True)
    if not 0 <= field <= FIELD_MAX_DEG:
        raise InputError("field_angle_deg", value, f"must be within [0, {FIELD_MAX_DEG}] deg")
    return field


#: Largest detector shift from the design's focus accepted, micron (a star's image is then a
#: donut 17" across, that of a point 100 km away).
FOCUS_MAX_UM = 1000.0


def check_focus_offset(value):
    """``value`` checked as a detector shift from the design's focus, micron: a finite number
    within [-:data:`FOCUS_MAX_UM`, :data:`FOCUS_MAX_UM`] (InputError otherwise)."""
    focus = finite("focus_offset_um", value, scalar=True)
    if not abs(focus) <= FOCUS_MAX_UM:
        raise InputError("focus_offset_um", value,
                         f"must be within [-{FOCUS_MAX_UM:g}, {FOCUS_MAX_UM:g}] micron")
    return focus


def _batoid():
    import batoid

    return batoid


def _model_path(name):
    return os.path.join(_batoid().datadir, "LSST", name)


def _model_files(band):
    """The batoid model files :func:`telescope` builds ``band``'s optics from."""
    return ("LSST_r_baffles.yaml", f"LSST_{band}.yaml")


def _model_config(name):
    import yaml

    with open(_model_path(name)) as f:
        return yaml.safe_load(f)["opticalSystem"]


@functools.lru_cache(maxsize=6)
def _model_identity(band):
    """The identity of ``band``'s optics model: batoid's version and a digest of its files.

    A kernel traced with other model files or another batoid is another kernel (the disk
    cache's key holds this).
    """
    digest = hashlib.sha256()
    for name in _model_files(band):
        with open(_model_path(name), "rb") as f:
            digest.update(f.read())
    return f"batoid {_batoid().__version__} {digest.hexdigest()[:16]}"


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
    baffled, own = _model_files(band)
    config = _model_config(baffled)
    plain = _model_config(own)
    camera = [item for item in plain["items"] if item["name"] == "LSSTCamera"]
    config["items"] = [item for item in config["items"] if item["name"] != "LSSTCamera"]
    config["items"] += copy.deepcopy(camera)
    # The band's own model is in vacuum; the baffled one in air. Keep the band's, so that the
    # camera's glass constants and the focus are the ones fitted together.
    config["inMedium"] = plain["inMedium"]
    config["medium"] = plain["medium"]
    return _batoid().parse.parse_optic(config)


def _throughput_path(band):
    return os.path.join(galsim.meta_data.share_dir, "bandpasses", f"LSST_{band}.dat")


@functools.lru_cache(maxsize=6)
def _throughput_identity(band):
    """GalSim's version and a digest of ``band``'s throughput file (the cache key holds it)."""
    with open(_throughput_path(band), "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()[:16]
    return f"galsim {galsim.__version__} LSST_{band}.dat {digest}"


def photon_spectrum(band, temperature_k=SUN_TEMPERATURE_K):
    """Photons the detector counts per nm from a blackbody seen through ``band``.

    The band's total throughput (GalSim's ``LSST_{band}.dat``: LSST's mirrors, lenses, filter,
    detector and the atmosphere at airmass 1.2) times the blackbody's ``F_lambda`` times
    ``lambda`` (energy to photons), normalised to a unit integral.

    Parameters
    ----------
    band : str
        LSST band, ``u g r i z y``.
    temperature_k : float
        The source's blackbody temperature, K (default: the Sun's).

    Returns
    -------
    wavelength_nm, density : ndarray
        Wavelengths every :data:`_SPECTRUM_STEP_NM` nm over the band's extent, and the
        normalised photon density there, per nm.
    """
    check_band(band)
    temperature_k = positive("temperature_k", temperature_k, scalar=True)
    throughput = galsim.Bandpass(_throughput_path(band), "nm")
    wave = np.arange(throughput.blue_limit, throughput.red_limit + _SPECTRUM_STEP_NM / 2,
                     _SPECTRUM_STEP_NM)
    # Planck's F_lambda times lambda, up to a constant: lambda^-4 / (exp(hc / lambda k T) - 1).
    photons = throughput(wave) * wave ** -4.0 / np.expm1(_HC_OVER_K_NM_K / (wave * temperature_k))
    return wave, photons / np.trapezoid(photons, wave)


#: Blackbody temperatures a satellite's spectrum may take, K: from a red M star's to a hot B
#: star's (g - r from 1.53 to -0.42 through LSST's bands).
SED_TEMPERATURE_RANGE_K = (3000.0, 30000.0)


def check_sed_temperature(value):
    """``value`` checked as a satellite's blackbody temperature, K: a finite number within
    :data:`SED_TEMPERATURE_RANGE_K` (InputError otherwise)."""
    temperature = finite("sed_temperature_k", value, scalar=True)
    low, high = SED_TEMPERATURE_RANGE_K
    if not low <= temperature <= high:
        raise InputError("sed_temperature_k", value, f"must be within [{low:g}, {high:g}] K")
    return temperature


@functools.lru_cache(maxsize=256)
def blackbody_colour(blue, red, temperature_k):
    """The AB colour ``blue - red`` of a blackbody through LSST's bands, mag.

    GalSim computes each magnitude: the blackbody's ``F_lambda`` as a GalSim SED (250 to 1200
    nm every nm) through the band's total throughput (``LSST_{band}.dat``) with the AB
    zeropoint.
    """
    wave = np.arange(250.0, 1200.5, 1.0)
    flux = wave ** -5.0 / np.expm1(_HC_OVER_K_NM_K / (wave * float(temperature_k)))
    sed = galsim.SED(galsim.LookupTable(wave, flux, interpolant="linear"), "nm", "flambda")

    def magnitude(band):
        return sed.calculateMagnitude(
            galsim.Bandpass(_throughput_path(band), "nm").withZeropoint("AB"))

    return float(magnitude(blue) - magnitude(red))


def colour_temperature(blue, red, colour):
    """The blackbody temperature (K) whose AB colour ``blue - red`` through LSST's bands is
    ``colour`` (:func:`blackbody_colour`), to 0.1 K.

    Raises
    ------
    InputError
        If the bands are not two different LSST bands, blue first, or no temperature within
        :data:`SED_TEMPERATURE_RANGE_K` has that colour.
    """
    from scipy.optimize import brentq

    check_band(blue)
    check_band(red)
    order = "ugrizy"
    if not order.index(blue) < order.index(red):
        raise InputError("colour", f"{blue}-{red}", "give the bluer band first, e.g. g-r")
    colour = finite(f"{blue}-{red}", colour, scalar=True)
    low, high = SED_TEMPERATURE_RANGE_K
    reddest, bluest = blackbody_colour(blue, red, low), blackbody_colour(blue, red, high)
    if not bluest <= colour <= reddest:
        raise InputError(f"{blue}-{red}", colour,
                         f"a blackbody of {low:g} to {high:g} K has {bluest:.3f} to "
                         f"{reddest:.3f}")
    # The colour falls as the temperature rises; brentq in log T is well conditioned.
    log_t = brentq(lambda t: blackbody_colour(blue, red, float(np.exp(t))) - colour,
                   np.log(low), np.log(high), xtol=1e-6)
    return float(round(np.exp(log_t), 1))


@functools.lru_cache(maxsize=64)
def band_wavelengths(band, n, temperature_k=SUN_TEMPERATURE_K):
    """The wavelengths a kernel is traced at over ``band``, and their weights.

    The band's photon spectrum (:func:`photon_spectrum`) cut into ``n`` slices of equal photon
    counts; each slice is traced at its mean wavelength and carries 1/n of the light. With
    ``n`` = 1 this is the band's photon-weighted mean wavelength for that spectrum.

    Parameters
    ----------
    band : str
    n : int
        Number of wavelengths.
    temperature_k : float
        The satellite's blackbody temperature, K.

    Returns
    -------
    wavelength_nm, weight : tuple of float
    """
    n = int(positive("n_wavelengths", n, scalar=True))
    wave, density = photon_spectrum(band, temperature_k)

    def cumulative(f):
        return np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(wave))])

    total = np.trapezoid(density, wave)
    cdf, moment = cumulative(density) / total, cumulative(density * wave) / total
    # Slice edges at equal steps of the cumulative photons (both linear between fine samples).
    edges = np.interp(np.linspace(0.0, 1.0, n + 1), cdf, wave)
    means = np.diff(np.interp(edges, wave, moment)) / np.diff(np.interp(edges, wave, cdf))
    return tuple(float(w) for w in means), (1.0 / n,) * n


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
        Light reaching the detector relative to a star of the same spectrum at the same field
        position (the flat field divides the star's vignetting out, so this is what the image
        keeps); each wavelength's own, weighted by its photons.
    star_throughput : float
        The star's light reaching the detector over that entering M1's clear annulus (what the
        spider vanes, baffles and vignetting take), over the wavelengths traced.
    band : str
    range_km : float
    field_angle_deg, field_position_angle_deg : float
    n_traced : int
        Rays traced (those entering M1's clear annulus, widened by a margin).
    focus_offset_um : float
        The detector's shift from the design's focus (:func:`traced_kernel`), micron.
    wavelengths_nm, wavelength_weights : tuple of float
        The wavelengths traced and the share of the light each carries.
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
    focus_offset_um: float = 0.0
    wavelengths_nm: tuple = ()
    wavelength_weights: tuple = ()

    def profile(self, gsparams=GSPARAMS):
        """The kernel as a GalSim profile (arcsec) with flux :attr:`transmitted`."""
        image = galsim.Image(np.ascontiguousarray(self.image * self.scale ** 2),
                             scale=self.scale)
        # A cubic k-interpolant: the streak's FWHM and peak with seeing within 1e-4 of the
        # default quintic's (1300 km, 1.5 deg), at about half the cost of a swept profile.
        return galsim.InterpolatedImage(image, flux=self.transmitted, gsparams=gsparams,
                                        k_interpolant=galsim.Cubic())

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


def _pupil_points(optic, n_rays, seed=_PUPIL_SEED):
    """Stratified points over M1's clear annulus (widened by a margin) on the stop plane, m.

    One point drawn uniformly in each cell of a square grid of ``sqrt(n_rays)`` cells across
    the pupil (a fixed ``seed``: the same points every time). A plain grid aliases with the
    5 cm spider vanes at 45 deg: it saw them block 1.81% of the annulus instead of 1.91%.
    """
    nx = max(int(np.sqrt(n_rays)), 8)
    size = optic.pupilSize
    cell = size / nx
    centres = (np.arange(nx) + 0.5) * cell - size / 2
    x, y = np.meshgrid(centres, centres)
    rng = np.random.default_rng(seed)
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


def _edges(dx, dy, weights, centre, scale):
    """Inner and outer half-plateau radii of the rays' azimuthally averaged surface density."""
    r = np.hypot(dx - centre[0], dy - centre[1])
    step = scale
    edges = np.arange(0.0, r.max() + 2 * step, step)
    counts, _ = np.histogram(r, edges, weights=weights)
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
                  n_rays=N_RAYS, pixel_scale=KERNEL_SCALE_ARCSEC, focus_offset_um=0.0,
                  n_wavelengths=N_WAVELENGTHS, temperature_k=SUN_TEMPERATURE_K,
                  wavelength_nm=None):
    """Trace a point at ``range_km`` through Rubin's telescope: the real defocus kernel.

    Parameters
    ----------
    band : str
        LSST band (``u g r i z y``): its camera (filter) model and throughput.
    range_km : float
        Distance from the telescope's entrance pupil to the point, km.
    field_angle_deg : float
        Angle of the point from the optical axis, deg (LSSTCam's science CCDs reach 2.05).
    field_position_angle_deg : float
        Direction of the field position in the focal plane, deg from batoid's +x.
    n_rays : int
        Rays over the pupil's square, divided equally among the wavelengths; at each, one in
        each cell of a square grid (those outside M1's clear annulus are not traced). The
        star used for the normalisation goes through the same pupil points.
    pixel_scale : float
        Sampling of the returned image, arcsec.
    focus_offset_um : float
        Shift of the detector from the design's position along batoid's z axis, micron (0:
        focused at infinity). A negative shift moves it towards the light arriving from L3,
        where a star is out of focus the way a point at finite range is (-50 um looks like a
        point about 2000 km away).
    n_wavelengths : int
        Wavelengths over the band (:func:`band_wavelengths`).
    temperature_k : float
        The satellite's spectrum: a blackbody of this temperature, K (default: the Sun's).
    wavelength_nm : float, optional
        Trace at this one wavelength instead of over the band, nm.

    Returns
    -------
    TracedKernel

    Notes
    -----
    The rays fill the entrance pupil uniformly (stratified), so at one wavelength each carries
    the same flux (the 8.4 m pupil seen from hundreds of km is a uniform beam to 1e-10); each
    wavelength's rays carry its share of the photons. Their landing points are mapped back to
    the sky through the local Jacobian of the star's centroid with field angle (plate scale and
    distortion at that field position) and measured from the centroid of a star of the same
    spectrum, so the kernel says how the point's image differs from a star's, not where the
    star is. The Jacobian is taken at the photon-weighted mean wavelength: across a band it
    changes by less than 1e-5 to 1.5 deg (3e-4 at 2 deg, where the baffles clip the star),
    against the kernel's percent.
    """
    check_band(band)
    range_km = positive("range_km", range_km, scalar=True)
    field = check_field_angle(field_angle_deg)
    pa = finite("field_position_angle_deg", field_position_angle_deg, scalar=True)
    n_rays = int(positive("n_rays", n_rays, scalar=True))
    scale = positive("pixel_scale", pixel_scale, scalar=True)
    focus = check_focus_offset(focus_offset_um)
    if wavelength_nm is None:
        waves, weights = band_wavelengths(band, n_wavelengths, temperature_k)
    else:
        waves, weights = (positive("wavelength_nm", wavelength_nm, scalar=True),), (1.0,)

    optic = telescope(band)
    if focus:
        optic = optic.withGloballyShiftedOptic(_DETECTOR, [0.0, 0.0, focus * 1e-6])
    theta = np.radians(field) * np.array([np.cos(np.radians(pa)), np.sin(np.radians(pa))])

    # Per wavelength: its own stratified pupil points, a star and the point through them. Each
    # ray entering M1's clear annulus carries weight / n_clear of the light M1 receives.
    star, point, n_traced = [], [], 0
    for k, (wave, weight) in enumerate(zip(waves, weights)):
        *points, n_clear = _pupil_points(optic, max(n_rays // len(waves), 64), _PUPIL_SEED + k)
        n_traced += len(points[0])
        ray_weight = weight / n_clear
        sx, sy = _landed(optic, _pupil_rays(optic, wave * 1e-9, points, theta))
        px, py = _landed(optic, _pupil_rays(optic, wave * 1e-9, points, theta,
                                            source_km=range_km))
        star.append((sx, sy, np.full(len(sx), ray_weight)))
        point.append((px, py, np.full(len(px), ray_weight)))
    sx, sy, sw = (np.concatenate(a) for a in zip(*star))
    px, py, pw = (np.concatenate(a) for a in zip(*point))
    if sw.sum() == 0 or pw.sum() == 0:
        raise InputError("field_angle_deg", field_angle_deg, "no light reaches the detector")

    # Focal plane -> field angle (arcsec) about the star's centroid.
    mean_wave = float(np.dot(waves, weights) / np.sum(weights))
    inverse = np.linalg.inv(_jacobian(optic, mean_wave * 1e-9, theta)) * ARCSEC_PER_RAD
    star_centre = np.array([np.average(sx, weights=sw), np.average(sy, weights=sw)])
    dx, dy = inverse @ (np.vstack([px, py]) - star_centre[:, None])

    transmitted = pw.sum() / sw.sum()
    centroid = (float(np.average(dx, weights=pw)), float(np.average(dy, weights=pw)))
    half = int(np.ceil((np.abs(np.concatenate([dx, dy])).max() + 4 * scale) / scale))
    n = 2 * half + 1
    bins = (np.arange(n + 1) - n / 2) * scale
    light, _, _ = np.histogram2d(dy, dx, bins=(bins, bins), weights=pw)
    image = light / sw.sum() / scale ** 2
    inner, outer = _edges(dx, dy, pw, centroid, scale)
    return TracedKernel(image=image, scale=scale, centroid=centroid,
                        inner_radius=float(inner), outer_radius=float(outer),
                        transmitted=float(transmitted), star_throughput=float(sw.sum()),
                        band=band, range_km=range_km, field_angle_deg=field,
                        field_position_angle_deg=pa, n_traced=n_traced,
                        focus_offset_um=focus, wavelengths_nm=tuple(waves),
                        wavelength_weights=tuple(weights))


# -------------------------------------------------------------------------------------------
# The kernel grid: what scenes use

#: Rays per traced kernel on the grid: the FWHM and peak of the streak's cross-section with
#: 0.67" seeing agree with 16 times as many to 0.011% (1000 km, 1.5 deg).
GRID_RAYS = 250_000

#: Ranges are traced at the centres of bins a factor 1.02 wide (log-spaced) and the kernel
#: scaled as 1/range to the range asked for (off by at most 1%): the cross-section's FWHM and
#: peak move by 0.03% per 1% of range scaled this way (measured at 400 and 1000 km).
RANGE_BIN_FACTOR = 1.02

#: Field angles at which kernels are traced, deg; between two, their kernels are mixed
#: linearly. Every 0.05 deg to 1.6 deg, 0.01 deg to 1.9, 0.002 deg to 2.05, where the baffles
#: cut the beam more and more (at 2.005 deg nodes 0.01 deg apart were 2.4% off in FWHM, 0.004
#: deg apart 0.27%). The error budget is measured in docs/explanation/physics.md.
FIELD_NODES_DEG = np.round(np.concatenate([np.arange(0.0, 1.6, 0.05),
                                           np.arange(1.6, 1.9, 0.01),
                                           np.arange(1.9, FIELD_MAX_DEG + 1e-9, 0.002)]), 6)

#: Field position angle in batoid's frame at which kernels are traced when a scene gives no
#: camera rotator, deg: the radius 22.5 deg from a vane (batoid's vanes lie at 45 and 135
#: deg), halfway between along a vane and between two, so off by at most half of what the
#: FWHM moves over that range (docs/explanation/physics.md). With a rotator the angle is
#: :func:`telescope_position_angle`'s, on :data:`VANE_STEP_DEG` nodes.
VANE_OFFSET_DEG = 22.5

#: Spacing of the field position angles in batoid's (the telescope's) frame at which kernels
#: are traced when the camera rotator is given, deg: the angle is taken to the nearest node. The
#: spider vanes repeat every 90 deg, so there are at most 18 nodes per range and field node.
VANE_STEP_DEG = 5.0


def telescope_position_angle(rotator_deg, radius_deg):
    """The field radius's direction in the telescope's frame, where the spider vanes are fixed.

    LSST's camera coordinate system (CCS) turns with the rotator: seen from the sky, it is
    turned counter-clockwise by rotTelPos from the telescope's optical coordinate system
    (OCS), which is batoid's frame (its field angles and focal plane share its axes; the
    vanes lie at 45 and 135 deg). inject's focal plane is obs_lsst's, the data-visualisation
    frame (DVCS), the transpose of CCS: a radius at ``radius_deg`` there is at 90 -
    ``radius_deg`` in CCS and 90 - ``radius_deg`` + rotTelPos in OCS. The transpose is a
    mirror, and the optics are symmetric about the vanes' bisectors, so the kernel seen on
    the focal plane is the one traced with the radius at ``radius_deg`` - rotTelPos, turned
    by rotTelPos: the angle returned, which the renderer turns from (the kernel's frame has
    the radius there; :meth:`inject.streak.StreakModel.defocus_profile`). The vanes' 4-fold
    symmetry reduces it modulo 90.

    Parameters
    ----------
    rotator_deg : float
        The camera rotator's angle, rotTelPos, deg.
    radius_deg : float
        Direction of the outward field radius on the focal plane (a CCD's pixel rows turn by
        multiples of 90 deg from it, which the vanes do not see), deg from +x.

    Returns
    -------
    float
        The field position angle in [0, 90) deg for :func:`traced_kernel`.
    """
    rotator = finite("rotator_deg", rotator_deg, scalar=True)
    radius = finite("field_position_angle_deg", radius_deg, scalar=True)
    return float((radius - rotator) % 90.0)


def vane_node(angle_deg):
    """``angle_deg`` (telescope frame, deg) at the nearest :data:`VANE_STEP_DEG` node in
    [0, 90): the angle :func:`kernel` traces."""
    return float(round(float(angle_deg) / VANE_STEP_DEG) * VANE_STEP_DEG % 90.0)


#: Version of the kernel files and of the code that traces them: files of another version are
#: not read (they stay in their own folder). Bump it when a change to this module changes the
#: kernels traced from the same inputs; the inputs themselves (band, wavelengths and their
#: weights, the throughput and spectrum they come from, range, field, vanes, rays, sampling,
#: focus, pupil points, optics model) are in each file's key.
CACHE_VERSION = 3

#: Errors that say a cache file is damaged (truncated, a bad CRC, not an npz, arrays missing):
#: the kernel is traced again and the file rewritten.
_DAMAGED = (OSError, EOFError, ValueError, KeyError, IndexError, TypeError, zipfile.BadZipFile)


def cache_dir():
    """Folder of the traced kernels kept between runs.

    ``$INJECT_CACHE_DIR`` if set, else the user's cache folder (``~/.cache/inject`` on Linux),
    in a sub-folder per :data:`CACHE_VERSION`. An empty ``INJECT_CACHE_DIR`` keeps kernels in
    memory only.
    """
    root = os.environ.get("INJECT_CACHE_DIR")
    if root is None:
        import platformdirs

        root = platformdirs.user_cache_dir("inject", appauthor=False)
    if not root:
        return None
    return os.path.join(root, "kernels", f"v{CACHE_VERSION}")


def _grid_trace(band, range_index, field_index, focus_offset_um=0.0, position_angle=None,
                temperature_k=SUN_TEMPERATURE_K):
    """The arguments of :func:`traced_kernel` for the grid node ``(range_index, field_index)``:
    range :data:`RANGE_BIN_FACTOR` ** ``range_index`` km, field angle
    ``FIELD_NODES_DEG[field_index]``, the field position angle ``position_angle`` in batoid's
    frame (None: :data:`VANE_OFFSET_DEG`),
    :data:`GRID_RAYS` rays over :data:`N_WAVELENGTHS` wavelengths of a blackbody of
    ``temperature_k`` (default: the Sun's), :data:`KERNEL_SCALE_ARCSEC` sampling, the detector
    ``focus_offset_um`` from the design's position."""
    return dict(band=band, range_km=RANGE_BIN_FACTOR ** range_index,
                field_angle_deg=float(FIELD_NODES_DEG[field_index]),
                field_position_angle_deg=(VANE_OFFSET_DEG if position_angle is None
                                          else float(position_angle)), n_rays=GRID_RAYS,
                pixel_scale=KERNEL_SCALE_ARCSEC, focus_offset_um=float(focus_offset_um),
                n_wavelengths=N_WAVELENGTHS, temperature_k=float(temperature_k))


def _cache_key(trace):
    """Everything a kernel traced with the arguments ``trace`` depends on.

    The arguments of :func:`traced_kernel` (band, range, field angle, the radius's angle to
    the vanes, rays, sampling, focus, number of wavelengths, the spectrum's temperature), the
    wavelengths and their weights, the band's throughput file (:func:`_throughput_identity`),
    the pupil points' seed and margin, the plate-scale Jacobian's step and grid, and the optics
    model's identity (:func:`_model_identity`). The code that traces is
    :data:`CACHE_VERSION`'s.

    Returns
    -------
    dict
        JSON-ready; its digest names the cache file.
    """
    band = trace["band"]
    waves, weights = band_wavelengths(band, trace["n_wavelengths"], trace["temperature_k"])
    return dict(trace, wavelengths_nm=list(waves), wavelength_weights=list(weights),
                throughput=_throughput_identity(band), pupil_seed=_PUPIL_SEED,
                pupil_margin_m=_PUPIL_MARGIN_M, jacobian_step_rad=_JACOBIAN_STEP_RAD,
                jacobian_grid=_JACOBIAN_GRID, model=_model_identity(band))


def _key_text(key):
    return json.dumps(key, sort_keys=True)


def _cache_path(folder, key):
    """The file in ``folder`` of the kernel of ``key`` (:func:`_cache_key`): its band, range
    and field for the reader, and a digest of the whole key."""
    digest = hashlib.sha256(_key_text(key).encode()).hexdigest()[:20]
    focus = f"_dz{key['focus_offset_um']:+g}um" if key["focus_offset_um"] else ""
    return os.path.join(folder, f"{key['band']}_{key['range_km']:.1f}km_"
                                f"f{key['field_angle_deg']:.3f}{focus}_{digest}.npz")


def _save(path, kernel, key):
    """Write a kernel and its key to ``path`` atomically (a partial file never has the final
    name)."""
    import tempfile

    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as stream:
            np.savez(stream, key=np.array(_key_text(key)),
                     image=kernel.image.astype(np.float32), scale=kernel.scale,
                     centroid=np.asarray(kernel.centroid),
                     radii=np.array([kernel.inner_radius, kernel.outer_radius]),
                     transmitted=kernel.transmitted, star_throughput=kernel.star_throughput,
                     n_traced=kernel.n_traced)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _load(path, key):
    """The kernel stored in ``path`` for ``key``; None if there is none, the file is damaged
    or it holds another key's kernel."""
    try:
        # The file opened here: np.load leaves it open when the zip is unreadable.
        with open(path, "rb") as stream, np.load(stream) as data:
            if str(data["key"][()]) != _key_text(key):
                return None
            image = data["image"].astype(float)
            scale, transmitted = float(data["scale"]), float(data["transmitted"])
            centroid, radii = data["centroid"].astype(float), data["radii"].astype(float)
            star_throughput, n_traced = float(data["star_throughput"]), int(data["n_traced"])
    except _DAMAGED:  # a missing file too (FileNotFoundError)
        return None
    n = image.shape[0] if image.ndim == 2 else 0
    # The light the image holds is stored twice: a file that does not agree is damaged.
    if not (image.shape == (n, n) and n % 2 == 1 and np.isfinite(image).all()
            and scale == key["pixel_scale"] and centroid.shape == radii.shape == (2,)
            and np.isclose(image.sum() * scale ** 2, transmitted, rtol=1e-4)):
        return None
    return TracedKernel(
        image=image, scale=scale, centroid=(float(centroid[0]), float(centroid[1])),
        inner_radius=float(radii[0]), outer_radius=float(radii[1]), transmitted=transmitted,
        star_throughput=star_throughput, band=key["band"], range_km=key["range_km"],
        field_angle_deg=key["field_angle_deg"],
        field_position_angle_deg=key["field_position_angle_deg"], n_traced=n_traced,
        focus_offset_um=key["focus_offset_um"], wavelengths_nm=tuple(key["wavelengths_nm"]),
        wavelength_weights=tuple(key["wavelength_weights"]))


#: Whether this process has said that the cache folder cannot be written.
_unwritable_said = False


def _unwritable(folder, err):
    """Say once per process that kernels cannot be kept in ``folder``."""
    global _unwritable_said
    if _unwritable_said:
        return
    _unwritable_said = True
    warnings.warn(f"kernel cache folder {folder!r} cannot be written ({err.strerror or err}): "
                  "pupil: rubin traces its kernels again on every run; set INJECT_CACHE_DIR "
                  "to a writable folder (or to an empty value to keep kernels in memory only)",
                  InputWarning, stacklevel=2)


@functools.lru_cache(maxsize=64)  # images of ~500 x 500 at 350 km: about 130 MB at most
def _grid_kernel(band, range_index, field_index, focus_offset_um=0.0, position_angle=None,
                 temperature_k=SUN_TEMPERATURE_K):
    """The kernel traced at a grid node, from the disk cache when it holds it.

    A damaged cache file is traced again and rewritten; a folder that cannot be written keeps
    the kernel in memory only (one :class:`~inject.errors.InputWarning` per process).
    """
    trace = _grid_trace(band, range_index, field_index, focus_offset_um, position_angle,
                        temperature_k)
    folder = cache_dir()
    if folder is None:
        return traced_kernel(**trace)
    key = _cache_key(trace)
    path = _cache_path(folder, key)
    kernel = _load(path, key)
    if kernel is None:
        kernel = traced_kernel(**trace)
        try:
            _save(path, kernel, key)
        except OSError as err:
            _unwritable(folder, err)
    return kernel


def _padded(image, n):
    pad = (n - image.shape[0]) // 2
    return np.pad(image, pad) if pad else image


def kernel(band, range_km, field_angle_deg=0.0, focus_offset_um=0.0,
           telescope_position_angle_deg=None, temperature_k=SUN_TEMPERATURE_K):
    """The traced kernel of a point at ``range_km`` and ``field_angle_deg``, from the grid.

    The kernel traced at the nearest range node (:data:`RANGE_BIN_FACTOR`) scaled as 1/range,
    mixed linearly between the two field-angle nodes around ``field_angle_deg``
    (:data:`FIELD_NODES_DEG`); nodes are traced once (:data:`GRID_RAYS` rays, the field radius
    at :data:`VANE_OFFSET_DEG` from the vanes) and kept in memory and in :func:`cache_dir`.

    Parameters
    ----------
    band : str
    range_km : float
    field_angle_deg : float
        Within [0, :data:`FIELD_MAX_DEG`].
    focus_offset_um : float
        The detector's shift from the design's position, micron (:func:`traced_kernel`).
    telescope_position_angle_deg : float, optional
        The field radius's direction in batoid's (the telescope's) frame, deg
        (:func:`telescope_position_angle`), traced at the nearest :data:`VANE_STEP_DEG` node;
        None (no rotator given): :data:`VANE_OFFSET_DEG`.
    temperature_k : float
        The satellite's spectrum, a blackbody of this temperature, K
        (:func:`check_sed_temperature`; default: the Sun's).

    Returns
    -------
    TracedKernel
        Its frame has the field radius at ``field_position_angle_deg`` (the node traced)
        from +x.
    """
    check_band(band)
    range_km = positive("range_km", range_km, scalar=True)
    field = check_field_angle(field_angle_deg)
    focus = check_focus_offset(focus_offset_um)
    temperature = check_sed_temperature(temperature_k)
    node = None
    if telescope_position_angle_deg is not None:
        node = vane_node(finite("telescope_position_angle_deg", telescope_position_angle_deg,
                                 scalar=True))
    range_index = int(round(np.log(range_km) / np.log(RANGE_BIN_FACTOR)))
    low = min(int(np.searchsorted(FIELD_NODES_DEG, field, side="right")) - 1,
              len(FIELD_NODES_DEG) - 1)
    weight = 0.0
    if low + 1 < len(FIELD_NODES_DEG):
        weight = (field - FIELD_NODES_DEG[low]) / (FIELD_NODES_DEG[low + 1] - FIELD_NODES_DEG[low])
    weight = 0.0 if weight < 1e-9 else float(weight)
    nodes = [(_grid_kernel(band, range_index, low, focus, node, temperature), 1.0 - weight)]
    if weight > 0:
        nodes.append((_grid_kernel(band, range_index, low + 1, focus, node, temperature), weight))
    n = max(k.image.shape[0] for k, _ in nodes)
    image = sum(w * _padded(k.image, n) for k, w in nodes)
    # 1/range: the node's kernel seen from range_km instead of the node's range.
    zoom = RANGE_BIN_FACTOR ** range_index / range_km
    base = nodes[0][0]
    mixed = {name: sum(w * getattr(k, name) for k, w in nodes)
             for name in ("transmitted", "star_throughput", "inner_radius", "outer_radius")}
    centroid = tuple(zoom * sum(w * k.centroid[a] for k, w in nodes) for a in (0, 1))
    return TracedKernel(image=image / zoom ** 2, scale=base.scale * zoom, centroid=centroid,
                        inner_radius=zoom * mixed["inner_radius"],
                        outer_radius=zoom * mixed["outer_radius"],
                        transmitted=mixed["transmitted"],
                        star_throughput=mixed["star_throughput"], band=band, range_km=range_km,
                        field_angle_deg=field,
                        field_position_angle_deg=base.field_position_angle_deg,
                        n_traced=base.n_traced, focus_offset_um=base.focus_offset_um,
                        wavelengths_nm=base.wavelengths_nm,
                        wavelength_weights=base.wavelength_weights)
