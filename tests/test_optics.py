"""The traced defocus kernel (inject.optics) against independent traces and closed forms.

The independent numbers come from batoid traces written out here (rays from a point through
the same model, histogrammed with the design's plate scale), from the spider vanes' geometry,
and from the issue's measurement of the edges against the annulus.
"""
import json
import os

import galsim
import numpy as np
import pytest

from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD, LSST
from inject.optics import (
    BAND_WAVELENGTH_NM,
    N_WAVELENGTHS,
    band_wavelengths,
    telescope,
    traced_kernel,
)
from inject.profile import Seeing

batoid = pytest.importorskip("batoid")

#: The design's plate scale, micron per arcsec (focal length 10.312 m).
UM_PER_ARCSEC = LSST.focal_length_m * 1e6 / ARCSEC_PER_RAD
WAVELENGTH_G = BAND_WAVELENGTH_NM["g"] * 1e-9
STOP_Z = 0.4393899  # the entrance pupil's plane in batoid's LSST models, m


@pytest.fixture(scope="module")
def on_axis_500():
    """At the g band's effective wavelength, which the independent traces here use."""
    return traced_kernel("g", 500.0, 0.0, n_rays=250_000, wavelength_nm=BAND_WAVELENGTH_NM["g"])


def _source(range_km):
    return np.array([0.0, 0.0, STOP_Z + range_km * 1e3])


def _fwhm(x, f):
    """Outermost half-maximum crossings, linearly interpolated."""
    half = 0.5 * f.max()
    above = np.flatnonzero(f >= half)
    lo, hi = above[0], above[-1]
    left = x[lo - 1] + (half - f[lo - 1]) * (x[lo] - x[lo - 1]) / (f[lo] - f[lo - 1])
    right = x[hi] + (half - f[hi]) * (x[hi + 1] - x[hi]) / (f[hi + 1] - f[hi])
    return right - left


def test_star_throughput_on_axis_is_the_spider_vanes_shadow(on_axis_500):
    # Four 5 cm vanes at 45 deg, each on a line 0.566/sqrt(2) m from the axis, cross the
    # annulus twice; the centre plate and cap lie inside the 2.558 m hole.
    d = 0.5656854249 / np.sqrt(2)
    chord = 2 * (np.sqrt(4.18 ** 2 - d ** 2) - np.sqrt(2.558 ** 2 - d ** 2))
    blocked = 4 * 0.05 * chord / (np.pi * (4.18 ** 2 - 2.558 ** 2))
    assert blocked == pytest.approx(0.0190, abs=1e-4)
    assert on_axis_500.star_throughput == pytest.approx(1 - blocked, abs=5e-4)


def test_the_kernel_holds_the_light_a_star_keeps(on_axis_500):
    k = on_axis_500
    assert k.image.sum() * k.scale ** 2 == pytest.approx(k.transmitted, rel=1e-12)
    # On axis the point's beam and the star's cross the same vanes: nothing more is lost.
    assert k.transmitted == pytest.approx(1.0, abs=2e-3)
    assert np.hypot(*k.centroid) < 0.002
    assert k.image.shape[0] % 2 == 1 and k.image.shape[0] == k.image.shape[1]


def _rim_radii(range_km=None, focus_offset_um=0.0):
    """Mean radii (arcsec, by the design's plate scale) at which rays through the rims of M1's
    clear annulus land, traced through batoid's plain g-band model: from a point on the axis
    ``range_km`` away, or from a star (None), the detector shifted by ``focus_offset_um``."""
    optic = batoid.Optic.fromYaml(os.path.join(batoid.datadir, "LSST", "LSST_g.yaml"))
    if focus_offset_um:
        optic = optic.withGloballyShiftedOptic("Detector", [0.0, 0.0, focus_offset_um * 1e-6])
    phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    radii = {}
    for name, rho in (("inner", 2.558 + 1e-4), ("outer", 4.18 - 1e-4)):
        x, y = rho * np.cos(phi), rho * np.sin(phi)
        z = np.full_like(x, STOP_Z)
        if range_km is None:
            u = np.vstack([0 * x, 0 * x, -np.ones_like(x)])
        else:
            u = np.vstack([x, y, z]) - _source(range_km)[:, None]
            u /= np.linalg.norm(u, axis=0)
        start = np.vstack([x, y, z]) - 15.0 * u
        out = optic.trace(batoid.RayVector(*start, *u, wavelength=WAVELENGTH_G))
        assert not out.vignetted.any()
        radii[name] = np.hypot(out.x, out.y).mean() * 1e6 / UM_PER_ARCSEC
    return radii


def test_edges_at_500_km_against_rim_rays_and_the_annulus(on_axis_500):
    """The half-plateau radii against rays through the rims of M1's clear annulus, traced
    here through batoid's plain g-band model and scaled by the design's plate scale."""
    radii = _rim_radii(500.0)
    assert on_axis_500.inner_radius == pytest.approx(radii["inner"], rel=5e-3)
    assert on_axis_500.outer_radius == pytest.approx(radii["outer"], rel=5e-3)
    # The measurement: the hole ~0.1" wider, the outer edge ~0.06" narrower than the
    # annulus R / r (1.055" and 1.724").
    annulus_inner = 2.558 / 500e3 * ARCSEC_PER_RAD
    annulus_outer = 4.18 / 500e3 * ARCSEC_PER_RAD
    assert 0.08 < on_axis_500.inner_radius - annulus_inner < 0.15
    assert -0.08 < on_axis_500.outer_radius - annulus_outer < -0.04


def test_a_focus_offset_makes_a_star_a_defocused_annulus():
    """A point 10^6 km away (defocus 0.001") with the detector 200 um towards L3: its edges
    against rim rays of a star traced through the plain model with the detector moved the
    same way (the paraxial R f / dz would be 0.99" and 1.62")."""
    k = traced_kernel("g", 1e6, 0.0, n_rays=250_000, focus_offset_um=-200.0,
                      wavelength_nm=BAND_WAVELENGTH_NM["g"])
    radii = _rim_radii(None, focus_offset_um=-200.0)
    assert k.focus_offset_um == -200.0
    assert k.inner_radius == pytest.approx(radii["inner"], rel=5e-3)
    assert k.outer_radius == pytest.approx(radii["outer"], rel=5e-3)
    assert 1.0 < radii["inner"] < 1.3 and 1.6 < radii["outer"] < 1.8


def test_fwhm_with_seeing_agrees_with_a_histogrammed_trace(on_axis_500):
    """500 km on axis, 0.67" Kolmogorov seeing: the kernel's cross-section FWHM against
    random rays from the point through the same model, projected, histogrammed and
    convolved with the seeing's own projection."""
    optic = telescope("g")
    rays = batoid.RayVector.asPolar(optic=optic, wavelength=WAVELENGTH_G,
                                    source=_source(500.0), nrandom=400_000, rng=5)
    out = optic.trace(rays)
    y = out.y[~out.vignetted] * 1e6 / UM_PER_ARCSEC
    step = 0.01
    edges = (np.arange(-1000, 1001) - 0.5) * step
    hist, _ = np.histogram(y, edges)
    seeing = galsim.Kolmogorov(fwhm=0.67).drawImage(nx=1501, ny=1501, scale=step,
                                                     method="no_pixel").array.sum(axis=1)
    lsf = np.convolve(hist.astype(float), seeing, mode="same")
    expected = _fwhm(np.arange(-1000, 1000) * step, lsf)
    got = on_axis_500.cross_section(0.0, Seeing(0.67)).fwhm()
    assert got == pytest.approx(expected, rel=5e-3)
    # The annulus and seeing give 3.2" here: the real pupil is measurably wider or narrower.
    assert 3.0 < got < 3.6


def test_on_axis_the_cross_section_is_the_same_along_and_across(on_axis_500):
    seeing = Seeing(0.67)
    along = on_axis_500.cross_section(0.0, seeing).fwhm()
    across = on_axis_500.cross_section(90.0, seeing).fwhm()
    assert along == pytest.approx(across, rel=1e-4)


def test_at_very_large_range_the_kernel_is_the_in_focus_spot():
    """At 10^6 km (defocus 0.001") the kernel is the telescope's own spot: its rms radius
    against a star traced here through batoid's plain g-band model, at tens of mas."""
    k = traced_kernel("g", 1e6, 0.0, n_rays=250_000, wavelength_nm=BAND_WAVELENGTH_NM["g"])
    n = k.image.shape[0]
    c = (np.arange(n) - n // 2) * k.scale
    xx, yy = np.meshgrid(c, c)
    w = k.image / k.image.sum()
    rms_kernel = np.sqrt(np.sum(w * ((xx - k.centroid[0]) ** 2 + (yy - k.centroid[1]) ** 2)))

    optic = batoid.Optic.fromYaml(os.path.join(batoid.datadir, "LSST", "LSST_g.yaml"))
    rays = batoid.RayVector.asPolar(optic=optic, wavelength=WAVELENGTH_G, theta_x=0.0,
                                    theta_y=0.0, nrandom=200_000, rng=3)
    out = optic.trace(rays)
    ok = ~out.vignetted
    x, y = out.x[ok] - out.x[ok].mean(), out.y[ok] - out.y[ok].mean()
    rms_star = np.sqrt(np.mean(x ** 2 + y ** 2)) * 1e6 / UM_PER_ARCSEC
    # The image's 0.01" pixels add scale^2/6 to the mean square radius.
    assert rms_kernel == pytest.approx(np.sqrt(rms_star ** 2 + k.scale ** 2 / 6), rel=0.03)
    assert 0.02 < rms_kernel < 0.1


@pytest.mark.slow
def test_fwhm_with_seeing_converges_in_ray_count():
    """1.5 deg, 500 km: across and along the field radius, to 0.1% from 250 000 to 4 000 000
    rays (measured: 0.003%)."""
    seeing = Seeing(0.67)
    coarse = traced_kernel("g", 500.0, 1.5, n_rays=250_000)
    fine = traced_kernel("g", 500.0, 1.5, n_rays=4_000_000)
    for angle in (0.0, 90.0):
        a = coarse.cross_section(angle, seeing).fwhm()
        b = fine.cross_section(angle, seeing).fwhm()
        assert a == pytest.approx(b, rel=1e-3)
    # Off axis the kernel is stretched across the field radius (tangentially).
    assert fine.cross_section(0.0, seeing).fwhm() > 1.02 * fine.cross_section(90.0, seeing).fwhm()


@pytest.mark.parametrize("kwargs", [dict(band="q"), dict(field_angle_deg=2.5),
                                    dict(range_km=-1.0), dict(n_rays=0),
                                    dict(focus_offset_um=float("nan"))])
def test_bad_input_is_an_input_error(kwargs):
    args = dict(band="g", range_km=500.0, field_angle_deg=0.0, n_rays=10_000) | kwargs
    with pytest.raises(InputError):
        traced_kernel(**args)


def _photon_weights(waves_nm):
    """The g band's photons from the Sun at ``waves_nm``: GalSim's LSST throughput times
    GalSim's photon density of a 5772 K blackbody (F_lambda given, photons worked out by
    GalSim)."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    sed = galsim.SED(lambda w: (w * 1e-9) ** -5 / np.expm1(h * c / (w * 1e-9 * k * 5772.0)),
                     "nm", "flambda")
    return galsim.Bandpass("LSST_g.dat", "nm")(waves_nm) * sed(waves_nm)


def test_the_band_is_cut_into_slices_of_the_suns_photons():
    """One wavelength is the photon-weighted mean of the Sun's light through g (GalSim's
    throughput and SED); slices of equal photons keep that mean and run blue to red."""
    fine = np.linspace(386.3, 567.0, 20001)
    photons = _photon_weights(fine)
    mean = np.trapezoid(photons * fine, fine) / np.trapezoid(photons, fine)
    [one], [weight] = band_wavelengths("g", 1)
    assert one == pytest.approx(mean, abs=0.02) and weight == 1.0
    waves, weights = band_wavelengths("g", 8)
    assert np.dot(waves, weights) == pytest.approx(mean, abs=0.02)
    assert np.all(np.diff(waves) > 0) and 386.3 < waves[0] and waves[-1] < 567.0
    assert weights == (1 / 8,) * 8
    # Half the photons lie blueward of the 4th/5th slices' boundary.
    median = fine[np.searchsorted(np.cumsum(photons), 0.5 * photons.sum())]
    assert waves[3] < median < waves[4]


def _plain_g(focus_offset_um=0.0):
    optic = batoid.Optic.fromYaml(os.path.join(batoid.datadir, "LSST", "LSST_g.yaml"))
    if focus_offset_um:
        optic = optic.withGloballyShiftedOptic("Detector", [0.0, 0.0, focus_offset_um * 1e-6])
    return optic


def _band_rays(range_km, focus_offset_um=0.0, n_waves=12, rays=30_000):
    """Random rays from a point on the axis ``range_km`` away through batoid's plain g model,
    at ``n_waves`` wavelengths evenly over the band weighted by the Sun's photons: their
    landing points (arcsec, by the model's own plate scale from a star 10" off axis) and
    weights."""
    optic = _plain_g(focus_offset_um)
    edges = np.linspace(386.3, 567.0, n_waves + 1)
    waves = 0.5 * (edges[1:] + edges[:-1])
    weights = _photon_weights(waves)
    off = np.radians(10.0 / 3600)
    star = optic.trace(batoid.RayVector.asPolar(
        optic=optic, wavelength=np.dot(waves, weights) / weights.sum() * 1e-9,
        theta_x=0.0, theta_y=off, nrandom=20_000, rng=1))
    m_per_arcsec = star.y[~star.vignetted].mean() / 10.0
    xs, ys, ws = [], [], []
    for i, (wave, weight) in enumerate(zip(waves, weights)):
        out = optic.trace(batoid.RayVector.asPolar(optic=optic, wavelength=wave * 1e-9,
                                                   source=_source(range_km), nrandom=rays,
                                                   rng=10 + i))
        ok = ~out.vignetted
        xs.append(out.x[ok] / m_per_arcsec)
        ys.append(out.y[ok] / m_per_arcsec)
        ws.append(np.full(ok.sum(), weight / rays))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(ws)


def _rms_radius(k):
    n = k.image.shape[0]
    c = (np.arange(n) - n // 2) * k.scale
    xx, yy = np.meshgrid(c, c)
    w = k.image / k.image.sum()
    # The image's pixels add scale^2/6 to the mean square radius.
    return np.sqrt(np.sum(w * ((xx - k.centroid[0]) ** 2 + (yy - k.centroid[1]) ** 2))
                   - k.scale ** 2 / 6)


@pytest.mark.parametrize("focus", [-10.0, 0.0, 10.0])
def test_the_band_kernel_has_the_spread_of_an_independent_band_trace(focus):
    """1293.8 km (550 km seen at zenith angle 70) on the axis, the detector moved by
    ``focus`` um: the kernel's rms radius against random rays at 12 wavelengths through the
    plain g model. A one-wavelength kernel at 476.7 nm is 1.1% wider at the design's focus."""
    x, y, w = _band_rays(1293.8, focus)
    expected = np.sqrt(np.average(x ** 2 + y ** 2, weights=w))
    k = traced_kernel("g", 1293.8, 0.0, n_rays=100_000, focus_offset_um=focus)
    assert _rms_radius(k) == pytest.approx(expected, rel=2e-3)
    assert k.wavelengths_nm == band_wavelengths("g", N_WAVELENGTHS)[0]
    if focus == 0:
        mono = traced_kernel("g", 1293.8, 0.0, n_rays=100_000,
                             wavelength_nm=BAND_WAVELENGTH_NM["g"])
        assert _rms_radius(mono) / expected - 1 > 0.008


def _seeing_fwhm(y, w, seeing_fwhm=0.67, step=0.005):
    """FWHM of the rays' projection ``y`` (weights ``w``) convolved with Kolmogorov seeing,
    through the Fourier transform (GalSim's of the seeing, the histogram's bins undone)."""
    n = 2 ** 14
    grid = (np.arange(n) - n // 2) * step
    hist, _ = np.histogram(y, np.append(grid - step / 2, grid[-1] + step / 2), weights=w)
    k = 2 * np.pi * np.fft.rfftfreq(n, step)
    seeing = galsim.Kolmogorov(fwhm=seeing_fwhm)
    mtf = np.array([seeing.kValue(0.0, kk).real for kk in k])
    spectrum = np.fft.rfft(np.fft.ifftshift(hist)) / np.sinc(k * step / (2 * np.pi)) * mtf
    return _fwhm(grid, np.fft.fftshift(np.fft.irfft(spectrum, n)))


def test_inject_profile_follows_the_focus(cli):
    """``inject profile --focus-offset``: the streak of a 5 cm disk at 550 km seen at zenith
    angle 70 (1293.8 km) on the axis, 0.67" seeing, against random rays at 12 wavelengths
    through batoid's plain g model with its detector moved, projected and convolved with the
    seeing here (1.480" and 1.312"). Moving the detector 10 um away from L3 narrows the streak
    by 11%."""
    fwhm = {}
    for focus in (0.0, 10.0):
        status, out, err = cli("profile", "--height", "550", "--zenith", "70", "--shape",
                               "disk", "--radius", "0.05", "--pupil", "rubin",
                               "--focus-offset", focus, "--json")
        assert status == 0, err
        result = json.loads(out)
        assert result["focus_offset_um"] == focus
        _, y, w = _band_rays(1293.8, focus)
        fwhm[focus] = result["fwhm_arcsec"]
        assert result["fwhm_arcsec"] == pytest.approx(_seeing_fwhm(y, w), rel=3e-3)
    assert fwhm[10.0] < 0.95 * fwhm[0.0]
    status, _, err = cli("profile", "--height", "550", "--focus-offset", "5", strict=True)
    assert status == 2 and "--focus-offset=5" in err and "--pupil rubin" in err
