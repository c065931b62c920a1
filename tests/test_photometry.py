"""Zero points, sky and magnitude scaling."""
import numpy as np
import pytest

from inject import InputError
from inject import photometry as ph


def test_smtn002_values():
    zp = {b: ph.BANDS[b].zeropoint for b in "ugrizy"}
    assert zp == {"u": 26.52, "g": 28.51, "r": 28.36, "i": 28.17, "z": 27.78, "y": 26.82}


def test_sky_level_g_30s():
    # ~465 e-/px in g for 30 s with the hardware zero point.
    assert ph.sky_per_pixel("g", 30.0) == pytest.approx(465, abs=1)


def test_electron_rate_at_zeropoint_is_one():
    for name, b in ph.BANDS.items():
        assert ph.electron_rate(b.zeropoint, name) == pytest.approx(1.0, rel=1e-14)


@pytest.mark.parametrize("name,zp", [("u", 26.52), ("g", 28.51), ("y", 26.82)])
def test_electron_rate_away_from_the_zeropoint(name, zp):
    # At the zero point any sign convention gives 1 e-/s: 2.5 mag brighter is 10 e-/s and
    # 5 mag fainter 0.01 e-/s (SMTN-002 zero points typed here, not read from the code).
    assert ph.electron_rate(zp - 2.5, name) == pytest.approx(10.0, rel=1e-12)
    assert ph.electron_rate(zp + 5.0, name) == pytest.approx(0.01, rel=1e-12)
    assert ph.electron_rate(20.0, name) == pytest.approx(10 ** (0.4 * (zp - 20.0)), rel=1e-12)


def test_apparent_magnitude_scaling():
    # At the reference range and face-on nothing changes; twice as far is 5 log10(2) fainter.
    assert ph.apparent_magnitude(5.0, 550.0, 0.0) == pytest.approx(5.0, abs=1e-14)
    assert ph.apparent_magnitude(5.0, 1100.0, 0.0) == pytest.approx(5 + 5 * np.log10(2))
    assert ph.apparent_magnitude(5.0, 550.0, 60.0) == pytest.approx(5 + 2.5 * np.log10(2))


def test_unknown_band():
    with pytest.raises(InputError, match="'w'"):
        ph.band("w")
