"""TRUTH_VERTICES: the vertices of each streak's part on the image, whose piecewise-linear path
is the STREAK_MODEL's ridge (to 0.1 px) where TRUTH's chord is not: a circular arc of known
centre and radius, and a real pass from a TLE."""
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

from inject import DEFAULT_SCENE, apply_overrides, read_truth

ROOT = Path(__file__).resolve().parents[1]
QUIET = {"stars": False, "sky": False, "noise": False}

#: The arc: centre and radius (px), vertices every ``step`` deg from 20 to 160 deg, its top at
#: y = 80 in a 240 x 160 image.
CENTRE, RADIUS = (120.0, -220.0), 300.0


def _arc_deg(step):
    return np.arange(20.0, 161.0, step)


def _write(tmp_path, raw, cli, name="scene"):
    scene = tmp_path / f"{name}.yaml"
    scene.write_text(yaml.safe_dump(raw))
    out = tmp_path / f"{name}.fits"
    status, _, err = cli("simulate", scene, "-o", out, "--truth", tmp_path / f"{name}.csv")
    assert status == 0, err
    return out


def _arc_scene(step=2.0):
    raw = apply_overrides(DEFAULT_SCENE, ["detector.nx=240", "detector.ny=160"])
    cx, cy = CENTRE
    a = np.radians(_arc_deg(step))
    raw["satellites"][0]["track"] = {"vertices": [
        {"x": float(cx + RADIUS * np.cos(t)), "y": float(cy + RADIUS * np.sin(t))} for t in a]}
    return {**raw, **QUIET}


def _distance_to_path(px, py, xs, ys):
    """Least distance from points to the segments of the path ``(xs, ys)``."""
    best = np.full(np.shape(px), np.inf)
    for ax, ay, bx, by in zip(xs[:-1], ys[:-1], xs[1:], ys[1:]):
        dx, dy = bx - ax, by - ay
        t = np.clip(((px - ax) * dx + (py - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
        best = np.minimum(best, np.hypot(px - ax - t * dx, py - ay - t * dy))
    return best


def _column_ridge(model, max_slope=1.0, half=14):
    """The ridge as ``(x, y)``: in each column whose peak is above half the image's, the
    centroid over a window of +-``half`` rows moved onto the centroid until it settles (the
    centre of a symmetric cross-section); columns whose window leaves the image, or where the
    ridge is steeper than ``max_slope``, are left out."""
    xs, ys = [], []
    for col in range(model.shape[1]):
        column = model[:, col]
        if column.max() < 0.5 * model.max():
            continue
        centre = float(np.argmax(column))
        for _ in range(20):
            rows = np.arange(round(centre) - half, round(centre) + half + 1)
            if rows[0] < 0 or rows[-1] >= len(column):
                break
            centre = float(np.sum(rows * column[rows]) / np.sum(column[rows]))
        else:
            xs.append(col)
            ys.append(centre)
    xs, ys = np.array(xs, float), np.array(ys)
    slope = np.abs(np.gradient(ys, xs))
    return xs[slope < max_slope], ys[slope < max_slope]


def _vertices_of(path, row=0):
    table = Table.read(path, hdu="TRUTH_VERTICES")
    mine = table[table["row"] == row]
    assert list(mine["vertex"]) == list(range(len(mine)))
    return np.array(mine["x"]), np.array(mine["y"])


@pytest.mark.parametrize("step", [2.0, 10.0])
def test_an_arc_s_ridge_is_the_path_through_its_vertices(tmp_path, cli, step):
    """A circular arc's part on the image, its vertices every 2 or 10 deg: the model's ridge,
    found column by column, is within 0.1 px of the path through TRUTH_VERTICES, whose ends
    are TRUTH's and whose points lie between the arc and its polygon; TRUTH's chord misses
    the ridge by the arc's sagitta over the part (tens of px). At 10 deg the ridge rounds the
    polygon's corners (0.2 px inside them), and the vertices follow it."""
    out = _write(tmp_path, _arc_scene(step), cli)
    with fits.open(out) as hdus:
        model = np.asarray(hdus["STREAK_MODEL"].data, float)
        row = hdus["TRUTH"].data[0]
    xs, ys = _vertices_of(out)
    assert (xs[0], ys[0], xs[-1], ys[-1]) == (row["x0"], row["y0"], row["x1"], row["y1"])
    # Inside the circle by at most a piece's sagitta, R (1 - cos(step / 2)), and a little
    # more at the rounded corners.
    radius = np.hypot(xs - CENTRE[0], ys - CENTRE[1])
    assert np.all(radius <= RADIUS + 1e-9)
    assert np.all(radius >= RADIUS * np.cos(np.radians(step / 2)) - 0.5)
    rx, ry = _column_ridge(model)
    assert len(rx) > 150
    assert _distance_to_path(rx, ry, xs, ys).max() < 0.1
    chord = _distance_to_path(rx, ry, xs[[0, -1]], ys[[0, -1]])
    assert chord.max() > 20.0
    a = np.radians(_arc_deg(step))
    polygon = _distance_to_path(rx, ry, CENTRE[0] + RADIUS * np.cos(a),
                                CENTRE[1] + RADIUS * np.sin(a))
    if step == 10.0:
        assert polygon.max() > 0.15


def test_a_real_pass_s_ridge_is_the_path_through_its_vertices(tmp_path, cli):
    """The pass of pass_example.yaml's TLE on a 512 x 512 CCD: the model's ridge within 0.1 px
    of the path through TRUTH_VERTICES, whose ends are TRUTH's and whose interior vertices
    are the pass's samples (computed here, every 0.1 s, in field angles: 0.2" pixels about
    the CCD's centre)."""
    from inject import Exposure, Orbit, Pointing, compute_pass
    from inject.orbits.passes import TRACK_STEP_S

    raw = {**yaml.safe_load((ROOT / "sample_fields" / "pass_example.yaml").read_text()),
           **QUIET, "detector": {"type": "itl", "nx": 512, "ny": 512},
           "time": "2026-06-15T23:29:58.5", "exptime": 3.0}  # a sample on the CCD
    raw["satellites"][0]["orbit"]["tle"] = str(ROOT / "sample_fields"
                                               / "example_starlink_like.tle")
    out = _write(tmp_path, raw, cli)
    with fits.open(out) as hdus:
        model = np.asarray(hdus["STREAK_MODEL"].data, float)
        row = hdus["TRUTH"].data[0]
    xs, ys = _vertices_of(out)
    assert (xs[0], ys[0], xs[-1], ys[-1]) == (row["x0"], row["y0"], row["x1"], row["y1"])
    assert len(xs) >= 3
    dense = compute_pass(Orbit.read_tle(raw["satellites"][0]["orbit"]["tle"]),
                         Exposure(raw["time"], raw["exptime"]),
                         Pointing(raw["pointing"]["ra"], raw["pointing"]["dec"], 0.0),
                         step_s=TRACK_STEP_S)
    px = 255.5 + dense.field_x_deg * 3600 / 0.2
    py = 255.5 + dense.field_y_deg * 3600 / 0.2
    for x, y in zip(xs[1:-1], ys[1:-1]):
        assert np.nanmin(np.hypot(px - x, py - y)) < 1e-6
    # The path's length is TRUTH's length_px (the part's along the track).
    assert np.hypot(np.diff(xs), np.diff(ys)).sum() == pytest.approx(row["length_px"],
                                                                     rel=1e-12)
    rx, ry = _column_ridge(model)
    assert len(rx) > 400
    assert _distance_to_path(rx, ry, xs, ys).max() < 0.1


def test_vertices_round_trip_through_the_reader_and_the_csv(tmp_path, cli):
    """The FITS table read back by :func:`inject.read_truth` and the CSV beside
    ``--truth``'s give the same vertices, for a straight track (its two ends) and a polyline,
    numbered by TRUTH row."""
    raw = _arc_scene(10.0)
    raw["satellites"].append({**raw["satellites"][0],
                              "track": {"x0": 10.0, "y0": 20.0, "angle": 30.0}})
    out = _write(tmp_path, raw, cli)
    rows = read_truth(out)
    assert len(rows) == 2
    assert rows[1]["vertices"] == ((rows[1]["x0"], rows[1]["y0"]), (rows[1]["x1"], rows[1]["y1"]))
    xs, ys = _vertices_of(out, row=0)
    assert rows[0]["vertices"] == tuple(zip(xs.tolist(), ys.tolist()))
    csv = Table.read(tmp_path / "scene_vertices.csv", format="ascii.csv")
    assert csv.colnames == ["row", "satellite", "vertex", "x", "y"]
    for i, row in enumerate(rows):
        mine = csv[csv["row"] == i]
        assert set(mine["satellite"]) == {row["satellite"]}
        assert tuple(zip(mine["x"].tolist(), mine["y"].tolist())) == row["vertices"]
    assert Table.read(tmp_path / "scene.csv", format="ascii.csv")["n_vertices"].tolist() == [
        len(_arc_deg(10.0)), 2]


def test_add_streak_keeps_the_input_s_vertices_and_adds_its_own(tmp_path, cli):
    """add-streak into a file with a polyline: TRUTH_VERTICES keeps the input's rows as they
    were and adds the new streak's two ends as row 1, satellite 1."""
    source = _write(tmp_path, _arc_scene(10.0), cli)
    out = tmp_path / "plus.fits"
    status, _, err = cli("add-streak", source, "-o", out, "--height", "550", "--zenith", "60",
                         "--mag", "9", "--x0", "20", "--y0", "30", "--angle", "15",
                         "--track-length", "100", "--seed", "1")
    assert status == 0, err
    before, after = Table.read(source, hdu="TRUTH_VERTICES"), Table.read(out,
                                                                           hdu="TRUTH_VERTICES")
    assert len(after) == len(before) + 2
    assert all(np.array_equal(after[c][:len(before)], before[c]) for c in before.colnames)
    added = after[len(before):]
    assert list(added["row"]) == [1, 1] and list(added["satellite"]) == [1, 1]
    truth = Table.read(out, hdu="TRUTH")
    assert (added["x"][0], added["y"][0], added["x"][1], added["y"][1]) == pytest.approx(
        (truth["x0"][1], truth["y0"][1], truth["x1"][1], truth["y1"][1]))
    assert (truth["x0"][1], truth["y0"][1]) == pytest.approx((20.0, 30.0))
