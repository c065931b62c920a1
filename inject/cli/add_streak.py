"""``inject add-streak``: one streak injected into a copy of an existing FITS image (any 2-D
image HDU, or an LSST MaskedImage/Exposure); the input is never modified."""
import logging
import os

from inject.cli.options import add_output_option, add_satellite_options, model_from_args
from inject.errors import InputError
from inject.io.atomic import check_writable
from inject.maskplanes import FLAG_OFF_IMAGE, FLAG_SATURATED

log = logging.getLogger(__name__)


def add_add_streak_parser(sub):
    """Register ``inject add-streak`` on an argparse sub-parser collection."""
    p = sub.add_parser(
        "add-streak", help="inject a streak into an existing FITS image",
        description="Inject one streak into a FITS image: any 2-D image HDU, or an LSST "
                    "MaskedImage/Exposure (IMAGE, MASK, VARIANCE found by EXTTYPE as afw does; "
                    "MASK gets a STREAK plane, VARIANCE the streak's Poisson variance, with "
                    "or without noise, unless --no-variance). Pixels "
                    "the streak does not reach are written back unchanged in the file's own "
                    "storage (integers stay integers, compressed HDUs are compressed "
                    "losslessly). The input is never modified.")
    p.add_argument("input", metavar="IN.fits", help="the FITS image (never modified)")
    add_output_option(p, "OUT.fits", "the copy with the streak: FITS, named .fits, .fit or "
                                     ".fts (.gz after it: gzipped) or .fz")
    add_satellite_options(p)
    track = p.add_argument_group(
        "track (array pixels: pixel (0, 0) is the centre of the first pixel of the stored "
        "array; with --parent, LSST parent pixels: array + xy0, xy0 from the LTV1/2 cards)")
    track.add_argument("--x0", type=float, help="start x (or use --ra0/--dec0 with a WCS)")
    track.add_argument("--y0", type=float, help="start y")
    track.add_argument("--parent", action="store_true",
                       help="--x0/--y0 are LSST parent pixels (afw's xy0 convention)")
    track.add_argument("--ra0", type=float, metavar="DEG",
                       help="start RA (needs a WCS, and --dec0; less than 90 deg from a TAN "
                            "WCS's reference point, off the image too)")
    track.add_argument("--dec0", type=float, metavar="DEG", help="start Dec (needs a WCS)")
    track.add_argument("--angle", type=float, default=0.0, metavar="DEG",
                       help="track angle, counter-clockwise from +x")
    track.add_argument("--track-length", type=float, metavar="PX",
                       help="track length from (x0, y0) along --angle; omit it for a line "
                            "through (x0, y0) both ways, across the whole image")
    p.add_argument("--gain", type=float, help="e- per image unit (default: header GAIN, or 1 "
                                              "if BUNIT is electrons)")
    p.add_argument("--seed", type=int, default=1, help="seed of the injected charge's noise")
    p.add_argument("--no-noise", action="store_true",
                   help="add the exact model, no Poisson noise (VARIANCE still grows by the "
                        "model's Poisson variance, as in LSST's source_injection)")
    p.add_argument("--no-variance", action="store_true",
                   help="leave VARIANCE as it is (by default it grows by model / gain^2)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.fits")
    p.set_defaults(func=run_add_streak)


def run_add_streak(args):
    """The ``inject add-streak`` command (``args`` from :func:`add_add_streak_parser`)."""
    # The engine (GalSim, astropy, NumPy): imported when the command runs, not for --help.
    import numpy as np

    from inject.addstreak import add_streaks, sky_to_array
    from inject.io.fits import check_fits_name
    from inject.io.reader import read_exposure
    from inject.trajectory import Track
    from inject.validate import check

    if os.path.exists(args.output) and os.path.samefile(args.input, args.output):
        raise InputError("-o", args.output, "must differ from the input (it is never modified)")
    for option, quantity in (("x0", "track.x0"), ("y0", "track.y0"), ("angle", "track.angle"),
                             ("track_length", "track.length"), ("ra0", "pointing.ra"),
                             ("dec0", "pointing.dec"), ("gain", "gain"), ("seed", "seed")):
        value = getattr(args, option)
        if value is not None:
            check(quantity, value, f"--{option.replace('_', '-')}")
    check_fits_name(args.output, compressed=True)
    if (args.ra0 is None) != (args.dec0 is None):
        raise InputError("--ra0/--dec0", (args.ra0, args.dec0), "give both")
    check_writable(args.output, args.overwrite)
    exposure = read_exposure(args.input)
    wcs = exposure.wcs
    pixel_scale = None
    if wcs is not None:
        from astropy.wcs.utils import proj_plane_pixel_scales

        pixel_scale = float(np.mean(proj_plane_pixel_scales(wcs))) * 3600.0
    if args.ra0 is not None or args.dec0 is not None:
        if wcs is None:
            raise InputError("--ra0/--dec0", (args.ra0, args.dec0), f"{args.input} has no WCS")
        if args.parent or args.x0 is not None or args.y0 is not None:
            raise InputError("--ra0/--dec0", (args.ra0, args.dec0),
                             "give either --ra0/--dec0 or --x0/--y0 (with --parent)")
        # The full WCS (SIP included): array pixels, as FITS headers give them.
        args.x0, args.y0 = sky_to_array(wcs, args.ra0, args.dec0, exposure.image_hdu.data.shape,
                                        "--ra0/--dec0")
    if args.x0 is None or args.y0 is None:
        raise InputError("--x0/--y0", (args.x0, args.y0), "give a start point (or --ra0/--dec0)")
    if args.parent:
        x0, y0 = exposure.xy0
        args.x0, args.y0 = args.x0 - x0, args.y0 - y0
    gain = args.gain
    if gain is None:
        unit = str(exposure.header_value("BUNIT") or "").lower()
        gain = 1.0 if unit.startswith("electron") else exposure.header_value("GAIN")
        if gain is None:
            raise InputError("--gain", None, f"{args.input} has no GAIN header and BUNIT is "
                                             f"not electrons: give --gain")
        gain = check("gain", gain, f"{args.input}'s GAIN header")
    model = model_from_args(args, pixel_scale,
                            "--pixel-scale" if pixel_scale is None else "the WCS's pixel scale")
    track = Track(args.x0, args.y0, args.angle, args.track_length)
    rng = np.random.default_rng(np.random.SeedSequence(args.seed))
    _, truth = add_streaks(exposure, [model], [track], float(gain), rng, noise=not args.no_noise,
                           variance=not args.no_variance)
    exposure.write(args.output, args.overwrite)
    row = truth[0]
    x0, y0 = exposure.xy0
    parent = f" (array pixels; LSST parent = array + ({x0}, {y0}))" if (x0, y0) != (0, 0) else ""
    log.info("wrote %s: streak from (%.1f, %.1f) to (%.1f, %.1f)%s, %.4g e- injected",
             args.output, row["x0"], row["y0"], row["x1"], row["y1"], parent,
             row["charge_in_image_e"])
    if row["flags"] & FLAG_OFF_IMAGE:
        log.warning("the track misses the image: 0 e- injected (TRUTH flags = 1)")
    if row["flags"] & FLAG_SATURATED:
        log.warning("the streak saturates the integer image (clipped at the ADC limit; SAT "
                    "set in MASK if there is one)")
