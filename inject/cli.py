"""Command-line interface: ``inject profile``, ``inject simulate``, ...

Each subcommand parses its options, calls the engine and prints or writes the result. Any
:class:`~inject.errors.InjectError` becomes a one-line message on stderr and exit status 2
(``--traceback`` shows the full stack instead); so do argparse's usage errors (without the
usage block: ``inject simulate --help`` shows it).
"""
import argparse
import json
import sys

from . import __version__
from .errors import InjectError, InputError


def _one_line(text):
    """``text`` with every run of whitespace (newlines included) as one space."""
    return " ".join(str(text).split())


def _usage_error(prog, message):
    """Exit with status 2 (argparse's, for usage errors) after ``PROG: error: MESSAGE``."""
    print(f"{prog}: error: {_one_line(message)}", file=sys.stderr)
    sys.exit(2)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, exit status 2.

    argparse prints the whole usage block before the error; that block is what ``--help``
    is for. Sub-parsers are of the same class (``add_subparsers`` uses the parent's), so
    their errors name the subcommand: ``inject simulate: error: argument --seed: ...``.
    """

    def error(self, message):
        _usage_error(self.prog, message)


def _add_satellite_options(p):
    """Options describing one satellite and its geometry (shared by profile and add-streak)."""
    p.add_argument("--height", type=float, required=True, metavar="KM", help="orbit height, km")
    p.add_argument("--zenith", type=float, default=0.0, metavar="DEG", help="zenith angle (0)")
    p.add_argument("--phi", type=float, default=90.0, metavar="DEG",
                   help="velocity rotation angle, paper eq. 8 (90: along constant azimuth)")
    p.add_argument("--shape", choices=("box", "disk"), default="box")
    p.add_argument("--length", type=float, metavar="M", help="box length along the motion (7.25)")
    p.add_argument("--width", type=float, metavar="M", help="box width across the motion (2.65)")
    p.add_argument("--radius", type=float, metavar="M", help="disk radius (1.0)")
    p.add_argument("--seeing", type=float, default=0.67, metavar="ARCSEC",
                   help="atmospheric FWHM (Kolmogorov unless --seeing-model), 0 for none")
    p.add_argument("--seeing-model", choices=("kolmogorov", "vonkarman"), default="kolmogorov")
    p.add_argument("--band", default="g", help="u g r i z y (g)")
    p.add_argument("--mag", type=float, default=5.0,
                   help="stationary AB magnitude at --ref-range, face-on (5.0)")
    p.add_argument("--ref-range", type=float, default=550.0, metavar="KM")
    p.add_argument("--pixel-scale", type=float, default=0.2, metavar="ARCSEC")


def _add_profile_parser(sub):
    p = sub.add_parser("profile", help="streak profile of one satellite in one geometry",
                       description="Geometry, photometry and cross-section of one streak.")
    _add_satellite_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run_profile)


def _model_from_args(args, pixel_scale=None):
    from .instrument import LSST
    from .profile import Seeing
    from .streak import StreakModel

    return StreakModel(
        height_km=args.height, zenith_deg=args.zenith, phi_deg=args.phi,
        shape=_shape_from_args(args), mag=args.mag, band_name=args.band,
        seeing=Seeing(args.seeing, args.seeing_model),
        telescope=LSST.with_pixel_scale(pixel_scale or args.pixel_scale),
        ref_range_km=args.ref_range)


def _shape_from_args(args):
    from .satellite import Box, Disk

    if args.shape == "box":
        if args.radius is not None:
            raise InputError("--radius", args.radius, "only applies to --shape disk")
        return Box(7.25 if args.length is None else args.length,
                   2.65 if args.width is None else args.width)
    if args.length is not None or args.width is not None:
        raise InputError("--length/--width", (args.length, args.width),
                         "only apply to --shape box")
    return Disk(1.0 if args.radius is None else args.radius)


def run_profile(args):
    model = _model_from_args(args)
    result = model.summary()
    if args.json:
        offsets, e_per_px = model.cross_section()
        result["cross_section"] = {"offset_arcsec": offsets.round(6).tolist(),
                                   "e_per_px": e_per_px.tolist()}
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    else:
        _print_table(result)


_TABLE_ROWS = (
    ("height_km", "orbit height", "km", "{:.1f}"),
    ("zenith_deg", "zenith angle", "deg", "{:.2f}"),
    ("range_km", "range", "km", "{:.2f}"),
    ("nadir_angle_deg", "nadir angle", "deg", "{:.3f}"),
    ("orbital_speed_m_s", "orbital speed", "m/s", "{:.1f}"),
    ("angular_speed_deg_s", "angular speed", "deg/s", "{:.4f}"),
    ("t_eff_s", "effective pixel exposure", "ms", "{:.4f}", 1e3),
    ("apparent_mag", "apparent magnitude", "AB mag", "{:.3f}"),
    ("zeropoint_mag", "zero point (1 e-/s)", "AB mag", "{:.2f}"),
    ("flux_per_px_e", "charge per pixel of track", "e-", "{:.1f}"),
    ("fwhm_arcsec", "streak FWHM", "arcsec", "{:.3f}"),
    ("peak_e_per_px", "peak surface brightness", "e-/px", "{:.1f}"),
)


def _print_table(result):
    for key, label, unit, fmt, *scale in _TABLE_ROWS:
        value = result[key] * (scale[0] if scale else 1)
        print(f"{label:<28s} {fmt.format(value):>14s}  {unit}")


def _add_simulate_parser(sub):
    p = sub.add_parser("simulate", help="simulate one CCD with streaks from a scene file",
                       description="Simulate one LSSTCam-like CCD from a YAML scene file.")
    p.add_argument("scene", help="YAML scene file (see sample_fields/)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.fits")
    p.add_argument("--exr", metavar="OUT.exr", help="also write OpenEXR")
    p.add_argument("--png", metavar="OUT.png", help="also write a quicklook PNG")
    p.add_argument("--truth", metavar="OUT.csv", help="also write the truth table as CSV")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    # default=[]: without it argparse lists this optional positional as "required".
    p.add_argument("overrides", nargs="*", default=[], metavar="key.path=value",
                   help="override scene keys, e.g. satellites.0.mag=6 detector.nx=512")
    p.set_defaults(func=run_simulate)


def run_simulate(args):
    """The ``inject simulate`` command: every output is written, or none (all-or-nothing)."""
    import os

    from .config import apply_overrides, load_scene_file, parse_scene
    from .io.atomic import output_group
    from .io.fits import write_exposure
    from .scene import simulate

    scene = parse_scene(apply_overrides(load_scene_file(args.scene), args.overrides))
    outputs = {option: path for option, path in (("-o", args.output), ("--exr", args.exr),
                                                 ("--png", args.png), ("--truth", args.truth))
               if path}
    for option, path in outputs.items():
        if os.path.exists(path) and os.path.samefile(path, args.scene):
            raise InputError(option, path, "would replace the scene file")
    # The group checks every target before the work, and moves the finished files into place
    # together at its end: a failing EXR leaves no new FITS behind.
    with output_group(outputs.values(), args.overwrite):
        wcs = None
        if scene.pointing is not None:
            from .instrument import LSST
            from .wcs import pointing_wcs

            wcs = pointing_wcs(scene.pointing, scene.detector.shape, LSST.pixel_scale_arcsec)
        result = simulate(scene, wcs=wcs)
        write_exposure(args.output, scene, result, scene.detector.gain,
                       wcs_header=None if wcs is None else wcs.to_header(relax=True),
                       overwrite=args.overwrite)
        if args.exr:
            from .io.exr import write_exr

            write_exr(args.exr, scene, result, overwrite=args.overwrite)
        if args.png:
            from .io.quicklook import write_quicklook

            write_quicklook(args.png, result, overwrite=args.overwrite)
        if args.truth:
            from .io.fits import write_truth_csv

            write_truth_csv(args.truth, result.truth, overwrite=args.overwrite)
    for path in outputs.values():
        print(f"wrote {path}", file=sys.stderr)


def _add_add_streak_parser(sub):
    p = sub.add_parser("add-streak", help="inject a streak into an existing FITS image",
                       description="Inject one streak into a FITS image (any 2-D image HDU or an "
                                   "LSST IMAGE/MASK/VARIANCE file). The input is never modified.")
    p.add_argument("input", metavar="IN.fits")
    p.add_argument("-o", "--output", required=True, metavar="OUT.fits")
    _add_satellite_options(p)
    track = p.add_argument_group("track (pixels; pixel (0, 0) is the centre of the first pixel)")
    track.add_argument("--x0", type=float, help="start x (or use --ra0/--dec0 with a WCS)")
    track.add_argument("--y0", type=float, help="start y")
    track.add_argument("--ra0", type=float, metavar="DEG", help="start RA (needs a WCS)")
    track.add_argument("--dec0", type=float, metavar="DEG", help="start Dec (needs a WCS)")
    track.add_argument("--angle", type=float, default=0.0, metavar="DEG",
                       help="track angle, counter-clockwise from +x (0)")
    track.add_argument("--track-length", type=float, metavar="PX",
                       help="track length; omit to cross the whole image")
    p.add_argument("--gain", type=float, help="e- per image unit (default: header GAIN, or 1 "
                                              "if BUNIT is electrons)")
    p.add_argument("--seed", type=int, default=1, help="seed of the injected charge's noise")
    p.add_argument("--no-noise", action="store_true", help="add the exact model, no Poisson noise")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.fits")
    p.set_defaults(func=run_add_streak)


def run_add_streak(args):
    import os

    import numpy as np

    from .config import Track
    from .addstreak import add_streaks
    from .io.atomic import atomic_path, check_writable
    from .io.reader import read_exposure

    if os.path.exists(args.output) and os.path.samefile(args.input, args.output):
        raise InputError("-o", args.output, "must differ from the input (it is never modified)")
    for option in ("x0", "y0", "angle", "track_length", "ra0", "dec0"):
        value = getattr(args, option)
        if value is not None and not np.isfinite(value):
            raise InputError(f"--{option.replace('_', '-')}", value, "must be finite")
    if args.seed < 1:
        raise InputError("--seed", args.seed, "must be >= 1")
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
        args.x0, args.y0 = (float(v) for v in wcs.world_to_pixel_values(args.ra0, args.dec0))
    if args.x0 is None or args.y0 is None:
        raise InputError("--x0/--y0", (args.x0, args.y0), "give a start point (or --ra0/--dec0)")
    gain = args.gain
    if gain is None:
        unit = str(exposure.header_value("BUNIT") or "").lower()
        gain = 1.0 if unit.startswith("electron") else exposure.header_value("GAIN")
        if gain is None:
            raise InputError("--gain", None, f"{args.input} has no GAIN header and BUNIT is "
                                             f"not electrons: give --gain")
    model = _model_from_args(args, pixel_scale)
    track = Track(args.x0, args.y0, args.angle, args.track_length)
    rng = np.random.default_rng(np.random.SeedSequence(args.seed))
    _, truth = add_streaks(exposure, [model], [track], float(gain), rng, noise=not args.no_noise)
    with atomic_path(args.output, args.overwrite) as tmp:
        exposure.hdus.writeto(tmp, overwrite=True)
    row = truth[0]
    print(f"wrote {args.output}: streak from ({row['x0']:.1f}, {row['y0']:.1f}) to "
          f"({row['x1']:.1f}, {row['y1']:.1f}), {row['charge_in_image_e']:.4g} e- injected",
          file=sys.stderr)


def build_parser():
    """The ``inject`` argument parser with every subcommand."""
    parser = _Parser(
        prog="inject", description="Realistic satellite streaks for Rubin/LSSTCam images.")
    parser.add_argument("--version", action="version", version=f"inject {__version__}")
    parser.add_argument("--traceback", action="store_true",
                        help="show the full traceback on errors")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_profile_parser(sub)
    _add_simulate_parser(sub)
    _add_add_streak_parser(sub)
    from .masking.cli_evaluate import add_evaluate_parser
    from .masking.run import add_mask_parser

    add_mask_parser(sub)
    add_evaluate_parser(sub)
    from .cli_focalplane import add_focalplane_parser

    add_focalplane_parser(sub)
    return parser


def main(argv=None):
    """Entry point of the ``inject`` console script; returns the exit status."""
    parser = build_parser()
    # Overrides (key.path=value) may come after options: argparse leaves those as extras.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if not hasattr(args, "overrides") or any("=" not in item for item in extra):
            # The subcommand's error, as argparse itself would word it.
            _usage_error(f"{parser.prog} {args.command}",
                         f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = list(args.overrides) + extra
    try:
        args.func(args)
    except InjectError as err:
        if args.traceback:
            raise
        # One line, whatever the library said.
        print(f"inject {args.command}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("inject: interrupted", file=sys.stderr)
        return 130
    return 0
