"""Track ends of narrow profiles at oblique angles, against the brute-force reference.

A profile of FWHM ~2 px is where the end-cap table's pixel response matters most: the square
pixel, rotated by the track angle in the track frame, shapes the ends at the 1e-3 level, and
at an angle like 23 deg (not a multiple of 45) the pixel seen at +angle and at -angle differ.
Flipping the sign of that rotation errs by 4e-4 of the peak (8x the default budget) for the
Gaussian below and by 1.2-1.5e-3 for a Kolmogorov profile of that width (issue 11), while on
the LSST profiles (FWHM ~7 px) it stays below 4e-5: these tests are what would notice.
The reference (:func:`inject.reference.render_brute_force`, GalSim stamps every 0.02 px) is
good to ~1e-5 of the peak for these profiles (its error falls as step^2, checked below).
"""
import galsim
import numpy as np
import pytest

from inject import Box, Budget, Seeing, Segment, StreakModel, render_brute_force, render_segment
from inject.profile import GSPARAMS
from inject.render import SweptProfile, render_streak

TOL = Budget().tolerance
PIXEL = 0.2
#: A small satellite far away in good seeing: the streak is the seeing, FWHM ~2 px.
SMALL_FAR = StreakModel(20000, 30, shape=Box(1.0, 0.5), seeing=Seeing(0.35))


def ends_error(image, ref):
    return np.abs(image - ref).max() / ref.max()


@pytest.mark.parametrize("angle", [23.0, -23.0, 113.0])
def test_gaussian_fwhm_2px_ends_against_brute_force(angle):
    profile = galsim.Gaussian(fwhm=2.0 * PIXEL, gsparams=GSPARAMS)
    seg = Segment(20.3, 30.6, angle, 24.0) if np.sin(np.radians(angle)) > 0 else \
        Segment(20.3, 40.6, angle, 24.0)
    shape = (72, 64)
    image = np.zeros(shape)
    render_segment(image, SweptProfile(profile, PIXEL, angle), seg, 1.0)
    ref = render_brute_force(shape, profile, PIXEL, seg, 1.0, step_px=0.02)
    assert ends_error(image, ref) <= TOL


@pytest.mark.slow  # ~30 s each: GalSim FFT stamps of a Kolmogorov profile every 0.02 px
@pytest.mark.parametrize("angle", [23.0, -23.0])
def test_small_satellite_in_good_seeing_against_brute_force(angle):
    assert SMALL_FAR.fwhm_arcsec / PIXEL == pytest.approx(1.9, abs=0.2)
    seg = Segment(20.4, 24.3 if angle > 0 else 31.7, angle, 12.0)
    shape = (56, 48)
    image = np.zeros(shape)
    render_streak(image, SMALL_FAR, seg)
    ref = render_brute_force(shape, SMALL_FAR.profile, PIXEL, seg, SMALL_FAR.flux_per_px,
                             step_px=0.02, stamp_half_size_px=24)
    assert ends_error(image, ref) <= TOL


def test_reference_step_converges_for_a_narrow_gaussian():
    """The reference's own error at 0.02 px, from its step^2 convergence, is << TOL."""
    profile = galsim.Gaussian(fwhm=2.0 * PIXEL, gsparams=GSPARAMS)
    seg = Segment(20.3, 30.6, 23.0, 24.0)
    fine, finer = (render_brute_force((72, 64), profile, PIXEL, seg, 1.0, step_px=s)
                   for s in (0.04, 0.02))
    # error(0.02) ~ (fine - finer) / 3 for a second-order rule
    assert np.abs(fine - finer).max() / 3 < TOL / 4 * finer.max()


@pytest.mark.parametrize("length", [0.5, 3.0])
def test_short_narrow_tracks_against_brute_force(length):
    """Tracks shorter than the profile: within the budget of their own (lower) peak, with the
    budget tightened by :func:`inject.render.short_track_budget` as the renderer does."""
    from inject.render import short_track_budget

    profile = galsim.Gaussian(fwhm=2.0 * PIXEL, gsparams=GSPARAMS)
    budget = short_track_budget(Budget(), profile, PIXEL, 23.0, length)
    assert (budget.tolerance < TOL) == (length < 2.0)  # shorter than the profile: tightened
    seg = Segment(24.3, 22.6, 23.0, length)
    shape = (48, 52)
    image = np.zeros(shape)
    render_segment(image, SweptProfile(profile, PIXEL, 23.0, budget), seg, 1.0)
    ref = render_brute_force(shape, profile, PIXEL, seg, 1.0, step_px=0.02)
    assert ends_error(image, ref) <= TOL
    assert image.sum() == pytest.approx(length, rel=1e-4)
