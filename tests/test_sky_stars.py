"""Random stars are fixed to the sky: the same sky gives the same stars at any rotation, pointing
offset or CCD, and the counts per deg^2 follow the model."""
import math

import numpy as np
import pytest

from inject import Pointing, ccd_wcs, pointing_wcs, skytiles
from inject.camera import layout as fp
from inject.stars import sample_stars, star_field_spec

SPEC = star_field_spec({"mag_limit": 22.0, "galactic_l": 90.0, "galactic_b": 40.0})


def test_the_tiles_cover_the_sphere_once():
    """The tiles' exact solid angles add up to the whole sky, 4 pi sr."""
    total = sum(skytiles.tile_area_deg2((j, i)) for j in range(skytiles._N_BANDS)
                for i in range(skytiles._band_count(j)))
    assert total == pytest.approx(4 * math.pi * (180 / math.pi) ** 2, rel=1e-9)


def _stars(wcs, shape=(4000, 4072), seed=7, margin=100.0):
    return skytiles.sky_stars(SPEC, wcs, shape, margin, "g", seed, sample_stars)


@pytest.mark.parametrize("other", [Pointing(50.0, -30.0, 110.0),  # rotated 90 deg
                                   Pointing(50.1, -30.05, 20.0)])  # moved ~0.1 deg
def test_the_same_sky_gives_the_same_stars(other):
    """Each star seen under both pointings lands, under the second, where the second WCS puts
    its sky position under the first (to 0.01 px); most stars are seen under both."""
    ccd = fp.ccd("R22_S11")
    first, second = ccd_wcs(ccd, Pointing(50.0, -30.0, 20.0)), ccd_wcs(ccd, other)
    a, b = _stars(first), _stars(second)
    at = {m: (x, y) for m, x, y in zip(b["mag"], b["x"], b["y"])}  # magnitudes are unique
    common = [(x, y, m) for x, y, m in zip(a["x"], a["y"], a["mag"]) if m in at]
    assert len(common) > 0.5 * a["mag"].size > 50
    for x, y, m in common:
        ra, dec = first.pixel_to_world_values(x, y)
        xb, yb = second.world_to_pixel_values(ra, dec)
        assert math.hypot(xb - at[m][0], yb - at[m][1]) < 0.01


def test_two_ccds_share_the_stars_of_their_overlap():
    """Two neighbouring CCDs' grown areas overlap across the gap: a star in both is the same
    star at the same sky position."""
    pointing = Pointing(120.0, 10.0, 0.0)
    left, right = fp.ccd("R22_S11"), fp.ccd("R22_S12")
    wl, wr = ccd_wcs(left, pointing), ccd_wcs(right, pointing)
    a, b = _stars(wl), _stars(wr)
    shared = np.intersect1d(a["mag"], b["mag"])
    assert shared.size > 0
    for m in shared:
        ra_a, dec_a = wl.pixel_to_world_values(a["x"][a["mag"] == m][0], a["y"][a["mag"] == m][0])
        ra_b, dec_b = wr.pixel_to_world_values(b["x"][b["mag"] == m][0], b["y"][b["mag"] == m][0])
        assert float(ra_a) == pytest.approx(float(ra_b), abs=1e-9)
        assert float(dec_a) == pytest.approx(float(dec_b), abs=1e-9)


@pytest.mark.parametrize("pointing", [Pointing(50.0, -30.0, 20.0), Pointing(10.0, 89.95, 0.0),
                                      Pointing(10.0, -90.0, 0.0), Pointing(359.99, 0.0, 0.0)])
def test_counts_per_square_degree_follow_the_model(pointing):
    """Over 40 seeds, the stars on a 2000 x 2000 image average the model's density times its
    area (within 4 sigma), at the equator, at RA 0 and at and near the poles."""
    from inject.stars import _cumulative_counts_grid

    shape = (2000, 2000)
    wcs = pointing_wcs(pointing, shape, 0.2)
    expected = (2000 * 0.2 / 3600) ** 2 * _cumulative_counts_grid(SPEC)[1][-1]
    counts = [_stars(wcs, shape, seed, margin=0.0)["mag"].size for seed in range(40)]
    assert abs(np.mean(counts) - expected) < 4 * math.sqrt(expected / 40)


@pytest.mark.parametrize("name", ["R22_S12", "R41_S00"])
def test_a_cutouts_stars_are_placed_as_the_full_ccds_bit_for_bit(name):
    """Through a focal-plane CCD's WCS, whose SIP inverse iterates, a star is placed on its
    own: the stars a cut-out shares with its full CCD are at the same pixel positions, bit
    for bit (astropy's default inverse iterates until the worst point of the set converges,
    so the company moved every star of R22_S12's cut-out by ~3e-11 px)."""
    wcs = ccd_wcs(fp.ccd(name), Pointing(50.0, -30.0, 20.0))
    assert wcs.sip is not None
    full, cut = _stars(wcs, (4000, 4072), margin=180.0), _stars(wcs, (900, 700), margin=180.0)
    at = {m: (x, y) for m, x, y in zip(full["mag"], full["x"], full["y"])}
    assert cut["mag"].size > 10 and set(cut["mag"]) <= set(at)
    for m, x, y in zip(cut["mag"], cut["x"], cut["y"]):
        assert (x, y) == at[m]
