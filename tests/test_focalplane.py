"""LSSTCam focal-plane layout, distortion and WCS against obs_lsst's numbers and independent
computations."""
import numpy as np
import pytest

from inject import InputError, ccd_wcs
from inject.camera import layout as fp

POINTING = {"ra": 52.0, "dec": -28.0, "rotation": 35.0}


def test_reference_numbers_from_obs_lsst():
    r22 = fp.ccd("R22_S11")
    assert r22.id == 94 and r22.vendor == "e2v"
    np.testing.assert_allclose(r22.pixel_to_focal(0, 0), (-20.475, -20.015), atol=1e-12)
    r01 = fp.ccd("R01_S00")
    assert r01.id == 0 and r01.vendor == "itl"
    np.testing.assert_allclose(r01.pixel_to_focal(*fp.REFPOS["itl"]), (-169.25, -296.25),
                               atol=1e-12)
    assert fp.ccd("R43_S22").id == 188
    assert fp.ccd(94) is r22 and fp.ccd("94") is r22


def test_ids_vendors_and_corner_rafts():
    assert [c.id for c in fp.CCDS] == list(range(189))
    assert len({c.name for c in fp.CCDS}) == 189
    itl = {c.raft for c in fp.CCDS if c.vendor == "itl"}
    assert itl == {"R01", "R02", "R03", "R10", "R20", "R41", "R42", "R43"}
    assert sum(c.vendor == "e2v" for c in fp.CCDS) == 13 * 9
    for corner in ("R00_S11", "R04_S00", "R40_S22", "R44_S12"):
        with pytest.raises(InputError, match="corner rafts"):
            fp.ccd(corner)
    for bad in ("R55_S11", "R22_S33", 189, -1, "x"):
        with pytest.raises(InputError):
            fp.ccd(bad)
    assert [c.name for c in fp.select("R22_S12,R01_S00, R22_S12")] == ["R01_S00", "R22_S12"]


def test_pixels_round_trip_and_ccds_never_overlap():
    rng = np.random.default_rng(3)
    for c in fp.CCDS[::17]:
        x, y = rng.uniform(-0.5, 4000, 50), rng.uniform(-0.5, 3999, 50)
        np.testing.assert_allclose(c.focal_to_pixel(*c.pixel_to_focal(x, y)), (x, y),
                                   atol=1e-9)
    boxes = np.array([c.bounds_mm() for c in fp.CCDS])
    for i in range(len(boxes)):
        overlap_x = np.minimum(boxes[i, 1], boxes[:, 1]) - np.maximum(boxes[i, 0], boxes[:, 0])
        overlap_y = np.minimum(boxes[i, 3], boxes[:, 3]) - np.maximum(boxes[i, 2], boxes[:, 2])
        overlap_x[i] = -1
        assert not np.any((overlap_x > 0) & (overlap_y > 0))
    # e2v CCDs are 40.96 x 40.04 mm on a 42.25 mm pitch: gaps of 1.29 and 2.21 mm in a raft.
    a, b = fp.ccd("R22_S11").bounds_mm(), fp.ccd("R22_S12").bounds_mm()
    assert b[0] - a[1] == pytest.approx(1.29, abs=1e-9)


def test_distortion_at_the_science_corners():
    # The far corner of R01_S00 is the science area's farthest point; the radial polynomial
    # moves it by ~0.43 mm (~43 px) from where the boresight plate scale would put it.
    x, y = fp.ccd("R01_S00").pixel_to_focal(-0.5, -0.5)
    r = np.hypot(x, y)
    theta = np.hypot(*fp.field_angle(x, y)) * 206264.80624709636
    shift_mm = r - theta / fp.PLATE_SCALE_ARCSEC_PER_MM
    assert shift_mm == pytest.approx(0.43, abs=0.01)
    # The inverse recovers the position.
    np.testing.assert_allclose(fp.focal_of_field_angle(*fp.field_angle(x, y)), (x, y),
                               atol=1e-10)


def test_plate_scales_are_derivatives_of_the_field_angle():
    for x, y in ((0.0, 0.0), (120.0, -80.0), (-250.0, 230.0)):
        r = np.hypot(x, y)
        radial, tangential = fp.plate_scales(x, y)
        h = 1e-3

        def theta(rr):
            return np.hypot(*fp.field_angle(rr * x / max(r, 1), rr * y / max(r, 1)))

        if r > 0:
            numeric = (theta(r + h) - theta(r - h)) / (2 * h) * 206264.80624709636
            assert radial == pytest.approx(numeric, rel=1e-9)
            assert tangential == pytest.approx(theta(r) / r * 206264.80624709636, rel=1e-12)
        # Along the radius the pixel scale is the radial one, across it the tangential one.
        a = np.degrees(np.arctan2(y, x)) if r else 0.0
        assert fp.pixel_scale_along(x, y, a) == pytest.approx(radial * 0.01, rel=1e-12)
        if r:
            assert fp.pixel_scale_along(x, y, a + 90) == pytest.approx(tangential * 0.01,
                                                                       rel=1e-12)


def _gnomonic(xi, eta, ra0, dec0):
    """Standard inverse gnomonic projection (radians in, degrees out), written out."""
    d0 = np.radians(dec0)
    denom = np.cos(d0) - eta * np.sin(d0)
    ra = np.radians(ra0) + np.arctan2(xi, denom)
    dec = np.arctan2(np.sin(d0) + eta * np.cos(d0), np.hypot(xi, denom))
    return np.degrees(ra) % 360, np.degrees(dec)


@pytest.mark.parametrize("name", ["R22_S11", "R01_S00", "R43_S22", "R30_S02", "R14_S20"])
@pytest.mark.parametrize("rotation", [0.0, 35.0, -120.0])
def test_ccd_wcs_matches_an_independent_projection(name, rotation):
    c = fp.ccd(name)
    pointing = dict(POINTING, rotation=rotation)
    wcs = ccd_wcs(c, pointing)
    ny, nx = c.shape
    x, y = np.meshgrid(np.linspace(-0.5, nx - 0.5, 13), np.linspace(-0.5, ny - 0.5, 11))
    xm, ym = c.pixel_to_focal(x, y)
    # Independent: the distortion written out, the rotator turning +y to PA = rotation.
    r2 = xm ** 2 + ym ** 2
    k = 20.005867576692737 / 206264.80624709636 * (1 - 8.33713991e-9 * r2
                                                   - 1.41389858e-15 * r2 ** 2)
    ax, ay = xm * k, ym * k
    pa = np.radians(rotation)
    east = ax * -np.cos(pa) + ay * np.sin(pa)
    north = ax * np.sin(pa) + ay * np.cos(pa)
    ra_ref, dec_ref = _gnomonic(east, north, pointing["ra"], pointing["dec"])
    ra, dec = wcs.pixel_to_world_values(x, y)
    dra = ((ra - ra_ref + 180) % 360 - 180) * np.cos(np.radians(dec_ref))
    assert np.abs(dra).max() * 3600 < 1e-6
    assert np.abs(dec - dec_ref).max() * 3600 < 1e-6
    # The SIP inverse (AP, BP) alone, without astropy's iteration, is good to 1e-6 px.
    u = np.column_stack([x.ravel(), y.ravel()]) + 1
    foc = wcs.sip_pix2foc(u, 1)
    back = wcs.sip_foc2pix(foc, 1)
    assert np.abs(back - u).max() < 1e-6
    # The header keeps it all (relax=True keeps SIP).
    from astropy.wcs import WCS

    again = WCS(wcs.to_header(relax=True))
    np.testing.assert_allclose(again.pixel_to_world_values(x, y), (ra, dec), rtol=0,
                               atol=1e-10)


def test_rotation_convention_is_rotskypos():
    c = fp.ccd("R22_S11")
    for rotation, up_pa in ((0.0, 0.0), (90.0, 90.0), (30.0, 30.0)):
        wcs = ccd_wcs(c, dict(POINTING, rotation=rotation))
        from astropy.coordinates import SkyCoord

        x0, y0 = c.boresight_pixel
        a = SkyCoord(*wcs.pixel_to_world_values(x0, y0), unit="deg")
        b = SkyCoord(*wcs.pixel_to_world_values(x0, y0 + 100), unit="deg")
        w = SkyCoord(*wcs.pixel_to_world_values(x0 + 100, y0), unit="deg")
        assert a.position_angle(b).deg % 360 == pytest.approx(up_pa % 360, abs=1e-4)
        # +x is 90 deg clockwise of +y (west of north at rotation 0): no flip.
        assert a.position_angle(w).deg % 360 == pytest.approx((up_pa - 90) % 360, abs=1e-4)
        assert a.ra.deg == pytest.approx(POINTING["ra"]) and a.dec.deg == pytest.approx(-28)


def _dense_crossed(x0, y0, angle, length, margin_mm):
    """CCDs touched by points every 2 um along a segment (no clipping algebra)."""
    t = np.arange(0.0, length, 0.002)
    px = x0 + t * np.cos(np.radians(angle))
    py = y0 + t * np.sin(np.radians(angle))
    hits = set()
    for c in fp.CCDS:
        nx_mm, ny_mm = c.shape[1] * 0.01, c.shape[0] * 0.01
        lo_x = c.centre_mm[0] - (c.refpos[0] + 0.5) * 0.01 - margin_mm
        lo_y = c.centre_mm[1] - (c.refpos[1] + 0.5) * 0.01 - margin_mm
        inside = ((px >= lo_x) & (px <= lo_x + nx_mm + 2 * margin_mm)
                  & (py >= lo_y) & (py <= lo_y + ny_mm + 2 * margin_mm))
        if inside.any():
            hits.add(c.name)
    return hits


@pytest.mark.parametrize("case", range(6))
def test_ccds_a_line_crosses_match_dense_sampling(case):
    rng = np.random.default_rng(case)
    angle = rng.uniform(0, 360)
    x0, y0 = rng.uniform(-200, 200, 2)
    margin_px = [0.0, 40.0][case % 2]
    # A segment across the whole focal plane, from well outside it.
    a = np.radians(angle)
    start = (x0 - 500 * np.cos(a), y0 - 500 * np.sin(a))
    end = (x0 + 500 * np.cos(a), y0 + 500 * np.sin(a))
    got = {c.name for c in fp.ccds_reached([start[0], end[0]], [start[1], end[1]], margin_px)}
    expected = _dense_crossed(*start, angle, 1000.0, margin_px * 0.01)
    assert got == expected and len(got) >= 5
