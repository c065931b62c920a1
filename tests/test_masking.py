"""Streak masking (inject.masking): detection, line and extent, FWHM, mask widths, lost pixels,
the ``inject mask`` command."""
import argparse
import json

import numpy as np
import pytest
from astropy.io import fits

from inject import (
    DEFAULT_SCENE,
    FileFormatError,
    InputError,
    MaskingError,
    OutputError,
    apply_overrides,
    parse_scene,
    simulate,
    write_exposure,
)
from inject.cli.mask import add_mask_parser
from inject.config import sky_level
from inject.masking.detect import BAD_PLANES, prepare
from inject.masking.evaluate import match_streaks
from inject.masking.geometry import Line, band_pixels, rectangle_spans
from inject.masking.mask import lost_pixels, mask_spans, paint
from inject.masking.measure import (
    BinnedStack,
    Profile,
    half_max_width,
    pixel_response,
    profile_fwhm,
)
from inject.masking.run import analyse, mask_image, write_masked
from inject.maskplanes import MASK_PLANES
from inject.scene import streak_models

BAD_BITS = sum(1 << MASK_PLANES[p] for p in BAD_PLANES)


def box_satellite(height, mag, x0, y0, angle, length=None):
    """The paper's satellite (7.25 x 2.65 m box) on a track."""
    track = {"x0": x0, "y0": y0, "angle": angle} | ({"length": length} if length else {})
    return {"height": height, "shape": {"type": "box", "length": 7.25, "width": 2.65},
            "mag": mag, "track": track}


def make_scene(satellites, seed=1, nx=1024, ny=1024, stars=True):
    raw = apply_overrides(DEFAULT_SCENE, [f"seed={seed}", f"detector.nx={nx}",
                                          f"detector.ny={ny}", f"stars={str(stars).lower()}"])
    raw["satellites"] = satellites
    return parse_scene(raw)


def run(scene, **options):
    """Simulate a scene and mask it: (result, truth rows, shape, noise sigma)."""
    r = simulate(scene)
    res = analyse(r.image, bad=(r.mask & BAD_BITS) != 0, **options)
    return res, r.truth, r.image.shape, r.noise_sigma


def mag_for_snr(height, snr, scene):
    """Stationary magnitude of the paper satellite giving a peak S/N per pixel of ``snr``."""
    sigma = np.sqrt(sky_level(scene) + scene.detector.read_noise ** 2)
    peak = streak_models(scene)[0].peak_e_per_px
    return scene.satellites[0].mag + 2.5 * np.log10(peak / sigma / snr)


# ---------------------------------------------------------------------------------------------
# Detection


def test_one_streak_angle_and_offset():
    res, truth, shape, _ = run(make_scene([box_satellite(550, 10.5, 100.0, 300.0, 21.7)]))
    matches, false = match_streaks(res.streaks, truth, shape, max_angle_deg=0.2,
                                   max_offset_px=1.0)
    assert matches[0].found_index is not None and not false
    assert matches[0].angle_error_deg < 0.2 and abs(matches[0].offset_px) < 1.0
    s = res.streaks[0]
    assert s["ends_at_edge"] == [True, True]
    assert -90 < s["angle_deg"] <= 90


def test_two_crossing_streaks():
    scene = make_scene([box_satellite(550, 9.5, 100.0, 300.0, 17.3),
                        box_satellite(350, 10.5, 600.0, 50.0, 101.7)], seed=2)
    res, truth, shape, _ = run(scene)
    matches, false = match_streaks(res.streaks, truth, shape, max_angle_deg=0.2,
                                   max_offset_px=1.0)
    assert [m.found_index is not None for m in matches] == [True, True]
    assert not false


def test_streak_ending_inside_the_image():
    scene = make_scene([box_satellite(550, 9.5, 200.0, 300.0, 27.7, length=450.0)], seed=3)
    res, truth, shape, _ = run(scene)
    matches, false = match_streaks(res.streaks, truth, shape, 0.2, 1.0)
    assert matches[0].found_index is not None and not false
    s, t = res.streaks[0], truth[0]
    assert s["ends_at_edge"] == [False, False]
    found = sorted([(s["x0"], s["y0"]), (s["x1"], s["y1"])])
    true = sorted([(t["x0"], t["y0"]), (t["x1"], t["y1"])])
    np.testing.assert_allclose(found, true, atol=4.0)  # ends to a few pixels
    assert s["length_px"] == pytest.approx(450.0, abs=6.0)


@pytest.mark.parametrize("seed", [2001, 2002, 2003, 2004])
def test_no_false_positive_on_streak_free_images(seed):
    """Seeds apart from the calibration's (1-100): this tests the threshold."""
    res, _, _, _ = run(make_scene([], seed=seed))
    assert res.streaks == []
    assert res.masked_pixels == 0


@pytest.mark.parametrize("size, seed", [
    (512, 3016), (512, 3037),
    # With the split Poisson draw of 2026-12-01 this cut-out gave an edge-hugging detection
    # (a bright star just beyond the left edge lighting the outer 12 px): the class the
    # README's masking limits name (about 1 in 120 streak-free 256 px cut-outs: seed 3079,
    # not in this list, is one now). With the stars' noise drawn stamp by stamp it gives none.
    (256, 3051),
    (512, 3005), (256, 3026)])
def test_no_false_positive_on_small_streak_free_cut_outs(size, seed):
    """Held-out seeds (the small-image thresholds were calibrated on 1-400): the first three
    gave edge-hugging false detections (z 6.6-8.7) before the edge guard, the first-round
    scales and the small-search threshold."""
    res, _, _, _ = run(make_scene([], seed=seed, nx=size, ny=size))
    assert res.streaks == []


def test_no_false_line_along_star_halos_in_an_unbinned_search():
    """A streak-free 1024 px cut-out (searched unbinned) with a bright star pair: their faint
    halos, outside the star mask of the unbinned image, added up along a tangent line at the
    pyramid's coarse levels to z 8.3 (threshold 7.5): a false streak 184 px long and 30 px
    wide across the top-left corner."""
    raw = apply_overrides(DEFAULT_SCENE, ["seed=3022", "stars={mag_limit: 24}",
                                          "detector.nx=1024", "detector.ny=1024"])
    raw["satellites"] = []
    res, _, _, _ = run(parse_scene(raw))
    assert res.streaks == []


def test_threshold_for_small_searches():
    from inject.masking.detect import FALSE_ALARM_Z, threshold_for
    assert threshold_for((1000, 1018)) == FALSE_ALARM_Z  # full CCD
    assert threshold_for((128, 128)) == FALSE_ALARM_Z  # 512 px cut-out
    assert FALSE_ALARM_Z < threshold_for((64, 64)) < threshold_for((32, 48))
    assert threshold_for((64, 64), 5.0) == pytest.approx(5.0 + threshold_for((64, 64))
                                                         - FALSE_ALARM_Z)


def test_bright_streak_found_once():
    """A very bright streak's wings must not come back as a parallel detection."""
    res, truth, shape, _ = run(make_scene([box_satellite(550, 5.0, 200.0, 300.0, -37.7)]))
    assert len(res.streaks) == 1
    m, _ = match_streaks(res.streaks, truth, shape, 0.2, 1.0)
    assert m[0].found_index == 0
    assert res.streaks[0]["fwhm_arcsec"] == pytest.approx(truth[0]["fwhm_arcsec"], rel=0.005)


# ---------------------------------------------------------------------------------------------
# FWHM at peak S/N = 1 per pixel: a streak crossing a full CCD's width (4072 px), stars on.


@pytest.mark.parametrize("height", [350, 550])
def test_fwhm_within_3_percent_at_snr_1(height):
    probe = make_scene([box_satellite(height, 5.0, 0.0, 80.0, 5.0)], nx=4072, ny=512)
    mag = mag_for_snr(height, 1.0, probe)
    scene = make_scene([box_satellite(height, mag, 0.0, 80.0, 5.0)], nx=4072, ny=512)
    res, truth, shape, noise = run(scene)
    assert truth[0]["peak_e_per_px"] / noise == pytest.approx(1.0, rel=1e-3)
    m, _ = match_streaks(res.streaks, truth, shape, 0.2, 1.0)
    s = res.streaks[m[0].found_index]
    # TRUTH fwhm_arcsec is the line-spread function without pixel response; fwhm_arcsec has
    # the pixel response removed, so they compare directly.
    assert s["fwhm_arcsec"] == pytest.approx(truth[0]["fwhm_arcsec"], rel=0.03)
    # The bootstrap error is of the size of the actual scatter (~1-2% here).
    assert 0.002 < s["fwhm_err_px"] / s["fwhm_px"] < 0.03


def test_fwhm_of_exact_profiles():
    """Noise-free: the stacked pixel profile gives the LSF FWHM once the pixel response is
    removed, for a flat-topped (550 km) and a two-horned (350 km, 3% dip) cross-section."""
    from inject.profile import line_spread

    for height in (350, 550):
        model = streak_models(make_scene([box_satellite(height, 5.0, 0, 0, 0)]))[0]
        for angle in (5.0, 33.0):
            cs = line_spread(model.profile, 0.2, step_arcsec=0.02, pixel_angle_deg=angle)
            d = cs.offset_arcsec / 0.2
            keep = np.abs(d) < 40
            profile = Profile(d[keep], cs.lsf[keep], np.full(keep.sum(), 100), 1.0, 0.0, angle)
            fwhm, pixelated, centre, _ = profile_fwhm(profile)
            assert fwhm * 0.2 == pytest.approx(model.fwhm_arcsec, rel=2e-4)
            assert pixelated > fwhm and abs(centre) < 1e-3


def test_half_max_width_takes_outermost_crossings():
    d = np.linspace(-10, 10, 2001)
    horns = np.exp(-0.5 * ((d - 3) / 1.0) ** 2) + np.exp(-0.5 * ((d + 3) / 1.0) ** 2)
    fwhm, centre, _ = half_max_width(d, horns)  # dips below half between the horns
    assert fwhm == pytest.approx(6 + 2 * np.sqrt(2 * np.log(2)), abs=1e-3)
    assert centre == pytest.approx(0, abs=1e-6)


def test_pixel_response_kernel():
    for angle, width in ((0.0, 1.0), (45.0, np.sqrt(2)), (30.0, np.cos(np.radians(30)) +
                                                              np.sin(np.radians(30)))):
        k = pixel_response(0.01, angle)
        x = (np.arange(k.size) - k.size // 2) * 0.01
        assert k.sum() == pytest.approx(1.0)
        assert np.ptp(x[k > 1e-9]) == pytest.approx(width, abs=0.03)
        assert np.sum(k * x ** 2) == pytest.approx(1 / 12, rel=0.01)  # any angle: p^2 / 12


def test_binned_stack_matches_numpy():
    rng = np.random.default_rng(4)
    bins, values = rng.integers(0, 7, 5000), rng.normal(size=5000)
    values[bins == 3] += 100 * (rng.random((bins == 3).sum()) < 0.1)  # "stars" in one bin
    stack = BinnedStack(bins, values, 8)
    expect = [np.median(values[bins == k]) for k in range(7)]
    np.testing.assert_allclose(stack.median()[:7], expect)
    assert np.isnan(stack.median()[7])
    weights = rng.integers(0, 3, 5000)
    expect = [np.median(np.repeat(values[bins == k], weights[bins == k])) for k in range(7)]
    np.testing.assert_allclose(stack.median(weights)[:7], expect)
    iq = stack.trimmed_mean()
    for k in range(7):
        v = np.sort(values[bins == k])
        q1, q3 = np.quantile(v, [0.25, 0.75])
        assert q1 <= iq[k] <= q3
    assert abs(iq[3] - np.median(values[bins == 3])) < 0.2  # the 10% outliers barely count


# ---------------------------------------------------------------------------------------------
# Rasterised masks and lost pixels


def test_lost_pixels_hand_counted_rectangle():
    shape = (20, 30)
    line = Line(5.0, 10.0, 15.0, 10.0)
    flagged = np.zeros(shape, dtype=bool)
    flagged[:, 5] = True  # a bad column through the mask
    flagged[0, 0] = True  # and a bad pixel outside it
    counts = lost_pixels(shape, line, 4.0, flagged)
    # Half-width 2, ends extended by 2: x 3..17 (15 columns), y 8..12 (5 rows), centres on
    # the boundary included.
    assert counts == {"masked_pixels": 75, "already_flagged_pixels": 5, "lost_pixels": 70,
                      "masked_fraction": 75 / 600}
    mask = paint(np.zeros(shape, dtype=bool), mask_spans(shape, line, 4.0))
    assert mask[8:13, 3:18].all() and mask.sum() == 75


def test_mask_clipped_to_the_image():
    shape = (20, 30)
    counts = lost_pixels(shape, Line(-50.0, 1.0, 50.0, 1.0), 4.0)
    assert counts["masked_pixels"] == 30 * 4  # rows 0..3 (row -1 is off the image)


def test_rectangle_rasterisation_matches_polygon_fill():
    from skimage.draw import polygon

    shape = (200, 300)
    line = Line(37.3, 41.9, 251.7, 163.2)
    hw, ext = 6.37, 3.11
    yy, xx = band_pixels(shape, line, hw, ext)
    (ux, uy), (nx, ny) = line.direction, line.normal
    corners = [(line.x0 - ext * ux + s * hw * nx, line.y0 - ext * uy + s * hw * ny)
               for s in (1, -1)]
    corners += [(line.x1 + ext * ux + s * hw * nx, line.y1 + ext * uy + s * hw * ny)
                for s in (-1, 1)]
    rr, cc = polygon([c[1] for c in corners], [c[0] for c in corners], shape)
    assert set(zip(yy.tolist(), xx.tolist())) == set(zip(rr.tolist(), cc.tolist()))
    rows, start, stop = rectangle_spans(shape, line, hw, ext)
    assert np.all(stop > start) and len(set(rows.tolist())) == len(rows)


def test_mask_widths_and_rules(tmp_path):
    res, truth, shape, noise = run(make_scene([box_satellite(550, 8.0, 100.0, 300.0, 21.7)],
                                              stars=False))
    s = res.streaks[0]
    widths = s["mask_widths_px"]
    assert set(widths) == {"sb", "fwhm", "lsst", "acstools"}
    assert s["mask_width_px"] == widths["sb"] and s["mask_rule"] == "sb"
    assert widths["fwhm"] == pytest.approx(3 * s["fwhm_px"])
    # Gaussian and Moffat fits are narrower than the model-free FWHM (a Moffat's wings widen the
    # model-free FWHM).
    assert s["gaussian_fwhm_px"] < s["fwhm_px"] and s["moffat_fwhm_px"] < s["fwhm_px"]
    # The sb mask ends where the streak drops below 1 sky sigma: check against the truth model.
    model = streak_models(make_scene([box_satellite(550, 8.0, 0, 0, 0)]))[0]
    offsets, e_per_px = model.cross_section()
    above = np.abs(offsets[e_per_px > noise]) / 0.2
    assert widths["sb"] / 2 == pytest.approx(above.max(), abs=1.0)
    fwhm_rule = analyse(simulate(make_scene([box_satellite(550, 8.0, 100.0, 300.0, 21.7)],
                                            stars=False)).image, rule="fwhm", fwhm_factor=2.0)
    assert fwhm_rule.streaks[0]["mask_width_px"] == pytest.approx(
        2 * fwhm_rule.streaks[0]["fwhm_px"])
    assert s["masked_fraction"] == pytest.approx(s["masked_pixels"] / (shape[0] * shape[1]))


# ---------------------------------------------------------------------------------------------
# Files and the command


@pytest.fixture(scope="module")
def simulated_file(tmp_path_factory):
    scene = make_scene([box_satellite(550, 10.0, 100.0, 300.0, 21.7)], seed=5)
    result = simulate(scene)
    path = tmp_path_factory.mktemp("mask") / "in.fits"
    write_exposure(path, scene, result, scene.detector.gain)
    return path


def mask_namespace(*argv):
    parser = argparse.ArgumentParser(prog="inject")
    sub = parser.add_subparsers(dest="command", required=True)
    add_mask_parser(sub)
    return parser.parse_args(["mask", *map(str, argv)])


def test_command_json_and_masked_file(simulated_file, tmp_path, capsys, digest):
    before = digest(simulated_file)
    out = tmp_path / "masked.fits"
    args = mask_namespace(simulated_file, "--json", "--out", out)
    args.func(args)
    report = json.loads(capsys.readouterr().out)
    keys = {"angle_deg", "x0", "y0", "x1", "y1", "fwhm_arcsec", "fwhm_px", "mask_width_px",
            "masked_pixels", "masked_fraction"}
    assert len(report["streaks"]) == 1 and keys <= set(report["streaks"][0])
    assert report["image"]["masked_pixels"] == report["streaks"][0]["masked_pixels"]
    assert digest(simulated_file) == before  # the input is never modified
    with fits.open(out) as hdus, fits.open(simulated_file) as orig:
        bit = hdus["MASK"].header["MP_STREAK"]
        streak = (hdus["MASK"].data >> bit) & 1
        assert streak.sum() == report["streaks"][0]["masked_pixels"]
        np.testing.assert_array_equal(hdus["IMAGE"].data, orig["IMAGE"].data)
        other = hdus["MASK"].data & ~np.int32(1 << bit)
        np.testing.assert_array_equal(other, orig["MASK"].data & ~np.int32(1 << bit))
    # Without --overwrite an existing output is an error, before any work.
    with pytest.raises(OutputError, match="exists"):
        args.func(args)
    args = mask_namespace(simulated_file, "--out", out, "--overwrite", "--mask-rule", "lsst")
    args.func(args)
    table = capsys.readouterr().out
    assert "1 streak(s)" in table


def test_command_errors(simulated_file, tmp_path):
    args = mask_namespace(simulated_file, "--out", simulated_file, "--overwrite")
    with pytest.raises(InputError, match="must differ from the input"):
        args.func(args)
    bad = tmp_path / "bad.fits"
    bad.write_text("not a FITS file")
    with pytest.raises(FileFormatError):
        mask_namespace(bad).func(mask_namespace(bad))
    with pytest.raises(InputError, match="--pixel-scale"):
        mask_namespace(simulated_file, "--pixel-scale", "-1").func(
            mask_namespace(simulated_file, "--pixel-scale", "-1"))
    with pytest.raises(MaskingError, match="too small"):
        mask_image(np.zeros((20, 20)))
    with pytest.raises(MaskingError, match="dimensions"):
        mask_image(np.zeros((2, 64, 64)))


def test_write_masked_and_plain_arrays(simulated_file, tmp_path):
    streaks = mask_image(simulated_file)
    assert streaks[0]["fwhm_arcsec"] == pytest.approx(1.463, rel=0.03)
    out = tmp_path / "m.fits"
    n = write_masked(simulated_file, out, streaks)
    assert n == streaks[0]["masked_pixels"]
    with pytest.raises(OutputError):
        write_masked(simulated_file, out, streaks)
    # A big-endian array straight from astropy gives the same answer as the file.
    with fits.open(simulated_file) as hdus:
        data = hdus["IMAGE"].data
        assert data.dtype.byteorder == ">"
        direct = mask_image(data)
    assert direct[0]["angle_deg"] == pytest.approx(streaks[0]["angle_deg"], abs=1e-6)
    # A plain image HDU (no MASK) gets a MASK extension in the copy.
    plain = tmp_path / "plain.fits"
    fits.PrimaryHDU(np.asarray(data, dtype=np.float32)).writeto(plain)
    write_masked(plain, tmp_path / "plain_masked.fits", streaks)
    with fits.open(tmp_path / "plain_masked.fits") as hdus:
        assert (hdus["MASK"].data >> MASK_PLANES["STREAK"] & 1).sum() == n


def test_parser_defaults_match_the_engine():
    from inject.masking import mask as mask_module
    from inject.masking import run as run_module
    from inject.maskplanes import STREAK_MASK_SIGMA

    assert run_module.DEFAULT_SB_SIGMA == STREAK_MASK_SIGMA
    assert run_module.DEFAULT_FWHM_FACTOR == mask_module.FWHM_FACTOR
    assert run_module.RULE_CHOICES == mask_module.RULES
    assert run_module.DEFAULT_RULE == mask_module.RULES[0]


def test_json_has_no_nan():
    from inject.masking.run import MaskResult

    res = MaskResult(streaks=[{"fwhm_px": float("nan"), "x": np.float32(1.5)}],
                     shape=(10, 10), sky_sigma=1.0, pixel_scale=0.2)
    text = json.dumps(res.to_json(), allow_nan=False)
    assert '"fwhm_px": null' in text and '"x": 1.5' in text


def test_prepare_ignores_bad_pixels():
    rng = np.random.default_rng(1)
    image = rng.normal(100.0, 5.0, (256, 256))
    bad = np.zeros(image.shape, dtype=bool)
    bad[:, 100:103] = True
    image[bad] = 1e5  # a hot column, flagged
    image[5, 7] = np.nan
    prep = prepare(image, bad)
    assert np.isnan(prep.residual[bad]).all() and np.isnan(prep.residual[5, 7])
    assert prep.sigma == pytest.approx(5.0, rel=0.03)
    assert mask_image(image, mask=bad) == []


def test_median_statistic_available():
    """The median per bin (the classic robust stack) gives the same FWHM within its noise."""
    from inject.masking.detect import detect_streaks
    from inject.masking.measure import measure_streak

    r = simulate(make_scene([box_satellite(550, 9.0, 100.0, 300.0, 21.7)], seed=6))
    prep = prepare(r.image, (r.mask & BAD_BITS) != 0)
    trace = detect_streaks(prep)[0].trace
    a = measure_streak(prep, trace, n_boot=0)
    b = measure_streak(prep, trace, n_boot=0, statistic="median")
    assert b.profile.statistic == "median"
    assert b.fwhm_px == pytest.approx(a.fwhm_px, rel=0.02)


@pytest.mark.slow
def test_full_ccd_two_streaks_one_faint_one_ending():
    """A full ITL CCD with stars: a faint crossing streak (peak S/N 0.2 per pixel) and a
    bright one ending inside; both found, nothing else; the bright FWHM within 3%, the faint
    one within 3 of its bootstrap errors (at S/N 0.2 that error is ~5%)."""
    raw = apply_overrides(DEFAULT_SCENE, ["seed=7", "stars={mag_limit: 24}"])
    raw["satellites"] = [box_satellite(550, 13.35, 1200.0, 900.0, 61.3),
                         box_satellite(350, 9.0, 2500.0, 3100.0, -12.4, length=1300.0)]
    res, truth, shape, noise = run(parse_scene(raw))
    assert truth[0]["peak_e_per_px"] / noise == pytest.approx(0.2, rel=0.05)
    matches, false = match_streaks(res.streaks, truth, shape, 0.2, 1.0)
    assert all(m.found_index is not None for m in matches) and not false
    faint, ending = (res.streaks[m.found_index] for m in matches)
    assert faint["fwhm_arcsec"] == pytest.approx(truth[0]["fwhm_arcsec"],
                                                 abs=3 * faint["fwhm_err_arcsec"])
    assert ending["fwhm_arcsec"] == pytest.approx(truth[1]["fwhm_arcsec"], rel=0.03)
    assert ending["length_px"] == pytest.approx(1300.0, abs=6.0)


def test_bootstrap_replicates_match_the_direct_computation():
    # The batched replicate FWHMs (one convolution of each replicate's change) equal
    # profile_fwhm of each replicate, and the integer-weight trimmed means equal float ones.
    from inject.masking.measure import replicate_fwhms, stack_samples

    rng = np.random.default_rng(7)
    d = rng.uniform(-40, 40, 60_000)
    t = rng.uniform(-500, 500, d.size)
    v = 10 * np.exp(-0.5 * (d / 3) ** 2) + rng.normal(0, 5, d.size)
    profile, stack = stack_samples(d, v, 40.0, 0.25, 5.0, 30.0)
    first, last = 100, 220
    sub = stack.subset(first, last)
    seg = np.clip(((t[sub.order] + 500) / 100).astype(int), 0, 9)
    rows = []
    for _ in range(4):
        draws = np.bincount(rng.integers(0, 10, 10), minlength=10)
        a = sub.trimmed_mean(sorted_weights=draws[seg])
        np.testing.assert_allclose(a, sub.trimmed_mean(sorted_weights=draws[seg].astype(float)),
                                   rtol=0, atol=1e-9)
        rows.append(a - profile.baseline)
    rows = np.array(rows)
    fast = replicate_fwhms(profile, rows, first, 1.5)
    for row, f in zip(rows, fast):
        value = profile.value.copy()
        value[first:last] = row
        assert f == pytest.approx(profile_fwhm(profile, value, 1.5)[0], abs=1e-9)
    # A split of a stack by groups equals a stack binned by group x bin from scratch.
    bins = np.clip(np.floor(d / 0.25 + 160).astype(int), 0, 319)
    g = (t > 0).astype(int)
    np.testing.assert_allclose(stack.split(g, 2).trimmed_mean(),
                               BinnedStack(g * 320 + bins, v, 640).trimmed_mean())


def test_clipped_box_medians_match_resorting():
    # One sort per row and order statistics give the same medians as clipping and sorting
    # again, NaNs (unusable) and constant rows included; robust_sigma is the MAD sigma.
    from inject.masking.detect import clipped_row_medians, robust_sigma

    def resorted(a):
        def medians(x):
            return np.array([np.median(r[np.isfinite(r)]) if np.isfinite(r).any() else np.nan
                             for r in x], dtype=x.dtype)
        med = medians(a)
        for _ in range(2):
            dev = np.abs(a - med[:, None])
            a = np.where(dev <= 3 * (1.4826 * medians(dev))[:, None], a, np.nan)
            med = medians(a)
        return med

    rng = np.random.default_rng(11)
    a = rng.normal(0, 1, (40, 300)).astype(np.float32)
    a[:, :12] += 40 * rng.random((40, 12)).astype(np.float32)  # stars in every box
    a[3], a[5, 7:], a[8] = np.nan, np.nan, 2.0
    np.testing.assert_array_equal(clipped_row_medians(a), resorted(a))
    v = rng.normal(3, 2, 1001)
    v[::10] = np.nan
    f = v[np.isfinite(v)]
    assert robust_sigma(v) == pytest.approx(1.4826 * np.median(np.abs(f - np.median(f))))


def test_image_size_not_a_multiple_of_the_binning():
    # 403 x 301: the boxes of the background stop at the last whole binned pixel; the rows and
    # columns beyond get the edge background (this raised a broadcasting error before).
    rng = np.random.default_rng(2)
    ny, nx = 403, 301
    yy, xx = np.mgrid[:ny, :nx]
    d = (yy - 0.5 * ny) * np.cos(np.radians(30)) - (xx - 0.5 * nx) * np.sin(np.radians(30))
    image = rng.normal(100, 10, (ny, nx)) + 10 * np.exp(-0.5 * (d / 3) ** 2)
    prep = prepare(image)
    assert prep.residual.shape == (ny, nx) and np.isfinite(prep.residual).all()
    assert abs(np.median(prep.residual[400:])) < 2 and prep.stars.shape == (ny, nx)
    (s,) = analyse(image, n_boot=0).streaks
    assert s["angle_deg"] == pytest.approx(30.0, abs=0.5)


def test_bin_value_order_is_lexsort():
    from inject.masking.measure import bin_value_order

    rng = np.random.default_rng(5)
    for n, nbins, scale in ((1, 1, 1.0), (2, 2, 1.0), (500, 3, 1e5), (2000, 50, 1e-3),
                            (300, 2 ** 40, 1.0), (1000, 7, 0.0)):
        v, b = np.round(rng.normal(size=n) * scale, 1), rng.integers(0, nbins, n)
        o, ref = bin_value_order(b, v), np.lexsort((v, b))
        np.testing.assert_array_equal(b[o], b[ref])
        np.testing.assert_array_equal(v[o], v[ref])
    v = np.array([1.0, np.nan, -np.inf, 0.0])  # non-finite values: the general way
    np.testing.assert_array_equal(bin_value_order(np.zeros(4, int), v), [2, 3, 0, 1])
