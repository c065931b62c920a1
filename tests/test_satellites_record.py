"""OUTDIR/satellites.csv: every satellite of a focal-plane run, with or without a streak."""
import csv
import json
from pathlib import Path

import pytest

from inject.cli.main import main
from inject.maskplanes import FLAG_OFF_IMAGE

ROOT = Path(__file__).resolve().parents[1]
TLE = ROOT / "sample_fields" / "example_starlink_like.tle"
SAT = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}
RAW = {"seed": 3, "band": "g", "zenith": 30, "exptime": 30, "time": "2026-06-15T23:29:45",
       "pointing": {"ra": 50.0, "dec": -30.0}, "sky": False, "stars": False, "noise": False,
       "cutout": {"nx": 64, "ny": 64}, "detectors": ["R22_S11", "R22_S12"],
       "satellites": [
           {**SAT, "height": 550, "track": {"x0_mm": 0.0, "y0_mm": -20.0, "angle": 0.0}},
           {**SAT, "height": 550, "track": {"x0_mm": 900.0, "y0_mm": 0.0, "angle": 90.0}},
           {**SAT, "orbit": {"tle": str(TLE)}},  # aimed at (151.95, -25.73): misses
       ]}


def _rows(out):
    with open(out / "satellites.csv", newline="") as stream:
        return list(csv.DictReader(stream))


def test_every_satellite_has_a_record(tmp_path, capsys):
    scene = tmp_path / "scene.yaml"
    scene.write_text(json.dumps(RAW))
    out = tmp_path / "out"
    assert main(["focalplane", str(scene), "-o", str(out), "--workers", "1",
                 "--no-mosaic"]) == 0
    err = capsys.readouterr().err
    assert "satellites[1]: renders on no CCD" in err and "misses the field" in err
    rows = _rows(out)
    assert [r["satellite"] for r in rows] == ["0", "1", "2"]
    crossing, outside, orbit = rows
    # The crossing track reaches both CCDs (R22_S11 by its row of pixels y = 0, R22_S12 by
    # the footprint's reach) and has a TRUTH row in each.
    from astropy.io import fits

    for name in crossing["ccds"].split():
        with fits.open(out / f"{name}.fits") as hdul:
            assert list(hdul["TRUTH"].data["satellite"]) == [0]
    assert crossing["ccds"] and crossing["flags"] == "0" and crossing["in_field"] == "true"
    assert crossing["source"] == "track" and crossing["sunlit"] == ""
    assert outside["ccds"] == "" and int(outside["flags"]) == FLAG_OFF_IMAGE
    assert outside["in_field"] == "false" and "reaches none" in outside["message"]
    assert orbit["source"] == "orbit" and orbit["in_field"] == "false"
    assert orbit["sunlit"] == "false" and "misses the field" in orbit["message"]
    assert int(orbit["flags"]) == FLAG_OFF_IMAGE and orbit["name"]
    with open(out / "manifest.csv", newline="") as stream:
        digest = {r["scene_sha256"] for r in csv.DictReader(stream)}
    assert {r["scene_sha256"] for r in rows} == digest  # the manifest's run
    # Another scene in the same directory: refused without --overwrite, nothing replaced.
    before = (out / "satellites.csv").read_bytes()
    scene.write_text(json.dumps({**RAW, "seed": 4}))
    assert main(["focalplane", str(scene), "-o", str(out), "--no-mosaic"]) == 2
    assert "satellites.csv: exists" in capsys.readouterr().err
    assert (out / "satellites.csv").read_bytes() == before


def test_plan_json_carries_the_same_records(capsys):
    from inject import OrbitWarning, make_plan, parse_focal_scene
    from inject.exposure.plan import satellite_records
    with pytest.warns(OrbitWarning):
        fscene = parse_focal_scene(RAW)
    records = satellite_records(make_plan(fscene))
    assert [r["n_ccds"] for r in records] == [len(r["ccds"].split()) for r in records]
    assert records[0]["n_ccds"] >= 1 and records[1]["n_ccds"] == records[2]["n_ccds"] == 0
    assert make_plan(fscene).summary()["satellites"] == records
