"""Checks against numbers and computations made outside the code under test.

Each test here stands against a bug that every test comparing the code with itself let pass
(issue 19's mutation audit): random streams keyed wrong (the same stars in every tile, the
same photons on every CCD), the ITL reference pixel checked only against the centre it was
defined from, apparent positions and orbit vertices compared at tolerances the size of the
error, a bright star's halo from a tile only its large stamp reaches; and the probe's cases
(a WCS at the pole, a one-sided cut-out, a UTC offset in a time).
"""
import json
import os

import numpy as np
import pytest

from inject import (
    Exposure,
    Orbit,
    Pointing,
    ccd_wcs,
    compute_pass,
    load_scene_file,
    parse_focal_scene,
    parse_scene,
    pointing_wcs,
    resolve_ccd_orbits,
    simulate,
    simulate_ccd,
)
from inject.camera import layout as fp
from inject.camera.wcs import focal_to_radec
from inject.orbits.passes import RUBIN, TRACK_STEP_S, aimed_orbit
from inject.photometry import band
from inject.profile import Seeing
from inject.stars import draw_stars, psf_stamps

ARCSEC = 1.0 / 3600.0
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TLE = os.path.join(ROOT, "sample_fields", "example_starlink_like.tle")


def _sep_arcsec(ra1, dec1, ra2, dec2):
    """Angular separation (arcsec) by the haversine formula (no astropy)."""
    ra1, dec1, ra2, dec2 = (np.radians(np.asarray(v, float)) for v in (ra1, dec1, ra2, dec2))
    h = np.sin((dec2 - dec1) / 2) ** 2 + np.cos(dec1) * np.cos(dec2) * np.sin(
        (ra2 - ra1) / 2) ** 2
    return np.degrees(2 * np.arcsin(np.sqrt(h))) * 3600


def _untangent(xi_deg, eta_deg, ra0_deg, dec0_deg):
    """(ra, dec) deg of gnomonic standard coordinates (xi East, eta North; tangent-plane
    radians written in degrees) about (ra0, dec0): the textbook inverse projection."""
    xi, eta = np.radians(xi_deg), np.radians(eta_deg)
    ra0, dec0 = np.radians(ra0_deg), np.radians(dec0_deg)
    denom = np.cos(dec0) - eta * np.sin(dec0)
    ra = ra0 + np.arctan2(xi, denom)
    dec = np.arctan2(np.sin(dec0) + eta * np.cos(dec0), np.hypot(xi, denom))
    return np.degrees(ra) % 360.0, np.degrees(dec)


def _focal(**keys):
    raw = {"seed": 11, "band": "g", "pointing": {"ra": 10.0, "dec": -30.0}, "seeing": 0.7,
           "satellites": [], "sky": False, "noise": False, "stars": False}
    raw.update(keys)
    return parse_focal_scene(raw)


# --- Random streams: different tiles, different detectors draw different numbers ----------

def test_two_star_tiles_draw_different_stars():
    """Each sky tile has its own stream: the stars of neighbouring tiles, in positions
    relative to their tile, share nothing (one stream for every tile would repeat the same
    pattern, star for star, across the sky)."""
    from inject import skytiles
    from inject.stars import sample_stars

    spec = _focal(stars={"density_per_deg2": 20000, "mag_limit": 22}).scene.stars
    tiles = [(1200, 40), (1200, 41), (1201, 40), (300, 7)]
    drawn = {}
    for tile in tiles:
        gen = skytiles.tile_generator(11, tile)
        mag = sample_stars(spec, skytiles.tile_area_deg2(tile), "g", gen)
        ra, dec = skytiles.tile_positions(gen, tile, mag.size)
        assert 100 < mag.size < 400  # 0.01 deg^2 at 20 000 per deg^2
        ra_lo, ra_hi, dec_lo, dec_hi = skytiles.tile_bounds(tile)
        assert np.all((ra >= ra_lo) & (ra < ra_hi) & (dec >= dec_lo) & (dec < dec_hi))
        drawn[tile] = ((ra - ra_lo) / (ra_hi - ra_lo), (dec - dec_lo) / (dec_hi - dec_lo), mag)
    for a in tiles:
        for b in tiles:
            if a >= b:
                continue
            (xa, ya, ma), (xb, yb, mb) = drawn[a], drawn[b]
            close = np.hypot(xa[:, None] - xb[None, :], ya[:, None] - yb[None, :]) < 1e-9
            assert not close.any(), f"tiles {a} and {b} share star positions"
            assert not np.isin(ma, mb).any(), f"tiles {a} and {b} share magnitudes"


def test_star_photons_are_keyed_on_the_detector():
    """The same star stamp on two detectors: independent Poisson draws. Each detector's
    counts scatter about the expected charge as Poisson does (variance = mean), and the two
    detectors' scatters are uncorrelated (one stream for every detector: identical)."""
    raw = {"seed": 4, "band": "g", "exptime": 30.0, "seeing": 0.7, "zenith": 30.0,
           "detector": {"type": "itl", "nx": 64, "ny": 64}, "sky": False, "stars": True,
           "noise": True, "satellites": []}
    scene = parse_scene(raw)
    stamps = psf_stamps(Seeing(0.7).profile(), 0.2)
    x, y, flux = 31.3, 30.6, 2e5

    def star(image, noise=None, variance=None):
        draw_stars(image, [x], [y], [flux], stamps, 0.2, noise=noise, variance=variance)

    def nothing(image, noise=None, variance=None):
        return None

    expected = np.zeros((64, 64))
    draw_stars(expected, [x], [y], [flux], stamps, 0.2)
    counts = []
    for detector_index in (3, 17):
        with_star = simulate(scene, detector_index=detector_index, add_stars=star).image
        without = simulate(scene, detector_index=detector_index, add_stars=nothing).image
        # No sky, no dark current: the difference is the star's collected charge (integers;
        # the read noise, drawn from the amplifiers' own streams, cancels).
        counts.append(np.rint(with_star.astype(np.float64) - without))
    lit = expected > 5.0
    assert lit.sum() > 100
    residuals = [(c[lit] - expected[lit]) / np.sqrt(expected[lit]) for c in counts]
    for r in residuals:
        assert 0.8 < r.var() < 1.2  # Poisson: variance = mean
    corr = np.corrcoef(residuals[0], residuals[1])[0, 1]
    assert abs(corr) < 5 / np.sqrt(lit.sum())


def test_ccd_noise_is_keyed_on_the_detector():
    """Two e2v CCDs of one focal-plane scene, same sky: their noise is independent (the
    difference of the two images has twice one image's variance, sky + read noise^2), not
    the same draws."""
    fscene = _focal(sky=True, noise=True, cutout={"nx": 64, "ny": 64})
    images = [simulate_ccd(fscene, fp.ccd(name), [])[1] for name in ("R22_S11", "R22_S12")]
    level = images[0].sky_level
    read = fp.ccd("R22_S11").detector.amp_value("read_noise", 0, 0)
    one = level + read ** 2
    diff = images[0].image.astype(np.float64) - images[1].image
    assert diff.var() == pytest.approx(2 * one, rel=0.1)


# --- Constants against obs_lsst's layout, written out ------------------------------------

#: Pixel-area corners (mm) of a few CCDs: the centre of pixel (-0.5, -0.5) and of pixel
#: (nx - 0.5, ny - 0.5), from obs_lsst's layout by hand: raft Rij at (127 (j - 2), 127 (i - 2))
#: mm, its CCD Skl at (42.25 (l - 1), 42.25 (k - 1)) mm from the raft centre, 10 um pixels,
#: the reference pixel at that position: e2v (2047.5, 2001.5) of 4096 x 4004, ITL
#: (2036.5, 2000.5) of 4072 x 4000. For ITL the lower-left corner is (2037, 2001) px = (20.37,
#: 20.01) mm from the centre, the upper-right (2035, 1999) px = (20.35, 19.99) mm; for e2v
#: both are (2048, 2002) px = (20.48, 20.02) mm.
CORNERS_MM = {
    # ITL, raft R01 at (-127, -254), S00 at (-42.25, -42.25): centre (-169.25, -296.25)
    "R01_S00": ("itl", (-189.62, -316.26), (-148.90, -276.26)),
    # e2v, the centre CCD: centre (0, 0)
    "R22_S11": ("e2v", (-20.48, -20.02), (20.48, 20.02)),
    # ITL, raft R43 at (127, 254), S22 at (42.25, 42.25): centre (169.25, 296.25)
    "R43_S22": ("itl", (148.88, 276.24), (189.60, 316.24)),
    # ITL, raft R10 at (-254, -127), S02 at (42.25, -42.25): centre (-211.75, -169.25)
    "R10_S02": ("itl", (-232.12, -189.26), (-191.40, -149.26)),
    # e2v, raft R30 at (-254, 127), S21 at (0, 42.25): centre (-254, 169.25)
    "R30_S21": ("e2v", (-274.48, 149.23), (-233.52, 189.27)),
}


@pytest.mark.parametrize("name", sorted(CORNERS_MM))
def test_ccd_corners_are_obs_lsst_s(name):
    vendor, lower, upper = CORNERS_MM[name]
    c = fp.ccd(name)
    assert c.vendor == vendor
    ny, nx = c.shape
    assert (nx, ny) == ((4072, 4000) if vendor == "itl" else (4096, 4004))
    for pixel, corner in (((-0.5, -0.5), lower), ((nx - 0.5, ny - 0.5), upper)):
        np.testing.assert_allclose(c.pixel_to_focal(*pixel), corner, atol=1e-9)
    np.testing.assert_allclose(c.bounds_mm(), (lower[0], upper[0], lower[1], upper[1]),
                               atol=1e-9)
    # The CCD's WCS puts its corners where the focal plane's mm go on the sky.
    pointing = {"ra": 30.0, "dec": -40.0, "rotation": 20.0}
    ra, dec = ccd_wcs(c, pointing).all_pix2world([(-0.5, -0.5), (nx - 0.5, ny - 0.5)], 0).T
    ra_fp, dec_fp = focal_to_radec(np.array([lower[0], upper[0]]),
                                   np.array([lower[1], upper[1]]), pointing)
    assert np.all(_sep_arcsec(ra, dec, ra_fp, dec_fp) < 1e-4)


# --- Apparent positions against skyfield, orbit vertices against the WCS ------------------

@pytest.fixture(scope="module")
def skyfield_ts(skyfield_timescale):
    """A skyfield timescale on the IERS table astropy ships (with polar motion)."""
    return skyfield_timescale


def _sf_time(ts, t):
    # Two-part Julian dates: one float64 JD is only good to ~20 us (0.15 m of a LEO
    # satellite's path, 0.05" at 600 km), skyfield's from_astropy keeps just one.
    return ts.tt_jd(t.tt.jd1, t.tt.jd2)


@pytest.mark.parametrize("alt, az", [(55.0, 290.0), (35.0, 200.0), (70.0, 120.0)])
def test_apparent_positions_match_an_independent_apparent_place(skyfield_ts, alt, az):
    """The field angles of a pass against skyfield's apparent place, to 0.05".

    Independent chain: skyfield's SGP4 and TEME -> GCRS, the satellite at the retarded time
    (light time iterated) seen from the site at the sample time (astrometric, GCRS axes),
    aberrated by the site's geocentric velocity (diurnal aberration: a satellite shares the
    Earth's orbital motion); then the ICRS direction of the star that appears there (inverting
    the stars' aberration by the site's barycentric velocity, astropy's ERFA ephemeris) and
    its gnomonic offsets about the ICRS boresight. The code's documented approximation (the
    Earth's rotation over the light time applied to the satellite instead of the site,
    omega tau <= 0.035" at these ranges) stays inside the tolerance; leaving out that rotation
    altogether moves the track by ~0.27".
    """
    from astropy import units as u
    from astropy.coordinates import ICRS, AltAz, SkyCoord, get_body_barycentric_posvel
    from skyfield.api import EarthSatellite, wgs84
    from skyfield.constants import AU_KM, C_AUDAY, DAY_S
    from skyfield.relativity import add_aberration

    ts = skyfield_ts
    exposure = Exposure("2026-06-15T23:30:00", 30.0)
    sat = aimed_orbit(exposure.middle, alt, az, name="INDEPENDENT")
    # Point at the apparent mid-exposure position (as a star would be), rotated.
    first = compute_pass(sat, exposure, Pointing(0.0, 0.0))
    mid = len(first.t_s) // 2
    c = SkyCoord(az=first.apparent_az_deg[mid] * u.deg, alt=first.apparent_alt_deg[mid] * u.deg,
                 frame=AltAz(obstime=first.utc[mid], location=RUBIN.location)).transform_to(ICRS())
    pointing = Pointing(c.ra.deg, c.dec.deg, 30.0)
    p = compute_pass(sat, exposure, pointing)

    esat = EarthSatellite(*sat.tle_lines(), ts=ts)
    site = wgs84.latlon(RUBIN.lat_deg, RUBIN.lon_deg, elevation_m=RUBIN.height_m)
    here = site.at(_sf_time(ts, p.utc))
    obs, v_obs = here.position.km, here.velocity.km_per_s
    tau = np.zeros(p.t_s.size)
    for _ in range(3):
        d = esat.at(_sf_time(ts, p.utc - tau * u.s)).position.km - obs
        tau = np.linalg.norm(d, axis=0) / 299792.458

    def aberrated(vec_km, v_km_s):
        pos = vec_km / AU_KM
        add_aberration(pos, v_km_s * DAY_S / AU_KM, np.linalg.norm(pos, axis=0) / C_AUDAY)
        return pos / np.linalg.norm(pos, axis=0)

    seen = aberrated(d, v_obs)
    _, v_earth = get_body_barycentric_posvel("earth", p.utc)
    v_bary = v_earth.xyz.to_value(u.km / u.s) + v_obs
    star = seen.copy()
    for _ in range(4):  # the ICRS direction whose aberrated image is where the satellite is
        star = star + (seen - aberrated(star, v_bary))
        star /= np.linalg.norm(star, axis=0)
    ra0, dec0 = np.radians(pointing.ra_deg), np.radians(pointing.dec_deg)
    centre = np.array([np.cos(dec0) * np.cos(ra0), np.cos(dec0) * np.sin(ra0), np.sin(dec0)])
    east = np.array([-np.sin(ra0), np.cos(ra0), 0.0])
    north = np.cross(centre, east)
    xi = np.degrees(east @ star / (centre @ star))
    eta = np.degrees(north @ star / (centre @ star))
    near = np.hypot(xi, eta) < 2.0  # the field and around it
    assert near.sum() >= 5
    off = np.hypot(xi - p.xi_deg, eta - p.eta_deg)[near] / ARCSEC
    assert off.max() < 0.05, off


def test_ccd_scene_orbit_vertices_are_where_the_wcs_puts_the_pass():
    """Every vertex of a CCD scene's orbit track, through the scene's WCS (pixel -> sky), is
    the pass's sky position at that sample (its ICRS gnomonic offsets about the pointing,
    projected back by the textbook formula) to 0.02" (a tenth of a pixel)."""
    start, exptime = "2026-06-15T23:29:59.5", 1.0
    ra0, dec0, rotation = 151.95, -25.73, 30.0
    raw = {"seed": 2, "band": "g", "exptime": exptime, "seeing": 0.7, "time": start,
           "pointing": {"ra": ra0, "dec": dec0, "rotation": rotation},
           "detector": {"type": "e2v", "nx": 300, "ny": 200}, "sky": False, "stars": False,
           "noise": False,
           "satellites": [{"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
                           "orbit": {"tle": list(Orbit.read_tle(TLE).tle_lines())}}]}
    resolved = resolve_ccd_orbits(raw)
    vertices = resolved["satellites"][0]["track"]["vertices"]
    assert len(vertices) >= 5
    dense = compute_pass(Orbit.read_tle(TLE), Exposure(start, exptime),
                         Pointing(ra0, dec0, rotation), step_s=TRACK_STEP_S)
    scene = parse_scene(resolved)
    wcs = pointing_wcs(scene.pointing, scene.detector.shape, 0.2)
    for v in vertices:
        (k,) = np.flatnonzero(dense.range_km == v["range"])  # the vertex's sample
        ra, dec = wcs.wcs_pix2world([[v["x"], v["y"]]], 0)[0]
        ra_p, dec_p = _untangent(dense.xi_deg[k], dense.eta_deg[k], ra0, dec0)
        assert _sep_arcsec(ra, dec, ra_p, dec_p) < 0.02


# --- A bright star's halo from a neighbouring tile ---------------------------------------

def test_bright_halo_from_a_tile_only_the_bright_stamp_reaches(monkeypatch):
    """R24_S00's pixel area starts at x = 211.75 - 20.48 = 191.27 mm. A 12th-magnitude star
    at x = 189.9 mm, in a sky tile outside the CCD, is 137.5 px from the first column: its
    core stamp (~0.5 mm) does not reach the CCD, its bright stamp (~1.9 mm) does. Its halo
    on a 40-column cut-out (137-177 px from it) is the star's flux times GalSim's
    pixel-integrated Kolmogorov PSF there."""
    import galsim

    import inject.stars as stars_module
    from inject import skytiles
    from inject.camera.wcs import ccd_wcs

    ccd = fp.ccd("R24_S00")
    star_x, star_y, mag = 189.9, -61.95, 12.5
    fscene = _focal(stars={"density_per_deg2": 1000, "mag_limit": 20, "mag_bright": 10},
                    detectors=["R24_S00"], cutout={"nx": 40, "ny": 64})
    # The star's sky position; every sky tile the CCD draws gets one star of this magnitude,
    # put at that position by the tile that holds it and on the far side of the sky by the
    # others.
    target = ccd_wcs(ccd, fscene.pointing).pixel_to_world_values(*ccd.focal_to_pixel(star_x,
                                                                                     star_y))
    target = tuple(float(v) for v in target)
    placed = []

    def positions(gen, tile, n):
        ra_lo, ra_hi, dec_lo, dec_hi = skytiles.tile_bounds(tile)
        if ra_lo <= target[0] < ra_hi and dec_lo <= target[1] < dec_hi:
            placed.append(tile)
            return np.full(n, target[0]), np.full(n, target[1])
        return np.full(n, (target[0] + 180.0) % 360.0), np.full(n, -target[1])

    monkeypatch.setattr(skytiles, "tile_positions", positions)
    monkeypatch.setattr(stars_module, "sample_stars", lambda *args: np.array([mag]))
    image = simulate_ccd(fscene, ccd, [])[1].image
    assert placed, "the star's tile was not drawn"

    px, py = ccd.focal_to_pixel(star_x, star_y)
    assert (px, py) == pytest.approx((-137.5, 31.5))
    flux = 10 ** (0.4 * (band("g").zeropoint - mag)) * 30.0
    # GalSim's drawing: the PSF centred at (-137.5, 31.5) on pixels x = 0..39, y = 0..63,
    # convolved with the pixel in real space (an FFT drawing at GalSim's default folding
    # threshold aliases 40% more into these far wings; the stamps, drawn in Fourier space at
    # the project's tighter threshold, keep ~2%).
    psf = galsim.Kolmogorov(fwhm=0.7)
    bounds = galsim.BoundsI(0, 39, 0, 63)
    drawn = psf.drawImage(galsim.ImageD(bounds, scale=0.2),
                          center=galsim.PositionD(px, py), method="real_space")
    expected = flux * drawn.array
    assert expected.sum() > 100  # e-: the halo is there to see
    assert image.sum() == pytest.approx(expected.sum(), rel=0.04)
    # Brightest in the first column, falling away from the star.
    cols = image.sum(axis=0)
    np.testing.assert_allclose(cols, expected.sum(axis=0), rtol=0.05)


# --- Probe cases ---------------------------------------------------------------------------

@pytest.mark.parametrize("ra", [0.0, 40.0, 250.0])
def test_wcs_at_the_pole_is_the_wcs_next_to_it(ra):
    """pointing.dec = 90 exactly and 1e-5 deg from it give the same sky for the same pixels
    (0.036" apart: the pointings' own offset), for a CCD scene and a focal-plane CCD."""
    offset = 1e-5 * 3600
    pixels = [(0.0, 0.0), (299.0, 0.0), (0.0, 199.0), (150.0, 100.0)]
    pole = pointing_wcs({"ra": ra, "dec": 90.0, "rotation": 10.0}, (200, 300), 0.2)
    near = pointing_wcs({"ra": ra, "dec": 90.0 - 1e-5, "rotation": 10.0}, (200, 300), 0.2)
    a, b = pole.wcs_pix2world(pixels, 0).T, near.wcs_pix2world(pixels, 0).T
    assert np.all(np.abs(_sep_arcsec(*a, *b) - offset) < 1e-3)
    c = fp.ccd("R03_S12")
    ny, nx = c.shape
    corners = [(0.0, 0.0), (nx - 1.0, 0.0), (0.0, ny - 1.0), (nx - 1.0, ny - 1.0)]
    for pointing in ({"ra": ra, "dec": 90.0, "rotation": 10.0},):
        a = ccd_wcs(c, pointing).all_pix2world(corners, 0).T
        b = ccd_wcs(c, dict(pointing, dec=90.0 - 1e-5)).all_pix2world(corners, 0).T
        assert np.all(np.abs(_sep_arcsec(*a, *b) - offset) < 1e-3)
        x, y = c.pixel_to_focal(*np.array(corners).T)
        a = focal_to_radec(x, y, pointing)
        b = focal_to_radec(x, y, dict(pointing, dec=90.0 - 1e-5))
        assert np.all(np.abs(_sep_arcsec(*a, *b) - offset) < 1e-3)


def test_cutout_takes_one_side_alone_and_clips_each_ccd_to_its_own_size():
    from inject.exposure.plan import ccd_shape

    e2v, itl = fp.ccd("R22_S11"), fp.ccd("R10_S02")  # 4096 x 4004 and 4072 x 4000
    cases = {
        (("nx", 64),): {e2v: (4004, 64), itl: (4000, 64)},
        (("ny", 50),): {e2v: (50, 4096), itl: (50, 4072)},
        (("nx", 4096), ("ny", 30)): {e2v: (30, 4096), itl: (30, 4072)},
        (("nx", 4080), ("ny", 4002)): {e2v: (4002, 4080), itl: (4000, 4072)},
    }
    for spec, shapes in cases.items():
        fscene = _focal(cutout=dict(spec))
        for c, shape in shapes.items():
            assert ccd_shape(fscene, c) == shape
    # Beyond the largest sensor, nothing, a fraction: refused, naming the key.
    from inject import SceneError
    for bad, where in (({"nx": 4097}, "cutout.nx=4097"), ({"ny": 4005}, "cutout.ny=4005"),
                       ({}, "cutout"), ({"nx": 0}, "cutout.nx=0"),
                       ({"ny": 2.5}, "cutout.ny=2.5")):
        with pytest.raises(SceneError, match=where.replace(".", r"\.")):
            _focal(cutout=bad)


def test_cutout_nx_alone_simulates_that_many_columns():
    fscene = _focal(cutout={"ny": 3}, sky={"level": 100.0})
    result = simulate_ccd(fscene, fp.ccd("R22_S11"), [])[1]
    assert result.image.shape == (3, 4096)
    np.testing.assert_array_equal(result.image, 100.0)


OFFSET_TIME = "2026-06-15T20:29:59.5-03:00"
UTC_TIME = "2026-06-15T23:29:59.500"


@pytest.mark.parametrize("text", [f"time: {OFFSET_TIME}", f"time: '{OFFSET_TIME}'",
                                  f'time: "{OFFSET_TIME}"'])
def test_utc_offset_in_a_scene_time_is_converted(tmp_path, text):
    """A YAML timestamp and a quoted string with the same offset give the same UTC time."""
    path = tmp_path / "scene.yaml"
    path.write_text("detector: {type: itl, nx: 16, ny: 16}\nstars: false\n" + text + "\n")
    assert parse_scene(load_scene_file(str(path))).time == UTC_TIME


def test_utc_offset_in_time_option_is_converted(cli):
    common = ["--orbit", "height=550,inclination=53,raan=10,mean_anomaly=40", "--exptime", "2",
              "--ra", "10", "--dec", "-30", "--json"]
    status, offset, _ = cli("pass", "--time", OFFSET_TIME, *common)
    assert status == 0
    status, utc, _ = cli("pass", "--time", UTC_TIME, *common)
    assert status == 0
    assert json.loads(offset) == json.loads(utc)
    status, _, err = cli("pass", "--time", "2026-06-15T20:29:59 -03:00 tomorrow", *common)
    assert status == 2 and "--time=" in err


def test_job_slices_are_interleaved():
    """``--job k --njobs n`` takes every n-th CCD from the k-th (so that the streak CCDs,
    neighbours in id, spread over the jobs), written out here for 7 CCDs in 3 jobs."""
    from inject.exposure.runner import slice_ccds

    ccds = fp.CCDS[:7]
    names = [[c.name for c in slice_ccds(ccds, job, 3)] for job in range(3)]
    assert names == [["R01_S00", "R01_S10", "R01_S20"], ["R01_S01", "R01_S11"],
                     ["R01_S02", "R01_S12"]]


@pytest.mark.parametrize("compressed", [False, True])
def test_reader_add_keeps_blank_pixels_undefined(tmp_path, compressed):
    """``read_exposure(...).add`` (the public reader's own guard, not add-streak's model
    cut to the usable pixels): a delta everywhere changes the defined integers by exactly
    it and leaves every BLANK pixel BLANK, plain or tile-compressed."""
    from astropy.io import fits

    from inject import read_exposure

    stored = np.arange(40 * 30, dtype=np.int16).reshape(30, 40) % 1000 + 100
    stored[5:9, 10:30] = -32768
    hdu = fits.CompImageHDU(stored, compression_type="RICE_1") if compressed \
        else fits.ImageHDU(stored)
    path = tmp_path / "blank.fits"
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(path)
    with fits.open(path, mode="update", do_not_scale_image_data=True) as hdus:
        hdus[1].header["BLANK"] = -32768
    exposure = read_exposure(str(path))
    exposure.add(exposure.image_index, np.full(stored.shape, 7.0))
    exposure.write(str(tmp_path / "out.fits"))
    with fits.open(tmp_path / "out.fits", do_not_scale_image_data=True) as hdus:
        new = np.asarray(hdus[1].data)
    undefined = stored == -32768
    assert np.all(new[undefined] == -32768)
    assert np.all(new[~undefined] == stored[~undefined] + 7)
