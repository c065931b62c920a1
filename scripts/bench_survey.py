"""Cost of the survey plan per visit, against the constellation's size.

Plans the visits of an opsim database (every ``--every``-th visit) against Walker
constellations of the sizes asked for (``--sizes``; each split evenly over three shells at
550 km inclined 53, 70 and 97.6 deg, like Starlink's), on one core, and prints per size: the
seconds per visit and their split between the candidates' prefilter, the visit's frames, the
exact passes, the streak models and the rest; the candidates, passes in the field and streaks
per visit. Building the constellation (SGP4 element sets) is timed apart: it is paid once
per run, not per visit.

Usage::

    python scripts/make_opsim_night.py -o out/night.db
    python scripts/bench_survey.py out/night.db [--sizes 5000 30000] [--every 5]
"""
import argparse
import time
import warnings


class Clock:
    """Seconds spent in wrapped functions, by name."""

    def __init__(self):
        self.seconds, self.calls = {}, {}

    def wrap(self, module, name, label=None):
        inner = getattr(module, name)
        label = label or name

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - start
                self.calls[label] = self.calls.get(label, 0) + 1

        setattr(module, name, timed)
        return inner


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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("visits", help="opsim database (scripts/make_opsim_night.py)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 30000])
    parser.add_argument("--every", type=int, default=5, help="plan every N-th visit")
    args = parser.parse_args()

    from inject.orbits.passes import FieldFrame
    from inject.survey import plan as engine
    from inject.survey.constellation import parse_constellation
    from inject.survey.visits import read_visits

    visits = read_visits(args.visits)[::args.every]
    warnings.simplefilter("ignore")
    print(f"{len(visits)} visits of {args.visits} (every {args.every}-th)")
    print(f"{'satellites':>10} {'build s':>8} {'s/visit':>8} {'prefilter':>9} {'frames':>7} "
          f"{'passes':>7} {'models':>7} {'other':>7} {'cand/v':>7} {'field/v':>7} "
          f"{'streaks/v':>9}")
    for size in args.sizes:
        raw = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
               "shells": shells(size)}
        start = time.perf_counter()
        constellation = parse_constellation(raw, visits[0].start.utc)
        build = time.perf_counter() - start
        engine.plan_visit(visits[0], constellation)  # astropy's first-call set-up, untimed
        clock = Clock()
        originals = [(engine, n, clock.wrap(engine, n)) for n in
                     ("crossing_candidates", "compute_pass", "_streak")]

        class Frames:  # the visit's frame, as the plan builds it (the prefilter's apart)
            @staticmethod
            def build(*a, **k):
                t0 = time.perf_counter()
                try:
                    return FieldFrame.build(*a, **k)
                finally:
                    clock.seconds["frames"] = clock.seconds.get("frames", 0.0) + \
                        time.perf_counter() - t0

        engine.FieldFrame = Frames
        try:
            start = time.perf_counter()
            plans = engine.plan_visits(visits, constellation)
            total = time.perf_counter() - start
        finally:
            for module, name, inner in originals:
                setattr(module, name, inner)
            engine.FieldFrame = FieldFrame
        n = len(visits)
        s = clock.seconds
        pre = s.get("crossing_candidates", 0.0)  # with its own coarse frame
        frames = s.get("frames", 0.0)
        passes = s.get("compute_pass", 0.0)
        models = s.get("_streak", 0.0)
        other = total - pre - frames - passes - models
        cand = sum(p.n_candidates for p in plans) / n
        field = clock.calls.get("compute_pass", 0) / n
        streaks = sum(len(p.streaks) for p in plans) / n
        print(f"{len(constellation):>10d} {build:8.1f} {total / n:8.3f} {pre / n:9.3f} "
              f"{frames / n:7.3f} {passes / n:7.3f} {models / n:7.3f} {other / n:7.3f} "
              f"{cand:7.2f} {field:7.2f} {streaks:9.3f}")


if __name__ == "__main__":
    main()
