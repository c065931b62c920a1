"""scripts/make_synthetic_survey.py: three June nights read by ``inject survey``'s reader,
their visits per night from the twilight's edges computed here with astropy's Sun, the
twilight visits in the twilight, and LSST's band mix."""
import importlib.util
import os
import sqlite3

import numpy as np
import pytest

SCRIPT = os.path.join(os.path.dirname(__file__), os.pardir, "scripts",
                      "make_synthetic_survey.py")
#: LSST's band mix.
SHARES = {"u": 0.06, "g": 0.09, "r": 0.22, "i": 0.22, "z": 0.20, "y": 0.21}
START = "2026-06-14"
NIGHTS = 3


def _script():
    spec = importlib.util.spec_from_file_location("make_synthetic_survey", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def survey3(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic")
    script = _script()
    path = str(folder / "survey.db")
    per_night = script.write_survey(path, START, NIGHTS, seed=11)
    con = sqlite3.connect(path)
    try:
        cursor = con.execute("SELECT * FROM observations ORDER BY observationId")
        names = [d[0] for d in cursor.description]
        rows = [dict(zip(names, r)) for r in cursor.fetchall()]
    finally:
        con.close()
    return {"path": path, "rows": rows, "per_night": per_night, "folder": folder,
            "script": script}


def _sun_alt_deg(mjd_utc):
    """The Sun's altitude at Rubin by astropy (not the script's formula)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, get_sun
    from astropy.time import Time

    from inject.orbits.passes import RUBIN

    t = Time(np.asarray(mjd_utc, float), format="mjd", scale="utc")
    return get_sun(t).transform_to(AltAz(obstime=t, location=RUBIN.location)).alt.to_value(u.deg)


def test_the_reader_takes_it_with_every_optional_column(survey3):
    from inject.survey.visits import read_visits

    visits = read_visits(survey3["path"])
    assert len(visits) == len(survey3["rows"]) == sum(survey3["per_night"])
    assert all(v.seeing_fwhm_eff is not None and v.sky_brightness is not None
               and v.rotator_deg is not None for v in visits)
    assert all("synthetic" in r["note"] for r in survey3["rows"])


def test_visits_per_night_follow_the_twilights_edges(survey3):
    """Per night: a 15 s twilight visit every 30 s while the Sun is between -12 and -18 deg,
    a dark visit every 44 s below -18 deg. The edges from astropy's Sun every minute: the
    counts within the 2 minutes of each edge (4 twilight or 3 dark visits an edge)."""
    from astropy.time import Time

    noon = Time(f"{START}T16:43:00", scale="utc").mjd
    for k, count in enumerate(survey3["per_night"]):
        t = noon + k + np.arange(24 * 60 + 1) / 1440.0
        alt = _sun_alt_deg(t)
        n12, n18 = np.flatnonzero(alt < -12.0), np.flatnonzero(alt < -18.0)
        twilight_s = ((t[n18[0]] - t[n12[0]]) + (t[n12[-1]] - t[n18[-1]])) * 86400.0
        dark_s = (t[n18[-1]] - t[n18[0]]) * 86400.0
        expected = twilight_s / 30.0 + dark_s / 44.0
        assert count == pytest.approx(expected, abs=4 * 4 + 2 * 3)
        assert 950 < count < 1100  # June: the year's longest nights
        mine = [r for r in survey3["rows"] if r["night"] == k + 1]
        short = [r for r in mine if r["visitExposureTime"] == 15.0]
        assert len(short) == pytest.approx(twilight_s / 30.0, abs=4 * 4)


def test_twilight_visits_are_in_the_twilight_and_the_others_in_the_dark(survey3):
    from astropy.time import Time

    rows = survey3["rows"]
    mjd = Time([r["observationStartMJD"] for r in rows], format="mjd", scale="tai").utc.mjd
    alt = _sun_alt_deg(mjd)
    short = np.array([r["visitExposureTime"] == 15.0 for r in rows])
    assert short.sum() > 200
    # Within a minute of the edges (the Sun moves 0.25 deg a minute at most).
    assert np.all((alt[short] > -18.3) & (alt[short] < -11.7))
    assert np.all(alt[~short] < -17.7)
    assert {r["visitExposureTime"] for r, s in zip(rows, short) if not s} == {30.0, 38.0}
    assert all(r["visitExposureTime"] == 38.0 for r, s in zip(rows, short)
               if not s and r["band"] == "u")


def test_each_nights_bands_are_lssts_mix(survey3):
    """Each night's visits per band are its count times LSST's shares, to a visit."""
    for k, count in enumerate(survey3["per_night"]):
        bands = [r["band"] for r in survey3["rows"] if r["night"] == k + 1]
        for band, share in SHARES.items():
            assert abs(bands.count(band) - share * count) < 1.0


def test_fields_follow_the_sidereal_time(survey3):
    """Every field is above airmass 2 at the visit's start (astropy's frames), and chosen
    near the meridian: its RA follows the local sidereal time, so the season."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.orbits.passes import RUBIN

    rows = survey3["rows"][::7]
    t = Time([r["observationStartMJD"] for r in rows], format="mjd", scale="tai")
    c = SkyCoord([r["fieldRA"] for r in rows] * u.deg, [r["fieldDec"] for r in rows] * u.deg)
    alt = c.transform_to(AltAz(obstime=t, location=RUBIN.location)).alt.deg
    assert alt.min() > 29.5
    lst = t.sidereal_time("mean", longitude=RUBIN.lon_deg * u.deg).deg
    ha = (lst - np.array([r["fieldRA"] for r in rows]) + 180.0) % 360.0 - 180.0
    # Weights exp(-|HA| / 22.5 deg): a median |HA| of 22.5 ln 2 = 15.6 deg over a uniform
    # spread of the fields above 30 deg.
    assert np.median(np.abs(ha)) < 20.0 and np.percentile(np.abs(ha), 90) < 60.0


def test_a_night_is_the_same_whatever_the_number_of_nights(survey3):
    """One stream per night from the SeedSequence: the first night alone is the first night
    of three."""
    path = str(survey3["folder"] / "one.db")
    survey3["script"].write_survey(path, START, 1, seed=11)
    con = sqlite3.connect(path)
    try:
        one = con.execute("SELECT * FROM observations ORDER BY observationId").fetchall()
    finally:
        con.close()
    first = [tuple(r.values()) for r in survey3["rows"] if r["night"] == 1]
    assert one == first
