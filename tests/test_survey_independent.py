"""``inject survey``'s numbers against ones computed here, without the plan's code.

Two satellites are aimed (inject.orbits.passes.aimed_orbit, the inputs' maker) at one point
of the sky at one instant, one on its northbound pass and one on its southbound: their
tracks cross at right angles about. Two visits are planned with them: a 30 s visit centred on
that point (two streaks crossing on R22_S11) and a 0.4 s visit with the point 1.41 deg south
of its boresight, in raft R02 (ITL CCDs only). Checked against skyfield's pass of the same TLEs
(the crossing's middle and its range), SMTN-002's sky and the sensors' read noise typed here
(the mask on ITL CCDs), the area two crossing masks share (w1 w2 / sin angle), the Walker
pattern by hand, local mean solar time by hand, a run on two workers, and the OUTDIR claim.
"""
import csv
import json
import math
import os

import numpy as np
import pytest

from inject.cli.main import main

#: The instant both satellites pass the aimed point (UTC), and the point (deg).
T_CROSS = "2026-06-15T23:12:15"
ALT_DEG, AZ_DEG = 70.0, 270.0
#: Rubin's site (deg, deg, m) and longitude, deg east.
SITE = (-30.2446, -70.7494, 2647.0)
LON_DEG = -70.7494
MODEL = "shape: {type: box, length: 7.25, width: 2.65}\nmag: 5.0\nref_range: 550\n"
COLUMNS = ("observationId", "observationStartMJD", "fieldRA", "fieldDec", "rotSkyPos", "band",
           "visitExposureTime", "numExposures", "seeingFwhmEff")
#: SMTN-002 g band: zero point (AB mag for 1 e-/s), extinction (mag/airmass), dark sky at
#: zenith (mag/arcsec^2); the sensors' median read noise, e- (obs_lsst's).
G_ZP, G_K, G_SKY = 28.51, 0.21, 22.25
READ_NOISE = {"e2v": 5.41, "itl": 6.4}
#: LSSTCam's ITL rafts (obs_lsst): every other science raft is e2v.
ITL_RAFTS = {"R01", "R02", "R03", "R10", "R20", "R41", "R42", "R43"}


def write_csv(path, rows):
    with open(path, "w", newline="") as stream:
        writer = csv.DictWriter(stream, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return str(path)


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def _row(vid, start_utc, coord, exptime=30.0, rotation=0.0, band="g", snaps=1):
    """A visit's row: ``start_utc`` an astropy Time, ``coord`` the boresight (ICRS)."""
    return {"observationId": vid, "observationStartMJD": repr(float(start_utc.tai.mjd)),
            "fieldRA": coord.ra.deg, "fieldDec": coord.dec.deg, "rotSkyPos": rotation,
            "band": band, "visitExposureTime": exptime, "numExposures": snaps,
            "seeingFwhmEff": 0.8}


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    """The two aimed satellites, the two visits, ``inject survey`` run on them (every call
    of the plan's mask rule recorded: the model and the noise it was given)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.orbits.passes import RUBIN, aimed_orbit
    from inject.survey import plan

    folder = tmp_path_factory.mktemp("crossing")
    t = Time(T_CROSS, scale="utc")
    sats = [aimed_orbit(t, ALT_DEG, AZ_DEG, ascending=up, name=name, satnum=k + 1)
            for k, (name, up) in enumerate((("NORTHBOUND", True), ("SOUTHBOUND", False)))]
    lines = [(o.name, *o.tle_lines()) for o in sats]
    (folder / "two.tle").write_text("".join(f"{a}\n{b}\n{c}\n" for a, b, c in lines))
    const = folder / "const.yaml"
    const.write_text(MODEL + "tle: two.tle\n")
    point = SkyCoord(AltAz(alt=ALT_DEG * u.deg, az=AZ_DEG * u.deg, obstime=t,
                           location=RUBIN.location)).icrs
    # rotSkyPos 0: the focal plane's +y is north, so a boresight 1.41 deg north of the point
    # puts it at (0, -254) mm, the centre of raft R02.
    north = point.directional_offset_by(0.0 * u.deg, 1.41 * u.deg)
    rows = [_row(1, t - 15.0 * u.s, point), _row(2, t - 0.2 * u.s, north, exptime=0.4)]
    visits = write_csv(folder / "night.csv", rows)
    calls = []
    real = plan.mask_width_px

    def recorded(model, sigma, *args):
        width = real(model, sigma, *args)
        calls.append((model, sigma, width))
        return width

    out = folder / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plan, "mask_width_px", recorded)
        assert main(["survey", visits, "-o", str(out), "--constellation", str(const),
                     "--no-plots"]) == 0
    streaks = read_csv(out / "streaks.csv")
    return {"lines": lines, "rows": rows, "point": point, "t": t, "calls": calls,
            "streaks": {(int(r["observationId"]), r["satellite"]): r for r in streaks},
            "visits": {int(r["observationId"]): r for r in read_csv(out / "visits.csv")},
            "folder": folder, "const": str(const), "csv": visits}


def _skyfield():
    from skyfield.api import load, wgs84

    ts = load.timescale(builtin=True)
    return ts, wgs84.latlon(SITE[0], SITE[1], elevation_m=SITE[2])


# --- the streak's model at the middle of its crossing (mutation: at its start) -------------

def test_the_streak_is_modelled_at_the_middle_of_its_crossing(crossing):
    """Each satellite passes the boresight of visit 1 (the centre of the point-symmetric field)
    at the instant skyfield puts it closest: the middle of its crossing. The row's t_mid_s is
    that instant (its model taken at a vertex within 1 s of it: a run's vertices are at most
    1 s apart; the crossing's first vertex on a CCD is about 2.4 s earlier), and its range_km
    skyfield's range at t_mid_s."""
    from skyfield.api import EarthSatellite

    ts, site = _skyfield()
    point = crossing["point"]
    aim = point.cartesian.xyz.value  # the boresight (ICRS unit vector)
    t_s = np.arange(0.0, 30.0001, 0.02)
    times = ts.utc(2026, 6, 15, 23, 12, t_s)  # visit 1: 23:12:00 to 23:12:30 UTC
    for name, line1, line2 in crossing["lines"]:
        row = crossing["streaks"][1, name]
        topo = (EarthSatellite(line1, line2, name, ts) - site).at(times)
        xyz = topo.position.km
        # The satellite's direction without the site's aberration (the boresight's ICRS
        # direction has none either: 20" apart at most, 0.01 s of its motion).
        gap = np.degrees(np.arccos(np.clip(aim @ xyz / np.linalg.norm(xyz, axis=0), -1, 1)))
        k = int(np.argmin(gap))
        assert gap[k] < 0.05  # aimed: it passes the boresight
        t_close = t_s[k]
        t_mid = float(row["t_mid_s"])
        assert abs(t_mid - t_close) <= 1.0, (name, t_mid, t_close)
        ranges = topo.distance().km
        at_mid = float(np.interp(t_mid, t_s, ranges))
        assert float(row["range_km"]) == pytest.approx(at_mid, abs=0.02)  # 4 m here
        # And against the range at the middle itself, within what 1 s can move it.
        drift = abs(float(np.interp(t_close + 1.0, t_s, ranges)) - ranges[k])
        assert abs(float(row["range_km"]) - ranges[k]) <= drift + 0.02


# --- the mask on ITL CCDs: their read noise (mutation: e2v's) -----------------------------

def test_a_streak_on_itl_ccds_only_has_the_itl_noises_mask(crossing):
    """Visit 2 (0.4 s, g, one snap) sees both satellites inside raft R02 only: their masks
    are the rule's width against sqrt(sky + 6.4^2), SMTN-002's dark sky over 0.4 s on a 0.2"
    pixel times the airmass, ITL's read noise typed here (e2v's 5.41 would give less)."""
    from inject.survey.plan import mask_width_px

    visit = crossing["visits"][2]
    alt = float(visit["alt_deg"])
    sky = 10 ** (0.4 * (G_ZP + G_K - G_SKY)) * 0.4 * 0.2 ** 2 / math.sin(math.radians(alt))
    assert float(visit["sky_e_per_px"]) == pytest.approx(sky, rel=1e-9)
    itl = math.sqrt(sky + READ_NOISE["itl"] ** 2)
    e2v = math.sqrt(sky + READ_NOISE["e2v"] ** 2)
    rows = [r for (vid, _), r in crossing["streaks"].items() if vid == 2]
    assert len(rows) == 2
    models = [m for m, sigma, _ in crossing["calls"] if sigma == pytest.approx(itl, rel=1e-12)]
    assert len(models) >= 2  # the plan asked the rule for ITL's noise, once per streak
    for row in rows:
        ccds = row["ccds"].split()
        assert ccds and all(c[:3] in ITL_RAFTS for c in ccds), ccds
        width = float(row["mask_width_px"])
        expected = [mask_width_px(m, itl) for m in models]
        assert any(width == pytest.approx(w, rel=1e-12) for w in expected), (width, expected)
        assert all(abs(width - mask_width_px(m, e2v)) > 0.05 for m in models)


# --- two crossing streaks share their overlap (mutation: counted twice) --------------------

def test_two_crossing_streaks_lose_their_overlap_once(crossing):
    """Visit 1's two streaks cross near the boresight at the angle between their motions on
    the sky (skyfield): the visit loses the sum of the streaks' pixels less the rhombus both
    masks cover, w1 w2 / sin(angle) (the masks straight there)."""
    from skyfield.api import EarthSatellite

    ts, site = _skyfield()
    times = ts.utc(2026, 6, 15, 23, 12, 15.0 + np.array([-0.5, 0.5]))
    motions = []
    for name, line1, line2 in crossing["lines"]:
        ra, dec, _ = (EarthSatellite(line1, line2, name, ts) - site).at(times).radec()
        d_ra = (ra.radians[1] - ra.radians[0]) * math.cos(dec.radians[0])
        motions.append(np.array([d_ra, dec.radians[1] - dec.radians[0]]))
    a, b = motions
    sin_angle = abs(a[0] * b[1] - a[1] * b[0]) / (np.linalg.norm(a) * np.linalg.norm(b))
    assert sin_angle > 0.5  # they cross, not graze
    rows = [crossing["streaks"][1, name] for name, _, _ in crossing["lines"]]
    assert all("R22_S11" in r["ccds"].split() for r in rows)
    w1, w2 = (float(r["mask_width_px"]) for r in rows)
    overlap = w1 * w2 / sin_angle
    shared = sum(int(r["pixels_lost"]) for r in rows) - int(crossing["visits"][1]["pixels_lost"])
    assert shared == pytest.approx(overlap, rel=0.02), (shared, overlap)  # 0.1% here


# --- the seeing: FWHMgeom from seeingFwhmEff (mutation: FWHMeff) -------------------------

def test_the_visits_seeing_is_fwhmgeom_of_the_databases_fwhmeff(crossing):
    """seeingFwhmEff 0.8" is FWHMgeom = 0.822 x 0.8 + 0.052 = 0.7096" (SMTN-002)."""
    for visit in crossing["visits"].values():
        assert float(visit["seeing_arcsec"]) == pytest.approx(0.822 * 0.8 + 0.052, rel=1e-12)


# --- Walker shells by hand ------------------------------------------------------------------

def test_a_shells_orbits_follow_the_walker_pattern_by_hand():
    """53: 12/3/1 with raan0 10 deg: plane k at RAAN 10 + 120 k, satellite j of it at
    argument of latitude 360 j / 4 + 360 x 1 x k / 12 (the element sets' own values)."""
    from inject.survey.constellation import parse_constellation

    shell = {"height": 550, "inclination": 53, "planes": 3, "per_plane": 4, "phasing": 1,
             "raan0": 10.0, "name": "w"}
    c = parse_constellation({"shape": {"type": "box", "length": 7.25, "width": 2.65},
                             "mag": 5.0, "ref_range": 550, "epoch": "2026-06-15T23:00:00",
                             "shells": [shell]})
    got = sorted((round(math.degrees(o.satrec.nodeo) % 360.0, 9),
                  round(math.degrees(o.satrec.mo) % 360.0, 9),
                  round(math.degrees(o.satrec.inclo), 9)) for o in c.orbits)
    by_hand = sorted((round((10.0 + 360.0 * k / 3) % 360.0, 9),
                      round((360.0 * j / 4 + 360.0 * 1 * k / 12) % 360.0, 9), 53.0)
                     for k in range(3) for j in range(4))
    assert got == by_hand


# --- the local hour (summary and plots) ------------------------------------------------------

#: A night's visits at these UTC times: local mean solar time = UTC + (-70.7494 / 15) h.
NIGHT_UTC = ["2026-06-15T22:50:00", "2026-06-15T23:40:00", "2026-06-16T00:30:00",
             "2026-06-16T01:20:00", "2026-06-16T02:10:00", "2026-06-16T03:00:00",
             "2026-06-16T03:50:00", "2026-06-16T04:40:00", "2026-06-16T05:30:00"]


def _local_hours():
    """The hours by hand: UTC hours (+24 after midnight UTC) plus lon/15, 24 added after
    local midnight."""
    out = []
    for text in NIGHT_UTC:
        day, clock = text.split("T")
        h, m, s = (float(x) for x in clock.split(":"))
        utc = h + m / 60 + s / 3600 + (24.0 if day.endswith("16") else 0.0)
        out.append(utc + LON_DEG / 15.0)
    return out


def test_the_plots_hour_axis_is_local_mean_solar_time(crossing, nine, monkeypatch, tmp_path):
    """The per-visit plots ``inject survey`` draws put each visit at its local mean solar
    time (the nine visits of NIGHT_UTC, by hand)."""
    from inject.survey import outputs

    figures = {}
    monkeypatch.setattr(outputs, "_save", lambda fig, path, overwrite: figures.__setitem__(
        os.path.basename(path), fig))
    assert main(["survey", nine, "-o", str(tmp_path / "out"), "--constellation",
                 crossing["const"], "--workers", "1"]) == 0
    for name in ("streaks_per_visit.png", "pixel_fraction.png"):
        (ax,) = figures[name].axes
        xs = np.concatenate([line.get_xdata() for line in ax.get_lines()])
        assert sorted(xs) == pytest.approx(sorted(_local_hours()), abs=1e-6)


# --- many visits on two workers --------------------------------------------------------------

@pytest.fixture(scope="module")
def nine(crossing):
    """Nine 30 s visits (more than a worker's chunk of 8), none near the satellites."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord
    from astropy.time import Time

    rows = [_row(100 + k, Time(t, scale="utc"), SkyCoord(15.0 * k * u.deg, -60.0 * u.deg))
            for k, t in enumerate(NIGHT_UTC)]
    return write_csv(crossing["folder"] / "nine.csv", rows)


def test_two_workers_plan_every_visit_once(crossing, nine, tmp_path):
    for workers in (1, 2):
        assert main(["survey", nine, "-o", str(tmp_path / str(workers)), "--constellation",
                     crossing["const"], "--no-plots", "--workers", str(workers)]) == 0
    one, two = (read_csv(tmp_path / w / "visits.csv") for w in ("1", "2"))
    assert [r["observationId"] for r in two] == [str(100 + k) for k in range(9)]
    assert two == one
    summary = json.loads((tmp_path / "2" / "summary.json").read_text())
    assert summary["visits"] == 9
    # The hours of the night by hand: summary.json's by_hour keys (local hours, mod 24):
    # 18 19 20 21 22 23 00.
    hours = sorted({int(h) for h in _local_hours()})
    assert list(summary["by_hour"]) == [f"{h % 24:02d}" for h in hours]


# --- the OUTDIR's claim: the visits' content is in its key -----------------------------------

def test_an_edited_visits_file_is_another_run(cli, crossing, nine, tmp_path):
    """Slice 0 of 2, then the same VISITS path holding other visits: slice 1 of 2 is another
    run's (its key has the file's SHA-256, not only its path), refused."""
    visits = tmp_path / "v.csv"
    visits.write_text(open(nine).read())
    out = tmp_path / "out"
    status, _, _ = cli("survey", visits, "-o", out, "--constellation", crossing["const"],
                       "--no-plots", "--job", 0, "--njobs", 2)
    assert status == 0
    rows = read_csv(nine)[:4]  # four visits, the last a day later: two nights, two slices
    rows[-1]["observationStartMJD"] = repr(float(rows[-1]["observationStartMJD"]) + 1.0)
    write_csv(visits, rows)
    status, _, err = cli("survey", visits, "-o", out, "--constellation", crossing["const"],
                         "--no-plots", "--job", 1, "--njobs", 2, strict=True)
    assert status == 2 and "another survey run" in err
