"""Walker shells over any span, and the literature's constellations as sample files.

A shell carries no drag: propagated a year from its epoch it keeps its height, and its planes
turn at the closed-form J2 rate. A TLE is still refused 60 days from a visit. The sample
files hold the shells and counts the literature gives (the totals added up here).
"""
import math
import os

import numpy as np
import pytest

ROOT = os.path.join(os.path.dirname(__file__), os.pardir, "sample_fields")
MODEL = "shape: {type: box, length: 7.25, width: 2.65}\nmag: 5.0\nref_range: 550\n"
#: Textbook constants, not SGP4's: GM (km^3/s^2), the equatorial radius (km) and J2 (EGM2008).
MU_KM3_S2 = 398600.4418
R_EQ_KM = 6378.137
J2 = 1.08262668e-3


def _rows(ids_starts):
    """A visits CSV: each (id, UTC start) a 30 s r visit at RA 250, Dec -30."""
    from astropy.time import Time

    cols = ("observationId,observationStartMJD,fieldRA,fieldDec,rotSkyPos,band,"
            "visitExposureTime,numExposures,seeingFwhmEff")
    rows = [f"{vid},{float(Time(start, scale='utc').tai.mjd)!r},250,-30,0,r,30,1,0.8"
            for vid, start in ids_starts]
    return "\n".join([cols, *rows]) + "\n"


# --- a shell over a year --------------------------------------------------------------------

@pytest.mark.parametrize("height, inclination", [(550.0, 53.0), (340.0, 53.0),
                                                 (604.0, 148.0), (1200.0, 87.9)])
def test_a_shell_a_year_on_keeps_its_height_and_turns_at_the_j2_rate(height, inclination):
    """One satellite of a shell, propagated a year from its epoch as the survey propagates it.

    The node of its orbital plane (from r x v) is sampled twice a day and fitted by a line: its
    rate is the closed form dOmega/dt = -3/2 n J2 (R/a)^2 cos i (e = 0). The closed form is
    first order in J2; SGP4 also keeps second-order terms (J2's change of the mean motion,
    J2^2 and J4 = -1.5e-3 J2), each a few times J2 (R/a)^2 of the rate: 5 J2 (R/a)^2 (0.38-0.45%
    here) bounds them.

    Its height: the mean of |r| over a day is the mean semi-major axis a = R + height less
    3/4 J2 R^2/a (3 cos^2 i - 1), the mean of J2's short-period radial term on a circular orbit
    (-0.4 to +4.3 km for these shells). It holds within 0.5 km at the epoch and a year on: a
    day is not a whole number of revolutions, and the term at twice the argument of latitude
    (J2 R^2 sin^2 i / 4a, about 1 km) averages to within 0.1 km over 13-15 revolutions. Drag
    at the smallest B* of a real Starlink TLE would have brought the 340 km shell down.
    """
    from astropy import units as u
    from astropy.time import Time

    from inject.orbits.passes import propagate_teme
    from inject.survey.constellation import parse_constellation

    epoch = "2023-10-01T00:00:00"
    shell = {"name": "s", "height": height, "inclination": inclination, "planes": 2,
             "per_plane": 2, "phasing": 1}
    constellation = parse_constellation({"shape": {"type": "box", "length": 7.25,
                                                   "width": 2.65}, "mag": 5.0,
                                         "ref_range": 550, "epoch": epoch, "shells": [shell]})
    orbit = constellation.orbits[0]
    assert orbit.satrec.bstar == 0.0 and orbit.satrec.ndot == 0.0 and orbit.satrec.nddot == 0.0
    start = Time(epoch, scale="utc")
    days = np.arange(0.0, 366.0, 0.5)
    r, v = propagate_teme([orbit], start + days * u.day)
    h = np.cross(r[0], v[0])
    node = np.degrees(np.unwrap(np.arctan2(h[:, 0], -h[:, 1])))
    rate = np.polyfit(days, node, 1)[0]  # deg/day
    a = R_EQ_KM + height
    n = math.sqrt(MU_KM3_S2 / a ** 3)
    closed = -1.5 * n * J2 * (R_EQ_KM / a) ** 2 * math.cos(math.radians(inclination))
    closed = math.degrees(closed) * 86400.0
    assert abs(node[-1] - node[0]) > 50.0  # the plane has turned a long way in a year
    assert rate == pytest.approx(closed, rel=5.0 * J2 * (R_EQ_KM / a) ** 2)

    expected = height - 0.75 * J2 * R_EQ_KM ** 2 / a * (
        3.0 * math.cos(math.radians(inclination)) ** 2 - 1.0)
    for day in (0.0, 365.0):
        times = start + (day + np.linspace(0.0, 1.0, 2881)) * u.day
        r, _ = propagate_teme([orbit], times)
        mean_height = float(np.linalg.norm(r[0], axis=1).mean()) - R_EQ_KM
        assert mean_height == pytest.approx(expected, abs=0.5)


def test_shells_a_year_from_their_epoch_are_planned(cli, tmp_path):
    """The check refuses no shell, however far its epoch (here a year before the visit)."""
    (tmp_path / "v.csv").write_text(_rows([(1, "2024-10-01T03:00:00")]))
    (tmp_path / "c.yaml").write_text(
        MODEL + "epoch: 2023-10-01T00:00:00\nshells:\n  - {name: s, height: 550, "
                "inclination: 53, planes: 4, per_plane: 4, phasing: 1}\n")
    status, _, err = cli("survey", tmp_path / "v.csv", "-o", tmp_path / "out",
                         "--constellation", tmp_path / "c.yaml", "--no-plots")
    assert status == 0, err
    assert "days" not in err


@pytest.mark.parametrize("days, refused", [(61.0, True), (59.0, False)])
def test_a_tle_61_days_from_a_visit_is_still_refused(cli, tmp_path, days, refused):
    """A TLE's epoch 61 days before the last visit: refused, naming the TLE, the visit and
    that the limit is a TLE's; 59 days: planned, with a warning (more than 14 days)."""
    from astropy import units as u
    from astropy.time import Time

    from inject.orbits.passes import Orbit

    first = Time("2026-06-15T23:00:00", scale="utc")
    last = first + 2 * u.hour
    epoch = (last - days * u.day).isot
    a, b = Orbit.circular(550.0, 53.0, 0.0, 0.0, epoch, name="OLD").tle_lines()
    (tmp_path / "old.tle").write_text(f"OLD\n{a}\n{b}\n")
    (tmp_path / "c.yaml").write_text(MODEL + "tle: old.tle\n")
    (tmp_path / "v.csv").write_text(_rows([(1, first.isot), (2, last.isot)]))
    status, _, err = cli("survey", tmp_path / "v.csv", "-o", tmp_path / "out",
                         "--constellation", tmp_path / "c.yaml", "--no-plots")
    if refused:
        assert status == 2
        assert "'OLD'" in err and "visit 2" in err and "61.0 days" in err
        assert "a TLE more than 60 days from a visit is refused" in err
        assert "Walker shell is propagated over any span" in err
        assert not (tmp_path / "out").exists()
    else:
        assert status == 0 and "59.0" in err and "TLEs have epochs" in err


# --- the literature's constellations ------------------------------------------------------

#: Each sample file's shells as the literature gives them: (height km, inclination deg,
#: planes, per plane), and the total the literature states.
LITERATURE = {
    "constellation_starlink_gen1.yaml": (
        [(550, 53.0, 72, 22), (540, 53.2, 72, 22), (570, 70.0, 36, 20), (560, 97.6, 6, 58),
         (560, 97.6, 4, 43)], 4408),
    "constellation_starlink_gen2.yaml": (
        [(340, 53.0, 48, 110), (345, 46.0, 48, 110), (350, 38.0, 48, 110),
         (360, 96.9, 30, 120), (525, 53.0, 28, 120), (530, 43.0, 28, 120),
         (535, 33.0, 28, 120), (604, 148.0, 12, 12), (614, 115.7, 18, 18)], 29988),
    "constellation_oneweb.yaml": (
        [(1200, 87.9, 36, 49), (1200, 40.0, 32, 72), (1200, 55.0, 32, 72)], 6372),
    "constellation_kuiper.yaml": (
        [(630, 51.9, 34, 34), (610, 42.0, 36, 36), (590, 33.0, 28, 28)], 3236),
}


@pytest.mark.parametrize("name", sorted(LITERATURE))
def test_the_literatures_constellations_load_with_their_counts(name):
    """Each file loads as ``inject survey`` reads it, with rubin_sim's epoch, no drag, the
    literature's shells (heights, inclinations, planes x per plane) and its stated total
    (the sum of planes x per plane, added here, is the literature's number)."""
    import yaml

    from inject.survey.constellation import read_constellation

    shells, total = LITERATURE[name]
    assert sum(p * s for _, _, p, s in shells) == total
    path = os.path.join(ROOT, name)
    with open(path) as stream:
        raw = yaml.safe_load(stream)
    assert [(s["height"], s["inclination"], s["planes"], s["per_plane"])
            for s in raw["shells"]] == shells
    constellation = read_constellation(path)
    assert constellation.epoch_isot == "2023-10-01T00:00:00.000000"
    assert len(constellation) == total
    assert [n for _, n in constellation.sources] == [p * s for _, _, p, s in shells]
    assert all(o.kind == "circular" and o.satrec.bstar == 0.0 for o in constellation.orbits)
    heights = sorted({round(o.mean_height_km, 3) for o in constellation.orbits})
    assert heights == sorted({float(h) for h, _, _, _ in shells})
