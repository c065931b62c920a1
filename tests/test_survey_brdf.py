"""Brightness as flown: the survey plan's streaks take a published BRDF model's magnitude.

``sample_fields/constellation_starlink_gen1_brdf.yaml`` carries the Starlink v1.5 model of
Fankhauser, Tyson & Askari (2023, AJ 166, 59) with the BRDFs they inferred from on-orbit
observations; ``constellation_starlink_gen2_brdf.yaml`` the V2 Mini model of Kandula et al.
(2025), fitted to laboratory BRDFs. A planned streak's magnitude is checked against lumos-sat's
own functions called here: its satellite's position from lumos's own TLE propagation, the
Sun's from lumos's own helper, the surfaces built here from the publications' numbers, typed
below. Skipped without lumos-sat (``make install-lumos``), except the missing-lumos error.
"""
import math
import os

import numpy as np
import pytest

ROOT = os.path.join(os.path.dirname(__file__), os.pardir, "sample_fields")
GEN1 = os.path.join(ROOT, "constellation_starlink_gen1.yaml")
GEN1_BRDF = os.path.join(ROOT, "constellation_starlink_gen1_brdf.yaml")
GEN2 = os.path.join(ROOT, "constellation_starlink_gen2.yaml")
GEN2_BRDF = os.path.join(ROOT, "constellation_starlink_gen2_brdf.yaml")
NADIR = (0.0, 0.0, -1.0)
#: Starlink v1.5 as Fankhauser et al. (2023) model it with their BRDFs inferred from on-orbit
#: observations: (area m^2, normal in lumos's brightness frame, BRDF) of the chassis and of
#: the solar array.
V1P5 = [(1.0, NADIR, ("phong", 0.34, 0.40, 8.9)),
        (1.0, (0.0, 1.0, 0.0), ("phong", 0.15, 0.25, 0.26))]
#: Starlink V2 Mini as Kandula et al. (2025) model it (their gen2_starlink/satellitemodels.py,
#: ABG for the bare aluminium): pantograph (C138), chassis mirror film (97.5% of 12 m^2),
#: boom, Ka and Ka/E dishes (LRB), twist (A700), diffuse offset, bare aluminium (2.5%).
_LRB = ("binomial", [[-2.014, 3.935], [0.906, -15.296], [-0.196, 13.039]],
        [[1568.713, -6957.513, 4197.732, -1078.46, 191.648, -29.161],
         [-7807.871, 6352.045, -4865.936, 2780.032, -896.354, 169.988],
         [10000.0, -8481.038, 3785.344, -2006.663, 871.593, -196.501]], 3.0, -3)
V2MINI = [
    (1.03, (0.0, math.sqrt(0.5), -math.sqrt(0.5)),
     ("binomial", [[-1.473, 0.752], [-2.331, 1.024], [5.148, -1.672]],
      [[-6.810e3, -9.991e3, -9.525e3, 3.044e3, 1.819e3, -7.336e2, 1.606e2, -4.217e1, 1.384e1,
        -3.637],
       [8.267e3, 9.423e3, 1.000e4, 1.430e3, -9.889e3, 6.254e3, -2.682e3, 1.078e3, -3.899e2,
        8.700e1],
       [-6.625e3, -9.465e3, -1.803e3, 7.089e3, -2.907e2, -3.307e3, 2.760e3, -1.458e3, 5.716e2,
        -1.287e2]], 3.0, -5)),
    (12 * 0.975, NADIR, ("binomial", [[1.078, -32.658]],
                         [[10000.0, -6040.756, 1392.37, -69.043, -52.863, 52.601]], 3.0, -3)),
    (2.2, NADIR, ("abg", 9.737e-05, 8.448e-06, 2.686)),
    (0.66, NADIR, _LRB),
    (0.19, NADIR, _LRB),
    (0.6, NADIR, ("binomial", [[-0.365, -4.975]], [[1.746, 5.717, 6.474, 1.831, 4.67, 1.163]],
                  1.0, -3)),
    (1.0, NADIR, ("phong", 0.056, 0.0, 0.194)),
    (12 * 0.025, NADIR, ("abg", 0.019989862079564824, 2.2851243807209376e-06,
                         2.2640286229702555)),
]
#: Each BRDF file, its fixed-magnitude twin and the published model it carries.
FILES = {"gen1": (GEN1_BRDF, GEN1, V1P5, 4408), "gen2": (GEN2_BRDF, GEN2, V2MINI, 29988)}
#: An instant of the sample June night at Rubin (the Sun ~15 deg down).
T_CROSS = "2026-06-15T23:12:15"


def _raw(path):
    from inject.schema import load_scene_file

    return load_scene_file(path)


def _brdf(spec):
    """lumos's own BRDF function of a published surface's (type, parameters...)."""
    import lumos.brdf.library

    kind, *params = spec
    if kind == "binomial":
        b, c, d, l1 = params
        return lumos.brdf.library.BINOMIAL(np.array(b), np.array(c), d, l1)
    return getattr(lumos.brdf.library, kind.upper())(*params)


def _model(published):
    """lumos Surfaces of a published model, built here."""
    import lumos.geometry

    return [lumos.geometry.Surface(a, np.array(n), _brdf(spec)) for a, n, spec in published]


@pytest.mark.parametrize("which", sorted(FILES))
def test_the_brdf_sample_files_carry_the_published_surfaces(which):
    """Each loads as ``inject survey`` reads it: its generation's shells and epoch as the
    fixed-magnitude file gives them, no earthshine, and the publication's surfaces (areas,
    normals), built into lumos Surfaces that scatter as lumos's own BRDFs with the published
    numbers, for directions on either side of each normal's specular direction."""
    pytest.importorskip("lumos.brdf.library", reason="needs lumos-sat: make install-lumos")
    from inject.orbits.lumos import surfaces
    from inject.survey.constellation import read_constellation

    path, fixed_path, published, total = FILES[which]
    raw, fixed = _raw(path), _raw(fixed_path)
    assert raw["shells"] == fixed["shells"] and raw["epoch"] == fixed["epoch"]
    constellation = read_constellation(path)
    assert len(constellation) == total
    assert constellation.lumos.get("earthshine") is False
    built, earth_brdf = surfaces("lumos", constellation.lumos)
    assert earth_brdf is None
    assert len(built) == len(published)
    rng = np.random.default_rng(5)
    for surface, (area, normal, spec) in zip(built, published):
        assert surface.area == pytest.approx(area, rel=1e-12)
        assert np.allclose(surface.normal, normal, atol=1e-12)
        reference = _brdf(spec)
        for _ in range(20):
            i, o = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)) + normal)
            assert float(surface.brdf(i, surface.normal, o)) == pytest.approx(
                float(reference(i, np.array(normal), o)), rel=1e-12)


@pytest.fixture(scope="module", params=sorted(FILES))
def planned(request, tmp_path_factory):
    """Satellites aimed at four points of the sky at ``T_CROSS`` (so at four phase angles),
    each planned in a 30 s r visit centred on it with a BRDF file's model and with the paper's
    fixed one, and a TLE file of them in lumos's own layout (name line, then two lines)."""
    pytest.importorskip("lumos.calculator", reason="needs lumos-sat: make install-lumos")
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.orbits.passes import RUBIN, aimed_orbit
    from inject.survey.constellation import parse_constellation
    from inject.survey.plan import plan_visit
    from inject.survey.visits import Visit

    folder = tmp_path_factory.mktemp("brdf")
    t = Time(T_CROSS, scale="utc")
    aims = [(70.0, 270.0), (45.0, 300.0), (60.0, 200.0), (80.0, 120.0)]
    sats = [aimed_orbit(t, alt, az, name=f"AIM{k}", satnum=k + 1)
            for k, (alt, az) in enumerate(aims)]
    tle = folder / "aimed.tle"
    tle.write_text("".join(f"{o.name}\n{a}\n{b}\n" for o in sats for a, b in [o.tle_lines()]))
    path, _, published, _ = FILES[request.param]
    raw = {k: v for k, v in _raw(path).items() if k not in ("shells", "epoch")}
    brdf = parse_constellation({**raw, "tle": tle.name}, folder=str(folder))
    fixed = parse_constellation({k: v for k, v in raw.items() if k != "lumos"} |
                                {"tle": tle.name}, folder=str(folder))
    streaks, fixed_mags = {}, {}
    for k, (alt, az) in enumerate(aims):
        point = SkyCoord(AltAz(alt=alt * u.deg, az=az * u.deg, obstime=t,
                               location=RUBIN.location)).icrs
        visit = Visit(k + 1, float((t - 15.0 * u.s).tai.mjd), point.ra.deg, point.dec.deg, 0.0,
                      "r", 30.0)
        for streak in plan_visit(visit, brdf).streaks:
            if streak.satellite == f"AIM{k}":
                streaks[streak.satellite] = (visit, streak)
        for streak in plan_visit(visit, fixed).streaks:
            if streak.satellite == f"AIM{k}":
                fixed_mags[streak.satellite] = streak.mag
    return {"tle": str(tle), "streaks": streaks, "fixed": fixed_mags, "model": published}


def _skyfield_range_m(tle, name, when):
    """The topocentric range (m) of satellite ``name`` of the TLE file from Rubin, skyfield's."""
    from skyfield.api import EarthSatellite, load, wgs84

    from inject.orbits.passes import RUBIN

    with open(tle) as stream:
        lines = stream.read().splitlines()
    k = lines.index(name)
    ts = load.timescale(builtin=True)
    site = wgs84.latlon(RUBIN.location.lat.deg, RUBIN.location.lon.deg,
                        elevation_m=RUBIN.location.height.to_value("m"))
    sat = EarthSatellite(lines[k + 1], lines[k + 2], name, ts)
    return float((sat - site).at(ts.from_astropy(when)).distance().m)


def _lumos_mag(published, tle, name, when):
    """lumos-sat's own AB magnitude and solar phase angle (deg) of satellite ``name`` of the
    TLE file at ``when``, seen from Rubin, with a published model: lumos's propagation, its
    Sun, its calculator."""
    import lumos.calculator
    import lumos.constants
    import lumos.constellation.library
    import lumos.conversions

    from inject.orbits.passes import RUBIN

    sats = lumos.constellation.library.ConstellationFromTLE(tle)
    alts, azs, _ = sats.get_hcs_position(when, RUBIN.location)
    k = sats.satellite_ids.index(name)
    # lumos's sphere (6378 km, the observer on it) at the satellite's true range: the height
    # from the triangle Earth's centre - observer - satellite, the range from skyfield.
    radius, rho = lumos.constants.EARTH_RADIUS, _skyfield_range_m(tle, name, when)
    height = math.sqrt(radius ** 2 + rho ** 2
                       + 2 * radius * rho * math.sin(math.radians(alts[k]))) - radius
    sun_alt, sun_az = lumos.calculator.get_sun_alt_az(when, RUBIN.location)
    flux = lumos.calculator.get_intensity_observer_frame(
        _model(published), height, float(alts[k]), float(azs[k]), float(sun_alt),
        float(sun_az), include_earthshine=False)
    mag = float(lumos.conversions.intensity_to_ab_mag(float(flux), clip=False))
    # The solar phase angle: between the directions from the satellite to the Sun and to the
    # observer (the Sun taken as infinitely far; lumos's frame puts it in the y-z plane).
    obs_x, obs_y, obs_z, past = lumos.calculator.get_brightness_coords(
        float(alts[k]), float(azs[k]), height, float(sun_alt), float(sun_az))
    to_obs = np.array([obs_x, obs_y, obs_z - (radius + height)],
                      float)
    to_sun = np.array([0.0, math.cos(past), -math.sin(past)])
    phase = math.degrees(math.acos(float(to_obs @ to_sun) / np.linalg.norm(to_obs)))
    return mag, phase


def test_a_planned_streaks_magnitude_is_lumos_sats_at_that_geometry(planned):
    """Each streak's magnitude (the plan's model at the middle of its crossing, t_mid_s) is
    lumos-sat's for the Sun, satellite and observer at that instant.

    The satellite's alt/az come here from lumos's own astropy propagation of the same TLE
    and its range from skyfield's (inject's plan takes them from SGP4 through its own frames);
    lumos is given the height at which its 6378 km sphere puts the satellite at that range.
    Tolerance 0.002 mag: the three propagations agree within arcseconds and metres, and the
    Phong lobe of n = 8.9 changes its flux by at most n tan(angle), under 1e-3 mag for 10
    arcsec, the 1/r^2 term by 2e-5 mag a metre at ~600 km. (lumos's own geodetic height
    instead would put the satellite 0.5% too far on that sphere, 0.01 mag fainter.) The
    streak is fully sunlit (no penumbra dimming, which lumos does not model).
    The four aims give four phase angles (63-117 deg): the BRDF's magnitudes less the
    paper's fixed model's (g = 5.0 at 550 km face-on, scaled by cos/r^2 alone) for the same
    crossings differ from aim to aim by more than 0.2 mag (0.40 with v1.5, 0.28 with V2
    Mini): the light scattered, not only the range and foreshortening, changes with the
    geometry."""
    from astropy import units as u

    streaks = planned["streaks"]
    assert len(streaks) == 4, sorted(streaks)
    assert sorted(planned["fixed"]) == sorted(streaks)
    phases, excess = [], []
    for name, (visit, streak) in sorted(streaks.items()):
        assert streak.sun_fraction_min == 1.0
        when = visit.start.utc + streak.t_mid_s * u.s
        expected, phase = _lumos_mag(planned["model"], planned["tle"], name, when)
        assert streak.mag == pytest.approx(expected, abs=0.002), (name, phase)
        phases.append(phase)
        excess.append(streak.mag - planned["fixed"][name])
    assert max(phases) - min(phases) > 45.0
    assert max(excess) - min(excess) > 0.2


def test_without_lumos_sat_the_brdf_file_is_a_one_line_error(cli, no_lumos, tmp_path):
    """``inject survey`` with the BRDF file and no lumos-sat: exit status 2, one line naming
    the file and ``make install-lumos``, nothing written."""
    (tmp_path / "v.csv").write_text(
        "observationId,observationStartMJD,fieldRA,fieldDec,rotSkyPos,band,visitExposureTime\n"
        "1,61206.97,250,-30,0,r,30\n")
    status, _, err = cli("survey", tmp_path / "v.csv", "-o", tmp_path / "out",
                         "--constellation", GEN1_BRDF, "--no-plots")
    assert status == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "constellation_starlink_gen1_brdf.yaml" in lines[0]
    assert "make install-lumos" in lines[0]
    assert not (tmp_path / "out").exists()


def test_into_earths_shadow_the_brdf_magnitude_runs_on_through_the_penumbra():
    """A satellite aimed to enter the Earth's shadow mid-exposure (alt 36, az 120 at
    ``T_CROSS``): lumos's own shadow, a point Sun behind its 6378 km sphere, ends in the
    middle of the pass's penumbra (a finite Sun, the WGS84 Earth). Where lumos has the
    satellite lit, each vertex is lumos's own magnitude (its function called here) dimmed by
    the penumbra; where lumos has it dark but the pass lit, the vertex keeps a magnitude (no
    99) that runs on from its neighbours: with the penumbra's dimming taken off, no step over
    0.05 mag between vertices (the geometry moves by ~0.1 deg a second; the lit vertices change
    by 0.01-0.02 mag a step)."""
    pytest.importorskip("lumos.calculator", reason="needs lumos-sat: make install-lumos")
    import lumos.brdf.library
    import lumos.calculator
    import lumos.constants
    import lumos.conversions
    import lumos.geometry
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord, get_sun
    from astropy.time import Time

    from inject import Exposure, Pointing, compute_pass
    from inject.geometry import nadir_angle
    from inject.orbits.passes import RUBIN, aimed_orbit
    from inject.orbits.tracks import sunlit_runs
    from inject.photometry import apparent_magnitude

    t = Time(T_CROSS, scale="utc")
    orbit = aimed_orbit(t, 36.0, 120.0)
    point = SkyCoord(AltAz(alt=36.0 * u.deg, az=120.0 * u.deg, obstime=t,
                           location=RUBIN.location)).icrs
    dense = compute_pass(orbit, Exposure(t - 15.0 * u.s, 30.0),
                         Pointing(point.ra.deg, point.dec.deg, 0.0))
    runs, _ = sunlit_runs("orbit", dense, 5.0, _raw(GEN1_BRDF)["lumos"], 550.0)
    assert len(runs) == 1
    run, values = runs[0]
    fraction = dense.sun_fraction[run]
    assert fraction.min() < 0.5 and fraction.max() > 0.9
    # The vertex's apparent magnitude (the streak model's cos/r^2 scaling of its mag) less
    # the penumbra's dimming.
    apparent = np.array([apparent_magnitude(v["mag"], v["range"],
                                            nadir_angle(v["height"], v["zenith"]), 550.0)
                         for v in values]) + 2.5 * np.log10(fraction)
    model = _model(V1P5)
    sun = get_sun(dense.utc[run]).transform_to(AltAz(obstime=dense.utc[run],
                                                     location=RUBIN.location))
    radius = lumos.constants.EARTH_RADIUS
    dark = 0
    for k, i in enumerate(run):
        rho = dense.range_km[i] * 1e3
        height = math.sqrt(radius ** 2 + rho ** 2
                           + 2 * radius * rho * math.sin(math.radians(dense.alt_deg[i]))) - radius
        flux = float(lumos.calculator.get_intensity_observer_frame(
            model, height, dense.alt_deg[i], dense.az_deg[i], sun.alt.deg[k], sun.az.deg[k],
            include_earthshine=False))
        if flux > 0:
            expected = lumos.conversions.intensity_to_ab_mag(flux, clip=False)
            assert apparent[k] == pytest.approx(expected, abs=1e-6)
        else:
            dark += 1
            assert fraction[k] > 0.0
    assert dark >= 2 and dark < len(run)  # lit by the pass, dark to lumos: both kinds
    assert apparent.max() < 10.0
    assert np.abs(np.diff(apparent)).max() < 0.05
