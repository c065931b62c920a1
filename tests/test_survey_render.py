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


def test_the_summary_records_the_workers_and_why(rendered):
    sizing = rendered["summary"]["render"]["sizing"]
    assert sizing["workers"] == 1 and sizing["why"].startswith("bound by --workers; the job has ")
    assert sizing["cpus"] >= 1 and sizing["memory_why"]


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
    (["--verify"], "--verify"), (["--no-lock"], "--no-lock"),
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


# --- the rendered files' time ---------------------------------------------------------------

def test_the_rendered_time_cards_are_the_visits_tai_start(rendered):
    """observationStartMJD is TAI: DATE-OBS/MJD-OBS are that instant in TAI (TIMESYS), and
    DATE-AVG/DATE-END half and all the open-shutter time later (astropy's own conversion; the
    TAI value read as UTC would be 37 s late)."""
    from astropy.io import fits
    from astropy.time import Time, TimeDelta

    con = sqlite3.connect(rendered["db"])
    (mjd_tai,) = con.execute("SELECT observationStartMJD FROM observations WHERE "
                             "observationId = 1").fetchone()
    con.close()
    start = Time(mjd_tai, format="mjd", scale="tai")
    # The database was written from this UTC start: TAI - UTC = 37 s in 2026.
    assert (start - Time(START, scale="utc")).sec == pytest.approx(0.0, abs=1e-4)
    assert (Time(start.isot, scale="utc") - Time(START, scale="utc")).sec == \
        pytest.approx(37.0, abs=1e-3)
    folder = rendered["out"] / "visits" / "1"
    name = next(p for p in sorted(os.listdir(folder)) if p.endswith(".fits"))
    header = fits.getheader(folder / name, 0)
    assert header["TIMESYS"] == "TAI"
    for key, offset in (("OBS", 0.0), ("AVG", EXPTIME / 2), ("END", EXPTIME)):
        when = start + TimeDelta(offset, format="sec")
        assert (Time(header[f"DATE-{key}"], scale="tai") - when).sec == \
            pytest.approx(0.0, abs=1e-3), key
        assert (header[f"MJD-{key}"] - when.mjd) * 86400 == pytest.approx(0.0, abs=1e-3), key


# --- a cut-out's box and the plan's pixels in it --------------------------------------------

def _track(ccd, xs_px, ys_px):
    """A FocalTrack (mm) through pixel points of ``ccd``."""
    from inject.trajectory import FocalTrack

    xs, ys = ccd.pixel_to_focal(np.asarray(xs_px, float), np.asarray(ys_px, float))
    return FocalTrack("polyline", tuple(map(float, xs)), tuple(map(float, ys)),
                      ({},) * len(xs_px), 0.0)


@pytest.mark.parametrize("box, expected", [
    # A horizontal mask 20 px wide about y = 1000.25 takes rows 991..1010 (centres inside).
    ((100, 995, 300, 50), 16 * 300),    # the box's first row cuts it: rows 995..1010
    ((100, 980, 300, 20), 9 * 300),     # its last row: rows 991..999
    ((100, 991, 300, 20), 20 * 300),    # exactly its rows
    ((4000, 900, 96, 500), 20 * 96),    # the CCD's last 96 columns
])
def test_planned_pixels_in_a_box_of_a_horizontal_mask(box, expected):
    from inject.camera import layout as fp
    from inject.survey.compare import planned_pixels

    ccd = fp.ccd("R22_S11")  # 4096 x 4004
    track = _track(ccd, [-1000.0, 6000.0], [1000.25, 1000.25])
    assert planned_pixels(track, 20.0, ccd, box) == expected
    assert planned_pixels(track, 20.0, ccd, None) == 20 * 4096


@pytest.mark.parametrize("box, expected", [
    ((900, 1000, 300, 100), 14 * 100),  # every row of the box holds 14 of the band's pixels
    ((900, 1099, 300, 1), 14),
    # The box's first column cuts rows 1000..1006, which lose 7, 6, ..., 1 columns left of it.
    ((1000, 1000, 300, 100), 14 * 100 - (7 + 6 + 5 + 4 + 3 + 2 + 1)),
])
def test_planned_pixels_in_a_box_of_a_diagonal_mask(box, expected):
    """A mask 10 px wide about y = x + 0.5: on row y, the pixel centres within 5 px of the
    line are those within 5 sqrt 2 = 7.07 px of it along x, columns y - 7 .. y + 6 (14)."""
    from inject.camera import layout as fp
    from inject.survey.compare import planned_pixels

    ccd = fp.ccd("R22_S11")
    track = _track(ccd, [-500.0, 3400.0], [-499.5, 3400.5])
    assert planned_pixels(track, 10.0, ccd, box) == expected


@pytest.mark.parametrize("ends, box", [
    ((1000.0, 1500.0, 2000.0, 2500.0), (1500 - 512, 2000 - 512, 1024, 1024)),
    # Clipped to the CCD first (its edge at x = -0.5): the middle is at x = 1499.75.
    ((-1000.0, 1000.0, 3000.0, 1000.0), (988, 1000 - 512, 1024, 1024)),
    ((100.0, 200.0, 900.0, 200.0), (0, 0, 1024, 1024)),          # held inside at the corner
    ((3900.0, 3950.0, 4100.0, 3950.0), (4096 - 1024, 4004 - 1024, 1024, 1024)),
])
def test_a_cut_out_box_is_centred_on_its_streak_and_held_inside_the_ccd(ends, box):
    from types import SimpleNamespace

    from inject.camera import layout as fp
    from inject.exposure.ccd import cutout_box

    ccd = fp.ccd("R22_S11")  # 4096 x 4004
    assert cutout_box(ccd, [SimpleNamespace(ends=ends)], 1024) == box
    assert cutout_box(ccd, [], 5000) == (0, 0, 4096, 4004)
