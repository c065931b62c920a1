"""``inject simulate``: one CCD with streaks from a YAML scene file, written as FITS (and
optionally OpenEXR, a quicklook picture and the truth table as CSV), all or nothing."""
import logging
import os

from inject.cli.options import add_output_option
from inject.errors import InputError
from inject.instrument import LSST
from inject.io.atomic import output_group

log = logging.getLogger(__name__)


def add_simulate_parser(sub):
    """Register ``inject simulate`` on an argparse sub-parser collection."""
    p = sub.add_parser("simulate", help="simulate one CCD with streaks from a scene file",
                       description="Simulate one LSSTCam-like CCD from a YAML scene file.")
    p.add_argument("scene", help="YAML scene file (examples: the repository's sample_fields/)")
    add_output_option(p, "OUT.fits", "the FITS file (IMAGE, MASK, VARIANCE, STREAK_MODEL, "
                                     "TRUTH), named .fits, .fit or .fts")
    p.add_argument("--exr", metavar="OUT.exr", help="also write OpenEXR")
    p.add_argument("--png", metavar="OUT.png",
                   help="also write a quicklook picture: PNG, or the format its extension "
                        "names (.jpg, .pdf, .svg, ...)")
    p.add_argument("--truth", metavar="OUT.csv",
                   help="also write the truth table as CSV, and its tracks' vertices beside it "
                        "(OUT_vertices.csv)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    # default=[]: without it argparse lists this optional positional as "required".
    p.add_argument("overrides", nargs="*", default=[], metavar="key.path=value",
                   help="override scene keys, e.g. satellites.0.mag=6 detector.nx=512 "
                        "detector.ny=512 (the last of a key given twice wins)")
    p.set_defaults(func=run_simulate)


def run_simulate(args):
    """The ``inject simulate`` command: every output is written, or none (all-or-nothing)."""
    # The engine (GalSim, astropy, YAML): imported when the command runs, not for --help.
    from inject.config import parse_scene
    from inject.io.fits import check_fits_name, write_exposure
    from inject.orbits.tracks import resolve_ccd_orbits
    from inject.scene import simulate
    from inject.schema import apply_overrides, load_scene_file

    check_fits_name(args.output)  # before the work: a picture name never holds FITS
    if args.png:
        from inject.io.quicklook import quicklook_format

        quicklook_format(args.png)
    raw = apply_overrides(load_scene_file(args.scene), args.overrides)
    scene = parse_scene(resolve_ccd_orbits(raw))  # orbit: satellites -> pixel tracks
    outputs = {option: path for option, path in (("-o", args.output), ("--exr", args.exr),
                                                 ("--png", args.png), ("--truth", args.truth))
               if path}
    if args.truth:
        from inject.io.fits import vertices_csv_path

        outputs["--truth (vertices)"] = vertices_csv_path(args.truth)
    for option, path in outputs.items():
        if os.path.exists(path) and os.path.samefile(path, args.scene):
            raise InputError(option, path, "would replace the scene file")
    # The group checks every target before the work, and moves the finished files into place
    # together at its end: a failing EXR leaves no new FITS behind.
    with output_group(outputs.values(), args.overwrite):
        wcs = None
        if scene.pointing is not None:
            from inject.camera.wcs import pointing_wcs

            wcs = pointing_wcs(scene.pointing, scene.detector.shape, LSST.pixel_scale_arcsec)
        result = simulate(scene, wcs=wcs)
        write_exposure(args.output, scene, result, scene.detector.gain,
                       wcs_header=None if wcs is None else wcs.to_header(relax=True),
                       overwrite=args.overwrite, digest=False)
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
        log.info("wrote %s", path)
