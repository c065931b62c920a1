"""PNG quicklooks: written atomically, sensible size, binning for large images."""
import os

import numpy as np
import pytest
from PIL import Image

from inject import OutputError, SceneResult
from inject.io.quicklook import bin_factor, block_mean, write_quicklook


def _result(ny=48, nx=64, seed=0):
    gen = np.random.default_rng(seed)
    image = gen.normal(100.0, 10.0, (ny, nx))
    y, x = np.mgrid[:ny, :nx]
    image += 500.0 * np.exp(-0.5 * ((y - 0.6 * x - 5.0) / 1.5) ** 2)  # a streak
    truth = [{"x0": 0.0, "y0": 5.0, "x1": nx - 1.0, "y1": 5.0 + 0.6 * (nx - 1), "flags": 0},
             {"x0": -900.0, "y0": -900.0, "x1": -890.0, "y1": -900.0, "flags": 1}]
    return SceneResult(image=image, mask=np.zeros((ny, nx), np.int32),
                       variance=np.full((ny, nx), 100.0), streak_model=np.zeros((ny, nx)),
                       truth=truth, sky_level=100.0, noise_sigma=10.0)


def test_writes_png(tmp_path):
    path = tmp_path / "q.png"
    write_quicklook(path, _result())
    with Image.open(path) as png:
        assert png.format == "PNG"
        width, height = png.size
    assert 300 <= width <= 2000 and 300 <= height <= 2000
    assert os.listdir(tmp_path) == ["q.png"]


def test_refuses_to_overwrite(tmp_path):
    path = tmp_path / "q.png"
    path.write_bytes(b"keep me")
    with pytest.raises(OutputError, match="exists"):
        write_quicklook(path, _result())
    assert path.read_bytes() == b"keep me"
    assert os.listdir(tmp_path) == ["q.png"]  # no temporary file left
    write_quicklook(path, _result(), overwrite=True, truth=False)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_large_image_is_binned(tmp_path):
    result = _result(ny=2100, nx=2050)
    assert bin_factor(result.image.shape) == 3
    path = tmp_path / "big.png"
    write_quicklook(path, result)
    with Image.open(path) as png:
        assert max(png.size) <= 2000


def test_flat_and_nan_images(tmp_path):
    result = _result()
    result.image[:] = 0.0
    write_quicklook(tmp_path / "flat.png", result)
    result.image[:] = np.nan
    write_quicklook(tmp_path / "nan.png", result)
    assert sorted(os.listdir(tmp_path)) == ["flat.png", "nan.png"]


def test_block_mean():
    image = np.arange(35.0).reshape(5, 7)
    binned = block_mean(image, 3)
    assert binned.shape == (2, 3)
    assert binned[0, 0] == image[:3, :3].mean()
    assert binned[1, 2] == image[3:, 6:].mean()  # overhanging edge block: its pixels only
    image[0, 0] = np.nan
    assert block_mean(image, 3)[0, 0] == np.nanmean(image[:3, :3])
    assert bin_factor((4000, 4072)) == 5 and bin_factor((48, 64)) == 1
