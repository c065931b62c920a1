"""The traced pupil in scenes (``pupil: rubin``): the kernel grid and its cache, the kernel's
orientation against the track, the light it keeps, CCD and focal-plane scenes, the command.

Independent numbers: exact traces at the asked range and field (for the grid), the traced
image's own second moments along and across the field radius (for the orientation), the
layout's field angle and the track's geometry (for the focal plane's field keys).
"""
import json
import os

import galsim
import numpy as np
import pytest
from astropy.io import fits

from inject import SceneError, make_plan, parse_focal_scene, parse_scene
from inject.camera import layout as fp
from inject.errors import InputError
from inject.io.fits import primary_header
from inject.optics import (
    BAND_WAVELENGTH_NM,
    GRID_RAYS,
    VANE_OFFSET_DEG,
    _grid_kernel,
    kernel,
    traced_kernel,
)
from inject.profile import Seeing
from inject.satellite import Disk
from inject.scene import streak_models
from inject.streak import StreakModel

pytest.importorskip("batoid")

SEEING = Seeing(0.67)
SAT = {"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}


def _fwhm_peak(k, track_angle):
    cs = k.cross_section(track_angle, SEEING, pixel_scale_arcsec=0.2)
    return np.array([cs.fwhm(), cs.peak()])


def test_grid_kernel_agrees_with_an_exact_trace_between_nodes():
    """612 km is 0.5% off its range node (scaled as 1/range), 0.83 deg between the nodes
    0.80 and 0.85 (mixed): FWHM and peak with seeing within 0.1% of a trace right there."""
    grid = kernel("g", 612.0, 0.83)
    exact = traced_kernel("g", 612.0, 0.83, VANE_OFFSET_DEG, n_rays=GRID_RAYS)
    assert grid.field_position_angle_deg == exact.field_position_angle_deg
    for across_radius in (0.0, 90.0):
        angle = VANE_OFFSET_DEG + across_radius
        np.testing.assert_allclose(_fwhm_peak(grid, angle), _fwhm_peak(exact, angle),
                                   rtol=1e-3)
    assert grid.outer_radius == pytest.approx(exact.outer_radius, rel=0.01)


def test_kernels_are_kept_on_disk_and_a_damaged_file_is_traced_again(tmp_path, monkeypatch):
    monkeypatch.setenv("INJECT_CACHE_DIR", str(tmp_path))
    _grid_kernel.cache_clear()
    first = kernel("r", 20000.0, 0.0)  # a node (field 0), far: a small, quick kernel
    files = [os.path.join(d, f) for d, _, names in os.walk(tmp_path) for f in names]
    assert len(files) == 1 and files[0].endswith(".npz")
    assert not any(os.path.basename(f).startswith(".tmp") for f in files)
    _grid_kernel.cache_clear()
    again = kernel("r", 20000.0, 0.0)
    np.testing.assert_allclose(again.image, first.image, rtol=1e-6)  # stored as float32
    assert again.transmitted == first.transmitted
    with open(files[0], "wb") as stream:
        stream.write(b"not a kernel")
    _grid_kernel.cache_clear()
    third = kernel("r", 20000.0, 0.0)
    np.testing.assert_allclose(third.image, first.image, rtol=1e-6)
    with np.load(files[0]) as data:  # rewritten
        assert data["image"].shape == first.image.shape
    _grid_kernel.cache_clear()


def test_an_empty_cache_dir_keeps_kernels_in_memory_only(tmp_path, monkeypatch):
    monkeypatch.setenv("INJECT_CACHE_DIR", "")
    monkeypatch.chdir(tmp_path)
    _grid_kernel.cache_clear()
    kernel("r", 20000.0, 0.0)
    assert not os.listdir(tmp_path)
    _grid_kernel.cache_clear()


@pytest.fixture(scope="module")
def off_axis():
    return kernel("g", 700.0, 1.5)


def _moments(k):
    """Centroid and variance of the traced image along and across the field radius."""
    n = k.image.shape[0]
    c = (np.arange(n) - n // 2) * k.scale
    x, y = np.meshgrid(c, c)
    pa = np.radians(k.field_position_angle_deg)
    radial = x * np.cos(pa) + y * np.sin(pa)
    tangential = -x * np.sin(pa) + y * np.cos(pa)
    w = k.image / k.image.sum()
    out = {}
    for name, u in (("radial", radial), ("tangential", tangential)):
        mean = float((w * u).sum())
        out[name] = (mean, float((w * (u - mean) ** 2).sum()))
    return out


def _lsf_moments(model):
    cs = model.lsf
    w = cs.lsf / cs.lsf.sum()
    mean = float((w * cs.offset_arcsec).sum())
    return mean, float((w * (cs.offset_arcsec - mean) ** 2).sum())


@pytest.mark.parametrize("position_angle, axis, sign", [
    (0.0, "tangential", 1), (90.0, "radial", 1), (-90.0, "radial", -1), (180.0, "tangential", -1)])
def test_the_cross_section_is_the_kernel_across_the_track(off_axis, position_angle, axis, sign):
    """A point source without seeing: the cross-section's centroid and variance are the
    traced image's along the direction across the track. ``field_position_angle_deg`` 90 puts
    the outward radius on the track frame's +y (the cross-section's positive offsets); 0
    makes the track run outward along the radius, so the cross-section is tangential."""
    model = StreakModel(700.0, 0.0, shape=Disk(0.01), seeing=Seeing(0.0), pupil="rubin",
                        field_angle_deg=1.5, field_position_angle_deg=position_angle,
                        range_km=700.0)
    mean, var = _lsf_moments(model)
    k_mean, k_var = _moments(off_axis)[axis]
    assert var == pytest.approx(k_var, rel=2e-3)
    assert mean == pytest.approx(sign * k_mean, abs=2e-4)
    if axis == "radial":  # off axis the kernel's centroid is off the star's along the radius
        assert abs(k_mean) > 1e-3


def _projected_fwhm(k, track_angle, seeing_fwhm, step=0.01):
    """FWHM across a track at ``track_angle`` deg from the kernel frame's +x, from the traced
    image itself: each pixel's light at its centre's offset across the track, histogrammed and
    convolved with the seeing's own projection (drawn by GalSim)."""
    n = k.image.shape[0]
    c = (np.arange(n) - n // 2) * k.scale
    x, y = np.meshgrid(c, c)
    a = np.radians(track_angle)
    across = -x * np.sin(a) + y * np.cos(a)
    m = 600
    edges = (np.arange(-m, m + 2) - 0.5) * step
    light, _ = np.histogram(across, edges, weights=k.image)
    seeing = galsim.Kolmogorov(fwhm=seeing_fwhm).drawImage(
        nx=2 * m + 1, ny=2 * m + 1, scale=step, method="no_pixel").array.sum(axis=1)
    lsf = np.convolve(light, seeing, mode="same")
    half = 0.5 * lsf.max()
    above = np.flatnonzero(lsf >= half)
    lo, hi = above[0], above[-1]
    left = lo - 1 + (half - lsf[lo - 1]) / (lsf[lo] - lsf[lo - 1])
    right = hi + (half - lsf[hi]) / (lsf[hi + 1] - lsf[hi])
    return (right - left) * step


@pytest.mark.parametrize("position_angle", [0.0, -90.0])
def test_the_cross_section_turns_the_kernel_to_the_track(off_axis, position_angle):
    """1.5 deg off axis, 0.67" seeing, the track along (0) and across (-90) the radius: the
    track runs at 22.5 and 112.5 deg in the kernel's frame. TracedKernel.cross_section and the
    renderer's profile (StreakModel) against the image projected here; turned the wrong way
    (the track at -22.5 or -112.5) the FWHM is 0.75% narrower or 3.5% wider."""
    track = off_axis.field_position_angle_deg - position_angle
    expected = _projected_fwhm(off_axis, track, 0.67)
    assert off_axis.cross_section(track, SEEING).fwhm() == pytest.approx(expected, rel=2e-3)
    model = StreakModel(700.0, 0.0, shape=Disk(0.01), seeing=SEEING, pupil="rubin",
                        field_angle_deg=1.5, field_position_angle_deg=position_angle,
                        range_km=700.0)
    assert model.fwhm_arcsec == pytest.approx(expected, rel=2e-3)
    # The test can tell: the mirrored track is more than twice the tolerance away.
    assert abs(_projected_fwhm(off_axis, -track, 0.67) / expected - 1) > 5e-3


def test_along_and_across_the_radius_differ_off_axis_not_on_axis():
    kw = dict(height_km=550, zenith_deg=70, seeing=SEEING, pupil="rubin")
    along = StreakModel(field_angle_deg=1.5, field_position_angle_deg=0, **kw).fwhm_arcsec
    across = StreakModel(field_angle_deg=1.5, field_position_angle_deg=90, **kw).fwhm_arcsec
    assert abs(across / along - 1) > 0.02  # the stretched, lopsided donut
    a0 = StreakModel(field_angle_deg=0, field_position_angle_deg=0, **kw).fwhm_arcsec
    a90 = StreakModel(field_angle_deg=0, field_position_angle_deg=90, **kw).fwhm_arcsec
    assert a90 == pytest.approx(a0, rel=2e-3)  # only the vanes break the symmetry


def test_the_light_kept_relative_to_a_star_scales_the_charge(off_axis):
    kw = dict(height_km=550, zenith_deg=70, range_km=700.0, seeing=SEEING)
    annulus = StreakModel(**kw)
    rubin = StreakModel(pupil="rubin", field_angle_deg=1.5, **kw)
    assert rubin.pupil_transmission == off_axis.transmitted
    assert rubin.flux_per_px / annulus.flux_per_px == pytest.approx(off_axis.transmitted,
                                                                     rel=1e-12)
    assert annulus.pupil_transmission == 1.0
    assert annulus.profile_key == StreakModel(**kw, field_angle_deg=1.0).profile_key


@pytest.mark.parametrize("kwargs, match", [
    ({"pupil": "ideal"}, "pupil"), ({"pupil": "rubin", "field_angle_deg": 2.5}, "field_angle"),
    ({"pupil": "rubin", "field_angle_deg": float("nan")}, "field_angle"),
    ({"pupil": "rubin", "field_position_angle_deg": float("inf")}, "field_position_angle")])
def test_bad_pupil_values_are_input_errors(kwargs, match):
    with pytest.raises(InputError, match=match):
        StreakModel(550, **kwargs)


def _ccd_scene(**keys):
    raw = {"seed": 2, "band": "r", "zenith": 70, "sky": False, "stars": False, "noise": False,
           "detector": {"type": "itl", "nx": 500, "ny": 240}, "pupil": "rubin",
           "satellites": [dict(SAT, track={"x0": 20, "y0": 100, "angle": 10})]}
    raw.update(keys)
    return raw


def test_a_ccd_scene_with_the_traced_pupil(tmp_path, cli):
    path = tmp_path / "scene.yaml"
    import yaml

    path.write_text(yaml.safe_dump(_ccd_scene(field={"angle": 1.2, "position_angle": 40})))
    out = tmp_path / "out.fits"
    status, _, err = cli("simulate", path, "-o", out)
    assert status == 0, err
    with fits.open(out) as hdul:
        assert hdul[0].header["PUPIL"] == "rubin"
        row = hdul["TRUTH"].data[0]
        total = float(hdul["STREAK_MODEL"].data.sum(dtype=float))
    assert row["field_angle_deg"] == 1.2
    assert row["field_position_angle_deg"] == 30.0  # 40 on the image, the track at 10
    model = StreakModel(550, 70, band_name="r", pupil="rubin", field_angle_deg=1.2,
                        field_position_angle_deg=30.0)
    assert row["fwhm_arcsec"] == pytest.approx(model.fwhm_arcsec, rel=1e-9)
    assert row["flux_per_px_e"] == pytest.approx(model.flux_per_px, rel=1e-9)
    assert total == pytest.approx(row["charge_in_image_e"], rel=1e-5)


@pytest.mark.parametrize("keys, match", [
    ({"pupil": "ideal"}, "pupil='ideal'"), ({"field": {"angle": 3}}, r"field\.angle=3"),
    ({"field": {"position_angle": 3}}, "angle"), ({"field": {"angle": 1, "pa": 3}}, "pa"),
    ({"pupil": "annulus", "focus_offset_um": 5}, "focus_offset_um=5.*pupil: rubin"),
    ({"focus_offset_um": 2000}, r"focus_offset_um=2000.*\[-1000, 1000\]"),
    ({"focus_offset_um": "near"}, "focus_offset_um")])
def test_bad_pupil_keys_name_the_value(keys, match):
    with pytest.raises(SceneError, match=match):
        parse_scene(_ccd_scene(**keys))


def test_the_focus_offset_reaches_each_streak_of_a_ccd_scene():
    scene = parse_scene(_ccd_scene(focus_offset_um=-5))
    assert scene.focus_offset_um == -5.0
    [model] = streak_models(scene)
    assert model.focus_offset_um == -5.0 and model.summary()["focus_offset_um"] == -5.0
    assert primary_header(scene)["FOCUSDZ"] == -5.0
    assert parse_scene(_ccd_scene()).focus_offset_um == 0.0
    assert model.profile_key != streak_models(parse_scene(_ccd_scene()))[0].profile_key


def _focal(track):
    return parse_focal_scene({
        "seed": 5, "band": "g", "zenith": 70, "pointing": {"ra": 50, "dec": -30},
        "sky": False, "stars": False, "noise": False, "pupil": "rubin",
        "satellites": [dict(SAT, track=track)]})


def _wrapped(angle):
    return (angle + 180) % 360 - 180


@pytest.mark.parametrize("track", [
    {"x0_mm": 60.0, "y0_mm": 20.0, "angle": 18.4349488, "length_mm": 200.0},  # outward
    {"x0_mm": 150.0, "y0_mm": -100.0, "angle": 90.0, "length_mm": 200.0}])
def test_focal_plane_ccds_take_the_field_at_their_part_of_the_track(track):
    """On each CCD, ``field_angle`` is the layout's at the middle of the track's part, and
    ``field_pa`` the angle from the track's direction to the radius there (in size: the CCD's
    pixel axes may mirror the focal plane's, which turns the angle's sign): 0 for the track
    pointing away from the axis, growing along x = 150 mm as the radius turns."""
    fscene = _focal(track)
    plan = make_plan(fscene)
    ccds = plan.streak_ccds()
    assert len(ccds) >= 3
    for ccd in ccds:
        for s in plan.streaks(ccd):
            values = s.values[0]
            x0, y0, x1, y1 = s.ends
            (xa, xb), (ya, yb) = ccd.pixel_to_focal(np.array([x0, x1]), np.array([y0, y1]))
            xm, ym = (xa + xb) / 2, (ya + yb) / 2
            assert values["field_angle"] == pytest.approx(
                np.degrees(np.hypot(*fp.field_angle(xm, ym))), abs=0.01)
            expected = _wrapped(np.degrees(np.arctan2(ym, xm)) - track["angle"])
            assert abs(_wrapped(values["field_pa"])) == pytest.approx(abs(expected), abs=0.3)
            assert all(v["field_angle"] == values["field_angle"] for v in s.values)


def test_inject_profile_with_the_traced_pupil(cli):
    status, out, err = cli("profile", "--height", "550", "--zenith", "70", "--pupil", "rubin",
                           "--field-angle", "1.25", "--field-position-angle", "90", "--json")
    assert status == 0, err
    result = json.loads(out)
    assert result["pupil"] == "rubin" and result["field_angle_deg"] == 1.25
    model = StreakModel(550, 70, pupil="rubin", field_angle_deg=1.25,
                        field_position_angle_deg=90)
    assert result["fwhm_arcsec"] == pytest.approx(model.fwhm_arcsec, rel=1e-12)
    status, _, err = cli("profile", "--height", "550", "--field-angle", "1", strict=True)
    assert status == 2 and "--pupil rubin" in err
    status, _, err = cli("profile", "--height", "550", "--pupil", "rubin", "--field-angle", "3",
                         strict=True)
    assert status == 2 and "--field-angle=3" in err


@pytest.mark.parametrize("band", ["u", "g", "r", "i", "z", "y"])
def test_every_band_has_its_camera_and_a_kernel_near_the_annulus(band):
    """Each band's filter and camera trace: on axis at 800 km the kernel's hole is wider and
    its outside narrower than the annulus's, by the telescope's aberrations (g: +0.13" and
    -0.06"; u, whose in-focus spot is 0.09" rms against 0.05-0.06" in the others: +0.24" and
    -0.11"), and the point keeps a star's light. At the band's effective wavelength: over the
    band the focus's colour blurs the edges."""
    k = traced_kernel(band, 800.0, 0.0, n_rays=100_000, wavelength_nm=BAND_WAVELENGTH_NM[band])
    inner = 2.558 / 800e3 * 206264.806
    outer = 4.18 / 800e3 * 206264.806
    assert inner + 0.05 < k.inner_radius < inner + 0.3
    assert outer - 0.15 < k.outer_radius < outer - 0.02
    assert k.transmitted == pytest.approx(1.0, abs=2e-3)


def test_a_polyline_takes_the_field_at_each_vertex():
    """Per vertex of a bending track: the layout's field angle at the vertex's place, and the
    radius's direction from the direction of the piece that starts there."""
    fscene = _focal({"vertices": [{"x_mm": -150.0, "y_mm": -60.0}, {"x_mm": 10.0, "y_mm": 5.0},
                                  {"x_mm": 150.0, "y_mm": 120.0}]})
    plan = make_plan(fscene)
    checked = 0
    for ccd in plan.streak_ccds():
        for s in plan.streaks(ccd):
            vertices = s.track.vertices
            xs = np.array([v["x"] for v in vertices])
            ys = np.array([v["y"] for v in vertices])
            xm, ym = ccd.pixel_to_focal(xs, ys)
            for k, v in enumerate(vertices):
                assert v["field_angle"] == pytest.approx(
                    np.degrees(np.hypot(*fp.field_angle(xm[k], ym[k]))), abs=1e-6)
                j = min(k, len(xs) - 2)
                heading = np.degrees(np.arctan2(ym[j + 1] - ym[j], xm[j + 1] - xm[j]))
                expected = _wrapped(np.degrees(np.arctan2(ym[k], xm[k])) - heading)
                assert abs(_wrapped(v["field_pa"])) == pytest.approx(abs(expected), abs=0.3)
                checked += 1
    assert checked >= 6
