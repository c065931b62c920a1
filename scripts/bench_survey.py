"""Cost of the survey plan per visit, against the constellation's size and the visits.

Plans the visits of an opsim database (every ``--every``-th visit; several values give
several rows) against Walker constellations of the sizes asked for (``--sizes``; each split
evenly over three shells at 550 km inclined 53, 70 and 97.6 deg, like Starlink's), on one
core, and prints per size and visit count: the seconds per visit and their split between the
prefilter (the night's :class:`~inject.survey.prefilter.NightPrefilter`: its set-up, SGP4 at
the nodes and the per-visit tests), the visits' dense frames, the exact passes, the streak
models and the rest; the candidates, passes in the field and streaks per visit. Building the
constellation (SGP4 element sets) is timed apart: it is paid once per run, not per visit.

``--before`` adds, for each row, the plan as it was before the night's prefilter: per visit
:func:`inject.orbits.passes.crossing_candidates` (SGP4 for every satellite at 7 times, its own
astropy frame, a 1 deg margin) and the dense frame from astropy at all 301 samples; both
plans must find the same streaks (checked).

Usage::

    python scripts/make_opsim_night.py -o out/night.db
    python scripts/bench_survey.py out/night.db [--sizes 5000 30000] [--every 1 5] [--before]
"""
import argparse
import time
import warnings


class Clock:
    """Seconds spent in wrapped functions, by name."""

    def __init__(self):
        self.seconds, self.calls = {}, {}

    def add(self, label, seconds):
        self.seconds[label] = self.seconds.get(label, 0.0) + seconds
        self.calls[label] = self.calls.get(label, 0) + 1

    def wrap(self, owner, name, label=None):
        inner = getattr(owner, name)
        label = label or name

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.add(label, time.perf_counter() - start)

        setattr(owner, name, timed)
        # The attribute as the owner holds it (a classmethod stays one when put back).
        return owner, name, vars(owner).get(name, inner) if isinstance(owner, type) else inner


def shells(total, per_plane=50):
    """Three Walker shells of ``total`` satellites in all (a multiple of ``per_plane``),
    planes of ``per_plane`` satellites shared out as evenly as they go."""
    planes = total // per_plane
    if planes * per_plane != total or planes < 3:
        raise SystemExit(f"--sizes: {total} is not a multiple of {per_plane} (at least 3 "
                         f"planes)")
    split = [planes // 3 + (k < planes % 3) for k in range(3)]
    return [{"height": 550.0, "inclination": inc, "planes": p, "per_plane": per_plane,
             "phasing": 1} for inc, p in zip((53.0, 70.0, 97.6), split)]


class BeforePrefilter:
    """The prefilter as the plan used it before the night's: per visit and from scratch."""

    def __init__(self, orbits, visits, site=None):
        self.orbits = orbits

    def candidates(self, visit, sunlit=False):
        """Every satellite near the field, sunlit or not (no umbra test then)."""
        from inject.camera.wcs import Pointing
        from inject.orbits.passes import Exposure, crossing_candidates
        from inject.survey.plan import visit_times

        ts = visit_times(visit)
        return crossing_candidates(self.orbits, Exposure(visit.start, float(ts[-1])),
                                   Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg))


def before_frame(start, ts, pointing, site=None, at_nodes=None):
    """The dense frame from astropy at every sample (before :func:`visit_frame`)."""
    from astropy import units as u

    from inject.orbits.passes import FieldFrame

    return FieldFrame.build(start + ts * u.s, pointing)


def run(engine, visits, constellation, before):
    """Plan ``visits``; returns (seconds, clock, plans)."""
    from inject.survey import prefilter as pre

    clock = Clock()
    saved = [(engine, "NightPrefilter", engine.NightPrefilter),
             (engine, "visit_frame", engine.visit_frame),
             (engine, "_frames_at_nodes", engine._frames_at_nodes)]
    if before:  # each visit its own frame from astropy at every sample, none built ahead
        engine.NightPrefilter, engine.visit_frame = BeforePrefilter, before_frame
        engine._frames_at_nodes = lambda visits, site: [None] * len(visits)
    from inject.orbits.passes import FieldFrame

    wrapped = [clock.wrap(engine, n) for n in ("compute_pass", "_streak", "visit_frame")]
    # The night's plan builds its visits' frames in batches (astropy at the nodes), then
    # interpolates each visit's (visit_frame): both are the frames' cost.
    wrapped.append(clock.wrap(FieldFrame, "build_many", "visit_frame"))
    cls = engine.NightPrefilter
    wrapped += [clock.wrap(cls, "__init__", "prefilter"), clock.wrap(cls, "candidates",
                                                                    "prefilter")]
    if not before:
        wrapped.append(clock.wrap(pre.NightPrefilter, "_propagate", "nodes"))
    try:
        start = time.perf_counter()
        plans = engine.plan_visits(visits, constellation)
        total = time.perf_counter() - start
    finally:
        for owner, name, inner in wrapped + saved:
            setattr(owner, name, inner)
    return total, clock, plans


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("visits", help="opsim database (scripts/make_opsim_night.py)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 30000])
    parser.add_argument("--every", type=int, nargs="+", default=[5],
                        help="plan every N-th visit (several: one row each)")
    parser.add_argument("--before", action="store_true",
                        help="also time the plan as it was before the night's prefilter")
    args = parser.parse_args()

    from inject.survey import plan as engine
    from inject.survey.constellation import parse_constellation
    from inject.survey.visits import read_visits

    night = read_visits(args.visits)
    warnings.simplefilter("ignore")
    print(f"{len(night)} visits in {args.visits}")
    print(f"{'satellites':>10} {'visits':>6} {'plan':>6} {'build s':>8} {'s/visit':>8} "
          f"{'prefilter':>9} {'(nodes)':>8} {'frames':>7} {'passes':>7} {'models':>7} "
          f"{'other':>7} {'cand/v':>7} {'field/v':>7} {'streaks/v':>9}")
    for size in args.sizes:
        raw = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
               "epoch": night[0].start.utc, "shells": shells(size)}
        start = time.perf_counter()
        constellation = parse_constellation(raw)
        build = time.perf_counter() - start
        engine.plan_visit(night[0], constellation)  # astropy's first-call set-up, untimed
        for every in args.every:
            visits = night[::every]
            results = {}
            for label in (("before", "night") if args.before else ("night",)):
                total, clock, plans = run(engine, visits, constellation, label == "before")
                results[label] = plans
                n = len(visits)
                s = clock.seconds
                pre, nodes = s.get("prefilter", 0.0), s.get("nodes", 0.0)
                frames, passes = s.get("visit_frame", 0.0), s.get("compute_pass", 0.0)
                models = s.get("_streak", 0.0)
                other = total - pre - frames - passes - models
                cand = sum(p.n_candidates for p in plans) / n
                field = clock.calls.get("compute_pass", 0) / n
                streaks = sum(len(p.streaks) for p in plans) / n
                print(f"{len(constellation):>10d} {n:>6d} {label:>6} {build:8.1f} "
                      f"{total / n:8.4f} {pre / n:9.4f} {nodes / n:8.4f} {frames / n:7.4f} "
                      f"{passes / n:7.4f} {models / n:7.4f} {other / n:7.4f} {cand:7.2f} "
                      f"{field:7.2f} {streaks:9.3f}", flush=True)
            if args.before:
                rows = [sorted((r["observationId"], r["satellite"], r["ccds"])
                               for p in results[k] for r in p.streak_rows())
                        for k in ("before", "night")]
                same = "the same" if rows[0] == rows[1] else "DIFFERENT"
                print(f"{'':>10} streaks before and after: {same} ({len(rows[1])})")


if __name__ == "__main__":
    main()
