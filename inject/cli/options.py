"""Options that several commands share: ``-q``/``-v`` of every command, the output option of
every command that writes one file, the options of the resumable runs on a batch system
(``inject focalplane``, ``inject survey --render``), and the options describing one satellite
(``inject profile``, ``inject add-streak``) with the :class:`~inject.streak.StreakModel` they
make."""
import argparse
import os

from inject.errors import InputError

# ``inject --help`` imports this module: what the satellite options check (NumPy) is imported
# inside the function that checks them.


def add_verbosity_options(p, after_command=False):
    """``-q/--quiet`` and ``-v/--verbose`` (:mod:`inject.cli.logs`), which exclude each other.

    ``after_command``: the copy every subcommand takes, so that they may follow its name
    too; not given there, the top-level value stands (the default is SUPPRESS).
    """
    default = argparse.SUPPRESS if after_command else False
    group = p.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true", default=default,
                       help="show warnings and errors only (no progress, no reports)")
    group.add_argument("-v", "--verbose", action="store_true", default=default,
                       help="show debugging messages too")


def add_output_option(p, metavar, help=None):
    """``-o/--output/--out``: every subcommand accepts the three spellings."""
    p.add_argument("-o", "--output", "--out", dest="output", required=True, metavar=metavar,
                   help=help)


def add_resume_options(p):
    """``--verify`` and ``--no-lock``: how a resumable run trusts its finished files and
    shares its output folder."""
    p.add_argument("--verify", action="store_true",
                   help="on a rerun, hash every finished file again and redo those whose "
                        "SHA-256 differs from the manifest's (default: trust a file whose size "
                        "and modification time are those the manifest recorded)")
    p.add_argument("--no-lock", action="store_true",
                   help="do not lock the output folder's manifest (for a file system mounted "
                        "without locking, e.g. Lustre's noflock or NFS's nolock): this run "
                        "must then be the only one writing there (no parallel --job slices)")


#: The SLURM job-array variables that give ``--job`` and ``--njobs`` their defaults.
SLURM_ARRAY = ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_MIN", "SLURM_ARRAY_TASK_COUNT")


def slurm_slice(args, environ=None):
    """Default ``args.job`` and ``args.njobs`` from a SLURM job array: the task's place in the
    array (``SLURM_ARRAY_TASK_ID - SLURM_ARRAY_TASK_MIN``, over ``SLURM_ARRAY_TASK_STEP``
    when the array steps) of ``SLURM_ARRAY_TASK_COUNT``. Options given win: nothing is
    changed if either was given, or outside an array.

    Returns
    -------
    str or None
        What was set and from what, for the run's log; None if nothing was.

    Raises
    ------
    InputError
        The array's indices are not an evenly stepped range (``--array=1,5,9`` is; ``1,2,7``
        is not): give ``--job`` and ``--njobs``.
    """
    environ = os.environ if environ is None else environ
    if args.job is not None or args.njobs is not None or \
            not all(environ.get(name) for name in SLURM_ARRAY):
        return None
    try:
        task, first, count = (int(environ[name]) for name in SLURM_ARRAY)
        step = int(environ.get("SLURM_ARRAY_TASK_STEP") or 1)
    except ValueError:
        raise InputError("SLURM_ARRAY_TASK_ID", environ.get("SLURM_ARRAY_TASK_ID"),
                         "the SLURM_ARRAY_TASK_* variables are not all integers; give --job "
                         "and --njobs") from None
    job, off = divmod(task - first, max(step, 1))
    if off or not 0 <= job < count:
        raise InputError("SLURM_ARRAY_TASK_ID", task,
                         f"not one of {count} tasks from {first} in steps of {step} (an "
                         f"array of uneven indices); give --job and --njobs")
    args.job, args.njobs = job, count
    return f"--job {job} --njobs {count} from the SLURM job array (SLURM_ARRAY_TASK_ID={task}, " \
           f"SLURM_ARRAY_TASK_MIN={first}, SLURM_ARRAY_TASK_COUNT={count})"


def add_satellite_options(p):
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
    p.add_argument("--pupil", choices=("annulus", "rubin"), default="annulus",
                   help="defocus kernel: the ideal annulus, or a point at the range traced "
                        "through Rubin's optics for --band (batoid)")
    p.add_argument("--field-angle", type=float, default=0.0, metavar="DEG",
                   help="with --pupil rubin: angle of the streak from the optical axis (0-2.05)")
    p.add_argument("--field-position-angle", type=float, default=0.0, metavar="DEG",
                   help="with --pupil rubin: direction of the outward field radius, deg "
                        "counter-clockwise from the direction of motion (0: moving outward "
                        "along the radius, 90: across it)")


def _sed_temperature(text, pupil):
    """``--sed``: ``sun``, a temperature ``4500K`` or a colour ``g-r=0.6``, as a blackbody
    temperature, K (:func:`inject.config.parse_sed`'s forms)."""
    from inject.optics import SUN_TEMPERATURE_K, check_sed_temperature, colour_temperature

    text = str(text).strip()
    if text == "sun":
        return SUN_TEMPERATURE_K
    if pupil != "rubin":
        raise InputError("--sed", text, "only applies to --pupil rubin (the annulus is the "
                                        "same at every wavelength)")
    colour, equals, value = text.partition("=")
    try:
        number = float(value if equals else text[:-1] if text[-1:] in ("k", "K") else "x")
    except ValueError:
        raise InputError("--sed", text, "give sun, a temperature such as 4500K or a colour "
                                        "such as g-r=0.6") from None
    if equals:
        blue, _, red = colour.partition("-")
        return colour_temperature(blue.strip(), red.strip(), number)
    return check_sed_temperature(number)


def model_from_args(args, pixel_scale=None, pixel_scale_name="--pixel-scale"):
    """The :class:`~inject.streak.StreakModel` of the satellite options, their ranges checked
    (:data:`inject.validate.RANGES`) before any profile is built."""
    from inject.instrument import LSST
    from inject.optics import FIELD_MAX_DEG, FOCUS_MAX_UM
    from inject.profile import Seeing  # GalSim: when a command runs, not for --help
    from inject.streak import StreakModel
    from inject.validate import check

    if not 0 <= args.field_angle <= FIELD_MAX_DEG:  # also NaN
        raise InputError("--field-angle", args.field_angle,
                         f"must be within [0, {FIELD_MAX_DEG}] deg (LSSTCam's CCDs reach 2.048)")
    focus = getattr(args, "focus_offset", 0.0)  # inject profile's
    if not abs(focus) <= FOCUS_MAX_UM or (focus and args.pupil != "rubin"):
        raise InputError("--focus-offset", focus,
                         f"must be within [-{FOCUS_MAX_UM:g}, {FOCUS_MAX_UM:g}] micron"
                         if args.pupil == "rubin" else
                         "only applies to --pupil rubin (the annulus is the design's focus)")
    sed = _sed_temperature(getattr(args, "sed", "sun"), args.pupil)  # inject profile's
    model = StreakModel(  # its own domain checks first (NaN, <= 0, zenith >= 90, band)
        height_km=args.height, zenith_deg=args.zenith, phi_deg=args.phi,
        shape=shape_from_args(args), mag=args.mag, band_name=args.band,
        seeing=Seeing(args.seeing, args.seeing_model),
        telescope=LSST.with_pixel_scale(pixel_scale or args.pixel_scale),
        ref_range_km=args.ref_range, pupil=args.pupil, field_angle_deg=args.field_angle,
        field_position_angle_deg=args.field_position_angle, focus_offset_um=focus,
        sed_temperature_k=sed)
    if args.pupil == "annulus" and (args.field_angle != 0 or args.field_position_angle != 0):
        raise InputError("--field-angle/--field-position-angle",
                         (args.field_angle, args.field_position_angle),
                         "only apply to --pupil rubin (the annulus is the same everywhere)")
    for quantity, option in (("height", "--height"), ("zenith", "--zenith"), ("phi", "--phi"),
                             ("mag", "--mag"), ("seeing", "--seeing"),
                             ("ref_range", "--ref-range")):
        check(quantity, getattr(args, option[2:].replace("-", "_")), option)
    check("pixel_scale", pixel_scale or args.pixel_scale, pixel_scale_name)
    option = "--radius" if args.shape == "disk" else "--length/--width"
    check("size", round(model.shape.size_m, 3), f"{option} (largest extent, m)")
    return model


def shape_from_args(args):
    """The :class:`~inject.satellite.Box` or :class:`~inject.satellite.Disk` of ``--shape``
    and its sizes (defaults: the paper's satellite)."""
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
