"""The brute-force reference renderer: flux, centroid, closed form, convergence, image edges."""
import galsim
import numpy as np
import pytest
from scipy import special

from inject import Disk, InputError, Segment, StreakModel
from inject.profile import GSPARAMS
from inject.reference import (
    default_stamp_half_size,
    n_steps,
    render_brute_force,
    sample_points,
    with_gsparams,
)

PAPER_550 = StreakModel(550, 70)
DISK_350 = StreakModel(350, 0, shape=Disk(1.0))
SCALE = 0.2
#: A Gaussian of sigma 2.5 px: closed form, and cheap stamps (~0.2 ms each).
GAUSS = galsim.Gaussian(sigma=2.5 * SCALE, gsparams=GSPARAMS)
#: The narrowest profile of the convergence claim: FWHM 2 px.
NARROW = galsim.Gaussian(fwhm=2 * SCALE, gsparams=GSPARAMS)
ANGLES = [0.0, 30.0, 90.0, 137.3]


def brute(model, shape, segment, **kw):
    return render_brute_force(shape, model.profile, model.pixel_scale, segment,
                              model.flux_per_px, **kw)


def centroid(image):
    y, x = np.indices(image.shape)
    w = image.sum()
    return (image * x).sum() / w, (image * y).sum() / w


def gaussian_pixel_fraction(offset, sigma):
    """Fraction of a 1-D Gaussian centred at 0 collected by a pixel centred at ``offset``."""
    r = np.sqrt(2) * sigma
    return 0.5 * (special.erf((offset + 0.5) / r) - special.erf((offset - 0.5) / r))


def test_sampling():
    assert n_steps(1.0, 0.05) == 20  # an exact multiple is not split into 21
    assert n_steps(1.01, 0.05) == 21
    assert n_steps(0.0, 0.05) == 1
    x, y, delta = sample_points(Segment(1.0, 2.0, 90.0, 1.0), 0.25)
    assert delta == 0.25
    np.testing.assert_allclose(y, [2.125, 2.375, 2.625, 2.875])
    np.testing.assert_allclose(x, 1.0, atol=1e-15)


# (1) Total flux.

@pytest.mark.parametrize("model", [PAPER_550, DISK_350], ids=["paper550", "disk350"])
def test_flux_of_lsst_profiles(model):
    # The Kolmogorov tails hold 5.4e-5 of the flux beyond the default 200-px stamp, 2.8e-5
    # beyond 300 px: a 300-px stamp leaves room under 1e-4.
    seg = Segment(350.3, 340.6, 30.0, 1.5)
    image = brute(model, (700, 710), seg, step_px=0.25, stamp_half_size_px=300)
    assert image.sum() == pytest.approx(model.flux_per_px * seg.length, rel=1e-4)


def test_default_stamp_half_size_from_closed_forms():
    # A Gaussian's stepk radius: where the flux outside falls to folding_threshold,
    # exp(-R^2 / 2 sigma^2) = ft, but at least stepk_minimum_hlr half-light radii (GalSim).
    sigma_px = 2.5
    radius = max(sigma_px * np.sqrt(-2 * np.log(GSPARAMS.folding_threshold)),
                 GSPARAMS.stepk_minimum_hlr * sigma_px * np.sqrt(2 * np.log(2)))
    assert default_stamp_half_size(GAUSS, SCALE) == np.ceil(radius) + 1
    # For any profile: half of GalSim's getGoodImageSize (its stepk rule), plus a pixel.
    for model in (PAPER_550, DISK_350):
        size = model.profile.getGoodImageSize(SCALE)
        assert default_stamp_half_size(model.profile, SCALE) == size // 2 + 1


def test_default_stamp_loses_less_than_folding_threshold():
    seg = Segment(250.3, 240.6, 30.0, 0.5)
    image = brute(PAPER_550, (500, 510), seg, step_px=0.25)
    lost = 1 - image.sum() / (PAPER_550.flux_per_px * seg.length)
    assert 0 < lost < GSPARAMS.folding_threshold


@pytest.mark.parametrize("angle", ANGLES)
def test_flux_of_gaussian(angle):
    seg = Segment(40.3 - 15 * np.cos(np.radians(angle)), 40.6 - 15 * np.sin(np.radians(angle)),
                  angle, 30.0)
    image = render_brute_force((80, 82), GAUSS, SCALE, seg, 123.0)
    assert image.sum() == pytest.approx(123.0 * 30.0, rel=1e-4)


# (2) Centroid at the segment's midpoint.

@pytest.mark.parametrize("angle", ANGLES)
def test_centroid_of_paper_profile(angle):
    seg = Segment(300.3, 290.6, angle, 3.0)
    image = brute(PAPER_550, (600, 610), seg, step_px=0.5)
    cx, cy = centroid(image)
    assert cx == pytest.approx(0.5 * (seg.x0 + seg.x1), abs=1e-3)
    assert cy == pytest.approx(0.5 * (seg.y0 + seg.y1), abs=1e-3)


@pytest.mark.parametrize("angle", ANGLES)
def test_centroid_of_long_gaussian_streak(angle):
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    seg = Segment(45.37 - 20 * c, 40.81 - 20 * s, angle, 40.0)
    image = render_brute_force((84, 90), GAUSS, SCALE, seg, 50.0)
    cx, cy = centroid(image)
    assert cx == pytest.approx(0.5 * (seg.x0 + seg.x1), abs=1e-3)
    assert cy == pytest.approx(0.5 * (seg.y0 + seg.y1), abs=1e-3)
    assert (cx, cy) == pytest.approx((45.37, 40.81), abs=1e-3)


# (3) A swept Gaussian against its closed form.

def test_gaussian_sweep_matches_closed_form():
    flux_per_px, y0 = 100.0, 30.3
    seg = Segment(10.2, y0, 0.0, 60.0)
    image = render_brute_force((60, 80), GAUSS, SCALE, seg, flux_per_px, step_px=0.05)
    interior = image[:, 35:45]  # > 20 px (8 sigma) from both ends
    np.testing.assert_allclose(interior.sum(axis=0), flux_per_px, rtol=1e-4)
    expected = flux_per_px * gaussian_pixel_fraction(np.arange(60) - y0, 2.5)
    assert np.abs(interior - expected[:, None]).max() < 1e-4 * expected.max()
    # Including the ends: a pixel collects F * g(dy) * integral_{x - x1}^{x - x0} g(u) du, with
    # g the pixel-integrated 1-D Gaussian, whose integral is sigma * psi(z), psi = z Phi + phi.
    def psi(z):
        return z * special.ndtr(z) + np.exp(-0.5 * z ** 2) / np.sqrt(2 * np.pi)

    x, sig = np.arange(80.0), 2.5
    along = sig * (psi((x - seg.x0 + 0.5) / sig) - psi((x - seg.x0 - 0.5) / sig)
                   - psi((x - seg.x1 + 0.5) / sig) + psi((x - seg.x1 - 0.5) / sig))
    assert np.abs(image - expected[:, None] * along[None, :]).max() < 1e-4 * expected.max()


# (4) Convergence in step_px.

def test_halving_the_step_paper_profile():
    seg = Segment(250.3, 240.6, 30.0, 0.5)  # two end caps, the worst case
    coarse = brute(PAPER_550, (500, 510), seg, step_px=0.05)
    fine = brute(PAPER_550, (500, 510), seg, step_px=0.025)
    assert np.abs(fine - coarse).max() < 2e-5 * fine.max()


def test_halving_the_step_narrow_gaussian_is_second_order():
    seg = Segment(10.2, 30.3, 25.0, 30.0)
    images = {step: render_brute_force((60, 60), NARROW, SCALE, seg, 100.0, step_px=step)
              for step in (0.1, 0.05, 0.025)}
    peak = images[0.025].max()
    change_coarse = np.abs(images[0.1] - images[0.05]).max() / peak
    change_default = np.abs(images[0.05] - images[0.025]).max() / peak
    assert change_default < 5e-5
    assert change_coarse / change_default == pytest.approx(4, rel=0.15)


# (5) Image edges.

def test_segment_outside_the_image_draws_nothing():
    seg = Segment(-100.0, -80.0, 45.0, 30.0)  # beyond the 17-px stamps
    image = render_brute_force((60, 70), GAUSS, SCALE, seg, 100.0)
    assert not image.any()
    assert default_stamp_half_size(GAUSS, SCALE) < 60


@pytest.mark.parametrize("angle", [0.0, 30.0, 137.3])
def test_segment_ending_inside_has_the_flux_of_its_inside_part(angle):
    # The track enters through one edge far from the corners and ends well inside. A symmetric
    # profile loses across the edge exactly what the part outside spills in, so the flux inside
    # is flux_per_px times the length inside.
    shape = (100, 120)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    seg = Segment(60.3 - 120 * c, 70.6 - 120 * s, angle, 120.0)
    t0, t1 = seg.clip(shape)
    assert t0 > 20 and t1 == 120.0  # starts > 8 sigma outside, ends inside
    image = render_brute_force(shape, GAUSS, SCALE, seg, 100.0)
    assert image.sum() == pytest.approx(100.0 * (t1 - t0), rel=1e-4)


def test_clipped_stamps_match_unclipped():
    # Stamps cut by the image edge give the same pixels as in a larger image.
    seg = Segment(1.3, -2.4, 30.0, 1.0)
    small = brute(PAPER_550, (40, 50), seg, step_px=0.5)
    big = brute(PAPER_550, (440, 450), Segment(201.3, 197.6, 30.0, 1.0), step_px=0.5)
    np.testing.assert_allclose(small, big[200:240, 200:250], rtol=0, atol=1e-12 * big.max())


# Odds and ends.

def test_zero_length_draws_nothing():
    image = render_brute_force((40, 40), GAUSS, SCALE, Segment(20.0, 20.0, 10.0, 0.0), 100.0)
    assert image.dtype == np.float64 and image.shape == (40, 40) and not image.any()


def test_adds_into_a_given_image():
    seg = Segment(10.0, 20.0, 0.0, 20.0)
    fresh = render_brute_force((40, 50), GAUSS, SCALE, seg, 10.0)
    base = np.full((40, 50), 7.0)
    out = render_brute_force((40, 50), GAUSS, SCALE, seg, 10.0, image=base)
    assert out is base
    np.testing.assert_allclose(base, fresh + 7.0, rtol=1e-14)
    # Non-contiguous views are written too.
    big = np.zeros((40, 100))
    view = big[:, ::2]
    render_brute_force((40, 50), GAUSS, SCALE, seg, 10.0, image=view)
    np.testing.assert_array_equal(big[:, ::2], fresh)
    assert not big[:, 1::2].any()


def test_gsparams_replace_the_profile_ones():
    seg = Segment(20.0, 20.0, 0.0, 5.0)
    a = render_brute_force((40, 50), galsim.Gaussian(sigma=0.5), SCALE, seg, 10.0,
                           gsparams=GSPARAMS)
    b = render_brute_force((40, 50), GAUSS, SCALE, seg, 10.0)
    np.testing.assert_array_equal(a, b)


def test_gsparams_apply_to_a_profile_already_used():
    # GalSim's withGSParams keeps a Convolution's cached stepk/maxk; with_gsparams must not.
    loose = galsim.GSParams(folding_threshold=5e-3, maxk_threshold=1e-3)
    parts = [galsim.Kolmogorov(fwhm=0.7), galsim.TopHat(1.0)]
    used = galsim.Convolve(parts, gsparams=GSPARAMS)
    tight_stepk = used.stepk
    fresh = galsim.Convolve(parts, gsparams=loose)
    swapped = with_gsparams(used, loose)
    assert (swapped.stepk, swapped.maxk) == (fresh.stepk, fresh.maxk)
    assert used.stepk == tight_stepk and used.gsparams == GSPARAMS  # the original is untouched
    assert default_stamp_half_size(swapped, SCALE) < default_stamp_half_size(used, SCALE) / 5
    seg = Segment(30.2, 30.7, 20.0, 2.0)
    a = render_brute_force((60, 60), used, SCALE, seg, 10.0, step_px=0.5, gsparams=loose)
    b = render_brute_force((60, 60), fresh, SCALE, seg, 10.0, step_px=0.5)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("kw", [dict(step_px=0), dict(pixel_scale=-1.0),
                                dict(flux_per_px=np.nan), dict(shape=(0, 5)),
                                dict(image=np.zeros((40, 50), dtype=np.float32)),
                                dict(image=np.zeros((41, 50))), dict(profile="gauss"),
                                dict(image=np.broadcast_to(0.0, (40, 50)))])
def test_bad_input(kw):
    args = dict(shape=(40, 50), profile=GAUSS, pixel_scale=SCALE,
                segment=Segment(20.0, 20.0, 0.0, 5.0), flux_per_px=10.0)
    args.update(kw)
    with pytest.raises(InputError):
        render_brute_force(**args)
