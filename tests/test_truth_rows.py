"""TRUTH rows describe the streak as rendered on their image (the rule of inject.truth), and every
TRUTH table has the same columns."""
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from inject import DEFAULT_SCENE, StreakModel, apply_overrides, parse_scene, render_streaks
from inject.maskplanes import FLAG_CLIPPED, FLAG_OFF_IMAGE
from inject.orbits.tracks import resolve_ccd_orbits
from inject.schema import load_scene_file
from inject.truth import TRUTH_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
QUIET = ["stars=false", "sky=false", "noise=false"]


def _chord_in_image(row, shape):
    """Length of the TRUTH line inside the image proper (pixel edges), by sampling it."""
    ny, nx = shape
    t = np.linspace(0.0, 1.0, 200001)
    x = row["x0"] + t * (row["x1"] - row["x0"])
    y = row["y0"] + t * (row["y1"] - row["y0"])
    inside = (x >= -0.5) & (x < nx - 0.5) & (y >= -0.5) & (y < ny - 0.5)
    return inside.mean() * np.hypot(row["x1"] - row["x0"], row["y1"] - row["y0"])


def _ridge_distance(image, row):
    """Largest distance (px) from the TRUTH line to the streak's ridge: in each column where
    the streak is bright, the charge-weighted centre of the rows near the peak."""
    x0, y0, x1, y1 = row["x0"], row["y0"], row["x1"], row["y1"]
    worst = 0.0
    for col in range(image.shape[1]):
        column = image[:, col]
        if column.max() < 0.5 * image.max():
            continue
        peak = int(np.argmax(column))
        rows = np.arange(max(0, peak - 15), min(len(column), peak + 16))  # the whole donut
        y = float(np.sum(rows * column[rows]) / np.sum(column[rows]))
        # Distance from (col, y) to the infinite TRUTH line.
        d = abs((x1 - x0) * (y0 - y) - (x0 - col) * (y1 - y0)) / np.hypot(x1 - x0, y1 - y0)
        worst = max(worst, d)
    return worst


@pytest.fixture(scope="module")
def orbit_scene():
    raw = {**load_scene_file(str(ROOT / "sample_fields" / "pass_example.yaml")),
           "exptime": 1.0, "time": "2026-06-15T23:29:59.5", "stars": False, "noise": False,
           "sky": False, "detector": {"type": "itl", "nx": 256, "ny": 256},
           "pointing": {"ra": 151.95, "dec": -25.73, "rotation": 0.0}}
    raw.pop("zenith", None)
    return parse_scene(resolve_ccd_orbits(raw))


def test_an_orbit_row_is_the_streak_on_the_image(orbit_scene):
    image, (row,) = render_streaks(orbit_scene)
    assert not row["flags"] & FLAG_OFF_IMAGE and row["charge_in_image_e"] > 0
    # The line lies on the rendered ridge, and its ends are those of the part received (the
    # image grown by the profile's reach), not the pass's (tens of thousands of px away).
    assert _ridge_distance(image, row) < 0.5
    assert all(-400 < v < 656 for v in (row["x0"], row["y0"], row["x1"], row["y1"]))
    # The charge per pixel of track at the middle times the length on the image is the
    # charge received (the charge varies linearly along the pass over one second).
    chord = _chord_in_image(row, image.shape)
    assert row["flux_per_px_e"] * chord == pytest.approx(row["charge_in_image_e"], rel=0.01)
    assert row["flux_per_px_min_e"] <= row["flux_per_px_e"] <= row["flux_per_px_max_e"]


def test_a_polyline_row_is_the_middle_of_its_received_part():
    """A horizontal polyline through the middle row of a 200 x 100 image, from far off its left
    edge to far off its right one, dimming from mag 5 to 8 along 2000 px: the row describes the
    middle of the part the image (grown by the reach) receives, by the linear ramp of the
    vertices' charge per pixel, with the ramp's range over that part."""
    raw = apply_overrides(DEFAULT_SCENE, ["detector.nx=200", "detector.ny=100", *QUIET])
    raw["satellites"][0]["track"] = {"vertices": [
        {"x": -900.0, "y": 50.0, "mag": 5.0}, {"x": 1100.0, "y": 50.0, "mag": 8.0}]}
    scene = parse_scene(raw)
    _, (row,) = render_streaks(scene)
    reach = -0.5 - row["x0"]
    assert reach > 0 and row["x1"] == pytest.approx(199.5 + reach)
    sat = scene.satellites[0]
    flux = [StreakModel(sat.height, scene.zenith, sat.phi, sat.shape, m, "g").flux_per_px
            for m in (5.0, 8.0)]

    def ramp(x):
        return flux[0] + (x + 900.0) / 2000.0 * (flux[1] - flux[0])

    middle = 0.5 * (row["x0"] + row["x1"])
    assert row["flux_per_px_e"] == pytest.approx(ramp(middle), rel=1e-9)
    assert row["flux_per_px_max_e"] == pytest.approx(ramp(row["x0"]), rel=1e-9)
    assert row["flux_per_px_min_e"] == pytest.approx(ramp(row["x1"]), rel=1e-9)
    assert row["length_px"] == pytest.approx(row["x1"] - row["x0"])
    at_middle = StreakModel(sat.height, scene.zenith, sat.phi, sat.shape,
                            5.0 + 3.0 * (middle + 900.0) / 2000.0, "g")
    assert row["apparent_mag"] == pytest.approx(at_middle.apparent_mag, abs=1e-9)


def test_a_segment_row_is_its_part_on_the_image():
    """A 5000 px horizontal segment starting 400 px off the left edge of a 300 x 100 image:
    the row's ends are those of the image grown by the reach on both sides (the same reach a
    line of that model gets), its length their distance, and it is flagged clipped (the image
    holds far less than the whole track's charge)."""
    overrides = ["detector.nx=300", "detector.ny=100", "satellites.0.track.x0=-400",
                 "satellites.0.track.y0=50", "satellites.0.track.angle=0", *QUIET]
    line = parse_scene(apply_overrides(DEFAULT_SCENE, overrides))
    segment = parse_scene(apply_overrides(DEFAULT_SCENE, [*overrides,
                                                          "satellites.0.track.length=5000"]))
    _, (whole,) = render_streaks(line)
    _, (row,) = render_streaks(segment)
    reach = -0.5 - whole["x0"]
    assert 0 < reach < 400
    assert (row["x0"], row["x1"]) == pytest.approx((-0.5 - reach, 299.5 + reach))
    assert row["y0"] == row["y1"] == 50.0
    assert row["length_px"] == pytest.approx(300.0 + 2 * reach)
    assert row["flags"] & FLAG_CLIPPED
    assert row["charge_in_image_e"] == pytest.approx(whole["charge_in_image_e"], rel=1e-6)


def test_a_track_that_misses_the_image_is_only_off_image():
    """A track too bright for full well that misses the image: flagged off-image, not
    saturated (no SAT pixel of its own)."""
    scene = parse_scene(apply_overrides(DEFAULT_SCENE, [
        "detector.nx=64", "detector.ny=64", "satellites.0.mag=1", "satellites.0.track.x0=-5000",
        "satellites.0.track.y0=-5000", "satellites.0.track.angle=0", "noise=false",
        "stars=false"]))
    from inject import simulate
    result = simulate(scene)
    (row,) = result.truth
    assert row["flags"] == FLAG_OFF_IMAGE


def test_every_truth_table_has_the_same_columns(tmp_path, cli):
    """Empty or not, simulated or as CSV: the columns of inject.truth, in order."""
    scene = tmp_path / "s.yaml"
    scene.write_text("detector: {type: itl, nx: 64, ny: 64}\nstars: false\nsatellites:\n"
                     "  - {height: 550, mag: 5, shape: {type: box, length: 7.25, width: 2.65},\n"
                     "     track: {x0: 10, y0: 20, angle: 30}}\n")
    empty = tmp_path / "empty.yaml"
    empty.write_text("detector: {type: itl, nx: 64, ny: 64}\nstars: false\nsatellites: []\n")
    tables = []
    for name, path in (("one", scene), ("none", empty)):
        out, csv = tmp_path / f"{name}.fits", tmp_path / f"{name}.csv"
        status, _, err = cli("simulate", path, "-o", out, "--truth", csv)
        assert status == 0, err
        with fits.open(out) as hdul:
            tables.append(Table(hdul["TRUTH"].data))
        tables.append(Table.read(csv, format="ascii.csv"))
    for table in tables:
        assert table.colnames == list(TRUTH_COLUMNS)
    assert [len(t) for t in tables] == [1, 1, 0, 0]
    with fits.open(tmp_path / "none.fits") as hdul:
        empty_types = [hdul["TRUTH"].columns[n].format for n in TRUTH_COLUMNS]
    with fits.open(tmp_path / "one.fits") as hdul:
        assert [hdul["TRUTH"].columns[n].format for n in TRUTH_COLUMNS] == empty_types


def _model_and_truth(path):
    with fits.open(path) as hdul:
        return (float(hdul["STREAK_MODEL"].data.astype(np.float64).sum()),
                Table(hdul["TRUTH"].data))


def test_streak_model_sums_to_truth_in_every_file(tmp_path, cli):
    """``sum(STREAK_MODEL) == sum(TRUTH.charge_in_image_e)`` for a simulated file, for
    add-streak into it (both streaks in one model, rows numbered on) and into a plain image;
    the added rows carry the plate scale the WCS gave."""
    scene = tmp_path / "s.yaml"
    scene.write_text("detector: {type: itl, nx: 200, ny: 160}\nstars: false\nsky: false\n"
                     "noise: false\npointing: {ra: 10, dec: -5}\nsatellites:\n"
                     "  - {height: 550, mag: 8, shape: {type: box, length: 7.25, width: 2.65},\n"
                     "     track: {x0: 10, y0: 20, angle: 30, length: 120}}\n")
    simulated, added = tmp_path / "sim.fits", tmp_path / "added.fits"
    assert cli("simulate", scene, "-o", simulated)[0] == 0
    args = ["--height", "350", "--mag", "8", "--x0", "20", "--y0", "120", "--angle", "-10",
            "--track-length", "150", "--no-noise"]
    assert cli("add-streak", simulated, "-o", added, *args)[0] == 0
    plain = tmp_path / "plain.fits"
    header = fits.Header({"GAIN": 1.0})
    fits.PrimaryHDU(np.zeros((160, 200), np.float32), header=header).writeto(plain)
    plain_out = tmp_path / "plain_out.fits"
    assert cli("add-streak", plain, "-o", plain_out, *args, "--pixel-scale", "0.2")[0] == 0
    for path, n in ((simulated, 1), (added, 2), (plain_out, 1)):
        total, truth = _model_and_truth(path)
        assert len(truth) == n and list(truth["satellite"]) == list(range(n))
        assert total == pytest.approx(float(np.sum(truth["charge_in_image_e"])), rel=1e-5)
        assert np.all(np.isfinite(truth["pixel_scale_arcsec"]))
    with fits.open(added) as hdul:
        assert "INJECTED_MODEL" not in [h.name for h in hdul]
        assert Table(hdul["TRUTH"].data)["pixel_scale_arcsec"][1] == pytest.approx(0.2,
                                                                                    rel=1e-6)
