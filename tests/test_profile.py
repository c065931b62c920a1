"""Stationary profile and cross-section against closed forms and the paper's numbers."""
import galsim
import numpy as np
import pytest
from scipy import integrate, optimize

from inject import LSST, Disk, Seeing, StreakModel, Telescope
from inject.instrument import ARCSEC_PER_RAD
from inject.profile import defocus_kernel, line_spread, line_spreads


def test_defocus_kernel_has_unit_flux_and_radii():
    k = defocus_kernel(550.0)
    assert k.flux == pytest.approx(1.0, rel=1e-14)
    a_o = 4.18 / 550e3 * ARCSEC_PER_RAD
    assert a_o == pytest.approx(1.568, abs=5e-4)
    assert 2.558 / 550e3 * ARCSEC_PER_RAD == pytest.approx(0.959, abs=5e-4)
    # Uniform surface brightness between the radii, nothing outside or in the hole.
    sb = 1.0 / (np.pi * (a_o ** 2 - (a_o * LSST.obscuration) ** 2))
    assert k.xValue(0.5 * (a_o + 0.959), 0) == pytest.approx(sb, rel=1e-12)
    assert k.xValue(0.5, 0) == pytest.approx(0, abs=1e-12)
    assert k.xValue(1.6, 0) == pytest.approx(0, abs=1e-12)


def _annulus_bin_integral(lo, hi, a_o, a_i):
    """Exact integral of Bektesevic et al. (2018) eq. 6 over [lo, hi] (arcsec)."""
    def chord_area(x, a):  # integral of sqrt(a^2 - t^2) from 0 to x, for |x| clipped to a
        x = np.clip(x, -a, a)
        return 0.5 * (x * np.sqrt(a ** 2 - x ** 2) + a ** 2 * np.arcsin(x / a))
    norm = 2.0 / (np.pi * (a_o ** 2 - a_i ** 2))
    return norm * (chord_area(hi, a_o) - chord_area(lo, a_o)
                   - chord_area(hi, a_i) + chord_area(lo, a_i))


@pytest.mark.parametrize("range_km", [350.0, 550.0, 1293.8])
def test_annulus_line_profile_matches_bektesevic(range_km):
    a_o = 4.18 / (range_km * 1e3) * ARCSEC_PER_RAD
    a_i = a_o * LSST.obscuration
    p = 0.2
    cs = line_spread(defocus_kernel(range_km), p)
    # The pixel-integrated LSF at offset d is the closed form integrated over [d - p/2, d + p/2].
    expected = _annulus_bin_integral(cs.offset_arcsec - p / 2, cs.offset_arcsec + p / 2, a_o, a_i)
    assert np.abs(cs.lsf * p - expected).max() < 1e-4 * expected.max()
    # Without pixels, pointwise away from the square-root edges (where any sampled transform
    # rings at a level set by the sampling).
    raw = line_spread(defocus_kernel(range_km), step_arcsec=a_o / 2000)
    y = np.abs(raw.offset_arcsec)
    closed = 2 / (np.pi * (a_o ** 2 - a_i ** 2)) * (
        np.sqrt(np.clip(a_o ** 2 - y ** 2, 0, None)) - np.sqrt(np.clip(a_i ** 2 - y ** 2, 0, None)))
    smooth = (np.abs(y - a_o) > 0.03 * a_o) & (np.abs(y - a_i) > 0.03 * a_o)
    assert np.abs(raw.lsf - closed)[smooth].max() < 1e-4 * closed.max()


def test_kolmogorov_lsf_fwhm():
    psf = Seeing(0.67).profile()
    cs = line_spread(psf, step_arcsec=0.002)
    # The design notes quote 0.705"; direct quadrature of GalSim's own profile gives 0.7023".
    assert cs.fwhm() == pytest.approx(0.705, abs=0.004)

    def lsf(y):
        return 2 * integrate.quad(lambda x: psf.xValue(x, y), 0, 60, limit=400)[0]
    half = lsf(0.0) / 2
    quad_fwhm = 2 * optimize.brentq(lambda y: lsf(y) - half, 0.2, 0.5)
    assert cs.fwhm() == pytest.approx(quad_fwhm, rel=3e-4)


def test_gaussian_lsf_closed_form():
    sigma = 0.4
    cs = line_spread(galsim.Gaussian(sigma=sigma), step_arcsec=0.01)
    expected = np.exp(-0.5 * (cs.offset_arcsec / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma)
    assert np.abs(cs.lsf - expected).max() < 1e-6 * expected.max()
    assert cs.fwhm() == pytest.approx(2.3548200450309493 * sigma, rel=1e-4)


def test_vonkarman_narrower_than_kolmogorov():
    vk = line_spread(Seeing(0.67, "vonkarman").profile(), step_arcsec=0.005).fwhm()
    kol = line_spread(Seeing(0.67).profile(), step_arcsec=0.005).fwhm()
    assert 0.7 < vk / kol < 0.9


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0, 90.0])
def test_pixel_response_preserves_integral(angle):
    cs = line_spread(StreakModel(550, 40).profile, 0.2, pixel_angle_deg=angle)
    assert cs.lsf.sum() * cs.step == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("height,expected", [(550.0, 3.106), (350.0, 4.739)])
def test_disk_fwhm_reference(height, expected):
    model = StreakModel(height, 0.0, shape=Disk(1.0))
    assert model.fwhm_arcsec == pytest.approx(expected, abs=0.0015)


def test_paper_case():
    low, high = StreakModel(350, 70), StreakModel(550, 70)
    assert high.fwhm_arcsec == pytest.approx(1.48, rel=0.02)
    assert low.fwhm_arcsec == pytest.approx(2.08, rel=0.02)
    rate_ratio = ((low.flux_per_px / low.geometry.t_eff_s)
                  / (high.flux_per_px / high.geometry.t_eff_s))
    assert rate_ratio == pytest.approx(1.977, abs=0.001)
    assert low.geometry.t_eff_s / high.geometry.t_eff_s == pytest.approx(0.736, abs=0.001)
    assert low.peak_e_per_px / high.peak_e_per_px == pytest.approx(1.04, abs=0.01)


def test_dip_at_centre_means_peak_is_off_centre():
    """At 350 km the cross-section dips at its centre: peak is the max over offsets."""
    model = StreakModel(350, 70)
    offsets, e = model.cross_section()
    centre = np.interp(0.0, offsets, e)
    assert model.peak_e_per_px == pytest.approx(e.max(), rel=1e-4)
    assert 0.95 < centre / model.peak_e_per_px < 0.995


@pytest.mark.parametrize("model", [StreakModel(550, 70), StreakModel(350, 0, shape=Disk(1.0)),
                                   StreakModel(2000, 30, phi_deg=20, seeing=Seeing(1.2))])
def test_cross_section_sums_to_flux_per_pixel(model):
    """Summing pixels across the track (spacing p) gives the charge per pixel of track."""
    offsets, e = model.cross_section(half_width_arcsec=np.inf)
    p = model.pixel_scale
    for shift in (0.0, 0.37 * p):
        centres = np.arange(offsets[0] + shift, offsets[-1], p)
        total = np.interp(centres, offsets, e).sum()
        assert total == pytest.approx(model.flux_per_px, rel=1e-4)


def test_other_telescope():
    small = Telescope(outer_radius_m=0.5, inner_radius_m=0.0, pixel_scale_arcsec=1.0)
    model = StreakModel(550, 0, shape=Disk(0.1), telescope=small, seeing=Seeing(0))
    # Filled 1 m pupil at 550 km: a disk of radius 0.1875"; its LSF FWHM is 2 a sqrt(3)/2 for a
    # semicircle (half max of sqrt(a^2 - x^2) at x = a sqrt(3)/2), slightly widened by the disk.
    a = 0.5 / 550e3 * ARCSEC_PER_RAD
    assert model.fwhm_arcsec == pytest.approx(np.sqrt(3) * a, rel=0.1)


def _plain_line_spread(profile, pixel_scale, step, pixel_angle_deg=0.0):
    """The line-spread function as GalSim's plain two-column drawing gives it: the kx = 0
    column of ``drawKImage(nx=2)``, the pixel's boxes as sincs, one inverse FFT."""
    n = int(2 ** np.ceil(np.log2(max(2 * np.pi / profile.stepk / step, 64))))
    dk = 2 * np.pi / (n * step)
    slice_k = profile.drawKImage(nx=2, ny=n, scale=dk).array[:, 1]
    ky = (np.arange(n) - n // 2) * dk
    if pixel_scale is not None:
        a = np.radians(pixel_angle_deg)
        for width in (pixel_scale * abs(np.cos(a)), pixel_scale * abs(np.sin(a))):
            slice_k = slice_k * np.sinc(ky * width / (2 * np.pi))
    return np.fft.fftshift(np.fft.ifft(np.fft.ifftshift(slice_k))).real * n * dk / (2 * np.pi)


_MODELS = [dict(height_km=550, zenith_deg=70), dict(height_km=350, shape=Disk(1.0)),
           dict(height_km=2000, zenith_deg=30, phi_deg=20,
                seeing=Seeing(1.2, model="vonkarman")),
           dict(height_km=550, zenith_deg=30, seeing=Seeing(0.0)),
           dict(height_km=36000, zenith_deg=10, shape=Disk(3.0), seeing=Seeing(0.5)),
           dict(height_km=700, pupil="rubin", field_angle_deg=1.2, field_position_angle_deg=30)]
#: Profiles by the name of a function that builds one (at the test, not at collection).
_PROFILES = {**{f"model{i}": (lambda kw=kw: StreakModel(**kw).profile)
                for i, kw in enumerate(_MODELS)},
             "kolmogorov": lambda: Seeing(0.7).profile(),
             "gaussian": lambda: galsim.Gaussian(sigma=0.4),
             "annulus": lambda: defocus_kernel(550.0),
             # An offset and a Jacobian (even the identity) make GalSim draw two columns.
             "shifted": lambda: galsim.Gaussian(sigma=0.4).shift(0.05, 0.0),
             "identity_jacobian": lambda: defocus_kernel(550.0).rotate(0 * galsim.degrees),
             "rotated_box": lambda: galsim.Convolve(
                 Seeing(0.7).profile(), galsim.Box(1.0, 0.3).rotate(30 * galsim.degrees))}


@pytest.mark.parametrize("name", _PROFILES)
def test_line_spreads_equal_galsim_two_column_drawing_bit_for_bit(name):
    """However the transform's kx = 0 column is drawn (alone where GalSim's symmetry allows,
    once for both functions), every value equals the plain recipe's to the last bit."""
    profile = _PROFILES[name]()
    p = 0.2
    step = min(np.pi / profile.maxk / 2, p / 40)
    bare, pixelated = line_spreads(profile, p, step_arcsec=step)
    assert bare.lsf.tobytes() == _plain_line_spread(profile, None, step).tobytes()
    assert pixelated.lsf.tobytes() == _plain_line_spread(profile, p, step).tobytes()
    for angle in (0.0, 30.0, 90.0):
        cs = line_spread(profile, p, pixel_angle_deg=angle)
        default_step = min(np.pi / profile.maxk / 2, p / 16)
        assert cs.lsf.tobytes() == _plain_line_spread(profile, p, default_step, angle).tobytes()
