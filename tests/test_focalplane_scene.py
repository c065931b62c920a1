"""Focal-plane scenes: parsing, the CCDs a streak reaches, tracks across CCDs, charge lost in
the gaps, per-CCD profiles and plate scale, stars consistent across CCDs."""
import json

import numpy as np
import pytest

from inject import SceneError, make_plan, parse_focal_scene, simulate_ccd
from inject.camera import layout as fp
from inject.exposure.plan import ccd_streaks, margins_px, vertex_model

SAT = {"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}


def focal(**keys):
    raw = {"seed": 5, "band": "g", "zenith": 70, "pointing": {"ra": 50, "dec": -30,
                                                              "rotation": 10},
           "sky": False, "stars": False, "noise": False,
           "satellites": [dict(SAT, track={"x0_mm": -19.0, "y0_mm": -3.0, "angle": 3.0})]}
    raw.update(keys)
    return parse_focal_scene(raw)


@pytest.mark.parametrize("raw, match", [
    ({"detector": {"type": "itl"}}, "no 'detector' key"),
    ({"pointing": None}, "pointing: required"),
    ({"detectors": ["R00_S11"]}, "corner rafts"),
    ({"cutout": {"nx": 0, "ny": 10}}, "cutout"),
    ({"satellites": [dict(SAT, track={"x0": 1, "y0": 2, "angle": 0})]}, "unknown keys"),
    ({"satellites": [dict(SAT, track={"x0_mm": 1, "y0_mm": 2, "angle": 0, "length_mm": -1})]},
     "length_mm"),
    ({"satellites": [dict(SAT, track={"vertices": [{"x_mm": 0, "y_mm": 0, "height": -5},
                                                   {"x_mm": 1, "y_mm": 0}]})]}, "height"),
    ({"pointing": {"ra": 400, "dec": 0}}, r"pointing\.ra=400"),
])
def test_bad_focal_scenes_name_the_value(raw, match):
    with pytest.raises(SceneError, match=match):
        focal(**raw)


def test_streak_across_two_ccds_is_one_line_and_loses_the_gap():
    fscene = focal()
    margins = margins_px(fscene)
    angle = 3.0
    a = np.radians(angle)
    total = 0.0
    rows = {}
    for name in ("R22_S11", "R22_S12"):
        ccd = fp.ccd(name)
        _, result, streaks, _ = simulate_ccd(fscene, ccd, ccd_streaks(fscene, ccd, margins))
        (row,) = result.truth
        rows[name] = row
        # The truth end points, back in focal-plane mm, lie on the scene's line.
        for x, y in ((row["x0"], row["y0"]), (row["x1"], row["y1"])):
            xm, ym = ccd.pixel_to_focal(x, y)
            distance_px = abs(-(xm + 19.0) * np.sin(a) + (ym + 3.0) * np.cos(a)) / 0.01
            assert distance_px < 0.05
        # An infinite uniform line: the charge in a vertical strip is F x the chord, exactly
        # (the line stays > 1000 px from the top and bottom edges).
        chord_px = ccd.shape[1] / np.cos(a)
        charge = result.streak_model.sum()
        assert charge == pytest.approx(row["flux_per_px_e"] * chord_px, rel=2e-4)
        total += charge
    # From the left edge of S11 to the right edge of S12 minus the gap between them.
    left = fp.ccd("R22_S11").bounds_mm()[0]
    right = fp.ccd("R22_S12").bounds_mm()[1]
    gap_mm = fp.ccd("R22_S12").bounds_mm()[0] - fp.ccd("R22_S11").bounds_mm()[1]
    flux = np.mean([r["flux_per_px_e"] for r in rows.values()])
    along = (right - left - gap_mm) / 0.01 / np.cos(a)
    assert total == pytest.approx(flux * along, rel=2e-4)
    assert total < flux * (right - left) / 0.01 / np.cos(a) * (1 - 0.9 * gap_mm / (right - left))


def test_charge_per_pixel_uses_the_local_plate_scale():
    # Far from the boresight the pixel is smaller on the sky along the radius: t_eff (and so
    # the charge per pixel of track) scales with the pixel's angular length along the track.
    ccd = fp.ccd("R02_S01")  # centred on x = 0, y = -254 mm: the track runs nearly radially
    x_mm = float(ccd.pixel_to_focal(32, 0)[0])
    fscene = focal(satellites=[dict(SAT, track={"x0_mm": x_mm, "y0_mm": -290.0,
                                                "angle": 90.0})],
                   cutout={"nx": 64, "ny": 64})
    (streak,) = ccd_streaks(fscene, ccd, margins_px(fscene))
    _, result, _, _ = simulate_ccd(fscene, ccd, [streak])
    nominal = vertex_model(fscene, 0, fscene.tracks[0].values[0])  # 0.2"/px
    # The scale is taken at the middle of the track's part on the whole CCD (grown by the
    # same margin on both sides), not of the cut-out's: the CCD's middle row.
    ym = float(ccd.pixel_to_focal(0, (ccd.shape[0] - 1) / 2)[1])
    # Written out: the step along +y has components along and across the radius.
    r2 = x_mm ** 2 + ym ** 2
    s = 20.005867576692737
    radial = s * (1 - 3 * 8.33713991e-9 * r2 - 5 * 1.41389858e-15 * r2 ** 2)
    tangential = s * (1 - 8.33713991e-9 * r2 - 1.41389858e-15 * r2 ** 2)
    cos_rel = ym / np.sqrt(r2)
    expected = 0.01 * np.hypot(radial * cos_rel, tangential * np.sqrt(1 - cos_rel ** 2)) / 0.2
    assert result.truth[0]["flux_per_px_e"] / nominal.flux_per_px == pytest.approx(
        expected, rel=1e-6)
    assert expected < 0.9995


def test_polyline_profile_is_the_one_where_the_ccd_sits():
    # Along the bottom edges of the raft row (the cut-outs are each CCD's first 300 rows).
    vertices = [{"x_mm": -250.0, "y_mm": -19.3, "height": 350.0, "mag": 4.0},
                {"x_mm": 250.0, "y_mm": -18.7, "height": 800.0, "mag": 7.0}]
    fscene = focal(satellites=[dict(SAT, track={"vertices": vertices})],
                   cutout={"nx": 300, "ny": 300})
    seen = []
    for name in ("R21_S11", "R22_S10", "R23_S12"):
        ccd = fp.ccd(name)
        (streak,) = ccd_streaks(fscene, ccd, margins_px(fscene))
        # Independent: the fraction along the polyline of the CCD's entry point.
        xm, ym = ccd.pixel_to_focal(streak.ends[0], streak.ends[1])
        f = (xm + 250.0) / 500.0
        assert streak.values[0]["height"] == pytest.approx(350 + f * 450, rel=1e-9)
        assert streak.values[0]["mag"] == pytest.approx(4 + f * 3, rel=1e-9)
        _, result, _, _ = simulate_ccd(fscene, ccd, [streak])
        seen.append(result.truth[0]["height_km"])
    assert seen[0] < seen[1] < seen[2]


def test_plan_lists_the_ccds_the_footprint_reaches():
    fscene = focal(satellites=[dict(SAT, track={"x0_mm": 13.0, "y0_mm": -40.0,
                                                "angle": 61.0})])
    margins = margins_px(fscene)
    got = make_plan(fscene, margins).summary()["detectors"]
    # Independent: points every 2 um along the line, within the margin of each CCD's pixel
    # area (the footprint's reach: a rectangle with rounded corners).
    a = np.radians(61.0)
    t = np.arange(-450.0, 450.0, 0.002)
    px, py = 13.0 + t * np.cos(a), -40.0 + t * np.sin(a)
    expected = []
    for c in fp.CCDS:
        x0, x1, y0, y1 = c.bounds_mm()
        gap = np.hypot(np.maximum.reduce([x0 - px, 0 * px, px - x1]),
                       np.maximum.reduce([y0 - py, 0 * py, py - y1]))
        if np.any(gap <= margins[0] * fp.PIXEL_MM):
            expected.append(c.name)
    assert [d["name"] for d in got] == expected
    for d in got:
        ccd = fp.ccd(d["name"])
        (s,) = d["streaks"]
        for x, y in ((s["x0"], s["y0"]), (s["x1"], s["y1"])):
            xm, ym = ccd.pixel_to_focal(x, y)
            assert abs(-(xm - 13.0) * np.sin(a) + (ym + 40.0) * np.cos(a)) / 0.01 < 1e-6
            # The end points are on the grown CCD's edge.
            ny, nx = ccd.shape
            m = margins[0]
            on_edge = min(abs(x + 0.5 + m), abs(x - nx + 0.5 - m), abs(y + 0.5 + m),
                          abs(y - ny + 0.5 - m))
            assert on_edge < 1e-6


def test_stars_are_where_the_scene_puts_them_whatever_is_rendered():
    # A cut-out's pixels are the full CCD's corner, stars included (tiles, not CCDs, seed
    # the stars), and the stars near a shared corner tile differ from another seed's.
    keys = dict(stars={"galactic_b": 30, "mag_limit": 22})
    full = focal(**keys)
    small = focal(cutout={"nx": 400, "ny": 300}, **keys)
    ccd = fp.ccd("R30_S21")
    a = simulate_ccd(full, ccd, make_plan(full).streaks(ccd))[1].image
    b = simulate_ccd(small, ccd, make_plan(small).streaks(ccd))[1].image
    assert b.shape == (300, 400) and b.sum() > 0
    np.testing.assert_array_equal(a[:300, :400], b)


def test_cli_plan_json(tmp_path, capsys):
    from inject.cli.main import main

    scene = tmp_path / "focal.yaml"
    scene.write_text(json.dumps({"pointing": {"ra": 10, "dec": -5}, "stars": False,
                                 "detectors": ["R22_S11", "R22_S12", "R30_S00"],
                                 "satellites": [dict(SAT, track={"x0_mm": -19.0, "y0_mm": 0.0,
                                                                 "angle": 0.0})]}))
    assert main(["focalplane", str(scene), "--plan", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [d["name"] for d in result["detectors"]] == ["R22_S11", "R22_S12"]
    for d in result["detectors"]:
        assert set(d) >= {"name", "id", "vendor", "streaks"}
        assert set(d["streaks"][0]) >= {"x0", "y0", "x1", "y1"}
    assert main(["focalplane", str(scene), "--plan", "--detectors", "R00_S00"]) == 2
    err = capsys.readouterr().err
    assert "R00_S00" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("gap_px, planned", [(0.8, True), (1.2, False)])
def test_a_ccd_counts_only_where_the_footprint_itself_reaches(gap_px, planned):
    """A 45 deg track passing R22_S11's top-right corner at ``gap_px`` margins from it: it
    lies inside the CCD's rectangle grown by the margin either way (the grown corner is
    sqrt(2) margins away), but only within one margin does its footprint reach the CCD."""
    ccd = fp.ccd("R22_S11")
    margin = margins_px(focal())[0]
    _, xmax, _, ymax = ccd.bounds_mm()
    d = gap_px * margin * fp.PIXEL_MM  # the track's distance to the corner, mm
    # Through the point at distance d from the corner along the outward diagonal, at -45 deg.
    x0, y0 = xmax + d / np.sqrt(2), ymax + d / np.sqrt(2)
    fscene = focal(satellites=[dict(SAT, track={"x0_mm": x0, "y0_mm": y0, "angle": -45.0})])
    assert bool(ccd_streaks(fscene, ccd, (margin,))) == planned
    assert (ccd in make_plan(fscene, (margin,)).streak_ccds()) == planned


def test_the_focus_offset_reaches_every_streak_and_the_header():
    """``focus_offset_um`` of a focal-plane scene is in each streak's model (the plan's and
    the CCD's renders build theirs with :func:`vertex_model`) and in each CCD's ``FOCUSDZ``."""
    from inject.exposure.ccd import ccd_scene
    from inject.io.fits import primary_header

    fscene = focal(pupil="rubin", focus_offset_um=-5)
    assert fscene.scene.focus_offset_um == -5.0
    model = vertex_model(fscene, 0, fscene.tracks[0].values[0])
    assert model.pupil == "rubin" and model.focus_offset_um == -5.0
    scene = ccd_scene(fscene, fp.ccd("R22_S11"))
    assert primary_header(scene)["FOCUSDZ"] == -5.0
    assert primary_header(ccd_scene(focal(), fp.ccd("R22_S11")))["FOCUSDZ"] == 0.0


@pytest.mark.parametrize("keys, match", [
    ({"focus_offset_um": 5}, r"^focus_offset_um=5\.0: only with pupil: rubin \(pupil: annulus"),
    ({"pupil": "rubin", "focus_offset_um": 2000},
     r"^focus_offset_um=2000.*\[-1000, 1000\]")])
def test_a_focal_plane_focus_offset_is_refused_as_a_ccd_scenes(keys, match):
    from inject import parse_scene

    with pytest.raises(SceneError, match=match) as focal_error:
        focal(**keys)
    ccd = {"detector": {"type": "itl", "nx": 64, "ny": 64}, "satellites": [], **keys}
    with pytest.raises(SceneError) as ccd_error:
        parse_scene(ccd)
    assert str(focal_error.value) == str(ccd_error.value)
