"""Earth's shadow: the WGS84 ellipsoid, optionally grown by a grazing atmosphere."""
import numpy as np
import pytest

from inject.orbits.passes import WGS84_A_KM, WGS84_B_KM, illumination

#: A Sun so far away along +x that its disc is ~1e-6 rad: the penumbra is millimetres wide,
#: and the shadow's edge is the Earth's silhouette seen along x.
FAR_SUN = np.array([1e12, 0.0, 0.0])


@pytest.mark.parametrize("atmosphere_km", [0.0, 30.0])
def test_shadow_edge_is_the_ellipse_seen_from_the_sun(atmosphere_km):
    """Behind the Earth, the silhouette is the ellipse y^2/A^2 + z^2/B^2 = 1 (A, B the
    equatorial and polar radii grown by the atmosphere): just inside it is umbra, just
    outside sunlit, over the pole and over the equator alike."""
    a, b = WGS84_A_KM + atmosphere_km, WGS84_B_KM + atmosphere_km
    for direction, radius in ((np.array([0.0, 0.0, 1.0]), b), (np.array([0.0, 1.0, 0.0]), a),
                              (np.array([0.0, 1.0, 1.0]) / np.sqrt(2), None)):
        if radius is None:  # at 45 deg between the axes: the ellipse's radius there
            radius = 1 / np.sqrt(0.5 / a ** 2 + 0.5 / b ** 2)
        for offset, lit in ((-0.5, 0.0), (0.5, 1.0)):
            sat = np.array([-7000.0, 0.0, 0.0]) + (radius + offset) * direction
            fraction, _ = illumination(sat, FAR_SUN, atmosphere_km=atmosphere_km)
            assert fraction == pytest.approx(lit, abs=1e-6)


def test_in_the_equatorial_plane_it_is_the_sphere_of_the_equatorial_radius():
    """With the Sun and the satellite in the equatorial plane, the ellipsoid's penumbra is
    that of a sphere of the equatorial radius (plus the atmosphere)."""
    sun = np.array([1.496e8, 0.0, 0.0])
    heights = np.linspace(-60.0, 120.0, 37)
    sats = np.array([[-7000.0, WGS84_A_KM + h, 0.0] for h in heights])
    for atmosphere in (0.0, 30.0):
        ours, _ = illumination(sats, sun, atmosphere_km=atmosphere)
        sphere, _ = illumination(sats, sun, earth_radius_km=WGS84_A_KM + atmosphere)
        np.testing.assert_allclose(ours, sphere, atol=1e-12)
        assert ours.min() == 0.0 and ours.max() == 1.0  # umbra, penumbra and sunlight
        assert np.any((ours > 0) & (ours < 1))


def test_atmosphere_moves_a_grazing_satellite_into_the_shadow():
    sat = np.array([-7000.0, WGS84_A_KM + 20.0, 0.0])
    sun = np.array([1.496e8, 0.0, 0.0])
    bare, _ = illumination(sat, sun)
    thick, _ = illumination(sat, sun, atmosphere_km=60.0)
    assert thick < bare
