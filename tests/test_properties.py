"""Property tests (hypothesis) of the streak engine and the writers, and regression tests of
bugs found by ``scripts/stress.py`` (narrow profiles' end caps, short tracks' own peak and
flux, lines outside the image, saturation on a cut-out).

Properties: flux conservation, translation by whole pixels, rotation by 90 deg about a pixel
centre, reversal of symmetric shapes, additivity, brightness monotonic in magnitude, agreement
with the closed form of a swept Gaussian, FITS and EXR round trips.
"""
import math
import os
import tempfile

import galsim
import numpy as np
import pytest
from astropy.io import fits
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from inject import (
    Box,
    Disk,
    SceneResult,
    Segment,
    StreakModel,
    Track,
    parse_scene,
    read_exposure,
    simulate,
    write_exposure,
    write_exr,
)
from inject.io.exr import read_exr
from inject.profile import GSPARAMS
from inject.render import (
    Budget,
    SweptProfile,
    render_segment,
    render_streak,
    short_track_budget,
    swept_profile,
)
from inject.scene import render_tracks

PAPER = StreakModel(550, 70)
DISK = StreakModel(550, 40, shape=Disk(1.0))
TOL = Budget().tolerance
FAST = settings(max_examples=12, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])

#: Examples of the properties whose short tracks build tight tables at each new angle (up to
#: seconds an example): 6 in the default suite, 12 in ``make slow`` (INJECT_TEST_EXAMPLES=12).
TABLES = settings(FAST, max_examples=int(os.environ.get("INJECT_TEST_EXAMPLES", "6")))

angles = st.floats(0.0, 360.0, allow_nan=False, exclude_max=True)
fractions = st.floats(0.0, 1.0, allow_nan=False, exclude_max=True)


def padded_render(model, angle, fx, fy, length, dtype=np.float64):
    """Render a track on an image that holds its whole footprint; return image, segment."""
    swept = swept_profile(model, angle)
    c, s = abs(math.cos(math.radians(angle))), abs(math.sin(math.radians(angle)))
    sup, cap = swept.plan.support_px, swept.plan.cap_px
    nx = 2 * math.ceil((length / 2 + cap) * c + sup * s + 4) + 1
    ny = 2 * math.ceil((length / 2 + cap) * s + sup * c + 4) + 1
    a = math.radians(angle)
    seg = Segment(round(nx // 2 - length / 2 * math.cos(a)) + fx,
                  round(ny // 2 - length / 2 * math.sin(a)) + fy, angle, length)
    image = np.zeros((ny, nx), dtype)
    render_segment(image, swept, seg, model.flux_per_px)
    return image, seg


# --- Flux conservation ---------------------------------------------------------------------

@FAST
@given(angle=angles, fx=fractions, fy=fractions, length=st.floats(5.0, 150.0))
def test_flux_is_conserved(angle, fx, fy, length):
    image, seg = padded_render(PAPER, angle, fx, fy, length)
    expected = PAPER.flux_per_px * seg.length
    assert np.isfinite(image).all()
    # The footprint leaves out at most flux_tolerance (5e-5) of the seeing wings.
    assert image.sum() == pytest.approx(expected, rel=1e-4)
    assert image.sum() <= expected * (1 + 1e-6)


# --- Translation by whole pixels -----------------------------------------------------------

@FAST
@given(angle=angles, fx=fractions, fy=fractions, length=st.floats(0.5, 60.0),
       dx=st.integers(-15, 15), dy=st.integers(-15, 15))
def test_translation_by_whole_pixels(angle, fx, fy, length, dx, dy):
    shape = (520, 540)
    swept = swept_profile(PAPER, angle)
    x0, y0 = 250 + fx, 240 + fy
    a = np.zeros(shape)
    b = np.zeros(shape)
    render_segment(a, swept, Segment(x0, y0, angle, length), PAPER.flux_per_px)
    render_segment(b, swept, Segment(x0 + dx, y0 + dy, angle, length), PAPER.flux_per_px)
    # Compare away from the image edges, where the footprint is clipped differently.
    inner = (slice(20, -20), slice(20, -20))
    shifted = np.roll(a, (dy, dx), axis=(0, 1))
    # Track-frame coordinates are recomputed from shifted origins: equal to rounding, except
    # that a pixel at the footprint's border (value < tol/2 of the peak) may flip in or out.
    np.testing.assert_allclose(b[inner], shifted[inner], rtol=0,
                               atol=TOL / 2 * PAPER.peak_e_per_px)
    np.testing.assert_allclose(b.sum(), a.sum(), rtol=1e-9)


# --- Rotation by 90 degrees about a pixel centre -------------------------------------------

@TABLES
@given(angle=angles, fx=st.floats(-20, 20), fy=st.floats(-20, 20),
       length=st.floats(0.5, 60.0))
def test_rotation_by_90_degrees(angle, fx, fy, length):
    n = 161
    c = (n - 1) // 2  # the centre pixel; the square image maps onto itself
    x0, y0 = c + fx, c + fy
    a = np.zeros((n, n))
    render_streak(a, PAPER, Segment(x0, y0, angle, length))
    # (x, y) -> (c - (y - c), c + (x - c)): new[x, n-1-y] = old[y, x].
    b = np.zeros((n, n))
    render_streak(b, PAPER, Segment(c - (y0 - c), c + (x0 - c), angle + 90.0, length))
    np.testing.assert_allclose(b, a.T[:, ::-1], rtol=0, atol=TOL * PAPER.peak_e_per_px)


# --- Reversal of symmetric shapes ----------------------------------------------------------

@TABLES
@given(angle=angles, fx=fractions, fy=fractions, length=st.floats(0.5, 80.0),
       model=st.sampled_from([PAPER, DISK]))
def test_reversed_track_of_symmetric_shape(angle, fx, fy, length, model):
    # A box and a disk are symmetric under a half turn, as are the annulus and the seeing.
    shape = (300, 300)
    seg = Segment(150 + fx - length / 2 * math.cos(math.radians(angle)),
                  150 + fy - length / 2 * math.sin(math.radians(angle)), angle, length)
    back = Segment(seg.x1, seg.y1, angle + 180.0, length)
    a, b = np.zeros(shape), np.zeros(shape)
    render_streak(a, model, seg)
    render_streak(b, model, back)
    assert np.abs(a - b).max() <= TOL * model.peak_e_per_px


# --- Additivity ----------------------------------------------------------------------------

@TABLES
@given(a1=angles, a2=angles, x1=st.floats(40, 160), y1=st.floats(40, 160),
       x2=st.floats(40, 160), y2=st.floats(40, 160), l1=st.floats(0.1, 100),
       l2=st.floats(0.1, 100))
def test_streaks_add(a1, a2, x1, y1, x2, y2, l1, l2):
    shape = (200, 210)
    s1, s2 = Segment(x1, y1, a1, l1), Segment(x2, y2, a2, l2)
    both = np.zeros(shape)
    render_streak(both, PAPER, s1)
    render_streak(both, DISK, s2)
    one, two = np.zeros(shape), np.zeros(shape)
    render_streak(one, PAPER, s1)
    render_streak(two, DISK, s2)
    peak = max(PAPER.peak_e_per_px, DISK.peak_e_per_px)
    np.testing.assert_allclose(both, one + two, rtol=0, atol=1e-12 * peak)


# --- Brightness monotonic in magnitude -----------------------------------------------------

@settings(max_examples=30, deadline=None)
@given(m1=st.floats(-5, 25), dm=st.floats(0.01, 10), height=st.floats(160, 36000),
       zenith=st.floats(0, 89.9))
def test_brightness_decreases_with_magnitude(m1, dm, height, zenith):
    bright = StreakModel(height, zenith, shape=Box(2.0, 1.0), mag=m1)
    faint = StreakModel(height, zenith, shape=Box(2.0, 1.0), mag=m1 + dm)
    assert bright.flux_per_px > faint.flux_per_px > 0
    assert bright.flux_per_px / faint.flux_per_px == pytest.approx(10 ** (0.4 * dm), rel=1e-9)
    # Same geometry and profile, so the peak scales with the flux.
    assert bright.peak_e_per_px / faint.peak_e_per_px == pytest.approx(10 ** (0.4 * dm),
                                                                       rel=1e-9)
    assert bright.apparent_mag < faint.apparent_mag


@settings(max_examples=8, deadline=None)
@given(m1=st.floats(-5, 25), dm=st.floats(0.01, 10), angle=angles)
def test_rendered_streak_scales_with_magnitude(m1, dm, angle):
    shape = (120, 130)
    seg = Segment(40.3, 50.6, angle, 30.0)
    images = []
    for mag in (m1, m1 + dm):
        image = np.zeros(shape)
        render_streak(image, StreakModel(550, 70, mag=mag), seg)
        images.append(image)
    assert images[0].max() > images[1].max()
    assert images[0].sum() > images[1].sum()
    np.testing.assert_allclose(images[1] * 10 ** (0.4 * dm), images[0], rtol=1e-9,
                               atol=1e-12 * images[0].max())


# --- An exact reference: a Gaussian swept along a row --------------------------------------

def swept_gaussian(shape, sigma, seg, flux):
    """Closed form: unit-flux Gaussian (sigma px) swept along +x, pixel-integrated."""
    from inject.reference import swept_gaussian as closed_form

    return closed_form(shape, sigma, seg, flux)


def gaussian_error(fwhm_px, x0, y0, length):
    """Largest error of the renderer against the closed form, relative to the long-streak
    peak (the peak of ``F p LSF``)."""
    sigma = fwhm_px / (2 * math.sqrt(2 * math.log(2)))
    swept = SweptProfile(galsim.Gaussian(sigma=sigma * 0.2, gsparams=GSPARAMS), 0.2, 0.0)
    seg = Segment(x0, y0, 0.0, length)
    image = np.zeros((80, 100))
    render_segment(image, swept, seg, 1.0)
    ref = swept_gaussian(image.shape, sigma, seg, 1.0)
    return np.abs(image - ref).max() / (swept.lsf.lsf.max() * 0.2), image, ref


@settings(max_examples=10, deadline=None)
@given(fwhm_px=st.floats(2.0, 6.0), fx=fractions, fy=fractions, length=st.floats(0.1, 40.0))
def test_swept_gaussian_matches_closed_form(fwhm_px, fx, fy, length):
    error, image, ref = gaussian_error(fwhm_px, 30 + fx, 40 + fy, length)
    assert error <= TOL
    if length >= 5:  # shorter tracks: see test_short_track_flux
        assert image.sum() == pytest.approx(ref.sum(), rel=1e-4)


# --- FITS and EXR round trips --------------------------------------------------------------

SCENE = parse_scene({"detector": {"type": "itl", "nx": 8, "ny": 8}, "sky": False,
                     "stars": False, "noise": False})


def float32_arrays(shape):
    return hnp.arrays(np.float32, shape, elements=st.floats(
        width=32, allow_nan=True, allow_infinity=True, allow_subnormal=True))


@st.composite
def scene_results(draw):
    shape = draw(st.tuples(st.integers(1, 12), st.integers(1, 12)))
    return SceneResult(
        image=draw(float32_arrays(shape)), variance=draw(float32_arrays(shape)),
        streak_model=draw(float32_arrays(shape)),
        mask=draw(hnp.arrays(np.int32, shape)),
        truth=[], sky_level=0.0, noise_sigma=0.0)


def same_bits(a, b):
    """Equal as float32, NaN included (NaN payloads need not survive)."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return a.shape == b.shape and bool(np.all((a == b) | (np.isnan(a) & np.isnan(b))))


@settings(max_examples=25, deadline=None)
@given(result=scene_results())
def test_fits_round_trip(result):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "out.fits")
        write_exposure(path, SCENE, result, 1.5)
        with fits.open(path) as hdus:
            assert same_bits(hdus["IMAGE"].data, result.image)
            assert same_bits(hdus["VARIANCE"].data, result.variance)
            assert same_bits(hdus["STREAK_MODEL"].data, result.streak_model)
            np.testing.assert_array_equal(hdus["MASK"].data, result.mask)
            assert hdus["IMAGE"].header["GAIN"] == 1.5
        exposure = read_exposure(path)  # inject's own reader
        assert same_bits(exposure.image, result.image)


@settings(max_examples=25, deadline=None)
@given(result=scene_results())
def test_exr_round_trip(result):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "out.exr")
        write_exr(path, SCENE, result)
        back = read_exr(path)
    assert same_bits(back["image"], result.image)
    assert same_bits(back["variance"], result.variance)
    assert same_bits(back["streak_model"], result.streak_model)
    np.testing.assert_array_equal(back["mask"], result.mask)
    assert back["mask"].dtype == np.int32
    assert back["header"]["BAND"] == "g"


# --- Known bugs (found by scripts/stress.py) -----------------------------------------------

@pytest.mark.parametrize("kind", ["view", "fortran"])
def test_render_into_non_contiguous_image(kind):
    if kind == "view":
        image = np.zeros((300, 320))[:, :300]
    else:
        image = np.zeros((300, 300), order="F")
    seg = Segment(120.3, 140.6, 30.0, 20.0)
    render_streak(image, PAPER, seg)
    expected = np.zeros((300, 300))
    render_streak(expected, PAPER, seg)
    np.testing.assert_array_equal(image, expected)


@pytest.mark.parametrize("fwhm_px", [1.0, 1.5])
def test_narrow_profile_end_caps_within_budget(fwhm_px):
    error, _, _ = gaussian_error(fwhm_px, 30.3, 40.2, 20.0)
    assert error <= TOL


def test_short_track_error_relative_to_its_own_peak():
    # A track shorter than the profile along it peaks lower than a long streak: its budget is
    # scaled by the ratio (down to AUTO_MIN_TOLERANCE) so the error stays relative to its own peak.
    sigma_px = 1.5  # an exact reference: a Gaussian of FWHM 3.5 px, a 0.1 px track
    profile = galsim.Gaussian(sigma=sigma_px * 0.2, gsparams=GSPARAMS)
    budget = short_track_budget(Budget(), profile, 0.2, 0.0, 0.1)
    assert budget.tolerance < Budget().tolerance / 20
    swept = SweptProfile(profile, 0.2, 0.0, budget)
    seg = Segment(30.3, 40.2, 0.0, 0.1)
    image = np.zeros((80, 100))
    render_segment(image, swept, seg, 1.0)
    ref = swept_gaussian(image.shape, sigma_px, seg, 1.0)
    assert np.abs(image - ref).max() <= TOL * ref.max()


@pytest.mark.parametrize("angle,length", [(0.0, 0.3), (0.0, 0.1), (45.0, 0.1), (90.0, 0.1),
                                          (45.0, 1.0), (1e-9, 0.3), (23.7, 2.0)])
def test_short_track_flux(angle, length):
    # The end-cap table blends into its limits (no step), so C(t) - C(t - L) keeps its flux
    # for tracks far shorter than a pixel; only the wings beyond the support are left out.
    image, seg = padded_render(PAPER, angle, 0.3, 0.7, length)
    assert image.sum() == pytest.approx(PAPER.flux_per_px * seg.length, rel=1e-4)


@pytest.mark.slow  # ~1 min: a 37" wide profile's swept tables
def test_crossing_line_outside_image_within_support():
    model = StreakModel(550, 0, shape=Box(1.0, 100.0))
    swept = swept_profile(model, 0.0)
    shape = (64, 64)
    y0 = -0.5 - swept.plan.cap_px - 1
    image, truth = render_tracks(shape, [model], [Track(10.0, y0, 0.0)])
    line = np.zeros(shape)
    render_segment(line, swept, Segment(-2000.0, y0, 0.0, 4000.0), model.flux_per_px)
    assert line.max() > 0.1 * model.peak_e_per_px  # the profile does reach the image
    assert np.abs(image - line).max() <= TOL * model.peak_e_per_px


def test_saturating_streak_on_e2v_cutout():
    scene = parse_scene({
        "seed": 3, "band": "g", "zenith": 70, "detector": {"type": "e2v", "nx": 256, "ny": 200},
        "sky": True, "stars": False, "noise": True,
        "satellites": [{"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65},
                        "mag": -5.0, "track": {"x0": 20.3, "y0": 30.7, "angle": 25.0}}]})
    result = simulate(scene)
    assert np.isfinite(result.image).all()
    assert result.image.max() <= scene.detector.full_well + 10 * scene.detector.read_noise
