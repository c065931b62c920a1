"""``inject survey`` against numbers it does not compute itself.

A three-visit twilight night at Rubin with a 400-satellite Walker shell, two of the visits
aimed at one of its satellites (found with SGP4 and astropy's frames, not the plan's), is
planned once. ``summary.json`` is checked against a hand count of its own tables and of the
189 CCDs' pixels; the sky's noise against SMTN-002's dark sky and the airmass; the local hour
against UTC and the site's longitude; the mask's rows against a closed form at a CCD's edges.
Then the inputs that once gave silently wrong answers: a visit planned differently in another
file, duplicate satellites, impossible times, missing seeing, an OUTDIR shared by two runs.
"""
import csv
import hashlib
import json
import math
import os

import numpy as np
import pytest

from inject.cli.main import main

#: The shell's epoch, also the aimed visit's start (UTC).
EPOCH = "2026-06-15T23:12:00"
#: The visits: (id, UTC start, band, rotSkyPos, snaps, aimed at a satellite).
VISITS = ((10, "2026-06-15T23:00:00", "g", 0.0, 1, False),
          (11, EPOCH, "r", 30.0, 1, True),
          (12, "2026-06-15T23:27:00", "i", 60.0, 2, True))
SHELL = "{name: s, height: 550, inclination: 53, planes: 20, per_plane: 20, phasing: 1}"
MODEL = "shape: {type: box, length: 7.25, width: 2.65}\nmag: 5.0\nref_range: 550\n"
COLUMNS = ("observationId", "observationStartMJD", "fieldRA", "fieldDec", "rotSkyPos", "band",
           "visitExposureTime", "numExposures", "seeingFwhmEff")
#: Rubin's longitude, deg east.
LON_DEG = -70.7494
#: The 189 science CCDs: 8 ITL rafts (R01 R02 R03 R10 R20 R41 R42 R43) of 4072 x 4000 px,
#: 13 e2v rafts of 4096 x 4004 px, 9 CCDs a raft.
ALL_PIXELS = 8 * 9 * 4072 * 4000 + 13 * 9 * 4096 * 4004


def write_csv(path, rows, columns=COLUMNS):
    with open(path, "w", newline="") as stream:
        writer = csv.DictWriter(stream, columns)
        writer.writeheader()
        writer.writerows({c: row.get(c, "") for c in columns} for row in rows)
    return str(path)


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def write_const(folder, body=f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n", name="const.yaml"):
    path = os.path.join(folder, name)
    with open(path, "w") as stream:
        stream.write(MODEL + body)
    return path


def survey(*args):
    return main(["survey", *[str(a) for a in args]])


def days_later(row, days):
    """``row`` moved ``days`` later: into another night (--job slices take nights)."""
    return {**row, "observationStartMJD": repr(float(row["observationStartMJD"]) + days)}


def _visit_rows():
    """The visits' rows: the aimed ones pointed at the highest satellite of the shell 15 s
    after their start (its topocentric direction from SGP4 and astropy's frames)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, FieldFrame, propagate_teme, walker_shell

    orbits = walker_shell(400, 20, 1, 550.0, 53.0, EPOCH, name="s")
    rows = []
    for vid, start, band, rotation, snaps, aimed in VISITS:
        t0 = Time(start, scale="utc")
        mid = Time([t0 + 15 * u.s])
        if aimed:
            frame = FieldFrame.build(mid, Pointing(0.0, 0.0), RUBIN)
            r, _ = propagate_teme(orbits, mid)
            _, _, alt, az = frame.to_altaz(np.einsum("tij,stj->sti", frame.teme_to_itrs, r))
            n = int(np.argmax(alt[:, 0]))
            assert alt[n, 0] > 40.0
            alt_deg, az_deg = float(alt[n, 0]), float(az[n, 0])
        else:
            alt_deg, az_deg = 75.0, 0.0
        aim = SkyCoord(AltAz(alt=alt_deg * u.deg, az=az_deg * u.deg, obstime=mid[0],
                             location=RUBIN.location)).icrs
        rows.append({"observationId": vid, "observationStartMJD": repr(float(t0.tai.mjd)),
                     "fieldRA": aim.ra.deg, "fieldDec": aim.dec.deg, "rotSkyPos": rotation,
                     "band": band, "visitExposureTime": 30.0, "numExposures": snaps,
                     "seeingFwhmEff": 0.8})
    return rows


@pytest.fixture(scope="module")
def night(tmp_path_factory):
    folder = tmp_path_factory.mktemp("trust")
    rows = _visit_rows()
    visits = write_csv(folder / "night.csv", rows)
    const = write_const(str(folder))
    out = folder / "out"
    assert survey(visits, "-o", out, "--constellation", const, "--no-plots") == 0
    return {"folder": folder, "rows": rows, "visits": visits, "const": const, "out": out,
            "streaks": read_csv(out / "streaks.csv"), "table": read_csv(out / "visits.csv"),
            "summary": json.loads((out / "summary.json").read_text())}


# --- summary.json against a hand count ------------------------------------------------------

def test_summary_totals_are_the_hand_count_of_the_tables(night):
    """The totals of summary.json from the rows of visits.csv and streaks.csv and the pixels
    of the 189 CCDs counted here: the total pixel fraction is over all the visits' pixels."""
    table, streaks, s = night["table"], night["streaks"], night["summary"]
    lost = {int(r["observationId"]): int(r["pixels_lost"]) for r in table}
    by_visit = {}
    for r in streaks:
        by_visit.setdefault(int(r["observationId"]), []).append(int(r["pixels_lost"]))
    assert set(by_visit) >= {11, 12}  # both aimed visits are streaked
    for vid, pixels in by_visit.items():  # one streak each here: no overlap to count once
        assert lost[vid] == sum(pixels) > 10_000
    assert s["total_pixels_per_visit"] == ALL_PIXELS == 3_091_580_928
    assert s["visits"] == 3 and s["streaks"] == len(streaks)
    assert s["streaked_visits"] == len(by_visit)
    assert s["streaks_per_visit"] == pytest.approx(len(streaks) / 3, rel=1e-15)
    assert s["pixels_lost"] == sum(lost.values())
    assert s["pixel_fraction_lost_total"] == pytest.approx(
        sum(lost.values()) / (3 * ALL_PIXELS), rel=1e-15)
    fractions = sorted(lost[v] / ALL_PIXELS for v in by_visit)
    assert s["pixel_fraction_lost_median_streaked"] == pytest.approx(
        fractions[len(fractions) // 2] if len(fractions) % 2
        else 0.5 * (fractions[0] + fractions[1]), rel=1e-15)
    assert s["pixel_fraction_lost_max"] == pytest.approx(max(fractions), rel=1e-15)


def test_numbers_are_written_to_read_back_exactly(night):
    """A visit's pixel fraction reads back as the float pixels / all pixels, a loss of
    1,500 px too (4.9e-7: 0.0 at six decimals), and every streak's number as written."""
    from inject.survey.outputs import csv_text

    text = csv_text([{"pixel_fraction_lost": 1500 / ALL_PIXELS}], ["pixel_fraction_lost"])
    assert float(text.split()[1]) == 1500 / ALL_PIXELS
    for row in night["table"]:
        pixels = int(row["pixels_lost"])
        assert float(row["pixel_fraction_lost"]) == pixels / ALL_PIXELS
    for row in night["streaks"]:
        for column in ("length_deg", "mask_width_px", "mjd", "t_mid_s"):
            assert repr(float(row[column])) == row[column]


# --- the sky's noise: SMTN-002 --------------------------------------------------------------

#: SMTN-002 (Yoachim et al., "LSST throughputs and sensitivity", v1.9): per band the zero
#: point (AB mag for 1 e-/s), the extinction (mag per airmass) and the dark sky at zenith
#: (mag/arcsec^2).
SMTN_002 = {"u": (26.52, 0.47, 23.05), "g": (28.51, 0.21, 22.25), "r": (28.36, 0.13, 21.20),
            "i": (28.17, 0.10, 20.46), "z": (27.78, 0.07, 19.61), "y": (26.82, 0.17, 18.60)}


def _dark_sky(band, exptime_s, alt_deg):
    """SMTN-002's dark sky in e- per 0.2" pixel (the hardware zero point: the sky's light is
    not extinguished), brightened by the airmass sec z = 1 / sin(alt)."""
    zp, k, mu = SMTN_002[band]
    return 10.0 ** (0.4 * (zp + k - mu)) * exptime_s * 0.2 ** 2 / math.sin(math.radians(alt_deg))


def test_the_sky_is_smtn002s_dark_sky_brightened_by_the_airmass(night):
    from inject.photometry import BANDS
    from inject.survey.plan import sky_sigma
    from inject.survey.visits import Visit

    for name, (zp, k, mu) in SMTN_002.items():
        assert (BANDS[name].zeropoint, BANDS[name].extinction, BANDS[name].sky_mag) == (zp, k, mu)
    assert _dark_sky("g", 30.0, 90.0) == pytest.approx(464.8, abs=0.1)  # the module's ~465
    for band in SMTN_002:
        visit = Visit(1, 61207.0, 0.0, 0.0, 0.0, band, 30.0)
        for alt in (90.0, 60.0, 30.0):  # airmass 1, 1.155, 2: brighter, never dimmer
            _, sky = sky_sigma(visit, alt, "e2v")
            assert sky == pytest.approx(_dark_sky(band, 30.0, alt), rel=1e-12)
    # The planned visits (no skyBrightness column): the sky each mask was computed against.
    for row in night["table"]:
        if row["sky_e_per_px"]:
            assert float(row["sky_e_per_px"]) == pytest.approx(
                _dark_sky(row["band"], 30.0, float(row["alt_deg"])), rel=1e-12)


def test_the_read_noise_counts_once_per_snap():
    """sigma^2 = sky + n_snaps x read^2: a 30 s visit of 2 snaps of 15 s reads twice."""
    from inject.camera import layout as fp
    from inject.survey.plan import sky_sigma
    from inject.survey.visits import Visit

    for vendor in fp.SENSORS:
        read = fp.SENSORS[vendor].median("read_noise")
        assert read == pytest.approx({"e2v": 5.41, "itl": 6.4}[vendor])
        for snaps in (1, 2):
            visit = Visit(1, 61207.0, 0.0, 0.0, 0.0, "r", 30.0, n_exposures=snaps)
            sigma, sky = sky_sigma(visit, 90.0, vendor)
            assert sky == pytest.approx(_dark_sky("r", 30.0, 90.0), rel=1e-12)
            assert sigma ** 2 == pytest.approx(sky + snaps * read ** 2, rel=1e-12)


# --- the local hour -------------------------------------------------------------------------

def test_the_local_hour_is_utc_plus_the_longitude(night):
    """Local mean solar time = UTC + longitude / 15 deg per hour: at Rubin (70.7494 deg west)
    04:00 UTC is 23:17:00.1 (23.28337 h), 06:00 UTC 01:17 (25.28337 h, after midnight)."""
    from astropy.time import Time

    from inject.survey.visits import local_hours

    hours = local_hours([Time(t, scale="utc").tai.mjd for t in (
        "2026-06-16T04:00:00", "2026-06-16T06:00:00", "2026-06-15T23:12:00")], LON_DEG)
    by_hand = [4.0 + LON_DEG / 15.0 + 24.0, 6.0 + LON_DEG / 15.0 + 24.0, 23.2 + LON_DEG / 15.0]
    assert hours == pytest.approx(by_hand, abs=1e-7)  # 0.4 ms
    # The night's visits at 23:00-23:27 UTC are at 18:17-18:44 local: one hour, "18".
    assert list(night["summary"]["by_hour"]) == ["18"]
    assert night["summary"]["by_hour"]["18"]["visits"] == 3


# --- a mask at a CCD's edges: closed forms --------------------------------------------------

def test_a_mask_across_a_ccd_edge_keeps_its_rows_on_the_ccd():
    """R22_S11 (e2v, 4096 x 4004 px, pixel (2047.5, 2001.5) at the focal plane's centre):
    pixel centres inside the 20 px wide rectangle, on the CCD's rows 0 .. 4003."""
    from inject.camera import layout as fp
    from inject.survey.plan import run_spans, union_pixels

    ccd = fp.ccd("R22_S11")

    def lost(xs_px, ys_px, width=20.0):
        xs = (np.asarray(xs_px, float) - 2047.5) * 0.010
        ys = (np.asarray(ys_px, float) - 2001.5) * 0.010
        return union_pixels(run_spans(xs, ys, width, ccd))

    # A column track from below the CCD to row 1000.25 (its end cap to 1010.25): rows
    # 0 .. 1010, columns 991 .. 1010.
    assert lost([1000.3, 1000.3], [-3000.0, 1000.25]) == 1011 * 20
    # From above the CCD down to row 3000.25 (cap to 2990.25): rows 2991 .. 4003.
    assert lost([1000.3, 1000.3], [7000.0, 3000.25]) == (4003 - 2991 + 1) * 20
    # A row track straddling the bottom edge, centre row 5.3: rows 0 .. 15 of [-4.7, 15.3].
    assert lost([-3000.0, 7000.0], [5.3, 5.3]) == 16 * 4096
    # And the top edge, centre row 4000.2: rows 3991 .. 4003 of [3990.2, 4010.2].
    assert lost([-3000.0, 7000.0], [4000.2, 4000.2]) == 13 * 4096
    # A track along the CCD's first row beyond its edge, centre row -10.4: rows -20.4 .. -0.4
    # hold no pixel centre of the CCD; at -10.6 row 0 is still out (-0.6), at -9.4 in.
    assert lost([-3000.0, 7000.0], [-10.6, -10.6]) == 0
    assert lost([-3000.0, 7000.0], [-9.4, -9.4]) == 4096


# --- a visit is planned alike in any file ---------------------------------------------------

def test_a_visit_plans_the_same_whole_alone_and_in_a_job_slice(night):
    """Visit 11's rows of streaks.csv: the whole night, a CSV of visit 11 alone, and the
    second of three --job slices of three nights, visit 10 moved a day earlier and 12 a day
    later (the shells' epoch is the constellation's, not the first visit's)."""
    folder, const = night["folder"], night["const"]
    alone = write_csv(folder / "alone.csv", [night["rows"][1]])
    assert survey(alone, "-o", folder / "alone", "--constellation", const, "--no-plots") == 0
    rows = night["rows"]
    three = write_csv(folder / "three.csv", [days_later(rows[0], -1.0), rows[1],
                                             days_later(rows[2], 1.0)])
    assert survey(three, "-o", folder / "job", "--constellation", const,
                  "--no-plots", "--job", 1, "--njobs", 3) == 0
    whole = [r for r in night["streaks"] if r["observationId"] == "11"]
    assert len(whole) == 1
    assert read_csv(folder / "alone" / "streaks.csv") == whole
    assert read_csv(folder / "job" / "streaks-job1-of-3.csv") == whole
    assert night["summary"]["epoch"] == "2026-06-15T23:12:00.000000"


def test_shells_without_an_epoch_are_refused(cli, night, tmp_path):
    const = write_const(str(tmp_path), f"shells:\n  - {SHELL}\n")
    status, _, err = cli("survey", night["visits"], "-o", tmp_path / "out", "--constellation",
                         const, strict=True)
    assert status == 2 and "epoch is missing" in err
    assert not (tmp_path / "out").exists()


def test_the_sample_constellations_state_their_epoch():
    """Both sample files give the same epoch: the start of the sample June night's first
    visit (scripts/make_opsim_night.py)."""
    from inject.survey.constellation import read_constellation

    root = os.path.join(os.path.dirname(__file__), "..", "sample_fields")
    epochs = set()
    for name in ("constellation_550km.yaml", "constellation_350km.yaml"):
        with open(os.path.join(root, name)) as stream:
            assert "\nepoch: 2026-06-15T22:47:07.303388\n" in stream.read()
        epochs.add(read_constellation(os.path.join(root, name)).epoch.isot)
    assert epochs == {"2026-06-15T22:47:07.303"}


# --- provenance ------------------------------------------------------------------------------

def _sha256(path):
    with open(path, "rb") as stream:
        return hashlib.sha256(stream.read()).hexdigest()


def test_the_summary_records_what_made_it(night):
    import inject

    s = night["summary"]
    assert s["inject_version"] == inject.__version__
    assert s["visits_sha256"] == _sha256(night["visits"])
    assert s["constellation_sha256"] == {os.path.abspath(night["const"]):
                                         _sha256(night["const"])}
    assert s["pupil"] == "annulus" and s["focus_offset_um"] == 0.0 and s["satellites"] == 400
    assert s["satellites_by_source"] == {"shells[0] s": 400}
    assert s["fallbacks"] == {"seeing_default_arcsec": 0.67, "visits_default_seeing": 0,
                              "visits_model_sky": 3,
                              "visits_rotator_from": {"rotTelPos": 0, "paraAngle": 0,
                                                      "computed": 0}}


def test_the_focus_offset_reaches_each_streaks_model_and_the_summary(night, tmp_path,
                                                                    monkeypatch):
    """A constellation's ``focus_offset_um`` is in the StreakModel of each streak the plan
    finds (visit 11's one), in summary.json beside ``pupil``, and in the visit's scene that
    ``--render`` renders. The plan's models are built as given and then without the traced
    pupil, the render's scene is not planned: plumbing, not the kernel's physics."""
    from inject.camera import layout as fp
    from inject.exposure import plan as exposure_plan
    from inject.exposure.ccd import ccd_scene
    from inject.io.fits import primary_header
    from inject.streak import StreakModel
    from inject.survey import plan
    from inject.survey.render import RenderOptions, VisitJob, model_keys, visit_plan
    from inject.survey.visits import read_visits

    given = []

    def untraced(**kw):
        given.append(kw)
        return StreakModel(**{k: v for k, v in kw.items() if k not in (
            "pupil", "focus_offset_um", "field_angle_deg", "field_position_angle_deg",
            "telescope_position_angle_deg")})

    monkeypatch.setattr(plan, "StreakModel", untraced)
    const = write_const(str(tmp_path), body=f"pupil: rubin\nfocus_offset_um: -5\n"
                                            f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n")
    alone = write_csv(tmp_path / "alone.csv", [night["rows"][1]])
    assert survey(alone, "-o", tmp_path / "out", "--constellation", const, "--no-plots") == 0
    assert len(given) == 1
    assert given[0]["pupil"] == "rubin" and given[0]["focus_offset_um"] == -5.0
    # The visit has no rotTelPos: its rotator comes from its parallactic angle.
    assert given[0]["telescope_position_angle_deg"] is not None
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["pupil"] == "rubin" and s["focus_offset_um"] == -5.0
    assert s["fallbacks"]["visits_rotator_from"] == {"rotTelPos": 0, "paraAngle": 0,
                                                     "computed": 1}
    # The visit's scene of --render: its every streak's model and each CCD's FOCUSDZ.
    monkeypatch.setattr(exposure_plan, "make_plan", lambda fscene: fscene)  # no kernels traced
    [row] = read_csv(tmp_path / "out" / "streaks.csv")
    ccds = tuple(row["ccds"].split())
    job = VisitJob(read_visits(alone)[0], (row["satellite"],), ccds, 0.8, 100.0,
                   float(row["alt_deg"]), "key")
    fscene = visit_plan(const, None, model_keys(const), job, RenderOptions(stars=False))
    assert fscene.scene.pupil == "rubin" and fscene.scene.focus_offset_um == -5.0
    track = fscene.tracks[0]
    model = exposure_plan.vertex_model(fscene, 0, next(v for v in track.values if v))
    assert model.focus_offset_um == -5.0
    assert primary_header(ccd_scene(fscene, fp.ccd(ccds[0])))["FOCUSDZ"] == -5.0


def test_the_tle_files_are_recorded_and_reread_when_edited(tmp_path):
    """A TLE file's SHA-256 is in the record, and an edited TLE file is read again by a
    long-lived process (the constellation file itself unchanged)."""
    from inject.orbits.passes import Orbit
    from inject.survey.constellation import file_digests, read_constellation_once

    lines = [Orbit.circular(550.0, 53.0, 10.0 * k, 0.0, EPOCH, name=f"A{k}", satnum=k + 1)
             .tle_lines() for k in range(3)]
    tle = tmp_path / "sats.tle"
    tle.write_text("".join(f"A{k}\n{a}\n{b}\n" for k, (a, b) in enumerate(lines[:2])))
    const = write_const(str(tmp_path), "tle: sats.tle\n")
    first = read_constellation_once(const)
    assert [o.name for o in first.orbits] == ["A0", "A1"]
    assert file_digests(first)[str(tle)] == _sha256(tle)
    assert first.sources == (("tle sats.tle", 2),)
    tle.write_text("".join(f"A{k}\n{a}\n{b}\n" for k, (a, b) in enumerate(lines)))
    assert [o.name for o in read_constellation_once(const).orbits] == ["A0", "A1", "A2"]


# --- inputs refused: one line, exit 2, nothing written ----------------------------------------

def test_a_time_outside_1900_2100_is_refused_naming_the_visit(cli, night, tmp_path):
    """observationStartMJD holding a JD (2461207: the year 8597) is not a visit's time."""
    rows = [dict(night["rows"][0]), dict(night["rows"][1])]
    rows[1]["observationStartMJD"] = float(rows[1]["observationStartMJD"]) + 2400000.5
    visits = write_csv(tmp_path / "jd.csv", rows)
    status, _, err = cli("survey", visits, "-o", tmp_path / "out", "--constellation",
                         night["const"], strict=True)
    assert status == 2 and "visit 11" in err and "outside 1900-2100" in err
    assert not (tmp_path / "out").exists()


def test_a_tle_far_from_a_visit_is_refused_naming_the_visit(cli, night, tmp_path):
    from inject.orbits.passes import Orbit

    a, b = Orbit.circular(550.0, 53.0, 0.0, 0.0, "2026-03-01T00:00:00", name="OLD").tle_lines()
    (tmp_path / "old.tle").write_text(f"OLD\n{a}\n{b}\n")
    const = write_const(str(tmp_path), "tle: old.tle\n")
    status, _, err = cli("survey", night["visits"], "-o", tmp_path / "out", "--constellation",
                         const, strict=True)
    assert status == 2 and "'OLD'" in err and "visit 12" in err and "days" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("body, words", [
    (f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n  - {SHELL}\n", "'s-000-000' twice"),
    (f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n  - {SHELL.replace('name: s', 'name: t')}\n",
     "'s-000-000' and 't-000-000'"),
    ("tle: twice.tle\n", "'A0' twice"),
])
def test_a_satellite_given_twice_is_refused(cli, night, tmp_path, body, words):
    from inject.orbits.passes import Orbit

    a, b = Orbit.circular(550.0, 53.0, 0.0, 0.0, EPOCH, name="A0").tle_lines()
    (tmp_path / "twice.tle").write_text(f"A0\n{a}\n{b}\n" * 2)
    const = write_const(str(tmp_path), body)
    status, _, err = cli("survey", night["visits"], "-o", tmp_path / "out", "--constellation",
                         const, strict=True)
    assert status == 2 and words in err and "each satellite once" in err
    assert not (tmp_path / "out").exists()


def test_a_missing_constellation_file_is_called_so(cli, night, tmp_path):
    status, _, err = cli("survey", night["visits"], "-o", tmp_path / "out", "--constellation",
                         tmp_path / "none.yaml", strict=True)
    assert status == 2 and "constellation file" in err and "scene file" not in err


def test_a_visit_without_seeing_is_warned_and_counted(cli, night, tmp_path):
    rows = [dict(night["rows"][0], seeingFwhmEff=""), dict(night["rows"][1])]
    visits = write_csv(tmp_path / "v.csv", rows)
    status, _, err = cli("survey", visits, "-o", tmp_path / "out", "--constellation",
                         night["const"], "--no-plots")
    assert status == 0
    warned = [ln for ln in err.splitlines() if "seeingFwhmEff" in ln]
    assert len(warned) == 1 and "visits 10)" in warned[0] and "0.67 arcsec" in warned[0]
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["fallbacks"]["visits_default_seeing"] == 1


# --- one OUTDIR, one run ----------------------------------------------------------------------

def _two_nights(tmp_path, night):
    """Two VISITS files (visits 10 and 12, 12 a day later: two nights; visit 10 alone) and
    the constellation."""
    rows = night["rows"]
    return (write_csv(tmp_path / "a.csv", [rows[0], days_later(rows[2], 1.0)]),
            write_csv(tmp_path / "b.csv", [rows[0]]), night["const"])


def test_another_run_is_refused_before_any_work(cli, night, tmp_path, digest):
    """Slices of one run share OUTDIR; a slice of another run (other VISITS) is refused at
    once, though its files' names are free, and the first run's files are untouched."""
    a, b, const = _two_nights(tmp_path, night)
    out = tmp_path / "out"
    for job in (0, 1):
        status, _, _ = cli("survey", a, "-o", out, "--constellation", const, "--no-plots",
                           "--job", job, "--njobs", 2)
        assert status == 0
    before = sorted(os.listdir(out))
    claim = digest(out / "survey_claim.json")
    status, _, err = cli("survey", b, "-o", out, "--constellation", const, "--no-plots",
                         "--job", 0, "--njobs", 3, strict=True)
    assert status == 2 and "another survey run" in err
    assert sorted(os.listdir(out)) == before and digest(out / "survey_claim.json") == claim


def test_overwrite_leaves_only_this_runs_outputs(cli, night, tmp_path):
    """--overwrite by the same run with --no-plots: its own plots go; by another run: every
    file of the earlier run's slices, and the visits/<id> folders this run does not render."""
    a, b, const = _two_nights(tmp_path, night)
    out = tmp_path / "out"
    tables = ["nights", "streaks.csv", "summary.json", "survey_claim.json", "visits.csv"]
    plots = ["by_sun_alt.png", "by_year.png", "pixel_fraction.png", "sky_map.png",
             "streaks_per_visit.png"]
    assert cli("survey", a, "-o", out, "--constellation", const)[0] == 0
    assert sorted(os.listdir(out)) == sorted(tables + plots)
    assert cli("survey", a, "-o", out, "--constellation", const, "--no-plots",
               "--overwrite")[0] == 0
    assert sorted(os.listdir(out)) == tables
    # Sliced, another run (the slices are in its key): the whole run's files go.
    assert cli("survey", a, "-o", out, "--constellation", const, "--job", 0, "--njobs", 2,
               "--overwrite")[0] == 0
    assert sorted(os.listdir(out)) == sorted(
        ["nights", "survey_claim.json"] + [n.replace(".", "-job0-of-2.") for n in tables + plots
                                           if n not in ("nights", "survey_claim.json")])
    (out / "visits" / "12").mkdir(parents=True)  # as an earlier --render leaves it
    (out / "visits" / "12" / "R22_S11.fits").write_text("")
    assert cli("survey", b, "-o", out, "--constellation", const, "--no-plots",
               "--overwrite")[0] == 0
    assert sorted(os.listdir(out)) == sorted(tables + ["visits"])
    assert os.listdir(out / "visits") == []
    assert [r["observationId"] for r in read_csv(out / "visits.csv")] == ["10"]


# --- the plots --------------------------------------------------------------------------------

def test_the_plots_keep_their_legend_and_labels_off_the_data(night, monkeypatch, tmp_path):
    """The legend of the per-visit plots lies outside their axes; the sky map's RA and Dec
    labels too (the axes' box holds the visits)."""
    from inject.survey import outputs
    from inject.survey.visits import local_hours, read_visits

    figures = {}
    monkeypatch.setattr(outputs, "_save", lambda fig, path, overwrite: figures.__setitem__(
        os.path.basename(path), fig))
    visits = read_visits(night["visits"])
    n_streaks = np.zeros(len(visits), int)
    n_streaks[1] = 1
    outputs.write_visit_plots(outputs.output_paths(str(tmp_path)), {
        "hours": local_hours([v.mjd_tai for v in visits], LON_DEG), "n_streaks": n_streaks,
        "fraction": n_streaks * 1e-5, "band": [v.band for v in visits],
        "ra": np.array([v.ra_deg for v in visits]),
        "dec": np.array([v.dec_deg for v in visits])})
    for name in ("streaks_per_visit.png", "pixel_fraction.png"):
        fig = figures[name]
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        (ax,) = fig.axes
        box = ax.get_window_extent(renderer)
        assert not ax.get_legend().get_window_extent(renderer).overlaps(box), name
    fig = figures["sky_map.png"]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    box = ax.get_window_extent(renderer)
    labels = [t for t in ax.get_xticklabels() + ax.get_yticklabels() if t.get_text()]
    assert labels
    for label in labels:
        extent = label.get_window_extent(renderer)
        assert not (box.x0 < extent.x0 and extent.x1 < box.x1 and box.y0 < extent.y0
                    and extent.y1 < box.y1), label.get_text()


def test_getting_started_links_the_survey_guide():
    root = os.path.join(os.path.dirname(__file__), "..", "docs")
    with open(os.path.join(root, "getting-started.md")) as stream:
        assert "(guides/survey.md)" in stream.read()


def test_a_constellation_tle_error_names_the_file_line(tmp_path):
    """A bad checksum on the file's line 3 (after a name line) is reported as line 3, not as
    the TLE's 'line 2'."""
    from inject.errors import OrbitError
    from inject.orbits.passes import Orbit
    from inject.survey.constellation import read_tles

    l1, l2 = Orbit.circular(550.0, 53.0, 0.0, 0.0, EPOCH, name="A", satnum=1).tle_lines()
    path = tmp_path / "bad.tle"
    path.write_text(f"A\n{l1}\n{l2[:68]}{(int(l2[68]) + 1) % 10}\n")
    with pytest.raises(OrbitError, match=rf"^TLE file '{path}' line 3='2 .*: bad checksum"):
        read_tles(path)
