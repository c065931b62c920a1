"""add-streak, pass and simulate where files and options are unusual: undefined (BLANK, NaN)
pixels, VARIANCE in ADU, sky starts far from the image, warnings, output names, and VARIANCE
without noise.

The expectations are computed here from the inputs (the streak's flux per pixel times the
length that lands on defined pixels, the sky and read noise over the amplifiers' gains), not
read back from the code under test.
"""
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from inject import StreakModel
from inject.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
GAIN = 1.25
SHAPE = (80, 160)  # ny, nx
#: A horizontal streak from x = 20.5 to 120.5 along y = 40.3; columns x >= CUT are undefined.
STREAK = ["--height", "550", "--zenith", "60", "--x0", "20.5", "--y0", "40.3", "--angle", "0",
          "--track-length", "100"]
CUT = 70


def _flux_per_px(mag):
    """e- per pixel of track of the streak STREAK draws (LSST's 0.2" pixels)."""
    return StreakModel(550, 60, mag=mag).flux_per_px


def _masked_image_file(path, image_hdu):
    """IMAGE (``image_hdu``), MASK and VARIANCE typed by EXTTYPE, as afw writes them."""
    image_hdu.header["EXTTYPE"] = "IMAGE"
    image_hdu.header["GAIN"] = GAIN
    mask_header = fits.Header({"EXTTYPE": "MASK"})
    mask_header["HIERARCH MP_BAD"], mask_header["HIERARCH MP_SAT"] = 0, 1
    mask = fits.ImageHDU(np.zeros(SHAPE, np.int32), header=mask_header)
    variance = fits.ImageHDU(np.full(SHAPE, 50.0, np.float32),
                             header=fits.Header({"EXTTYPE": "VARIANCE"}))
    fits.HDUList([fits.PrimaryHDU(), image_hdu, mask, variance]).writeto(path)
    return path


# -- BLANK: undefined integer pixels ----------------------------------------------------------

BLANK_KINDS = {
    # kind: (stored dtype, BSCALE, BZERO, BLANK, compressed)
    "int16-scaled": (np.int16, 2.0, 1000.0, -32768, False),
    "int32": (np.int32, 1.0, 0.0, -999, False),
    "uint16-top": (np.int16, 1.0, 32768.0, 32767, False),  # BLANK at the type's top
    "rice-int16": (np.int16, 1.0, 0.0, -32768, True),
    "rice-int16-scaled": (np.int16, 0.5, 200.0, -32768, True),
}


def _blank_file(tmp_path, kind):
    """A MaskedImage whose integer IMAGE holds BLANK in every column x >= CUT."""
    dtype, bscale, bzero, blank, compressed = BLANK_KINDS[kind]
    stored = np.full(SHAPE, 300, dtype)
    stored[:, CUT:] = blank
    path = tmp_path / f"{kind}.fits"
    if compressed:
        hdu = fits.CompImageHDU(stored, compression_type="RICE_1")
    else:
        hdu = fits.ImageHDU(stored)
    _masked_image_file(path, hdu)
    # The stored integers and their cards as a writer of such files leaves them (astropy
    # would rescale the pixels if the cards were set before writing).
    with fits.open(path, mode="update", do_not_scale_image_data=True) as hdus:
        header = hdus[1].header
        if (bscale, bzero) != (1.0, 0.0):
            header["BSCALE"], header["BZERO"] = bscale, bzero
        header["BLANK"] = blank
    with fits.open(path, do_not_scale_image_data=True) as hdus:
        assert np.array_equal(hdus[1].data, stored)
    return path, stored, blank


@pytest.mark.parametrize("kind", sorted(BLANK_KINDS))
def test_blank_pixels_stay_blank_and_get_no_charge(tmp_path, kind):
    path, stored, blank = _blank_file(tmp_path, kind)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "4",
                 "--no-noise"]) == 0
    with fits.open(out, do_not_scale_image_data=True) as hdus:
        new = np.array(hdus[1].data)
        assert (new.dtype.kind, new.dtype.itemsize) == ("i", stored.dtype.itemsize)
        assert hdus[1].header["BLANK"] == blank
    undefined = stored == blank
    assert np.all(new[undefined] == blank)
    assert np.any(new[~undefined] != stored[~undefined])  # the streak did land
    with fits.open(out) as hdus:
        truth = Table(hdus["TRUTH"].data)
        model = hdus["STREAK_MODEL"].data
        variance = hdus[3].data
    # The streak's first CUT - 20.5 = 49.5 px lie on defined pixels: half its charge.
    expected = _flux_per_px(4) * (CUT - 20.5)
    assert truth["charge_in_image_e"][0] == pytest.approx(expected, rel=0.02)
    assert truth["flags"][0] & 2  # part of the streak is lost
    assert np.all(model[undefined] == 0)
    assert np.all(variance[undefined] == 50.0)


def test_blank_at_the_top_is_not_produced_by_clipping(tmp_path):
    """BLANK = the type's largest value: a pixel clipped there would turn undefined."""
    path, stored, blank = _blank_file(tmp_path, "uint16-top")
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "-2",
                 "--no-noise"]) == 0
    with fits.open(out, do_not_scale_image_data=True) as hdus:
        new = hdus[1].data
        sat = (hdus[2].data & 2) != 0  # MASK's SAT plane (afw's bit 1)
    defined = stored != blank
    assert np.count_nonzero(new[defined] == blank) == 0
    assert np.any(new[defined] == blank - 1) and np.all(sat[defined] == (new[defined]
                                                                          == blank - 1))


# -- VARIANCE in ADU ----------------------------------------------------------------------------

def test_adu_variance_is_electron_variance_over_gain_squared(tmp_path):
    """``units: adu`` with noise: VARIANCE (ADU^2) per amplifier = (sky + read noise^2) /
    gain^2, and the image's own scatter agrees with it."""
    gains = [1.2 + 0.25 * i for i in range(16)]  # ITL amplifiers are 509 px wide
    sky, read_noise = 900.0, 6.0
    scene = tmp_path / "adu.yaml"
    scene.write_text(
        "seed: 3\nband: g\nexptime: 30\nseeing: 0.7\nzenith: 30\n"
        f"detector: {{type: itl, nx: 1100, ny: 60, gains: {gains}, read_noise: {read_noise}}}\n"
        f"sky: {{level: {sky}}}\nstars: false\nnoise: true\nunits: adu\nsatellites: []\n")
    out = tmp_path / "adu.fits"
    assert main(["simulate", str(scene), "-o", str(out)]) == 0
    with fits.open(out) as hdus:
        image = hdus["IMAGE"].data.astype(np.float64)
        variance = hdus["VARIANCE"].data.astype(np.float64)
        assert hdus["VARIANCE"].header["BUNIT"] == "adu**2"
    for amp, columns in enumerate((slice(0, 509), slice(509, 1018), slice(1018, 1100))):
        expected = (sky + read_noise ** 2) / gains[amp] ** 2
        np.testing.assert_allclose(variance[:, columns], expected, rtol=1e-5)
        scatter = image[:, columns].var()
        n = image[:, columns].size
        # The sample variance of n Gaussian draws: relative error sqrt(2 / n) (< 0.025 here).
        assert scatter == pytest.approx(expected, rel=5 * np.sqrt(2 / n))
        assert image[:, columns].mean() == pytest.approx(sky / gains[amp], rel=1e-3)


# -- --ra0/--dec0 -------------------------------------------------------------------------------

def _afw_file(tmp_path):
    """The afw-layout Exposure of tests/test_lsst_files.py (TAN-SIP about (150, 2), 150 x 120
    px, xy0 = (100, 200)) and its IMAGE header."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from check_lsst import write_afw_exposure
    finally:
        sys.path.pop(0)
    path = write_afw_exposure(tmp_path / "calexp.fits")
    return path, fits.getheader(path, 1)


def _gnomonic_deg(ra, dec, ra0, dec0):
    """Standard coordinates (xi East, eta North), deg, of (ra, dec) about (ra0, dec0)."""
    ra, dec, ra0, dec0 = np.radians([ra, dec, ra0, dec0])
    cos_c = np.sin(dec0) * np.sin(dec) + np.cos(dec0) * np.cos(dec) * np.cos(ra - ra0)
    xi = np.cos(dec) * np.sin(ra - ra0) / cos_c
    eta = (np.cos(dec0) * np.sin(dec) - np.sin(dec0) * np.cos(dec) * np.cos(ra - ra0)) / cos_c
    return np.degrees(xi), np.degrees(eta)


def _sip_start(header, ra, dec):
    """Array pixel of (ra, dec) by the documented rule, written out: the TAN pixel, less the
    SIP distortion at the nearest point of the image (fixed point)."""
    xi, eta = _gnomonic_deg(ra, dec, header["CRVAL1"], header["CRVAL2"])
    pc = np.array([[header.get("PC1_1", 1.0), header.get("PC1_2", 0.0)],
                   [header.get("PC2_1", 0.0), header.get("PC2_2", 1.0)]])
    pc *= np.array([[header["CDELT1"]], [header["CDELT2"]]])
    centre = np.array([header["CRPIX1"] - 1, header["CRPIX2"] - 1])  # array pixels
    linear = centre + np.linalg.solve(pc, [xi, eta])

    def distortion(p):
        u, v = p - centre
        return np.array([sum(header.get(f"{ab}_{i}_{j}", 0.0) * u ** i * v ** j
                             for i in range(3) for j in range(3)) for ab in "AB"])
    high = np.array([header["NAXIS1"] - 0.5, header["NAXIS2"] - 0.5])
    x = linear
    for _ in range(200):
        x = linear - distortion(np.clip(x, -0.5, high))
    return x


def test_ra_dec_far_off_a_sip_image(tmp_path):
    """5 deg off a TAN-SIP image (astropy's inverse diverges there): the start by the rule, and
    a long streak from it reaches the image."""
    path, header = _afw_file(tmp_path)
    # 5 deg East of the reference point, 30 rows below it: x far to the left of the image.
    ra = 155.0
    dec = float(np.degrees(np.arctan(np.tan(np.radians(2.0)) * np.cos(np.radians(5.0)))))
    dec -= 30 * 5.5e-5
    x, y = _sip_start(header, ra, dec)
    assert x < -9e4 and 0 < y < header["NAXIS2"] - 1
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), "--height", "550", "--zenith", "60",
                 "--mag", "7", "--ra0", repr(ra), "--dec0", repr(dec), "--angle", "0",
                 "--track-length", str(-x + 100), "--no-noise"]) == 0
    truth = Table.read(out, hdu="TRUTH")
    # TRUTH describes the part on the image (grown by the reach): its far end is the start
    # plus the track's length, and its row the start's.
    assert truth["x1"][0] == pytest.approx(x + (-x + 100), abs=1e-3)
    assert truth["y0"][0] == pytest.approx(y, abs=1e-3)
    assert truth["y1"][0] == pytest.approx(y, abs=1e-3)
    assert x < truth["x0"][0] < -0.5
    assert truth["charge_in_image_e"][0] > 0


@pytest.mark.parametrize("extra, words", [
    (["--ra0", "150"], "give both"),
    (["--dec0", "2"], "give both"),
    (["--ra0", "240.5", "--dec0", "2"], "90.43 deg from"),  # beyond the TAN hemisphere
    (["--ra0", "330", "--dec0", "-2"], "180 deg from"),    # the opposite point
])
def test_ra_dec_refused_in_one_line(tmp_path, capsys, extra, words):
    path, _ = _afw_file(tmp_path)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), "--height", "550", "--mag", "7",
                 *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("inject add-streak: error: --ra0/--dec0") and err.count("\n") == 1
    assert words in err
    assert not out.exists()


# -- warnings -----------------------------------------------------------------------------------

PASS_ARGS = ["--exptime", "10", "--ra", "151.95", "--dec", "-25.73"]
ORBIT = "height=550,inclination=53,raan=208.851,mean_anomaly=321.2313"


def _stderr_lines(*args):
    """Exit status and stderr lines of ``inject ARGS`` in a fresh interpreter (as typed: no
    test harness recording the warnings in its place)."""
    code = "import sys; from inject.cli.main import main; sys.exit(main(sys.argv[1:]))"
    run = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                         cwd=ROOT)
    lines = run.stderr.splitlines()
    for line in lines:  # one line each, no path or source line of the library that warned
        assert line.startswith(f"inject {args[0]}: "), line
        assert ".py:" not in line and "site-packages" not in line
    assert len(lines) == len(set(lines)), "a warning printed twice"
    return run.returncode, lines


def test_time_beyond_the_tables_warns_in_single_lines():
    status, lines = _stderr_lines("pass", "--orbit", ORBIT, "--time", "2100-06-15T23:29:45",
                                  *PASS_ARGS)
    assert status == 0
    iers = [line for line in lines if "beyond the bundled IERS table" in line]
    assert len(iers) == 1 and iers[0].startswith("inject pass: warning: time 2100-06-15")
    assert not any("polar motion" in line and "IERS table" not in line for line in lines)
    # Then an error: the warnings before it are single lines too.
    status, lines = _stderr_lines("pass", "--tle", "sample_fields/example_starlink_like.tle",
                                  "--time", "2100-06-15T23:29:45", *PASS_ARGS)
    assert status == 2
    assert lines[-1].startswith("inject pass: error: orbit") and "days from" in lines[-1]
    assert len(lines) > 1
    assert all(line.startswith("inject pass: warning: ") for line in lines[:-1])


# -- NaN pixels ---------------------------------------------------------------------------------

def _float_file(tmp_path, image):
    return _masked_image_file(tmp_path / "float.fits", fits.ImageHDU(image.astype(np.float32)))


def test_nan_pixels_take_no_charge(tmp_path):
    image = np.full(SHAPE, 100.0)
    image[:, CUT:] = np.nan
    path = _float_file(tmp_path, image)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "6",
                 "--no-noise"]) == 0
    with fits.open(out) as hdus:
        truth = Table(hdus["TRUTH"].data)
        model = hdus["STREAK_MODEL"].data
        new = hdus[1].data
    assert np.all(np.isnan(new[:, CUT:])) and np.all(model[:, CUT:] == 0)
    # Only the 49.5 px of the streak before column CUT land on pixels that hold a value.
    assert truth["charge_in_image_e"][0] == pytest.approx(_flux_per_px(6) * (CUT - 20.5),
                                                          rel=0.02)
    assert truth["flags"][0] & 2
    # The image gained what TRUTH says (electrons over the gain), nothing more.
    added = np.nansum(new.astype(np.float64)) - np.nansum(image)
    assert added * GAIN == pytest.approx(truth["charge_in_image_e"][0], rel=1e-4)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # numpy's "Mean of empty slice", ...
@pytest.mark.parametrize("fill", [np.nan, np.inf])
def test_image_without_usable_pixels_is_refused(tmp_path, capsys, fill):
    path = _float_file(tmp_path, np.full(SHAPE, fill))
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "6"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("inject add-streak: error: ") and err.count("\n") == 1
    assert "float.fits" in err and "no usable pixel" in err
    assert not out.exists()


# -- output formats follow their names ----------------------------------------------------------

#: The first bytes of each format, from its specification.
MAGIC = {"svg": b"<?xml", "pdf": b"%PDF-", "jpg": b"\xff\xd8\xff", "png": b"\x89PNG\r\n\x1a\n"}
EXAMPLE_PASS = ["--tle", str(ROOT / "sample_fields/example_starlink_like.tle"), "--time",
                "2026-06-15T23:29:45", "--exptime", "30", "--ra", "151.95", "--dec", "-25.73"]


@pytest.mark.parametrize("ext", sorted(MAGIC))
def test_pass_plot_is_written_in_the_format_its_name_says(tmp_path, ext):
    out = tmp_path / f"pass.{ext}"
    assert main(["pass", *EXAMPLE_PASS, "--plot", str(out)]) == 0
    assert out.read_bytes().startswith(MAGIC[ext])


@pytest.mark.parametrize("name", ["pass.fits", "pass.csv", "pass.json"])
def test_pass_plot_refuses_data_names(tmp_path, capsys, name):
    out = tmp_path / name
    assert main(["pass", *EXAMPLE_PASS, "--plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("inject pass: error: ") and err.count("\n") == 1
    assert "picture" in err and not out.exists()


@pytest.mark.parametrize("name", ["out.png", "out.jpg", "out.svg", "out.csv", "out"])
def test_add_streak_output_must_be_a_fits_name(tmp_path, capsys, name):
    path = _float_file(tmp_path, np.full(SHAPE, 100.0))
    out = tmp_path / name
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "6"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("inject add-streak: error: ") and err.count("\n") == 1
    assert ".fits" in err and not out.exists()


@pytest.mark.parametrize("name, magic", [("out.fits", b"SIMPLE  ="), ("out.FIT", b"SIMPLE  ="),
                                         ("out.fits.gz", b"\x1f\x8b"), ("out.fz", b"SIMPLE  =")])
def test_add_streak_fits_names(tmp_path, name, magic):
    path = _float_file(tmp_path, np.full(SHAPE, 100.0))
    out = tmp_path / name
    assert main(["add-streak", str(path), "-o", str(out), *STREAK, "--mag", "6"]) == 0
    assert out.read_bytes().startswith(magic)
    with fits.open(out) as hdus:
        assert "TRUTH" in hdus


def test_simulate_output_must_be_a_fits_name(tmp_path, capsys):
    scene = tmp_path / "s.yaml"
    scene.write_text("detector: {type: itl, nx: 64, ny: 64}\nstars: false\nsatellites: []\n")
    out = tmp_path / "out.png"
    assert main(["simulate", str(scene), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("inject simulate: error: ") and err.count("\n") == 1
    assert not out.exists()


# -- VARIANCE with and without noise ------------------------------------------------------------

AFW_STREAK = ["--height", "550", "--zenith", "60", "--mag", "7", "--x0", "30", "--y0", "40",
              "--angle", "20", "--track-length", "80"]


def test_no_noise_still_adds_the_model_variance(tmp_path):
    """As LSST's source_injection (inject_variance on, add_noise off): VARIANCE (ADU^2) grows
    by the charge (e-) over gain^2, i.e. by the image's increase (ADU) over the gain."""
    path, _ = _afw_file(tmp_path)
    gain = fits.getheader(path, 0)["GAIN"]  # afw writes it in the primary header
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *AFW_STREAK, "--no-noise"]) == 0
    with fits.open(path) as old, fits.open(out) as new:
        d_image = new[1].data.astype(np.float64) - old[1].data
        d_variance = new[3].data.astype(np.float64) - old[3].data
    # float32 storage: ~500 ADU images and ~64 ADU^2 variances round at 3e-5 and 4e-6.
    np.testing.assert_allclose(d_variance, d_image / gain, atol=1e-4)
    # The 80 px streak lies on the 150 x 120 image, 30 px from its edge at most: its charge is
    # flux per px x length, less the seeing wings beyond the edges (~1%).
    charge = d_variance.sum() * gain ** 2
    expected = _flux_per_px(7) * 80
    assert 0.97 * expected < charge < expected * (1 + 1e-4)


@pytest.mark.parametrize("noise", [[], ["--no-noise"]])
def test_no_variance_leaves_variance_as_it_was(tmp_path, noise):
    path, _ = _afw_file(tmp_path)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), *AFW_STREAK, *noise,
                 "--no-variance"]) == 0
    with fits.open(path) as old, fits.open(out) as new:
        assert np.array_equal(new[3].data.view(np.uint32), old[3].data.view(np.uint32))
        assert np.any(new[1].data != old[1].data)  # the streak is in the image


def test_compressed_files_written_at_different_times_have_the_same_bytes(tmp_path, monkeypatch):
    """A GZIP_2 tile and a gzipped file carry no time of writing: the same data written with
    the clock a day apart give the same bytes, and read back as the data."""
    import gzip
    import time

    import numpy as np
    from astropy.io import fits

    from inject.io.reader import read_exposure

    data = np.random.default_rng(3).normal(size=(40, 30)).astype(np.float32)
    written = []
    for k, clock in enumerate((1.0e9, 1.0e9 + 86400.0)):
        monkeypatch.setattr(time, "time", lambda clock=clock: clock)
        path = tmp_path / f"tiles{k}.fits"
        fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(
            data, compression_type="GZIP_2", quantize_level=0.0)]).writeto(path)
        exposure = read_exposure(path)
        exposure.write(tmp_path / f"whole{k}.fits.gz")
        written.append(((tmp_path / f"tiles{k}.fits").read_bytes(),
                        (tmp_path / f"whole{k}.fits.gz").read_bytes()))
    assert written[0] == written[1]
    with fits.open(tmp_path / "tiles1.fits") as hdus:
        assert hdus[1].data.tobytes() == data.tobytes()
    with fits.open(io.BytesIO(gzip.decompress(written[1][1]))) as hdus:
        assert hdus[1].data.tobytes() == data.tobytes()
