"""Absolute photometry pinned to an independent computation.

Everything expected here is computed in this file from first principles: the constants are
typed in (IAU 2015 nominal Earth values, SMTN-002 v1.9 zero points), the geometry is solved
with vectors in the Earth-centred plane of the line of sight (not with the paper's formulas
the code uses), and the charge per pixel of track is ``10^(0.4 (ZP - m)) t_eff``. A bug in
any factor of the streak's flux (speed, range, t_eff, zero point or its sign, a magnitude
offset, extinction applied to the streak) changes the numbers checked in every output: the
``profile --json`` summary, the TRUTH table of ``simulate`` and that of ``add-streak``.
"""
import json

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

from inject import StreakModel
from inject.cli.main import main

R_EARTH_M = 6378.1e3        # IAU 2015 nominal equatorial radius
GM_EARTH = 3.986004e14      # IAU 2015 nominal, m^3 s^-2
ARCSEC = np.pi / (180 * 3600)
PIXEL_ARCSEC = 0.2          # LSSTCam
#: SMTN-002 v1.9: AB magnitude giving 1 e-/s at airmass 1 (extinction included).
ZERO_POINTS = {"u": 26.52, "g": 28.51, "r": 28.36, "i": 28.17, "z": 27.78, "y": 26.82}


def pass_geometry(height_km, zenith_deg, phi_deg=90.0):
    """Range (m), nadir angle (rad) and angular speed (rad/s) by vectors.

    Earth's centre at the origin, the telescope at (0, 0, R), the line of sight tilted by
    ``z`` towards +x. The satellite is where the line meets the sphere of radius R + h; its
    velocity (circular orbit, speed sqrt(GM / (R + h))) is perpendicular to its radius, at
    ``phi`` from the normal of the plane of the line of sight (phi = 90: in that plane).
    """
    z = np.radians(zenith_deg)
    telescope = np.array([0.0, 0.0, R_EARTH_M])
    u = np.array([np.sin(z), 0.0, np.cos(z)])
    a = R_EARTH_M + height_km * 1e3
    # |T + r u|^2 = a^2: r^2 + 2 r (T.u) + |T|^2 - a^2 = 0, the positive root.
    b = telescope @ u
    r = -b + np.sqrt(b * b - (R_EARTH_M ** 2 - a * a))
    sat = telescope + r * u
    nadir = -sat / np.linalg.norm(sat)
    to_telescope = -u
    nadir_angle = np.arccos(np.clip(nadir @ to_telescope, -1, 1))
    in_plane = np.cross(np.array([0.0, 1.0, 0.0]), sat)
    in_plane /= np.linalg.norm(in_plane)
    normal = np.array([0.0, 1.0, 0.0])
    phi = np.radians(phi_deg)
    v = np.sqrt(GM_EARTH / a) * (np.cos(phi) * normal + np.sin(phi) * in_plane)
    v_t = v - (v @ u) * u  # the part across the line of sight
    return r, nadir_angle, np.linalg.norm(v_t) / r


def expected_photometry(height_km, zenith_deg, phi_deg, mag, band, ref_range_km=550.0):
    """(range km, nadir deg, t_eff s, apparent mag, e- per pixel of track), independently."""
    r, nadir, omega = pass_geometry(height_km, zenith_deg, phi_deg)
    t_eff = PIXEL_ARCSEC * ARCSEC / omega
    apparent = mag + 5 * np.log10(r / 1e3 / ref_range_km) - 2.5 * np.log10(np.cos(nadir))
    flux = 10 ** (0.4 * (ZERO_POINTS[band] - apparent)) * t_eff
    return r / 1e3, np.degrees(nadir), t_eff, apparent, flux


@pytest.mark.parametrize("height,charge", [(550, 75_772), (350, 110_325)])
def test_paper_case_charge_per_pixel_of_track(height, charge):
    # The paper's satellite (7.25 x 2.65 m box), g = 5 at 550 km face-on, z = 70 deg.
    *_, flux = expected_photometry(height, 70.0, 90.0, 5.0, "g")
    assert flux == pytest.approx(charge, abs=0.5)  # the published figure, rounded to 1 e-
    model = StreakModel(height, 70.0, mag=5.0, band_name="g")
    assert model.flux_per_px == pytest.approx(flux, rel=1e-9)


def test_geometry_by_vectors_matches_the_paper_numbers():
    r, nadir, omega = pass_geometry(550.0, 0.0)
    assert r == pytest.approx(550e3, rel=1e-12)
    assert np.degrees(omega) == pytest.approx(0.7902, abs=5e-5)  # the paper's 0.79 deg/s
    r, nadir, _ = pass_geometry(550.0, 70.0)
    assert r / 1e3 == pytest.approx(1293.8, abs=0.05) and np.degrees(nadir) == pytest.approx(
        59.89, abs=0.005)


def check_row(row, height, zenith, phi, mag, band, rel=1e-9):
    """One output's photometry against the independent computation, and against itself:
    ``flux_per_px = 10^(0.4 (ZP - m)) t_eff`` with the reported m and t_eff."""
    r, nadir, t_eff, apparent, flux = expected_photometry(height, zenith, phi, mag, band)
    assert row["range_km"] == pytest.approx(r, rel=rel)
    assert row["nadir_angle_deg"] == pytest.approx(nadir, rel=rel, abs=1e-9)
    assert row["t_eff_s"] == pytest.approx(t_eff, rel=rel)
    assert row["apparent_mag"] == pytest.approx(apparent, rel=rel)
    assert row["flux_per_px_e"] == pytest.approx(flux, rel=rel)
    assert row["flux_per_px_e"] == pytest.approx(
        10 ** (0.4 * (ZERO_POINTS[band] - row["apparent_mag"])) * row["t_eff_s"], rel=1e-12)


CASES = [(550.0, 70.0, 90.0, 5.0, "g"), (350.0, 70.0, 90.0, 5.0, "g"),
         (1200.0, 30.0, 40.0, 7.5, "r"), (20000.0, 55.0, 0.0, 3.0, "y"),
         (400.0, 0.0, 120.0, 6.0, "u")]


@pytest.mark.parametrize("height,zenith,phi,mag,band", CASES)
def test_profile_json(capsys, height, zenith, phi, mag, band):
    assert main(["profile", "--height", str(height), "--zenith", str(zenith), "--phi", str(phi),
                 "--mag", str(mag), "--band", band, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["zeropoint_mag"] == ZERO_POINTS[band]
    check_row(out, height, zenith, phi, mag, band)


def test_simulate_truth(tmp_path):
    scene = {"seed": 2, "zenith": 55.0, "band": "r",
             "detector": {"type": "itl", "nx": 300, "ny": 200},
             "sky": False, "stars": False, "noise": False,
             "satellites": [{"height": h, "phi": phi, "mag": mag,
                             "shape": {"type": "box", "length": 7.25, "width": 2.65},
                             "track": {"x0": 60.0, "y0": 50.0 + 40 * i, "angle": 10.0,
                                       "length": 150.0}}
                            for i, (h, phi, mag) in enumerate([(550.0, 90.0, 5.0),
                                                               (1200.0, 40.0, 8.0),
                                                               (20000.0, 0.0, 3.0)])]}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene))
    out = tmp_path / "out.fits"
    assert main(["simulate", str(path), "-o", str(out)]) == 0
    truth = Table.read(out, hdu="TRUTH")
    model = fits.getdata(out, "STREAK_MODEL").astype(np.float64)
    for row, sat in zip(truth, scene["satellites"]):
        check_row(row, sat["height"], 55.0, sat["phi"], sat["mag"], "r")
    # and the image holds that charge: F L over the three tracks (a little of the
    # wings falls outside the 300 x 200 image)
    total = sum(expected_photometry(s["height"], 55.0, s["phi"], s["mag"], "r")[-1] * 150.0
                for s in scene["satellites"])
    assert total * (1 - 2e-3) < model.sum() <= total * (1 + 1e-4)


def test_add_streak_truth(tmp_path):
    data = np.zeros((200, 240), np.float32)
    path = tmp_path / "in.fits"
    fits.PrimaryHDU(data).writeto(path)
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(path), "-o", str(out), "--height", "800", "--zenith", "35",
                 "--phi", "60", "--mag", "6.5", "--band", "i", "--x0", "60.5", "--y0", "100.2",
                 "--angle", "-20", "--track-length", "80", "--gain", "1.0", "--no-noise"]) == 0
    truth = Table.read(out, hdu="TRUTH")
    check_row(truth[0], 800.0, 35.0, 60.0, 6.5, "i")
    with fits.open(out) as hdus:
        injected = hdus["STREAK_MODEL"].data.astype(np.float64)
    flux = expected_photometry(800.0, 35.0, 60.0, 6.5, "i")[-1]
    assert flux * 80 * (1 - 2e-3) < injected.sum() <= flux * 80 * (1 + 1e-4)
