"""Observing geometry against closed forms and the paper's numbers."""
import numpy as np
import pytest

from inject import InputError
from inject import geometry as geo

R = geo.R_EARTH_KM


def paper_range(h, z_deg):
    """The paper's range form, R sin(z - theta_N) / sin(theta_N), valid away from zenith."""
    z = np.radians(z_deg)
    tn = np.arcsin(R / (R + h) * np.sin(z))
    return R * np.sin(z - tn) / np.sin(tn)


@pytest.mark.parametrize("h", [160.0, 350.0, 550.0, 2000.0, 36000.0])
@pytest.mark.parametrize("z", [1.0, 20.0, 45.0, 70.0, 89.9])
def test_range_matches_paper_form(h, z):
    assert geo.slant_range(h, z) == pytest.approx(paper_range(h, z), rel=1e-9)


def test_range_is_height_at_zenith_and_continuous():
    h = np.array([160.0, 550.0, 36000.0])
    np.testing.assert_allclose(geo.slant_range(h, 0.0), h, rtol=1e-15)
    np.testing.assert_allclose(geo.slant_range(h, 1e-9), h, rtol=1e-12)


def test_range_law_of_cosines():
    # Triangle Earth centre - telescope - satellite: (R+h)^2 = R^2 + r^2 + 2 R r cos z.
    h, z = np.meshgrid([200.0, 550.0, 20000.0], np.radians([0.0, 30.0, 60.0, 85.0]))
    r = geo.slant_range(h, np.degrees(z))
    np.testing.assert_allclose(R ** 2 + r ** 2 + 2 * R * r * np.cos(z), (R + h) ** 2, rtol=1e-12)


def test_reference_numbers():
    g = geo.Geometry.from_orbit(550, 0)
    assert g.range_km == pytest.approx(550.0, rel=1e-12)
    assert g.orbital_speed_m_s == pytest.approx(7585.1, abs=0.05)
    assert np.degrees(g.angular_speed_rad_s) == pytest.approx(0.7902, abs=5e-5)
    assert g.t_eff_s * 1e3 == pytest.approx(0.0703, abs=5e-5)
    g = geo.Geometry.from_orbit(550, 40)
    assert g.range_km == pytest.approx(698.94, abs=0.005)
    assert np.degrees(g.angular_speed_rad_s) == pytest.approx(0.5012, abs=5e-5)
    assert g.t_eff_s * 1e3 == pytest.approx(0.1108, abs=5e-5)
    assert np.degrees(geo.angular_speed(350, 0)) == pytest.approx(1.2600, abs=5e-5)
    g = geo.Geometry.from_orbit(550, 70)
    assert g.nadir_angle_deg == pytest.approx(59.89, abs=0.005)
    assert g.range_km == pytest.approx(1293.8, abs=0.05)


def test_orbital_speed_closed_form():
    h = np.array([160.0, 550.0, 35786.0])
    v = geo.orbital_speed(h)
    np.testing.assert_allclose(v ** 2 * (R + h) * 1e3, geo.GM_EARTH, rtol=1e-14)


@pytest.mark.parametrize("phi", [0.0, 30.0, 90.0, 137.0, 270.0])
@pytest.mark.parametrize("z", [0.0, 40.0, 70.0, 89.0])
def test_tangential_velocity_from_3d_vectors(phi, z):
    """Eq. 8 against an explicit projection v - (v.r)r in the satellite frame."""
    h = 550.0
    tn = np.radians(geo.nadir_angle(h, z))
    r_hat = np.array([0.0, np.sin(tn), np.cos(tn)])  # to the telescope; z points to nadir
    v = geo.orbital_speed(h) * np.array([np.cos(np.radians(phi)), np.sin(np.radians(phi)), 0.0])
    expected = v - (v @ r_hat) * r_hat
    got = geo.tangential_velocity(h, z, phi)
    np.testing.assert_allclose(got, expected, atol=1e-9 * np.linalg.norm(v))
    assert geo.tangential_speed(h, z, phi) == pytest.approx(np.linalg.norm(expected), rel=1e-12)


def line_of_sight_rate(h_km, z_deg, phi_deg, dt=0.02):
    """Angular speed of the line of sight (rad/s) by moving the satellite along its circular
    orbit for +-dt and measuring the angle swept, in an Earth-centred frame (no eq. 8);
    central differences err by ~(omega dt)^2, < 1e-7 relative here."""
    r_e, gm = 6378.1e3, 3.986004e14  # IAU 2015 nominal values, typed here
    z, phi = np.radians(z_deg), np.radians(phi_deg)
    telescope = np.array([0.0, 0.0, r_e])
    u = np.array([np.sin(z), 0.0, np.cos(z)])
    a = r_e + h_km * 1e3
    b = telescope @ u
    sat = telescope + (-b + np.sqrt(b * b - r_e ** 2 + a * a)) * u
    radial = sat / a
    in_plane = np.cross([0.0, 1.0, 0.0], radial)
    along = np.cos(phi) * np.array([0.0, 1.0, 0.0]) + np.sin(phi) * in_plane / np.linalg.norm(
        in_plane)
    n = np.sqrt(gm / a ** 3)  # mean motion

    def sight(t):
        pos = a * (np.cos(n * t) * radial + np.sin(n * t) * along)
        return (pos - telescope) / np.linalg.norm(pos - telescope)
    before, after = sight(-dt), sight(dt)  # the angle between them, well conditioned
    return np.arctan2(np.linalg.norm(np.cross(before, after)), before @ after) / (2 * dt)


@pytest.mark.parametrize("h", [350.0, 550.0, 1200.0, 20000.0])
@pytest.mark.parametrize("z,phi", [(0.0, 90.0), (45.0, 90.0), (80.0, 90.0), (60.0, 0.0),
                                   (70.0, 35.0)])
def test_t_eff_from_the_motion_of_the_line_of_sight(h, z, phi):
    omega = line_of_sight_rate(h, z, phi)
    t_eff = 0.2 / (180 * 3600 / np.pi) / omega  # a 0.2" pixel
    assert geo.effective_exposure(h, z, phi, 0.2) == pytest.approx(t_eff, rel=1e-6)
    assert geo.Geometry.from_orbit(h, z, phi).t_eff_s == pytest.approx(t_eff, rel=1e-6)


def test_t_eff_vectorised_and_lower_orbits_faster():
    h = np.array([350.0, 550.0, 1200.0])[:, None]
    z = np.array([0.0, 45.0, 80.0])[None, :]
    t = geo.effective_exposure(h, z, 90.0, 0.2)
    assert t.shape == (3, 3)
    for i in range(3):
        for j in range(3):
            assert t[i, j] == geo.effective_exposure(h[i, 0], z[0, j], 90.0, 0.2)
    # Lower orbits move faster across the sky at every zenith angle.
    assert np.all(np.diff(t, axis=0) > 0)


@pytest.mark.parametrize("bad", [dict(height_km=-1), dict(height_km=np.nan), dict(height_km=0),
                                 dict(zenith_deg=90), dict(zenith_deg=-1), dict(zenith_deg=np.inf)])
def test_bad_input_raises_value_error(bad):
    args = dict(height_km=550.0, zenith_deg=10.0) | bad
    with pytest.raises(InputError) as info:
        geo.slant_range(**args)
    assert isinstance(info.value, ValueError)
    assert next(iter(bad)) in str(info.value)
