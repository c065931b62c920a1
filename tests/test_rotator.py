"""The camera rotator turns the focal plane against the spider vanes of the traced pupil."""
import functools

import galsim
import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from test_pupil import SAT
from test_pupil import _ccd_scene as _pupil_scene

from inject import SceneError, parse_scene
from inject.errors import InputError
from inject.io.fits import primary_header
from inject.optics import telescope_position_angle, traced_kernel, vane_node
from inject.profile import Seeing
from inject.scene import streak_models
from inject.streak import StreakModel
from inject.survey.visits import read_visits

pytest.importorskip("batoid")

SEEING = Seeing(0.67)


def _ccd_scene(**keys):
    """test_pupil's CCD scene, in g at the zenith."""
    return _pupil_scene(**{"band": "g", "zenith": 0, **keys})


def test_the_telescope_position_angle_is_the_radius_minus_the_rotator_modulo_90():
    # By hand: 100 - 30 = 70; 5 + 10 = 15; 200 - 250 = -50 -> 40; 10 - 20 = -10 -> 80.
    assert telescope_position_angle(30, 100) == pytest.approx(70.0)
    assert telescope_position_angle(-10, 5) == pytest.approx(15.0)
    assert telescope_position_angle(250, 200) == pytest.approx(40.0)
    assert telescope_position_angle(20, 10) == pytest.approx(80.0)
    assert [vane_node(a) for a in (42.4, 42.6, 87.6, 2.4)] == [40.0, 45.0, 0.0, 0.0]


def test_the_rotator_reaches_each_streak_of_a_ccd_scene():
    scene = parse_scene(_ccd_scene(rotator_deg=30, field={"angle": 1.5, "position_angle": 100}))
    assert scene.rotator_deg == 30.0
    [model] = streak_models(scene)
    assert model.telescope_position_angle_deg == pytest.approx(70.0)
    [plain] = streak_models(parse_scene(_ccd_scene(field={"angle": 1.5, "position_angle": 100})))
    assert plain.telescope_position_angle_deg is None
    assert model.profile_key != plain.profile_key
    assert primary_header(scene)["ROTTELPOS"] == 30.0
    assert "ROTTELPOS" not in primary_header(parse_scene(_ccd_scene()))


def test_the_rotator_reaches_each_streak_of_a_focal_plane_scene():
    from inject import make_plan, parse_focal_scene
    from inject.exposure.plan import vertex_model

    fscene = parse_focal_scene({
        "seed": 5, "band": "g", "zenith": 70, "pointing": {"ra": 50, "dec": -30},
        "sky": False, "stars": False, "noise": False, "pupil": "rubin", "rotator_deg": 12,
        "satellites": [dict(SAT, track={"x0_mm": 60.0, "y0_mm": 20.0, "angle": 90.0,
                                        "length_mm": 100.0})]})
    plan = make_plan(fscene)
    [ccd, *_] = plan.streak_ccds()
    [s] = plan.streaks(ccd)
    values = s.values[0]
    x0, y0, x1, y1 = s.ends
    (xa, xb), (ya, yb) = ccd.pixel_to_focal(np.array([x0, x1]), np.array([y0, y1]))
    radius = np.degrees(np.arctan2((ya + yb) / 2, (xa + xb) / 2))
    assert values["field_radius"] == pytest.approx(radius, abs=0.01)
    model = vertex_model(fscene, 0, values)
    assert model.telescope_position_angle_deg == pytest.approx((radius - 12) % 90, abs=0.01)


def test_rotTelPos_is_read_when_present(tmp_path):
    head = "observationId,observationStartMJD,fieldRA,fieldDec,rotSkyPos,band,visitExposureTime"
    row = "7,61000.1,10,-30,20,r,30"
    (tmp_path / "a.csv").write_text(f"{head},rotTelPos\n{row},-33.5\n")
    (tmp_path / "b.csv").write_text(f"{head}\n{row}\n")
    assert read_visits(str(tmp_path / "a.csv"))[0].rotator_deg == -33.5
    assert read_visits(str(tmp_path / "b.csv"))[0].rotator_deg is None


def test_rotTelPos_comes_from_paraAngle_when_it_is_missing(tmp_path):
    head = "observationId,observationStartMJD,fieldRA,fieldDec,rotSkyPos,band,visitExposureTime"
    (tmp_path / "a.csv").write_text(f"{head},paraAngle\n7,61000.1,10,-30,20,r,30,35\n"
                                    f"8,61000.1,10,-30,300,r,30,-170\n")
    (tmp_path / "b.csv").write_text(f"{head},rotTelPos,paraAngle\n7,61000.1,10,-30,20,r,30,5,35\n")
    # By hand: rotTelPos = paraAngle - rotSkyPos - 90: 35 - 20 - 90 = -75; -170 - 300 - 90 =
    # -560 -> 160 (wrapped to [-180, 180)).
    first, second = read_visits(str(tmp_path / "a.csv"))
    assert (first.rotator_deg, first.rotator_source) == (pytest.approx(-75.0), "paraAngle")
    assert second.rotator_deg == pytest.approx(160.0)
    [given] = read_visits(str(tmp_path / "b.csv"))
    assert (given.rotator_deg, given.rotator_source) == (5.0, "rotTelPos")


def test_rotTelPos_computed_from_the_parallactic_angle_is_lssts_worked_example():
    """LSST's note on its rotation angles works an example: HD116244 (13:25:05.13
    -74:53:32.5, ICRS) from Rubin at MJD 61975.91735 and 61976.03248 (TAI), where rotTelPos 0
    gives rotSkyPos -90.2069 and -40.9595 deg (its pseudo parallactic angle, from the ICRS
    pole, -0.2069 and 49.0405 deg). Back from those rotSkyPos, inject finds rotTelPos 0."""
    from inject.orbits.passes import Site
    from inject.survey.visits import Visit, with_rotators

    site = Site(lat_deg=-30.2444, lon_deg=-70.7494, height_m=2650.0)
    ra, dec = 15 * (13 + 25 / 60 + 5.13 / 3600), -(74 + 53 / 60 + 32.5 / 3600)
    visits = [Visit(1, 61975.91735, ra, dec, -90.2069, "r", 30.0),
              Visit(2, 61976.03248, ra, dec, -40.9595, "r", 30.0),
              Visit(3, 61976.03248, ra, dec, 0.0, "r", 30.0, rotator_deg=12.0,
                    rotator_source="rotTelPos")]
    with pytest.warns(Warning, match="IERS"):  # 2028: beyond the bundled Earth orientation
        first, second, given = with_rotators(visits, site)
    assert first.rotator_deg == pytest.approx(0.0, abs=0.01)
    assert second.rotator_deg == pytest.approx(0.0, abs=0.01)
    assert first.rotator_source == second.rotator_source == "computed"
    assert given is visits[2]


def test_the_rotator_is_refused_without_the_traced_pupil():
    with pytest.raises(SceneError, match=r"rotator_deg=10\.0: only with pupil: rubin"):
        parse_scene(_ccd_scene(pupil="annulus", rotator_deg=10))
    with pytest.raises(SceneError, match="rotator_deg"):
        parse_scene(_ccd_scene(rotator_deg="north"))
    with pytest.raises(InputError, match="telescope_position_angle_deg"):
        StreakModel(550, telescope_position_angle_deg=10.0)


def _fwhm_across(kernel, along_radius):
    """FWHM with seeing of a track along the field radius (``along_radius``) or across it."""
    track = kernel.field_position_angle_deg + (0.0 if along_radius else 90.0)
    return kernel.cross_section(track, SEEING, pixel_scale_arcsec=0.2).fwhm()


@pytest.mark.parametrize("along_radius", [True, False])
def test_rotators_45_deg_apart_change_the_fwhm_as_a_trace_does_and_90_apart_do_not(
        cheap_grid, along_radius):
    """At 1.5 deg, the radius at 0 deg on the image: rotators 0 and 45 put it along a vane's
    diagonal and 45 deg from it, 1% apart in FWHM; an independent trace at the exact angles
    agrees, and a rotator 90 deg on gives the rotator 0's kernel (the vanes' 4-fold symmetry,
    which the trace at 90 deg confirms to its ray noise)."""
    fwhm = {}
    for rotator in (0, 45, 90):
        scene = parse_scene(_ccd_scene(rotator_deg=rotator,
                                       field={"angle": 1.5, "position_angle": 0}))
        [model] = streak_models(scene)
        fwhm[rotator] = _fwhm_across(model.traced_kernel, along_radius)
    trace = {pa: _fwhm_across(traced_kernel("g", 550.0, 1.5, pa, n_rays=40_000,
                                            n_wavelengths=2), along_radius)
             for pa in (0.0, 45.0, 90.0)}
    assert fwhm[0] == pytest.approx(trace[0.0], rel=2e-3)
    assert fwhm[45] == pytest.approx(trace[45.0], rel=2e-3)
    assert abs(fwhm[0] / fwhm[45] - 1) > 3e-3
    assert fwhm[0] / fwhm[45] - 1 == pytest.approx(trace[0.0] / trace[45.0] - 1, abs=1.5e-3)
    assert fwhm[90] == fwhm[0]
    assert trace[90.0] == pytest.approx(trace[0.0], rel=2e-3)


def test_models_whose_angles_share_a_node_share_a_profile():
    kw = dict(height_km=550, pupil="rubin", field_angle_deg=1.5)
    assert (StreakModel(**kw, telescope_position_angle_deg=41.0).profile_key
            == StreakModel(**kw, telescope_position_angle_deg=39.0).profile_key)
    assert (StreakModel(**kw, telescope_position_angle_deg=41.0).profile_key
            != StreakModel(**kw, telescope_position_angle_deg=46.0).profile_key)


def test_a_survey_streak_takes_its_visits_rotator():
    from inject.survey.plan import _field

    # A sample at (-100, 100) mm: its radius at 135 deg on the focal plane; with rotTelPos 30
    # its kernel is the one traced at 135 - 30 = 105 deg, 15 modulo the vanes' 90.
    xd, yd = np.array([-100.0, -90.0]), np.array([100.0, 100.0])
    field = _field(xd, yd, [0, 1], 0, rotator_deg=30.0)
    assert field["telescope_position_angle_deg"] == pytest.approx(15.0)
    assert "telescope_position_angle_deg" not in _field(xd, yd, [0, 1], 0)


def _folded_azimuths(x, y, weights):
    """The light's azimuth about its centroid, 0.5 deg bins folded modulo 90 (the four
    vanes' shadows fall on one another), normalised to a unit mean."""
    cx, cy = np.average(x, weights=weights), np.average(y, weights=weights)
    azimuth = np.degrees(np.arctan2(y - cy, x - cx)) % 90.0
    counts, _ = np.histogram(azimuth, bins=180, range=(0.0, 90.0), weights=weights)
    return counts / counts.mean()


def _turn_between(a, b):
    """The turn (deg, in (-45, 45]) that best lays folded azimuths ``b`` on ``a``."""
    shifts = np.arange(180)
    score = [np.dot(a - 1, np.roll(b, k) - 1) for k in shifts]
    turn = 0.5 * shifts[int(np.argmax(score))]
    return turn - 90.0 if turn > 45.0 else turn


def _ring_from_batoid(rotator_deg, range_km=1000.0, n=1_000_000):
    """A point on the axis ``range_km`` away, traced by batoid directly through its baffled
    model (the spider vanes) with the camera turned as LSST's simulators turn it for the
    rotator (RotZ(rotTelPos) in the telescope's frame): where its rays land in the camera's
    frame (CCS), transposed to obs_lsst's focal plane (DVCS)."""
    import batoid

    telescope = batoid.Optic.fromYaml("LSST_r_baffles.yaml").withLocallyRotatedOptic(
        "LSSTCamera", batoid.RotZ(np.radians(rotator_deg)))
    # Random points over the pupil: a square grid's own azimuths would fold onto the vanes'.
    x, y = np.random.default_rng(3).uniform(-0.5, 0.5, (2, n)) * telescope.pupilSize
    z = np.full_like(x, telescope.stopSurface.coordSys.origin[2])
    # From a point range_km above the stop on the axis; light travels down (-z).
    u = np.vstack([x, y, z - (z[0] + range_km * 1e3)])
    u /= np.sqrt((u * u).sum(axis=0))
    back = telescope.backDist
    index = telescope.inMedium.getN(620e-9)
    rays = batoid.RayVector(x - back * u[0], y - back * u[1], z - back * u[2],
                            u[0] / index, u[1] / index, u[2] / index, wavelength=620e-9)
    out = telescope.trace(rays)  # in the detector's frame, which turns with the camera: CCS
    ok = ~(out.vignetted | out.failed)
    return out.y[ok], out.x[ok], np.ones(ok.sum())  # DVCS is CCS transposed


@functools.cache  # the unturned camera's ring is every case's reference: traced once
def _batoid_azimuths(rotator_deg):
    """:func:`_folded_azimuths` of :func:`_ring_from_batoid`, read-only."""
    folded = _folded_azimuths(*_ring_from_batoid(rotator_deg))
    folded.flags.writeable = False
    return folded


@pytest.mark.parametrize("rotator", [20.0, -35.0])
def test_the_vanes_shadows_fall_where_a_camera_turned_by_the_rotator_sees_them(
        cheap_grid, rotator):
    """LSST's definitions, not inject's code: the camera turns by RotZ(rotTelPos) in batoid's
    telescope frame (CCS against OCS) and obs_lsst's focal plane is the camera frame
    transposed. A point on the axis makes a ring whose vanes' shadows show the rotator; the
    shadows of inject's kernel on a CCD scene's image fall where batoid's do, and 2 x
    rotTelPos from where the old convention (radius plus rotator) put them."""
    truth = _batoid_azimuths(rotator)
    at_zero = _batoid_azimuths(0.0)
    assert _turn_between(truth, at_zero) == pytest.approx(rotator, abs=1.0)
    # inject: a CCD scene on the axis (its radius along the image's +x), its track at 30 deg;
    # the model's kernel turned from the track frame to the image's.
    scene = parse_scene(_ccd_scene(band="r", rotator_deg=rotator,
                                   field={"angle": 0.0, "position_angle": 0}))
    [model] = streak_models(scene)
    profile = model.defocus_profile.rotate(scene.satellites[0].track.angle * galsim.degrees)
    scale = 0.004
    image = profile.drawImage(nx=601, ny=601, scale=scale, method="no_pixel").array
    # Read on a polar grid (a square grid's pixels would weigh the azimuths unevenly): light
    # per 0.5 deg of azimuth, the radii weighted as the area they stand for.
    r, phi = np.meshgrid(np.arange(0.05, 1.2, 0.002), np.radians(np.arange(0.25, 360, 0.5)))
    light = map_coordinates(image, [300 + r * np.sin(phi) / scale, 300 + r * np.cos(phi) / scale],
                            order=1) * r
    found = light.sum(axis=1).reshape(4, 180).sum(axis=0)
    assert _turn_between(truth, found / found.mean()) == pytest.approx(0.0, abs=1.5)
