"""OpenEXR output: exact round trips of arrays, mask bits, header text and truth; row order."""
import json
import os

import numpy as np
import OpenImageIO as oiio
import pytest
from astropy.io import fits

import inject.io.exr as exr
from inject import (
    DEFAULT_SCENE,
    FileFormatError,
    OutputError,
    SceneResult,
    apply_overrides,
    parse_scene,
    write_exposure,
    write_exr,
)
from inject.io.exr import read_exr
from inject.io.fits import primary_header
from inject.maskplanes import MASK_PLANES

NY, NX = 48, 64
MJD = 60123.123456789


@pytest.fixture
def scene():
    return parse_scene(apply_overrides(DEFAULT_SCENE, [f"detector.nx={NX}", f"detector.ny={NY}"]))


@pytest.fixture
def result():
    gen = np.random.default_rng(42)
    image = gen.normal(0.0, 3e5, (NY, NX))          # beyond half-float range, both signs
    image[0, 0], image[-1, -1] = 65504.5, -1e30     # just above half max; huge negative
    mask = np.zeros((NY, NX), dtype=np.int32)
    mask[::3, ::5] |= 1 << MASK_PLANES["STREAK"]
    mask[1::4, ::2] |= 1 << 30
    mask[2, 3] = 0x7FFFFFFF
    truth = [
        {"x0": 1.25, "y0": 2.5, "x1": 60.125, "y1": 40.0, "flags": 0, "angle_deg": 33.0,
         "range_km": 1234.567890123456789, "apparent_mag": np.float64(7.1)},
        {"x0": -900.0, "y0": -900.0, "x1": -890.0, "y1": -900.0, "flags": np.int64(1),
         "angle_deg": 0.0, "range_km": 600.0, "apparent_mag": 6.0},
    ]
    return SceneResult(image=image, mask=mask, variance=np.abs(image) + 41.0,
                       streak_model=gen.uniform(0.0, 2e5, (NY, NX)), truth=truth,
                       sky_level=0.0, noise_sigma=0.0)


@pytest.fixture
def with_mjd(monkeypatch):
    """Make write_exr's primary header carry a double that float32 cannot hold."""
    def header(scene):
        hdr = primary_header(scene)
        hdr["MJD-OBS"] = (MJD, "[d] start of exposure")
        return hdr
    monkeypatch.setattr(exr, "primary_header", header)
    return header


def _raw_parts(path):
    """Every part of an EXR as OpenImageIO returns it: (spec, pixels) by part name."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    parts, index = {}, 0
    while inp.seek_subimage(index, 0):
        spec = inp.spec()
        fmt = oiio.UINT if spec.getattribute("name") == "mask" else oiio.FLOAT
        parts[spec.getattribute("name")] = (spec, inp.read_image(fmt))
        index += 1
    inp.close()
    return parts


def test_float_arrays_round_trip_exactly(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    back = read_exr(path)
    for name in ("image", "variance", "streak_model"):
        expected = getattr(result, name).astype(np.float32)
        assert back[name].dtype == np.float32 and back[name].shape == (NY, NX)
        assert np.array_equal(back[name], expected), name
    assert back["image"][0, 0] == np.float32(65504.5)  # half floats would give inf
    assert back["image"][-1, -1] == np.float32(-1e30)


def test_mask_bits_round_trip_exactly(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    back = read_exr(path)
    assert back["mask"].dtype == np.int32  # the FITS MASK type
    assert np.array_equal(back["mask"], result.mask)
    assert back["mask"][2, 3] == 0x7FFFFFFF
    assert (back["mask"] & (1 << 30)).any() and (back["mask"] & (1 << 9)).any()
    assert back["mask_planes"] == MASK_PLANES


def test_mask_sign_bit_survives(tmp_path, scene, result):
    result.mask[5, 5] = np.int32(-(1 << 31))  # bit 31 alone
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    back = read_exr(path)
    assert np.array_equal(back["mask"].view(np.uint32), result.mask.view(np.uint32))
    raw_mask = _raw_parts(path)["mask"][1]
    assert raw_mask.dtype == np.uint32 and raw_mask[NY - 1 - 5, 5, 0] == 1 << 31


def test_header_text_round_trips_exactly(tmp_path, scene, result, with_mjd):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    expected = with_mjd(scene)
    stored = _raw_parts(path)["image"][0].getattribute("inject:fits_header")
    assert stored == exr.header_text(expected)
    header = read_exr(path)["header"]
    assert header["MJD-OBS"] == MJD  # a float32 attribute would give 60123.125
    assert header.tostring() == expected.tostring()
    assert list(header.items()) == list(expected.items())
    assert header.comments["MJD-OBS"] == "[d] start of exposure"


def test_truth_json_round_trip(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    truth = read_exr(path)["truth"]
    assert truth == json.loads(json.dumps([{k: (v.item() if isinstance(v, np.generic) else v)
                                            for k, v in row.items()} for row in result.truth]))
    assert truth[0]["range_km"] == 1234.567890123456789  # JSON keeps doubles exact
    assert truth[1]["flags"] == 1 and truth[0]["x1"] == 60.125


def test_empty_truth(tmp_path, scene, result):
    result.truth = []
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    assert read_exr(path)["truth"] == []


def test_row_order_flipped_in_file_restored_on_read(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    back = read_exr(path)
    assert np.array_equal(back["image"], result.image.astype(np.float32))
    parts = _raw_parts(path)
    spec, raw = parts["image"]
    names = list(spec.channelnames)
    assert set(names) == {"IMAGE", "VARIANCE", "STREAK_MODEL"}
    raw_image = raw[:, :, names.index("IMAGE")]
    # EXR row 0 (top of a picture) holds the last FITS row (top of the ds9 display).
    assert np.array_equal(raw_image[0], result.image[-1].astype(np.float32))
    assert np.array_equal(raw_image[::-1], result.image.astype(np.float32))
    assert spec.getattribute("inject:row_order") == exr.ROW_ORDER
    assert parts["mask"][0].getattribute("inject:row_order") == exr.ROW_ORDER


def test_arrays_identical_to_fits(tmp_path, scene, result):
    write_exposure(tmp_path / "x.fits", scene, result, gain=1.0)
    write_exr(tmp_path / "x.exr", scene, result)
    back = read_exr(tmp_path / "x.exr")
    with fits.open(tmp_path / "x.fits") as hdus:
        for name in ("IMAGE", "MASK", "VARIANCE", "STREAK_MODEL"):
            data = hdus[name].data
            assert back[name.lower()].dtype == data.dtype.newbyteorder("=")
            assert np.array_equal(back[name.lower()], data), name
        assert back["header"].tostring() == primary_header(scene).tostring()


def test_file_layout(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    write_exr(path, scene, result)
    parts = _raw_parts(path)
    assert list(parts) == ["image", "mask"]
    image_spec, mask_spec = parts["image"][0], parts["mask"][0]
    assert (image_spec.width, image_spec.height) == (NX, NY)
    assert image_spec.format == oiio.FLOAT and not image_spec.channelformats  # no halves
    assert mask_spec.format == oiio.UINT and list(mask_spec.channelnames) == ["MASK"]
    for spec in (image_spec, mask_spec):
        assert spec.getattribute("compression") == "zip"
        assert spec.getattribute("DateTime") is None  # no write-time stamp
    assert json.loads(image_spec.getattribute("inject:units"))["VARIANCE"] == "electron2"


def test_output_is_deterministic(tmp_path, scene, result):
    write_exr(tmp_path / "a.exr", scene, result)
    write_exr(tmp_path / "b.exr", scene, result)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()


def test_refuses_to_overwrite(tmp_path, scene, result):
    path = tmp_path / "x.exr"
    path.write_bytes(b"keep me")
    with pytest.raises(OutputError, match="exists"):
        write_exr(path, scene, result)
    assert path.read_bytes() == b"keep me"
    assert os.listdir(tmp_path) == ["x.exr"]  # no temporary file left
    write_exr(path, scene, result, overwrite=True)
    assert np.array_equal(read_exr(path)["mask"], result.mask)
    assert os.listdir(tmp_path) == ["x.exr"]


def test_failed_write_leaves_nothing(tmp_path, scene, result):
    result.mask = result.mask[1:]  # wrong size: OpenImageIO refuses it mid-file
    with pytest.raises(OutputError, match="buffer is wrong size"):
        write_exr(tmp_path / "x.exr", scene, result)
    assert os.listdir(tmp_path) == []  # the half-written temporary file is gone


def test_read_rejects_other_files(tmp_path):
    junk = tmp_path / "junk.exr"
    junk.write_text("not an exr")
    with pytest.raises(FileFormatError, match="junk.exr"):
        read_exr(junk)
    with pytest.raises(FileFormatError):
        read_exr(tmp_path / "missing.exr")
    plain = tmp_path / "plain.exr"
    out = oiio.ImageOutput.create(str(plain))
    assert out.open(str(plain), oiio.ImageSpec(4, 3, 1, oiio.FLOAT))
    assert out.write_image(np.zeros((3, 4, 1), np.float32))
    out.close()
    with pytest.raises(FileFormatError, match="not an inject EXR"):
        read_exr(plain)
