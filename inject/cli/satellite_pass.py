"""``inject pass``: a satellite (TLE or circular orbit) seen from the site during one exposure,
and the CCDs its apparent track crosses."""
import json
import math
import sys
import warnings

from inject.errors import InputError
from inject.io.atomic import atomic_path, check_writable

# ``inject --help`` imports this module: NumPy, the orbits (astropy, SGP4), the camera layout
# and the streak model are imported inside the functions that use them.


def add_pass_parser(sub):
    p = sub.add_parser(
        "pass", help="where a satellite (TLE or orbit) crosses the focal plane in an exposure",
        description="A satellite seen from the site (Rubin by default) during the exposure "
                    "that starts at --time, the telescope tracking (ra, dec) sidereally: "
                    "geometric alt/az and range, nadir angle and phi, angular speed across "
                    "the star field, sunlit or in Earth's shadow, and its apparent position "
                    "on the focal plane (mm), at least every second; the science CCDs the "
                    "track crosses.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--tle", metavar="FILE", help="two TLE lines, optionally after a name line")
    src.add_argument("--orbit", metavar="KEY=VALUE,...",
                     help="a circular orbit: height (km), inclination, raan, mean_anomaly "
                          "(deg, argument of latitude at epoch), epoch (UTC; default --time), "
                          "e.g. height=550,inclination=53,raan=10,mean_anomaly=40")
    p.add_argument("--time", required=True, metavar="UTC",
                   help="exposure start, ISO 8601 UTC (e.g. 2026-06-15T23:30:00)")
    p.add_argument("--exptime", required=True, type=float, metavar="S", help="exposure, s")
    p.add_argument("--ra", required=True, type=float, metavar="DEG", help="boresight RA, ICRS")
    p.add_argument("--dec", required=True, type=float, metavar="DEG", help="boresight Dec, ICRS")
    p.add_argument("--rotation", type=float, default=0.0, metavar="DEG",
                   help="rotSkyPos: position angle of focal-plane +y, north through east")
    p.add_argument("--site", metavar="LAT,LON,M",
                   help="geodetic latitude, longitude (deg) and height (m), given with '=' "
                        "as it starts with - (default: Rubin, --site=-30.2446,-70.7494,2647)")
    p.add_argument("--shadow-atmosphere", type=float, default=0.0, metavar="KM",
                   help="height of the grazing atmosphere taken to block the Sun in Earth's "
                        "shadow (0: the solid WGS84 Earth)")
    p.add_argument("--json", action="store_true", help="one JSON object instead of a table")
    p.add_argument("--plot", metavar="OUT.png",
                   help="the track on the focal plane, and range, speed, FWHM and peak along "
                        "it: PNG, or the format its extension names (.jpg, .pdf, .svg, ...)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --plot file")
    p.set_defaults(func=run_pass)


def parse_orbit_option(text, time):
    """An :class:`~inject.orbits.passes.Orbit` from ``--orbit`` text ``key=value,...`` (through
    :func:`inject.orbits.passes.orbit_from_spec`, as a scene's ``orbit:``)."""
    from inject.orbits.passes import CIRCULAR_ORBIT_KEYS, orbit_from_spec
    values = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in CIRCULAR_ORBIT_KEYS:
            raise InputError("--orbit", item, f"each item must be KEY=VALUE with KEY one of "
                                              f"{', '.join(CIRCULAR_ORBIT_KEYS)}")
        if key in values:
            raise InputError("--orbit", text, f"{key} given twice")
        values[key] = value.strip()
    return orbit_from_spec(values, time, "--orbit"), values


def pass_report(orbit, exposure, pointing, site, atmosphere_km=0.0, spec=None):
    """The ``inject pass`` result.

    Returns
    -------
    report : dict
        The documented keys (``in_field``, ``message``, ``detectors``: the CCDs the track
        crosses while sunlit, those with a streak, ``samples``) and more
        (``detectors_in_shadow``: CCDs crossed only in Earth's shadow).
    p : inject.orbits.passes.Pass
        The pass at the report's samples (1 s apart, with the middle).
    track : tuple
        ``(dense, x_mm, y_mm, runs)``: the pass every :data:`~inject.orbits.passes.TRACK_STEP_S` and
        its focal-plane polylines (:func:`inject.orbits.passes.track_runs`), what ``detectors`` is
        computed from.
    """
    from inject.camera import layout as fp
    from inject.orbits.passes import TRACK_STEP_S, compute_pass, track_runs
    p = compute_pass(orbit, exposure, pointing, site, atmosphere_km=atmosphere_km)
    dense = compute_pass(orbit, exposure, pointing, site, step_s=TRACK_STEP_S,
                         check_epoch=False, atmosphere_km=atmosphere_km)
    xd, yd, runs = track_runs(dense)

    def crossed(parts):
        reached = set()
        for run in parts:
            reached.update(fp.ccds_reached(xd[run], yd[run]))
        return reached

    # Only sunlit parts leave a streak; the CCDs listed are those inject focalplane renders
    # for this pass (its plan: where the footprint of the default satellite's sunlit streak
    # reaches), CCDs crossed only in Earth's shadow apart.
    lit = crossed(track_runs(dense, lit_only=True)[2])
    if spec is not None and lit:
        lit = set(_planned_ccds(spec, exposure, pointing, site, atmosphere_km))
    detectors = [c.name for c in sorted(lit, key=lambda c: c.id)]
    dark = [c.name for c in sorted(crossed(runs) - lit, key=lambda c: c.id)]
    in_field = bool(detectors or dark)
    message = p.message
    if p.in_field and not in_field:
        message = "enters the field but crosses no science CCD (a gap or outside the CCDs)"
    elif in_field and not p.in_field:  # the disc test on 1 s chords missed a corner cut
        message = "crosses the field"
    if dark and not detectors:
        message = "crosses the CCDs in Earth's shadow: no streak"
    report = p.to_dict()
    x, y = p.focal_mm()
    samples = report["samples"]
    for row, xi, yi in zip(samples, x, y):
        row["x_mm"] = float(xi) if math.isfinite(xi) else None
        row["y_mm"] = float(yi) if math.isfinite(yi) else None
    report.update(in_field=in_field, message=message, detectors=detectors,
                  detectors_in_shadow=dark, samples=samples)
    return report, p, (dense, xd, yd, runs)


def _planned_ccds(spec, exposure, pointing, site, atmosphere_km):
    """The CCDs :func:`inject.exposure.plan.make_plan` renders for this pass: a focal-plane
    scene of the default satellite (the paper's box, mag 5 at 550 km) on this orbit."""
    from inject.config import DEFAULT_SCENE
    from inject.exposure.plan import make_plan
    from inject.exposure.scene import parse_focal_scene

    sat = {k: v for k, v in DEFAULT_SCENE["satellites"][0].items()
           if k in ("shape", "mag", "ref_range")}
    raw = {"time": exposure.start.utc.isot, "exptime": exposure.exptime_s,
           "pointing": pointing.as_mapping(), "shadow_atmosphere_km": atmosphere_km,
           "site": {"lat": site.lat_deg, "lon": site.lon_deg, "height": site.height_m},
           "satellites": [{**sat, "orbit": spec}]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the pass above has said what there is to say
        return make_plan(parse_focal_scene(raw)).streak_ccds()


def run_pass(args):
    from inject.camera.wcs import Pointing
    from inject.orbits.passes import Exposure, orbit_from_spec, site_from_spec
    from inject.validate import RANGES, check_pointing, parse_time

    time = parse_time(args.time, "--time")
    if args.tle is not None:
        spec = {"tle": args.tle}
        orbit = orbit_from_spec(spec, time, "--tle")
    else:
        orbit, spec = parse_orbit_option(args.orbit, time)
    site = site_from_spec(args.site, "--site")
    exposure = Exposure(time, RANGES["exptime"].check(args.exptime, "--exptime"))
    pointing = Pointing(*check_pointing({"ra": args.ra, "dec": args.dec,
                                         "rotation": args.rotation},
                                        {"ra": "--ra", "dec": "--dec", "rotation": "--rotation"}))
    if args.plot:
        from inject.io.quicklook import quicklook_format

        # Fail before the work: a data name (.fits, .csv, ...) or an unwritable path.
        plot_format = quicklook_format(args.plot, "the plot")
        check_writable(args.plot, args.overwrite)
    atmosphere = RANGES["shadow_atmosphere_km"].check(args.shadow_atmosphere,
                                                      "--shadow-atmosphere")
    report, p, track = pass_report(orbit, exposure, pointing, site, atmosphere, spec)
    if args.plot:
        write_plot(args.plot, report, p, track, args.overwrite, plot_format)
    if args.json:
        json.dump(report, sys.stdout)
        sys.stdout.write("\n")
        return
    print(f"{report['satellite']}: {report['message']}")
    print(f"detectors: {', '.join(report['detectors']) or 'none'}")
    if report["detectors_in_shadow"]:
        print(f"crossed in Earth's shadow only (no streak): "
              f"{', '.join(report['detectors_in_shadow'])}")
    print(f"{'t_s':>5} {'utc':23} {'alt':>6} {'az':>7} {'range_km':>9} {'nadir':>6} "
          f"{'phi':>7} {'rad/s':>8} {'sunlit':>6} {'x_mm':>8} {'y_mm':>8}")
    for s in report["samples"]:
        def num(v, fmt):
            return format(v, fmt) if v is not None else "-".rjust(len(format(0.0, fmt)))
        print(f"{s['t_s']:5.1f} {s['utc']:23} {s['alt_deg']:6.2f} {s['az_deg']:7.2f} "
              f"{s['range_km']:9.1f} {num(s['nadir_angle_deg'], '6.2f')} "
              f"{num(s['phi_deg'], '7.2f')} {s['angular_speed_rad_s']:8.5f} "
              f"{'yes' if s['sunlit'] else 'no':>6} {num(s['x_mm'], '8.2f')} "
              f"{num(s['y_mm'], '8.2f')}")


def streak_along(p, idx, mag_ref=5.0):
    """FWHM (arcsec) and peak surface brightness (e-/px) of the paper's satellite
    (:class:`~inject.streak.StreakModel` defaults: 7.25 m x 2.65 m box, ``mag_ref`` g at 550 km)
    at samples ``idx`` of a pass: each sample's height, zenith (90 - alt) and phi, with the
    pass's exact range and angular speed."""
    import numpy as np

    from inject.streak import StreakModel

    fwhm, peak = [], []
    for i in idx:
        if not (p.alt_deg[i] > 0 and np.isfinite(p.phi_deg[i])):
            fwhm.append(np.nan)
            peak.append(np.nan)
            continue
        m = StreakModel(height_km=float(p.height_km[i]), zenith_deg=float(90 - p.alt_deg[i]),
                        phi_deg=float(p.phi_deg[i]), mag=mag_ref,
                        range_km=float(p.range_km[i]),
                        angular_speed_rad_s=float(p.angular_speed_rad_s[i]))
        fwhm.append(m.fwhm_arcsec)
        peak.append(m.peak_e_per_px * p.sun_fraction[i])  # the penumbra dims it
    return np.array(fwhm), np.array(peak)


def write_plot(path, report, p, track, overwrite=False, file_format="png"):
    """The track on the focal-plane outline (crossed CCDs shaded) and panels of range, angular
    speed, FWHM and peak surface brightness along the exposure, as ``file_format`` (a
    matplotlib format: :func:`inject.io.quicklook.quicklook_format` of the name)."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from inject.camera import layout as fp

    dense, xd, yd, runs = track
    fig = Figure(figsize=(11, 6))
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0.05, 0.08, 0.45, 0.84])
    crossed, dark = set(report["detectors"]), set(report["detectors_in_shadow"])
    for c in fp.CCDS:
        x0, x1, y0, y1 = c.bounds_mm()
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, lw=0.4, ec="#4a5568",
                               fc="#f6ad55" if c.name in crossed else
                               "#cbd5e0" if c.name in dark else "none"))
    lit = dense.sun_fraction > 0
    for run in runs:
        xs, ys = xd[run[0]:run[-1] + 1], yd[run[0]:run[-1] + 1]
        sun = lit[run[0]:run[-1] + 1]
        # Solid where sunlit, dotted in Earth's shadow (each sample joins its neighbour on
        # the side of its own light, so the two lines meet at the shadow's edge).
        edge = sun | np.r_[sun[1:], False]
        ax.plot(np.where(edge, xs, np.nan), np.where(edge, ys, np.nan), color="#2b6cb0", lw=1.2)
        if (~sun).any():
            ax.plot(np.where(~sun, xs, np.nan), np.where(~sun, ys, np.nan), color="#718096",
                    lw=1.2, ls=":")
    x, y = p.focal_mm()
    ax.plot(x, y, "o", ms=2.5, color="#2b6cb0")
    ok = np.isfinite(x)
    if ok.any():
        i0 = np.flatnonzero(ok)[0]
        ax.annotate(f"t = {p.t_s[i0]:.0f} s", (x[i0], y[i0]), fontsize=7)
    xmin, xmax, ymin, ymax = fp.extent_mm()
    ax.set_xlim(xmin - 20, xmax + 20)
    ax.set_ylim(ymin - 20, ymax + 20)
    ax.set_aspect("equal")
    ax.set_xlabel("focal-plane x (mm)")
    ax.set_ylabel("focal-plane y (mm)")
    ax.set_title(f"{report['satellite']}: {report['message']}", fontsize=8)
    fwhm, peak = streak_along(p, range(len(p.t_s)))
    panels = ((p.range_km, "range (km)"), (np.degrees(p.angular_speed_rad_s), "speed (deg/s)"),
              (fwhm, "FWHM (arcsec)"), (peak, "peak (e-/px), paper's sat."))
    for k, (values, label) in enumerate(panels):
        pax = fig.add_axes([0.60, 0.08 + 0.22 * (3 - k), 0.37, 0.18])
        pax.plot(p.t_s, values, color="#2b6cb0", lw=1.0)
        pax.plot(np.where(p.sunlit, np.nan, p.t_s), values, color="#718096", lw=1.0, ls=":")
        pax.set_ylabel(label, fontsize=7)
        pax.tick_params(labelsize=6)
        if k < 3:
            pax.set_xticklabels([])
    pax.set_xlabel("t from exposure start (s); dotted: in Earth's shadow", fontsize=7)
    with atomic_path(path, overwrite) as tmp:
        fig.savefig(tmp, format=file_format, dpi=80)
