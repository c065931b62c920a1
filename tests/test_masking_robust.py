"""Masking where it used to give wrong answers silently (issue 11): streaks at image edges,
images with holes, close parallel streaks, bad thresholds, huge values.

Truth comes from the simulator (the track and the line-spread FWHM it renders); closed forms
are used for the profile-level checks. Larger sweeps (limits per angle) are in
``scripts/bench_mask.py --sections limits``.
"""
import json
import math

import numpy as np
import pytest

from inject import DEFAULT_SCENE, InputError, apply_overrides, parse_scene, simulate, write_exposure
from inject.cli.main import main
from inject.masking.detect import BAD_PLANES, detect_streaks, prepare
from inject.masking.geometry import Line
from inject.masking.mask import FALLBACK_MAX_PX, mask_spans, paint
from inject.masking.measure import (
    Profile,
    _robust_line_fit,
    half_max_width,
    profile_fwhm,
    wing_reach,
)
from inject.masking.run import MaskResult, analyse
from inject.scene import MASK_PLANES

BAD_BITS = sum(1 << MASK_PLANES[p] for p in BAD_PLANES)


def satellite(mag, x0, y0, angle, height=550):
    """The paper's satellite (7.25 x 2.65 m box) on a track crossing the image."""
    return {"height": height, "shape": {"type": "box", "length": 7.25, "width": 2.65},
            "mag": mag, "track": {"x0": float(x0), "y0": float(y0), "angle": float(angle)}}


def simulated(satellites, seed, size=512):
    raw = apply_overrides(DEFAULT_SCENE, [f"seed={seed}", f"detector.nx={size}",
                                          f"detector.ny={size}"])
    raw["satellites"] = satellites
    return simulate(parse_scene(raw))


def true_line(row):
    return Line(row["x0"], row["y0"], row["x1"], row["y1"])


def distance_to(line, streak):
    """Largest distance (px) of a found streak's two ends from a true line."""
    return max(abs(line.coordinates(streak[f"x{k}"], streak[f"y{k}"])[1]) for k in (0, 1))


# ---------------------------------------------------------------------------------------------
# Profiles cut by an edge (closed forms)


def gaussian_profile(sigma, amp, cut=None, step=0.1, half=30.0, pixel=False):
    """A noise-free Gaussian profile; bins beyond ``cut`` (px, positive side) hold no pixels.
    ``pixel``: the Gaussian convolved with a 1-px box (the pixel values of a 0-deg track)."""
    from scipy.special import erf

    d = np.arange(-half, half, step) + 0.5 * step
    if pixel:
        z = np.sqrt(2) * sigma
        value = amp * 0.5 * (erf((d + 0.5) / z) - erf((d - 0.5) / z))
    else:
        value = amp * np.exp(-0.5 * (d / sigma) ** 2)
    count = np.full(d.size, 100)
    if cut is not None:
        count[d > cut] = 0
        value[d > cut] = np.nan
    return Profile(d, value, count, 1.0, 0.0, 0.0)


def test_fwhm_of_a_cut_profile_is_measured_or_flagged():
    sigma = 3.0
    fwhm = 2 * np.sqrt(2 * np.log(2)) * sigma
    # Pixel values of a 0-deg track (the Gaussian times a 1-px box) cut well beyond the half
    # maximum: the pixel response removed, the Gaussian's own FWHM (closed form).
    f, _, centre, _ = profile_fwhm(gaussian_profile(sigma, 10.0, cut=3 * sigma, pixel=True))
    assert f == pytest.approx(fwhm, rel=1e-3) and abs(centre) < 0.02
    # Cut inside the half maximum (a streak within half a FWHM of the edge): no FWHM, not a
    # crossing invented at the cut.
    for cut in (0.0, 0.3 * fwhm, 0.5 * fwhm):
        f, _, centre, _ = profile_fwhm(gaussian_profile(sigma, 10.0, cut=cut, pixel=True))
        assert math.isnan(f) and math.isnan(centre)


def test_line_fit_is_not_pulled_by_one_heavy_segment():
    """Segment offsets on the line s = 0.1 + 0.002 t (17 segments, weight 1) and one on a
    star beside it: 2.5 px off with 5 times the weight (its amplitude). The fit is the line,
    to rounding; a weighted least-squares start is pulled 1.4 px towards the star and would
    see every other segment as an outlier (the old fit ended 1.3 px off)."""
    t = np.arange(-200.0, 201.0, 25.0)
    s = 0.1 + 0.002 * t
    w = np.ones(t.size)
    s[10] -= 2.5
    w[10] = 5.0
    a, b = _robust_line_fit(t, s, w)
    assert a == pytest.approx(0.1, abs=1e-9) and b == pytest.approx(0.002, abs=1e-12)


def test_wing_reach_is_one_sided_at_a_cut():
    sigma, amp, level = 3.0, 10.0, 1.0
    reach = sigma * np.sqrt(2 * np.log(amp / level))  # closed form of the level crossing
    left, right = wing_reach(gaussian_profile(sigma, amp), level, smooth_px=0.5)
    assert left == pytest.approx(reach, abs=0.02) and right == pytest.approx(reach, abs=0.02)
    # Cut before the level is reached: that side is not measured (NaN), the other is.
    left, right = wing_reach(gaussian_profile(sigma, amp, cut=0.5 * reach), level,
                             smooth_px=0.5)
    assert left == pytest.approx(reach, abs=0.02) and math.isnan(right)
    # A window too small on a measured side: None (the window must grow).
    left, right = wing_reach(gaussian_profile(sigma, amp, half=0.8 * reach), level, 0.5)
    assert left is None and right is None


def test_half_max_width_with_a_dip_limit_keeps_one_of_two_streaks():
    d = np.linspace(-30, 30, 6001)
    s = 7.3 / 2.3548
    pair = np.exp(-0.5 * (d / s) ** 2) + 0.9 * np.exp(-0.5 * ((d - 24) / s) ** 2)
    fwhm, centre, _ = half_max_width(d, pair, dip=0.25)
    assert fwhm == pytest.approx(7.3, rel=1e-3) and abs(centre) < 1e-3


# ---------------------------------------------------------------------------------------------
# Edge streaks


@pytest.mark.parametrize("angle, x0, y0", [
    (0.0, 0.0, 3.0),      # 3.5 px from the bottom edge (y = -0.5)
    (0.0, 0.0, 6.0),
    (0.0, 0.0, 508.0),    # 3.5 px from the top edge
    (90.0, 508.0, 0.0),   # vertical, 3.5 px from the right edge (the x = 1020)
    (90.0, 3.0, 0.0),     # 3.5 px from the left edge
    (1.0, 0.0, 3.0),      # leaves the edge slowly: 3 to 12 px
    (45.0, 30.0, 0.0),    # diagonal past a corner: ~21 px from it
])
def test_edge_streaks_are_located_and_masked_within_bounds(angle, x0, y0):
    r = simulated([satellite(10.5, x0, y0, angle)], seed=11)
    res = analyse(r.image, bad=(r.mask & BAD_BITS) != 0, n_boot=10)
    assert len(res.streaks) == 1
    s, truth = res.streaks[0], r.truth[0]
    fwhm_true = truth["fwhm_arcsec"] / 0.2
    line = true_line(truth)
    assert distance_to(line, s) < 1.0  # the line where the streak is, not pulled inward
    if s["fwhm_measured"]:
        assert s["fwhm_px"] == pytest.approx(fwhm_true, rel=0.05)
    else:
        assert math.isnan(s["fwhm_px"])
    # The mask is bounded (never the hundreds of px of a failed measurement; a normal one
    # here is ~1.2 FWHM) and covers the simulator's truth STREAK plane (drawn where the
    # streak is above 1 sky sigma, the sb rule's level).
    assert s["mask_width_px"] <= 3 * fwhm_true
    assert res.masked_pixels < 0.03 * r.image.size
    mask = paint(np.zeros(r.image.shape, bool), mask_spans(r.image.shape, Line(
        s["x0"], s["y0"], s["x1"], s["y1"]), s["mask_width_px"]))
    truth_plane = ((r.mask >> MASK_PLANES["STREAK"]) & 1).astype(bool)
    # At most one row of the 8 of this faint streak's 1-sigma region is left out (pixels
    # right at the level, with the line a few tenths of a pixel off).
    assert mask[truth_plane].mean() > 0.85
    # JSON: no NaN, the flag says what was not measured.
    text = json.dumps(res.to_json(), allow_nan=False)
    row = json.loads(text)["streaks"][0]
    assert row["fwhm_measured"] == s["fwhm_measured"]
    assert (row["fwhm_px"] is None) == (not s["fwhm_measured"])


def test_fallback_mask_is_bounded_and_said():
    """A profile cut on both sides (a streak in a slit between two holes) has no measured
    drop: the mask falls back to the stated bounded rule."""
    from inject.masking.mask import FALLBACK_FWHM, sb_width
    from inject.masking.measure import Measurement

    p = gaussian_profile(3.0, 10.0, cut=2.0)
    p.count[p.distance < -2.0] = 0
    p.value[p.distance < -2.0] = np.nan
    m = Measurement(line=Line(0, 0, 100, 0), at_edge=(True, True), fwhm_px=float("nan"),
                    fwhm_err_px=float("nan"), fwhm_pixelated_px=float("nan"), peak=10.0,
                    profile=p, gaussian_sigma_px=float("nan"), moffat_alpha_px=float("nan"),
                    snr=50.0, width_px=7.0, fwhm_measured=False)
    width, rule = sb_width(m, 1.0, 1.0)
    assert width == pytest.approx(FALLBACK_FWHM * 7.0)
    assert "not measured" in rule and "FWHM" in rule
    m.width_px = 1000.0  # a nonsense width estimate stays bounded too
    assert sb_width(m, 1.0, 1.0)[0] == FALLBACK_MAX_PX


# ---------------------------------------------------------------------------------------------
# Holes


def _holes(shape_name, image):
    """Image with a hole of the named shape (NaN, zeros or a mask) and the bad mask."""
    ny, nx = image.shape
    yy, xx = np.indices(image.shape)
    img = image.astype(np.float32).copy()
    bad = np.zeros(image.shape, dtype=bool)
    if shape_name == "half_nan":
        img[:, : nx // 2] = np.nan
    elif shape_name == "vignetted_corners":
        img[np.hypot(xx - nx / 2, yy - ny / 2) > 0.6 * nx] = np.nan
    elif shape_name == "bad_columns":
        for x, w in ((60, 1), (200, 3), (330, 8), (331 + 40, 1)):
            bad[:, x:x + w] = True
    elif shape_name == "mosaic_gap_zeros":
        img[:, 240:290] = 0.0  # a CCD gap filled with zeros (zero weight, no flag)
        img[300:330, :] = 0.0
    elif shape_name == "masked_band":
        bad[np.abs(yy - 0.7 * xx - 100) < 30] = True  # NO_DATA band at an angle
    return img, bad


@pytest.mark.parametrize("shape_name", ["half_nan", "vignetted_corners", "bad_columns",
                                        "mosaic_gap_zeros", "masked_band"])
@pytest.mark.parametrize("seed", [1, 5, 6])
def test_holes_raise_no_detections(shape_name, seed):
    """Streak-free images (seeds 1-6 include the issue's 5 failing ones for the half plane);
    pytest turns any RuntimeWarning into an error."""
    r = simulated([], seed)
    img, bad = _holes(shape_name, r.image)
    res = analyse(img, bad=bad | ((r.mask & BAD_BITS) != 0), n_boot=0)
    assert res.streaks == [] and res.masked_pixels == 0


def test_streak_found_beside_a_hole():
    r = simulated([satellite(11.0, 380.0, 100.0, 70.0)], seed=3)
    img, bad = _holes("half_nan", r.image)
    res = analyse(img, bad=bad, n_boot=0)
    assert len(res.streaks) == 1
    s = res.streaks[0]
    assert distance_to(true_line(r.truth[0]), s) < 1.0
    assert s["fwhm_px"] == pytest.approx(r.truth[0]["fwhm_arcsec"] / 0.2, rel=0.05)


# ---------------------------------------------------------------------------------------------
# Close parallel streaks


@pytest.mark.parametrize("separation", [24.0, 40.0, 100.0, 250.0])
def test_close_parallel_streaks_are_both_found(separation):
    """Mag 9 at 30 deg (the issue's case): the mask is ~12 px wide, so 24 px is twice it."""
    a = math.radians(30.0)
    nx, ny = -math.sin(a), math.cos(a)
    x0, y0 = 200.0 - 0.5 * separation * nx, 250.0 - 0.5 * separation * ny
    r = simulated([satellite(9.0, x0, y0, 30.0),
                   satellite(9.0, x0 + separation * nx, y0 + separation * ny, 30.0)], seed=7)
    res = analyse(r.image, bad=(r.mask & BAD_BITS) != 0, n_boot=0)
    assert len(res.streaks) == 2
    for truth in r.truth:
        line = true_line(truth)
        best = min(res.streaks, key=lambda s: distance_to(line, s))
        assert distance_to(line, best) < 1.0
        assert abs(best["angle_deg"] - 30.0) < 0.2
        # Each mask is its own streak's, not one mask over both.
        assert best["mask_width_px"] < 0.5 * separation + 8
        if best["fwhm_measured"]:
            assert best["fwhm_px"] == pytest.approx(truth["fwhm_arcsec"] / 0.2, rel=0.05)


# ---------------------------------------------------------------------------------------------
# Bad thresholds, huge values


@pytest.mark.parametrize("threshold", [-5.0, 0.0, float("nan"), float("inf")])
def test_bad_thresholds_are_refused(threshold):
    image = np.random.default_rng(1).normal(100.0, 5.0, (256, 256))
    with pytest.raises(InputError, match="threshold"):
        analyse(image, threshold=threshold)
    with pytest.raises(InputError, match="threshold"):
        detect_streaks(prepare(image), threshold=threshold)


def test_negative_threshold_from_the_command_line(tmp_path, capsys):
    raw = apply_overrides(DEFAULT_SCENE, ["seed=2", "detector.nx=256", "detector.ny=256"])
    scene = parse_scene(raw)
    path = tmp_path / "in.fits"
    write_exposure(path, scene, simulate(scene), scene.detector.gain)
    assert main(["mask", str(path), "--threshold", "-5"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--threshold" in err and "-5" in err


def test_huge_values_are_refused_in_one_line():
    image = np.random.default_rng(2).normal(100.0, 5.0, (256, 256)) * 1e298
    with pytest.raises(InputError, match="rescale") as info:
        analyse(image)
    assert "\n" not in str(info.value)


def test_scaled_image_gives_the_same_streaks():
    """Scale invariance, an independent check of the large-value path: the same image times
    1e25 (float64, within the accepted range) gives the same lines and widths, and the sky
    noise times 1e25; infinite pixels are unusable, like NaN."""
    r = simulated([satellite(10.5, 100.0, 120.0, 21.7)], seed=4)
    bad = (r.mask & BAD_BITS) != 0
    ref = analyse(r.image.astype(np.float64), bad=bad, n_boot=0)
    big = r.image.astype(np.float64) * 1e25
    big[400:410, 30:60] = np.inf
    res = analyse(big, bad=bad, n_boot=0)
    assert isinstance(res, MaskResult) and len(res.streaks) == len(ref.streaks) == 1
    assert res.sky_sigma == pytest.approx(ref.sky_sigma * 1e25, rel=1e-3)
    for key in ("angle_deg", "y0", "y1", "mask_width_px"):
        assert res.streaks[0][key] == pytest.approx(ref.streaks[0][key], rel=1e-3, abs=0.05)
