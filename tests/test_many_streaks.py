"""Scenes with many streaks: what streaks share is built once, without changing the image."""
import logging

import numpy as np
import pytest

from inject import Seeing, Segment, StreakModel, Track
from inject.render import (
    AUTO_MIN_TOLERANCE,
    TOLERANCE_STEPS_PER_OCTAVE,
    Budget,
    ProfileCache,
    render_streak,
    short_track_budget,
    snap_tolerance,
    swept_profile,
)
from inject.scene import PROGRESS_MIN_STREAKS, render_tracks

SHAPE = (700, 700)


def train(n, mags, seed=5):
    """``n`` short tracks at one angle, at scattered sub-pixel positions."""
    rng = np.random.default_rng(seed)
    models = [StreakModel(550, 70, mag=float(m)) for m in mags]
    tracks = [Track(float(rng.uniform(300, 380)), float(rng.uniform(300, 380)), 23.0, 20.0)
              for _ in range(n)]
    return models, tracks


def test_shared_profiles_give_the_image_of_streaks_rendered_alone():
    # Magnitudes 3-9 in noise: the budgets are tightened by brightness (some to the same
    # grid step, some not), so hits and misses both happen.
    mags = [3.0, 3.0, 4.2, 4.25, 6.0, 8.0, 8.0, 9.0]
    models, tracks = train(len(mags), mags)
    cache = ProfileCache()
    shared, truth = render_tracks(SHAPE, models, tracks, noise_sigma=25.0, cache=cache)
    assert cache.hits > 0
    alone = np.zeros(SHAPE)
    for model, track in zip(models, tracks):
        image, _ = render_tracks(SHAPE, [model], [track], noise_sigma=25.0, cache=None)
        alone += image
    np.testing.assert_allclose(shared, alone, rtol=0, atol=1e-12 * alone.max())
    # and each streak whose footprint fits keeps its charge, F L (bright ones reach the edges)
    whole = [(m, row) for m, row in zip(models, truth) if row["flags"] == 0]
    assert len(whole) >= 4
    for model, row in whole:
        assert row["charge_in_image_e"] == pytest.approx(model.flux_per_px * 20.0, rel=1e-4)


def test_cache_key_is_what_determines_the_tables():
    cache = ProfileCache()
    base = StreakModel(550, 70)
    first = swept_profile(base, 23.0, cache=cache)
    # Magnitude and band only scale the charge: shared.
    assert swept_profile(StreakModel(550, 70, mag=9.0, band_name="r"), 23.0, cache=cache) is first
    # Anything that changes the profile, the angle or the budget builds its own, equal to a
    # fresh build.
    others = [(StreakModel(551, 70), 23.0, Budget()),
              (StreakModel(550, 70, phi_deg=80), 23.0, Budget()),
              (StreakModel(550, 70, seeing=Seeing(0.8)), 23.0, Budget()),
              (base, -23.0, Budget()),
              (base, 23.0, Budget(tolerance=1e-4))]
    for model, angle, budget in others:
        got = swept_profile(model, angle, budget, cache=cache)
        assert got is not first
        fresh = swept_profile(model, angle, budget, cache=None)
        seg = Segment(40.3, 50.6, angle, 12.0)
        a, b = np.zeros((120, 120)), np.zeros((120, 120))
        render_streak(a, model, seg, budget, cache=cache)
        render_streak(b, model, seg, budget, cache=None)
        np.testing.assert_array_equal(a, b)
        assert got.plan == fresh.plan


def test_cache_is_bounded():
    model = StreakModel(550, 70)
    cache = ProfileCache(max_entries=3)
    for angle in (10.0, 20.0, 30.0, 40.0, 50.0):
        swept_profile(model, angle, cache=cache)
    assert len(cache) <= 3
    small = ProfileCache(max_bytes=2 ** 20)  # below one table: nothing big is kept
    swept_profile(model, 10.0, cache=small)
    assert small.nbytes <= 2 ** 20


def test_snapped_tolerances_are_never_looser_and_on_the_grid():
    n = TOLERANCE_STEPS_PER_OCTAVE
    for tol in np.geomspace(2e-6, 5e-5, 37):
        snapped = snap_tolerance(tol)
        assert snapped <= tol and snapped > tol / 2 ** (1 / n) * (1 - 1e-12)
        assert snap_tolerance(snapped) == snapped
        steps = np.log2(snapped) * n
        assert abs(steps - round(steps)) < 1e-9
    # A zero-length track: no log of 0 (a RuntimeWarning), the budget clamped as before.
    assert snap_tolerance(0.0) == 0.0
    model = StreakModel(550, 70)
    assert short_track_budget(Budget(), model.profile, 0.2, 23.0, 0.0).tolerance == \
        AUTO_MIN_TOLERANCE


def test_progress_only_for_many_streaks(caplog):
    """Progress is the logger's (INFO, on a stream that is no terminal: a line per tenth);
    a short scene gives none, and the library never prints."""
    caplog.set_level(logging.INFO, logger="inject")
    models, tracks = train(1, [8.0])
    render_tracks(SHAPE, models, tracks)
    assert caplog.messages == []
    n = PROGRESS_MIN_STREAKS
    models, tracks = train(n, [8.0] * n)
    render_tracks(SHAPE, models, tracks)
    lines = [m for m in caplog.messages if "rendering streaks" in m]
    # 20 streaks: a line after every second one (each tenth), the last at 20 of 20.
    assert len(lines) == 10
    assert lines[0].startswith(f"[2/{n}]") and lines[-1].startswith(f"[{n}/{n}]")
