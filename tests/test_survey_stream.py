"""``inject survey`` night by night: a run stopped and rerun as typed writes the same bytes as
one that was not stopped; nights are grouped by the local date at the site, noon to noon
(counted here by hand); ``--job`` slices split the nights; the nights' Parquet tables hold the
rows of the CSV files; ``by_year`` and ``by_sun_alt`` are the hand counts of the tables."""
import importlib.util
import json
import os
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

# The same shell, satellite model, columns and file helpers as the one-night tests.
from test_survey_trust import COLUMNS, EPOCH, MODEL, SHELL, read_csv, survey, write_csv

ROOT = os.path.join(os.path.dirname(__file__), os.pardir)
#: Each night's visits: minutes after 23:12 UTC, band, aimed at a satellite.
PATTERN = ((-12.0, "g", False), (0.0, "r", True), (15.0, "i", True))
NIGHTS = 4


def _rows():
    """Four nights of three visits (June 15-18, 2026), two a night aimed at the highest
    satellite of the shell (SGP4 and astropy's frames, not the plan's)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, FieldFrame, propagate_teme, walker_shell

    orbits = walker_shell(400, 20, 1, 550.0, 53.0, EPOCH, name="s")
    rows = []
    for night in range(NIGHTS):
        for k, (minutes, band, aimed) in enumerate(PATTERN):
            t0 = Time(EPOCH, scale="utc") + (night * 1440 + minutes) * u.min
            mid = Time([t0 + 15 * u.s])
            alt_deg, az_deg = 75.0, 40.0 * night
            if aimed:
                frame = FieldFrame.build(mid, Pointing(0.0, 0.0), RUBIN)
                r, _ = propagate_teme(orbits, mid)
                _, _, alt, az = frame.to_altaz(np.einsum("tij,stj->sti", frame.teme_to_itrs, r))
                n = int(np.argmax(alt[:, 0]))
                alt_deg, az_deg = float(alt[n, 0]), float(az[n, 0])
            aim = SkyCoord(AltAz(alt=alt_deg * u.deg, az=az_deg * u.deg, obstime=mid[0],
                                 location=RUBIN.location)).icrs
            rows.append({"observationId": 100 * night + k,
                         "observationStartMJD": repr(float(t0.tai.mjd)),
                         "fieldRA": aim.ra.deg, "fieldDec": aim.dec.deg,
                         "rotSkyPos": 30.0 * k, "band": band, "visitExposureTime": 30.0,
                         "numExposures": 1, "seeingFwhmEff": 0.8})
    return rows


@pytest.fixture(scope="module")
def nights(tmp_path_factory):
    """The four nights as a CSV, their constellation, and the run of them uninterrupted."""
    folder = tmp_path_factory.mktemp("stream")
    rows = _rows()
    visits = write_csv(folder / "nights.csv", rows)
    const = os.path.join(folder, "const.yaml")
    with open(const, "w") as stream:
        stream.write(MODEL + f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n")
    whole = folder / "whole"
    assert survey(visits, "-o", whole, "--constellation", const, "--csv", "always") == 0
    return {"folder": folder, "rows": rows, "visits": visits, "const": const, "whole": whole}


def _files(folder):
    """``{relative path: bytes}`` of every file under ``folder``, summary.json without its
    timings."""
    out = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            with open(path, "rb") as stream:
                data = stream.read()
            if name == "summary.json":
                data = json.loads(data)
                data.pop("timings")
            out[os.path.relpath(path, folder)] = data
    return out


def _stopped(visits, out, const, after, *extra):
    """Run in a subprocess sent SIGINT once its manifest holds ``after`` nights."""
    # SIGINT as a terminal's Ctrl-C delivers it: a shell starts background jobs (a CI
    # runner's, `cmd &`) with SIGINT ignored, and inject keeps an ignored signal ignored.
    code = ("import os, signal, sys\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            "from inject.survey import stream\n"
            "from inject.cli.main import main\n"
            "add = stream.NightManifest.add\n"
            "def stop(self, *a, **k):\n"
            "    add(self, *a, **k)\n"
            f"    if len(self.entries) == {after}:\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "stream.NightManifest.add = stop\n"
            "sys.exit(main(sys.argv[1:]))\n")
    env = {**os.environ, "PYTHONPATH": os.path.abspath(ROOT)}
    return subprocess.run([sys.executable, "-c", code, "survey", str(visits), "-o", str(out),
                           "--constellation", str(const), "--csv", "always", *extra],
                          env=env, capture_output=True, text=True, timeout=600)


def test_the_nights_stream_some_streaks(nights):
    """The fixture is worth resuming: four nights, each of them streaked."""
    table = read_csv(nights["whole"] / "visits.csv")
    assert len(table) == 3 * NIGHTS
    streaked = {r["night"] for r in table if int(r["n_streaks"])}
    assert streaked == {"2026-06-15", "2026-06-16", "2026-06-17", "2026-06-18"}


@pytest.mark.parametrize("stops, extra", [((1, 3), ()), ((2,), ("--workers", "2"))],
                         ids=["twice", "two-workers"])
def test_a_stopped_run_resumed_writes_the_same_bytes(nights, tmp_path, stops, extra):
    """SIGINT after the 1st of 4 nights, then after the 3rd (or after the 2nd on two workers,
    resumed on two): the rerun as typed plans only the nights not done, and every file (the
    nights' Parquet files, the manifest, the CSV files, the plots, summary.json but for its
    timings) is the uninterrupted run's, byte for byte. A single stop on one worker is
    test_a_night_file_changed_is_planned_again's run."""
    out = tmp_path / "out"
    for after in stops:
        result = _stopped(nights["visits"], out, nights["const"], after, *extra)
        assert result.returncode != 0, result.stderr
        manifest = json.loads((out / "nights" / "manifest.json").read_text())
        assert len(manifest["nights"]) == after
        assert not (out / "summary.json").exists()
    assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                  "--csv", "always", *extra) == 0
    timings = json.loads((out / "summary.json").read_text())["timings"]
    assert timings["nights_done_before"] == stops[-1]
    assert timings["nights_planned"] == NIGHTS - stops[-1]
    resumed, whole = _files(out), _files(nights["whole"])
    assert sorted(resumed) == sorted(whole)
    for name in whole:
        assert resumed[name] == whole[name], name


def test_a_night_file_changed_is_planned_again(nights, tmp_path):
    """SIGINT after the 2nd of 4 nights, then a night's Parquet file whose SHA-256 is not the
    manifest's: it is not taken as done, and every file of the rerun is the uninterrupted
    run's, byte for byte."""
    import shutil

    out = tmp_path / "out"
    result = _stopped(nights["visits"], out, nights["const"], 2)
    assert result.returncode != 0, result.stderr
    assert len(json.loads((out / "nights" / "manifest.json").read_text())["nights"]) == 2
    assert not (out / "summary.json").exists()
    path = out / "nights" / "visits-2026-06-15.parquet"
    good = path.read_bytes()
    path.write_bytes(good[:-10])
    assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                  "--csv", "always") == 0
    assert path.read_bytes() == good
    timings = json.loads((out / "summary.json").read_text())["timings"]
    assert (timings["nights_done_before"], timings["nights_planned"]) == (1, 3)
    resumed, whole = _files(out), _files(nights["whole"])
    assert sorted(resumed) == sorted(whole)
    for name in whole:
        assert resumed[name] == whole[name], name
    shutil.rmtree(out)


# --- the night of a visit, by hand ----------------------------------------------------------

#: Rubin at 70.7494 deg W: local mean noon is 70.7494 / 15 h = 4 h 42 min 59.86 s after
#: 12:00 on the MJD's clock, 16:42:59.86.
AROUND_NOON = (("2026-06-15T16:41:00", "2026-06-14"),  # before the noon: the night before
               ("2026-06-15T16:44:00", "2026-06-15"),  # after it: the evening to come
               ("2026-06-16T04:00:00", "2026-06-15"),  # after midnight: the same night
               ("2026-06-16T16:42:50", "2026-06-15"),  # 10 s before the next noon
               ("2026-06-16T16:43:10", "2026-06-16"))  # 10 s after it


def _noon_rows():
    from astropy.time import Time

    # The times on the MJD's own clock (TAI), as the opsim column holds them.
    return [{"observationId": 7 + k, "observationStartMJD": repr(float(Time(t, scale="tai").mjd)),
             "fieldRA": 10.0 * k, "fieldDec": -30.0, "rotSkyPos": 0.0, "band": "r",
             "visitExposureTime": 30.0, "numExposures": 1, "seeingFwhmEff": 0.8}
            for k, (t, _) in enumerate(AROUND_NOON)]


def test_night_of_counts_noon_to_noon():
    from astropy.time import Time

    from inject.survey.nights import night_label, night_of

    for t, night in AROUND_NOON:
        assert night_label(night_of(Time(t, scale="tai").mjd, -70.7494)) == night, t


@pytest.mark.parametrize("kind", ["csv", "csv-shuffled", "sqlite"])
def test_visits_around_local_noon_fall_in_their_nights(nights, tmp_path, kind):
    """A CSV in time order (read in one pass), out of order (read whole) and a database
    (one ordered cursor): each visit's night in the tables and the files of nights/."""
    rows = _noon_rows()
    if kind == "csv-shuffled":
        rows = [rows[k] for k in (3, 0, 4, 2, 1)]
    if kind == "sqlite":
        path = str(tmp_path / "noon.db")
        con = sqlite3.connect(path)
        con.execute(f"CREATE TABLE observations ({', '.join(COLUMNS)})")
        con.executemany(f"INSERT INTO observations VALUES ({', '.join('?' * len(COLUMNS))})",
                        [[r[c] for c in COLUMNS] for r in rows[::-1]])
        con.commit()
        con.close()
    else:
        path = write_csv(tmp_path / "noon.csv", rows)
    out = tmp_path / "out"
    assert survey(path, "-o", out, "--constellation", nights["const"], "--no-plots") == 0
    table = read_csv(out / "visits.csv")
    assert [(int(r["observationId"]), r["night"]) for r in table] == \
        [(7 + k, night) for k, (_, night) in enumerate(AROUND_NOON)]
    assert sorted(os.listdir(out / "nights")) == [
        "manifest.json", *[f"{kind}-{n}.parquet" for kind in ("streaks", "visits")
                           for n in ("2026-06-14", "2026-06-15", "2026-06-16")]]
    manifest = json.loads((out / "nights" / "manifest.json").read_text())
    assert [(e["night"], e["visits"]) for e in manifest["nights"]] == \
        [("2026-06-14", 1), ("2026-06-15", 3), ("2026-06-16", 1)]


# --- --job by night -------------------------------------------------------------------------

def test_job_slices_split_the_nights_and_together_are_the_whole(nights, tmp_path):
    """Three slices of the four nights: slice 0 takes the 1st and 4th, 1 the 2nd, 2 the 3rd;
    their rows together are the whole run's."""
    out = tmp_path / "out"
    tables = {}
    for job in range(3):
        assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                      "--no-plots", "--job", job, "--njobs", 3) == 0
        tables[job] = (read_csv(out / f"visits-job{job}-of-3.csv"),
                       read_csv(out / f"streaks-job{job}-of-3.csv"))
    assert [sorted({r["night"] for r in tables[job][0]}) for job in range(3)] == [
        ["2026-06-15", "2026-06-18"], ["2026-06-16"], ["2026-06-17"]]
    whole_visits = read_csv(nights["whole"] / "visits.csv")
    whole_streaks = read_csv(nights["whole"] / "streaks.csv")

    def key(row):
        return (row["observationId"], row.get("satellite", ""))

    assert sorted((r for t in tables.values() for r in t[0]), key=key) == \
        sorted(whole_visits, key=key)
    assert sorted((r for t in tables.values() for r in t[1]), key=key) == \
        sorted(whole_streaks, key=key)
    assert sum(json.loads((out / f"summary-job{j}-of-3.json").read_text())["visits"]
               for j in range(3)) == len(whole_visits)


# --- Parquet and CSV ------------------------------------------------------------------------

def _same(text, value):
    """A CSV cell and a Parquet value: empty is null or NaN, numbers read back equal."""
    if text == "":
        return value is None or (isinstance(value, float) and np.isnan(value))
    if isinstance(value, str):
        return text == value
    return float(text) == value


def test_the_parquet_tables_hold_the_csv_rows(nights):
    import pyarrow.parquet as pq

    for kind in ("visits", "streaks"):
        rows = read_csv(nights["whole"] / f"{kind}.csv")
        parquet = []
        for name in sorted(os.listdir(nights["whole"] / "nights")):
            if name.startswith(kind + "-"):
                parquet += pq.read_table(nights["whole"] / "nights" / name).to_pylist()
        assert len(parquet) == len(rows) > 0, kind
        for row, value in zip(rows, parquet):
            assert list(row) == list(value), kind
            for column in row:
                assert _same(row[column], value[column]), (kind, column, row[column])


def test_csv_auto_leaves_out_the_csv_only_above_its_size(nights, tmp_path, monkeypatch):
    from inject.survey import stream

    out = tmp_path / "small"
    assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                  "--no-plots", "--csv", "auto") == 0
    assert (out / "visits.csv").exists() and (out / "streaks.csv").exists()
    monkeypatch.setattr(stream, "CSV_AUTO_VISITS", 3 * NIGHTS - 1)
    out = tmp_path / "large"
    assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                  "--no-plots", "--csv", "auto") == 0
    assert sorted(os.listdir(out)) == ["nights", "summary.json", "survey_claim.json"]
    assert json.loads((out / "summary.json").read_text())["visits"] == 3 * NIGHTS
    # By default the combined files are written whatever the run's size (the command's
    # documented outputs).
    out = tmp_path / "default"
    assert survey(nights["visits"], "-o", out, "--constellation", nights["const"],
                  "--no-plots") == 0
    assert (out / "visits.csv").exists() and (out / "streaks.csv").exists()


# --- per year, per Sun altitude -------------------------------------------------------------

def _script():
    spec = importlib.util.spec_from_file_location(
        "make_synthetic_survey", os.path.join(ROOT, "scripts", "make_synthetic_survey.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def new_year(tmp_path_factory):
    """The synthetic survey's nights of 2026-12-31 and 2027-01-01, every 5th visit, against
    Starlink's first generation."""
    folder = tmp_path_factory.mktemp("new_year")
    script = _script()
    path = str(folder / "survey.db")
    script.write_survey(path, "2026-12-31", 2, seed=3)
    con = sqlite3.connect(path)
    con.execute("DELETE FROM observations WHERE observationId % 5 != 0")
    con.commit()
    sun = dict(con.execute("SELECT observationId, sunAlt FROM observations"))
    con.close()
    out = folder / "out"
    const = os.path.join(ROOT, "sample_fields", "constellation_starlink_gen1.yaml")
    assert survey(path, "-o", out, "--constellation", const, "--no-plots") == 0
    return {"out": out, "sun": sun, "script": script,
            "visits": read_csv(out / "visits.csv"), "streaks": read_csv(out / "streaks.csv"),
            "summary": json.loads((out / "summary.json").read_text())}


def _hand(visits, streaks):
    ids = {r["observationId"] for r in visits}
    chosen = [r for r in streaks if r["observationId"] in ids]
    lost = sum(int(r["pixels_lost"]) for r in visits)
    return {"visits": len(visits), "streaks": len(chosen), "pixels_lost": lost,
            "streaked_visits": sum(int(r["n_streaks"]) > 0 for r in visits)}


def test_the_sun_altitude_is_the_almanacs(new_year):
    """sun_alt_deg against the synthetic survey's own Sun (the Astronomical Almanac's
    low-precision formulae, not astropy) within 0.02 deg."""
    for row in new_year["visits"]:
        assert float(row["sun_alt_deg"]) == pytest.approx(
            new_year["sun"][int(row["observationId"])], abs=0.02)


def test_by_year_and_by_sun_alt_are_hand_counts(new_year):
    visits, streaks, summary = new_year["visits"], new_year["streaks"], new_year["summary"]
    # The night of 2026-12-31 runs into 2027-01-01 UTC: its visits are all 2026's.
    first = [r for r in visits if r["night"] == "2026-12-31"]
    assert any(r["mjd"] and float(r["mjd"]) > 61406.0 for r in first)  # past 0h UTC Jan 1
    years = {"2026": first, "2027": [r for r in visits if r["night"] == "2027-01-01"]}
    assert len(years["2026"]) + len(years["2027"]) == len(visits)
    bins = {"-18_to_-12": [r for r in visits if -18.0 <= float(r["sun_alt_deg"]) < -12.0],
            "below_-18": [r for r in visits if float(r["sun_alt_deg"]) < -18.0]}
    assert len(bins["-18_to_-12"]) + len(bins["below_-18"]) == len(visits)
    for block, groups in (("by_year", years), ("by_sun_alt", bins)):
        assert list(summary[block]) == list(groups), block
        for name, rows in groups.items():
            assert rows, (block, name)
            got = {k: summary[block][name][k] for k in ("visits", "streaks", "pixels_lost",
                                                       "streaked_visits")}
            assert got == _hand(rows, streaks), (block, name)
    assert summary["streaks"] > 0


def test_the_per_year_and_sun_plots_are_written(nights):
    for name in ("by_year.png", "by_sun_alt.png", "sky_map.png"):
        assert (nights["whole"] / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"



def test_the_sun_bins_hold_their_lower_edges():
    from inject.survey.nights import SUN_ALT_BINS, sun_alt_bins

    names = [SUN_ALT_BINS[k][0] for k in sun_alt_bins([5.0, -12.0, -12.001, -18.0, -18.001,
                                                       -70.0])]
    assert names == ["above_-12", "above_-12", "-18_to_-12", "-18_to_-12", "below_-18",
                     "below_-18"]


def test_progress_by_whole_nights_says_each_night_that_ends_a_tenth(caplog):
    """A night's visits counted at once (the workers' progress): one line for each update
    that enters a new tenth, with its note."""
    import logging

    from inject.progress import Progress

    logger = logging.getLogger("inject.test_stream_progress")
    with caplog.at_level(logging.INFO, logger=logger.name):
        progress = Progress(100, "planning 4 nights", "visit", logger)
        for k in range(4):
            progress.update(f"{k + 1}/4 nights", n=25)
        progress.close()
    assert [r.getMessage() for r in caplog.records] == [
        f"[{25 * k}/100] planning 4 nights: {k}/4 nights" for k in range(1, 5)]


def test_nights_of_another_inject_version_are_not_taken(tmp_path):
    """A manifest's nights count as done for the same run key and inject version only."""
    from inject.survey.stream import NightManifest

    night = tmp_path / "nights" / "visits-2026-06-15.parquet"
    night.parent.mkdir()
    night.write_bytes(b"rows")
    fallbacks = {"visits_default_seeing": 0}
    NightManifest(str(tmp_path), "k", version="1.0").add(61206, 3, 1, {"visits": str(night)},
                                                         fallbacks)
    assert NightManifest(str(tmp_path), "k", version="1.0").load().done([61206]) == {61206}
    assert NightManifest(str(tmp_path), "k", version="1.1").load().done([61206]) == set()
    assert NightManifest(str(tmp_path), "other", version="1.0").load().done([61206]) == set()
    night.write_bytes(b"rowz")  # another file under the name: not done
    assert NightManifest(str(tmp_path), "k", version="1.0").load().done([61206]) == set()

