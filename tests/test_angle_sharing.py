"""Streaks at different angles share tables: exactly every 90 deg, and on a measured grid of
pixel orientations in between.

The profile is given in the track frame, so the angle reaches the tables only through the
orientation of the square pixel there (:class:`inject.render.SweptProfile`). Tracks are
rendered through :func:`inject.render.swept_profile` (the snapped tables) at their own angle
and compared with the brute-force reference (:func:`inject.reference.render_brute_force`),
which sums GalSim stamps along the track and knows nothing of tables or orientations.
"""
from dataclasses import dataclass

import galsim
import numpy as np
import pytest

from inject import Box, Seeing, Segment, StreakModel, render_brute_force
from inject.profile import GSPARAMS
from inject.render import (
    ORIENTATION_FRACTION,
    ORIENTATION_SAFETY,
    Budget,
    ProfileCache,
    SweptProfile,
    orientation_slope,
    orientation_step,
    render_segment,
    snap_orientation,
    swept_profile,
)

TOL = Budget().tolerance
PAPER_550 = StreakModel(550, 70)
#: A small satellite far away in good seeing: FWHM ~2 px (Kolmogorov).
SMALL_FAR = StreakModel(20000, 30, shape=Box(1.0, 0.5), seeing=Seeing(0.35))
#: Angles where +angle and -angle differ, and their images 90, 180 deg on.
ANGLES = [23.0, 67.0, 113.0, 203.0]


@dataclass(frozen=True)
class GaussianModel:
    """The parts of a StreakModel that :func:`swept_profile` reads, for a Gaussian of FWHM
    ``fwhm_px`` (cheap reference stamps)."""

    fwhm_px: float
    pixel_scale: float = 0.2
    flux_per_px: float = 1.0

    @property
    def profile_key(self):
        return ("gaussian", self.fwhm_px, self.pixel_scale)

    @property
    def profile(self):
        return galsim.Gaussian(fwhm=self.fwhm_px * self.pixel_scale, gsparams=GSPARAMS)

    def render_profile(self, tolerance):
        return self.profile, (), 0.0


NARROW = GaussianModel(2.0)


def shared_render(model, segment, shape, cache, budget=Budget()):
    """Render through the shared path, as render_tracks does."""
    image = np.zeros(shape)
    swept = swept_profile(model, segment.angle_deg, budget, segment.length, cache)
    result = render_segment(image, swept, segment, model.flux_per_px)
    return image, result


def test_narrow_profile_at_many_angles_against_brute_force():
    cache = ProfileCache()
    rng = np.random.default_rng(11)
    angles = ANGLES + [-23.0] + list(rng.uniform(-180, 180, 3))
    for angle in angles:
        c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        length = 24.0
        seg = Segment(36.3 - 0.5 * length * c, 34.6 - 0.5 * length * s, angle, length)
        shape = (70, 72)
        image, result = shared_render(NARROW, seg, shape, cache)
        ref = render_brute_force(shape, NARROW.profile, NARROW.pixel_scale, seg, 1.0,
                                 step_px=0.02)
        assert np.abs(image - ref).max() <= TOL * ref.max(), angle
        assert result.plan.predicted_error["orientation"] <= ORIENTATION_FRACTION * TOL
        assert image.sum() == pytest.approx(length, rel=1e-5)


@pytest.mark.parametrize("angle", [pytest.param(23.0, marks=pytest.mark.slow), 67.0])
def test_lsst_profile_against_brute_force(angle):
    """The paper's satellite at 550 km, z = 70 deg (FWHM ~7 px), on a short track. The
    reference's error falls as step^2: two steps extrapolate it away (Richardson)."""
    model = PAPER_550
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    seg = Segment(60.3 - 3 * c, 60.6 - 3 * s, angle, 6.0)
    shape = (120, 120)
    image, result = shared_render(model, seg, shape, ProfileCache())
    coarse, fine = (render_brute_force(shape, model.profile, model.pixel_scale, seg,
                                       model.flux_per_px, step_px=h) for h in (0.25, 0.125))
    ref = (4 * fine - coarse) / 3
    assert np.abs(image - ref).max() <= TOL * ref.max()
    # The snapped tables are not the angle's own: the plan says how far and at what cost.
    swept = swept_profile(model, angle, Budget(), seg.length, ProfileCache())
    assert swept.angle_deg != angle % 90
    assert 0 < result.plan.predicted_error["orientation"] <= ORIENTATION_FRACTION * TOL


def test_charge_is_conserved_at_snapped_orientations():
    cache = ProfileCache()
    for angle in (23.0, 67.0, 113.0, 203.0, 301.7):
        seg = Segment(200.3, 210.6, angle, 40.0)
        image, result = shared_render(PAPER_550, seg, (420, 420), cache)
        expected = PAPER_550.flux_per_px * seg.length
        assert result.charge_added == pytest.approx(expected, rel=2 * TOL)
        assert image.sum() == pytest.approx(result.charge_added, rel=1e-12)


@pytest.mark.parametrize("model", [PAPER_550, NARROW], ids=["lsst", "narrow"])
def test_angles_90_degrees_apart_build_identical_tables(model):
    builds = [SweptProfile(model.profile, model.pixel_scale, 23.0 + k * 90.0)
              for k in range(-1, 4)]
    for other in builds[1:]:
        assert other.angle_deg == builds[0].angle_deg
        np.testing.assert_array_equal(other._table, builds[0]._table)
        np.testing.assert_array_equal(other.lsf.lsf, builds[0].lsf.lsf)
        assert other.plan == builds[0].plan
    cache = ProfileCache()
    first = swept_profile(model, 23.0, cache=cache)
    assert all(swept_profile(model, a, cache=cache) is first for a in (113.0, 203.0, -67.0))
    # +23 and -23 (= 67) see mirror-image pixels in an asymmetric profile: not shared.
    assert swept_profile(model, -23.0, cache=cache) is not first


@pytest.mark.parametrize("model", [PAPER_550, NARROW], ids=["lsst", "narrow"])
def test_orientation_slope_bounds_the_change_between_orientations(model):
    """Pixel values of tracks of several lengths at tables built for two orientations differ
    by at most the measured slope times their separation, and by not much less (the
    measure is tight, not a loose guess)."""
    slope = orientation_slope(model.profile, model.pixel_scale)
    t, d = np.meshgrid(np.arange(-20, 60, 0.37), np.arange(-25, 25, 0.29))
    t, d = t.ravel(), d.ravel()
    for a, b in ((0.0, 7.5), (22.5, 30.0), (40.0, 45.0), (80.0, 91.0)):
        first, second = (SweptProfile(model.profile, model.pixel_scale, x) for x in (a, b))
        peak = first._peak * model.pixel_scale
        change = max(np.abs(first.pixel_values(t, d, length) - second.pixel_values(t, d, length)
                            ).max() for length in (0.5, 3.0, 40.0)) / peak
        separation = abs((b - a + 45) % 90 - 45)
        assert change <= slope * separation
        if (a, b) == (22.5, 30.0):  # where cos 4a is steepest
            assert change >= 0.5 * slope * separation


def test_orientation_step_follows_from_the_measured_slope():
    slopes = {name: orientation_slope(m.profile, m.pixel_scale)
              for name, m in (("lsst", PAPER_550), ("narrow", NARROW), ("small_far", SMALL_FAR))}
    # Narrow profiles change ~30-55x faster with the pixel's orientation (~1e-3 of the peak
    # between 0 and 45 deg, against ~2.5e-5 for the LSST profile).
    assert slopes["narrow"] > 20 * slopes["lsst"] and slopes["small_far"] > 20 * slopes["lsst"]
    steps = {}
    for name, slope in slopes.items():
        for tol in (5e-5, 1e-5, 2e-6):
            step, error = orientation_step(slope, tol)
            steps[name, tol] = step
            if step == 0:  # exact angles: more than MAX_ORIENTATION_STEPS would be needed
                assert error == 0
                continue
            n = round(90 / step)
            # The fewest steps whose snapping error (half a step, with the safety margin)
            # stays within the fraction of the tolerance.
            assert error == pytest.approx(ORIENTATION_SAFETY * slope * step / 2)
            assert error <= ORIENTATION_FRACTION * tol * (1 + 1e-12)
            if n > 1:
                assert ORIENTATION_SAFETY * slope * 45 / (n - 1) > ORIENTATION_FRACTION * tol
    # The step shrinks for narrow profiles and for tight budgets, down to exact angles.
    assert steps["narrow", 5e-5] < steps["lsst", 5e-5] / 10
    assert steps["lsst", 2e-6] < steps["lsst", 5e-5] / 10
    assert steps["narrow", 2e-6] == 0 and steps["small_far", 2e-6] == 0
    assert steps["lsst", 5e-5] > 5  # a handful of tables for all angles at the default budget


def test_snap_orientation():
    assert snap_orientation(23.0, 0.0) == 23.0
    assert snap_orientation(113.0, 0.0) == 23.0
    assert snap_orientation(-23.0, 0.0) == pytest.approx(67.0)
    assert snap_orientation(23.0, 10.0) == 20.0
    assert snap_orientation(-23.0, 10.0) == 70.0
    assert snap_orientation(88.0, 10.0) == 0.0  # 90 is 0
    for angle in np.random.default_rng(2).uniform(-720, 720, 200):
        snapped = snap_orientation(angle, 90 / 7)
        assert 0 <= snapped < 90
        assert abs((angle - snapped + 45) % 90 - 45) <= 90 / 14 + 1e-9


def test_segment_outside_the_orientation_bin_is_refused():
    from inject import InputError
    swept = swept_profile(PAPER_550, 23.0, cache=ProfileCache())
    half = swept.angle_tolerance_deg
    assert half > 0
    image = np.zeros((60, 60))
    for angle in (swept.angle_deg + half, swept.angle_deg - half + 90, swept.angle_deg + 180):
        render_segment(image, swept, Segment(30, 30, angle, 5.0), 1.0)
    with pytest.raises(InputError, match="segment.angle_deg"):
        render_segment(image, swept, Segment(30, 30, swept.angle_deg + half + 0.01, 5.0), 1.0)


@pytest.mark.parametrize("model", [PAPER_550, NARROW], ids=["lsst", "narrow"])
def test_along_peak_floor_keeps_short_track_budgets_exact(model):
    """Tracks long enough by the orientation-free bound keep the budget at every angle, as the
    per-angle check (:func:`short_track_budget`) would; shorter ones still get that check."""
    from inject.render import along_peak_floor, short_track_budget

    p = model.pixel_scale
    floor = along_peak_floor(model.profile, p)
    long_enough = 1.0 / (p * floor)
    for angle in np.random.default_rng(5).uniform(0, 360, 6):
        assert short_track_budget(Budget(), model.profile, p, angle, long_enough) == Budget()
        # The bound is close: 5% shorter, the per-angle check tightens the budget.
        short = short_track_budget(Budget(), model.profile, p, angle, 0.95 * long_enough)
        assert short.tolerance < TOL
        cache = ProfileCache()
        swept = swept_profile(model, angle, Budget(), 0.95 * long_enough, cache)
        assert swept.budget == short


def test_polyline_snaps_only_profiles_that_recur():
    """A polyline whose vertices each have a profile of their own (a height per vertex, as
    an orbit's or a focal-plane CCD's interpolated ends) is rendered at its exact angles, the
    orientation grid never measured; one whose vertices share a profile (only the magnitude
    changes) snaps to the grid, as segments do. Both keep the track's charge."""
    from dataclasses import replace

    from inject import Polyline, render_polyline
    poly = Polyline((20.0, 150.0, 260.0), (30.0, 90.0, 120.0))
    own = [StreakModel(h, 70) for h in (540.0, 550.0, 560.0)]
    shared = [replace(PAPER_550, mag=m) for m in (5.0, 5.5, 6.0)]
    for models, snapped in ((own, False), (shared, True)):
        cache = ProfileCache()
        image = np.zeros((200, 300))
        charge = render_polyline(image, poly, models, cache=cache).charge_added
        orientation_keys = [k for k in cache._items if k[0] == "orientation"]
        assert bool(orientation_keys) == snapped
        swept = [v for v, _ in cache._items.values() if isinstance(v, SweptProfile)]
        angles = {round(s.angle_deg, 9) for s in swept}
        exact = {round(seg.angle_deg % 90.0, 9) for seg in poly.segments()}
        assert (angles == exact) != snapped
        fluxes = [m.flux_per_px for m in models]
        track = sum(0.5 * (a + b) * seg.length
                    for a, b, seg in zip(fluxes[:-1], fluxes[1:], poly.segments()))
        assert charge == pytest.approx(image.sum(), rel=1e-12)
        assert charge == pytest.approx(track, rel=2e-3)  # the whole track is on the image
