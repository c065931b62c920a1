"""Detect, measure and mask the streaks of an image: the engine of ``inject mask``.

:func:`mask_image` returns one dict per streak with the keys documented in
docs/reference/file-formats.md; :func:`write_masked` writes a copy of an input FITS file with
the STREAK mask plane set.
The command line is :mod:`inject.cli.mask`, which imports this module to build its parser:
the modules that need OpenCV, SciPy or astropy, and the geometry the engine alone uses, are
imported inside the functions, so registering the command costs next to nothing.
"""
import math
import os
from dataclasses import dataclass

from inject.errors import InputError
from inject.maskplanes import MASK_PLANES, header_planes, mask_header
from inject.validate import positive

#: Defaults of the command (the engine's own defaults, repeated here so the parser needs no
#: NumPy or OpenCV; tests check they agree).
DEFAULT_PIXEL_SCALE = 0.2
DEFAULT_RULE = "sb"
DEFAULT_SB_SIGMA = 1.0
DEFAULT_FWHM_FACTOR = 3.0
RULE_CHOICES = ("sb", "fwhm", "lsst", "acstools")

#: A streak whose measured FWHM is under this many pixels is at the pixel scale: the pixel
#: response, not the streak, sets most of its width, and the FWHM (an upper bound, ~25% high
#: at 0.8 px) is flagged ``fwhm_at_pixel_scale`` rather than reported as a measurement. From
#: 2 px up it is within a few percent (docs/guides/masking.md).
PIXEL_SCALE_FWHM_PX = 2.0


@dataclass
class MaskResult:
    """Streaks of one image and what masking them costs.

    Attributes
    ----------
    streaks : list of dict
        One per streak, most significant first (keys: see :func:`streak_record`).
    shape : tuple
        ``(ny, nx)`` of the image.
    sky_sigma : float
        Robust per-pixel noise (image units).
    pixel_scale : float
        Arcsec per pixel used for the arcsec values.
    pixel_scale_source : str
        Where it came from: ``"option"`` (given), ``"wcs"`` (the file's WCS) or ``"default"``
        (neither: 0.2"/px assumed, and the arcsec values are only as right as that).
    masked_pixels : int
        Pixels under any streak's mask (overlaps counted once).
    lost_pixels : int
        Of these, pixels not already flagged.
    """

    streaks: list
    shape: tuple
    sky_sigma: float
    pixel_scale: float
    masked_pixels: int = 0
    lost_pixels: int = 0
    source: str | None = None
    pixel_scale_source: str = "option"

    def to_json(self):
        """The ``inject mask --json`` object: ``{"streaks": [...], "image": {...}}``."""
        npix = self.shape[0] * self.shape[1]
        image = {"path": self.source, "nx": self.shape[1], "ny": self.shape[0],
                 "sky_sigma": self.sky_sigma, "pixel_scale_arcsec": self.pixel_scale,
                 "pixel_scale_source": self.pixel_scale_source,
                 "n_streaks": len(self.streaks), "masked_pixels": self.masked_pixels,
                 "masked_fraction": self.masked_pixels / npix,
                 "lost_pixels": self.lost_pixels, "lost_fraction": self.lost_pixels / npix}
        return json_safe({"streaks": self.streaks, "image": image})


def json_safe(value):
    """NaN and infinities become None (JSON has no NaN); NumPy scalars become Python ones."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def check_options(pixel_scale, rule, sb_sigma, fwhm_factor, threshold=None, max_streaks=None):
    """Refuse bad options of :func:`analyse` (:class:`InputError` naming the command-line
    option), before any work."""
    import numpy as np

    if pixel_scale is not None:
        positive("--pixel-scale", pixel_scale, scalar=True)
    if not isinstance(rule, str) or rule not in RULE_CHOICES:
        raise InputError("--mask-rule", rule, f"choose one of {', '.join(RULE_CHOICES)}")
    positive("--sb-sigma", sb_sigma, scalar=True)
    positive("--fwhm-factor", fwhm_factor, scalar=True)
    if threshold is not None:
        # A significance <= 0 passes every line of the noise: refused, not searched.
        positive("--threshold", threshold, scalar=True)
    if max_streaks is not None and not (isinstance(max_streaks, (int, np.integer))
                                        and max_streaks >= 1):
        raise InputError("--max-streaks", max_streaks, "must be an integer >= 1")


def streak_record(measurement, detection, widths, rule, counts, pixel_scale, sky_sigma,
                  fallback=None):
    """The dict of one streak (the documented keys first); ``rule`` is the mask-width rule applied,
    ``fallback`` the words of the bounded rule that replaced the measured ``sb`` width (or
    None).

    ``fwhm_measured`` is False (and the FWHMs NaN, null in JSON) when the profile is cut
    before a half-maximum crossing (a streak within about half a FWHM of an image edge, a
    hole or a close neighbour's midline). ``fwhm_at_pixel_scale`` is True when the FWHM is
    measured but under :data:`PIXEL_SCALE_FWHM_PX`: an undersampled streak, whose width is
    an upper bound.

    The direction of motion cannot be seen in an image: ``angle_deg`` is the line's orientation
    in ``(-90, 90]`` and ``(x0, y0) -> (x1, y1)`` runs that way.
    """
    from inject.masking.mask import fitted_fwhm

    line = measurement.line
    at_edge = measurement.at_edge
    angle = line.angle_deg
    if not -90 < angle <= 90:
        line = type(line)(line.x1, line.y1, line.x0, line.y0)
        at_edge = at_edge[::-1]
        angle = line.angle_deg
    fits = fitted_fwhm(measurement)
    return {
        "angle_deg": angle, "x0": line.x0, "y0": line.y0, "x1": line.x1, "y1": line.y1,
        "fwhm_arcsec": measurement.fwhm_px * pixel_scale, "fwhm_px": measurement.fwhm_px,
        "mask_width_px": widths[rule], **counts,
        "length_px": line.length, "ends_at_edge": list(at_edge),
        "fwhm_err_px": measurement.fwhm_err_px,
        "fwhm_err_arcsec": measurement.fwhm_err_px * pixel_scale,
        "fwhm_pixelated_px": measurement.fwhm_pixelated_px,
        "gaussian_fwhm_px": fits["gaussian"], "moffat_fwhm_px": fits["moffat"],
        "peak": measurement.peak, "peak_snr": measurement.peak / sky_sigma,
        "snr": measurement.snr, "significance": detection.significance,
        "mask_rule": rule, "mask_widths_px": widths,
        "fwhm_measured": measurement.fwhm_measured, "mask_fallback": fallback,
        "fwhm_at_pixel_scale": bool(measurement.fwhm_px < PIXEL_SCALE_FWHM_PX),
    }


def analyse(image, *, bad=None, flagged=None, pixel_scale=DEFAULT_PIXEL_SCALE,
            rule=DEFAULT_RULE, sb_sigma=DEFAULT_SB_SIGMA, fwhm_factor=DEFAULT_FWHM_FACTOR,
            threshold=None, max_streaks=None, n_boot=50, source=None,
            pixel_scale_source="option"):
    """Detect, measure and size the masks of the streaks of an image array.

    Parameters
    ----------
    image : array_like
        2-D image, any units.
    bad : array_like of bool, optional
        Pixels not to use for detection or measurement.
    flagged : array_like of bool, optional
        Pixels already flagged (counted apart from the pixels a mask costs); default ``bad``.
    pixel_scale : float
        Arcsec per pixel.
    rule : str
        Mask-width rule of ``mask_width_px`` (one of ``sb``, ``fwhm``, ``lsst``, ``acstools``).
    sb_sigma, fwhm_factor : float
        Parameters of the ``sb`` and ``fwhm`` rules.
    threshold : float, optional
        Detection threshold (default :data:`~inject.masking.detect.FALSE_ALARM_Z`).
    max_streaks : int, optional
    n_boot : int
        Bootstrap replicates of the FWHM error.
    source : str, optional
        Where the image came from (reported).
    pixel_scale_source : str
        Where ``pixel_scale`` came from (reported; see :class:`MaskResult`).

    Returns
    -------
    MaskResult
    """
    import numpy as np

    from inject.masking.detect import FALSE_ALARM_Z, MAX_STREAKS, detect_streaks, prepare
    from inject.masking.geometry import span_indices
    from inject.masking.mask import lost_pixels, mask_spans, mask_widths, sb_width
    from inject.masking.measure import measure_streak

    check_options(pixel_scale, rule, sb_sigma, fwhm_factor, threshold, max_streaks)
    prep = prepare(image, bad)
    flagged = bad if flagged is None else flagged
    flagged = None if flagged is None else np.asarray(flagged, dtype=bool)
    detections = detect_streaks(prep, FALSE_ALARM_Z if threshold is None else threshold,
                                MAX_STREAKS if max_streaks is None else max_streaks)
    pixels = []  # flat indices of each mask (their union is counted once)
    streaks = []
    for det in detections:
        # Each streak is measured without the pixels nearer to another (a close neighbour).
        others = [d.line for d in detections if d is not det]
        m = measure_streak(prep, det.trace, wing_level=sb_sigma * prep.sigma, n_boot=n_boot,
                           exclude=others)
        widths = mask_widths(m, prep.sigma, sb_sigma, fwhm_factor)
        # A Gaussian or Moffat fit can fail, or the FWHM be unmeasurable: then the sb rule.
        applied = rule if np.isfinite(widths[rule]) else DEFAULT_RULE
        fallback = sb_width(m, prep.sigma, sb_sigma)[1] if applied == "sb" else None
        counts = lost_pixels(prep.shape, m.line, widths[applied], flagged)
        yy, xx = span_indices(*mask_spans(prep.shape, m.line, widths[applied]))
        pixels.append(yy * prep.shape[1] + xx)
        streaks.append(streak_record(m, det, widths, applied, counts, pixel_scale, prep.sigma,
                                     fallback))
    # The masks' union from their pixel indices, not a full-size image (a few passes over a
    # 16 Mpx CCD would cost more than the masks themselves).
    union = np.unique(np.concatenate(pixels)) if len(pixels) > 1 else \
        (pixels[0] if pixels else np.zeros(0, dtype=np.intp))
    masked = int(union.size)
    already = int(np.count_nonzero(flagged.ravel()[union])) if flagged is not None else 0
    return MaskResult(streaks=streaks, shape=prep.shape, sky_sigma=prep.sigma,
                      pixel_scale=pixel_scale, masked_pixels=masked, lost_pixels=masked - already,
                      source=source, pixel_scale_source=pixel_scale_source)


def _mask_bits(exposure):
    """``{plane: bit}`` of an exposure's MASK header (``MSKN`` and ``MP_`` cards); afw's
    default bits if it names none."""
    if exposure.mask_index is None:
        return dict(MASK_PLANES)
    return header_planes(exposure.file_header(exposure.mask_index)) or dict(MASK_PLANES)


def _exposure_arrays(exposure):
    """Image, bad-pixel mask (or None) and pixel scale from WCS (or None) of an exposure."""
    import numpy as np

    from inject.masking.detect import BAD_PLANES

    image = exposure.image
    bad = None
    if exposure.mask_index is not None:
        mask = np.asarray(exposure.hdus[exposure.mask_index].data).astype(np.int64)
        if mask.shape == image.shape:
            bits = _mask_bits(exposure)
            planes = sum(1 << bits[p] for p in BAD_PLANES if p in bits)
            bad = (mask & planes) != 0
    scale = None
    wcs = exposure.wcs
    if wcs is not None:
        from astropy.wcs.utils import proj_plane_pixel_scales

        scale = float(np.mean(proj_plane_pixel_scales(wcs))) * 3600.0
    return image, bad, scale


def mask_image(source, *, mask=None, pixel_scale=None, **options):
    """Streaks of an image, one dict each (the documented keys and more).

    Parameters
    ----------
    source : str, os.PathLike, ndarray or InputExposure
        A FITS file (any 2-D image HDU, or an LSST-style IMAGE/MASK/VARIANCE file, whose bad
        planes are ignored), an image array, or an exposure already read.
    mask : ndarray of bool, optional
        Pixels not to use (arrays only; a file's MASK HDU is used automatically).
    pixel_scale : float, optional
        Arcsec per pixel; default: from the WCS if the file has one, else 0.2.
    **options
        Passed to :func:`analyse` (``rule``, ``sb_sigma``, ``fwhm_factor``, ``threshold``,
        ``max_streaks``, ``n_boot``).

    Returns
    -------
    list of dict
        Each with ``angle_deg, x0, y0, x1, y1, fwhm_arcsec, fwhm_px, mask_width_px,
        masked_pixels, masked_fraction`` and the extras of :func:`streak_record`.
    """
    return analyse_source(source, mask, pixel_scale, **options).streaks


def analyse_source(source, mask=None, pixel_scale=None, **options):
    """The :class:`MaskResult` of :func:`mask_image` (same arguments): every streak, and what
    masking them costs."""
    from inject.io.reader import InputExposure, read_exposure

    name = None
    if isinstance(source, (str, os.PathLike)):
        name = os.fspath(source)
        source = read_exposure(source)
    origin = "option" if pixel_scale else None
    if isinstance(source, InputExposure):
        image, bad, wcs_scale = _exposure_arrays(source)
        if not pixel_scale and wcs_scale:
            pixel_scale, origin = wcs_scale, "wcs"
    else:
        image, bad = source, mask
    return analyse(image, bad=bad, pixel_scale=pixel_scale or DEFAULT_PIXEL_SCALE,
                   source=name, pixel_scale_source=origin or "default", **options)


def _set_streak_plane(exposure, streaks):
    """Replace the STREAK plane of ``exposure`` (in memory) with the masks of ``streaks``.

    The mask keeps the file's own pixel type and plane bits (:meth:`InputExposure.set_bits`:
    a uint16 mask stays int16 + BZERO); STREAK goes on the lowest free bit if the file has no
    such plane. A MASK HDU (int32, afw's planes named) is added if the file has none.
    Returns the number of pixels set.
    """
    import numpy as np
    from astropy.io import fits

    from inject.masking.geometry import Line
    from inject.masking.mask import mask_spans, paint

    shape = exposure.image_hdu.data.shape
    if exposure.mask_index is None:
        exposure.hdus.append(fits.ImageHDU(np.zeros(shape, dtype=np.int32),
                                           header=mask_header(fits.Header()), name="MASK"))
        exposure.mask_index = len(exposure.hdus) - 1
    index = exposure.mask_index
    plane = np.zeros(shape, dtype=bool)
    for i, s in enumerate(streaks):
        try:
            ends = [float(s[key]) for key in ("x0", "y0", "x1", "y1", "mask_width_px")]
        except (KeyError, TypeError, ValueError):
            raise InputError(f"streaks[{i}]", s, "needs numbers x0, y0, x1, y1 and "
                             "mask_width_px (as mask_image returns)") from None
        paint(plane, mask_spans(shape, Line(*ends[:4]), ends[4]))
    exposure.set_bits(index, exposure.name_plane(index, "STREAK"), plane, replace=True)
    exposure.set_card(index, "NSTREAK", len(streaks))
    return int(plane.sum())


def write_masked(in_path, out_path, streaks, overwrite=False):
    """Write a copy of ``in_path`` whose MASK STREAK plane holds the masks of ``streaks``.

    The input is never modified; any STREAK bits it had are replaced in the copy (e.g. the
    truth plane of a simulated image). The output is written atomically.

    Parameters
    ----------
    in_path, out_path : str or os.PathLike
    streaks : list of dict
        As returned by :func:`mask_image` (``x0, y0, x1, y1, mask_width_px``).
    overwrite : bool

    Returns
    -------
    int
        Pixels in the STREAK plane.
    """
    from inject.io.reader import read_exposure

    check_distinct(in_path, out_path)
    return write_masked_exposure(read_exposure(in_path), out_path, streaks, overwrite)


def check_distinct(in_path, out_path):
    """Refuse an output that is the input file itself (it is never modified)."""
    if os.path.exists(in_path) and os.path.exists(out_path) and os.path.samefile(in_path,
                                                                                 out_path):
        raise InputError("--out", os.fspath(out_path),
                         "must differ from the input (it is never modified)")


def write_masked_exposure(exposure, out_path, streaks, overwrite=False):
    """:func:`write_masked` of an exposure already read (:class:`~inject.io.reader.InputExposure`,
    changed in memory)."""
    count = _set_streak_plane(exposure, streaks)
    exposure.write(out_path, overwrite)  # atomic; HDUs other than MASK copied byte for byte
    return count
