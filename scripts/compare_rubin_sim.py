"""inject survey's plan against rubin_sim's ``Constellation.check_pointings``, same visits and TLEs.

Runs only where rubin_sim is importable (a separate environment: rubin_sim needs its own
dependencies; see docs/guides/survey.md, "Against rubin_sim"). Offline: skyfield's ephemeris
(de421) and Earth-orientation table come from the ``skyfield-data`` package, and rubin_sim's
``load`` is pointed at them.

The satellites are rubin_sim's own Starlink generators (``--constellation v1``: 4,408 in five
shells, ``v2``: 29,988 in nine), their epoch moved to the night's first visit (rubin_sim's
default, 2023-10-01, is more than two years before the sample night: SGP4 with its drag term
would move them by hundreds of km, and inject refuses TLEs 60 days off); the same TLE strings
go to both, inject reading them from a TLE file.

Per visit it counts:

* ``rubin_sim``: ``check_pointings``: satellites sunlit at the visit's start or end, above
  20 deg at its start or end, whose geometric track (skyfield, every ~2 s, no light time, no
  aberration) crosses the 1.75 deg circle (gnomonic radius) about the boresight. Its time is
  UT1: the visits' TAI starts are converted (as given, opsim's MJD would put every satellite
  37 s late, 280 km along its orbit).
* ``inject_rule``: the same rule on inject's exact passes (light time, aberration, every
  0.1 s): sunlit (any of the Sun's disc) at the start or end, above 20 deg at the start or
  end, the apparent track entering the 1.75 deg circle. Like with like: the difference with
  rubin_sim is the two codes' geometry and shadow (skyfield's spherical Earth against
  inject's ellipsoid and penumbra).
* ``inject_lit``: satellites whose *sunlit* apparent track enters the 1.75 deg circle (the
  sunlit part, not the start or end).
* ``inject_ccd``: inject survey's streaks: sunlit tracks crossing a science CCD (the gaps
  between CCDs and the corners beyond 1.75 deg included, the 2 s readout between snaps
  excluded).

With ``--literature`` rubin_sim is run as the literature ran it (``observationStartMJD``
given as it is, read as UT1 by rubin_sim; each visit lasting its ``visitTime``), and set
beside ``inject survey --rule rubin_sim`` (:mod:`inject.survey.rubin_rule`, which reads the
times the same way): the satellites both count and each alone, with each difference's
numbers (the track's closest approach, the altitudes and the shadow test at the start and
end, by skyfield and by inject), and the literature's table: streaked visits, streaks, total
length and pixels lost by the rule with a 300 px band against inject's physics (CCDs, gaps,
the masker's width).

``--constellation oneweb`` takes rubin_sim's ``oneweb_tles`` (6,372 at 1,200 km). Its shells
have 49 planes of 36 at 87.9 deg and 72 planes of 32 at 40 and 55 deg, the numbers of planes
and of satellites per plane swapped against OneWeb's filing (36 of 49 and 32 of 72,
sample_fields/constellation_oneweb.yaml), and every plane's satellites at the same mean
anomalies; the comparison gives both codes the same TLEs. ``--model YAML`` takes the
satellites' model (shape, mag, ref_range, lumos) from a constellation file instead of a
7.25 m x 2.65 m box of g = 5.0.

It prints the totals, the satellites both find and each alone (rubin_sim's satellites are
read from inside its loop), the visits where the counts agree, and the seconds per visit of
``check_pointings`` (all the visits in one call, as it is meant to be used) and of inject's
plan (:func:`inject.survey.plan.plan_visits`) on the same visits and satellites, one core.

Usage (in the rubin_sim environment)::

    python scripts/make_opsim_night.py -o out/night.db
    python scripts/compare_rubin_sim.py out/night.db --constellation v1 [--twilight]
        [--every N] [--csv out/compare_v1.csv]
    python scripts/compare_rubin_sim.py out/night.db --constellation oneweb --literature \
        --model sample_fields/constellation_oneweb.yaml
"""
import argparse
import csv
import functools
import os
import sys
import tempfile
import time
import warnings
from dataclasses import replace

#: rubin_sim's defaults: the circle's radius (deg) and the altitude limit (deg).
RADIUS_DEG = 1.75
ALT_LIMIT_DEG = 20.0


def need_rubin_sim():
    """rubin_sim's satellite module, or exit with a message saying how to get it."""
    try:
        from rubin_sim.satellite_constellations import sat_utils
        from skyfield_data import get_skyfield_data_path
    except ImportError as err:
        raise SystemExit(f"compare_rubin_sim.py: {err.name or err} is not importable here. "
                         f"Run it in a separate environment: python3.12 -m venv /tmp/rsvenv "
                         f"&& /tmp/rsvenv/bin/pip install rubin-sim skyfield-data && "
                         f"/tmp/rsvenv/bin/pip install -e . (docs/guides/survey.md)") from None
    return sat_utils, get_skyfield_data_path()


def tle_epoch(time):
    """A TLE epoch (YYDDD.dddddddd) of an astropy Time (UTC)."""
    dt = time.utc.datetime
    start = dt.replace(month=1, day=1, hour=0, minute=0, second=0, microsecond=0)
    return (dt.year % 100) * 1000 + (dt - start).total_seconds() / 86400.0 + 1.0


def make_tles(sat_utils, which, epoch):
    """rubin_sim's Starlink TLEs (``v1`` or ``v2``) with their epoch moved to ``epoch``."""
    make = {"v1": sat_utils.starlink_tles_v1, "v2": sat_utils.starlink_tles_v2,
            "oneweb": sat_utils.oneweb_tles}[which]
    original = sat_utils.create_constellation
    sat_utils.create_constellation = functools.partial(original, epoch=tle_epoch(epoch))
    try:
        return make()
    finally:
        sat_utils.create_constellation = original


def twilight(visits, site):
    """Which visits start with the Sun above -18 deg (astronomical twilight)."""
    import numpy as np
    from astropy.coordinates import AltAz, get_sun
    from astropy.time import Time

    t = Time([v.mjd_tai for v in visits], format="mjd", scale="tai")
    alt = get_sun(t).transform_to(AltAz(obstime=t, location=site.location)).alt.deg
    return np.asarray(alt) > -18.0


#: rubin_sim's length (rad) of each (visit index, satellite index) it counted.
RS_LENGTHS = {}


def found_key(caller):
    return int(caller["ob_indx"]), int(caller["sat_in"])


def rubin_sim_counts(sat_utils, data_path, tles, visits, literature=False):
    """check_pointings on the visits: (build seconds, seconds, n_streaks per visit,
    {(visit index, name)}, lengths per visit (deg)). ``literature``: the MJDs as given (read
    as UT1) and ``visitTime``; else the TAI starts converted to UT1 and the span of the
    snaps."""
    import numpy as np
    from astropy.time import Time
    from skyfield.api import Loader

    sat_utils.load = Loader(data_path, verbose=False)  # de421 from skyfield-data: offline
    found = set()
    original = sat_utils._streak_length
    RS_LENGTHS.clear()

    def recorded(*args):
        length = original(*args)
        if length > 0:  # the visit and satellite of rubin_sim's own loop
            caller = sys._getframe(1).f_locals
            found.add((int(caller["ob_indx"]), int(caller["sat_in"])))
            RS_LENGTHS[found_key(caller)] = float(length)
        return length

    build = time.perf_counter()
    constellation = sat_utils.Constellation(tles)
    build = time.perf_counter() - build
    sat_utils._cached = constellation  # for skyfield_track
    starts = Time([v.mjd_tai for v in visits], format="mjd", scale="tai")
    if literature:
        from inject.survey.rubin_rule import visit_span

        mjds = np.array([v.mjd_tai for v in visits])
        span = np.array([visit_span(v)[0] for v in visits])
    else:
        mjds = np.asarray(starts.ut1.mjd)
        span = np.array([v.snaps()[-1][0] + v.snaps()[-1][1] for v in visits])
    sat_utils._streak_length = recorded
    try:
        start = time.perf_counter()
        lengths, n = constellation.check_pointings(
            np.array([v.ra_deg for v in visits]), np.array([v.dec_deg for v in visits]),
            mjds, span)
        seconds = time.perf_counter() - start
    finally:
        sat_utils._streak_length = original
    names = [t.split("\n")[0] for t in tles]
    for (k, i) in list(RS_LENGTHS):
        RS_LENGTHS[(k, names[i])] = RS_LENGTHS.pop((k, i))
    return build, seconds, n, {(k, names[i]) for k, i in found}, lengths


def write_constellation(tles, folder, model=None):
    """The TLEs as an inject constellation file in ``folder``: the satellites' model from
    the constellation file ``model`` (its orbits left out), else a box of g = 5.0."""
    import yaml

    tle_file = os.path.join(folder, "satellites.tle")
    with open(tle_file, "w") as stream:
        stream.write("\n".join(tles) + "\n")
    spec = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}
    if model is not None:
        with open(model) as stream:
            spec = {k: v for k, v in yaml.safe_load(stream).items()
                    if k not in ("shells", "tle", "epoch", "satellites")}
    spec["tle"] = "satellites.tle"
    const_file = os.path.join(folder, "constellation.yaml")
    with open(const_file, "w") as stream:
        yaml.safe_dump(spec, stream)
    return const_file


def inject_counts(tles, visits, folder, model=None):
    """inject's plan and its exact passes on the visits: (seconds of the plan, plans,
    {(visit index, name)} by the rubin_sim rule, {(visit index, name)} sunlit in circle)."""
    import numpy as np

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, Exposure, compute_pass, segment_distances
    from inject.survey import plan as engine
    from inject.survey.constellation import read_constellation
    from inject.survey.prefilter import NightPrefilter

    const_file = write_constellation(tles, folder, model)
    constellation = read_constellation(const_file, visits[0].start.utc)
    engine.plan_visit(visits[0], constellation)  # astropy's first-call set-up, untimed
    start = time.perf_counter()
    plans = engine.plan_visits(visits, constellation)
    seconds = time.perf_counter() - start

    rule, lit = set(), set()
    night = NightPrefilter(constellation.orbits, visits, RUBIN, field_radius_deg=RADIUS_DEG)
    for k, visit in enumerate(visits):
        idx = night.candidates(visit)
        if not len(idx):
            continue
        ts = engine.visit_times(visit)
        pointing = Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg)
        exposure = Exposure(visit.start, float(ts[-1]))
        frame = engine.visit_frame(exposure.start, ts, pointing)
        for i in idx:
            p = compute_pass(constellation.orbits[i], exposure, pointing, t_s=ts,
                             frame=frame, check_epoch=False)
            xi, eta = np.nan_to_num(p.xi_deg, nan=1e9), np.nan_to_num(p.eta_deg, nan=1e9)
            ok = np.isfinite(p.xi_deg) & (p.apparent_alt_deg > 0)
            d = np.hypot(xi, eta)
            chord = segment_distances(xi, eta)

            def enters(mask):
                return bool((mask & (d <= RADIUS_DEG)).any()
                            or (mask[:-1] & mask[1:] & (chord <= RADIUS_DEG)).any())

            name = constellation.orbits[i].name
            ends = [0, len(ts) - 1]
            if ((p.sun_fraction[ends] > 0).any() and (p.alt_deg[ends] > ALT_LIMIT_DEG).any()
                    and enters(ok)):
                rule.add((k, name))
            if enters(ok & (p.sun_fraction > 0)):
                lit.add((k, name))
    return seconds, plans, rule, lit


def skyfield_track(sat_utils, tle, visit):
    """rubin_sim's own numbers for one satellite and visit (skyfield, as check_pointings
    computes them): altitudes and shadow at the start and end, the Sun line's height above
    skyfield's sphere there (km; None on the day side), the track's closest approach to the
    boresight (deg, gnomonic) and its length in the circle (deg)."""
    import numpy as np
    from rubin_scheduler.utils import gnomonic_project_toxy
    from skyfield.api import EarthSatellite

    from inject.survey.rubin_rule import sample_times, visit_span

    name, l1, l2 = tle.split("\n")
    c = sat_utils._cached  # the Constellation of rubin_sim_counts
    sat = EarthSatellite(l1, l2, name, c.ts)
    span, _ = visit_span(visit)
    mjd = visit.mjd_tai + sample_times(span) / 86400.0
    t = c.ts.ut1_jd(mjd + 2400000.5)
    at = sat.at(t)
    topo = at - c.observatory_site.at(t)
    alt = topo.altaz()[0].degrees[[0, -1]]
    lit = at.is_sunlit(c.eph)[[0, -1]]
    sun = (c.eph["sun"] - c.eph["earth"]).at(t).position.km[:, [0, -1]].T
    r = at.position.km[:, [0, -1]].T
    ra, dec, _ = topo.radec()
    x, y = gnomonic_project_toxy(ra.radians, dec.radians, np.radians(visit.ra_deg),
                                 np.radians(visit.dec_deg))
    length = sat_utils._streak_length(ra.radians, dec.radians, np.radians(visit.ra_deg),
                                      np.radians(visit.dec_deg), np.radians(RADIUS_DEG))
    return {"alt": alt, "lit": lit, "clear": [sun_line_height(a, b, 6378.1366)
                                              for a, b in zip(r, sun)],
            "closest": float(np.degrees(np.nanmin(np.hypot(x, y)))),
            "length": float(np.degrees(length))}


def sun_line_height(r, sun, radius):
    """Height (km) above the sphere of ``radius`` of the line from ``r`` to the Sun, where
    it passes the Earth (None when the Earth is not between: the satellite is on the day
    side)."""
    import numpy as np

    u = (sun - r) / np.linalg.norm(sun - r)
    s = -float(r @ u)
    if s <= 0:
        return None
    return float(np.linalg.norm(r + s * u) - radius)


def inject_track(visit, orbit):
    """The same numbers by inject's rule (:func:`inject.survey.rubin_rule.tracks`)."""
    import numpy as np

    from inject.survey import rubin_rule

    got = rubin_rule.tracks(visit, [orbit])
    x, y = rubin_rule.gnomonic(got["d"][0], visit.ra_deg, visit.dec_deg)
    return {"alt": got["alt_deg"][0, [0, -1]], "lit": got["sunlit"][0],
            "clear": [sun_line_height(r, s, rubin_rule.SKYFIELD_EARTH_RADIUS_KM)
                      for r, s in zip(got["r_km"][0], got["sun_km"])],
            "closest": float(np.degrees(np.nanmin(np.hypot(x, y)))),
            "length": float(np.degrees(rubin_rule.length_in_polygon(
                x, y, np.radians(rubin_rule.RADIUS_DEG))))}


def ut1_shift(sat_utils, visits):
    """Per visit, (TAI - UT1) of its MJD read as UT1 by astropy minus by skyfield, s."""
    import numpy as np
    from astropy.time import Time

    mjd = np.array([v.mjd_tai for v in visits])
    astropy = (Time(mjd, format="mjd", scale="ut1").tai.mjd - mjd) * 86400.0
    t = sat_utils._cached.ts.ut1_jd(mjd + 2400000.5)
    skyfield = (t.tai - (mjd + 2400000.5)) * 86400.0
    return astropy - skyfield


def agreement(label, plans, rs_n, rs_found, rs_len):
    """Print how ``plans`` (inject --rule rubin_sim) agree with rubin_sim's counts."""
    import numpy as np

    found = {(k, s.satellite) for k, p in enumerate(plans) for s in p.streaks}
    n = [len(p.streaks) for p in plans]
    same = sum(int(a) == b for a, b in zip(rs_n, n))
    length = {(k, s.satellite): s.length_deg for k, p in enumerate(plans) for s in p.streaks}
    diffs = [abs(np.degrees(RS_LENGTHS[key]) - length[key]) for key in rs_found & found]
    print(f"\n{label}: satellites x visits: rubin_sim {len(rs_found)}, inject --rule "
          f"rubin_sim {len(found)}, both {len(rs_found & found)}, rubin_sim only "
          f"{len(rs_found - found)}, inject only {len(found - rs_found)}; visits with equal "
          f"counts {same} of {len(plans)}; streaked visits rubin_sim "
          f"{int(np.count_nonzero(rs_n))}, inject {sum(c > 0 for c in n)}; total length "
          f"rubin_sim {float(np.sum(rs_len)):.4f} deg, inject "
          f"{sum(length.values()):.4f} deg; largest difference of a satellite both count "
          f"{max(diffs, default=0.0):.4f} deg", flush=True)
    for key in sorted(rs_found & found):
        print(f"    visit index {key[0]} {key[1]}: rubin_sim {np.degrees(RS_LENGTHS[key]):.4f} "
              f"deg, inject {length[key]:.4f} deg")


def literature(args, sat_utils, data_path, tles, visits, width_px=300.0):
    """rubin_sim as the literature ran it against ``inject survey --rule rubin_sim``, and the
    literature's table (the rule with a ``width_px`` band against inject's physics)."""
    import numpy as np

    from inject.survey import plan as engine
    from inject.survey import rubin_rule
    from inject.survey.constellation import read_constellation

    build, rs_s, rs_n, rs_found, rs_len = rubin_sim_counts(sat_utils, data_path, tles, visits,
                                                           literature=True)
    print(f"rubin_sim check_pointings (MJD as given, visitTime): {rs_s / len(visits):.4f} s "
          f"per visit ({rs_s:.1f} s; its Constellation built in {build:.1f} s)", flush=True)
    shift = ut1_shift(sat_utils, visits)
    print(f"TAI - UT1 of the MJDs read as UT1: astropy's minus skyfield's "
          f"{shift.min():.4f} to {shift.max():.4f} s", flush=True)
    with tempfile.TemporaryDirectory() as folder:
        const_file = write_constellation(tles, folder, args.model)
        constellation = read_constellation(const_file, visits[0].start.utc)
        start = time.perf_counter()
        rule = rubin_rule.plan_visits(visits, constellation, width_px=width_px)
        rule_s = time.perf_counter() - start
        # The same on skyfield's UT1: each MJD moved so that astropy's UT1 instant is
        # skyfield's (a check of the explanation, not a rule).
        moved = [replace(v, mjd_tai=v.mjd_tai - d / 86400.0) for v, d in zip(visits, shift)]
        rule_sf = rubin_rule.plan_visits(moved, constellation, width_px=width_px)
        start = time.perf_counter()
        physics = engine.plan_visits(visits, constellation, fixed_width_px=width_px)
        phys_s = time.perf_counter() - start
    print(f"inject --rule rubin_sim: {rule_s / len(visits):.4f} s per visit ({rule_s:.1f} s); "
          f"inject's physics: {phys_s / len(visits):.4f} s per visit ({phys_s:.1f} s)",
          flush=True)
    for label, plans in (("on astropy's UT1 (the rule)", rule),
                         ("on skyfield's UT1 (MJDs moved)", rule_sf)):
        agreement(label, plans, rs_n, rs_found, rs_len)
    found = {(k, s.satellite) for k, p in enumerate(rule) for s in p.streaks}
    n_rule = [len(p.streaks) for p in rule]
    len_rule = np.array([p.streak_length_deg for p in rule])
    by_name = {t.split("\n")[0]: t for t in tles}
    orbit = {o.name: o for o in constellation.orbits}
    for label, pairs in (("rubin_sim only", rs_found - found), ("inject only", found - rs_found)):
        for k, name in sorted(pairs):
            v = visits[k]
            a = skyfield_track(sat_utils, by_name[name], v)
            b = inject_track(v, orbit[name])
            print(f"  {label}: visit {v.observation_id} {name}")
            for who, x in (("skyfield", a), ("inject", b)):
                clear = ", ".join("day side" if c is None else f"{c:+.2f} km" for c in x["clear"])
                print(f"    {who:<8} alt start/end {x['alt'][0]:.3f}/{x['alt'][1]:.3f} deg, "
                      f"sunlit {bool(x['lit'][0])}/{bool(x['lit'][1])} (Sun line above the "
                      f"sphere: {clear}), closest {x['closest']:.4f} deg, length in circle "
                      f"{x['length']:.4f} deg")
    # The literature's table: the rule with a fixed band, and inject's physics.
    rows = [("rubin_sim check_pointings", int(np.count_nonzero(rs_n)), int(np.sum(rs_n)),
             float(np.sum(rs_len)), None),
            (f"inject --rule rubin_sim, {width_px:g} px band in the circle",
             sum(c > 0 for c in n_rule), sum(n_rule), float(len_rule.sum()),
             sum(p.pixels_lost for p in rule)),
            ("inject physics: CCDs, the masker's width", sum(len(p.streaks) > 0 for p in physics),
             sum(len(p.streaks) for p in physics),
             float(sum(p.streak_length_deg for p in physics)),
             sum(p.pixels_lost for p in physics)),
            (f"inject physics: CCDs, a {width_px:g} px band",
             sum(len(p.streaks) > 0 for p in physics), sum(len(p.streaks) for p in physics),
             float(sum(p.streak_length_deg for p in physics)),
             sum(p.pixels_fixed_mask for p in physics))]
    print(f"\n{'':<48} {'visits':>7} {'streaks':>7} {'length deg':>10} {'pixels lost':>12}")
    for label, nv, ns, length, px in rows:
        print(f"{label:<48} {nv:>7} {ns:>7} {length:>10.2f} "
              f"{'-' if px is None else format(px, ','):>12}")
    return 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("visits", help="opsim database (scripts/make_opsim_night.py)")
    parser.add_argument("--constellation", choices=("v1", "v2", "oneweb"), default="v1",
                        help="rubin_sim's starlink_tles_v1 (4,408), v2 (29,988) or "
                             "oneweb_tles (6,372)")
    parser.add_argument("--literature", action="store_true",
                        help="rubin_sim as the literature ran it (MJD as given, visitTime) "
                             "against inject survey --rule rubin_sim, and the literature's "
                             "table")
    parser.add_argument("--model", help="the satellites' model from this constellation file "
                                        "(its orbits left out)")
    parser.add_argument("--twilight", action="store_true",
                        help="only the visits with the Sun above -18 deg")
    parser.add_argument("--every", type=int, default=1, help="every N-th visit")
    parser.add_argument("--csv", help="write the counts per visit here")
    args = parser.parse_args()

    sat_utils, data_path = need_rubin_sim()
    warnings.simplefilter("ignore")
    from inject.orbits.passes import RUBIN
    from inject.survey.visits import read_visits

    visits = read_visits(args.visits)[::args.every]
    if args.twilight:
        visits = tuple(v for v, t in zip(visits, twilight(visits, RUBIN)) if t)
    tles = make_tles(sat_utils, args.constellation, visits[0].start)
    print(f"{len(visits)} visits of {args.visits}"
          f"{' (twilight)' if args.twilight else ''}; rubin_sim's "
          f"{'oneweb_tles' if args.constellation == 'oneweb' else 'starlink_tles_'}"
          f"{'' if args.constellation == 'oneweb' else args.constellation}: {len(tles)} "
          f"satellites, epoch moved to "
          f"{visits[0].start.utc.isot[:19]} UTC", flush=True)

    if args.literature:
        return literature(args, sat_utils, data_path, tles, visits)
    build, rs_s, rs_n, rs_found, _ = rubin_sim_counts(sat_utils, data_path, tles, visits)
    print(f"rubin_sim check_pointings: {rs_s / len(visits):.4f} s per visit "
          f"({rs_s:.1f} s; its Constellation built in {build:.1f} s)", flush=True)
    with tempfile.TemporaryDirectory() as folder:
        in_s, plans, rule, lit = inject_counts(tles, visits, folder, args.model)
    print(f"inject plan:               {in_s / len(visits):.4f} s per visit ({in_s:.1f} s): "
          f"{rs_s / in_s:.1f} x faster", flush=True)

    n = len(visits)
    per = {key: [0] * n for key in ("rubin_sim", "inject_rule", "inject_lit", "inject_ccd")}
    for key, pairs in (("rubin_sim", rs_found), ("inject_rule", rule), ("inject_lit", lit)):
        for k, _ in pairs:
            per[key][k] += 1
    for k, plan in enumerate(plans):
        per["inject_ccd"][k] = len(plan.streaks)
    assert per["rubin_sim"] == [int(x) for x in rs_n], "rubin_sim's loop read wrongly"
    print(f"\n{'count':<12} {'total':>6} {'visits > 0':>10} {'visits equal to rubin_sim':>26}")
    for key, counts in per.items():
        same = sum(a == b for a, b in zip(counts, per["rubin_sim"]))
        print(f"{key:<12} {sum(counts):>6} {sum(c > 0 for c in counts):>10} {same:>26}")
    both = rs_found & rule
    print(f"\nsatellites x visits: rubin_sim {len(rs_found)}, inject by rubin_sim's rule "
          f"{len(rule)}, both {len(both)}, rubin_sim only {len(rs_found - rule)}, inject only "
          f"{len(rule - rs_found)}")
    for label, pairs in (("rubin_sim only", rs_found - rule), ("inject only", rule - rs_found)):
        for k, name in sorted(pairs)[:10]:
            print(f"  {label}: visit {visits[k].observation_id} {name}")
    if args.csv:
        with open(args.csv, "w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(["observationId", "mjd_tai", *per])
            for k, v in enumerate(visits):
                writer.writerow([v.observation_id, v.mjd_tai, *(per[key][k] for key in per)])
    return 0


if __name__ == "__main__":
    sys.exit(main())
