"""``inject profile``: geometry, photometry and cross-section of one streak, as a table or
one JSON object."""
import json
import sys

from inject.cli.options import add_satellite_options, model_from_args


def add_profile_parser(sub):
    """Register ``inject profile`` on an argparse sub-parser collection."""
    p = sub.add_parser("profile", help="streak profile of one satellite in one geometry",
                       description="Geometry, photometry and cross-section of one streak.")
    add_satellite_options(p)
    p.add_argument("--focus-offset", type=float, default=0.0, metavar="UM",
                   help="with --pupil rubin: the detector's shift from the design's focus "
                        "along the optical axis, micron (negative: towards the camera's last "
                        "lens; 0: focused at infinity)")
    p.add_argument("--sed", default="sun", metavar="SPEC",
                   help="with --pupil rubin: the satellite's spectrum the kernel is traced "
                        "over: sun, a blackbody temperature such as 4500K, or an AB colour "
                        "through LSST's bands such as g-r=0.6")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run_profile)


def run_profile(args):
    """The ``inject profile`` command (``args`` from :func:`add_profile_parser`)."""
    model = model_from_args(args)
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

#: Rows added with the traced pupil.
_PUPIL_ROWS = (
    ("field_angle_deg", "field angle", "deg", None),
    ("field_position_angle_deg", "field radius from motion", "deg", "{:.0f}"),
    ("focus_offset_um", "detector from design focus", "um", None),
    ("sed_temperature_k", "spectrum as a blackbody", "K", "{:.1f}"),
    ("pupil_transmission", "light vs a star there", "", "{:.4f}"),
)


def _print_table(result):
    print(f"{'defocus kernel':<28s} {result['pupil']:>14s}")
    rows = _TABLE_ROWS + (_PUPIL_ROWS if result["pupil"] != "annulus" else ())
    for key, label, unit, fmt, *scale in rows:
        value = result[key] * (scale[0] if scale else 1)
        text = repr(float(value)) if fmt is None else fmt.format(value)
        print(f"{label:<28s} {text:>14s}  {unit}")
