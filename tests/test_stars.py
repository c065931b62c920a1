"""Star counts, star fields, catalogs and the phase-stamp star renderer."""
import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from scipy import stats

from inject import FileFormatError, InputError, SceneError, pointing_wcs
from inject import stars as st
from inject.scene import rng

PIXEL = 0.2
PSF = galsim.Kolmogorov(fwhm=0.67)


@pytest.fixture(scope="module")
def stamps():
    return st.psf_stamps(PSF, PIXEL)


# --- counts -------------------------------------------------------------------------------

def test_bahcall_soneira_reference_counts():
    # The paper: N(<20) = 1440 at b = 90, 5191 at b = 30, l = 90.
    assert st.cumulative_counts(20.0, 0.0, 90.0) == pytest.approx(1440, rel=0.01)
    assert st.cumulative_counts(20.0, 90.0, 30.0) == pytest.approx(5191, rel=0.01)
    # Symmetric in b, vectorised over magnitude, increasing with magnitude.
    assert st.cumulative_counts(20.0, 90.0, -30.0) == st.cumulative_counts(20.0, 90.0, 30.0)
    m = np.linspace(8, 28, 201)
    n = st.cumulative_counts(m, 45.0, 40.0)
    assert n.shape == m.shape and np.all(np.diff(n) > 0)


def test_counts_refuse_low_latitude_without_override():
    with pytest.raises(InputError, match=r"\|b\| >= 20"):
        st.cumulative_counts(20.0, 0.0, 10.0)
    with pytest.raises(InputError, match="density_per_deg2"):
        st.StarFieldSpec(galactic_b=5.0)
    spec = st.StarFieldSpec(galactic_b=5.0, density_per_deg2=1e4)
    assert spec.counts(spec.mag_limit) == pytest.approx(1e4)


def test_spec_checks():
    with pytest.raises(InputError, match="mag_bright"):
        st.StarFieldSpec(mag_bright=24.0, mag_limit=20.0)
    with pytest.raises(InputError, match="density_per_deg2"):
        st.StarFieldSpec(density_per_deg2=-1.0)
    with pytest.raises(InputError, match="band"):
        st.sample_stars(st.StarFieldSpec(), 1.0, "w", rng(1, "stars"))


def test_density_override_keeps_the_shape():
    model = st.StarFieldSpec(galactic_l=90, galactic_b=30, mag_limit=22)
    scaled = st.StarFieldSpec(galactic_l=90, galactic_b=30, mag_limit=22, density_per_deg2=1000)
    assert scaled.counts(22.0) == pytest.approx(1000)
    m = np.array([14.0, 18.0, 21.0])
    ratio = scaled.counts(m) / model.counts(m)
    assert np.allclose(ratio, ratio[0], rtol=1e-12)


# --- sampling -----------------------------------------------------------------------------

def test_sampled_count_and_magnitudes_follow_the_model():
    spec = st.StarFieldSpec(galactic_l=90, galactic_b=30, mag_limit=24, mag_bright=12)
    area = 1.0
    mags = st.sample_stars(spec, area, "r", rng(7, "stars"))
    expected = area * (spec.counts(24.0) - spec.counts(12.0))
    assert abs(mags.size - expected) < 4 * np.sqrt(expected)
    assert mags.min() >= 12 and mags.max() <= 24

    def cdf(m):
        return (spec.counts(m) - spec.counts(12.0)) / (spec.counts(24.0) - spec.counts(12.0))
    assert stats.kstest(mags, cdf).pvalue > 1e-3
    # Same seed, same stars.
    assert np.array_equal(mags, st.sample_stars(spec, area, "r", rng(7, "stars")))


def test_star_field_positions():
    spec = st.StarFieldSpec(density_per_deg2=1e7)  # ~800 stars on 220 x 120 px
    field = st.star_field(spec, (100, 200), PIXEL, "g", rng(3, "stars"), margin_px=10)
    assert field["x"].size == field["y"].size == field["mag"].size > 0
    assert field["x"].min() >= -10.5 and field["x"].max() < 209.5
    assert field["y"].min() >= -10.5 and field["y"].max() < 109.5
    assert (field["x"] < -0.5).any()  # the margin is used


# --- drawing ------------------------------------------------------------------------------

def _galsim_star(stamps, shape, x, y, flux):
    ny, nx = shape
    ref = galsim.ImageD(nx, ny, scale=PIXEL)
    stamps.psf.drawImage(image=ref, offset=(x - (nx - 1) / 2, y - (ny - 1) / 2), method="auto")
    return ref.array * flux


def test_stamp_sizes_hold_the_flux(stamps):
    assert stamps.core_lost < 1e-3 and stamps.bright_lost < 1e-4
    assert stamps.core_half < stamps.bright_half


def test_flux_and_centroid_well_inside(stamps):
    gen = np.random.default_rng(11)
    n = 25
    x = gen.uniform(100, 400, n)
    y = gen.uniform(100, 300, n)
    flux = gen.uniform(1e3, 1e5, n)
    image = np.zeros((400, 500))
    drawn = st.draw_stars(image, x, y, flux, PSF, PIXEL)
    assert np.all(np.abs(drawn / flux - 1) < 1e-3)
    assert image.sum() == pytest.approx(drawn.sum(), rel=1e-12)
    h = stamps.core_half
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    for k in range(n):
        ix, iy = int(np.floor(x[k])), int(np.floor(y[k]))
        one = np.zeros_like(image)
        st.draw_stars(one, [x[k]], [y[k]], [flux[k]], stamps, PIXEL)
        cut = one[iy - h:iy + h + 1, ix - h:ix + h + 1]
        assert (cut * (xx + ix)).sum() / cut.sum() == pytest.approx(x[k], abs=0.01)
        assert (cut * (yy + iy)).sum() / cut.sum() == pytest.approx(y[k], abs=0.01)


def test_matches_galsim_single_stars(stamps):
    # Bilinear interpolation between 16 phases per pixel: < 5e-4 of the peak (measured 4.6e-4).
    gen = np.random.default_rng(5)
    shape = (64, 64)
    for _ in range(10):
        x, y = gen.uniform(28, 36, 2)
        image = np.zeros(shape)
        st.draw_stars(image, [x], [y], [1.0], stamps, PIXEL)
        ref = _galsim_star(stamps, shape, x, y, 1.0)
        assert np.abs(image - ref).max() < 5e-4 * ref.max()
        assert image.sum() == pytest.approx(ref.sum(), abs=1e-4)


def test_exact_at_the_phases(stamps):
    image = np.zeros((64, 64))
    x, y = 31 + 5 / 16, 32 + 11 / 16
    st.draw_stars(image, [x], [y], [1.0], stamps, PIXEL)
    ref = _galsim_star(stamps, image.shape, x, y, 1.0)
    assert np.abs(image - ref).max() < 1e-6 * ref.max()


def test_bright_star_keeps_the_wings(stamps):
    shape = (401, 401)
    x, y = 200.3, 199.8
    flux = 1e7
    image = np.zeros(shape)
    drawn = st.draw_stars(image, [x], [y], [flux], stamps, PIXEL)
    assert 1 - drawn[0] / flux < 1e-4
    ref = _galsim_star(stamps, shape, x, y, flux)
    assert np.abs(image - ref).max() < 5e-4 * ref.max()
    # Just outside the core stamp the ring follows GalSim to ~1e-9 of the flux per pixel.
    h = stamps.core_half
    assert np.abs(image - ref)[200, 200 + h + 1:].max() < 1e-8 * flux


def test_clipping_at_edges_and_float32(stamps):
    image = np.zeros((60, 80), dtype=np.float32)
    x = np.array([0.2, 79.4, 40.0, -200.0])
    y = np.array([0.7, 30.0, 59.9, 30.0])
    flux = np.array([1e4, 1e4, 1e4, 1e4])
    drawn = st.draw_stars(image, x, y, flux, stamps, PIXEL)
    assert image.dtype == np.float32
    assert drawn[3] == 0.0  # off the image
    assert np.all(drawn[:3] < 0.8 * flux[:3]) and np.all(drawn[:3] > 0.2 * flux[:3])
    assert image.sum(dtype=np.float64) == pytest.approx(drawn.sum(), rel=1e-6)


def test_draw_input_checks():
    with pytest.raises(InputError, match="fluxes_e"):
        st.draw_stars(np.zeros((10, 10)), [1.0], [1.0], [-1.0], PSF, PIXEL)
    with pytest.raises(InputError, match="same length"):
        st.draw_stars(np.zeros((10, 10)), [1.0, 2.0], [1.0], [1.0], PSF, PIXEL)
    with pytest.raises(InputError, match="2-D"):
        st.draw_stars(np.zeros(10), [1.0], [1.0], [1.0], PSF, PIXEL)
    with pytest.raises(InputError, match="GalSim"):
        st.draw_stars(np.zeros((10, 10)), [1.0], [1.0], [1.0], "kolmogorov", PIXEL)


# --- catalogs -----------------------------------------------------------------------------

def test_read_csv_catalog(tmp_path):
    path = tmp_path / "stars.csv"
    path.write_text("X,y,Mag,extra\n10.5,20.25,18.0,a\n-3,4,21.5,b\n")
    cat = st.read_catalog(path)
    assert np.array_equal(cat["x"], [10.5, -3.0])
    assert np.array_equal(cat["y"], [20.25, 4.0])
    assert np.array_equal(cat["mag"], [18.0, 21.5])
    spec = st.StarFieldSpec(catalog=str(path))
    assert np.array_equal(st.star_field(spec, (50, 50), PIXEL, "r", None)["x"], cat["x"])


def test_read_fits_catalog_with_wcs(tmp_path):
    wcs = pointing_wcs({"ra": 150.0, "dec": -30.0, "rotation": 20.0}, (4000, 4072), PIXEL)
    x = np.array([0.0, 100.25, 4071.0, 2035.5])
    y = np.array([0.0, 3999.0, 17.75, 1999.5])
    ra, dec = wcs.pixel_to_world_values(x, y)
    path = tmp_path / "stars.fits"
    Table({"RA": ra, "DEC": dec, "MAG": [17.0, 18.0, 19.0, 20.0]}).write(path)
    cat = st.read_catalog(path, wcs)
    assert np.allclose(cat["x"], x, atol=1e-6) and np.allclose(cat["y"], y, atol=1e-6)
    assert np.array_equal(cat["mag"], [17.0, 18.0, 19.0, 20.0])
    with pytest.raises(InputError, match="WCS"):
        st.read_catalog(path)


def test_bad_catalogs(tmp_path):
    with pytest.raises(FileFormatError, match="no such file"):
        st.read_catalog(tmp_path / "missing.csv")
    cols = tmp_path / "cols.csv"
    cols.write_text("u,v,mag\n1,2,3\n")
    with pytest.raises(FileFormatError, match="needs columns x, y, mag.*found u, v, mag"):
        st.read_catalog(cols)
    text = tmp_path / "text.csv"
    text.write_text("x,y,mag\n1,2,bright\n")
    with pytest.raises(FileFormatError, match="'mag' must be numeric"):
        st.read_catalog(text)
    nan = tmp_path / "nan.csv"
    nan.write_text("x,y,mag\n1,2,3\n4,,6\n")
    with pytest.raises(FileFormatError, match=r"'y' has missing .* row\(s\) 2"):
        st.read_catalog(nan)
    image = tmp_path / "image.fits"
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(image)
    with pytest.raises(FileFormatError, match="cannot read it as a FITS table"):
        st.read_catalog(image)
    junk = tmp_path / "junk.fits"
    junk.write_bytes(b"\x00\x01 not fits at all" * 10)
    with pytest.raises(FileFormatError, match="cannot read"):
        st.read_catalog(junk)


@pytest.mark.slow
def test_full_ccd_twenty_thousand_stars():
    # How fast (~1 s, against ~25 s for GalSim star by star) is scripts/bench_stars.py's job,
    # not a unit test's: here only that all of them are drawn, with their flux.
    shape = (4000, 4072)
    area = shape[0] * shape[1] * (PIXEL / 3600) ** 2
    spec = st.StarFieldSpec(galactic_l=90, galactic_b=30, density_per_deg2=20000 / area)
    field = st.star_field(spec, shape, PIXEL, "r", rng(1, "stars"))
    flux = 10 ** (0.4 * (28.36 - field["mag"])) * 30.0
    image = np.zeros(shape)
    drawn = st.draw_stars(image, field["x"], field["y"], flux, PSF, PIXEL)
    assert field["x"].size > 15000
    assert image.sum() == pytest.approx(drawn.sum(), rel=1e-9)
    assert drawn.sum() / flux.sum() > 0.998


# --- scene glue ---------------------------------------------------------------------------

def test_scene_with_stars():
    from inject import DEFAULT_SCENE, apply_overrides, parse_scene
    scene = parse_scene(apply_overrides(DEFAULT_SCENE, [
        "detector.nx=300", "detector.ny=200", "satellites=[]", "zenith=0",
        "stars.galactic_l=90", "stars.galactic_b=30"]))
    image = np.zeros(scene.detector.shape)
    stars_added = st.add_star_field(image, scene, rng(scene.seed, "stars"))
    assert stars_added["x"].size > 0
    assert image.sum() == pytest.approx(stars_added["charge_in_image_e"].sum(), rel=1e-9)
    expected = 10 ** (0.4 * (28.51 - stars_added["mag"])) * scene.exptime  # g, airmass 1
    assert np.allclose(stars_added["flux_e"], expected)
    with pytest.raises(SceneError, match="unknown key"):
        parse_scene(apply_overrides(DEFAULT_SCENE, ["stars.density=3"]))  # at parse time


# --- collected charge (noise) ---------------------------------------------------------------

def _star_draws(stamps, n, x, y, flux, shape=(40, 50)):
    """``n`` collected-charge drawings of the same stars (seeds 0..n-1) and the one expected
    image and variance plane."""
    expected = np.zeros(shape)
    st.draw_stars(expected, x, y, flux, stamps, PIXEL)
    draws, variances = [], []
    for seed in range(n):
        image, variance = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        st.draw_stars(image, x, y, flux, stamps, PIXEL, noise=np.random.default_rng(seed),
                      variance=variance)
        draws.append(image)
        variances.append(variance)
    return expected, np.array(draws), np.array(variances)


@pytest.mark.parametrize("photons_per_pixel_max, bright", [
    (0.0, 3e6),                        # every stamp pixel by pixel
    (st.PHOTONS_PER_PIXEL_MAX, 3e6),   # as chosen: the faint core and the ring as photons
    (np.inf, 3e3),                     # every stamp photon by photon (no 3e6-photon core)
])
def test_collected_star_charge_is_poisson_of_the_expected(stamps, monkeypatch,
                                                          photons_per_pixel_max, bright):
    """Stars drawn stamp by stamp with noise: two overlapping stars, a faint one and one at
    the image edge (with the ring of a bright star when it is bright); stamps drawn pixel by
    pixel, photon by photon, and as chosen by default. Each pixel is Poisson of the summed
    expected charge (mean and variance per pixel over 1500 drawings, the whole distribution
    where the stars overlap, in a core, a faint star and a bright one's far ring), and the
    variance plane is that expected charge."""
    from test_noise_split import chi_square_pvalue

    monkeypatch.setattr(st, "PHOTONS_PER_PIXEL_MAX", photons_per_pixel_max)
    x, y, flux = [18.3, 24.8, 47.6, 6.5], [20.1, 21.7, 12.2, 33.4], [2500.0, 900.0, bright, 300.0]
    expected, draws, variances = _star_draws(stamps, 1500, x, y, flux)
    assert np.all(draws == np.rint(draws)) and draws.min() >= 0
    np.testing.assert_allclose(variances, np.broadcast_to(expected, variances.shape),
                               rtol=1e-6, atol=1e-9)
    n = len(draws)
    pull = (draws.mean(axis=0) - expected) / np.sqrt(np.maximum(expected, 1e-12) / n)
    assert np.abs(pull).max() < 5.5  # 2000 pixels: a 5.5-sigma pull has p ~ 1e-4
    lit = expected > 0.5
    ratio = draws.var(axis=0)[lit] / expected[lit]
    assert abs(ratio.mean() - 1) < 0.01
    # overlap, core, edge star's wing (its far ring when bright), wing, faint star
    for pixel in [(21, 21), (20, 18), (5, 40), (39, 3), (33, 6)]:
        mean = expected[pixel]
        assert mean > 0
        assert chi_square_pvalue(draws[(slice(None), *pixel)], mean) > 1e-4, (pixel, mean)


def test_collected_star_charge_is_reproducible_and_needs_a_variance(stamps):
    _, a, _ = _star_draws(stamps, 2, [10.5], [11.5], [5e3])
    _, b, _ = _star_draws(stamps, 2, [10.5], [11.5], [5e3])
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[0], a[1])
    with pytest.raises(InputError, match="variance"):
        st.draw_stars(np.zeros((20, 20), np.float32), [5.0], [5.0], [10.0], stamps, PIXEL,
                      noise=np.random.default_rng(1))
