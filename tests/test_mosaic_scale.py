"""The focal-plane mosaic draws every binned block at its true size."""
import numpy as np
import pytest

from inject.camera import layout as fp
from inject.exposure.mosaic import block_extent
from inject.io.quicklook import block_mean


@pytest.mark.parametrize("name", ["R22_S11", "R01_S00"])  # e2v 4096 x 4004, ITL 4072 x 4000
@pytest.mark.parametrize("factor", [40, 64, 7])
def test_blocks_span_factor_pixels_and_start_at_the_ccd_corner(name, factor):
    ccd = fp.ccd(name)
    ny, nx = ccd.shape
    binned = block_mean(np.zeros((ny, nx), np.float32), factor)
    bounds = ccd.bounds_mm()
    x0, x1, y0, y1 = block_extent(bounds, (ny, nx), binned.shape, factor)
    by, bx = binned.shape
    assert (x0, y0) == (bounds[0], bounds[2])
    assert abs(x1 - x0) / bx == pytest.approx(factor * fp.PIXEL_MM, rel=1e-12)
    assert abs(y1 - y0) / by == pytest.approx(factor * fp.PIXEL_MM, rel=1e-12)
    # The overhang beyond the CCD is less than one block.
    assert 0 <= abs(x1 - x0) - abs(bounds[1] - bounds[0]) < factor * fp.PIXEL_MM
