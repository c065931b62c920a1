"""An orbit's streak model is the pass's: TRUTH's angular speed, range, t_eff and charge per
pixel of a real pass (issue 13), in a CCD scene with a pointing and on a focal-plane CCD."""
from pathlib import Path

import numpy as np
import pytest

from inject import (
    Exposure,
    Geometry,
    Orbit,
    Pointing,
    compute_pass,
    load_scene_file,
    parse_scene,
    resolve_ccd_orbits,
)
from inject.instrument import ARCSEC_PER_RAD
from inject.orbits.passes import TRACK_STEP_S
from inject.photometry import band

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "sample_fields" / "pass_example.yaml"
TLE = ROOT / "sample_fields" / "example_starlink_like.tle"
RA, DEC = 151.95, -25.73
START, EXPTIME = "2026-06-15T23:29:59.5", 1.0


@pytest.fixture(scope="module")
def dense():
    """The pass, independently of any scene: every 0.1 s, as the tracks are sampled."""
    return compute_pass(Orbit.read_tle(TLE), Exposure(START, EXPTIME), Pointing(RA, DEC, 0.0),
                        step_s=TRACK_STEP_S)


def _raw(**changes):
    raw = {**load_scene_file(str(SCENE)), "exptime": EXPTIME, "time": START,
           "stars": False, "noise": False, "sky": False}
    return {**raw, **changes}


def _check_row(row, omega, range_km, pixel_scale):
    """The row's speed and range are the pass's to 0.1%, its t_eff the pixel over that speed,
    its charge per pixel the count rate at its magnitude times that t_eff."""
    assert row["angular_speed_rad_s"] == pytest.approx(omega, rel=1e-3)
    assert row["range_km"] == pytest.approx(range_km, rel=1e-3)
    t_eff = pixel_scale / ARCSEC_PER_RAD / omega
    assert row["t_eff_s"] == pytest.approx(t_eff, rel=1e-3)
    rate = 10 ** (0.4 * (band("g").zeropoint - row["apparent_mag"]))
    assert row["flux_per_px_e"] == pytest.approx(rate * t_eff, rel=1e-3)
    # The spherical-Earth model at the row's (height, zenith, phi) was 3-4% too fast: the
    # check above tells the two apart.
    paper = Geometry.from_orbit(row["height_km"], row["zenith_deg"], row["phi_deg"])
    assert abs(paper.angular_speed_rad_s / omega - 1) > 0.02


def test_ccd_scene_truth_is_the_pass(dense):
    from inject import render_streaks
    raw = _raw(detector={"type": "itl", "nx": 256, "ny": 256},
               pointing={"ra": RA, "dec": DEC, "rotation": 0.0})
    raw.pop("zenith")
    scene = parse_scene(resolve_ccd_orbits(raw))
    _, truth = render_streaks(scene)
    row = truth[0]
    # The row describes the middle of the part the image receives: the pass's values at the
    # altitude the row reports (the altitude changes monotonically over this second).
    order = np.argsort(dense.alt_deg)
    alt = 90 - row["zenith_deg"]
    assert dense.alt_deg.min() < alt < dense.alt_deg.max()
    omega, range_km = (np.interp(alt, dense.alt_deg[order], v[order])
                       for v in (dense.angular_speed_rad_s, dense.range_km))
    _check_row(row, omega, range_km, 0.2)


def test_focal_plane_ccd_truth_is_the_pass(dense):
    """R22_S12's corner (a 400 x 400 cut-out) is crossed in this second; the TRUTH row
    describes where the clipped track enters the CCD's reach: the pass there, interpolated
    between its 0.1 s samples in focal-plane mm."""
    from inject import make_plan, parse_focal_scene, simulate_ccd
    from inject.camera import layout as fp
    fscene = parse_focal_scene(_raw(cutout={"nx": 400, "ny": 400}))
    ccd = fp.BY_NAME["R22_S12"]
    _, result, streaks, _ = simulate_ccd(fscene, ccd, make_plan(fscene).streaks(ccd))
    assert len(result.truth) == 1 and result.truth[0]["charge_in_image_e"] > 0
    row = result.truth[0]
    x_mm, y_mm = ccd.pixel_to_focal(row["x0"], row["y0"])
    xd, yd = dense.focal_mm()
    d = np.hypot(xd - x_mm, yd - y_mm)
    j = int(np.nanargmin(d))
    k = j + 1 if (j + 1 < len(d) and (j == 0 or d[j + 1] < d[j - 1])) else j - 1
    a, b = sorted((j, k))
    f = np.hypot(x_mm - xd[a], y_mm - yd[a]) / np.hypot(xd[b] - xd[a], yd[b] - yd[a])
    omega = dense.angular_speed_rad_s[a] + f * np.diff(dense.angular_speed_rad_s[[a, b]])[0]
    rng = dense.range_km[a] + f * np.diff(dense.range_km[[a, b]])[0]
    _check_row(row, omega, rng, streaks[0].pixel_scale)


def test_focal_charge_check_uses_the_pass():
    """The focal-plane scene's charge check (refusing > 1e15 e- per pixel) bounds the pass's
    own vertices (range, speed, zenith), not a 550 km placeholder: its figure is the largest
    charge per pixel of track over the pass's samples on the track, from independent models."""
    import re
    import warnings

    from inject import SceneError, Seeing, StreakModel, parse_focal_scene
    raw = _raw()
    track = parse_focal_scene(raw).tracks[0]
    p = compute_pass(Orbit.read_tle(TLE), Exposure(START, EXPTIME), Pointing(RA, DEC, 0.0),
                     step_s=TRACK_STEP_S)
    x, y = p.focal_mm()
    idx = [int(np.nanargmin(np.hypot(x - a, y - b))) for a, b in zip(track.xs, track.ys)]
    mag = -21.0
    worst = max(StreakModel(float(p.height_km[i]), float(90 - p.alt_deg[i]),
                            float(p.phi_deg[i]), mag=mag, seeing=Seeing(raw["seeing"]),
                            range_km=float(p.range_km[i]),
                            angular_speed_rad_s=float(p.angular_speed_rad_s[i])).flux_per_px
                for i in idx)
    raw["satellites"] = [{**raw["satellites"][0], "mag": mag}]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # mag -21 is warned about as implausible
        with pytest.raises(SceneError, match=r"expected charge per pixel from satellites\[0\]"
                           ) as err:
            parse_focal_scene(raw)
    figure = float(re.search(r"satellites\[0\]=([0-9.e+]+)", str(err.value)).group(1))
    assert figure == pytest.approx(worst, rel=5e-3)  # printed to 3 significant figures
    placeholder = StreakModel(550.0, raw["zenith"], 90.0, mag=mag).flux_per_px
    assert abs(placeholder / worst - 1) > 0.02  # the old check's figure is told apart


def test_scene_time_reaches_the_headers(tmp_path):
    """DATE-OBS/MJD-OBS (start), DATE-AVG/MJD-AVG (middle), DATE-END/MJD-END in TAI with
    TIMESYS = 'TAI', as LSSTCam and afw write them: 37 s after the UTC time of the scene
    (TAI - UTC since 2017), in a CCD scene and on a focal-plane CCD; none without a time."""
    from datetime import datetime, timedelta

    from astropy.io import fits

    from inject.cli.main import main

    start_utc = datetime.fromisoformat(START)

    def check(header, exptime):
        assert header["TIMESYS"] == "TAI"
        for key, dt in (("OBS", 0.0), ("AVG", exptime / 2), ("END", exptime)):
            tai = start_utc + timedelta(seconds=37 + dt)
            assert datetime.fromisoformat(header[f"DATE-{key}"]) == tai
            # MJD 40587 is 1970-01-01
            mjd = 40587 + (tai - datetime(1970, 1, 1)).total_seconds() / 86400
            assert header[f"MJD-{key}"] == pytest.approx(mjd, abs=1e-8)  # 1 ms

    import yaml

    raw = _raw(detector={"type": "itl", "nx": 64, "ny": 64}, pointing={"ra": RA, "dec": DEC})
    raw.pop("zenith")
    path = tmp_path / "ccd.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["simulate", str(path), "-o", str(tmp_path / "ccd.fits")]) == 0
    check(fits.getheader(tmp_path / "ccd.fits", 0), EXPTIME)
    raw = {k: v for k, v in raw.items() if k not in ("time", "satellites")}
    path.write_text(yaml.safe_dump(raw))
    assert main(["simulate", str(path), "-o", str(tmp_path / "none.fits")]) == 0
    assert "DATE-OBS" not in fits.getheader(tmp_path / "none.fits", 0)

    from inject import make_plan, parse_focal_scene
    from inject.camera import layout as fp
    from inject.exposure.runner import Task, render_ccd
    fscene = parse_focal_scene(_raw(cutout={"nx": 64, "ny": 64}))
    ccd = fp.ccd("R22_S12")
    row = render_ccd(Task(fscene, ccd.name, str(tmp_path), tuple(make_plan(fscene).streaks(ccd))))
    check(fits.getheader(tmp_path / row["file"], 0), EXPTIME)


@pytest.mark.parametrize("case", ["pass", "terminator"])
def test_sampled_margin_bounds_every_vertex(case):
    """The footprint margin from a few vertices (focalscene._sampled, + REACH_ALLOWANCE) is
    at least the largest reach over every vertex, and not much more: for the example pass
    and a pass fading in the penumbra (its brightness, so its tolerance, changes)."""
    from inject import parse_focal_scene
    from inject.exposure.plan import REACH_ALLOWANCE, margins_px
    if case == "pass":
        raw = _raw(exptime=3.0, time="2026-06-15T23:29:58.5", noise=True, sky=True)
    else:
        from test_pass_cli import _terminator_pass

        orbit, exposure, pointing = _terminator_pass(aim_s=8.0)
        raw = _raw(exptime=exposure.exptime_s, time=exposure.start.isot, noise=True, sky=True,
                   pointing={"ra": pointing.ra_deg, "dec": pointing.dec_deg})
        raw["satellites"] = [{**raw["satellites"][0],
                              "orbit": {"tle": list(orbit.tle_lines())}}]
    fscene = parse_focal_scene(raw)
    n = len(fscene.tracks[0].values)
    assert n > 7  # more vertices than _sampled picks at most
    (every,) = margins_px(fscene, exhaustive=True)
    (sampled,) = margins_px(fscene)
    assert every <= sampled <= (every - 2.0) * (1 + REACH_ALLOWANCE) + 2.0 + 1e-9
