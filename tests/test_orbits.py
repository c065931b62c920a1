"""The orbit engine (inject/orbits.py) against independent geometry.

skyfield is the independent code path (its own TEME -> GCRS -> ITRS chain, site and time
scales); it is given the same finals2000A.all that astropy-iers-data ships, as the issue explains
(its built-in timescale has no polar motion and its own UT1: ~5" apart at 600 km). The orbits are
synthetic example TLEs (Starlink-like 550 km, 53 deg shell orbits) built by
:func:`inject.orbits.passes.aimed_orbit` to be at a chosen alt/az over Rubin at a chosen time.
"""
import json
import math
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import ICRS, AltAz, SkyCoord
from astropy.time import Time

from inject import InjectError, InputError, OrbitError, OrbitWarning, Pointing, geometry
from inject.camera.wcs import tangent_to_focal
from inject.orbits.passes import (
    RUBIN,
    Exposure,
    Orbit,
    aimed_orbit,
    compute_pass,
    crossing_candidates,
    find_passes,
    illumination,
    propagate_teme,
    sunlight,
    walker_shell,
)

skyfield_api = pytest.importorskip("skyfield.api")
from skyfield.framelib import true_equator_and_equinox_of_date  # noqa: E402

#: Exposure start of the example field: 2026 June 15, ~1.6 h after sunset at Rubin (Sun ~20 deg
#: below the horizon), within the measured part of the bundled IERS table.
START = "2026-06-15T23:30:00"
ARCSEC = 1.0 / 3600.0


@pytest.fixture(scope="module")
def ts(skyfield_timescale):
    """A skyfield timescale on astropy-iers-data's finals2000A.all, with polar motion."""
    return skyfield_timescale


@pytest.fixture(scope="module")
def topos():
    return skyfield_api.wgs84.latlon(RUBIN.lat_deg, RUBIN.lon_deg, elevation_m=RUBIN.height_m)


@pytest.fixture(scope="module")
def exposure():
    return Exposure(START, 30.0)


@pytest.fixture(scope="module")
def sat(exposure):
    """Example TLE: at alt 55, az 290 (towards the set Sun, so sunlit) at mid-exposure."""
    return aimed_orbit(exposure.middle, 55.0, 290.0, name="EXAMPLE-550-53")


def _pointing_on(p, i, rotation=0.0, apparent=True):
    """ICRS pointing (astropy AltAz -> ICRS, as for a star) on sample ``i`` of pass ``p``."""
    alt = p.apparent_alt_deg[i] if apparent else p.alt_deg[i]
    az = p.apparent_az_deg[i] if apparent else p.az_deg[i]
    c = SkyCoord(az=az * u.deg, alt=alt * u.deg,
                 frame=AltAz(obstime=p.utc[i], location=RUBIN.location)).transform_to(ICRS())
    return Pointing(c.ra.deg, c.dec.deg, rotation)


@pytest.fixture(scope="module")
def centred(sat, exposure):
    """The pass with the pointing on the satellite's apparent mid-exposure position."""
    first = compute_pass(sat, exposure, Pointing(0.0, 0.0))
    return compute_pass(sat, exposure, _pointing_on(first, len(first.t_s) // 2, rotation=30.0))


def _sf_sat(orbit, ts):
    return skyfield_api.EarthSatellite(*orbit.tle_lines(), ts=ts)


# --- example TLE, orbits, errors ----------------------------------------------------------------

def test_example_tle_is_valid_and_on_target(sat, exposure, ts, topos):
    l1, l2 = sat.tle_lines()
    back = Orbit.from_tle(l1, l2)  # checksums verified on reading
    assert back.satrec.inclo == pytest.approx(math.radians(53.0), abs=1e-6)
    assert abs(back.mean_height_km - 550.0) < 0.5
    # skyfield puts it where it was aimed, to the TLE's rounding (1e-4 deg of elements).
    alt, az, _ = (_sf_sat(sat, ts) - topos).at(ts.from_astropy(exposure.middle)).altaz()
    assert alt.degrees == pytest.approx(55.0, abs=0.01)
    assert az.degrees == pytest.approx(290.0, abs=0.02)


def test_circular_orbit_radius_and_period_are_keplerian():
    t0 = Time(START)
    orbit = Orbit.circular(550.0, 53.0, 10.0, 20.0, t0)
    a_km = geometry.R_EARTH_KM + 550.0
    period = 2 * math.pi * math.sqrt((a_km * 1e3) ** 3 / geometry.GM_EARTH)
    times = t0 + np.linspace(0.0, period, 400) * u.s
    r = np.linalg.norm(propagate_teme([orbit], times)[0][0], axis=-1)
    # Short-period J2 terms make the osculating radius oscillate by a few km about the mean.
    assert abs(r.mean() - a_km) < 5.0 and r.std() < 10.0
    # SGP4's mean motion and Kepler's law agree to the J2 correction (~1e-3).
    n_rad_s = orbit.satrec.no_kozai / 60.0
    assert 2 * math.pi / n_rad_s == pytest.approx(period, rel=2e-3)


def test_walker_shell_planes_and_phasing():
    t0 = Time(START)
    shell = walker_shell(12, 3, 1, 550.0, 53.0, t0)
    assert len(shell) == 12
    raans = sorted({round(math.degrees(o.satrec.nodeo), 6) for o in shell})
    assert raans == pytest.approx([0.0, 120.0, 240.0])
    # Plane 1 is shifted by 360 F / T = 30 deg of argument of latitude.
    assert math.degrees(shell[4].satrec.mo - shell[0].satrec.mo) % 360 == pytest.approx(30.0)
    with pytest.raises(InputError, match="walker"):
        walker_shell(10, 3, 1, 550.0, 53.0, t0)


def test_bad_checksum_is_refused(sat):
    l1, l2 = sat.tle_lines()
    bad = l2[:68] + str((int(l2[68]) + 1) % 10)
    with pytest.raises(OrbitError, match="bad checksum") as err:
        Orbit.from_tle(l1, bad)
    assert "\n" not in str(err.value)
    with pytest.raises(OrbitError, match="non-empty lines"):
        Orbit.from_text(l1 + "\n")


def test_decayed_orbit_is_refused():
    from inject import InputError
    # A circular orbit's height by the input-ranges table (orbit.height >= 80 km) ...
    with pytest.raises(InputError, match="orbit.height=50.0: .*decayed"):
        Orbit.circular(50.0, 53.0, 0.0, 0.0, Time(START))
    # ... any element set (a TLE) by its perigee.
    from sgp4.io import compute_checksum

    l1, l2 = Orbit.circular(550.0, 53.0, 0.0, 0.0, Time(START)).tle_lines()
    l2 = l2[:26] + "0700000" + l2[33:68]  # eccentricity 0.07: perigee ~40 km
    with pytest.raises(OrbitError, match="perigee height .* decayed"):
        Orbit.from_tle(l1, l2 + str(compute_checksum(l2)))


def test_epoch_far_from_exposure_warns_then_refuses(sat):
    with pytest.warns(OrbitWarning, match="20.0 days"):
        sat.check_epoch(sat.epoch + 20 * u.day)
    with pytest.raises(OrbitError, match="61.0 days"):
        sat.check_epoch(sat.epoch - 61 * u.day)
    with warnings.catch_warnings():
        warnings.simplefilter("error", OrbitWarning)
        sat.check_epoch(sat.epoch + 13 * u.day)


@pytest.mark.filterwarnings("ignore::erfa.ErfaWarning")
@pytest.mark.filterwarnings("ignore::astropy.utils.exceptions.AstropyWarning")
def test_time_beyond_iers_table_warns_not_fails():
    when = Time("2029-03-01T03:00:00")
    orbit = Orbit.circular(550.0, 53.0, 0.0, 0.0, when)
    with pytest.warns(OrbitWarning, match="beyond the bundled IERS table"):
        p = compute_pass(orbit, Exposure(when, 2.0), Pointing(0.0, -30.0))
    assert np.all(np.isfinite(p.range_km))


def test_bad_inputs_are_one_line_inject_errors():
    for call in (lambda: Exposure("yesterday", 30.0), lambda: Exposure(START, -1.0),
                 lambda: Pointing(10.0, 95.0), lambda: Orbit.circular(-5, 53, 0, 0, START),
                 lambda: Orbit.from_tle("1 bad", "2 bad")):
        with pytest.raises(InjectError) as err:
            call()
        assert "\n" not in str(err.value)


# --- geometry against skyfield --------------------------------------------------------------------

def test_altaz_and_range_match_skyfield_over_a_pass(sat, ts, topos):
    # Five minutes around the example crossing, rising to setting part, every 5 s.
    long = Exposure(Time(START) - 135 * u.s, 300.0)
    p = compute_pass(sat, long, Pointing(0.0, 0.0), step_s=5.0)
    alt, az, dist = (_sf_sat(sat, ts) - topos).at(ts.from_astropy(p.utc)).altaz()
    up = alt.degrees > 0
    assert up.sum() > 20
    d_alt = (alt.degrees - p.alt_deg)[up] * 3600
    d_az = ((az.degrees - p.az_deg + 180) % 360 - 180)[up] * 3600 * np.cos(np.radians(
        p.alt_deg[up]))
    assert np.abs(d_alt).max() < 1.0 and np.abs(d_az).max() < 1.0
    assert np.abs(dist.km - p.range_km)[up].max() < 0.050


def test_angular_speed_matches_skyfield_finite_differences(centred, sat, ts, topos):
    p = centred
    h = 0.05  # s: central differences of skyfield's ICRS-axes topocentric directions
    sf = _sf_sat(sat, ts) - topos

    def direction(dt):
        v = sf.at(ts.from_astropy(p.utc + dt * u.s)).position.km
        return v / np.linalg.norm(v, axis=0)

    a, b = direction(-h), direction(h)
    rate = np.arccos(np.clip(np.sum(a * b, axis=0), -1, 1)) / (2 * h)
    np.testing.assert_allclose(p.angular_speed_rad_s, rate, rtol=5e-3)
    # The tracking term is the paper's "under 10%": here it changes the rate by 0.1-2%.
    assert np.all(p.angular_speed_rad_s > 0.005)


def test_nadir_angle_and_phi_match_the_paper_formulas(centred, sat, ts, topos):
    """The straight-line case: eq. 1 and eq. 8 (inject/geometry.py) at the matching geometry.

    The paper's Earth is a sphere of radius R with the telescope on it; the real site sits at
    |r_obs| from the centre. The triangle centre-site-satellite is the same as the paper's one
    scaled by R / |r_obs|, i.e. at the height ``h = R (|r_sat| / |r_obs| - 1)``, at the geocentric
    zenith angle. Positions and the inertial velocity come from skyfield (GCRS).
    """
    p = centred
    t = ts.from_astropy(p.utc)
    sat_gcrs = _sf_sat(sat, ts).at(t)
    r_sat, v_sat = sat_gcrs.position.km.T, sat_gcrs.velocity.km_per_s.T
    r_obs = topos.at(t).position.km.T
    los = r_sat - r_obs
    z_gc = np.degrees(np.arccos(np.sum(los * r_obs, axis=1) / (
        np.linalg.norm(los, axis=1) * np.linalg.norm(r_obs, axis=1))))
    h_match = geometry.R_EARTH_KM * (np.linalg.norm(r_sat, axis=1) /
                                     np.linalg.norm(r_obs, axis=1) - 1)
    np.testing.assert_allclose(p.nadir_angle_deg, geometry.nadir_angle(h_match, z_gc),
                               atol=1e-4)
    # |v_T| of eq. 8 with the engine's phi against the satellite's own inertial velocity
    # perpendicular to the line of sight (eq. 8 is a unit-free statement about directions).
    l_hat = -los / np.linalg.norm(los, axis=1)[:, None]  # satellite -> site
    v_perp = v_sat - np.sum(v_sat * l_hat, axis=1)[:, None] * l_hat
    speed = np.linalg.norm(v_sat, axis=1)
    scale = speed / (geometry.orbital_speed(h_match) / 1e3)
    vt = geometry.tangential_speed(h_match, z_gc, p.phi_deg) / 1e3 * scale
    np.testing.assert_allclose(vt, np.linalg.norm(v_perp, axis=1), rtol=3e-3)
    # The component towards the site is v sin(phi) sin(theta_N) (phi = 90: straight at it).
    toward = speed * np.sin(np.radians(p.phi_deg)) * np.sin(np.radians(p.nadir_angle_deg))
    np.testing.assert_allclose(toward, np.sum(v_sat * l_hat, axis=1), atol=0.02)


# --- the field -----------------------------------------------------------------------------------

def test_pointing_on_the_satellite_centres_the_track(centred):
    p = centred
    mid = len(p.t_s) // 2
    assert p.t_s[mid] == pytest.approx(15.0)
    assert math.hypot(p.field_x_deg[mid], p.field_y_deg[mid]) < 2 * ARCSEC
    assert p.in_field and p.visible and p.message == "crosses the field, sunlit"
    # The track runs through the field: its ends are far out (~0.6 deg/s for 15 s).
    assert math.hypot(p.xi_deg[0], p.eta_deg[0]) > 5.0


def test_light_time_puts_the_apparent_position_behind(centred):
    """A pointing on the *geometric* mid position is off by the light-time lag (~2-5")."""
    p = centred
    mid = len(p.t_s) // 2
    geo = compute_pass(p.orbit, p.exposure, _pointing_on(p, mid, apparent=False))
    lag = math.hypot(geo.xi_deg[mid], geo.eta_deg[mid]) * 3600
    expected = p.angular_speed_rad_s[mid] * p.light_time_s[mid] * 206264.806
    assert 2.0 < lag < 6.0
    assert lag == pytest.approx(expected, rel=0.05)
    # Behind: the apparent position is where the geometric one was a light time ago.
    motion = np.array([geo.xi_deg[mid + 1] - geo.xi_deg[mid - 1],
                       geo.eta_deg[mid + 1] - geo.eta_deg[mid - 1]])
    assert np.dot(motion, [geo.xi_deg[mid], geo.eta_deg[mid]]) < 0


def test_astrometric_radec_pointing_would_be_20_arcsec_off(centred, sat, ts, topos):
    """The issue's trap: the satellite's own (astrometric) RA/Dec is not where it is among the
    stars; pointing there leaves the mid-exposure track off-centre by the annual aberration
    (up to 20.5"; 9.4" for this direction and date)."""
    p = centred
    mid = len(p.t_s) // 2
    # skyfield's astrometric direction at the retarded time (light time) in ICRS axes.
    t = ts.from_astropy(p.utc[mid] - p.light_time_s[mid] * u.s)
    ra, dec, _ = (_sf_sat(sat, ts).at(t) - topos.at(ts.from_astropy(p.utc[mid]))).radec()
    naive = compute_pass(sat, p.exposure, Pointing(ra._degrees, dec.degrees))
    off = math.hypot(naive.xi_deg[mid], naive.eta_deg[mid]) * 3600
    # Independent: annual aberration (v / c) sin(angle to the Earth's velocity), the velocity
    # 90 deg behind the almanac Sun's ecliptic longitude, its size from vis-viva. The neglected
    # flight-path angle (< 1 deg) and diurnal aberration (0.3") stay under 0.5".
    n = p.utc[mid].ut1.jd - 2451545.0
    g = math.radians((357.528 + 0.9856003 * n) % 360)
    lam = math.radians((280.460 + 0.9856474 * n) % 360 + 1.915 * math.sin(g)
                       + 0.020 * math.sin(2 * g)) - math.pi / 2
    eps = math.radians(23.439)
    v_dir = np.array([math.cos(lam), math.cos(eps) * math.sin(lam), math.sin(eps) * math.sin(lam)])
    v = 29.7847 * math.sqrt(2 / (1.00014 - 0.01671 * math.cos(g)) - 1)  # km/s
    d = np.array([math.cos(dec.radians) * math.cos(ra.radians),
                  math.cos(dec.radians) * math.sin(ra.radians), math.sin(dec.radians)])
    expected = v / 299792.458 * np.linalg.norm(np.cross(d, v_dir)) * 206264.806
    assert off == pytest.approx(expected, abs=0.5)
    assert off > 5.0  # far outside the 2" of the correct pointing


def test_rotation_convention():
    # +y at position angle rot (North through East); +x at rot - 90 (West at 0, afw flipX=False).
    for rot in (0.0, 30.0, 135.0, -70.0):
        xi, eta = tangent_to_focal(0.0, 1.0, rot)
        assert math.degrees(math.atan2(xi, eta)) == pytest.approx((rot + 180) % 360 - 180)
        xi, eta = tangent_to_focal(1.0, 0.0, rot)
        assert math.degrees(math.atan2(xi, eta)) == pytest.approx((rot + 90) % 360 - 180)
        x, y = tangent_to_focal(*tangent_to_focal(0.3, -0.7, rot), rot)
        assert (x, y) == pytest.approx((0.3, -0.7))


def test_field_rotation_of_the_track(centred):
    p = centred
    back_xi, back_eta = tangent_to_focal(p.field_x_deg, p.field_y_deg, p.pointing.rotation_deg)
    np.testing.assert_allclose(back_xi, p.xi_deg, atol=1e-12)
    np.testing.assert_allclose(back_eta, p.eta_deg, atol=1e-12)


def test_pass_that_misses_the_field(centred):
    p = centred
    mid = len(p.t_s) // 2
    # Offset the pointing 5 deg perpendicular to the track: the pass misses.
    c = p.pointing.icrs
    d_xi = p.xi_deg[mid + 1] - p.xi_deg[mid - 1]
    d_eta = p.eta_deg[mid + 1] - p.eta_deg[mid - 1]
    pa_track = math.degrees(math.atan2(d_xi, d_eta))
    off = c.directional_offset_by((pa_track + 90) * u.deg, 5 * u.deg)
    miss = compute_pass(p.orbit, p.exposure, Pointing(off.ra.deg, off.dec.deg))
    assert not miss.in_field and not miss.visible
    assert "misses the field" in miss.message
    closest = float(miss.message.split("closest ")[1].split(" deg")[0])
    assert 4.0 < closest < 5.5
    out = miss.to_dict()
    assert out["in_field"] is False
    json.dumps(out)  # JSON-ready
    for key in ("t_s", "utc", "alt_deg", "az_deg", "range_km", "nadir_angle_deg", "phi_deg",
                "angular_speed_rad_s", "sunlit"):
        assert key in out["samples"][0]


def test_pass_below_the_horizon(sat, exposure):
    later = Exposure(Time(exposure.start) + 40 * u.min, 30.0)
    p = compute_pass(sat, later, Pointing(0.0, -30.0))
    assert not p.in_field and "below the horizon" in p.message


def test_samples_include_the_middle_and_one_per_second(exposure):
    for exptime, step in ((30.0, 1.0), (15.0, 1.0), (7.3, 0.5), (0.4, 1.0)):
        t = Exposure(START, exptime).sample_times(step)
        assert t[0] == 0.0 and t[-1] == pytest.approx(exptime)
        assert np.any(np.isclose(t, exptime / 2))
        assert np.diff(t).max() <= step + 1e-12


# --- shadow --------------------------------------------------------------------------------------

def test_illumination_closed_forms():
    au = 1.495978707e8
    sun = np.array([au, 0.0, 0.0])
    r = 7000.0
    frac, state = illumination(np.array([[r, 0, 0], [-r, 0, 0], [0, r, 0]]), sun)
    assert list(state) == ["sunlit", "umbra", "sunlit"] and list(frac) == [1.0, 0.0, 1.0]
    # Sun's centre on the Earth's limb seen from the satellite: about half the disc.
    b = math.asin(geometry.R_EARTH_KM / r)
    pos = -r * np.array([math.cos(b), math.sin(b), 0.0])  # c = b up to the Sun's parallax
    frac, state = illumination(pos, sun)
    assert state == "penumbra" and frac == pytest.approx(0.5, abs=0.01)


def _sun_of_date_low_precision(jd_ut):
    """Geometric Sun, true equator and equinox of date, km (Astronomical Almanac, C5; 0.01 deg).

    Independent of astropy's get_sun: the almanac's low-precision formulae.
    """
    n = jd_ut - 2451545.0
    g = np.radians((357.528 + 0.9856003 * n) % 360)
    lam = np.radians((280.460 + 0.9856474 * n) % 360 + 1.915 * np.sin(g) + 0.020 * np.sin(2 * g))
    eps = np.radians(23.439 - 0.0000004 * n)
    dist = (1.00014 - 0.01671 * np.cos(g) - 0.00014 * np.cos(2 * g)) * 1.495978707e8
    return dist[..., None] * np.stack(
        [np.cos(lam), np.cos(eps) * np.sin(lam), np.sin(eps) * np.sin(lam)], axis=-1)


def test_shadow_entry_matches_a_cylindrical_shadow(sat, ts):
    """Over one orbit at 1 s, the conical model's mid-penumbra (half the Sun hidden) and an
    independent cylindrical shadow (skyfield positions, almanac Sun) enter within a time step."""
    t0 = Time(START)
    times = t0 + np.arange(0.0, 5800.0, 1.0) * u.s
    frac, state = sunlight(sat, times)
    assert set(state) == {"sunlit", "penumbra", "umbra"}
    enter = np.flatnonzero((frac[:-1] >= 0.5) & (frac[1:] < 0.5))
    r = _sf_sat(sat, ts).at(ts.from_astropy(times)).frame_xyz(
        true_equator_and_equinox_of_date).km.T
    s_hat = _sun_of_date_low_precision(times.ut1.jd)
    s_hat /= np.linalg.norm(s_hat, axis=-1, keepdims=True)
    along = np.sum(r * s_hat, axis=-1)
    perp = np.linalg.norm(r - along[:, None] * s_hat, axis=-1)
    dark = (along < 0) & (perp < geometry.R_EARTH_KM)
    enter_cyl = np.flatnonzero(~dark[:-1] & dark[1:])
    assert len(enter) == len(enter_cyl) >= 1
    assert np.all(np.abs(enter - enter_cyl) <= 1)
    # The penumbra lies on both sides of the cylinder's edge, and the umbra inside.
    i = enter[0]
    assert state[i - 30] == "sunlit" or frac[i - 30] > 0.9
    assert state[i + 60] == "umbra" and dark[i + 60]


def test_pass_reports_shadow(sat, exposure):
    # Looking east (away from the set Sun) at the same time the satellite is eclipsed.
    east = aimed_orbit(exposure.middle, 60.0, 120.0, name="EXAMPLE-EAST")
    first = compute_pass(east, exposure, Pointing(0.0, 0.0))
    p = compute_pass(east, exposure, _pointing_on(first, len(first.t_s) // 2))
    assert p.in_field and not p.visible
    assert p.message == "crosses the field in Earth's shadow"
    assert not p.sunlit[len(p.t_s) // 2]


# --- many satellites ------------------------------------------------------------------------------

def test_prefilter_keeps_every_crossing(centred, exposure):
    p = centred
    mid = len(p.t_s) // 2
    c = p.pointing.icrs
    # The example satellite plus copies aimed 1.0, 1.9 and 3.5 deg off the boresight, and a
    # small Walker shell that does not come near.
    aimed = [p.orbit]
    for k, sep in enumerate((1.0, 1.9, 3.5)):
        off = c.directional_offset_by(40 * u.deg, sep * u.deg).transform_to(
            AltAz(obstime=p.utc[mid], location=RUBIN.location))
        aimed.append(aimed_orbit(exposure.middle, off.alt.deg, off.az.deg, ascending=k % 2 == 0,
                                 name=f"OFF-{sep}", satnum=90010 + k))
    shell = walker_shell(24, 6, 1, 550.0, 53.0, exposure.start)
    catalog = aimed + shell
    idx = set(crossing_candidates(catalog, exposure, p.pointing).tolist())
    exact = {i for i, o in enumerate(catalog)
             if compute_pass(o, exposure, p.pointing).in_field}
    assert exact <= idx
    assert {0, 1, 2} <= exact
    found = find_passes(catalog, exposure, p.pointing)
    assert sorted(q.orbit.name for q in found) == sorted(catalog[i].name for i in exact)


def test_shared_rotations_are_astropys(exposure):
    """The per-exposure matrices reproduce astropy's own transforms (and the retarded time's)."""
    from inject.orbits.passes import (
        EARTH_ROTATION_RAD_S,
        FieldFrame,
        _rot_z,
        altaz_basis,
        teme_to_itrs,
    )
    times = exposure.start + exposure.sample_times(5.0) * u.s
    frame = FieldFrame.build(times, Pointing(10.0, -20.0), RUBIN)
    r = np.tile([5000.0, -3000.0, 3500.0], (len(times), 1))
    np.testing.assert_allclose(np.einsum("tij,tj->ti", frame.teme_to_itrs, r),
                               teme_to_itrs(r, times), atol=1e-6)  # km: 1 mm
    tau = 0.0025
    turned = np.einsum("tij,tj->ti", _rot_z(np.full(len(times), EARTH_ROTATION_RAD_S * tau))
                       @ frame.teme_to_itrs, r)
    np.testing.assert_allclose(turned, teme_to_itrs(r, times - tau * u.s), atol=1e-6)
    np.testing.assert_allclose(frame.itrs_to_altaz, np.stack(altaz_basis(RUBIN)), atol=1e-12)


def test_frames_built_together_are_each_exposures_own_bit_for_bit():
    """:meth:`FieldFrame.build_many` against :meth:`FieldFrame.build` one exposure at a time:
    every array equal bit for bit (ERFA and numpy compute each time apart), for pointings
    across the sky (the pole, RA 0/360), 2 to 6 times each over a night, one exposure in UTC
    among TAI ones; the boresight's place is astropy's own AltAz of each."""
    from inject.orbits.passes import FieldFrame

    rng = np.random.default_rng(5)
    starts = Time(61206.95 + np.sort(rng.uniform(0.0, 0.4, 12)), format="mjd", scale="tai")
    pointings = [Pointing(float(ra), float(dec), float(rot)) for ra, dec, rot in zip(
        rng.uniform(0.0, 360.0, 12), rng.uniform(-89.0, 30.0, 12), rng.uniform(0, 360.0, 12))]
    pointings[3], pointings[7] = Pointing(0.0, -90.0, 10.0), Pointing(359.9999, -10.0)
    times = [start + np.linspace(0.0, 30.0, 2 + k % 5) * u.s for k, start in enumerate(starts)]
    times[4] = times[4].utc
    together = FieldFrame.build_many(times, pointings, RUBIN)
    names = ("centre", "east", "north", "alt_deg", "az_deg", "teme_to_itrs", "itrs_to_altaz",
             "sun_itrs", "to_icrs")
    for t, pointing, frame in zip(times, pointings, together):
        alone = FieldFrame.build(t, pointing, RUBIN)
        assert frame.pointing == pointing and frame.times.scale == t.scale
        assert np.array_equal(frame.jd_utc, alone.jd_utc)
        for name in names:
            assert np.array_equal(getattr(frame, name), getattr(alone, name)), name
        seen = pointing.icrs.transform_to(AltAz(obstime=t, location=RUBIN.location))
        np.testing.assert_allclose(frame.alt_deg, seen.alt.deg, rtol=0, atol=1e-9)
        np.testing.assert_allclose(frame.az_deg, seen.az.deg, rtol=0, atol=1e-9)
    assert FieldFrame.build_many([], [], RUBIN) == []
    with pytest.raises(InputError, match="pointings"):
        FieldFrame.build_many(times, pointings[:-1], RUBIN)


def test_tle_file_with_a_name_line(sat, tmp_path):
    path = tmp_path / "example.tle"
    path.write_text("EXAMPLE 550/53 (example data)\n" + "\n".join(sat.tle_lines()) + "\n")
    back = Orbit.read_tle(path)
    assert back.name == "EXAMPLE 550/53 (example data)" and back.kind == "tle"
    assert back.tle_lines() == sat.tle_lines()
    with pytest.raises(OrbitError, match="cannot be read"):
        Orbit.read_tle(tmp_path / "missing.tle")


def test_in_field_pass_to_json(centred):
    out = json.loads(json.dumps(centred.to_dict()))
    assert out["in_field"] is True and out["visible"] is True
    assert len(out["samples"]) == 31 and out["samples"][15]["t_s"] == 15.0
    s = out["samples"][15]
    assert s["sunlit"] is True and s["shadow"] == "sunlit"
    assert abs(s["field_x_deg"]) < 1e-3 and abs(s["field_y_deg"]) < 1e-3
    assert Orbit.from_tle(*out["tle"]).tle_lines() == centred.orbit.tle_lines()


def test_a_shared_frame_must_match(centred):
    from inject.orbits.passes import FieldFrame
    p = centred
    frame = FieldFrame.build(p.utc, p.pointing, RUBIN)
    again = compute_pass(p.orbit, p.exposure, p.pointing, frame=frame)
    np.testing.assert_array_equal(again.xi_deg, p.xi_deg)
    with pytest.raises(InputError, match="frame"):
        compute_pass(p.orbit, p.exposure, Pointing(0.0, 0.0), frame=frame)


def test_magnitude_along_the_pass_follows_the_paper_and_fades_in_the_penumbra(centred, sat):
    from inject import apparent_magnitude
    p = centred
    m = p.magnitude(5.0)
    np.testing.assert_allclose(m, apparent_magnitude(5.0, p.range_km, p.nadir_angle_deg))
    # At mid-exposure: range 666 km, nadir angle 31.8 deg -> 5 log10(666/550) + 0.19 mag fainter.
    mid = len(p.t_s) // 2
    expected = 5.0 + 5 * math.log10(p.range_km[mid] / 550.0) - 2.5 * math.log10(
        math.cos(math.radians(p.nadir_angle_deg[mid])))
    assert m[mid] == pytest.approx(expected)
    # Into the shadow (~215 s after the start): fainter through the penumbra, then no light.
    late = compute_pass(sat, Exposure(Time(START) + 195 * u.s, 40.0), p.pointing,
                        check_epoch=False)
    ml = late.magnitude(5.0)
    pen = late.shadow == "penumbra"
    assert pen.any() and np.all(np.isinf(ml[late.shadow == "umbra"]))
    base = apparent_magnitude(5.0, late.range_km, late.nadir_angle_deg)
    np.testing.assert_allclose((ml - base)[pen], -2.5 * np.log10(late.sun_fraction[pen]))
    assert np.all(np.diff(late.sun_fraction[pen]) <= 0)


def test_a_tle_file_error_names_the_file_line(sat, tmp_path):
    """After a name line and a blank one, TLE line 2 is the file's line 4."""
    l1, l2 = sat.tle_lines()
    bad = l2[:68] + str((int(l2[68]) + 1) % 10)
    path = tmp_path / "bad.tle"
    path.write_text(f"EXAMPLE\n{l1}\n\n{bad}\n")
    with pytest.raises(OrbitError, match=rf"^TLE file '{path}' line 4='2 .*: bad checksum"):
        Orbit.read_tle(path)
    path.write_text(f"{l1[:-1]}x\n{l2}\n")
    with pytest.raises(OrbitError, match=r"line 1='1 .*: bad checksum"):
        Orbit.read_tle(path)
