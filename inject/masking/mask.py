"""Mask widths and the pixels a streak mask costs.

Four width rules, so that results compare with the tools in use:

``sb`` (default)
    The surface-brightness rule: out to where the measured profile drops below ``t`` times the
    sky noise per pixel (default ``t`` = :data:`inject.maskplanes.STREAK_MASK_SIGMA`, the level of
    the simulator's truth STREAK plane, so masks compare pixel for pixel), and never narrower
    than :data:`MIN_FWHM` FWHM (a faint streak below ``t`` sigma still gets its core masked).
``fwhm``
    ``k`` times the measured FWHM (default ``k`` = :data:`FWHM_FACTOR`).
``lsst``
    LSST ``meas_algorithms`` ``maskStreaks``: a Moffat profile ``(1 + d^2 / alpha^2)^-2.5`` is
    fitted and pixels within ``nSigmaMask = 5`` alpha of the line are masked: 10 alpha wide, a
    fixed multiple of the width, whatever the brightness.
``acstools``
    acstools ``findsat_mrt``: a Gaussian is fitted to the median profile and the trail is
    ``2 x 3 sigma`` = 6 sigma wide.

Masks are rasterised over the real chord (the streak's extent inside the image, with its end
caps), not counted as width x length: pixel centres inside the rectangle, clipped to the image.
"""
import numpy as np

from inject.masking.geometry import rectangle_spans, span_indices
from inject.masking.measure import GAUSSIAN_FWHM_PER_SIGMA, MOFFAT_FWHM_PER_ALPHA, wing_reach
from inject.maskplanes import STREAK_MASK_SIGMA

#: Mask-width rules, the default first.
RULES = ("sb", "fwhm", "lsst", "acstools")

#: ``k`` of the ``k x FWHM`` rule.
FWHM_FACTOR = 3.0

#: Narrowest ``sb`` mask, in FWHM.
MIN_FWHM = 1.0

#: LSST ``maskStreaks`` ``nSigmaMask``: the mask reaches this many Moffat alpha each side.
LSST_N_ALPHA = 5.0

#: acstools ``findsat_mrt``: the trail reaches this many Gaussian sigma each side.
ACSTOOLS_N_SIGMA = 3.0

#: Width of the ``sb`` mask, in FWHM (the measured one, else the detection's estimate), when
#: the profile's drop below the level is measured on neither side (both cut by an image edge,
#: a hole or a neighbour) or not inside the widest window: a failed measurement must not set
#: a mask hundreds of pixels wide.
FALLBACK_FWHM = 3.0

#: Widest fallback mask, px (3 x the widest matched filter's FWHM, 26 px).
FALLBACK_MAX_PX = 80.0


def mask_widths(measurement, sky_sigma, sb_sigma=STREAK_MASK_SIGMA, fwhm_factor=FWHM_FACTOR):
    """Full mask widths (px) of a measured streak under every rule of :data:`RULES`.

    Parameters
    ----------
    measurement : measure.Measurement
    sky_sigma : float
        Sky noise per pixel (image units).
    sb_sigma : float
        ``t`` of the surface-brightness rule.
    fwhm_factor : float
        ``k`` of the FWHM rule.

    Returns
    -------
    dict
        ``{rule: width}``; NaN where the measurement does not allow it (a failed fit).
    """
    fwhm = measurement.fwhm_px
    return {
        "sb": sb_width(measurement, sky_sigma, sb_sigma)[0],
        "fwhm": fwhm_factor * fwhm,
        "lsst": 2 * LSST_N_ALPHA * measurement.moffat_alpha_px,
        "acstools": 2 * ACSTOOLS_N_SIGMA * measurement.gaussian_sigma_px,
    }


def sb_width(measurement, sky_sigma, sb_sigma=STREAK_MASK_SIGMA):
    """Full width (px) of the ``sb`` mask and, if it is not the measured one, the rule used.

    The half-width is where the profile drops below ``sb_sigma x sky_sigma`` on the side(s)
    where it is measured, or out to where a side is cut while still above it (an image edge,
    a hole or a neighbour's midline; at most twice the measured side's), never below
    :data:`MIN_FWHM` / 2 FWHM. Where that drop is measured on neither side,
    or not inside the widest window, the mask is :data:`FALLBACK_FWHM` FWHM wide (at most
    :data:`FALLBACK_MAX_PX`), and the rule is said.

    Returns
    -------
    width : float
    fallback : str or None
        The rule applied instead of the measured drop, in words; None if measured.
    """
    width = measurement.width_px
    profile = measurement.profile
    sides = wing_reach(profile, sb_sigma * sky_sigma, near=width)
    measured = [r for r in sides if r is not None and np.isfinite(r)]
    if measured and None not in sides:
        reach = max(measured)
        # A side cut while still above the level is masked out to the cut at least (the
        # image edge, a hole's edge or the midline to a neighbour), within twice the
        # measured reach.
        ends = profile.distance[profile.measured]
        for r, end in zip(sides, (-ends[0], ends[-1])):
            if not np.isfinite(r):
                reach = max(reach, min(end + 0.5 * profile.step, 2 * max(measured)))
        return 2 * max(reach, 0.5 * MIN_FWHM * width), None
    reach = None if None in sides else float("nan")
    why = ("still above the level at the widest window" if reach is None else
           "cut on both sides by image edges, holes or neighbours")
    fallback = min(FALLBACK_FWHM * width, FALLBACK_MAX_PX)
    source = "measured" if measurement.fwhm_measured else "detection's"
    return float(fallback), (f"{FALLBACK_FWHM:g} x the {source} FWHM ({width:.1f} px), at most "
                             f"{FALLBACK_MAX_PX:g} px: the profile's drop below "
                             f"{sb_sigma:g} sky sigma was not measured ({why})")


def fitted_fwhm(measurement):
    """FWHM (px) of the Gaussian and Moffat fits, for comparison with the model-free one."""
    return {"gaussian": GAUSSIAN_FWHM_PER_SIGMA * measurement.gaussian_sigma_px,
            "moffat": MOFFAT_FWHM_PER_ALPHA * measurement.moffat_alpha_px}


def mask_spans(shape, line, width):
    """Row runs of the mask of a streak: a rectangle ``width`` wide along ``line``, extended
    by half the width at both ends (the end caps), clipped to the image."""
    return rectangle_spans(shape, line, 0.5 * width, extend=0.5 * width)


def paint(target, spans, value=True):
    """Set the pixels of row runs in a 2-D array (``|=`` for integer masks)."""
    yy, xx = span_indices(*spans)
    if target.dtype == bool:
        target[yy, xx] = value
    else:
        target[yy, xx] |= value
    return target


def lost_pixels(shape, line, width, flagged=None):
    """Pixels a streak mask covers, and how many of them were already flagged.

    Parameters
    ----------
    shape : tuple
        ``(ny, nx)``.
    line : Line
        The streak's extent in the image.
    width : float
        Full mask width, px.
    flagged : ndarray of bool, optional
        Pixels already unusable (bad, saturated, cosmic rays...): counted apart.

    Returns
    -------
    dict
        ``masked_pixels`` (in the mask), ``already_flagged_pixels`` (of these, already
        flagged), ``lost_pixels`` (the difference: what the streak mask costs) and
        ``masked_fraction`` (``masked_pixels`` over the image's pixel count).
    """
    spans = mask_spans(shape, line, width)
    masked = int(np.sum(spans[2] - spans[1]))
    already = 0
    if flagged is not None and masked:
        yy, xx = span_indices(*spans)
        already = int(np.count_nonzero(flagged[yy, xx]))
    return {"masked_pixels": masked, "already_flagged_pixels": already,
            "lost_pixels": masked - already, "masked_fraction": masked / float(np.prod(shape))}
