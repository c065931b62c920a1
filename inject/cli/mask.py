"""``inject mask``: detect, measure and mask the streaks of a FITS image.

The command line of :mod:`inject.masking.run` (the engine): its parser, the run that reads the
image, masks it and writes the copy, and the table it prints.
"""
import json
import logging
import os
import sys

from inject.io.atomic import check_writable
from inject.masking.run import (
    DEFAULT_FWHM_FACTOR,
    DEFAULT_RULE,
    DEFAULT_SB_SIGMA,
    PIXEL_SCALE_FWHM_PX,
    RULE_CHOICES,
    analyse_source,
    check_distinct,
    check_options,
    write_masked_exposure,
)

log = logging.getLogger(__name__)


def add_mask_parser(sub):
    """Register ``inject mask`` on an argparse sub-parser collection."""
    p = sub.add_parser(
        "mask", help="detect, measure and mask the streaks of a FITS image",
        description="Detect satellite streaks (matched filter + fast Hough transform on a "
                    "binned, star-cleaned image), measure their line and model-free FWHM, and "
                    "size their masks. The input is never modified.")
    p.add_argument("image", metavar="IMAGE.fits", help="the FITS image (never modified)")
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
    p.add_argument("--max-streaks", type=int, metavar="N", help="most streaks to find (default: 8)")
    p.set_defaults(func=run_mask)
    return p


def run_mask(args):
    """The ``inject mask`` command (``args`` from :func:`add_mask_parser`)."""
    check_options(args.pixel_scale, args.mask_rule, args.sb_sigma, args.fwhm_factor,
                  args.threshold, args.max_streaks)
    if args.out:  # fail before the work, not after it
        check_distinct(args.image, args.out)
        check_writable(args.out, args.overwrite)
    from inject.io.reader import read_exposure  # astropy: after the options' checks

    exposure = read_exposure(args.image)
    result = analyse_source(exposure, pixel_scale=args.pixel_scale, rule=args.mask_rule,
                            sb_sigma=args.sb_sigma, fwhm_factor=args.fwhm_factor,
                            threshold=args.threshold, max_streaks=args.max_streaks)
    result.source = os.fspath(args.image)
    if args.out:
        write_masked_exposure(exposure, args.out, result.streaks, args.overwrite)
    if args.json:
        json.dump(result.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        _print_table(result)
    if args.out:
        log.info("wrote %s", args.out)


def _print_table(result):
    scale = {"wcs": "from the WCS", "option": "given",
             "default": "assumed: no WCS, give --pixel-scale"}[result.pixel_scale_source]
    print(f"{len(result.streaks)} streak(s) in {result.source or 'image'} "
          f"({result.shape[1]} x {result.shape[0]} px, sky sigma {result.sky_sigma:.4g}, "
          f"{result.pixel_scale:.4g}\"/px {scale})")
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
        if s["fwhm_measured"] and s["fwhm_at_pixel_scale"]:
            print(f"streak {k + 1}: FWHM {s['fwhm_px']:.2f} px is at the pixel scale "
                  f"(under {PIXEL_SCALE_FWHM_PX:g} px): undersampled, an upper bound")
        if s["mask_fallback"]:
            print(f"streak {k + 1}: mask width {s['mask_width_px']:.1f} px by "
                  f"{s['mask_fallback']}")
    npix = result.shape[0] * result.shape[1]
    print(f"masked {result.masked_pixels} px ({result.masked_pixels / npix:.4%}), "
          f"{result.lost_pixels} not already flagged")
