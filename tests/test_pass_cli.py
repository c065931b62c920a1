"""``inject pass`` and orbit tracks on the focal plane (issue 13)."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy import units as u
from astropy.coordinates import ICRS, AltAz, SkyCoord

from inject import ccd_wcs, resolve_ccd_orbits
from inject.camera import layout as fp
from inject.cli.main import main
from inject.orbits.passes import (
    RUBIN,
    TRACK_STEP_S,
    Exposure,
    Orbit,
    Pointing,
    compute_pass,
    track_runs,
)
from inject.trajectory import clip_path

ROOT = Path(__file__).resolve().parents[1]
TLE = ROOT / "sample_fields" / "example_starlink_like.tle"
#: The example TLE is aimed (orbits.aimed_orbit) at alt 60, az 270 seen from Rubin at
#: 2026-06-15T23:30:00, the middle of this exposure; (RA, Dec) is that direction in ICRS.
START, EXPTIME, RA, DEC = "2026-06-15T23:29:45", 30.0, 151.95, -25.73
SAMPLE_KEYS = {"t_s": float, "utc": str, "alt_deg": float, "az_deg": float, "range_km": float,
               "nadir_angle_deg": float, "phi_deg": float, "angular_speed_rad_s": float,
               "sunlit": bool}


def run_json(capsys, *args):
    status = main(["pass", *map(str, args), "--json"])
    out, err = capsys.readouterr()
    assert status == 0, err
    return json.loads(out), err


@pytest.fixture(scope="module")
def example():
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["pass", "--tle", str(TLE), "--time", START, "--exptime", str(EXPTIME),
                     "--ra", str(RA), "--dec", str(DEC), "--json"]) == 0
    return json.loads(buf.getvalue())


def test_json_keys_and_types(example):
    assert isinstance(example["in_field"], bool)
    assert isinstance(example["message"], str)
    assert isinstance(example["detectors"], list)
    assert all(isinstance(d, str) for d in example["detectors"])
    samples = example["samples"]
    t = np.array([s["t_s"] for s in samples])
    assert t[0] == 0 and t[-1] == EXPTIME and np.diff(t).max() <= 1.0
    assert EXPTIME / 2 in t  # one at the middle
    for s in samples:
        for key, kind in SAMPLE_KEYS.items():
            assert isinstance(s[key], kind), key
        for key in ("x_mm", "y_mm"):
            assert s[key] is None or isinstance(s[key], float)
    assert any(s["x_mm"] is not None for s in samples)


def test_aimed_example_crosses_the_centre(example):
    assert example["in_field"] and example["message"] == "crosses the field, sunlit"
    assert "R22_S11" in example["detectors"]
    # At the middle the satellite is where the pointing is: the focal-plane centre (the TLE's
    # rounding and the pointing's rounding to 0.01 deg leave it a few mm off at most).
    mid = next(s for s in example["samples"] if s["t_s"] == EXPTIME / 2)
    assert math.hypot(mid["x_mm"], mid["y_mm"]) < 3.0
    # The crossed CCDs are those a straight line through the samples' positions reaches,
    # independently clipped here against each CCD's box.
    pts = [(s["x_mm"], s["y_mm"]) for s in example["samples"] if s["x_mm"] is not None]
    (x0, y0), (x1, y1) = pts[0], pts[-1]
    expected = set()
    for c in fp.CCDS:
        bx0, bx1, by0, by1 = c.bounds_mm()
        tt = np.linspace(-0.5, 1.5, 20001)
        xs, ys = x0 + tt * (x1 - x0), y0 + tt * (y1 - y0)
        inside = (xs > bx0 + 0.05) & (xs < bx1 - 0.05) & (ys > by0 + 0.05) & (ys < by1 - 0.05)
        if inside.any():
            expected.add(c.name)
    assert expected <= set(example["detectors"])
    # The bend of the distortion (< 1 mm) adds at most CCDs touched at a corner.
    assert len(set(example["detectors"]) - expected) <= 2


def test_a_miss_gives_no_detectors(capsys):
    report, _ = run_json(capsys, "--tle", TLE, "--time", START, "--exptime", EXPTIME,
                         "--ra", (RA + 40) % 360, "--dec", DEC)
    assert report["in_field"] is False
    assert report["detectors"] == []
    assert "misses the field" in report["message"]
    assert all(s["x_mm"] is None for s in report["samples"])


@pytest.mark.parametrize("rotation", [0.0, 35.0])
def test_focal_positions_through_the_ccd_wcs(rotation):
    """A sample's x_mm, y_mm through its CCD's WCS (astropy) is the satellite's apparent
    direction, converted from AltAz to ICRS by astropy as a star seen there would be."""
    orbit = Orbit.read_tle(TLE)
    p = compute_pass(orbit, Exposure(START, EXPTIME), Pointing(RA, DEC, rotation), RUBIN)
    x, y = p.focal_mm()
    pointing = {"ra": RA, "dec": DEC, "rotation": rotation}
    checked = 0
    for i in np.flatnonzero(np.isfinite(x)):
        hits = [c for c in fp.CCDS if clip_path([x[i], x[i] + 1e-6], [y[i], y[i]],
                                                   c.bounds_mm())]
        if not hits:
            continue  # in a gap between CCDs
        ccd = hits[0]
        px, py = ccd.focal_to_pixel(x[i], y[i])
        sky = ccd_wcs(ccd, pointing).pixel_to_world(px, py)
        frame = AltAz(obstime=p.utc[i], location=RUBIN.location)
        truth = SkyCoord(az=p.apparent_az_deg[i] * u.deg, alt=p.apparent_alt_deg[i] * u.deg,
                         frame=frame).transform_to(ICRS())
        assert sky.separation(truth).to_value(u.arcsec) < 0.1
        checked += 1
    assert checked >= 5


def test_track_vertices_follow_the_path():
    """The renderer's vertices (from the 0.1 s pass) against the pass sampled in between:
    every off-grid position within 0.1 px of the polyline."""
    orbit = Orbit.read_tle(TLE)
    exposure, pointing = Exposure(START, EXPTIME), Pointing(RA, DEC, 20.0)
    dense = compute_pass(orbit, exposure, pointing, step_s=TRACK_STEP_S)
    xd, yd, runs = track_runs(dense)
    assert len(runs) == 1
    run = runs[0]
    assert np.diff(dense.t_s[run]).max() <= 1.0 + 1e-9
    probe = compute_pass(orbit, exposure, pointing, t_s=np.arange(0.037, EXPTIME, 0.29))
    xp, yp = probe.focal_mm()
    vx, vy = xd[run], yd[run]
    worst = 0.0
    for xq, yq, tq in zip(xp, yp, probe.t_s):
        if not np.isfinite(xq) or not dense.t_s[run[0]] <= tq <= dense.t_s[run[-1]]:
            continue
        k = np.searchsorted(dense.t_s[run], tq) - 1
        ax, ay, bx, by = vx[k], vy[k], vx[k + 1], vy[k + 1]
        d = abs((xq - ax) * (by - ay) - (yq - ay) * (bx - ax)) / math.hypot(bx - ax, by - ay)
        worst = max(worst, d / fp.PIXEL_MM)
    assert 0 < worst < 0.1


def test_orbit_option(capsys):
    report, _ = run_json(capsys, "--orbit", "height=550,inclination=53,raan=10,mean_anomaly=40",
                         "--time", START, "--exptime", 16, "--ra", 10, "--dec", -30)
    assert report["orbit_kind"] == "circular" and report["tle"][1].startswith("2 99999  53.0")
    assert [s["t_s"] for s in report["samples"]] == [float(k) for k in range(17)]
    assert report["in_field"] is False and "below the horizon" in report["message"]


def test_far_epoch_warns_in_one_line(capsys):
    _, err = run_json(capsys, "--orbit", "height=550,inclination=53,raan=10,mean_anomaly=40,"
                                         "epoch=2026-06-01T00:00:00",
                      "--time", START, "--exptime", 2, "--ra", 10, "--dec", -30)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("inject pass: warning: ")
    assert "days from the exposure" in lines[0]


@pytest.mark.parametrize("edit, what", [
    (lambda lines: [lines[0], lines[1][:-1] + str((int(lines[1][-1]) + 1) % 10), lines[2]],
     "bad checksum"),
    (lambda lines: lines[:2], "expected 2 TLE lines"),
])
def test_bad_tle_file(tmp_path, capsys, edit, what):
    bad = tmp_path / "bad.tle"
    bad.write_text("\n".join(edit(TLE.read_text().splitlines())) + "\n")
    if what == "expected 2 TLE lines":
        bad.write_text(TLE.read_text().splitlines()[1] + "\n")
    status = main(["pass", "--tle", str(bad), "--time", START, "--exptime", "30", "--ra",
                   str(RA), "--dec", str(DEC)])
    out, err = capsys.readouterr()
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("inject pass: error: ")
    assert what in err


@pytest.mark.parametrize("args, named", [
    (["--orbit", "height=550,inclination=53,raan=10"], "mean_anomaly"),
    (["--orbit", "height=550,inclination=53,raan=10,mean_anomaly=4,colour=red"], "colour"),
    (["--tle", str(TLE), "--site", "30,70"], "30,70"),
    (["--tle", str(TLE), "--exptime", "-1"], "-1"),
    # The input-ranges table (inject.validate.RANGES) on every value of inject pass:
    (["--tle", str(TLE), "--exptime", "4000"], "--exptime=4000.0: must be > 0 and <= 3600"),
    (["--orbit", "height=550,inclination=200,raan=0,mean_anomaly=0"],
     "--orbit.inclination=200.0: must be >= 0 and <= 180"),
    (["--orbit", "height=20,inclination=50,raan=0,mean_anomaly=0"],
     "--orbit.height=20.0: must be >= 80"),
    (["--orbit", "height=550,inclination=50,raan=x,mean_anomaly=0"],
     "--orbit.raan='x': must be a number"),
    (["--orbit", f"height=550,inclination=50,raan=0,mean_anomaly=0,epoch={'2026-01-01'}"],
     "more than 60 is refused"),
    (["--tle", str(TLE), "--site", "-95,-70,2000"], "--site lat=-95.0: must be >= -90"),
    (["--tle", str(TLE), "--site", "-30,-70,20000"], "--site height=20000.0: must be >= -500 "
                                                      "and <= 10000 m"),
    (["--tle", str(TLE), "--ra", "400"], "--ra=400.0: must be >= 0 and < 360"),
    (["--tle", str(TLE), "--dec", "-91"], "--dec=-91.0: must be >= -90"),
])
def test_bad_options_one_line(capsys, args, named):
    base = {"--time": START, "--exptime": "30", "--ra": str(RA), "--dec": str(DEC)}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v
    # (a value starting with '-' needs KEY=VALUE, as the help of --site says)
    argv = ["pass"] + [item for k, v in base.items()
                       for item in ([f"{k}={v}"] if v.startswith("-") else [k, v])]
    status = main(argv)
    _, err = capsys.readouterr()
    assert status == 2 and len(err.strip().splitlines()) == 1 and named in err


def test_plot_written_and_not_replaced(tmp_path, capsys):
    out = tmp_path / "pass.png"
    argv = ["pass", "--tle", str(TLE), "--time", START, "--exptime", "4", "--ra", str(RA),
            "--dec", str(DEC), "--plot", str(out)]
    assert main(argv) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()
    assert main(argv) == 2  # exists: not replaced without --overwrite
    assert "exists" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0


# --- orbit tracks in focal-plane scenes ------------------------------------------------------

SCENE = ROOT / "sample_fields" / "pass_example.yaml"


def _scene(**changes):
    from inject import load_scene_file
    return {**load_scene_file(str(SCENE)), **changes}


def test_plan_of_the_orbit_scene_matches_inject_pass(capsys, monkeypatch):
    """`inject focalplane --plan --json` of the example scene (a 4 s exposure about the
    middle, to keep the test quick) reaches the CCDs `inject pass` says the track crosses, and
    others only within a footprint's reach of the pass's own samples."""
    start = "2026-06-15T23:29:58"
    assert main(["focalplane", str(SCENE), "--plan", "--json", "exptime=4",
                 f"time={start}"]) == 0
    plan = json.loads(capsys.readouterr().out)
    names = {d["name"] for d in plan["detectors"]}
    report, _ = run_json(capsys, "--tle", TLE, "--time", start, "--exptime", 4, "--ra", RA,
                         "--dec", DEC)
    assert report["detectors"] and set(report["detectors"]) <= names
    pts = np.array([(s["x_mm"], s["y_mm"]) for s in report["samples"]])
    (x0, y0), (x1, y1) = pts[0], pts[-1]
    for name in names - set(report["detectors"]):
        bx0, bx1, by0, by1 = fp.BY_NAME[name].bounds_mm()
        tt = np.linspace(0, 1, 4001)
        dx = np.maximum(np.maximum(bx0 - (x0 + tt * (x1 - x0)), 0), (x0 + tt * (x1 - x0)) - bx1)
        dy = np.maximum(np.maximum(by0 - (y0 + tt * (y1 - y0)), 0), (y0 + tt * (y1 - y0)) - by1)
        assert np.hypot(dx, dy).min() < 3.0  # mm: 300 px, more than the footprint's reach
    (record,) = plan["satellites"]
    assert record["message"] == "crosses the field, sunlit" and record["sunlit"]
    assert set(record["ccds"].split()) == names and record["in_field"]


def test_orbit_track_vertices_carry_the_pass():
    from inject import parse_focal_scene
    from inject.orbits.passes import Pass
    fscene = parse_focal_scene(_scene(exptime=4, time="2026-06-15T23:29:58"))
    track = fscene.tracks[0]
    assert track.kind == "polyline" and len(track.xs) >= 5
    orbit = Orbit.read_tle(TLE)
    dense = compute_pass(orbit, Exposure("2026-06-15T23:29:58", 4.0), Pointing(RA, DEC, 0.0),
                         step_s=TRACK_STEP_S)
    x, y = dense.focal_mm()
    for xv, yv, values in zip(track.xs, track.ys, track.values):
        i = int(np.nanargmin(np.hypot(x - xv, y - yv)))
        assert math.hypot(x[i] - xv, y[i] - yv) < 1e-9  # a vertex is a sample of the pass
        assert values["zenith"] == pytest.approx(90 - dense.alt_deg[i], abs=1e-9)
        assert values["phi"] == pytest.approx(dense.phi_deg[i], abs=1e-9)
        assert values["mag"] == pytest.approx(5.0)  # sunlit: the reference magnitude
        # The vertex carries the pass's exact range and angular speed (the spherical Earth's
        # would be 0.5% and 3.5% off), so the model's brightness is Pass.magnitude's (the
        # nadir angle is still the spherical Earth's: < 0.01 mag).
        from inject.exposure.plan import vertex_model
        model = vertex_model(fscene, 0, values)
        assert model.geometry.range_km == pytest.approx(dense.range_km[i], rel=1e-12)
        assert model.geometry.angular_speed_rad_s == pytest.approx(
            dense.angular_speed_rad_s[i], rel=1e-12)
        assert model.apparent_mag == pytest.approx(Pass.magnitude(dense, 5.0)[i], abs=0.01)


@pytest.mark.parametrize("changes, why", [
    ({"pointing": {"ra": (RA + 40) % 360, "dec": DEC}}, "misses the field"),
    ("shadow", "Earth's shadow"),
])
def test_orbit_scene_without_a_streak_says_why(changes, why, capsys):
    from inject import OrbitWarning, make_plan, parse_focal_scene
    from inject.orbits.passes import aimed_orbit
    if changes == "shadow":  # the same shell, aimed east at the same time: in Earth's shadow
        orbit = aimed_orbit("2026-06-15T23:30:00", 60.0, 90.0)
        from astropy.time import Time
        frame = AltAz(obstime=Time("2026-06-15T23:30:00"), location=RUBIN.location)
        c = SkyCoord(az=90 * u.deg, alt=60 * u.deg, frame=frame).transform_to(ICRS())
        raw = _scene(exptime=4, time="2026-06-15T23:29:58",
                     pointing={"ra": float(c.ra.deg), "dec": float(c.dec.deg)})
        raw["satellites"] = [{**raw["satellites"][0], "orbit": {"tle": list(orbit.tle_lines())}}]
    else:
        raw = _scene(exptime=4, time="2026-06-15T23:29:58", **changes)
    with pytest.warns(OrbitWarning, match=why):
        fscene = parse_focal_scene(raw)
    assert fscene.tracks[0].xs == ()
    result = make_plan(fscene).summary()
    assert result["detectors"] == []
    assert why in result["satellites"][0]["message"]


@pytest.mark.parametrize("change, named", [
    ({"time": None}, "time: required"),
    ({"satellites": [{"mag": 5, "shape": {"type": "box", "length": 7, "width": 2},
                      "orbit": {"tle": ["1 bad", "2 bad"]}}]}, "TLE line 1"),
    ({"satellites": [{"mag": 5, "height": 550, "shape": {"type": "box", "length": 7,
                                                          "width": 2},
                      "orbit": {"height": 550, "inclination": 53, "raan": 0,
                                "mean_anomaly": 0}}]}, "comes from the orbit"),
    ({"satellites": [{"mag": 5, "shape": {"type": "box", "length": 7, "width": 2},
                      "orbit": {"height": 550, "inclination": 53}}]}, "raan"),
    # The same table and parser as inject pass's --orbit and --site:
    ({"satellites": [{"mag": 5, "shape": {"type": "box", "length": 7, "width": 2},
                      "orbit": {"height": 550, "inclination": -3, "raan": 0,
                                "mean_anomaly": 0}}]},
     r"^satellites\[0\]\.orbit\.inclination=-3: must be >= 0 and <= 180"),
    ({"satellites": [{"mag": 5, "shape": {"type": "box", "length": 7, "width": 2},
                      "orbit": {"height": 550, "inclination": 53, "raan": 0,
                                "mean_anomaly": 0, "epoch": "2026-01-01"}}]},
     "more than 60 is refused"),
    ({"site": {"lat": -30, "lon": -70, "height": 1e5}}, "site height=100000.0: must be"),
    ({"site": [-30, -70]}, "site=\\[-30, -70\\]: must be LAT,LON,M"),
    ({"pointing": {"ra": 151.95, "dec": 95}}, r"pointing\.dec=95"),
])
def test_bad_orbit_scene(change, named):
    from inject import SceneError, parse_focal_scene
    with pytest.raises(SceneError, match=named):
        parse_focal_scene(_scene(**change))


def test_shadow_entry_ends_the_streak_and_the_penumbra_fades_it():
    """A pass through the penumbra into the umbra while in the field (the example shell aimed
    east near the terminator): the track stops at the last sunlit sample of the 0.1 s pass, and
    each vertex's mag is the reference dimmed by -2.5 log10 of the visible Sun."""
    from astropy.time import Time

    from inject import parse_focal_scene
    from inject.orbits.passes import aimed_orbit
    t_aim = Time("2026-06-15T23:27:00")
    orbit = aimed_orbit(t_aim, 60.0, 90.0)
    exposure = Exposure(t_aim + 8 * u.s, 10.0)
    # Point at where the satellite appears at the middle of the exposure (ICRS as a star).
    first = compute_pass(orbit, exposure, Pointing(0.0, 0.0), t_s=[5.0])
    frame = AltAz(obstime=first.utc[0], location=RUBIN.location)
    c = SkyCoord(az=first.apparent_az_deg[0] * u.deg, alt=first.apparent_alt_deg[0] * u.deg,
                 frame=frame).transform_to(ICRS())
    pointing = Pointing(float(c.ra.deg), float(c.dec.deg))
    dense = compute_pass(orbit, exposure, pointing, step_s=TRACK_STEP_S)
    lit = dense.sun_fraction > 0
    assert lit[0] and not lit[-1] and (dense.sun_fraction[lit] < 1).all()  # penumbra -> umbra
    raw = _scene(exptime=10.0, time=exposure.start.isot,
                 pointing={"ra": pointing.ra_deg, "dec": pointing.dec_deg})
    raw["satellites"] = [{**raw["satellites"][0], "orbit": {"tle": list(orbit.tle_lines())}}]
    track = parse_focal_scene(raw).tracks[0]
    assert "shadow" in track.message
    x, y = dense.focal_mm()
    idx = [int(np.nanargmin(np.hypot(x - xv, y - yv))) for xv, yv in zip(track.xs, track.ys)]
    last = np.flatnonzero(lit)[-1]
    assert idx[-1] == last and np.isfinite(x[last + 1])  # ends at umbra entry, in the field
    mags = np.array([v["mag"] for v in track.values])
    # (the scene time is the ISO string, rounded to 1 ms: 1e-6 mag where the Sun is a sliver)
    np.testing.assert_allclose(mags, 5.0 - 2.5 * np.log10(dense.sun_fraction[idx]), atol=1e-4)
    assert (np.diff(mags) > 0).all()  # fading


def _ccd_scene_raw(start="2026-06-15T23:29:58", exptime=4.0, **changes):
    raw = _scene(exptime=exptime, time=start, detector={"type": "itl", "nx": 2000, "ny": 2000},
                 stars=False, noise=False, sky=False)
    raw.pop("zenith")
    return {**raw, **changes}


def test_orbit_in_a_ccd_scene_lands_where_the_wcs_says():
    """`inject simulate`'s scene: the orbit's vertices in the CCD's pixels, through the scene's
    WCS (inject.camera.wcs.pointing_wcs), are the satellite's apparent place (ICRS as a star) to
    < 0.1"; the middle of the exposure is near the image centre."""
    from inject import LSST, parse_scene, pointing_wcs
    scene = parse_scene(resolve_ccd_orbits(
        _ccd_scene_raw(pointing={"ra": RA, "dec": DEC, "rotation": 25.0})))
    vertices = scene.satellites[0].track.vertices
    assert len(vertices) >= 5
    wcs = pointing_wcs(scene.pointing, scene.detector.shape, LSST.pixel_scale_arcsec)
    dense = compute_pass(Orbit.read_tle(TLE), Exposure("2026-06-15T23:29:58", 4.0),
                         Pointing(RA, DEC, 25.0), step_s=TRACK_STEP_S)
    for v in vertices:
        sky = wcs.pixel_to_world(v["x"], v["y"])
        i = int(np.argmin(np.abs(dense.alt_deg - (90 - v["zenith"]))))  # the vertex's sample
        frame = AltAz(obstime=dense.utc[i], location=RUBIN.location)
        truth = SkyCoord(az=dense.apparent_az_deg[i] * u.deg,
                         alt=dense.apparent_alt_deg[i] * u.deg, frame=frame).transform_to(ICRS())
        assert sky.separation(truth).to_value(u.arcsec) < 0.1
    xs = np.array([v["x"] for v in vertices])
    assert xs.min() < 0 < 1999 < xs.max()  # across the whole CCD


def test_simulate_an_orbit_scene(tmp_path, capsys):
    import yaml
    from astropy.io import fits

    path = tmp_path / "ccd_pass.yaml"
    path.write_text(yaml.safe_dump(_ccd_scene_raw(start="2026-06-15T23:29:59.5", exptime=1.0)))
    out = tmp_path / "ccd.fits"
    assert main(["simulate", str(path), "-o", str(out), "detector.nx=256",
                 "detector.ny=256"]) == 0, capsys.readouterr().err
    with fits.open(out) as hdul:
        image = hdul[1].data
        assert image.max() > 100  # the streak's charge, no sky or noise
        from inject.maskplanes import FLAG_OFF_IMAGE
        truth = hdul["TRUTH"].data[0]
        assert not truth["flags"] & FLAG_OFF_IMAGE
    # TRUTH describes the streak drawn, at the middle of the part the image receives (not
    # the scene's zenith and phi): the vertices' values interpolated at that point.
    from inject.config import parse_scene
    from inject.schema import apply_overrides
    vertices = parse_scene(resolve_ccd_orbits(apply_overrides(
        yaml.safe_load(path.read_text()), ["detector.nx=256", "detector.ny=256"]))
    ).satellites[0].track.vertices
    xs, ys = np.array([v["x"] for v in vertices]), np.array([v["y"] for v in vertices])
    steps = np.hypot(np.diff(xs), np.diff(ys))
    along = np.concatenate([[0.0], np.cumsum(steps)])
    mid_x = 0.5 * (truth["x0"] + truth["x1"])
    mid_y = 0.5 * (truth["y0"] + truth["y1"])
    s = along[int(np.argmin(np.hypot(xs - mid_x, ys - mid_y)))]  # vertices 0.1 s apart
    for key, column in (("zenith", "zenith_deg"), ("phi", "phi_deg"), ("height", "height_km")):
        expected = np.interp(s, along, [v[key] for v in vertices])
        spacing = np.abs(np.diff([v[key] for v in vertices])).max()
        assert truth[column] == pytest.approx(expected, abs=spacing + 1e-9)
    assert truth["length_px"] == pytest.approx(np.hypot(truth["x1"] - truth["x0"],
                                                        truth["y1"] - truth["y0"]), rel=1e-3)


def test_ccd_scene_orbit_that_misses_says_why():
    from inject import OrbitWarning, SceneError, parse_scene
    raw = _ccd_scene_raw(pointing={"ra": (RA + 40) % 360, "dec": DEC})
    with pytest.warns(OrbitWarning, match="no streak: misses the field"):
        scene = parse_scene(resolve_ccd_orbits(raw))
    assert all(v["x"] < -1e5 for v in scene.satellites[0].track.vertices)  # off the image
    with pytest.raises(SceneError, match="pointing: required with an orbit"):
        resolve_ccd_orbits({k: v for k, v in raw.items() if k != "pointing"})


def _terminator_pass(aim_s=5.0):
    """The example shell aimed east near the terminator: in the field, through the penumbra
    into the umbra (as in the test above), the pointing on where it appears ``aim_s`` after
    the start. Returns the orbit, exposure and pointing."""
    from astropy.time import Time

    from inject.orbits.passes import aimed_orbit
    t_aim = Time("2026-06-15T23:27:00")
    orbit = aimed_orbit(t_aim, 60.0, 90.0)
    exposure = Exposure(t_aim + 8 * u.s, 10.0)
    first = compute_pass(orbit, exposure, Pointing(0.0, 0.0), t_s=[aim_s])
    frame = AltAz(obstime=first.utc[0], location=RUBIN.location)
    c = SkyCoord(az=first.apparent_az_deg[0] * u.deg, alt=first.apparent_alt_deg[0] * u.deg,
                 frame=frame).transform_to(ICRS())
    return orbit, exposure, Pointing(float(c.ra.deg), float(c.dec.deg))


def _pass_args(orbit, exposure, pointing, tmp_path):
    tle = tmp_path / "sat.tle"
    tle.write_text("\n".join(orbit.tle_lines()) + "\n")
    return ("--tle", tle, "--time", exposure.start.isot, "--exptime", exposure.exptime_s,
            "--ra", pointing.ra_deg, "--dec", pointing.dec_deg)


def test_pass_lists_only_the_sunlit_ccds_as_focalplane_renders(capsys, tmp_path):
    """`inject pass`'s detectors are the CCDs the focal-plane scene's (sunlit) track crosses;
    those crossed only in the umbra are listed apart, with no streak."""
    from inject import make_plan, parse_focal_scene
    orbit, exposure, pointing = _terminator_pass(aim_s=8.0)  # umbra entry in the field
    report, _ = run_json(capsys, *_pass_args(orbit, exposure, pointing, tmp_path))
    raw = _scene(exptime=exposure.exptime_s, time=exposure.start.isot,
                 pointing={"ra": pointing.ra_deg, "dec": pointing.dec_deg})
    raw["satellites"] = [{**raw["satellites"][0], "orbit": {"tle": list(orbit.tle_lines())}}]
    raw["satellites"][0] = {k: raw["satellites"][0][k] for k in ("orbit",)} | {
        "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}
    rendered = {c.name for c in make_plan(parse_focal_scene(raw)).streak_ccds()}
    assert rendered and set(report["detectors"]) == rendered
    assert report["detectors_in_shadow"]  # the umbra part crosses CCDs too
    assert not rendered & set(report["detectors_in_shadow"])
    assert report["in_field"]


def test_pass_in_shadow_crosses_ccds_but_lists_none(capsys, tmp_path):
    from astropy.time import Time

    from inject.orbits.passes import aimed_orbit
    t = Time("2026-06-15T23:30:00")
    orbit = aimed_orbit(t, 60.0, 90.0)  # east at this time: in Earth's shadow
    frame = AltAz(obstime=t, location=RUBIN.location)
    c = SkyCoord(az=90 * u.deg, alt=60 * u.deg, frame=frame).transform_to(ICRS())
    report, _ = run_json(capsys, *_pass_args(orbit, Exposure(t - 2 * u.s, 4.0),
                                             Pointing(float(c.ra.deg), float(c.dec.deg)),
                                             tmp_path))
    assert report["detectors"] == [] and report["detectors_in_shadow"]
    assert report["in_field"] and "shadow" in report["message"]


def test_every_sunlit_part_is_rendered(monkeypatch):
    """A pass that leaves Earth's shadow and re-enters it in one exposure (made here by
    darkening the middle of the example pass) renders both sunlit parts, with the gap
    between them dark: no CCD streak covers the shadowed stretch."""
    from inject import parse_focal_scene
    from inject.exposure.plan import ccd_streaks, margins_px
    from inject.orbits import tracks as focalscene
    real = focalscene.orbit_pass

    def darkened(*args, **kwargs):
        dense = real(*args, **kwargs)
        dark = (dense.t_s > 1.5) & (dense.t_s < 2.5)
        dense.sun_fraction = np.where(dark, 0.0, dense.sun_fraction)
        return dense

    monkeypatch.setattr(focalscene, "orbit_pass", darkened)
    fscene = parse_focal_scene(_scene(exptime=4, time="2026-06-15T23:29:58"))
    track = fscene.tracks[0]
    parts = track.parts()
    assert len(parts) == 2 and "2 sunlit parts" in track.message
    dense = darkened("x", _scene()["satellites"][0]["orbit"], time="2026-06-15T23:29:58",
                     exptime=4.0, pointing=fscene.pointing)
    x, y = dense.focal_mm()
    t_of = [dense.t_s[[int(np.nanargmin(np.hypot(x - a, y - b))) for a, b in zip(p.xs, p.ys)]]
            for p in parts]
    assert t_of[0].max() <= 1.5 and t_of[1].min() >= 2.5  # each part on its own side
    margins = margins_px(fscene)
    pieces = [(ccd, s) for ccd in fscene.ccds for s in ccd_streaks(fscene, ccd, margins)]
    assert pieces
    # No rendered piece bridges the gap: every segment of every piece stays > 0.5 mm from
    # the shadowed samples (the satellite moves ~5 mm per 0.1 s).
    gap = (dense.t_s > 1.6) & (dense.t_s < 2.4)
    gx, gy = x[gap], y[gap]
    for ccd, s in pieces:
        xm, ym = ccd.pixel_to_focal(np.array([v["x"] for v in s.track.vertices]),
                                    np.array([v["y"] for v in s.track.vertices]))
        for x0, y0, x1, y1 in zip(xm[:-1], ym[:-1], xm[1:], ym[1:]):
            dx, dy = x1 - x0, y1 - y0
            t = np.clip(((gx - x0) * dx + (gy - y0) * dy) / (dx * dx + dy * dy), 0, 1)
            assert np.hypot(x0 + t * dx - gx, y0 + t * dy - gy).min() > 0.5


def test_pass_and_focalplane_plan_agree_on_the_ccds(cli, tmp_path):
    """The probe's case: the example pass at rotation 45, where the pass listed 15 CCDs and
    the focal-plane plan rendered 19. Both now come from the plan (for the default
    satellite, whose model the scene below shares)."""
    tle = tmp_path / "sat.tle"
    scene = yaml.safe_load((ROOT / "sample_fields" / "pass_example.yaml").read_text())
    tle.write_text("\n".join(scene["satellites"][0]["orbit"]["tle"]) + "\n")
    status, out, err = cli("pass", "--tle", tle, "--time", "2026-06-15T23:29:45",
                           "--exptime", "30", "--ra", "151.95", "--dec", "-25.73",
                           "--rotation", "45", "--json")
    assert status == 0, err
    listed = json.loads(out)["detectors"]
    status, out, err = cli("focalplane", ROOT / "sample_fields" / "pass_example.yaml", "--plan",
                           "--json", "pointing.rotation=45", "seeing=0.67", "zenith=70",
                           "stars=true")
    assert status == 0, err
    planned = [d["name"] for d in json.loads(out)["detectors"]]
    assert listed == planned and len(planned) > 15
