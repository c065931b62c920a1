"""The fast renderer: flux, symmetry, equivariance, and agreement with independent methods."""
import galsim
import numpy as np
import pytest

from inject import Box, Budget, Disk, InputError, Seeing, Segment, StreakModel, render_segment
from inject.baselines import render_galsim_box
from inject.render import SweptProfile, footprint, render_streak
from inject.satellite import Composite, Part

PAPER_550 = StreakModel(550, 70)
DISK_350 = StreakModel(350, 0, shape=Disk(1.0))
COMPOSITE = StreakModel(500, 40, phi_deg=60, shape=Composite((
    Part(Box(2.0, 1.5)), Part(Box(1.0, 6.0), dx=0.5, dy=4.0, reflectance=2.0))))
BOX_IDIOM_GSPARAMS = galsim.GSParams(folding_threshold=1e-4, maxk_threshold=1e-6,
                                     maximum_fft_size=16384)


def render(model, segment, shape=(400, 420), budget=Budget()):
    image = np.zeros(shape)
    render_streak(image, model, segment, budget)
    return image


@pytest.mark.parametrize("model", [PAPER_550, DISK_350, COMPOSITE], ids=["box", "disk", "comp"])
@pytest.mark.parametrize("angle", [0.0, 45.0, 90.0, 137.3, 1e-9])
def test_flux_is_conserved(model, angle):
    # Short track in a large image: everything lands on it.
    seg = Segment(400.37, 380.81, angle, 37.5)
    image = render(model, seg, shape=(800, 840))
    assert image.sum() == pytest.approx(model.flux_per_px * seg.length, rel=1e-4)


@pytest.mark.parametrize("model", [PAPER_550, DISK_350, COMPOSITE], ids=["box", "disk", "comp"])
@pytest.mark.parametrize("angle,x0,y0", [(0.0, 150.3, 200.2), (23.0, 140.7, 180.4),
                                         (90.0, 260.5, 150.0), (137.3, 300.2, 160.9)])
def test_agrees_with_galsim_box_idiom(model, angle, x0, y0):
    """An independent method (FFT of Box(L) x profile) agrees to the budget."""
    seg = Segment(x0, y0, angle, 90.0)
    fast = render(model, seg)
    ref = render_galsim_box(fast.shape, model.profile, model.pixel_scale, seg, model.flux_per_px,
                            BOX_IDIOM_GSPARAMS)
    assert np.abs(fast - ref).max() < 1e-4 * ref.max()


def test_interior_is_the_pixel_cross_section():
    model = PAPER_550
    image = render(model, Segment(10.0, 200.3, 0.0, 400.0))
    column = image[:, 210]
    rows = np.arange(image.shape[0])
    offsets, e_per_px = model.cross_section(half_width_arcsec=np.inf)
    expected = np.interp((rows - 200.3) * model.pixel_scale, offsets, e_per_px)
    assert np.abs(column - expected).max() < 2e-5 * expected.max()
    assert column.sum() == pytest.approx(model.flux_per_px, rel=5e-5)


def test_translation_by_whole_pixels():
    a = render(COMPOSITE, Segment(100.3, 120.6, 33.0, 80.0))
    b = render(COMPOSITE, Segment(107.3, 115.6, 33.0, 80.0))
    np.testing.assert_allclose(b[15:-15, 15:-15], np.roll(a, (-5, 7), (0, 1))[15:-15, 15:-15],
                               atol=1e-9 * a.max())


def test_reversed_track_of_symmetric_shape_is_identical():
    seg = Segment(120.2, 140.9, 21.0, 150.0)
    back = Segment(seg.x1, seg.y1, 201.0, 150.0)
    a, b = render(DISK_350, seg), render(DISK_350, back)
    assert np.abs(a - b).max() < Budget().tolerance * a.max()


def test_mirror_symmetry_of_box():
    """A box swept along +x on a pixel row is symmetric about that row."""
    a = render(PAPER_550, Segment(50.0, 200.0, 0.0, 200.0))
    np.testing.assert_allclose(a[201:400], a[199:0:-1], atol=1e-9 * a.max())


def test_additivity_of_streaks():
    s1, s2 = Segment(50.3, 60.2, 10.0, 200.0), Segment(80.1, 300.7, -35.0, 180.0)
    both = np.zeros((400, 420))
    render_streak(both, PAPER_550, s1)
    render_streak(both, DISK_350, s2)
    np.testing.assert_allclose(both, render(PAPER_550, s1) + render(DISK_350, s2), rtol=1e-12)


def test_float32_image_accumulates():
    image = np.zeros((400, 420), dtype=np.float32)
    seg = Segment(150.2, 200.3, 12.0, 60.0)
    render_streak(image, PAPER_550, seg)
    ref = render(PAPER_550, seg)
    assert np.abs(image - ref).max() < 1e-6 * ref.max()


def test_footprint_holds_every_significant_pixel():
    """Dense evaluation everywhere: pixels outside the footprint are below the tolerance."""
    budget = Budget()
    swept = SweptProfile(PAPER_550.profile, 0.2, 31.0, budget)
    seg = Segment(150.4, 160.3, 31.0, 40.0)
    shape = (320, 330)
    y, x = np.indices(shape)
    c, s = seg.direction
    t = (x - seg.x0) * c + (y - seg.y0) * s
    d = -(x - seg.x0) * s + (y - seg.y0) * c
    dense = swept.pixel_values(t.ravel(), d.ravel(), seg.length).reshape(shape)
    fy, fx, _, _ = footprint(shape, seg, swept.plan.support_px, swept.plan.cap_px)
    outside = np.ones(shape, bool)
    outside[fy, fx] = False
    assert np.abs(dense[outside]).max() < budget.tolerance * dense.max()
    assert len(fy) == len(set(zip(fy.tolist(), fx.tolist())))  # no pixel twice


@pytest.mark.parametrize("tolerance", [1e-3, 1e-4, 5e-5])
def test_looser_budget_smaller_footprint_and_bounded_error(tolerance):
    seg = Segment(150.3, 200.2, 23.0, 90.0)
    ref = render_galsim_box((400, 420), PAPER_550.profile, 0.2, seg, PAPER_550.flux_per_px,
                            BOX_IDIOM_GSPARAMS)
    image = np.zeros((400, 420))
    result = render_streak(image, PAPER_550, seg, Budget(tolerance, flux_tolerance=tolerance))
    # The Box idiom itself is good to ~2e-5 of the peak.
    assert np.abs(image - ref).max() < (result.plan.total_predicted_error * ref.max()
                                        + 3e-5 * ref.max())


def test_segment_angle_must_match_profile_angle():
    swept = SweptProfile(PAPER_550.profile, 0.2, 10.0)
    with pytest.raises(InputError, match="segment.angle_deg"):
        render_segment(np.zeros((10, 10)), swept, Segment(0, 0, 11.0, 5.0), 1.0)


@pytest.mark.slow  # ~40 s: a no-seeing profile against the brute-force sweep
def test_no_seeing_two_horns():
    """Without an atmosphere the defocused disk streak has two horns and still conserves flux."""
    model = StreakModel(350, 0, shape=Disk(0.5), seeing=Seeing(0.0))
    seg = Segment(30.2, 100.4, 0.0, 140.0)
    image = render(model, seg, shape=(200, 200))
    assert image.sum() == pytest.approx(model.flux_per_px * seg.length, rel=1e-4)
    column = image[:, 100]
    assert column[100] < 0.8 * column.max()  # a dip in the middle


@pytest.mark.parametrize("model", [PAPER_550, COMPOSITE], ids=["box", "comp"])
def test_linear_brightness_ramp_matches_fine_constant_pieces(model):
    """A track whose charge per pixel ramps linearly equals the sum of many short pieces."""
    seg = Segment(120.3, 150.8, 17.0, 60.0)
    f0, f1 = 1000.0, 4000.0
    swept = SweptProfile(model.profile, model.pixel_scale, seg.angle_deg)
    ramp = np.zeros((300, 320))
    render_segment(ramp, swept, seg, f0, f1)
    pieces = np.zeros_like(ramp)
    n = 240
    c, s = seg.direction
    for i in range(n):
        a = seg.length * i / n
        piece = Segment(seg.x0 + a * c, seg.y0 + a * s, seg.angle_deg, seg.length / n)
        render_segment(pieces, swept, piece, f0 + (f1 - f0) * (i + 0.5) / n)
    assert ramp.sum() == pytest.approx(0.5 * (f0 + f1) * seg.length, rel=1e-4)
    assert np.abs(ramp - pieces).max() < 2e-5 * ramp.max()


def test_polyline_with_equal_models_is_the_straight_track():
    from inject import Polyline, render_polyline
    seg = Segment(60.2, 80.7, 25.0, 150.0)
    mid_x, mid_y = seg.x0 + 70 * np.cos(np.radians(25)), seg.y0 + 70 * np.sin(np.radians(25))
    poly = Polyline((seg.x0, mid_x, seg.x1), (seg.y0, mid_y, seg.y1))
    image = np.zeros((300, 320))
    render_polyline(image, poly, [PAPER_550] * 3)
    straight = render(PAPER_550, seg, shape=(300, 320))
    assert np.abs(image - straight).max() < 1e-6 * straight.max()


def test_polyline_brightness_ramp_and_bend_conserve_flux():
    """A bent track whose satellite brightens 4x along it: flux is the trapezoid of its
    vertices' charge per pixel, and the bend joins without gap or overlap."""
    from inject import Polyline, render_polyline
    dim = StreakModel(550, 70, mag=6.5)
    poly = Polyline((300.0, 420.5, 480.0), (300.0, 350.2, 470.9))
    image = np.zeros((800, 820))
    added = render_polyline(image, poly,
                            [dim, PAPER_550, StreakModel(350, 70, mag=5.5)]).charge_added
    lengths = [s.length for s in poly.segments()]
    f = [dim.flux_per_px, PAPER_550.flux_per_px, StreakModel(350, 70, mag=5.5).flux_per_px]
    expected = 0.5 * (f[0] + f[1]) * lengths[0] + 0.5 * (f[1] + f[2]) * lengths[1]
    assert added == pytest.approx(expected, rel=1e-4)
    assert image.sum() == pytest.approx(expected, rel=1e-4)


@pytest.mark.parametrize("height,tolerance,expect_drop", [
    (36000.0, 5e-3, ("defocus",)), (550.0, 5e-3, ()), (36000.0, 5e-5, ())])
def test_dropping_components_and_its_predicted_error(height, tolerance, expect_drop):
    """At GEO the defocus annulus (0.05") is negligible against 0.67" seeing at a loose budget;
    the predicted error of dropping it bounds the measured one."""
    from inject.render import swept_profile

    model = StreakModel(height, 30.0)
    seg = Segment(100.3, 120.7, 31.0, 80.0)
    swept = swept_profile(model, seg.angle_deg, Budget(tolerance, flux_tolerance=5e-5))
    assert set(expect_drop) <= set(swept.plan.dropped)
    if not expect_drop:
        assert swept.plan.dropped == ()
    image = np.zeros((300, 320))
    render_segment(image, swept, seg, model.flux_per_px)
    exact = render(model, seg, shape=(300, 320), budget=Budget(1e-5, flux_tolerance=5e-5))
    measured = np.abs(image - exact).max() / exact.max()
    predicted = swept.plan.total_predicted_error
    assert measured <= predicted + 1e-5


@pytest.mark.parametrize("n_t", [1024, 1025, 3125])
def test_end_cap_antiderivatives_of_a_gaussian_for_odd_and_even_grids(n_t):
    # The exact spectral antiderivative starts at the grid's first sample whatever the parity
    # of the transform size (an odd size once shifted every C by LSF step / (2 period)).
    from scipy.special import erf

    sigma, step = 0.7, 0.05
    k = 2 * np.pi * np.arange(n_t // 2 + 1) / (n_t * step)
    coeffs = np.exp(-(k * sigma) ** 2 / 2)[None, :].astype(complex)
    t = (np.arange(n_t) - n_t // 2) * step
    cdf = 0.5 * (1 + erf(t / (sigma * np.sqrt(2))))
    first = SweptProfile._antiderivative(coeffs, 1, t)[0]
    second = SweptProfile._antiderivative(coeffs, 2, t)[0]
    assert np.abs(first - cdf).max() < 1e-12
    exact = t * cdf + sigma ** 2 * np.exp(-t ** 2 / (2 * sigma ** 2)) / (sigma * np.sqrt(2 * np.pi))
    assert np.abs(second - (exact - exact[0])).max() < 1e-9


def test_wide_profile_at_a_tight_budget_meets_it():
    # A 160 km pass (5" defocus annulus) at tol 2e-5: its ends must meet 0 and LSF(d) (an
    # odd transform size used to leave them 1.6e-4 of the peak off).
    swept = SweptProfile(StreakModel(160, 0).profile, 0.2, 33.0, Budget(2e-5))
    assert swept.plan.predicted_error["cap_table"] <= 2e-5 / 2


def test_next_fast_length_is_scipys():
    from scipy import fft

    from inject.render import next_fast_length
    lengths = list(range(1, 5000)) + [65537, 99991, 1_000_001]
    assert [next_fast_length(n) for n in lengths] == [fft.next_fast_len(n) for n in lengths]


def test_uniform_spline_interpolates_a_cumulative_and_integrates_it_exactly():
    # A cumulative flat at both ends (the end caps' Phi): an error function sampled every
    # 0.05 sigma. Against the function itself (a cubic spline's h^4 error), and the integral
    # against Simpson's rule on each piece of the spline, exact for cubics (independent of
    # the quartic's running sums).
    from scipy import special

    from inject.render import UniformSpline
    t = np.linspace(-6.0, 6.0, 241)
    phi = 0.5 * (1.0 + special.erf(t / np.sqrt(2.0)))
    spline = UniformSpline(t[0], t[1] - t[0], phi)
    assert np.abs(spline(t) - phi).max() < 1e-13  # the filter's rounding
    x = np.linspace(-6.0, 6.0, 4801)
    exact = 0.5 * (1.0 + special.erf(x / np.sqrt(2.0)))
    assert np.abs(spline(x) - exact).max() < 2e-8  # h^4 / 384 max|phi (4)| ~ 1e-8
    assert np.isscalar(spline(0.3)) and np.isscalar(spline.antiderivative(0.3))
    below = t[np.clip(np.searchsorted(t, x, side="right") - 1, 0, len(t) - 2)]
    pieces = (t[1:] - t[:-1]) / 6 * (spline(t[:-1]) + 4 * spline((t[:-1] + t[1:]) / 2)
                                     + spline(t[1:]))
    at_knots = np.concatenate(([0.0], np.cumsum(pieces)))
    rest = (x - below) / 6 * (spline(below) + 4 * spline((below + x) / 2) + spline(x))
    simpson = at_knots[np.searchsorted(t, below)] + rest
    assert np.abs(spline.antiderivative(x) - simpson).max() < 1e-13
    # And the integral of the Gaussian's cumulative, x Phi(x) + pdf(x), from -6.
    f = x * exact + np.exp(-x * x / 2) / np.sqrt(2 * np.pi)
    assert np.abs(spline.antiderivative(x) - (f - f[0])).max() < 1e-8
