"""`inject add-streak`: injection into a user's FITS image, which is never modified."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from inject import StreakModel, pointing_wcs
from inject.cli.main import main

ARGS = ["--height", "550", "--zenith", "70", "--mag", "8", "--x0", "20.5", "--y0", "60.2",
        "--angle", "15", "--track-length", "100"]


@pytest.fixture
def plain_image(tmp_path):
    """A bare 2-D primary HDU in ADU with a GAIN key and a WCS."""
    rng = np.random.default_rng(5)
    data = (1000 + rng.normal(0, 10, (200, 240))).astype(">f4")
    header = pointing_wcs({"ra": 10.0, "dec": -5.0}, data.shape, 0.2).to_header()
    header["GAIN"] = 1.6
    path = tmp_path / "plain.fits"
    fits.PrimaryHDU(data, header=header).writeto(path)
    return path


@pytest.fixture
def lsst_image(tmp_path):
    rng = np.random.default_rng(6)
    image = rng.normal(0, 20, (150, 160)).astype(np.float32)
    mask_header = fits.Header()
    mask_header["HIERARCH MP_BAD"] = 0
    mask_header["HIERARCH MP_SAT"] = 1
    hdus = fits.HDUList([fits.PrimaryHDU(),
                         fits.ImageHDU(image, name="IMAGE",
                                       header=fits.Header({"BUNIT": "electron"})),
                         fits.ImageHDU(np.zeros(image.shape, np.int32), header=mask_header,
                                       name="MASK"),
                         fits.ImageHDU(np.full(image.shape, 400.0, np.float32), name="VARIANCE")])
    path = tmp_path / "lsst.fits"
    hdus.writeto(path)
    return path


def test_plain_image_in_adu(plain_image, tmp_path, digest):
    before = digest(plain_image)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(plain_image), "-o", str(out), *ARGS, "--no-noise"]) == 0
    assert digest(plain_image) == before
    original = fits.getdata(plain_image).astype(np.float64)
    with fits.open(out) as hdus:
        added = hdus[0].data.astype(np.float64) - original
        model = hdus["STREAK_MODEL"].data.astype(np.float64)
        truth = Table(hdus["TRUTH"].data)
    expected = StreakModel(550, 70, mag=8).flux_per_px * 100
    # The seeing wings reach past the 200 x 240 image's edges: a little charge misses it.
    assert expected * (1 - 1e-3) < model.sum() < expected
    # Added in ADU: electrons divided by the header gain (float32 rounding of ~1000 ADU pixels).
    np.testing.assert_allclose(added, model / 1.6, atol=2e-4 * 1000)
    assert truth["charge_in_image_e"][0] == pytest.approx(model.sum(), rel=1e-6)


def test_poisson_noise_only_on_injected_charge(plain_image, tmp_path):
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(plain_image), "-o", str(out), *ARGS, "--seed", "4"]) == 0
    original = fits.getdata(plain_image).astype(np.float64)
    with fits.open(out) as hdus:
        added_e = (hdus[0].data.astype(np.float64) - original) * 1.6
        model = hdus["STREAK_MODEL"].data.astype(np.float64)
    bright = model > 200
    residual = (added_e - model)[bright] / np.sqrt(model[bright])
    assert abs(residual.mean()) < 0.1 and 0.9 < residual.std() < 1.1
    assert np.all(added_e[model == 0] == pytest.approx(0, abs=0.1 * 1.6))


def test_ra_dec_start_uses_wcs(plain_image, tmp_path):
    out = tmp_path / "out.fits"
    args = [a for a in ARGS]
    i = args.index("--x0")
    del args[i:i + 4]
    assert main(["add-streak", str(plain_image), "-o", str(out), *args,
                 "--ra0", "10.0", "--dec0", "-5.0", "--no-noise"]) == 0
    truth = Table.read(out, hdu="TRUTH")
    assert truth["x0"][0] == pytest.approx(119.5, abs=1e-6)
    assert truth["y0"][0] == pytest.approx(99.5, abs=1e-6)


def test_lsst_file_updates_variance_and_mask(lsst_image, tmp_path):
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(lsst_image), "-o", str(out), *ARGS]) == 0
    with fits.open(out) as hdus:
        model = hdus["STREAK_MODEL"].data.astype(np.float64)
        np.testing.assert_allclose(hdus["VARIANCE"].data, 400.0 + model, rtol=1e-6)
        bit = hdus["MASK"].header["MP_STREAK"]
        assert bit not in (0, 1)
        streak = (hdus["MASK"].data & (1 << bit)) != 0
        assert streak.any()
        assert np.all(model[streak] > 20.0) and np.all(model[~streak] <= 20.0)


@pytest.mark.parametrize("content", [b"", b"SIMPLE  =                    T" + b" " * 50,
                                     b"garbage" * 100])
def test_unreadable_input(tmp_path, capsys, content):
    bad = tmp_path / "bad.fits"
    bad.write_bytes(content)
    assert main(["add-streak", str(bad), "-o", str(tmp_path / "o.fits"), *ARGS]) == 2
    err = capsys.readouterr().err
    assert "bad.fits" in err and err.count("\n") == 1
    assert not (tmp_path / "o.fits").exists()


def test_output_must_differ_from_input(plain_image, capsys, digest):
    before = digest(plain_image)
    assert main(["add-streak", str(plain_image), "-o", str(plain_image), *ARGS,
                 "--overwrite"]) == 2
    assert "never modified" in capsys.readouterr().err
    assert digest(plain_image) == before


def test_missing_gain(tmp_path, capsys):
    path = tmp_path / "nogain.fits"
    fits.PrimaryHDU(np.zeros((50, 50), np.float32)).writeto(path)
    assert main(["add-streak", str(path), "-o", str(tmp_path / "o.fits"), *ARGS]) == 2
    assert "--gain" in capsys.readouterr().err
