"""``inject survey --rule rubin_sim`` (:mod:`inject.survey.rubin_rule`): rubin_sim's
``check_pointings`` rule, against numbers computed here independently.

The references: closed forms (a chord of a circle, a strip of a disc, the line to the Sun
past a sphere) and skyfield (its own SGP4, TEME -> GCRS, site and altitude; its UT1 from the
IERS table astropy bundles, so that no file is downloaded, and its polar motion, which
rubin_sim's skyfield leaves out: the site 10 m off, 3" at 600 km), the satellites placed with
:func:`inject.orbits.passes.aimed_orbit` over Rubin on the sample night's evening twilight.
"""
import csv
import json
import math

import numpy as np
import pytest

from inject.orbits.passes import RUBIN, aimed_orbit
from inject.survey import rubin_rule
from inject.survey.visits import Visit

#: The sample night's first visit (evening twilight, the Sun ~-13 deg), MJD as opsim writes it.
MJD = 61206.9498183263
#: An hour later (the Sun at -20 deg): the shadow's edge at 550 km crosses the sky.
MJD_SHADOW = MJD + 0.03
#: skyfield's Earth radius, km (skyfield.constants.ERAD).
ERAD_KM = 6378.1366


@pytest.fixture(scope="module")
def sf(skyfield_timescale):
    """skyfield's timescale (:func:`conftest.skyfield_timescale`) and Rubin's site."""
    api = pytest.importorskip("skyfield.api")
    ts = skyfield_timescale
    site = api.wgs84.latlon(RUBIN.lat_deg, RUBIN.lon_deg, elevation_m=RUBIN.height_m)
    return {"ts": ts, "site": site, "api": api}


def skyfield_track(sf, orbit, mjd, t_s):
    """skyfield's geometric topocentric unit vectors (GCRS), altitudes (deg) and geocentric
    positions (km) of ``orbit`` at ``t_s`` seconds after ``mjd`` read as UT1."""
    line1, line2 = orbit.tle_lines()
    sat = sf["api"].EarthSatellite(line1, line2, orbit.name, sf["ts"])
    t = sf["ts"].ut1_jd(mjd + 2400000.5 + np.asarray(t_s) / 86400.0)
    topo = (sat - sf["site"]).at(t)
    d = topo.position.km.T
    return (d / np.linalg.norm(d, axis=1, keepdims=True), topo.altaz()[0].degrees,
            sat.at(t).position.km.T)


def radec(u):
    return (math.degrees(math.atan2(u[1], u[0])) % 360.0,
            math.degrees(math.asin(np.clip(u[2], -1, 1))))


def offset(u, v, angle_deg):
    """The direction ``angle_deg`` from ``u`` perpendicular to the motion ``v`` (unit)."""
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    a = math.radians(angle_deg)
    return math.cos(a) * u + math.sin(a) * n


def visit(ra, dec, mjd=MJD, visit_time=34.0, exptime=30.0, n_exp=2):
    return Visit(observation_id=1, mjd_tai=mjd, ra_deg=ra, dec_deg=dec, rotation_deg=0.0,
                 band="r", exptime_s=exptime, n_exposures=n_exp, visit_time_s=visit_time)


def rule_time(mjd, t_s=0.0):
    """The instant the rule reads ``mjd`` as (UT1), plus ``t_s``: astropy Time."""
    from astropy import units as u
    from astropy.time import Time

    return Time(mjd, format="mjd", scale="ut1") + t_s * u.s


def counted(v, orbit):
    return [h["index"] for h in rubin_rule.count_visit(v, [orbit], [0])] == [0]


def fine_track(x, y, n=100001):
    """The polyline's segments near the circle (within 3 deg) resampled at ``n`` points:
    steps of < 1e-4 deg, which a length counted over whole steps inside misses twice."""
    near = np.flatnonzero(np.hypot(x, y) < math.radians(3.0))
    lo, hi = max(near.min() - 1, 0), min(near.max() + 1, len(x) - 1)
    k = np.linspace(lo, hi, n)
    return np.interp(k, np.arange(len(x)), x), np.interp(k, np.arange(len(x)), y)


def in_polygon(x, y, r=math.radians(1.75), sides=64):
    """Inside shapely's 64-gon on the circle of ``r`` (a vertex at angle 0): on the inner
    side of every edge, whose outward normals are at (k + 1/2) 360 / 64 deg."""
    a = (np.arange(sides) + 0.5) * 2 * math.pi / sides
    return np.all(np.outer(x, np.cos(a)) + np.outer(y, np.sin(a))
                  <= r * math.cos(math.pi / sides), axis=1)


def sun_line_height(r, sun):
    """Closed form: height of the line from ``r`` to the Sun above skyfield's sphere where
    it passes the Earth (+inf on the day side)."""
    u = (sun - r) / np.linalg.norm(sun - r)
    s = -float(r @ u)
    return math.inf if s <= 0 else float(np.linalg.norm(r + s * u) - ERAD_KM)


def sun_gcrs(mjd_tai):
    from astropy import units as u
    from astropy.coordinates import get_sun
    from astropy.time import Time

    return get_sun(Time(mjd_tai, format="mjd", scale="tai")).cartesian.xyz.to_value(u.km)


# --- the pieces, closed forms --------------------------------------------------------------

@pytest.mark.parametrize("d_deg, inside", [(1.70, True), (1.749, True), (1.751, False),
                                           (1.80, False)])
def test_a_straight_track_counts_inside_the_circle_only(d_deg, inside):
    """A track passing ``d`` from the centre: its length in the circle is the chord
    2 sqrt(R^2 - d^2) (R = 1.75 deg of the plane), or nothing just outside (the circle of
    the band's pixels, :func:`~inject.survey.rubin_rule.length_in_circle`)."""
    r, d = math.radians(1.75), math.radians(d_deg)
    x = np.linspace(-0.05, 0.05, 17)
    length = rubin_rule.length_in_circle(x, np.full(17, d), r)
    chord = 2.0 * math.sqrt(max(r * r - d * d, 0.0))
    assert length == pytest.approx(chord, abs=1e-12)
    assert (length > 0) is inside


@pytest.mark.parametrize("d_deg", [1.745, 1.749])
def test_rubin_sims_circle_is_a_64_sided_polygon(d_deg):
    """A horizontal track at d near the top vertex (0, R) of shapely's 64-gon: it cuts the
    two edges to the vertices at 90 -+ 5.625 deg, a chord of 2 (R - d) cot(a) / ... by
    similar triangles: 2 (R - d) R cos(a) / (R - R sin(a)), a = 84.375 deg."""
    r, d = math.radians(1.75), math.radians(d_deg)
    a = math.radians(90.0 - 360.0 / 64)
    assert d > r * math.sin(a)  # the premise: above the vertices beside the top one
    x = np.linspace(-0.05, 0.05, 17)
    chord = 2.0 * (r - d) * r * math.cos(a) / (r - r * math.sin(a))
    assert rubin_rule.length_in_polygon(x, np.full(17, d), r) == pytest.approx(chord,
                                                                               rel=1e-9)
    # Through the centre at 45 deg: between the apothem's chord and the diameter.
    t = np.linspace(-0.05, 0.05, 17)
    length = rubin_rule.length_in_polygon(t, t, r)
    assert 2 * r * math.cos(math.pi / 64) <= length <= 2 * r * (1 + 1e-12)


@pytest.mark.parametrize("y_km, lit", [(ERAD_KM + 1.0, True), (ERAD_KM - 1.0, False),
                                       (0.0, False)])
def test_the_shadow_is_the_line_to_the_suns_centre_past_a_sphere(y_km, lit):
    """The Sun 1 AU along +x, the satellite 7,000 km behind the Earth and ``y`` off the axis:
    the line to the Sun's centre passes the centre at y (1 - 7000 / AU) (similar triangles),
    0.7 km above the sphere for y = R + 1 km, 1.3 km below it for R - 1 km."""
    au = 1.495978707e8
    sat, sun = np.array([-7000.0, y_km, 0.0]), np.array([au, 0.0, 0.0])
    miss = y_km * au / math.hypot(au + 7000.0, y_km)
    assert (miss > ERAD_KM) is lit
    assert bool(rubin_rule.sunlit(sat, sun)) is lit
    assert bool(rubin_rule.sunlit(np.array([7000.0, 0.0, 0.0]), sun))  # the day side


def test_the_span_is_visittime_else_the_exposure_and_readouts():
    assert rubin_rule.visit_span(visit(0, 0, visit_time=34.0)) == (34.0, "visitTime")
    assert rubin_rule.visit_span(visit(0, 0, visit_time=None)) == (32.0, "exposure+readouts")
    # rubin_sim's np.linspace(mjd, mjd + span, round(span / 2 s)): 17 samples over 34 s.
    ts = rubin_rule.sample_times(34.0)
    assert len(ts) == 17 and ts[0] == 0.0 and ts[-1] == 34.0


def test_the_band_on_a_track_through_the_circle_is_a_strip_of_the_disc():
    """A straight track across the whole circle at d from the centre: the pixels are the
    disc's strip |y - d| <= w/2, by the circular segments' areas, to a pixel per row."""
    disc = rubin_rule.Disc()
    px = disc.pixel_rad
    w, d = 300.0, 10000.0
    x = np.linspace(-1.2, 1.2, 3) * disc.r_px * px
    spans = rubin_rule.band_spans(x, np.full(3, d * px), w, disc)
    from inject.survey.plan import union_pixels

    r = disc.r_px

    def segment(h):  # area of the disc beyond the line at distance h from the centre
        return r * r * math.acos(h / r) - h * math.sqrt(r * r - h * h)

    strip = segment(d - w / 2) - segment(d + w / 2)
    rows = 2 * math.sqrt(r * r - d * d)
    assert abs(union_pixels(spans) - strip) < 2 * rows
    assert disc.area() == pytest.approx(math.pi * r * r, rel=1e-4)


# --- against skyfield ----------------------------------------------------------------------

def aim(alt, az, t, **kw):
    return aimed_orbit(t, alt, az, name="RULE", **kw)


@pytest.mark.parametrize("miss_deg, inside", [(1.70, True), (1.80, False)])
def test_a_track_crossing_the_circle_counts_and_one_just_outside_does_not(sf, miss_deg,
                                                                          inside):
    """A satellite at 60 deg at the rule's middle, the boresight placed ``miss`` from its
    skyfield track: counted inside 1.75 deg only, with skyfield's length in the circle."""
    ts = rubin_rule.sample_times(34.0)
    orbit = aim(60.0, 100.0, rule_time(MJD, 17.0))
    d, alt, r = skyfield_track(sf, orbit, MJD, ts)
    mid = len(ts) // 2
    motion = d[mid + 1] - d[mid - 1]
    ra, dec = radec(offset(d[mid], motion / np.linalg.norm(motion), miss_deg))
    # skyfield's track in the gnomonic plane about that boresight, finely resampled.
    fx, fy = fine_track(*rubin_rule.gnomonic(d, ra, dec))
    rad = math.degrees(np.hypot(fx, fy).min())
    assert (rad < 1.745) is inside and (rad > 1.755) is not inside  # the premise
    assert min(alt[0], alt[-1]) > 20.0
    assert min(sun_line_height(r[0], sun_gcrs(MJD)), 0.0) == 0.0  # sunlit at the start
    hits = rubin_rule.count_visit(visit(ra, dec), [orbit], [0])
    assert bool(hits) is inside
    if inside:
        # The chord's length moves 2 d / sqrt(R^2 - d^2) = 8.2 times the track's distance
        # from the centre, which the two codes' frames put within 0.4" (1.1e-4 deg).
        step = np.hypot(np.diff(fx), np.diff(fy))
        inside_poly = in_polygon(fx, fy)
        within = inside_poly[:-1] & inside_poly[1:]
        assert hits[0]["length_deg"] == pytest.approx(math.degrees(step[within].sum()),
                                                      abs=1e-3)


@pytest.mark.parametrize("aim_alt, counts", [(21.0, True), (19.0, False)])
def test_the_altitude_limit_is_20_deg_at_the_start_or_end(sf, aim_alt, counts):
    """A satellite at 19 or 21 deg at the start (skyfield), falling: counted at 21 only.
    The boresight is on its track at the visit's middle."""
    ts = rubin_rule.sample_times(4.0)  # 2 samples, 4 s apart: it moves < 1 deg
    for az in (250.0, 70.0, 160.0, 340.0):
        for ascending in (True, False):
            orbit = aim(aim_alt, az, rule_time(MJD), ascending=ascending)
            d, alt, _ = skyfield_track(sf, orbit, MJD, ts)
            if alt[-1] < alt[0]:
                break
        if alt[-1] < alt[0]:
            break
    assert alt[-1] < alt[0] and bool(alt[0] > 20.0) is counts and alt[-1] < 21.0  # premise
    assert bool(max(alt) > 20.0) is counts
    ra, dec = radec((d[0] + d[-1]) / np.linalg.norm(d[0] + d[-1]))
    assert counted(visit(ra, dec, visit_time=4.0), orbit) is counts


def _entering_shadow(sf, span):
    """A satellite sunlit at the rule's start and in the shadow at its end (the closed-form
    shadow on skyfield's positions, more than 10 km either side), and its track."""
    ts = rubin_rule.sample_times(span)
    sun = sun_gcrs(MJD_SHADOW)
    for az in range(0, 360, 15):
        for alt in (30.0, 45.0, 60.0, 75.0):
            for ascending in (True, False):
                orbit = aim(alt, float(az), rule_time(MJD_SHADOW, span / 2),
                            ascending=ascending)
                d, alts, r = skyfield_track(sf, orbit, MJD_SHADOW, ts)
                h = [sun_line_height(p, sun) for p in r]
                if h[0] > 10.0 and h[-1] < -10.0 and min(alts) > 25.0:
                    return orbit, d
    pytest.fail("no satellite entering the shadow found")


def test_sunlit_at_the_start_only_counts_and_dark_at_both_ends_does_not(sf):
    """Entering the shadow during the visit, sunlit at the start only: counted (rubin_sim
    counts it whole). The same track 34 s later, dark at both ends: not counted, though it
    crosses the circle."""
    orbit, d = _entering_shadow(sf, 34.0)
    mid = len(d) // 2
    ra, dec = radec(d[mid])
    assert counted(visit(ra, dec, mjd=MJD_SHADOW), orbit)
    later = MJD_SHADOW + 34.0 / 86400.0
    d2, _, r2 = skyfield_track(sf, orbit, later, rubin_rule.sample_times(34.0))
    sun = sun_gcrs(later)
    assert sun_line_height(r2[0], sun) < -10.0 and sun_line_height(r2[-1], sun) < -10.0
    ra2, dec2 = radec(d2[len(d2) // 2])
    assert not counted(visit(ra2, dec2, mjd=later), orbit)


def test_the_start_read_as_ut1_places_the_satellite_tai_minus_ut1_later(sf):
    """observationStartMJD read as UT1: the rule's first sample is where skyfield puts the
    satellite at UT1 = MJD, (TAI - UT1) = 36.99 s after the TAI instant: it has moved by its
    angular speed (skyfield, 0.5 s steps) times those seconds, 21 deg at 70 deg altitude."""
    from astropy.time import Time

    orbit = aim(70.0, 30.0, Time(MJD, format="mjd", scale="tai"))
    got = rubin_rule.tracks(visit(0.0, 0.0, visit_time=2.0), [orbit])
    d_ut1, _, _ = skyfield_track(sf, orbit, MJD, [0.0])
    dt = (Time(MJD, format="mjd", scale="ut1").tai.mjd - MJD) * 86400.0
    assert dt == pytest.approx(36.99, abs=0.02)  # TAI - UT1 in June 2026
    sat = sf["api"].EarthSatellite(*orbit.tle_lines(), "RULE", sf["ts"])
    steps = np.linspace(0.0, dt, 75)  # 0.5 s apart
    tai = sf["ts"].tai_jd(MJD + 2400000.5 + steps / 86400.0)
    d_tai = (sat - sf["site"]).at(tai).position.km.T
    d_tai /= np.linalg.norm(d_tai, axis=1, keepdims=True)

    def angle(a, b):
        return math.degrees(math.acos(np.clip(a @ b, -1, 1)))

    moved = sum(angle(p, q) for p, q in zip(d_tai[:-1], d_tai[1:]))  # speed x seconds
    assert moved > 15.0
    assert angle(got["d"][0, 0], d_ut1[0]) < 1e-3  # where skyfield puts it at UT1 = MJD
    assert angle(got["d"][0, 0], d_tai[-1]) < 1e-3
    assert angle(got["d"][0, 0], d_tai[0]) == pytest.approx(moved, rel=0.01)


# --- the command ---------------------------------------------------------------------------

def test_inject_survey_rule_rubin_sim_writes_the_rule_and_its_band(sf, tmp_path, cli):
    """One visit crossed through its centre: streaks.csv says the rule, no CCDs, skyfield's
    length in the circle and a 300 px band (the strip of the disc); summary.json records the
    rule, the time's reading and the spans' source."""
    ts = rubin_rule.sample_times(34.0)
    orbit = aim(60.0, 100.0, rule_time(MJD, 17.0))
    d, _, _ = skyfield_track(sf, orbit, MJD, ts)
    ra, dec = radec(d[len(ts) // 2])
    (tmp_path / "sat.tle").write_text("RULE\n" + "\n".join(orbit.tle_lines()) + "\n")
    (tmp_path / "const.yaml").write_text("shape: {type: box, length: 7.25, width: 2.65}\n"
                                         "mag: 5.0\ntle: sat.tle\n")
    with open(tmp_path / "visits.csv", "w", newline="") as stream:
        w = csv.writer(stream)
        w.writerow(["observationId", "observationStartMJD", "fieldRA", "fieldDec",
                    "rotSkyPos", "band", "visitExposureTime", "numExposures", "visitTime"])
        w.writerow([7, MJD, ra, dec, 0.0, "r", 30.0, 2, 34.0])
    out = tmp_path / "out"
    cli("survey", str(tmp_path / "visits.csv"), "-o", str(out), "--constellation",
        str(tmp_path / "const.yaml"), "--rule", "rubin_sim", "--no-plots")
    rows = list(csv.DictReader(open(out / "streaks.csv")))
    assert len(rows) == 1
    row = rows[0]
    assert row["rule"] == "rubin_sim" and row["n_ccds"] == "0" and row["ccds"] == ""
    fx, fy = fine_track(*rubin_rule.gnomonic(d, ra, dec))
    inside = in_polygon(fx, fy)
    seg = np.hypot(np.diff(fx), np.diff(fy))[inside[:-1] & inside[1:]]
    length_deg = math.degrees(seg.sum())
    assert float(row["length_deg"]) == pytest.approx(length_deg, abs=2e-4)
    # Through the centre, both ends outside: a strip of width 300 px across the disc.
    r = math.radians(1.75) / math.radians(0.2 / 3600.0)
    strip = 2 * (150.0 * math.sqrt(r * r - 150.0 ** 2) + r * r * math.asin(150.0 / r))
    assert int(row["pixels_lost"]) == pytest.approx(strip, rel=0.01)
    assert float(row["mask_width_px"]) == 300.0
    summary = json.load(open(out / "summary.json"))
    assert summary["rule"]["name"] == "rubin_sim"
    assert "UT1" in summary["rule"]["time"]
    assert summary["rule"]["visits_span_from"] == {"visitTime": 1, "exposure+readouts": 0}
    assert summary["rule"]["mask_width_px"] == 300.0 and "fixed_mask" not in summary
    assert summary["streaks"] == 1 and summary["pixels_lost"] == int(row["pixels_lost"])
    # The default rule says so too, and reads the start as TAI: the satellite reaches the
    # boresight 37 + 17 s after the visit's real start, when the shutter has closed.
    cli("survey", str(tmp_path / "visits.csv"), "-o", str(tmp_path / "phys"), "--constellation",
        str(tmp_path / "const.yaml"), "--no-plots")
    phys = json.load(open(tmp_path / "phys" / "summary.json"))
    assert phys["rule"]["name"] == "inject" and phys["streaks"] == 0


def test_the_rule_has_no_ccds_to_render(cli, tmp_path):
    status, _, err = cli("survey", "visits.csv", "-o", str(tmp_path / "out"),
                         "--constellation", "c.yaml", "--rule", "rubin_sim", "--render")
    assert status != 0 and "--rule inject" in err
    assert not (tmp_path / "out").exists()


def test_visits_read_visittime_when_given(tmp_path):
    """visitTime is read (the rule's span) when the column is there, refused at 0, and
    absent otherwise."""
    from inject.errors import InputError
    from inject.survey.visits import read_visits

    head = ["observationId", "observationStartMJD", "fieldRA", "fieldDec", "rotSkyPos",
            "band", "visitExposureTime", "numExposures"]
    for extra, value, expect in ((["visitTime"], [34.0], 34.0), ([], [], None)):
        path = tmp_path / f"v{len(extra)}.csv"
        with open(path, "w", newline="") as stream:
            w = csv.writer(stream)
            w.writerow(head + extra)
            w.writerow([1, MJD, 10.0, -30.0, 0.0, "r", 30.0, 2] + value)
        assert read_visits(str(path))[0].visit_time_s == expect
    with open(tmp_path / "bad.csv", "w", newline="") as stream:
        w = csv.writer(stream)
        w.writerow(head + ["visitTime"])
        w.writerow([1, MJD, 10.0, -30.0, 0.0, "r", 30.0, 2, 0.0])
    with pytest.raises(InputError, match="visitTime"):
        read_visits(str(tmp_path / "bad.csv"))
