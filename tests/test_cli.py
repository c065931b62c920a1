"""The command-line interface."""
import json
import subprocess
import sys

import numpy as np
import pytest

from inject.cli.main import main

PROFILE_KEYS = {"range_km", "nadir_angle_deg", "orbital_speed_m_s", "angular_speed_rad_s",
                "t_eff_s", "apparent_mag", "zeropoint_mag", "flux_per_px_e", "fwhm_arcsec",
                "peak_e_per_px", "cross_section"}


def run_json(capsys, *argv):
    assert main(["profile", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_profile_json_paper_case(capsys):
    out = run_json(capsys, "--height", "550", "--zenith", "70", "--length", "7.25",
                   "--width", "2.65", "--mag", "5", "--band", "g")
    assert PROFILE_KEYS <= set(out)
    assert out["range_km"] == pytest.approx(1293.8, abs=0.05)
    assert out["zeropoint_mag"] == 28.51
    cs = out["cross_section"]
    assert len(cs["offset_arcsec"]) == len(cs["e_per_px"]) > 100
    assert max(cs["e_per_px"]) == pytest.approx(out["peak_e_per_px"], rel=1e-4)
    # e_per_px sampled every p/40: summing every 40th sample adds up the pixels across.
    assert np.sum(cs["e_per_px"][::40]) == pytest.approx(out["flux_per_px_e"], rel=1e-3)


def test_profile_disk_and_table(capsys):
    out = run_json(capsys, "--height", "550", "--shape", "disk", "--radius", "1")
    assert out["fwhm_arcsec"] == pytest.approx(3.106, abs=0.002)
    paper = run_json(capsys, "--height", "550", "--zenith", "70")
    assert main(["profile", "--height", "550", "--zenith", "70"]) == 0
    table = capsys.readouterr().out
    fwhm_row = next(line for line in table.splitlines() if line.startswith("streak FWHM"))
    assert fwhm_row.split()[-2] == f"{paper['fwhm_arcsec']:.3f}"
    assert paper["fwhm_arcsec"] == pytest.approx(paper_case_fwhm(), abs=5e-4)


def paper_case_fwhm():
    """FWHM (arcsec) of the paper's streak, built here from its parts and measured in real
    space: GalSim draws box x annulus x Kolmogorov (no pixel) and the image is summed along
    the track (the code takes the Fourier slice instead). The 2.65 m side lies across the
    track, the 7.25 m side along it, foreshortened by cos(nadir angle); swapping them would
    widen the FWHM by 0.011"."""
    import galsim

    r_e, h, z = 6378.1, 550.0, np.radians(70.0)  # km
    nadir = np.arcsin(r_e / (r_e + h) * np.sin(z))
    range_m = (np.sqrt((r_e + h) ** 2 - (r_e * np.sin(z)) ** 2) - r_e * np.cos(z)) * 1e3
    arcsec = 180 * 3600 / np.pi / range_m  # arcsec per metre at the satellite
    box = galsim.Box(7.25 * np.cos(nadir) * arcsec, 2.65 * arcsec)
    outer, inner = 4.18 * arcsec, 2.558 * arcsec  # LSST M1 clear annulus
    eps2 = (inner / outer) ** 2
    pupil = (galsim.TopHat(outer, flux=1 / (1 - eps2))
             - galsim.TopHat(inner, flux=eps2 / (1 - eps2)))
    scale, n = 0.01, 1024
    drawn = galsim.Convolve([box, pupil, galsim.Kolmogorov(fwhm=0.67)]).drawImage(
        nx=n, ny=n, scale=scale, method="no_pixel")
    lsf = drawn.array.sum(axis=1)
    y = (np.arange(n) - n // 2) * scale
    half = lsf.max() / 2
    above = np.flatnonzero(lsf >= half)
    lo, hi = above[0], above[-1]
    left = y[lo - 1] + (half - lsf[lo - 1]) * scale / (lsf[lo] - lsf[lo - 1])
    right = y[hi] + (half - lsf[hi]) * scale / (lsf[hi + 1] - lsf[hi])
    return right - left


@pytest.mark.parametrize("argv,needle", [
    (["--height", "-5"], "height_km=-5.0"),
    (["--height", "nan"], "height_km=nan"),
    (["--height", "550", "--zenith", "90"], "zenith_deg=90.0"),
    (["--height", "550", "--band", "w"], "band='w'"),
    (["--height", "550", "--radius", "2"], "--radius"),
])
def test_profile_bad_input_one_line(capsys, argv, needle):
    assert main(["profile", *argv]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err


def test_python_dash_m():
    proc = subprocess.run([sys.executable, "-m", "inject", "profile", "--height", "-1"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.startswith("inject profile: error: height_km=-1.0")
