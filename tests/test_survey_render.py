"""``inject survey --render``: the streaked CCDs rendered, compressed, masked and measured.

A 2-visit night and one satellite aimed (``inject.orbits.passes.aimed_orbit``) at the first
visit's boresight in twilight; the second visit, ten minutes later, sees nothing. The
measured FWHM is checked against the plan's model, the files against astropy's reading and
the quantisation noise against its closed form (a uniform error over a step of a tenth of the
noise: ``1 / (10 sqrt 12)``), and a rerun against the manifest (nothing rendered twice).
"""
import csv
import json
import math
import os
import sqlite3

import numpy as np
import pytest

START = "2026-06-15T23:12:00"
EXPTIME = 2.0  # s: the track crosses ~1.2 deg of the field (9 CCDs)
ALT, AZ = 62.0, 200.0
CUTOUT = 384


def _night(folder):
    """The TLE of a satellite over (ALT, AZ) at the first visit's middle, the constellation
    file, and the opsim database of the two visits (the first pointed there)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time, TimeDelta

    from inject.orbits.passes import RUBIN, aimed_orbit

    start = Time(START, scale="utc")
    mid = start + TimeDelta(EXPTIME / 2, format="sec")
    orbit = aimed_orbit(mid, ALT, AZ, height_km=550.0, inclination_deg=53.0, name="AIMED")
    (folder / "sat.tle").write_text("AIMED\n" + "\n".join(orbit.tle_lines()) + "\n")
    (folder / "const.yaml").write_text("shape: {type: box, length: 7.25, width: 2.65}\n"
                                       "mag: 5.0\nref_range: 550\ntle: sat.tle\n")
    boresight = SkyCoord(AltAz(alt=ALT * u.deg, az=AZ * u.deg, obstime=mid,
                               location=RUBIN.location)).icrs
    rows = [(k + 1, (start + TimeDelta(600.0 * k, format="sec")).tai.mjd, boresight.ra.deg,
             boresight.dec.deg, 20.0, "r", EXPTIME, 1, 0.8) for k in range(2)]
    db = folder / "night.db"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE observations (observationId INTEGER, observationStartMJD REAL, "
                "fieldRA REAL, fieldDec REAL, rotSkyPos REAL, band TEXT, "
                "visitExposureTime REAL, numExposures INTEGER, seeingFwhmEff REAL)")
    con.executemany("INSERT INTO observations VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", rows)
    con.commit()
    con.close()
    return db, folder / "const.yaml"


def _read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def _run(db, const, out, *extra):
    from inject.cli.main import main

    return main(["survey", str(db), "-o", str(out), "--constellation", str(const),
                 "--no-plots", "--render", "--cutouts", "--cutout-size", str(CUTOUT),
                 "--workers", "1", *extra])


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("render")
    db, const = _night(folder)
    out = folder / "out"
    assert _run(db, const, out) == 0
    return {"db": db, "const": const, "out": out,
            "streaks": _read_csv(out / "streaks.csv"),
            "summary": json.loads((out / "summary.json").read_text())}


def test_the_streaked_ccds_are_rendered_under_their_visit(rendered):
    (row,) = rendered["streaks"]
    ccds = row["ccds"].split()
    assert row["observationId"] == "1" and len(ccds) >= 5
    folder = rendered["out"] / "visits" / "1"
    assert sorted(p for p in os.listdir(folder) if p.endswith(".fits")) == \
        sorted(f"{c}.fits" for c in ccds)
    assert not (rendered["out"] / "visits" / "2").exists()  # no streak, nothing rendered
    assert row["rendered_ccds"] == str(len(ccds))


def test_the_measured_fwhm_is_the_planned_one(rendered):
    """A bright streak (peak ~9,700 e-/px against ~12 e- of noise): the masker's FWHM within
    2% of the model's, found on every CCD it crosses."""
    (row,) = rendered["streaks"]
    assert float(row["peak_e_per_px"]) > 1000
    assert row["found_ccds"] == row["rendered_ccds"]
    assert float(row["measured_fwhm_arcsec"]) == pytest.approx(float(row["fwhm_arcsec"]),
                                                               rel=0.02)


def test_the_measured_mask_and_pixels_are_near_the_planned_ones(rendered):
    """The masker's sb width at 1 sigma against the plan's (the same rule on the model's
    profile) within 10%, and the pixels its masks take on the cut-outs against the plan's
    mask on the same pixels within 10%."""
    (row,) = rendered["streaks"]
    assert float(row["measured_mask_width_px"]) == pytest.approx(float(row["mask_width_px"]),
                                                                 rel=0.10)
    planned = int(row["planned_pixels_rendered"])
    # Each cut-out holds a chord of about its side: the planned pixels are about
    # CCDs x side x width.
    assert 0.5 < planned / (int(row["rendered_ccds"]) * CUTOUT * float(row["mask_width_px"])) \
        < 1.5
    assert int(row["measured_pixels_lost"]) == pytest.approx(planned, rel=0.10)
    render = rendered["summary"]["render"]
    assert render["ccds"] == int(row["rendered_ccds"]) and render["ccds_failed"] == 0
    assert render["compression"] == "lossless" and 0 < render["size_ratio"] < 1


def test_the_compressed_files_read_back_in_astropy_with_their_cut_out_origin(rendered):
    from astropy.io import fits
    from astropy.wcs import WCS

    from inject.camera import layout as fp
    from inject.camera.wcs import Pointing, ccd_wcs
    from inject.exposure.runner import read_manifest, sha256_file

    folder = rendered["out"] / "visits" / "1"
    manifest = read_manifest(folder)
    visit = _read_csv(rendered["out"] / "visits.csv")[0]
    pointing = Pointing(float(visit["fieldRA"]), float(visit["fieldDec"]),
                        float(visit["rotSkyPos"]))
    for name, row in manifest.items():
        path = folder / row["file"]
        assert row["status"] == "done" and row["sha256"] == sha256_file(path)
        box = json.loads((folder / f"{name}.mask.json").read_text())["box"]
        with fits.open(path) as hdus:
            assert [h.name for h in hdus] == ["PRIMARY", "IMAGE", "MASK", "VARIANCE",
                                              "STREAK_MODEL", "TRUTH", "TRUTH_VERTICES"]
            assert all(isinstance(hdus[k], fits.CompImageHDU) for k in range(1, 5))
            image = hdus["IMAGE"]
            assert image.data.shape == (CUTOUT, CUTOUT)
            assert (-image.header["LTV1"], -image.header["LTV2"]) == tuple(box[:2])
            # The cut-out's WCS is the whole CCD's, moved by its origin.
            sky = WCS(image.header).pixel_to_world_values(10.0, 20.0)
        whole = ccd_wcs(fp.ccd(name), pointing).pixel_to_world_values(box[0] + 10.0,
                                                                      box[1] + 20.0)
        assert np.allclose(sky, whole, atol=1e-9)


def test_a_resumed_run_renders_only_what_is_missing(rendered, tmp_path, capsys):
    """A run stopped before its last CCD and its tables: the rerun renders that CCD alone;
    the others' files are not touched."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(rendered["out"], out)
    folder = out / "visits" / "1"
    names = sorted(p for p in os.listdir(folder) if p.endswith(".fits"))
    (folder / names[-1]).unlink()
    for name in ("streaks.csv", "visits.csv", "summary.json"):
        (out / name).unlink()
    before = {n: os.stat(folder / n).st_mtime_ns for n in names[:-1]}
    capsys.readouterr()
    assert _run(rendered["db"], rendered["const"], out) == 0
    err = capsys.readouterr().err
    assert f"1 CCDs rendered, {len(names) - 1} already done, 0 failed" in err
    assert {n: os.stat(folder / n).st_mtime_ns for n in names[:-1]} == before
    assert (folder / names[-1]).exists()
    assert _read_csv(out / "streaks.csv") == rendered["streaks"]


def test_other_render_options_are_refused_over_a_run_without_overwrite(rendered, tmp_path,
                                                                       capsys):
    import shutil

    out = tmp_path / "out"
    shutil.copytree(rendered["out"], out)
    for name in ("streaks.csv", "visits.csv", "summary.json"):
        (out / name).unlink()
    assert _run(rendered["db"], rendered["const"], out, "--compression", "lossy") == 2
    assert "pass --overwrite" in capsys.readouterr().err


@pytest.mark.parametrize("argv, words", [
    (["--cutouts"], "--cutouts"), (["--compression", "lossy"], "--compression"),
    (["--render", "--cutout-size", "64"], "only with --cutouts"),
    (["--render", "--cutouts", "--cutout-size", "4"], "must be >= 16"),
])
def test_render_options_go_with_render(cli, tmp_path, argv, words):
    db, const = _night(tmp_path)
    status, _, err = cli("survey", db, "-o", tmp_path / "out", "--constellation", const,
                         *argv, strict=True)
    assert status == 2 and words in err
    assert not (tmp_path / "out").exists()


# --- compression of a CCD file --------------------------------------------------------------

@pytest.fixture(scope="module")
def small_ccd():
    from inject.config import parse_scene
    from inject.scene import simulate

    scene = parse_scene({"detector": {"type": "e2v", "nx": 600, "ny": 500}, "satellites": [{
        "height": 550.0, "phi": 90.0, "shape": {"type": "box", "length": 7.25, "width": 2.65},
        "mag": 5.0, "ref_range": 550.0, "track": {"x0": 30.0, "y0": 20.0, "angle": 33.0}}]})
    return scene, simulate(scene)


def _planes(path):
    from astropy.io import fits

    with fits.open(path) as hdus:
        return {n: np.array(hdus[n].data) for n in ("IMAGE", "MASK", "VARIANCE",
                                                    "STREAK_MODEL")}


def test_lossless_files_read_back_equal(small_ccd, tmp_path):
    from inject.io.fits import write_exposure

    scene, result = small_ccd
    path = tmp_path / "ccd.fits"
    write_exposure(path, scene, result, 1.0, compression="lossless")
    planes = _planes(path)
    assert np.array_equal(planes["IMAGE"], result.image)
    assert np.array_equal(planes["MASK"], result.mask)
    assert np.array_equal(planes["VARIANCE"], result.variance)
    # The model is written as float32, as a plain file has it.
    assert np.array_equal(planes["STREAK_MODEL"], result.streak_model.astype(np.float32))
    assert os.path.getsize(path) < 0.8 * 16 * 600 * 500


def test_lossy_files_add_the_quantisation_noise_of_a_tenth_of_sigma(small_ccd, tmp_path):
    """IMAGE quantised to steps of sigma / 10 with dithering: the error is uniform over a
    step, its rms sigma / (10 sqrt 12) = 0.0289 sigma (measured on the sky's pixels, where the
    noise cfitsio estimates per tile is the image's); MASK and the model stay exact."""
    from inject.io.fits import LOSSY_NOISE, write_exposure

    scene, result = small_ccd
    path = tmp_path / "ccd.fits"
    write_exposure(path, scene, result, 1.0, compression="lossy")
    planes = _planes(path)
    assert np.array_equal(planes["MASK"], result.mask)
    assert np.array_equal(planes["STREAK_MODEL"], result.streak_model.astype(np.float32))
    sky = result.streak_model == 0
    error = (planes["IMAGE"] - result.image)[sky]
    sigma = np.sqrt(np.median(result.variance))
    assert LOSSY_NOISE == pytest.approx(1 / (10 * math.sqrt(12)))
    assert np.sqrt(np.mean(error ** 2)) / sigma == pytest.approx(LOSSY_NOISE, rel=0.15)
    assert abs(np.mean(error)) < 0.01 * sigma  # dithering leaves no bias
