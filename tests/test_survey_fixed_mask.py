"""``inject survey --mask-width``: a band of one width along every streak, counted beside the
plan's own mask, and the visits' streak length.

The band's pixels against hand counts on R22_S11 and R22_S12 (a track on one CCD, a track
over two CCDs and the gap between them, a track along the gap); the option's syntax; and on
a small aimed night, its columns and summary block against a hand count of the tables and
the streaks' lengths in pixels.
"""
import json
import math

import numpy as np
import pytest
from test_survey_trust import _visit_rows as aimed_rows
from test_survey_trust import read_csv, survey, write_const, write_csv

from inject.camera import layout as fp

#: The band's width in the hand counts, px; 60 arcsec at 0.2 arcsec a pixel.
WIDTH = 300.0
#: A row of R22_S11 and R22_S12 (they share their rows' frame: both centred on y = 0 mm),
#: 0.3 px off the pixel centres so that no band edge falls on one.
ROW = 2001.8


def _x_s11(px):
    """Focal-plane mm of R22_S11's column ``px`` (pixel 2047.5 at x = 0, 10 um pixels)."""
    return (px - 2047.5) * 0.010


def _x_s12(px):
    """Focal-plane mm of R22_S12's column ``px`` (its left edge, -0.5, at x = 21.77 mm)."""
    return 21.77 + (px + 0.5) * 0.010


def _y(row):
    return (row - 2001.5) * 0.010


def _band(xs_mm, ys_mm, width=WIDTH):
    """Pixels of a band along a track, by CCD, as the plan counts the fixed mask."""
    from inject.survey.plan import ccd_pixels, mask_spans

    return ccd_pixels(mask_spans(np.asarray(xs_mm, float), np.asarray(ys_mm, float),
                                 [np.arange(len(xs_mm))], dict.fromkeys(fp.SENSORS, width)))


def test_the_geometry_of_the_hand_counts():
    s11, s12 = fp.ccd("R22_S11"), fp.ccd("R22_S12")
    assert s11.bounds_mm()[:2] == pytest.approx((-20.48, 20.48))
    assert s12.bounds_mm()[:2] == pytest.approx((21.77, 62.73))
    assert s11.shape == s12.shape == (4004, 4096)


def test_a_band_on_one_ccd_is_its_length_and_caps_times_its_width():
    """From column 1047.8 to 3047.8 of R22_S11 on row 2001.8: the band holds rows 1852-2151
    (2001.8 +- 150) and, with its caps of 150 px, columns 898-3197: 300 x 2300."""
    got = _band([_x_s11(1047.8), _x_s11(3047.8)], [_y(ROW)] * 2)
    assert got == {"R22_S11": 300 * (3197 - 898 + 1)} == {"R22_S11": 690_000}


def test_a_band_over_two_ccds_counts_both_and_not_the_gap():
    """From column 1000.3 of R22_S11 to column 3000.3 of R22_S12: on S11 from the start's cap
    (850.3) to its last column, 851-4095; on S12 from its first column to the end's cap
    (3150.3), 0-3150; 300 rows on each. The 129 px of gap between them hold no pixel."""
    got = _band([_x_s11(1000.3), _x_s12(3000.3)], [_y(ROW)] * 2)
    assert got == {"R22_S11": 300 * (4095 - 851 + 1), "R22_S12": 300 * (3150 + 1)}
    assert sum(got.values()) == 1_918_800


def test_a_band_along_the_gap_counts_the_ccds_on_either_side():
    """A column track at x = 21.123 mm, in the gap between S11 (to 20.48 mm) and S12 (from
    21.77 mm), rows 1001.2 to 3001.2: the band, 19.623-22.623 mm, holds S11's columns
    4009.8-4095.5 (4010-4095: 86) and S12's -0.5-84.8 (0-84: 85), rows 852-3151 (2300)
    with the caps."""
    got = _band([21.123, 21.123], [_y(1001.2), _y(3001.2)])
    assert got == {"R22_S11": 86 * 2300, "R22_S12": 85 * 2300}


def test_the_same_width_as_the_mask_gives_the_masks_pixels():
    """The band is the mask's rasteriser: at the mask's width it counts the mask's pixels
    (run_spans, the closed forms of tests/test_survey.py)."""
    from inject.survey.plan import run_spans, union_pixels

    xs, ys = [_x_s11(1000.25), _x_s11(3000.25)], [_y(ROW)] * 2
    assert _band(xs, ys, 20.0) == {"R22_S11": (2000 + 20) * 20}
    assert union_pixels(run_spans(xs, ys, 20.0, fp.ccd("R22_S11"))) == (2000 + 20) * 20


# --- the option ----------------------------------------------------------------------------

@pytest.mark.parametrize("text, px", [("300px", 300.0), ("60arcsec", 300.0),
                                      ("60 arcsec", 300.0), ("12.5px", 12.5),
                                      ("1e2PX", 100.0), ("819.2arcsec", 4096.0)])
def test_the_width_reads_in_px_or_arcsec(text, px):
    from inject.survey.fixed_mask import parse_mask_width

    assert parse_mask_width(text).width_px == pytest.approx(px, rel=1e-15)


@pytest.mark.parametrize("text, words", [
    ("300", "give its unit"), ("60as", "unknown unit 'as'"), ("1mm", "unknown unit 'mm'"),
    ('60"', "unknown unit"), ("0px", "> 0"), ("-5px", "> 0"), ("5000px", "wider than a CCD"),
    ("wide", "e.g. 300px or 60arcsec"), ("px", "e.g. 300px or 60arcsec")])
def test_a_bad_width_is_refused_in_one_line(cli, tmp_path, text, words):
    status, _, err = cli("survey", tmp_path / "none.csv", "-o", tmp_path / "out",
                         "--constellation", tmp_path / "none.yaml", f"--mask-width={text}",
                         strict=True)
    assert status == 2 and "--mask-width" in err and words in err
    assert not (tmp_path / "out").exists()


# --- on a night -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def nights(tmp_path_factory):
    """The aimed three-visit night of tests/test_survey_trust.py planned without and with
    ``--mask-width 60arcsec``."""
    folder = tmp_path_factory.mktemp("fixed")
    visits = write_csv(folder / "night.csv", aimed_rows())
    const = write_const(str(folder))
    out = {}
    for name, extra in (("plain", []), ("fixed", ["--mask-width", "60arcsec"])):
        assert survey(visits, "-o", folder / name, "--constellation", const, "--no-plots",
                      *extra) == 0
        out[name] = {"streaks": read_csv(folder / name / "streaks.csv"),
                     "visits": read_csv(folder / name / "visits.csv"),
                     "summary": json.loads((folder / name / "summary.json").read_text())}
    return out


def test_without_the_option_no_fixed_mask_is_written(nights):
    plain = nights["plain"]
    assert "pixels_fixed_mask" not in plain["streaks"][0]
    assert "pixels_fixed_mask" not in plain["visits"][0]
    assert "fixed_mask" not in plain["summary"]


def test_the_fixed_mask_columns_and_totals_are_the_hand_count(nights):
    plain, fixed = nights["plain"], nights["fixed"]
    # The plan itself is the same with and without the band.
    drop = ("pixels_fixed_mask", "pixel_fraction_fixed_mask")
    assert [{k: v for k, v in r.items() if k not in drop} for r in fixed["visits"]] == \
        plain["visits"]
    all_pixels = 8 * 9 * 4072 * 4000 + 13 * 9 * 4096 * 4004
    by_visit = {}
    for r in fixed["streaks"]:
        by_visit.setdefault(r["observationId"], []).append(int(r["pixels_fixed_mask"]))
    assert len(by_visit) >= 2
    for r in fixed["visits"]:
        mine = by_visit.get(r["observationId"], [])
        assert int(r["pixels_fixed_mask"]) == sum(mine)  # one streak a visit: no overlap
        assert float(r["pixel_fraction_fixed_mask"]) == int(r["pixels_fixed_mask"]) / all_pixels
    block = fixed["summary"]["fixed_mask"]
    total = sum(int(r["pixels_fixed_mask"]) for r in fixed["visits"])
    assert block["width"] == "60arcsec" and block["width_px"] == 300.0
    assert block["width_arcsec"] == pytest.approx(60.0, rel=1e-15)
    assert block["pixels_lost"] == total
    assert block["pixel_fraction_lost_total"] == pytest.approx(total / (3 * all_pixels),
                                                               rel=1e-15)
    assert block["pixels_lost_physical"] == fixed["summary"]["pixels_lost"]
    assert block["ratio_to_physical"] == pytest.approx(
        total / fixed["summary"]["pixels_lost"], rel=1e-15)


def test_each_streaks_band_is_its_length_times_the_width(nights):
    """A streak's band: its length on the CCDs in pixels (0.2 arcsec each, within the
    distortion's 1%) times 300 px, plus at most a cap of 150 px at each end of each part;
    the physical mask's pixels are the same band at the mask's width: their ratio is the
    widths' within the caps' share (2 x 300 px over the length) and the 1% by which the
    sensors' widths differ from their length-weighted mean."""
    for r in nights["fixed"]["streaks"]:
        length_px = float(r["length_deg"]) * 3600.0 / 0.2
        parts = int(r["sunlit_parts"])
        band = int(r["pixels_fixed_mask"])
        assert 0.99 * length_px * WIDTH <= band <= 1.01 * (length_px + parts * WIDTH) * WIDTH
        ratio = band / int(r["pixels_lost"])
        width = float(r["mask_width_px"])
        assert ratio == pytest.approx(WIDTH / width, rel=0.01 + 2 * WIDTH / length_px)


def test_a_visits_streak_length_is_the_sum_of_its_streaks(nights):
    lengths = {}
    for r in nights["plain"]["streaks"]:
        lengths[r["observationId"]] = lengths.get(r["observationId"], 0.0) + \
            float(r["length_deg"])
    for r in nights["plain"]["visits"]:
        assert float(r["streak_length_deg"]) == pytest.approx(
            lengths.get(r["observationId"], 0.0), rel=1e-12)
    assert math.isclose(sum(lengths.values()),
                        sum(float(r["streak_length_deg"]) for r in nights["plain"]["visits"]))


def test_the_file_formats_page_lists_the_columns_in_order():
    """docs/reference/file-formats.md names every column of both tables, in the order the
    files have them."""
    import os

    from inject.survey.compare import MEASURED_FIELDS
    from inject.survey.plan import (
        FIXED_STREAK_FIELDS,
        FIXED_VISIT_FIELDS,
        STREAK_FIELDS,
        VISIT_FIELDS,
    )

    path = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "reference",
                        "file-formats.md")
    with open(path) as stream:
        text = " ".join(stream.read().split())
    for fields in (STREAK_FIELDS, VISIT_FIELDS, FIXED_STREAK_FIELDS, FIXED_VISIT_FIELDS,
                   MEASURED_FIELDS):
        assert ", ".join(fields) in text, fields


def test_another_width_into_the_same_outdir_is_another_run(cli, tmp_path):
    """The band's width is part of the run's key: the other --job slice of a run with
    another width is refused at once, though its files' names are free; with the same width
    it is the same run's slice."""
    first, second = aimed_rows()[:2]
    second = {**second, "observationStartMJD": repr(float(second["observationStartMJD"]) + 1)}
    visits = write_csv(tmp_path / "night.csv", [first, second])  # two nights: two slices
    const = write_const(str(tmp_path))
    out = tmp_path / "out"

    def run(width, job, strict=False):
        return cli("survey", visits, "-o", out, "--constellation", const, "--no-plots",
                   "--mask-width", width, "--job", job, "--njobs", 2, strict=strict)

    assert run("300px", 0)[0] == 0
    before = sorted(p.name for p in out.iterdir())
    status, _, err = run("100px", 1, strict=True)
    assert status == 2 and "another survey run" in err
    assert sorted(p.name for p in out.iterdir()) == before
    assert run("60arcsec", 1)[0] == 0  # the same 300 px
