"""Scoring maskers against injected truth (inject.masking.evaluate), the ``inject evaluate``
command (inject.cli.evaluate) and the acstools findsat_mrt adapter."""
import argparse
import csv
import json
import logging

import numpy as np
import pytest

from inject import InputError
from inject.cli.evaluate import (
    add_evaluate_parser,
    bad_pixels,
    campaign_images,
    false_positive_summary,
    markdown_table,
    pixel_loss,
    streak_free_images,
)
from inject.masking import MaskerOutput
from inject.masking.evaluate import (
    Masker,
    completeness_point,
    evaluate,
    inject_masker,
    load_masker,
    match_streaks,
    score_image,
    summarise,
)


def one_image(mag=11.0, height=550.0, seed=1, size=512):
    return next(campaign_images([height], [mag], [seed], size))


def everything(image):
    """A masker that masks the whole image (module:function target of a test)."""
    return np.ones(np.shape(image), dtype=bool)


def nothing(image):
    return np.zeros(np.shape(image), dtype=bool)


@pytest.fixture(scope="module")
def bright():
    return one_image()


def test_perfect_mask_of_the_true_region(bright):
    sim, _ = bright
    region = sim.streak_model > sim.noise_sigma
    image, rows = score_image(sim, MaskerOutput(region))
    assert image["recall"] == 1 and image["overmask"] == 0 and image["iou"] == 1
    assert image["false_positives"] == 0
    assert 0 < image["flux_left"] < 0.5  # the wings below 1 sigma (23% of a mag-11 streak)
    (row,) = rows
    assert row["found"] and row["line_found"] is None and np.isnan(row["fwhm_meas"])


def test_scores_of_a_streak_of_known_cross_section():
    """flux_left, peak_sb and int_snr against the cross-section the streak must have.

    A horizontal track through pixel centres, across the whole image: every column holds
    the pixel cross-section ``v_j = F p LSF(j p)`` at whole-pixel offsets j (taken from
    :meth:`StreakModel.cross_section`, not from the image), so a mask of rows ``|j| <= k``
    leaves ``1 - sum_{|j|<=k} v_j / sum_j v_j`` of the charge, the peak is ``v_0`` and the
    matched-filter S/N is ``sqrt(W sum_j v_j^2) / sigma``.
    """
    from inject import SceneResult, StreakModel, Track
    from inject.scene import render_tracks
    model, shape, y0, sigma, k = StreakModel(550, 70, mag=9.0), (161, 200), 80.0, 20.0, 6
    streaks, truth = render_tracks(shape, [model], [Track(0.0, y0, 0.0)])
    sim = SceneResult(image=streaks, mask=np.zeros(shape, np.int32), variance=streaks,
                      streak_model=streaks, truth=truth, sky_level=0.0, noise_sigma=sigma)
    offsets, e_per_px = model.cross_section(half_width_arcsec=np.inf)
    rows_px = np.arange(shape[0]) - y0
    v = np.interp(rows_px * model.pixel_scale, offsets, e_per_px)
    mask = np.zeros(shape, bool)
    mask[np.abs(rows_px) <= k] = True
    image, (row,) = score_image(sim, MaskerOutput(mask))
    assert image["flux_left"] == pytest.approx(1 - v[np.abs(rows_px) <= k].sum() / v.sum(),
                                               rel=1e-3)
    assert row["peak_sb"] == pytest.approx(v.max() / sigma, rel=1e-4)
    assert row["int_snr"] == pytest.approx(np.sqrt(shape[1] * (v ** 2).sum()) / sigma, rel=1e-4)


#: A bent truth path on a 100 x 200 image: up 10 px to the middle, down again.
BENT = {"x0": -0.5, "y0": 50.0, "x1": 199.5, "y1": 50.0, "angle_deg": 0.0, "length_px": 201.0,
        "fwhm_arcsec": 1.2, "peak_e_per_px": 100.0,
        "vertices": ((-0.5, 50.0), (99.5, 60.0), (199.5, 50.0))}


def test_a_detection_is_scored_against_the_truth_path_not_its_chord():
    """The chord of the bent path (its ends' line, where TRUTH's x0..y1 put it) is 10 px
    below the path's middle: measured there, against the first piece (rising 10 px over
    100), it is 1000 / hypot(100, 10) = 9.950 px to the right of the path, 5.71 deg off. A
    line along the second piece through the middle matches it exactly."""
    shape = (100, 200)
    chord = {"x0": -0.5, "y0": 50.0, "x1": 199.5, "y1": 50.0}
    matches, false = match_streaks([chord], [BENT], shape, max_angle_deg=6.0,
                                   max_offset_px=10.0)
    (m,) = matches
    assert m.found_index == 0 and not false
    assert m.offset_px == pytest.approx(-1000 / np.hypot(100, 10), rel=1e-12)
    assert m.angle_error_deg == pytest.approx(np.degrees(np.arctan(0.1)), rel=1e-12)
    matches, false = match_streaks([chord], [BENT], shape)  # 0.5 deg, 5 px: not this one
    assert matches[0].found_index is None and false == [0]
    second = {"x0": 99.5, "y0": 60.0, "x1": 199.5, "y1": 50.0}
    (m,), _ = match_streaks([second], [BENT], shape)
    assert m.found_index == 0 and abs(m.offset_px) < 1e-9 and m.angle_error_deg < 1e-9


def test_the_core_of_a_bent_streak_follows_its_path():
    """The core is the pixels within half the FWHM (3 px) of the path's pieces: a mask of the
    pixels within 3 px of the path (by distance, computed here) covers it, one of the chord's
    band covers under half of it; and every charged pixel belongs to the streak."""
    from inject import SceneResult
    shape = (100, 200)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    rise = np.where(xx <= 99.5, (xx + 0.5) / 10.0, (199.5 - xx) / 10.0)
    across = np.abs(yy - 50.0 - rise) * np.cos(np.arctan(0.1))  # distance to the path
    model = np.exp(-0.5 * (across / 2.0) ** 2)
    sim = SceneResult(image=model, mask=np.zeros(shape, np.int32), variance=model,
                      streak_model=model, truth=[BENT], sky_level=0.0, noise_sigma=0.01)
    image, (row,) = score_image(sim, MaskerOutput(across <= 3.0 + 1e-9))
    assert row["core_cover"] == 1.0 and row["found"]
    chord_band = np.abs(yy - 50.0) <= 3.0
    _, (row,) = score_image(sim, MaskerOutput(chord_band))
    assert row["core_cover"] < 0.5 and not row["found"]


def test_empty_and_misplaced_masks(bright):
    sim, _ = bright
    image, (row,) = score_image(sim, MaskerOutput(nothing(sim.image)))
    assert image["recall"] == 0 and image["flux_left"] == 1 and not row["found"]
    corner = nothing(sim.image)
    corner[:5, :5] = True  # the track runs through the central 60%
    region = sim.streak_model > sim.noise_sigma
    assert not (corner & region).any()
    image, _ = score_image(sim, MaskerOutput(corner))
    assert image["false_positives"] == 1 and image["iou"] == 0
    assert image["overmask"] == pytest.approx(25 / region.sum())


def test_truth_sigma_sets_the_region(bright):
    sim, _ = bright
    wide = sim.streak_model > 0.5 * sim.noise_sigma
    image, _ = score_image(sim, MaskerOutput(wide), truth_sigma=0.5)
    assert image["iou"] == 1
    image, _ = score_image(sim, MaskerOutput(wide), truth_sigma=1.0)
    assert image["recall"] == 1 and image["overmask"] > 0


def test_builtin_masker_scores_well(bright):
    sim, labels = bright
    (rec,) = evaluate([(sim, labels)], ["inject"], bad=bad_pixels)
    assert rec["masker"] == "inject" and rec["mag"] == 11.0
    assert rec["found"] and rec["line_found"] and rec["false_positives"] == 0
    assert rec["angle_err_deg"] < 0.1 and abs(rec["offset_px"]) < 0.5
    assert rec["fwhm_meas"] == pytest.approx(rec["fwhm_true"], rel=0.05)
    assert rec["recall"] > 0.99 and rec["iou"] > 0.85 and rec["time_s"] > 0


def test_masker_loading():
    assert load_masker("inject").func is inject_masker
    m = load_masker("tests.test_masking_evaluate:everything")
    assert m.name == "tests.test_masking_evaluate:everything"
    out, seconds = m(np.zeros((8, 8)), bad=np.ones((8, 8), bool))  # no bad keyword: not given
    assert out.mask.all() and out.streaks is None and seconds >= 0
    assert load_masker(nothing).name == "nothing"
    for spec in ("nocolon", "no_such_module_xyz:f", "numpy:no_such_function", "numpy:pi"):
        with pytest.raises(InputError):
            load_masker(spec)
    with pytest.raises(ValueError, match="shape"):
        Masker(lambda im: np.zeros((2, 2), bool))(np.zeros((4, 4)))


def test_summary_and_completeness_point():
    recs = [{"masker": "a", "height_km": 550, "mag": m, "found": f, "peak_sb": sb,
             "false_positives": 0, "fwhm_meas": 1.1, "fwhm_true": 1.0, "masked_px": 10,
             "time_s": 0.1, "line_found": None}
            for m, sb, fs in ((12, 1.0, (1, 1)), (14, 0.1, (1, 0)), (15, 0.01, (0, 0)))
            for f in fs]
    summary = summarise(recs)
    assert [r["completeness"] for r in summary] == [1.0, 0.5, 0.0]
    assert summary[0]["fwhm_bias_pct"] == pytest.approx(10.0)
    assert summary[0]["fwhm_scatter_pct"] == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(summary[0]["line_completeness"])
    assert completeness_point([1.0, 0.1, 0.01], [1.0, 0.5, 0.0]) == pytest.approx(0.1)
    assert completeness_point([1.0, 0.1], [1.0, 0.0]) == pytest.approx(np.sqrt(0.1))
    assert np.isnan(completeness_point([1.0], [0.2]))
    assert "| a | 550 | 12.00 |" in markdown_table(summary)
    loss = pixel_loss([{"masker": "a", "height_km": 550.0, "mag": 12, "masked_px": 100},
                       {"masker": "a", "height_km": 350.0, "mag": 12, "masked_px": 150}], "a")
    assert loss == [{"mag": 12, "px_550": 100, "px_350": 150, "ratio": 1.5}]


def test_campaign_is_seeded():
    a = [(s.image.copy(), lab) for s, lab in campaign_images([550], [12.0], [3], 256)]
    b = [(s.image, lab) for s, lab in campaign_images([550], [12.0], [3], 256)]
    np.testing.assert_array_equal(a[0][0], b[0][0])
    assert a[0][1] == {"height_km": 550, "mag": 12.0, "seed": 3}


def parse(argv):
    p = argparse.ArgumentParser()
    add_evaluate_parser(p.add_subparsers())
    return p.parse_args(["evaluate", *argv])


def test_evaluate_command(tmp_path, capsys, caplog):
    out = tmp_path / "ev"
    args = parse(["--out", str(out), "--seeds", "1", "--mags", "11", "16", "--detector", "512",
                  "--masker", "inject", "--masker", "tests.test_masking_evaluate:nothing",
                  "--streak-free", "2", "--json"])
    caplog.set_level(logging.INFO, logger="inject")
    args.func(args)
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    # One progress over the 2 x 2 campaign images and the 2 streak-free ones; under ten
    # images, a line for each.
    progress = [m for m in caplog.messages if "images" in m and m.startswith("[")]
    assert progress[0] == "[1/6] simulating and masking images: 550 km mag 11.00 seed 1"
    assert progress[-1] == "[6/6] simulating and masking images: streak-free seed 1002"
    assert len(progress) == 6
    names = {r["masker"] for r in result["summary"]}
    assert names == {"inject", "tests.test_masking_evaluate:nothing"}
    ours = {(r["height_km"], r["mag"]): r for r in result["summary"] if r["masker"] == "inject"}
    assert ours[(550.0, 11.0)]["completeness"] == 1 and ours[(550.0, 16.0)]["completeness"] == 0
    loss = result["pixel_loss"]
    assert loss[0]["mag"] == 11.0 and loss[0]["ratio"] > 1  # lower orbit: wider streak
    for name in ("records.csv", "summary.csv", "summary.md", "pixel_loss.csv",
                 "completeness.png", "fwhm_bias.png", "pixel_loss.png"):
        assert (out / name).stat().st_size > 0
    false = result["false_positives"]
    assert false["tests.test_masking_evaluate:nothing"] == {
        "images": 2, "detections": 0, "per_image": 0.0, "per_ccd": 0.0}
    free = {r["masker"]: r for r in result["summary"] if r["height_km"] is None}
    assert set(free) == names and all(r["n"] == 0 for r in free.values())
    for name, r in free.items():  # the summary row holds the same false positives
        assert r["fp_per_ccd"] == pytest.approx(false[name]["per_image"])
    with open(out / "records.csv", newline="") as f:
        # 2 heights x 2 mags x 2 maskers, and 2 streak-free images x 2 maskers
        assert len(list(csv.DictReader(f))) == 12
    assert not list(out.glob(".inject-*"))  # no temporary files left


def test_no_false_positives_on_streak_free_cutouts():
    # Streak-free 1024 x 1024 cut-outs of the campaign's field with stars, seeds held out
    # from the threshold's calibration (the full-CCD check is scripts/bench_mask.py).
    images = list(streak_free_images(3, 1024))
    assert [lab["seed"] for _, lab in images] == [1001, 1002, 1003]
    records = evaluate(images, ["inject"], bad=bad_pixels)
    assert len(records) == 3 and all(r["found"] is None for r in records)
    assert false_positive_summary(records, 1024)["inject"]["detections"] == 0


#: Writes the campaign's plots under a backend the caller chose (argv[1]) with a pyplot figure
#: of its own open, then prints the backend and the caller's figures.
PLOTS_UNDER_A_CHOSEN_BACKEND = """
import sys
import matplotlib
matplotlib.use(sys.argv[1])
import matplotlib.pyplot as plt
from inject.cli.evaluate import write_plots
mine = plt.figure()
rows = [{"masker": "inject", "height_km": h, "mag": m, "peak_sb": 2.0 / m,
         "int_snr": 50.0 / m, "completeness": 1.0, "fwhm_bias_pct": 1.0}
        for h in (550.0, 350.0) for m in (11.0, 12.0)]
loss = [{"mag": 11.0, "px_550": 100.0, "px_350": 150.0, "ratio": 1.5}]
paths = write_plots(rows, loss, sys.argv[2], "inject")
print(matplotlib.get_backend(), plt.get_fignums() == [mine.number], len(paths))
"""


@pytest.mark.parametrize("backend", ["svg", "pdf"])
def test_the_plots_leave_the_callers_backend_and_figures(tmp_path, backend):
    """Before: write_plots switched matplotlib to Agg, under a notebook's or a program's own
    backend, and closed figures through pyplot."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    run = subprocess.run([sys.executable, "-c", PLOTS_UNDER_A_CHOSEN_BACKEND, backend,
                          str(tmp_path)], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=root))
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == [backend, "True", "3"]
    for name in ("completeness.png", "fwhm_bias.png", "pixel_loss.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_evaluate_command_rejects_bad_options(tmp_path):
    for argv in (["--seeds", "0"], ["--heights", "-5"], ["--masker", "nope"],
                 ["--truth-sigma", "0"], ["--streak-free", "-1"]):
        args = parse(["--out", str(tmp_path / "x"), "--mags", "11", *argv])
        with pytest.raises(InputError):
            args.func(args)


def test_findsat_mrt_adapter(bright):
    pytest.importorskip("acstools")
    from inject.masking.external import findsat_mrt_mask, findsat_mrt_trails

    sim, _ = bright
    out = findsat_mrt_trails(sim.image, bad=bad_pixels(sim))
    assert out.mask.shape == sim.image.shape and out.mask.dtype == bool
    # Its own trail catalogue: one line along the truth, with a FWHM near the true one.
    (trail,) = out.streaks
    assert -90 < trail["angle_deg"] <= 90 and trail["status"] == 2
    image, (row,) = score_image(sim, out)
    assert row["found"] and row["line_found"] and image["recall"] > 0.9
    assert image["false_positives"] == 0
    assert abs(row["angle_err_deg"]) < 0.5 and abs(row["offset_px"]) < 5
    assert row["fwhm_meas"] == pytest.approx(row["fwhm_true"], rel=0.25)
    assert trail["findsat_width_px"] > trail["fwhm_px"]  # masks 6 sigma wide
    np.testing.assert_array_equal(findsat_mrt_mask(sim.image, bad=bad_pixels(sim)), out.mask)
    assert load_masker("findsat_mrt").func is findsat_mrt_trails


def test_findsat_trail_records_convert_binned_lines():
    from inject.masking.external import trail_records

    rows = [{"status": 2, "endpoints": [[10.0, 0.0], [0.0, 10.0]], "width": 6.0, "snr": 9.0,
             "persistence": 1.0},
            {"status": 1, "endpoints": [[0.0, 0.0], [5.0, 5.0]], "width": 6.0, "snr": 4.0,
             "persistence": 0.0}]
    (t,) = trail_records(rows, binning=4)  # status 1 (not persistent) is not masked
    # Binned (10, 0) -> image (41.5, 1.5); oriented in (-90, 90]: from (1.5, 41.5) down.
    assert (t["x0"], t["y0"], t["x1"], t["y1"]) == (1.5, 41.5, 41.5, 1.5)
    assert t["angle_deg"] == pytest.approx(-45.0)
    # 6 sigma = 6 binned px: sigma 4 image px, less the 4-px box (variance 16 / 12).
    assert t["fwhm_px"] == pytest.approx(2.3548 * np.sqrt(16 - 16 / 12), rel=1e-4)
    assert t["fwhm_arcsec"] == pytest.approx(0.2 * t["fwhm_px"])
    assert trail_records(None, 4) == []


def test_findsat_mrt_missing_gives_a_clear_error(monkeypatch):
    import sys

    from inject import MaskingError
    from inject.masking.external import findsat_mrt_mask

    monkeypatch.setitem(sys.modules, "acstools.findsat_mrt", None)  # import fails
    with pytest.raises(MaskingError, match="pip install acstools"):
        findsat_mrt_mask(np.zeros((64, 64)))
