"""Brute-force reference renderer: the streak as a dense row of stationary exposures.

This module is the *reference* the fast renderer (:mod:`inject.render`) and the baselines are
checked against in the tests and benchmarks. It is written to be obviously correct, not fast,
and nothing in ``inject`` uses it by default.

The method is the definition of a streak. A satellite moving at constant speed over the
exposure deposits its charge uniformly along the track, so the image is the stationary profile
integrated along the segment. That integral is done by the midpoint rule: the segment is split
into ``n = max(1, ceil(length / step_px))`` equal sub-steps of length ``delta = length / n``
pixels, and at the midpoint of each sub-step GalSim draws the profile, rotated to the track
angle, with flux ``flux_per_px * delta`` and the pixel response included (``drawImage``
with the default ``method="auto"``), centred at that exact sub-pixel position.

Accuracy
--------
* Along the track: the midpoint rule's error is second order, ``O(step_px**2)``. Far from
  the end points the sum of a smooth profile over many equally spaced points is accurate far
  beyond GalSim's own accuracy (the column sums of a swept Gaussian are exact to 1e-9); at the
  end caps the error is
  about ``step_px**2 / 24`` times the along-track derivative of the pixel-convolved profile.
  At the default ``step_px = 0.05``, halving the step changes no pixel by more than
  ``2e-5`` of the peak pixel for the LSST profiles of :class:`~inject.streak.StreakModel`
  (``5e-5`` for a Gaussian of FWHM 2 px, ~1e-4 for FWHM 1 px); ``tests/test_reference.py``
  checks this.
* Each stationary exposure is as accurate as GalSim's ``GSParams`` of the profile (or
  ``gsparams``) make it; pass :data:`inject.profile.GSPARAMS` for profiles built elsewhere.
* Each exposure is drawn on a square stamp of half-size ``stamp_half_size_px`` (default: the
  radius that holds ``1 - folding_threshold`` of the profile's flux according to GalSim's
  ``stepk``, plus a pixel for the pixel response). Flux beyond the stamp, up to
  ``folding_threshold`` of the total, is not drawn (5.4e-5 of it for the Kolmogorov-seeing
  profiles of :class:`~inject.streak.StreakModel`, whose tails fall as ``r**(-11/3)``): pass a
  larger stamp to check total flux to better than that.

Conventions are those of :mod:`inject.trajectory`: pixel ``(0, 0)`` is the centre of the first
pixel, ``x`` runs along columns and ``y`` along rows (numpy index ``[y, x]``), angles are
counter-clockwise from ``+x``. GalSim's pixel coordinates of an image with ``xmin = ymin = 0``
are the same, so positions are handed to GalSim unchanged.

Cost: one FFT draw per point, 30-45 ms per point for the LSST profiles with
:data:`inject.profile.GSPARAMS` (whose ``folding_threshold = 1e-4`` makes the stamps ~400 px
wide), i.e. ~15 min for a 1000-pixel streak at the default step.
"""
import math

import galsim
import numpy as np

from inject.errors import InputError
from inject.validate import finite, positive

#: Slack in ``ceil(length / step_px)`` so that a length that is an exact multiple of the step
#: (up to rounding) is not split into one extra sub-step.
_CEIL_SLACK = 1e-9


def n_steps(length, step_px):
    """Number of sub-steps the segment is split into: ``max(1, ceil(length / step_px))``.

    Parameters
    ----------
    length : float
        Segment length, pixels (>= 0).
    step_px : float
        Largest sub-step, pixels (> 0).

    Returns
    -------
    int
    """
    return max(1, int(math.ceil(length / step_px - _CEIL_SLACK)))


def sample_points(segment, step_px):
    """Midpoints of the sub-steps of ``segment`` and the length of each sub-step.

    Parameters
    ----------
    segment : Segment
        The track (pixels).
    step_px : float
        Largest sub-step, pixels.

    Returns
    -------
    x, y : ndarray
        Pixel coordinates of the ``n`` midpoints, from ``(x0, y0)`` towards ``(x1, y1)``.
    delta : float
        Length of every sub-step, ``segment.length / n`` pixels.
    """
    n = n_steps(segment.length, step_px)
    delta = segment.length / n
    t = (np.arange(n) + 0.5) * delta
    c, s = segment.direction
    return segment.x0 + t * c, segment.y0 + t * s, delta


def default_stamp_half_size(profile, pixel_scale):
    """Half-size (pixels) of the stamp each point is drawn on, from the profile's ``stepk``.

    GalSim sets ``stepk = pi / R`` with ``R`` the radius (arcsec) enclosing
    ``1 - folding_threshold`` of the flux (half of ``getGoodImageSize``); one pixel is added
    for the pixel response.

    Parameters
    ----------
    profile : galsim.GSObject
        The profile as it will be drawn (its ``GSParams`` set the threshold).
    pixel_scale : float
        Arcsec per pixel.

    Returns
    -------
    int
    """
    return int(math.ceil(math.pi / (profile.stepk * pixel_scale))) + 1


def with_gsparams(profile, gsparams):
    """``profile.withGSParams(gsparams)`` without values cached under the old ``GSParams``.

    GalSim's ``withGSParams`` copies the object, and for compound objects (``Convolution``,
    ``Sum``, ``Transformation``) the copy keeps the lazily cached ``stepk``, ``maxk`` and the
    like computed under the old parameters (GalSim 2.8), so a profile that has been drawn or
    asked for its ``stepk`` would keep its old accuracy. This clears those caches on the new
    objects only; the caller's profile and its components are not touched.

    Parameters
    ----------
    profile : galsim.GSObject
    gsparams : galsim.GSParams

    Returns
    -------
    galsim.GSObject
    """
    old = {id(obj) for obj in _tree(profile)}
    new = profile.withGSParams(gsparams)
    for obj in _tree(new):
        if id(obj) in old:
            continue
        for cls in type(obj).__mro__:
            for name, attr in vars(cls).items():
                if isinstance(attr, galsim.utilities.lazy_property):
                    obj.__dict__.pop(name, None)
    return new


def _tree(obj, seen=None):
    """``obj`` and every GSObject it holds, depth first, each once."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return []
    seen.add(id(obj))
    found = [obj]
    for value in vars(obj).values():
        children = value if isinstance(value, (list, tuple)) else (value,)
        for child in children:
            if isinstance(child, galsim.GSObject):
                found += _tree(child, seen)
    return found


def render_brute_force(shape, profile, pixel_scale, segment, flux_per_px, step_px=0.05,
                       gsparams=None, image=None, stamp_half_size_px=None):
    """Draw a streak as a sum of stationary exposures along the segment (slow reference).

    Parameters
    ----------
    shape : tuple of int
        ``(ny, nx)`` of the image.
    profile : galsim.GSObject
        Unit-flux stationary profile in the track frame (arcsec, motion along +x), e.g.
        :attr:`inject.streak.StreakModel.profile`.
    pixel_scale : float
        Arcsec per pixel.
    segment : Segment
        The track, pixels; ``segment.angle_deg`` is counter-clockwise from +x.
    flux_per_px : float
        Charge (e-) deposited per pixel of track length.
    step_px : float, optional
        Largest distance between consecutive exposures along the track, pixels.
    gsparams : galsim.GSParams, optional
        Replace the profile's ``GSParams`` (accuracy and FFT size); by default keep them.
    image : ndarray, optional
        float64 array of ``shape`` to add the streak to, in place. By default a new zero image.
    stamp_half_size_px : int, optional
        Half-size of the square stamp drawn around each point (the stamp is
        ``2 * stamp_half_size_px + 1`` pixels wide, clipped to the image). By default
        :func:`default_stamp_half_size`.

    Returns
    -------
    ndarray
        float64 image of ``shape`` (``image`` itself when given), indexed ``[y, x]``.

    Notes
    -----
    The segment is split into ``n = max(1, ceil(length / step_px))`` equal sub-steps of
    ``delta = length / n`` pixels. At the midpoint of each, the profile rotated by
    ``segment.angle_deg`` with flux ``flux_per_px * delta`` is drawn by
    ``drawImage(method="auto", add_to_image=True)`` (so including the pixel response) into the
    sub-image of the stamp around the point, centred exactly at the point. A zero-length
    segment is a point source of zero flux and draws nothing; points whose stamp misses the
    image are skipped.
    """
    ny, nx = _shape(shape)
    pixel_scale = float(positive("pixel_scale", pixel_scale))
    flux_per_px = float(finite("flux_per_px", flux_per_px))
    step_px = float(positive("step_px", step_px))
    if not isinstance(profile, galsim.GSObject):
        raise InputError("profile", profile, "must be a galsim.GSObject")

    if image is None:
        image = np.zeros((ny, nx))
    elif not (isinstance(image, np.ndarray) and image.dtype == np.float64
              and image.shape == (ny, nx) and image.flags.writeable):
        raise InputError("image", getattr(image, "shape", image),
                         f"must be a writeable float64 array of shape {(ny, nx)}")
    # GalSim writes through to the array only if it is C-contiguous; otherwise work on a copy.
    work = image if image.flags.c_contiguous else np.ascontiguousarray(image)

    x, y, delta = sample_points(segment, step_px)
    flux = flux_per_px * delta
    if flux != 0.0:
        base = profile if gsparams is None else with_gsparams(profile, gsparams)
        # Built once: every point is the same object, only its centre changes.
        obj = base.rotate(segment.angle_deg * galsim.degrees).withFlux(flux)
        h = (default_stamp_half_size(obj, pixel_scale) if stamp_half_size_px is None
             else math.ceil(positive("stamp_half_size_px", stamp_half_size_px)))
        full = galsim.ImageD(work, xmin=0, ymin=0, scale=pixel_scale)
        for xi, yi in zip(x, y):
            ix, iy = int(round(xi)), int(round(yi))
            bounds = galsim.BoundsI(ix - h, ix + h, iy - h, iy + h) & full.bounds
            if not bounds.isDefined():
                continue
            obj.drawImage(image=full[bounds], center=galsim.PositionD(xi, yi),
                          add_to_image=True, method="auto")
    if work is not image:
        image[...] = work
    return image


def _shape(shape):
    try:
        ny, nx = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise InputError("shape", shape, "must be (ny, nx)") from None
    if ny <= 0 or nx <= 0 or (ny, nx) != tuple(shape):
        raise InputError("shape", shape, "must be two positive integers")
    return ny, nx


def swept_gaussian(shape, sigma_px, segment, flux_per_px):
    """Closed form of a unit-flux circular Gaussian (``sigma_px``) swept along +x from
    ``(segment.x0, segment.y0)`` over ``segment.length`` px, pixel-integrated: the exact
    reference the renderers are checked against (the angle is ignored: along +x only)."""
    from scipy import special

    def cdf(u):
        return 0.5 * (1 + special.erf(u / np.sqrt(2)))

    def icdf(u):  # the integral of the cdf
        return u * cdf(u) + np.exp(-u * u / 2) / np.sqrt(2 * np.pi)

    y, x = np.indices(shape, dtype=float)
    dy, dx = y - segment.y0, x - segment.x0
    s, length = sigma_px, segment.length
    across = cdf((dy + 0.5) / s) - cdf((dy - 0.5) / s)
    along = s * (icdf((dx + 0.5) / s) - icdf((dx - 0.5) / s)
                 - icdf((dx + 0.5 - length) / s) + icdf((dx - 0.5 - length) / s))
    return flux_per_px * across * along
