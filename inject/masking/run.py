"""``inject mask``: detect, measure and mask the streaks of an image.

:func:`mask_image` returns one dict per streak with the keys of CONTRACT.md;
:func:`write_masked` writes a copy of an input FITS file with the STREAK mask plane set;
:func:`add_mask_parser` and :func:`run_mask` make the command. Heavy modules are imported
inside the functions, so registering the command costs nothing.
"""
import json
import math
import os
import sys
from dataclasses import dataclass

from inject.errors import InputError
from inject.masking import MaskingError

#: Defaults of the command (the engine's own defaults, repeated here so the parser needs no
#: NumPy or OpenCV; tests check they agree).
DEFAULT_PIXEL_SCALE = 0.2
DEFAULT_RULE = "sb"
DEFAULT_SB_SIGMA = 1.0
DEFAULT_FWHM_FACTOR = 3.0
RULE_CHOICES = ("sb", "fwhm", "lsst", "acstools")


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

    def to_json(self):
        """The ``inject mask --json`` object: ``{"streaks": [...], "image": {...}}``."""
        npix = self.shape[0] * self.shape[1]
        image = {"path": self.source, "nx": self.shape[1], "ny": self.shape[0],
                 "sky_sigma": self.sky_sigma, "pixel_scale_arcsec": self.pixel_scale,
                 "n_streaks": len(self.streaks), "masked_pixels": self.masked_pixels,
                 "masked_fraction": self.masked_pixels / npix,
                 "lost_pixels": self.lost_pixels, "lost_fraction": self.lost_pixels / npix}
        return _json_safe({"streaks": self.streaks, "image": image})


def _json_safe(value):
    """NaN and infinities become None (JSON has no NaN); NumPy scalars become Python ones."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _check_options(pixel_scale, rule, sb_sigma, fwhm_factor, threshold=None, max_streaks=None):
    import numpy as np

    from inject.validate import positive

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
    """The dict of one streak (CONTRACT keys first); ``rule`` is the mask-width rule applied,
    ``fallback`` the words of the bounded rule that replaced the measured ``sb`` width (or
    None).

    ``fwhm_measured`` is False (and the FWHMs NaN, null in JSON) when the profile is cut
    before a half-maximum crossing (a streak within about half a FWHM of an image edge, a
    hole or a close neighbour's midline).

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
    }


def analyse(image, *, bad=None, flagged=None, pixel_scale=DEFAULT_PIXEL_SCALE,
            rule=DEFAULT_RULE, sb_sigma=DEFAULT_SB_SIGMA, fwhm_factor=DEFAULT_FWHM_FACTOR,
            threshold=None, max_streaks=None, n_boot=50, source=None):
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

    Returns
    -------
    MaskResult
    """
    import numpy as np

    from inject.masking.detect import FALSE_ALARM_Z, MAX_STREAKS, detect_streaks, prepare
    from inject.masking.geometry import span_indices
    from inject.masking.mask import lost_pixels, mask_spans, mask_widths, sb_width
    from inject.masking.measure import measure_streak

    _check_options(pixel_scale, rule, sb_sigma, fwhm_factor, threshold, max_streaks)
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
                      source=source)


def _mask_bits(exposure):
    """``{plane: bit}`` of an exposure's MASK header (``MSKN`` and ``MP_`` cards); afw's
    default bits if it names none."""
    from inject.maskplanes import MASK_PLANES, header_planes

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
    """Streaks of an image, one dict each (CONTRACT.md keys and more).

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
    return _analyse_source(source, mask, pixel_scale, **options).streaks


def _analyse_source(source, mask=None, pixel_scale=None, **options):
    from inject.io.reader import InputExposure, read_exposure

    name = None
    if isinstance(source, (str, os.PathLike)):
        name = os.fspath(source)
        source = read_exposure(source)
    if isinstance(source, InputExposure):
        image, bad, wcs_scale = _exposure_arrays(source)
        pixel_scale = pixel_scale or wcs_scale
    else:
        image, bad = source, mask
    return analyse(image, bad=bad, pixel_scale=pixel_scale or DEFAULT_PIXEL_SCALE,
                   source=name, **options)


def _set_streak_plane(exposure, streaks):
    """Replace the STREAK plane of ``exposure`` (in memory) with the masks of ``streaks``.

    The mask keeps the file's own pixel type and plane bits (:meth:`InputExposure.set_bits`:
    a uint16 mask stays int16 + BZERO); STREAK goes on the lowest free bit if the file has no
    such plane. A MASK HDU (int32, afw's planes named) is added if the file has none.
    Returns the number of pixels set.
    """
    import numpy as np
    from astropy.io import fits

    from inject.maskplanes import mask_header
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

    _check_distinct(in_path, out_path)
    return _write_exposure(read_exposure(in_path), out_path, streaks, overwrite)


def _check_distinct(in_path, out_path):
    if os.path.exists(in_path) and os.path.exists(out_path) and os.path.samefile(in_path,
                                                                                 out_path):
        raise InputError("--out", os.fspath(out_path),
                         "must differ from the input (it is never modified)")


def _write_exposure(exposure, out_path, streaks, overwrite):
    count = _set_streak_plane(exposure, streaks)
    exposure.write(out_path, overwrite)  # atomic; HDUs other than MASK copied byte for byte
    return count


def add_mask_parser(sub):
    """Register ``inject mask`` on an argparse sub-parser collection."""
    p = sub.add_parser(
        "mask", help="detect, measure and mask the streaks of a FITS image",
        description="Detect satellite streaks (matched filter + fast Hough transform on a "
                    "binned, star-cleaned image), measure their line and model-free FWHM, and "
                    "size their masks. The input is never modified.")
    p.add_argument("image", metavar="IMAGE.fits")
    p.add_argument("--json", action="store_true",
                   help='print {"streaks": [...], "image": {...}} as JSON')
    p.add_argument("-o", "--out", "--output", metavar="MASKED.fits",
                   help="write a copy with the STREAK mask plane set")
    p.add_argument("--overwrite", action="store_true", help="replace an existing MASKED.fits")
    p.add_argument("--pixel-scale", type=float, metavar="ARCSEC",
                   help="arcsec per pixel (default: from the WCS, else 0.2)")
    p.add_argument("--mask-rule", choices=RULE_CHOICES, default=DEFAULT_RULE,
                   help="mask width: sb = where the profile drops below --sb-sigma x sky noise "
                        "(default), fwhm = --fwhm-factor x FWHM, lsst = +-5 alpha of a Moffat "
                        "beta 2.5 fit (maskStreaks), acstools = 6 sigma of a Gaussian fit "
                        "(findsat_mrt); all four widths are reported")
    p.add_argument("--sb-sigma", type=float, default=DEFAULT_SB_SIGMA, metavar="T",
                   help="surface-brightness threshold of the sb rule, in sky sigma")
    p.add_argument("--fwhm-factor", type=float, default=DEFAULT_FWHM_FACTOR, metavar="K",
                   help="k of the fwhm rule")
    p.add_argument("--threshold", type=float, metavar="Z",
                   help="detection threshold on the Hough significance (default: calibrated "
                        "false-alarm level)")
    p.add_argument("--max-streaks", type=int, metavar="N", help="most streaks to find (8)")
    p.set_defaults(func=run_mask)
    return p


def run_mask(args):
    """The ``inject mask`` command (``args`` from :func:`add_mask_parser`)."""
    from inject.io.atomic import check_writable
    from inject.io.reader import read_exposure

    _check_options(args.pixel_scale, args.mask_rule, args.sb_sigma, args.fwhm_factor,
                   args.threshold, args.max_streaks)
    if args.out:  # fail before the work, not after it
        _check_distinct(args.image, args.out)
        check_writable(args.out, args.overwrite)
    exposure = read_exposure(args.image)
    result = _analyse_source(exposure, pixel_scale=args.pixel_scale, rule=args.mask_rule,
                             sb_sigma=args.sb_sigma, fwhm_factor=args.fwhm_factor,
                             threshold=args.threshold, max_streaks=args.max_streaks)
    result.source = os.fspath(args.image)
    if args.out:
        _write_exposure(exposure, args.out, result.streaks, args.overwrite)
    if args.json:
        json.dump(result.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        _print_table(result)
    if args.out:
        print(f"wrote {args.out}", file=sys.stderr)


def _print_table(result):
    print(f"{len(result.streaks)} streak(s) in {result.source or 'image'} "
          f"({result.shape[1]} x {result.shape[0]} px, sky sigma {result.sky_sigma:.4g})")
    if result.streaks:
        names = ("angle", "x0", "y0", "x1", "y1", "FWHM\"", "+-", "width", "masked", "frac", "z")
        widths = (8, 8, 8, 8, 8, 7, 6, 7, 9, 7, 7)
        print(" ".join(name.rjust(w) for name, w in zip(names, widths)))
    for s in result.streaks:
        # An unmeasured FWHM (a streak cut by an edge, a hole or a neighbour) reads n/a.
        fwhm = (f"{s['fwhm_arcsec']:7.3f} {s['fwhm_err_arcsec']:6.3f}" if s["fwhm_measured"]
                else f"{'n/a':>7s} {'':6s}")
        print(f"{s['angle_deg']:8.3f} {s['x0']:8.1f} {s['y0']:8.1f} {s['x1']:8.1f} "
              f"{s['y1']:8.1f} {fwhm} "
              f"{s['mask_width_px']:7.1f} {s['masked_pixels']:9d} {s['masked_fraction']:7.4f} "
              f"{s['significance']:7.1f}")
    for k, s in enumerate(result.streaks):
        if s["mask_fallback"]:
            print(f"streak {k + 1}: mask width {s['mask_width_px']:.1f} px by "
                  f"{s['mask_fallback']}")
    npix = result.shape[0] * result.shape[1]
    print(f"masked {result.masked_pixels} px ({result.masked_pixels / npix:.4%}), "
          f"{result.lost_pixels} not already flagged")
