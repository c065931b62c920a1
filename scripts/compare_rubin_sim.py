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

and prints the totals, the satellites both find and each alone (rubin_sim's satellites are
read from inside its loop), the visits where the counts agree, and the seconds per visit of
``check_pointings`` (all the visits in one call, as it is meant to be used) and of inject's
plan (:func:`inject.survey.plan.plan_visits`) on the same visits and satellites, one core.

Usage (in the rubin_sim environment)::

    python scripts/make_opsim_night.py -o out/night.db
    python scripts/compare_rubin_sim.py out/night.db --constellation v1 [--twilight]
        [--every N] [--csv out/compare_v1.csv]
"""
import argparse
import csv
import functools
import os
import sys
import tempfile
import time
import warnings

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
    make = {"v1": sat_utils.starlink_tles_v1, "v2": sat_utils.starlink_tles_v2}[which]
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


def rubin_sim_counts(sat_utils, data_path, tles, visits):
    """check_pointings on the visits: (seconds, n_streaks per visit, {(visit index, name)})."""
    import numpy as np
    from astropy.time import Time
    from skyfield.api import Loader

    sat_utils.load = Loader(data_path, verbose=False)  # de421 from skyfield-data: offline
    found = set()
    original = sat_utils._streak_length

    def recorded(*args):
        length = original(*args)
        if length > 0:  # the visit and satellite of rubin_sim's own loop
            caller = sys._getframe(1).f_locals
            found.add((int(caller["ob_indx"]), int(caller["sat_in"])))
        return length

    build = time.perf_counter()
    constellation = sat_utils.Constellation(tles)
    build = time.perf_counter() - build
    starts = Time([v.mjd_tai for v in visits], format="mjd", scale="tai")
    span = np.array([v.snaps()[-1][0] + v.snaps()[-1][1] for v in visits])
    sat_utils._streak_length = recorded
    try:
        start = time.perf_counter()
        _, n = constellation.check_pointings(
            np.array([v.ra_deg for v in visits]), np.array([v.dec_deg for v in visits]),
            np.asarray(starts.ut1.mjd), span)
        seconds = time.perf_counter() - start
    finally:
        sat_utils._streak_length = original
    names = [t.split("\n")[0] for t in tles]
    return build, seconds, n, {(k, names[i]) for k, i in found}


def inject_counts(tles, visits, folder):
    """inject's plan and its exact passes on the visits: (seconds of the plan, plans,
    {(visit index, name)} by the rubin_sim rule, {(visit index, name)} sunlit in circle)."""
    import numpy as np

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, Exposure, compute_pass, segment_distances
    from inject.survey import plan as engine
    from inject.survey.constellation import read_constellation
    from inject.survey.prefilter import NightPrefilter

    tle_file = os.path.join(folder, "satellites.tle")
    with open(tle_file, "w") as stream:
        stream.write("\n".join(tles) + "\n")
    const_file = os.path.join(folder, "constellation.yaml")
    with open(const_file, "w") as stream:
        stream.write("shape: {type: box, length: 7.25, width: 2.65}\nmag: 5.0\n"
                     "tle: satellites.tle\n")
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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("visits", help="opsim database (scripts/make_opsim_night.py)")
    parser.add_argument("--constellation", choices=("v1", "v2"), default="v1",
                        help="rubin_sim's starlink_tles_v1 (4,408) or v2 (29,988)")
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
          f"{' (twilight)' if args.twilight else ''}; rubin_sim's starlink_tles_"
          f"{args.constellation}: {len(tles)} satellites, epoch moved to "
          f"{visits[0].start.utc.isot[:19]} UTC", flush=True)

    build, rs_s, rs_n, rs_found = rubin_sim_counts(sat_utils, data_path, tles, visits)
    print(f"rubin_sim check_pointings: {rs_s / len(visits):.4f} s per visit "
          f"({rs_s:.1f} s; its Constellation built in {build:.1f} s)", flush=True)
    with tempfile.TemporaryDirectory() as folder:
        in_s, plans, rule, lit = inject_counts(tles, visits, folder)
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
