"""LSST-native files: what `inject simulate` writes follows afw's MaskedImage layout, and
`add-streak` works on afw's own files and keeps every storage type.

The afw-layout fixtures are written here from afw's documented conventions (MaskedImage.cc,
ExposureInfo.cc, fits.cc, MaskDict.cc): IMAGE/MASK/VARIANCE at HDUs 1-3 typed by EXTTYPE with no
EXTNAME, xy0 in LTV1/2 and the "A" WCS, a uint16 mask stored as int16 + BZERO 32768 with MP_
cards, archive binary tables (with a heap) after VARIANCE.
"""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from inject import StreakModel, Track, add_streaks, read_exposure
from inject.cli.main import main
from inject.maskplanes import MASK_PLANES, PLANE_DESCRIPTIONS, header_planes, plane_bit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from check_lsst import AFW_GAIN as GAIN  # noqa: E402
from check_lsst import AFW_SHAPE as SHAPE  # noqa: E402
from check_lsst import AFW_XY0 as XY0  # noqa: E402
from check_lsst import find_python, write_afw_exposure  # noqa: E402

sys.path.pop(0)
STREAK_ARGS = ["--height", "550", "--zenith", "60", "--mag", "7", "--angle", "20",
               "--track-length", "80"]


@pytest.fixture
def afw_exposure(tmp_path):
    """An afw-layout Exposure in ADU (no EXTNAME, xy0 != 0, SIP, uint16 mask, archives)."""
    path = write_afw_exposure(tmp_path / "calexp.fits")
    with fits.open(path) as hdus:
        assert all("EXTNAME" not in hdu.header for hdu in hdus[1:4])
        assert hdus[2].header["BITPIX"] == 16 and hdus[2].header["BZERO"] == 32768
    return path


def _hdu_bytes(path):
    """The bytes of every HDU of a file (header and data, padding included)."""
    raw = Path(path).read_bytes()
    with fits.open(path) as hdus:
        spans = [hdus.fileinfo(i) for i in range(len(hdus))]
    return [raw[s["hdrLoc"]:s["datLoc"] + s["datSpan"]] for s in spans]


def _model(mag=7.0):
    return StreakModel(550, 60, mag=mag)


def test_afw_exposure_streak_mask_variance(afw_exposure, tmp_path):
    """STREAK on the first free bit, set on the injected pixels; VARIANCE + model / gain**2;
    every other plane, card and HDU as it was."""
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(afw_exposure), "-o", str(out), *STREAK_ARGS, "--parent",
                 "--x0", str(XY0[0] + 30.0), "--y0", str(XY0[1] + 40.0), "--seed", "3"]) == 0
    before, after = _hdu_bytes(afw_exposure), _hdu_bytes(out)
    assert len(after) == len(before) + 3  # + TRUTH, TRUTH_VERTICES and STREAK_MODEL
    for index in (0, 4, 5):  # primary and archive tables (heap included): byte for byte
        assert after[index] == before[index]
    with fits.open(afw_exposure) as old, fits.open(out) as new:
        for index in (1, 2, 3):  # the input's cards in order; EXTNAME (lsst-images needs it)
            old_cards = [c.image for c in old[index].header.cards]
            new_cards = [c.image for c in new[index].header.cards]
            assert [c for c in new_cards if c in old_cards] == old_cards
            added = {c.keyword for c in new[index].header.cards if c.image not in old_cards}
            assert added == ({"EXTNAME", "MP_STREAK"} if index == 2 else {"EXTNAME"})
            assert new[index].header["EXTNAME"] == new[index].header["EXTTYPE"]
        model = new["STREAK_MODEL"].data.astype(np.float64)
        truth = Table(new["TRUTH"].data)
        # Parent pixels: the array start is the parent start minus xy0.
        assert truth["x0"][0] == pytest.approx(30.0) and truth["y0"][0] == pytest.approx(40.0)
        assert new["TRUTH"].header["PARENTX0"] == XY0[0]
        reached = model > 0
        assert 0 < reached.sum() < reached.size
        # IMAGE: only reached pixels change, by the injected charge in ADU (Poisson draw).
        image_old, image_new = old[1].data, new[1].data
        assert np.array_equal(image_new[~reached].view(np.uint32),
                              image_old[~reached].view(np.uint32))
        assert np.signbit(image_new[3, 4])
        added = (image_new.astype(np.float64) - image_old) * GAIN
        bright = model > 100
        residual = (added - model)[bright] / np.sqrt(model[bright])
        assert abs(residual.mean()) < 0.15 and 0.8 < residual.std() < 1.2
        # VARIANCE: + the Poisson variance of the noise-free model, in ADU^2.
        var_old = old[3].data.astype(np.float64)
        np.testing.assert_allclose(new[3].data, var_old + model / GAIN ** 2, rtol=2e-7)
        assert np.array_equal(new[3].data[~reached], old[3].data[~reached])
        # MASK: still uint16 stored as int16 + BZERO; STREAK named on bit 11, the lowest free.
        assert new[2].header["BITPIX"] == 16 and new[2].header["BZERO"] == 32768
        mask_old, mask_new = old[2].data, new[2].data
        assert mask_new.dtype == np.uint16
        bit = new[2].header["MP_STREAK"]
        assert bit == 11
        streak = (mask_new & (1 << bit)) != 0
        sigma = np.sqrt(np.median(var_old))
        np.testing.assert_array_equal(streak, model > sigma * GAIN)
        assert streak.sum() > 50
        np.testing.assert_array_equal(mask_new & ~np.uint16(1 << bit), mask_old)


def test_ra_dec_start_uses_sip(afw_exposure, tmp_path):
    """--ra0/--dec0 go through the full WCS, SIP distortion included (array pixels)."""
    header = fits.getheader(afw_exposure, 1)
    wcs = WCS(header)
    x, y = 130.0, 100.0
    ra, dec = wcs.all_pix2world(x, y, 0)
    linear = WCS(header).wcs_world2pix(ra, dec, 0)  # without SIP
    assert np.hypot(linear[0] - x, linear[1] - y) > 2  # the distortion matters here
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(afw_exposure), "-o", str(out), *STREAK_ARGS,
                 "--ra0", f"{float(ra):.12f}", "--dec0", f"{float(dec):.12f}",
                 "--no-noise"]) == 0
    truth = Table.read(out, hdu="TRUTH")
    assert truth["x0"][0] == pytest.approx(x, abs=1e-5)
    assert truth["y0"][0] == pytest.approx(y, abs=1e-5)


def test_parent_pixels_on_a_file_without_origin(tmp_path):
    """--parent on a file with no LTV and no "A" WCS: xy0 = (0, 0), as LSST readers take it."""
    path = tmp_path / "bare.fits"
    fits.PrimaryHDU(np.zeros((60, 70), np.float32), header=fits.Header({"GAIN": 1.0})).writeto(path)
    exposure = read_exposure(path)
    assert exposure.xy0 == (0, 0)
    out = tmp_path / "o.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK_ARGS, "--parent",
                 "--x0", "10", "--y0", "20", "--no-noise"]) == 0
    assert Table.read(out, hdu="TRUTH")["x0"][0] == pytest.approx(10.0)


def _storage_file(tmp_path, kind):
    """A MaskedImage whose IMAGE is stored as ``kind``, and the physical values it holds."""
    rng = np.random.default_rng(4)
    physical = np.rint(1000 + rng.normal(0, 20, SHAPE))
    mask = np.zeros(SHAPE, np.int32)
    mask_header = fits.Header({"EXTTYPE": "MASK"})
    for name, bit in MASK_PLANES.items():
        mask_header[f"HIERARCH MP_{name}"] = bit
    image_header = fits.Header({"EXTTYPE": "IMAGE", "GAIN": 1.0, "BUNIT": "adu"})
    if kind == "float32":
        image = fits.ImageHDU(physical.astype(np.float32), header=image_header)
    elif kind == "float64":
        image = fits.ImageHDU(physical + rng.random(SHAPE), header=image_header)
    elif kind == "uint16":  # int16 + BZERO 32768, as raw LSST amplifier data
        image = fits.ImageHDU(physical.astype(np.uint16), header=image_header)
    elif kind == "int32":
        image = fits.ImageHDU(physical.astype(np.int32), header=image_header)
    elif kind == "scaled-int16":  # BSCALE 0.5, BZERO 1000: astropy shows float32
        image = fits.ImageHDU(((physical - 1000) / 0.5).astype(np.int16), header=image_header)
        image.header["BSCALE"], image.header["BZERO"] = 0.5, 1000.0
    elif kind == "rice-float32":  # quantised: lossy as the input was written
        image = fits.CompImageHDU((physical + rng.random(SHAPE)).astype(np.float32),
                                  header=image_header, compression_type="RICE_1")
    elif kind == "rice-int16":
        image = fits.CompImageHDU(physical.astype(np.int16), header=image_header,
                                  compression_type="RICE_1")
    hdus = fits.HDUList([fits.PrimaryHDU(), image,
                         fits.ImageHDU(mask, header=mask_header),
                         fits.ImageHDU(np.full(SHAPE, 400.0, np.float32),
                                       header=fits.Header({"EXTTYPE": "VARIANCE"}))])
    path = tmp_path / f"{kind}.fits"
    if kind == "scaled-int16":
        # Write the integers as they are (astropy would otherwise rescale them on write).
        hdus.writeto(path)
        with fits.open(path, mode="update", do_not_scale_image_data=True) as f:
            f[1].header["BSCALE"], f[1].header["BZERO"] = 0.5, 1000.0
    else:
        hdus.writeto(path)
    return path


STORAGES = ["float32", "float64", "uint16", "int32", "scaled-int16", "rice-float32",
            "rice-int16"]


def _stored(path, index):
    """(stored pixels, header) of an HDU as in the file (no scaling)."""
    with fits.open(path, do_not_scale_image_data=True) as hdus:
        return np.array(hdus[index].data), hdus[index].header.copy()


@pytest.mark.parametrize("kind", STORAGES)
def test_storage_kept_and_untouched_pixels_identical(tmp_path, kind):
    """Each storage through add-streak: same type; pixels the streak does not reach equal bit
    for bit (as the input decompresses, for compressed images); reached ones rounded and
    clipped for integers, SAT where the type's limit is hit."""
    path = _storage_file(tmp_path, kind)
    out = tmp_path / "out.fits"
    # Bright (mag 1): the peak passes the uint16 / int16 limits.
    assert main(["add-streak", str(path), "-o", str(out), "--height", "550", "--zenith", "60",
                 "--mag", "1", "--x0", "20", "--y0", "30", "--angle", "25",
                 "--track-length", "90", "--no-noise"]) == 0
    with fits.open(out) as new, fits.open(path) as old:
        model = new["STREAK_MODEL"].data.astype(np.float64)
        reached = model > 0
        before, after = np.array(old[1].data), np.array(new[1].data)
        assert after.dtype == before.dtype
        assert type(new[1]) is type(old[1])
        if isinstance(new[1], fits.CompImageHDU):
            assert new[1].compression_type in ("RICE_1", "GZIP_2")
            if before.dtype.kind == "f":
                assert new[1].compression_type == "GZIP_2" and new[1].quantize_level == 0
        width = before.dtype.itemsize * 8
        view = {32: np.uint32, 64: np.uint64, 16: np.uint16}[width]
        assert np.array_equal(after[~reached].view(view), before[~reached].view(view))
        mask = new[2].data
        sat = (mask & (1 << MASK_PLANES["SAT"])) != 0
        if kind in ("uint16", "int32", "rice-int16"):
            top = np.iinfo(before.dtype).max
            expected = np.clip(np.rint(before.astype(np.float64) + model), None, top)
            # STREAK_MODEL is float32: a pixel of 3e5 e- may round the other way.
            assert np.abs(after.astype(np.float64) - expected).max() <= 1
            assert np.mean(after == expected) > 0.99
            np.testing.assert_array_equal(sat, reached & (after == top))
            if kind != "int32":
                assert sat.sum() > 0
        elif kind == "scaled-int16":
            expected = np.clip(np.rint((before - 1000 + model) / 0.5), -32768, 32767)
            assert np.abs(after - (expected * 0.5 + 1000)).max() <= 0.5
            np.testing.assert_array_equal(sat, reached & (after == 32767 * 0.5 + 1000))
            assert sat.sum() > 0
        else:
            np.testing.assert_allclose(after, before + model, rtol=1e-6)
            assert not sat.any()
    if kind in ("uint16", "int32", "scaled-int16"):  # the stored integers: same cards, same type
        stored_old, header_old = _stored(path, 1)
        stored_new, header_new = _stored(out, 1)
        assert stored_new.dtype == stored_old.dtype
        assert header_new.pop("EXTNAME") == "IMAGE"  # typed by EXTTYPE only: named too
        assert header_new.tostring() == header_old.tostring()


def test_missing_track_warns(tmp_path, capsys):
    path = _storage_file(tmp_path, "float32")
    out = tmp_path / "o.fits"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK_ARGS, "--x0", "-900",
                 "--y0", "-900", "--no-noise"]) == 0
    err = capsys.readouterr().err
    assert "warning: the track misses the image: 0 e- injected" in err
    assert Table.read(out, hdu="TRUTH")["flags"][0] & 1
    with fits.open(out) as new, fits.open(path) as old:
        assert np.array_equal(new[1].data, old[1].data)


def test_plane_bit_lowest_free():
    """afw's MaskDict::getUnusedPlane: the lowest gap, else one past the highest."""
    header = fits.Header()
    for name, bit in {"BAD": 0, "SAT": 2, "CR": 3}.items():
        header[f"HIERARCH MP_{name}"] = bit
    assert plane_bit(header, "STREAK") == 1 and header["MP_STREAK"] == 1
    assert plane_bit(header, "STREAK") == 1  # named once
    assert "MSKN0001" not in header  # afw files stay afw-only
    full = fits.Header()
    for bit in range(16):
        full[f"HIERARCH MP_P{bit}"] = bit
    assert plane_bit(full, "STREAK", nbits=16) is None


SCENE = {"seed": 2, "band": "r", "exptime": 15.0, "zenith": 40,
         "detector": {"type": "e2v", "nx": 160, "ny": 120},
         "sky": True, "stars": False, "noise": True,
         "pointing": {"ra": 45.0, "dec": -30.0, "rotation": 20.0},
         "satellites": [{"height": 550, "shape": {"type": "disk", "radius": 1.0}, "mag": 4.0,
                         "track": {"x0": 10, "y0": 20, "angle": 30.0}}]}


@pytest.fixture
def simulated(tmp_path):
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump(SCENE))
    out = tmp_path / "sim.fits"
    assert main(["simulate", str(scene), "-o", str(out)]) == 0
    return out


def test_simulated_file_has_afw_cards(simulated):
    """What lsst-images' read_legacy and afw's MaskedImageFitsReader take from the file,
    checked with astropy alone (the slow test runs lsst-images itself)."""
    with fits.open(simulated) as hdus:
        primary = hdus[0].header
        assert primary["FILTER"] == "r" and primary["EXPTIME"] == 15.0
        assert primary["BORE-RA"] == 45.0 and primary["BORE-DEC"] == -30.0
        assert primary["BORE-ROTANG"] == 20.0 and primary["ROTTYPE"] == "SKY"
        assert "EXTNAME" not in primary
        for index, exttype in enumerate(("IMAGE", "MASK", "VARIANCE"), start=1):
            header = hdus[index].header
            assert header["EXTTYPE"] == exttype and header["EXTNAME"] == exttype
            assert header["INHERIT"] is True
            assert header["LTV1"] == 0 and header["LTV2"] == 0
            assert header["CTYPE1A"] == "LINEAR" and header["CTYPE2A"] == "LINEAR"
            assert header["CRVAL1A"] - (header["CRPIX1A"] - 1) == 0
            assert header["CUNIT1A"] == "PIXEL"
            # The same celestial WCS on the three planes.
            assert WCS(header).wcs.compare(WCS(hdus[1].header).wcs)
        assert hdus[1].header["BUNIT"] == "electron"
        assert hdus[3].header["BUNIT"] == "electron**2"
        mask = hdus[2].header
        assert mask["BITPIX"] == 32
        # afw's MP_ cards and lsst-images' MSKN/MSKM/MSKD cards name the same planes.
        mp = {k[3:]: v for k, v in mask.items() if k.startswith("MP_")}
        assert mp == MASK_PLANES
        assert MASK_PLANES["STREAK"] == 10 and MASK_PLANES["VIGNETTED"] == 9
        for name, bit in MASK_PLANES.items():
            assert mask[f"MSKN{bit:04d}"] == name
            assert mask[f"MSKM{bit:04d}"] == 1 << bit
            assert mask[f"MSKD{bit:04d}"] == PLANE_DESCRIPTIONS[name]
        assert header_planes(mask) == MASK_PLANES
        assert [h.name for h in hdus][4:6] == ["STREAK_MODEL", "TRUTH"]
        assert (hdus[2].data & (1 << 10)).any()


def test_primary_cards_and_xy0(tmp_path):
    """write_exposure: extra primary cards (a focal-plane CCD's DETNAME, DETECTOR) and xy0."""
    from inject import parse_scene, simulate, write_exposure
    scene = parse_scene({**SCENE, "pointing": None, "sky": False, "noise": False})
    result = simulate(scene)
    out = tmp_path / "ccd.fits"
    write_exposure(out, scene, result, 1.0, primary_cards={"DETNAME": "R22_S11",
                                                            "DETECTOR": (94, "detector id")},
                   xy0=(4000, 8000))
    with fits.open(out) as hdus:
        assert hdus[0].header["DETNAME"] == "R22_S11" and hdus[0].header["DETECTOR"] == 94
        assert "BORE-RA" not in hdus[0].header
        assert hdus[2].header["LTV1"] == -4000 and hdus[2].header["CRVAL2A"] == 8000
    assert read_exposure(out).xy0 == (4000, 8000)


def test_add_streaks_api_keeps_dtype(tmp_path):
    """The in-memory view after add_streaks has the file's types too."""
    path = _storage_file(tmp_path, "uint16")
    exposure = read_exposure(path)
    add_streaks(exposure, [_model(3.0)], [Track(20, 30, 25.0, 60.0)], 1.0, 1, noise=False)
    assert exposure.image_hdu.data.dtype.newbyteorder("=") == np.uint16
    assert exposure.hdus[exposure.mask_index].data.dtype.newbyteorder("=") == np.int32


@pytest.mark.slow
def test_lsst_images_reads_our_files(tmp_path):
    """scripts/check_lsst.py: lsst-images' MaskedImage.read_legacy on simulate and add-streak
    outputs (builds its venv once, outside the repository)."""
    if find_python() is None:
        pytest.skip("no Python >= 3.12 on this machine: lsst-images needs one")
    venv = os.environ.get("INJECT_LSST_VENV")
    cmd = [sys.executable, str(ROOT / "scripts" / "check_lsst.py"), "--workdir", str(tmp_path)]
    if venv:
        cmd += ["--venv", venv]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ALL CHECKS PASSED" in done.stdout


def test_compressed_afw_exposure(afw_exposure, tmp_path):
    """A tile-compressed (.fits.fz) Exposure, every plane compressed as afw writes it:
    compressed again losslessly, untouched pixels as the input decompresses them."""
    path = tmp_path / "calexp.fits.fz"
    with fits.open(afw_exposure) as hdus:
        planes = [fits.CompImageHDU(np.array(h.data), header=h.header.copy(),
                                    compression_type=kind)
                  for h, kind in zip(hdus[1:4], ("RICE_1", "GZIP_2", "RICE_1"))]
        fits.HDUList([hdus[0].copy(), *planes, hdus[4].copy()]).writeto(path)
    out = tmp_path / "out.fits.fz"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK_ARGS, "--x0", "30",
                 "--y0", "40"]) == 0
    with fits.open(path) as old, fits.open(out) as new:
        reached = new["STREAK_MODEL"].data > 0
        for index in (1, 2, 3):
            assert isinstance(new[index], fits.CompImageHDU)
            a, b = np.array(old[index].data), np.array(new[index].data)
            assert a.dtype == b.dtype
            view = np.uint16 if a.dtype.itemsize == 2 else np.uint32
            assert np.array_equal(b[~reached].view(view), a[~reached].view(view))
            if a.dtype.kind == "f":  # the input was quantised: lossless now
                assert new[index].compression_type == "GZIP_2"
                assert new[index].quantize_level == 0
        bit = new[2].header["MP_STREAK"]
        assert bit == 11 and ((new[2].data & (1 << bit)) != 0).sum() > 50
        assert new[4].data.tobytes() == old[4].data.tobytes()


def test_checksums_stay_valid(tmp_path):
    """An HDU with CHECKSUM/DATASUM that the streak changes gets them computed again."""
    path = _storage_file(tmp_path, "uint16")
    with fits.open(path) as hdus:
        hdus.writeto(tmp_path / "sum.fits", checksum=True)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(tmp_path / "sum.fits"), "-o", str(out), *STREAK_ARGS,
                 "--x0", "20", "--y0", "30", "--no-noise"]) == 0
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # astropy warns on a checksum that does not match
        with fits.open(out, checksum=True) as hdus:
            for hdu in hdus:
                hdu.data  # noqa: B018
            assert hdus[1].data.dtype.newbyteorder("=") == np.uint16
            assert (hdus["STREAK_MODEL"].data > 0).any()
            assert "CHECKSUM" in hdus[1].header and "CHECKSUM" in hdus[2].header
    stored, header = _stored(out, 1)
    assert stored.dtype.newbyteorder("=") == np.int16 and header["BZERO"] == 32768


def test_gzipped_input(afw_exposure, tmp_path):
    import gzip

    path = tmp_path / "calexp.fits.gz"
    path.write_bytes(gzip.compress(afw_exposure.read_bytes()))
    out = tmp_path / "out.fits.gz"
    assert main(["add-streak", str(path), "-o", str(out), *STREAK_ARGS, "--x0", "30",
                 "--y0", "40", "--no-noise"]) == 0
    with fits.open(out) as hdus:
        assert hdus[2].header["MP_STREAK"] == 11
        assert hdus[5].data.tobytes() == fits.getdata(afw_exposure, 5).tobytes()


def test_date_avg_when_the_scene_has_a_start():
    """DATE-AVG is the middle of the exposure in TAI (TAI - UTC = 37 s since 2017)."""
    from dataclasses import replace

    from inject import parse_scene
    from inject.io.fits import primary_header

    scene = parse_scene(SCENE)
    header = primary_header(replace(scene, time="2025-03-01T04:00:00"))
    assert header["DATE-AVG"] == "2025-03-01T04:00:44.500"  # + 7.5 s + 37 s
    assert header["TIMESYS"] == "TAI"
    assert "DATE-AVG" not in primary_header(scene)


def _painted(shape, streak):
    """The STREAK plane ``inject mask --out`` should write for one streak, from the masking
    module's own span painter (its geometry is tested in test_masking_geometry)."""
    from inject.masking.geometry import Line
    from inject.masking.mask import mask_spans, paint

    plane = np.zeros(shape, dtype=bool)
    ends = [streak[key] for key in ("x0", "y0", "x1", "y1")]
    paint(plane, mask_spans(shape, Line(*ends), streak["mask_width_px"]))
    return plane


def test_mask_out_keeps_the_files_storage(afw_exposure, tmp_path):
    """`inject mask --out` on an afw file: the uint16 mask stays int16 + BZERO, STREAK goes on
    the lowest free bit, every other plane and every other HDU is unchanged."""
    from inject.masking import write_masked

    streak = {"x0": 10.0, "y0": 20.0, "x1": 180.0, "y1": 90.0, "mask_width_px": 9.0}
    out = tmp_path / "masked.fits"
    count = write_masked(afw_exposure, out, [streak])
    before, after = _hdu_bytes(afw_exposure), _hdu_bytes(out)
    assert len(before) == len(after)
    assert [i for i, (a, b) in enumerate(zip(before, after)) if a != b] == [2]  # the MASK
    with fits.open(afw_exposure, do_not_scale_image_data=True) as old, \
            fits.open(out, do_not_scale_image_data=True) as new:
        assert new[2].header["BITPIX"] == 16 and new[2].header["BZERO"] == 32768
        assert new[2].data.dtype.kind == "i" and new[2].data.dtype.itemsize == 2
    with fits.open(afw_exposure) as old, fits.open(out) as new:
        planes = header_planes(new[2].header)
        bit = planes["STREAK"]
        assert bit == min(set(range(16)) - set(header_planes(old[2].header).values()))
        expected = _painted(SHAPE, streak)
        assert count == expected.sum() > 0
        got = (new[2].data.astype(np.int64) >> bit) & 1
        np.testing.assert_array_equal(got.astype(bool), expected)
        others = ~np.int64(1 << bit)
        np.testing.assert_array_equal(new[2].data.astype(np.int64) & others,
                                      old[2].data.astype(np.int64))


def test_mask_out_replaces_an_existing_plane_on_bit_31(tmp_path):
    """A STREAK plane on the sign bit of an int32 mask: replaced, not overflowed; the old
    STREAK pixels cleared, the other bits kept."""
    from inject.masking import write_masked
    from inject.maskplanes import mask_header

    shape = (120, 200)
    mask = np.zeros(shape, np.int32)
    mask[:, :5] = np.int32(-2 ** 31) | 1  # STREAK (bit 31) and BAD on the left columns
    header = mask_header(fits.Header(), {"BAD": 0, "STREAK": 31})
    path = tmp_path / "in.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros(shape, np.float32), name="IMAGE"),
                  fits.ImageHDU(mask, header=header, name="MASK")]).writeto(path)
    streak = {"x0": 20.0, "y0": 60.0, "x1": 180.0, "y1": 60.0, "mask_width_px": 6.0}
    write_masked(path, tmp_path / "out.fits", [streak])
    with fits.open(tmp_path / "out.fits") as hdus:
        data = hdus["MASK"].data
        assert data.dtype == np.dtype(">i4")
        np.testing.assert_array_equal(data < 0, _painted(shape, streak))
        np.testing.assert_array_equal(data & 1, mask & 1)
