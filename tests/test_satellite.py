"""Projected satellite shapes."""
import numpy as np
import pytest

from inject import Box, Disk, InputError, shape_from_dict
from inject.instrument import ARCSEC_PER_RAD
from inject.satellite import Composite, Part


def moments(profile, scale=0.005, n=400):
    img = profile.drawImage(nx=n, ny=n, scale=scale, method="no_pixel").array
    y, x = (np.indices(img.shape) - (n - 1) / 2) * scale
    w = img / img.sum()
    return (w * x * x).sum(), (w * y * y).sum(), (w * x * y).sum()


def test_box_foreshortened_along_motion_for_phi_90():
    r, tn = 1000.0, 60.0
    prof = Box(4.0, 1.0).profile(r, tn, 90.0)
    assert prof.flux == pytest.approx(1.0)
    scale = ARCSEC_PER_RAD / (r * 1e3)
    xx, yy, xy = moments(prof)
    # A uniform box of side s has variance s^2 / 12.
    assert np.sqrt(12 * xx) == pytest.approx(4.0 * 0.5 * scale, rel=0.02)
    assert np.sqrt(12 * yy) == pytest.approx(1.0 * scale, rel=0.02)
    assert abs(xy) < 1e-3 * xx


def test_box_not_foreshortened_along_motion_for_phi_0():
    r, tn = 250.0, 60.0
    xx, yy, _ = moments(Box(4.0, 1.0).profile(r, tn, 0.0), scale=0.01)
    scale = ARCSEC_PER_RAD / (r * 1e3)
    assert np.sqrt(12 * xx) == pytest.approx(4.0 * scale, rel=0.02)
    assert np.sqrt(12 * yy) == pytest.approx(0.5 * scale, rel=0.02)


def test_disk_becomes_ellipse():
    xx, yy, _ = moments(Disk(1.0).profile(500.0, 60.0, 90.0))
    assert np.sqrt(xx / yy) == pytest.approx(0.5, rel=0.02)


def test_composite_flux_weights_and_centroid():
    comp = Composite((Part(Box(1.0, 1.0), dx=2.0), Part(Box(1.0, 1.0), dx=-2.0, reflectance=3.0)))
    prof = comp.profile(ARCSEC_PER_RAD / 1e3, 0.0, 0.0)  # range chosen so 1 m = 1 arcsec
    assert prof.flux == pytest.approx(1.0)
    img = prof.drawImage(nx=200, ny=100, scale=0.05, method="no_pixel").array
    x = (np.arange(200) - 99.5) * 0.05
    centroid = (img.sum(0) * x).sum() / img.sum()
    assert centroid == pytest.approx((2.0 - 3 * 2.0) / 4, abs=0.01)


def test_shape_from_dict():
    assert shape_from_dict({"type": "box", "length": 7.25, "width": 2.65}) == Box(7.25, 2.65)
    assert shape_from_dict({"type": "disk", "radius": 1}) == Disk(1.0)
    comp = shape_from_dict({"type": "composite", "parts": [
        {"type": "box", "length": 2, "width": 1}, {"type": "disk", "radius": 1, "dy": 3}]})
    assert comp.parts[1] == Part(Disk(1.0), dy=3.0)
    for bad in ({"type": "box", "length": 1}, {"type": "cone"}, {"type": "disk", "radius": -1},
                {"type": "disk", "radius": 1, "colour": "red"}, "box",
                {"type": "box", "length": "long", "width": 1}):
        with pytest.raises(InputError):
            shape_from_dict(bad)
