"""Command-line interface: ``inject profile``, ``inject simulate``, ...

Each subcommand parses its options, calls the engine and prints or writes the result. Any
:class:`~inject.errors.InjectError` becomes a one-line message on stderr and exit status 2
(``--traceback``, before or after the subcommand, shows the full stack instead); so do
argparse's usage errors (without the usage block: ``inject simulate --help`` shows it).
Warnings about implausible values (:class:`~inject.errors.InputWarning`) are one line too.
SIGINT, SIGTERM and SIGHUP stop a command cleanly (:mod:`inject.signals`: no temporary or
half-moved file is left) with exit status 128 + the signal's number; a closed pipe on stdout
(``inject profile --json | head``) ends it quietly, as Unix tools do.
"""
import argparse
import json
import os
import sys
import warnings

from inject import __version__
from inject.errors import InjectError, InputError, InputWarning, OrbitWarning
from inject.validate import check


def _one_line(text):
    """``text`` with every run of whitespace (newlines included) as one space."""
    return " ".join(str(text).split())


def _usage_error(prog, message):
    """Exit with status 2 (argparse's, for usage errors) after ``PROG: error: MESSAGE``."""
    print(f"{prog}: error: {_one_line(message)}", file=sys.stderr)
    sys.exit(2)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, except where there is none to show (None,
    False for a flag, an empty list)."""

    def _get_help_string(self, action):
        default = action.default
        if default is None or default is False or default == [] or default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, exit status 2.

    argparse prints the whole usage block before the error; that block is what ``--help``
    is for. Sub-parsers are of the same class (``add_subparsers`` uses the parent's), so
    their errors name the subcommand: ``inject simulate: error: argument --seed: ...``, and
    their help shows the defaults.
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        _usage_error(self.prog, message)


def _add_output_option(p, metavar, help=None):
    """``-o/--output/--out``: every subcommand accepts the three spellings."""
    p.add_argument("-o", "--output", "--out", dest="output", required=True, metavar=metavar,
                   help=help)


def _add_satellite_options(p):
    """Options describing one satellite and its geometry (shared by profile and add-streak)."""
    p.add_argument("--height", type=float, required=True, metavar="KM",
                   help="orbit height, km (100 or more)")
    p.add_argument("--zenith", type=float, default=0.0, metavar="DEG", help="zenith angle")
    p.add_argument("--phi", type=float, default=90.0, metavar="DEG",
                   help="velocity rotation angle, paper eq. 8 (90: along constant azimuth)")
    p.add_argument("--shape", choices=("box", "disk"), default="box", help="satellite shape")
    p.add_argument("--length", type=float, metavar="M",
                   help="box length along the motion (default: 7.25)")
    p.add_argument("--width", type=float, metavar="M",
                   help="box width across the motion (default: 2.65)")
    p.add_argument("--radius", type=float, metavar="M", help="disk radius (default: 1.0)")
    p.add_argument("--seeing", type=float, default=0.67, metavar="ARCSEC",
                   help="atmospheric FWHM (Kolmogorov unless --seeing-model), 0 for none")
    p.add_argument("--seeing-model", choices=("kolmogorov", "vonkarman"), default="kolmogorov",
                   help="atmospheric PSF")
    p.add_argument("--band", default="g", help="LSST filter: u g r i z y")
    p.add_argument("--mag", type=float, default=5.0,
                   help="stationary AB magnitude at --ref-range, face-on")
    p.add_argument("--ref-range", type=float, default=550.0, metavar="KM",
                   help="range at which --mag is given")
    p.add_argument("--pixel-scale", type=float, default=0.2, metavar="ARCSEC",
                   help="arcsec per pixel")


def _add_profile_parser(sub):
    p = sub.add_parser("profile", help="streak profile of one satellite in one geometry",
                       description="Geometry, photometry and cross-section of one streak.")
    _add_satellite_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run_profile)


def _model_from_args(args, pixel_scale=None, pixel_scale_name="--pixel-scale"):
    """The :class:`~inject.streak.StreakModel` of the satellite options, their ranges checked
    (:data:`inject.validate.RANGES`) before any profile is built."""
    from inject.instrument import LSST
    from inject.profile import Seeing
    from inject.streak import StreakModel

    model = StreakModel(  # its own domain checks first (NaN, <= 0, zenith >= 90, band)
        height_km=args.height, zenith_deg=args.zenith, phi_deg=args.phi,
        shape=_shape_from_args(args), mag=args.mag, band_name=args.band,
        seeing=Seeing(args.seeing, args.seeing_model),
        telescope=LSST.with_pixel_scale(pixel_scale or args.pixel_scale),
        ref_range_km=args.ref_range)
    for quantity, option in (("height", "--height"), ("zenith", "--zenith"), ("phi", "--phi"),
                             ("mag", "--mag"), ("seeing", "--seeing"),
                             ("ref_range", "--ref-range")):
        check(quantity, getattr(args, option[2:].replace("-", "_")), option)
    check("pixel_scale", pixel_scale or args.pixel_scale, pixel_scale_name)
    option = "--radius" if args.shape == "disk" else "--length/--width"
    check("size", round(model.shape.size_m, 3), f"{option} (largest extent, m)")
    return model


def _shape_from_args(args):
    from inject.satellite import Box, Disk

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


#: ``(key, label, unit, format[, scale])``; format None: the value as given (the inputs are
#: echoed with every digit, so 89.999999 does not print as 90.00).
_TABLE_ROWS = (
    ("height_km", "orbit height", "km", None),
    ("zenith_deg", "zenith angle", "deg", None),
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
        text = repr(float(value)) if fmt is None else fmt.format(value)
        print(f"{label:<28s} {text:>14s}  {unit}")


def _add_simulate_parser(sub):
    p = sub.add_parser("simulate", help="simulate one CCD with streaks from a scene file",
                       description="Simulate one LSSTCam-like CCD from a YAML scene file.")
    p.add_argument("scene", help="YAML scene file (see sample_fields/)")
    _add_output_option(p, "OUT.fits", "the FITS file (IMAGE, MASK, VARIANCE, STREAK_MODEL, "
                                      "TRUTH)")
    p.add_argument("--exr", metavar="OUT.exr", help="also write OpenEXR")
    p.add_argument("--png", metavar="OUT.png",
                   help="also write a quicklook picture: PNG, or the format its extension "
                        "names (.jpg, .pdf, .svg, ...)")
    p.add_argument("--truth", metavar="OUT.csv", help="also write the truth table as CSV")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    # default=[]: without it argparse lists this optional positional as "required".
    p.add_argument("overrides", nargs="*", default=[], metavar="key.path=value",
                   help="override scene keys, e.g. satellites.0.mag=6 detector.nx=512 "
                        "detector.ny=512 (the last of a key given twice wins)")
    p.set_defaults(func=run_simulate)


def run_simulate(args):
    """The ``inject simulate`` command: every output is written, or none (all-or-nothing)."""
    import os

    from inject.config import parse_scene
    from inject.schema import apply_overrides, load_scene_file
    from inject.io.atomic import output_group
    from inject.io.fits import write_exposure
    from inject.orbits.tracks import resolve_ccd_orbits
    from inject.scene import simulate

    if args.png:
        from inject.io.quicklook import quicklook_format

        quicklook_format(args.png)  # before the work
    raw = apply_overrides(load_scene_file(args.scene), args.overrides)
    scene = parse_scene(resolve_ccd_orbits(raw))  # orbit: satellites -> pixel tracks
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
            from inject.instrument import LSST
            from inject.camera.wcs import pointing_wcs

            wcs = pointing_wcs(scene.pointing, scene.detector.shape, LSST.pixel_scale_arcsec)
        result = simulate(scene, wcs=wcs)
        write_exposure(args.output, scene, result, scene.detector.gain,
                       wcs_header=None if wcs is None else wcs.to_header(relax=True),
                       overwrite=args.overwrite)
        if args.exr:
            from inject.io.exr import write_exr

            write_exr(args.exr, scene, result, overwrite=args.overwrite)
        if args.png:
            from inject.io.quicklook import write_quicklook

            write_quicklook(args.png, result, overwrite=args.overwrite)
        if args.truth:
            from inject.io.fits import write_truth_csv

            write_truth_csv(args.truth, result.truth, overwrite=args.overwrite)
    for path in outputs.values():
        print(f"wrote {path}", file=sys.stderr)


def _add_add_streak_parser(sub):
    p = sub.add_parser(
        "add-streak", help="inject a streak into an existing FITS image",
        description="Inject one streak into a FITS image: any 2-D image HDU, or an LSST "
                    "MaskedImage/Exposure (IMAGE, MASK, VARIANCE found by EXTTYPE as afw does; "
                    "MASK gets a STREAK plane, VARIANCE the streak's Poisson variance). Pixels "
                    "the streak does not reach are written back unchanged in the file's own "
                    "storage (integers stay integers, compressed HDUs are compressed "
                    "losslessly). The input is never modified.")
    p.add_argument("input", metavar="IN.fits")
    _add_output_option(p, "OUT.fits", "the copy with the streak")
    _add_satellite_options(p)
    track = p.add_argument_group(
        "track (array pixels: pixel (0, 0) is the centre of the first pixel of the stored "
        "array; with --parent, LSST parent pixels: array + xy0, xy0 from the LTV1/2 cards)")
    track.add_argument("--x0", type=float, help="start x (or use --ra0/--dec0 with a WCS)")
    track.add_argument("--y0", type=float, help="start y")
    track.add_argument("--parent", action="store_true",
                       help="--x0/--y0 are LSST parent pixels (afw's xy0 convention)")
    track.add_argument("--ra0", type=float, metavar="DEG", help="start RA (needs a WCS)")
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
                   help="add the exact model, no Poisson noise (VARIANCE left as it is)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.fits")
    p.set_defaults(func=run_add_streak)


def run_add_streak(args):
    import os

    import numpy as np

    from inject.addstreak import add_streaks
    from inject.trajectory import Track
    from inject.io.atomic import check_writable
    from inject.io.reader import read_exposure
    from inject.maskplanes import FLAG_OFF_IMAGE, FLAG_SATURATED

    if os.path.exists(args.output) and os.path.samefile(args.input, args.output):
        raise InputError("-o", args.output, "must differ from the input (it is never modified)")
    for option, quantity in (("x0", "track.x0"), ("y0", "track.y0"), ("angle", "track.angle"),
                             ("track_length", "track.length"), ("ra0", "pointing.ra"),
                             ("dec0", "pointing.dec"), ("gain", "gain"), ("seed", "seed")):
        value = getattr(args, option)
        if value is not None:
            check(quantity, value, f"--{option.replace('_', '-')}")
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
        args.x0, args.y0 = (float(v) for v in wcs.all_world2pix(args.ra0, args.dec0, 0))
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
    model = _model_from_args(args, pixel_scale,
                             "--pixel-scale" if pixel_scale is None else "the WCS's pixel scale")
    track = Track(args.x0, args.y0, args.angle, args.track_length)
    rng = np.random.default_rng(np.random.SeedSequence(args.seed))
    _, truth = add_streaks(exposure, [model], [track], float(gain), rng, noise=not args.no_noise)
    exposure.write(args.output, args.overwrite)
    row = truth[0]
    x0, y0 = exposure.xy0
    parent = f" (array pixels; LSST parent = array + ({x0}, {y0}))" if (x0, y0) != (0, 0) else ""
    print(f"wrote {args.output}: streak from ({row['x0']:.1f}, {row['y0']:.1f}) to "
          f"({row['x1']:.1f}, {row['y1']:.1f}){parent}, {row['charge_in_image_e']:.4g} e- "
          f"injected", file=sys.stderr)
    if row["flags"] & FLAG_OFF_IMAGE:
        print("inject add-streak: warning: the track misses the image: 0 e- injected "
              "(TRUTH flags = 1)", file=sys.stderr)
    if row["flags"] & FLAG_SATURATED:
        print("inject add-streak: warning: the streak saturates the integer image (clipped "
              "at the ADC limit; SAT set in MASK if there is one)", file=sys.stderr)


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
    from inject.cli.evaluate import add_evaluate_parser
    from inject.cli.mask import add_mask_parser

    add_mask_parser(sub)
    add_evaluate_parser(sub)
    from inject.cli.focalplane import add_focalplane_parser

    add_focalplane_parser(sub)
    from inject.cli.satellite_pass import add_pass_parser

    add_pass_parser(sub)
    for command in sub.choices.values():
        # After the subcommand too; SUPPRESS: not given there, the top-level value stands.
        command.add_argument("--traceback", action="store_true", default=argparse.SUPPRESS,
                             help="show the full traceback on errors")
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None,
                  command="inject"):
    """Input warnings as one line, ``inject CMD: warning: ...`` (others as Python shows them)."""
    if issubclass(category, (InputWarning, OrbitWarning)):
        print(f"{command}: warning: {_one_line(message)}", file=sys.stderr)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def _quiet_broken_pipe():
    """After EPIPE on stdout: point it at /dev/null, so the interpreter's final flush does not
    fail again (the recipe of Python's signal documentation)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout replaced (tests) or closed
        pass


def main(argv=None):
    """Entry point of the ``inject`` console script; returns the exit status."""
    import signal

    from inject.signals import Stopped, handling

    command = "inject"
    try:
        # The stop signals are handled from the start: a Ctrl-C while the parser imports the
        # engine is a clean stop too, not a traceback.
        with handling():
            parser = build_parser()
            # Overrides (key.path=value) may come after options: argparse leaves them as extras.
            args, extra = parser.parse_known_args(argv)
            command = f"inject {args.command}"
            if extra:
                if not hasattr(args, "overrides") or any("=" not in item for item in extra):
                    # The subcommand's error, as argparse itself would word it.
                    _usage_error(command, f"unrecognized arguments: {' '.join(extra)}")
                args.overrides = list(args.overrides) + extra
            return _run(args, command)
    except BrokenPipeError:
        # The reader went away (| head): stop quietly, with the status of a process killed by
        # SIGPIPE, as Unix tools do.
        _quiet_broken_pipe()
        return 128 + signal.SIGPIPE
    except Stopped as stop:
        print(f"{command}: {stop}; no output left half-written", file=sys.stderr)
        return stop.exit_status
    except KeyboardInterrupt:  # raised by Python's own handler, outside inject.signals
        print(f"{command}: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT


def _run(args, command):
    """Run the subcommand; an :class:`InjectError` is one line and status 2."""
    import functools

    try:
        with warnings.catch_warnings():
            warnings.showwarning = functools.partial(_show_warning, command=command)
            args.func(args)
            sys.stdout.flush()  # a closed pipe shows here, where main catches it
    except InjectError as err:
        if args.traceback:
            raise
        # One line, whatever the library said.
        print(f"{command}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    return 0
