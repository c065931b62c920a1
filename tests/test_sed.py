"""The satellite's spectrum (``sed:``) that the traced pupil's kernel is taken over.

Independent numbers: a blackbody's AB colour through GalSim's LSST throughput files integrated
here with numpy (not GalSim's SED), the photon-weighted mean wavelength of throughput times
blackbody integrated the same way, and the camera's chromatic focus (a bluer spectrum, a wider
ring in g).
"""
import json
import os

import galsim
import numpy as np
import pytest
from test_pupil import SAT
from test_pupil import _ccd_scene as _pupil_scene

from inject import SceneError, parse_scene
from inject.cli.main import main
from inject.errors import InputError
from inject.optics import (
    SUN_TEMPERATURE_K,
    blackbody_colour,
    colour_temperature,
    kernel,
)
from inject.scene import streak_models
from inject.streak import StreakModel
from inject.survey.constellation import parse_constellation

pytest.importorskip("batoid")

#: h c / k, nm K.
HC_OVER_K = 1.438776877e7


def _throughput(band):
    """GalSim's LSST total throughput table: wavelength (nm), throughput."""
    path = os.path.join(galsim.meta_data.share_dir, "bandpasses", f"LSST_{band}.dat")
    wave, through = np.loadtxt(path, unpack=True)
    return wave, through


def _ab_magnitude(band, temperature_k):
    """AB magnitude (up to one constant for all bands) of a blackbody: the photons counted,
    f_nu weighted by T / lambda, against a flat f_nu's."""
    wave, through = _throughput(band)
    fine = np.linspace(wave.min(), wave.max(), 20001)
    t = np.interp(fine, wave, through)
    f_lambda = fine ** -5.0 / np.expm1(HC_OVER_K / (fine * temperature_k))
    f_nu = f_lambda * fine ** 2
    return -2.5 * np.log10(np.trapezoid(f_nu * t / fine, fine) / np.trapezoid(t / fine, fine))


def _photon_mean_wavelength(band, temperature_k):
    wave, through = _throughput(band)
    fine = np.linspace(wave.min(), wave.max(), 20001)
    photons = np.interp(fine, wave, through) * fine ** -4.0 / np.expm1(
        HC_OVER_K / (fine * temperature_k))
    return np.trapezoid(photons * fine, fine) / np.trapezoid(photons, fine)


@pytest.mark.parametrize("blue, red", [("g", "r"), ("r", "i"), ("u", "g")])
@pytest.mark.parametrize("temperature", [3500.0, SUN_TEMPERATURE_K, 12000.0])
def test_a_blackbodys_colour_is_a_numpy_integral_of_the_throughputs(blue, red, temperature):
    expected = _ab_magnitude(blue, temperature) - _ab_magnitude(red, temperature)
    assert blackbody_colour(blue, red, temperature) == pytest.approx(expected, abs=2e-3)
    assert colour_temperature(blue, red, expected) == pytest.approx(temperature, rel=2e-3)


def test_colours_beyond_the_blackbodys_and_bands_out_of_order_are_refused():
    with pytest.raises(InputError, match="3000 to 30000 K"):
        colour_temperature("g", "r", 2.5)
    with pytest.raises(InputError, match="bluer band first"):
        colour_temperature("r", "g", 0.5)


def test_the_kernel_is_traced_over_the_satellites_photons(cheap_grid):
    """The wavelengths' photon-weighted mean follows the spectrum as a numpy integral of
    throughput x blackbody does (the slices' means average to it), and the camera's chromatic
    focus makes a bluer satellite's ring wider in g: 1.70" at 420 nm against 1.32" at 540 nm
    at this range through batoid's g model."""
    means, radii = {}, {}
    for temperature in (3500.0, SUN_TEMPERATURE_K, 12000.0):
        k = kernel("g", 1293.8, temperature_k=temperature)
        means[temperature] = np.dot(k.wavelengths_nm, k.wavelength_weights)
        assert means[temperature] == pytest.approx(
            _photon_mean_wavelength("g", temperature), abs=0.3)
        radii[temperature] = k.outer_radius
    assert means[3500.0] > means[SUN_TEMPERATURE_K] + 5 > means[12000.0] + 10
    assert radii[3500.0] < radii[SUN_TEMPERATURE_K] < radii[12000.0]


def _ccd_scene(**keys):
    return _pupil_scene(**{"band": "g", "zenith": 0, **keys})


def test_a_scenes_sed_reaches_its_streaks_model_and_truth(cheap_grid):
    blue = dict(SAT, sed={"blackbody_k": 9000}, track={"x0": 30, "y0": 40, "angle": 10})
    coloured = dict(SAT, sed={"g-r": 0.62}, track={"x0": 30, "y0": 80, "angle": 10})
    scene = parse_scene(_ccd_scene(satellites=[blue, coloured, dict(
        SAT, track={"x0": 30, "y0": 120, "angle": 10})]))
    models = streak_models(scene)
    assert [m.sed_temperature_k for m in models] == [
        9000.0, colour_temperature("g", "r", 0.62), SUN_TEMPERATURE_K]
    assert models[0].profile_key != models[2].profile_key
    assert models[0].summary()["sed_temperature_k"] == 9000.0
    # The kernel each model draws is the one traced over its own spectrum.
    for model in models:
        assert model.traced_kernel.wavelengths_nm == kernel(
            "g", model.geometry.range_km, temperature_k=model.sed_temperature_k).wavelengths_nm


def test_an_sed_is_refused_without_the_traced_pupil_or_in_a_bad_form():
    sat = dict(SAT, sed={"blackbody_k": 9000}, track={"x0": 30, "y0": 40, "angle": 10})
    with pytest.raises(SceneError, match=r"satellites\[0\]\.sed: only with pupil: rubin"):
        parse_scene(_ccd_scene(pupil="annulus", satellites=[sat]))
    for bad, words in (("red", "give sun"), ({"blackbody_k": 100}, "3000, 30000"),
                       ({"g-r": 0.5, "blackbody_k": 5000}, "give sun"),
                       ({"gr": 0.5}, "not blackbody_k or a colour"),
                       ({"r-g": 0.5}, "bluer band first")):
        with pytest.raises(SceneError, match=words):
            parse_scene(_ccd_scene(satellites=[dict(sat, sed=bad)]))
    with pytest.raises(InputError, match="sed_temperature_k"):
        StreakModel(550, sed_temperature_k=4000.0)


def test_a_constellations_sed_is_its_satellites():
    raw = {"shape": SAT["shape"], "mag": 5.0, "epoch": "2026-06-15T23:00:00",
           "shells": [{"height": 550, "inclination": 53, "planes": 2, "per_plane": 2,
                       "phasing": 1}]}
    assert parse_constellation(dict(raw, pupil="rubin", sed={"blackbody_k": 4000})
                               ).satellite.sed_temperature_k == 4000.0
    with pytest.raises(SceneError, match=r"satellite\.sed: only with pupil: rubin"):
        parse_constellation(dict(raw, sed={"blackbody_k": 4000}))


def test_the_profile_command_takes_an_sed(cheap_grid, capsys):
    assert main(["profile", "--height", "550", "--pupil", "rubin", "--sed", "4500K",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sed_temperature_k"] == 4500.0
    assert main(["profile", "--height", "550", "--sed", "4500K"]) == 2
    assert "only applies to --pupil rubin" in capsys.readouterr().err
