"""Planning time of the 30 s example pass (sample_fields/pass_example.yaml): the footprint
margin from a few sampled vertices vs from every vertex, interleaved, caches cleared.

    .venv/bin/python scripts/bench_pass_plan.py
"""
import time
from inject.config import load_scene_file
from inject.exposure import scene as focalscene
from inject.exposure.scene import parse_focal_scene, margins_px, plan
from inject.render import PROFILE_CACHE
raw = load_scene_file("sample_fields/pass_example.yaml")
f = parse_focal_scene(raw)
for rep in range(2):
    for exhaustive in (True, False):
        focalscene._reach_px.cache_clear(); PROFILE_CACHE.clear()
        t0 = time.perf_counter(); m = margins_px(f, exhaustive=exhaustive); p = plan(f, margins=m)
        t1 = time.perf_counter()
        print(f"exhaustive={exhaustive}: margins+plan {t1-t0:.2f} s, margin {m[0]:.3f} px, "
              f"{len(p['detectors'])} CCDs")
