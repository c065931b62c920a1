"""The survey night by night, the rubin_sim rule and the fixed mask against numbers made
outside the code: the manifest's trust in a night's two files, the sky map's HEALPix pixels
(RING order, Gorski et al. 2005's closed form), the summary's blocks on a constructed table
(hand counts), a visit's streak length (a sum typed here), and the rule's "at the start or
the end" for the altitude and the Sun (skyfield's altitudes, the closed-form shadow) and its
prefilter on the whole circle (skyfield's track 1.5 deg from the boresight).

Small inputs: the rule's tests follow one aimed satellite (the helpers of
tests/test_survey_rubin_rule.py); the rest build no plan at all.
"""
import math

import numpy as np
import pytest
from test_survey_rubin_rule import (
    MJD,
    aim,
    fine_track,
    in_polygon,
    offset,
    radec,
    rule_time,
    skyfield_track,
    sun_gcrs,
    sun_line_height,
    visit,
)

from inject.survey import rubin_rule

#: Pixels of a visit's 189 science CCDs (obs_lsst: 8 ITL rafts of 4072 x 4000, 13 e2v rafts
#: of 4096 x 4004).
ALL_PIXELS = 8 * 9 * 4072 * 4000 + 13 * 9 * 4096 * 4004
#: The sample night's morning twilight (the Sun at -16.6 deg), MJD (TAI).
MJD_DAWN = 61207.43


@pytest.fixture(scope="module")
def sf(skyfield_timescale):
    api = pytest.importorskip("skyfield.api")
    from inject.orbits.passes import RUBIN

    site = api.wgs84.latlon(RUBIN.lat_deg, RUBIN.lon_deg, elevation_m=RUBIN.height_m)
    return {"ts": skyfield_timescale, "site": site, "api": api}


# --- the manifest -----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["visits", "streaks"])
@pytest.mark.parametrize("change", ["edited", "removed"])
def test_a_night_is_done_only_while_both_its_files_keep_their_digests(tmp_path, kind, change):
    """Either of a night's two files edited or gone after its entry was written: the night is
    not done (planned again), the other night still is."""
    from inject.survey.stream import NightManifest

    folder = tmp_path / "nights"
    folder.mkdir()
    paths, manifest = {}, NightManifest(str(tmp_path), "key", version="1")
    for night in (61206, 61207):
        paths[night] = {k: folder / f"{k}-{night}.parquet" for k in ("visits", "streaks")}
        for k, path in paths[night].items():
            path.write_bytes(f"{k} of {night}".encode())
        manifest.add(night, 3, 1, {k: str(p) for k, p in paths[night].items()}, {})
    assert NightManifest(str(tmp_path), "key", version="1").load().done(
        [61206, 61207]) == {61206, 61207}
    path = paths[61206][kind]
    if change == "edited":
        path.write_bytes(path.read_bytes() + b" ")
    else:
        path.unlink()
    assert NightManifest(str(tmp_path), "key", version="1").load().done(
        [61206, 61207]) == {61207}


# --- the sky map ------------------------------------------------------------------------------

NSIDE = 16


def ring_centre(ring, j, nside=NSIDE):
    """RING index, RA and Dec (deg) of the ``j``-th pixel (from 1) of ``ring`` (from 1 at the
    north pole), north cap or equatorial belt (Gorski et al. 2005, eqs. 4-9)."""
    if ring < nside:  # the north polar cap: 4 i pixels a ring
        z = 1.0 - ring * ring / (3.0 * nside * nside)
        phi = math.pi / (2 * ring) * (j - 0.5)
        index = 2 * ring * (ring - 1) + j - 1
    else:  # the belt: 4 nside pixels a ring, every other ring shifted by half a pixel
        z = 4.0 / 3.0 - 2.0 * ring / (3.0 * nside)
        shift = (ring - nside + 1) % 2
        phi = math.pi / (2 * nside) * (j - shift / 2.0)
        index = 2 * nside * (nside - 1) + 4 * nside * (ring - nside) + j - 1
    return index, math.degrees(phi), math.degrees(math.asin(z))


def test_the_sky_map_is_the_mean_of_each_ring_pixels_visits():
    """Two visits in the cap's pixel 16 (ring 3, 5th pixel), one in the belt's pixel 1513
    (the equator's 10th): the map holds their means there and NaN in the other 3070."""
    pytest.importorskip("healpy")
    from inject.survey.stream import SKY_NSIDE, healpix_fraction

    assert SKY_NSIDE == NSIDE
    cap, ra_cap, dec_cap = ring_centre(3, 5)
    belt, ra_belt, dec_belt = ring_centre(2 * NSIDE, 10)
    assert (cap, belt) == (16, 1513)
    sky = healpix_fraction([ra_cap + 0.3, ra_cap - 0.3, ra_belt],
                           [dec_cap, dec_cap - 0.2, dec_belt + 0.5], [0.1, 0.3, 0.5])
    assert sky.shape == (12 * NSIDE ** 2,)
    assert sky[cap] == pytest.approx(0.2, rel=1e-12) and sky[belt] == 0.5
    assert np.flatnonzero(np.isfinite(sky)).tolist() == [cap, belt]


# --- the summary from the tables --------------------------------------------------------------

def _columns():
    """Six visits of two nights, one each side of 2027-01-01 0h UTC on the first; streaks on
    the 2nd, 4th and 5th (two on the 5th); a fixed band beside the mask."""
    from astropy.time import Time

    tai = Time(["2026-12-31T23:00:00", "2027-01-01T01:00:00", "2027-01-01T08:00:00",
                "2027-01-02T01:00:00", "2027-01-02T03:00:00", "2027-01-02T05:00:00"],
               scale="utc").tai.mjd
    visits = {"observationId": np.arange(1, 7), "mjd": tai,
              "band": np.array(list("grrizg"), object),
              "n_streaks": np.array([0, 1, 0, 1, 2, 0]),
              "pixels_lost": np.array([0, 40_000, 0, 10_000, 90_000, 0]),
              "year": np.array([2026, 2026, 2026, 2027, 2027, 2027]),
              "sun_alt_deg": np.array([-5.0, -12.0, -15.0, -18.0, -25.0, -70.0]),
              "fieldRA": np.zeros(6), "fieldDec": np.full(6, -30.0),
              "pixels_fixed_mask": np.array([0, 600_000, 0, 300_000, 1_500_000, 0])}
    streaks = {"observationId": np.array([2, 4, 5, 5]),
               "fwhm_arcsec": np.array([1.0, 2.0, 3.0, 4.0]),
               "mask_width_px": np.array([20.0, 30.0, 40.0, 50.0]),
               "peak_e_per_px": np.array([100.0, 200.0, 300.0, 400.0]),
               "mag": np.array([5.0, 6.0, 7.0, 8.0]), "length_deg": np.array([1.0, 2.0, 0.5, 3.0])}
    return visits, streaks


def test_the_summarys_blocks_are_the_hand_counts_of_a_constructed_table():
    """``by_year`` by the night's year (the 2nd visit is 2027 in UTC, its night 2026's),
    ``by_sun_alt`` with each bin's lower edge in it, the fixed band's median over the
    streaked visits only (600,000, 300,000 and 1,500,000 px: 600,000)."""
    from inject.survey.stream import summary_from_tables

    visits, streaks = _columns()
    out = summary_from_tables(visits, streaks, {}, {}, -70.7494, 300.0)
    assert out["total_pixels_per_visit"] == ALL_PIXELS
    assert {y: (b["visits"], b["streaks"], b["pixels_lost"]) for y, b in
            out["by_year"].items()} == {"2026": (3, 1, 40_000), "2027": (3, 3, 100_000)}
    assert {s: (b["visits"], b["streaks"], b["streaked_visits"]) for s, b in
            out["by_sun_alt"].items()} == {"above_-12": (2, 1, 1), "-18_to_-12": (2, 1, 1),
                                           "below_-18": (2, 2, 1)}
    block = out["fixed_mask"]
    assert block["pixels_lost"] == 2_400_000
    assert block["pixel_fraction_lost_total"] == pytest.approx(2_400_000 / (6 * ALL_PIXELS),
                                                               rel=1e-15)
    assert block["pixel_fraction_lost_median_streaked"] == pytest.approx(
        600_000 / ALL_PIXELS, rel=1e-15)
    assert block["ratio_to_physical"] == pytest.approx(2_400_000 / 140_000, rel=1e-15)
    assert block["width_arcsec"] == pytest.approx(60.0, rel=1e-15)


# --- a visit's streak length ------------------------------------------------------------------

def test_a_visits_streak_length_is_the_sum_of_its_two_streaks():
    from inject.survey.plan import Streak, VisitPlan

    plan = VisitPlan(visit(0.0, -30.0))
    for name, length in (("A", 0.25), ("B", 1.5)):
        plan.streaks.append(Streak(satellite=name, ccds=("R22_S11",), length_deg=length,
                                   mag=6.0, fwhm_arcsec=1.0, peak_e_per_px=100.0,
                                   mask_width_px=20.0))
    assert plan.visit_row()["streak_length_deg"] == 1.75


# --- the rubin_sim rule: at the start or the end ----------------------------------------------

def test_a_satellite_rising_through_20_deg_counts_by_its_end(sf):
    """Below 20 deg at the start and above it at the end (skyfield's altitudes): counted."""
    span = 8.0
    ts = rubin_rule.sample_times(span)
    for az in (250.0, 70.0, 160.0, 340.0):
        for ascending in (True, False):
            orbit = aim(19.85, az, rule_time(MJD), ascending=ascending)
            d, alt, _ = skyfield_track(sf, orbit, MJD, ts)
            if alt[0] < 20.0 < alt[-1]:
                break
        if alt[0] < 20.0 < alt[-1]:
            break
    assert alt[0] < 19.95 and alt[-1] > 20.05  # the premise, a margin either side
    ra, dec = radec((d[0] + d[-1]) / np.linalg.norm(d[0] + d[-1]))
    hits = rubin_rule.count_visit(visit(ra, dec, visit_time=span), [orbit], [0])
    assert [h["index"] for h in hits] == [0]


def test_a_satellite_leaving_the_shadow_counts_by_its_end(sf):
    """In the shadow at the start and sunlit at the end (the closed-form line to the Sun
    past skyfield's sphere, 10 km either side, on skyfield's positions), in the morning
    twilight as the shadow withdraws: counted."""
    span = 34.0
    ts = rubin_rule.sample_times(span)
    sun = sun_gcrs(MJD_DAWN)
    found = None
    for az in range(225, 225 + 360, 15):  # from the first found, to keep the search short
        for alt in (30.0, 45.0, 60.0, 75.0):
            for ascending in (True, False):
                orbit = aim(alt, float(az % 360), rule_time(MJD_DAWN, span / 2),
                            ascending=ascending)
                d, alts, r = skyfield_track(sf, orbit, MJD_DAWN, ts)
                h = [sun_line_height(p, sun) for p in r]
                if h[0] < -10.0 and h[-1] > 10.0 and min(alts) > 25.0:
                    found = orbit, d
                    break
            if found:
                break
        if found:
            break
    assert found, "no satellite leaving the shadow"
    orbit, d = found
    ra, dec = radec(d[len(d) // 2])
    hits = rubin_rule.count_visit(visit(ra, dec, mjd=MJD_DAWN), [orbit], [0])
    assert [h["index"] for h in hits] == [0]
    assert hits[0]["sunlit"].tolist() == [False, True]


def test_the_rules_prefilter_keeps_a_track_1_5_deg_from_the_boresight(sf):
    """The whole rule (its night's prefilter, its UT1 start, the count): a satellite whose
    skyfield track passes 1.5 deg from the boresight is one streak, of skyfield's length
    inside the 64-gon (the chord, 2 sqrt(1.75^2 - 1.5^2) = 1.80 deg, a little less)."""
    from types import SimpleNamespace

    span = 34.0
    ts = rubin_rule.sample_times(span)
    orbit = aim(60.0, 100.0, rule_time(MJD, span / 2))
    d, _, _ = skyfield_track(sf, orbit, MJD, ts)
    mid = len(ts) // 2
    motion = d[mid + 1] - d[mid - 1]
    ra, dec = radec(offset(d[mid], motion / np.linalg.norm(motion), 1.5))
    fx, fy = fine_track(*rubin_rule.gnomonic(d, ra, dec))
    assert math.degrees(np.hypot(fx, fy).min()) == pytest.approx(1.5, abs=0.01)  # premise
    inside = in_polygon(fx, fy)
    length = math.degrees(np.hypot(np.diff(fx), np.diff(fy))[inside[:-1] & inside[1:]].sum())
    assert length == pytest.approx(2 * math.sqrt(1.75 ** 2 - 1.5 ** 2), abs=0.03)
    plans = rubin_rule.plan_visits([visit(ra, dec)], SimpleNamespace(orbits=[orbit]))
    assert [s.satellite for s in plans[0].streaks] == [orbit.name]
    assert plans[0].streaks[0].length_deg == pytest.approx(length, abs=1e-3)
