"""Scene statistics: noise against VARIANCE, reproducibility, saturation, units."""
import numpy as np
import pytest

from inject import InputError, SceneError, simulate
from inject.camera.detector import ITL, bleed_saturation, detector_from_spec
from inject.config import sky_level
from inject.maskplanes import MASK_PLANES
from inject.photometry import sky_per_pixel

BASE = ["detector.nx=300", "detector.ny=260", "stars=false", "satellites.0.track.x0=10",
        "satellites.0.track.y0=40", "satellites.0.track.angle=20"]


def test_sky_noise_matches_variance(small_scene):
    res = simulate(small_scene(*BASE, "satellites=[]"))
    sky = sky_per_pixel("g", 30.0)
    assert res.image.mean() == pytest.approx(sky, rel=2e-3)
    assert res.image.std() == pytest.approx(np.sqrt(res.variance.mean()), rel=0.02)
    np.testing.assert_allclose(res.variance, sky + ITL.read_noise ** 2)


def test_same_seed_bit_identical_other_seed_not(small_scene):
    a, b = simulate(small_scene(*BASE)), simulate(small_scene(*BASE))
    np.testing.assert_array_equal(a.image, b.image)
    c = simulate(small_scene(*BASE, "seed=2"))
    assert not np.array_equal(a.image, c.image)
    np.testing.assert_array_equal(a.streak_model, c.streak_model)  # the truth has no noise


def test_streak_flux_recovered_within_poisson(small_scene):
    res = simulate(small_scene(*BASE, "satellites.0.mag=9"))
    signal = (res.image - res.sky_level).sum()
    expected = res.streak_model.sum()
    sigma = np.sqrt(res.variance.sum())
    assert abs(signal - expected) < 4 * sigma


def test_saturating_streak_bleeds_and_conserves_charge(small_scene):
    sat = small_scene(*BASE, "satellites.0.mag=1", "noise=false", "sky=false",
                "satellites.0.track.angle=0", "satellites.0.track.y0=130")
    res = simulate(sat)
    sat_bit = 1 << MASK_PLANES["SAT"]
    assert (res.mask & sat_bit).any()
    assert res.image.max() == pytest.approx(ITL.full_well)
    columns = np.arange(60, 240)
    # Charge moved along columns only: every column keeps its charge.
    np.testing.assert_allclose(res.image[:, columns].sum(0), res.streak_model[:, columns].sum(0),
                               rtol=1e-9)
    assert res.truth[0]["flags"] & 4


def test_bleed_respects_e2v_midline():
    column = np.full((40, 1), 10.0)
    column[18] = 6e5
    total = column.sum()
    bleed_saturation(column, 1e5, midline=20)
    assert column.sum() == pytest.approx(total)
    assert np.all(column[20:] == 10.0)  # nothing crossed into the upper half
    assert np.count_nonzero(column[:20] >= 1e5) == 5


def test_units_adu_divides_by_amp_gain(small_scene):
    e = simulate(small_scene(*BASE, "noise=false"))
    adu = simulate(small_scene(*BASE, "noise=false", "units=adu"))
    np.testing.assert_allclose(adu.image, e.image / ITL.gain)


def test_per_amp_gains_and_cutout():
    det = detector_from_spec({"type": "e2v", "gains": [1.0 + i / 10 for i in range(16)]})
    gains = det.per_pixel("gain")
    assert gains[0, 0] == 1.0 and gains[0, 4095] == pytest.approx(1.7)
    assert gains[4003, 0] == pytest.approx(1.8) and det.midline == 2002
    with pytest.raises(InputError):
        detector_from_spec({"type": "itl", "gains": [1.0, 2.0]})


def test_sky_options(small_scene):
    assert sky_level(small_scene(*BASE, "sky=false")) == 0
    assert sky_level(small_scene(*BASE, "sky.level=123.5")) == 123.5
    dark = sky_level(small_scene(*BASE))
    assert sky_level(small_scene(*BASE, "sky.airmass_scaling=true")) == pytest.approx(
        dark / np.cos(np.radians(70)))
    assert sky_level(small_scene(*BASE, "sky.mag=21.25")) == pytest.approx(dark * 10 ** 0.4)
    with pytest.raises(SceneError, match="unknown keys"):
        sky_level(small_scene(*BASE, "sky.colour=blue"))


def test_cosmic_rays_and_dark_current(small_scene):
    # The rate is per CCD: this 1000 x 1000 cut-out gets ~1/16 of its 300 rays.
    res = simulate(small_scene(*BASE, "cosmic_rays=10", "dark_current=0.5", "satellites=[]",
                               "sky=false", "detector.nx=1000", "detector.ny=1000"))
    cr = (res.mask & (1 << MASK_PLANES["CR"])) != 0
    assert cr.any()
    assert np.median(res.image[~cr]) == pytest.approx(15.0, abs=1.0)


def test_raw_layout_with_bias_and_overscan(small_scene):

    res = simulate(small_scene(*BASE, "detector.type=e2v", "detector.nx=1024", "detector.ny=2100",
                         "detector.layout=raw", "detector.bias=1200", "stars=false"))
    det = detector_from_spec({"type": "e2v"})
    seg_w = det.prescan + det.amp_nx + det.serial_overscan
    assert res.raw.shape == (2 * (det.amp_ny + det.parallel_overscan), 2 * seg_w)
    first = res.raw_sections[0]
    x = slice(det.prescan, det.prescan + det.amp_nx)
    data = res.raw[:det.amp_ny, x]
    overscan = res.raw[:det.amp_ny, det.prescan + det.amp_nx:seg_w]
    # Overscan: bias plus read noise in ADU; data: bias plus collected charge over the gain.
    assert overscan.mean() == pytest.approx(1200, abs=0.1)
    assert overscan.std() == pytest.approx(det.read_noise / det.gain, rel=0.05)
    sky_adu = res.sky_level / det.gain
    assert np.median(data) == pytest.approx(1200 + sky_adu, rel=2e-3)
    assert first["datasec"] == f"[{det.prescan + 1}:{det.prescan + det.amp_nx},1:{det.amp_ny}]"
    # The upper amplifiers read out through the top edge: overscan rows lie below their data.
    upper = next(s for s in res.raw_sections if s["amp"] == det.N_AMP_COLS)
    rows_in_cutout = 2100 - det.amp_ny
    top = 2 * (det.amp_ny + det.parallel_overscan)
    assert upper["datasec"].endswith(f",{top - rows_in_cutout + 1}:{top}]")
