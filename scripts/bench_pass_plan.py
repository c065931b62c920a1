"""Planning time of the 30 s example pass (sample_fields/pass_example.yaml): the footprint
margin from a few sampled vertices vs from every vertex, interleaved, caches cleared.

    .venv/bin/python scripts/bench_pass_plan.py
"""
import time

from inject.exposure import plan as focalplan
from inject.exposure.plan import make_plan, margins_px
from inject.exposure.scene import parse_focal_scene
from inject.render import PROFILE_CACHE
from inject.schema import load_scene_file

raw = load_scene_file("sample_fields/pass_example.yaml")
f = parse_focal_scene(raw)
for _ in range(2):
    for exhaustive in (True, False):
        focalplan._reach_px.cache_clear()
        PROFILE_CACHE.clear()
        t0 = time.perf_counter()
        m = margins_px(f, exhaustive=exhaustive)
        p = make_plan(f, m).summary()
        t1 = time.perf_counter()
        print(f"exhaustive={exhaustive}: margins+plan {t1-t0:.2f} s, margin {m[0]:.3f} px, "
              f"{len(p['detectors'])} CCDs")
