"""`inject simulate` for streak-only scenes: IMAGE, STREAK_MODEL and TRUTH from the renderer."""
import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

from inject import StreakModel
from inject.cli.main import main

SCENE = {
    "seed": 3, "band": "g", "zenith": 70, "detector": {"type": "itl", "nx": 400, "ny": 300},
    "sky": False, "stars": False, "noise": False,
    "satellites": [
        {"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
         "track": {"x0": 150.3, "y0": 140.7, "angle": 23.0, "length": 60.0}},
        {"height": 350, "shape": {"type": "disk", "radius": 1.0}, "mag": 6.0,
         "track": {"x0": 100, "y0": 40, "angle": -10.0}},
        {"height": 550, "shape": {"type": "disk", "radius": 1.0}, "mag": 6.0,
         "track": {"x0": -900, "y0": -900, "angle": 0.0, "length": 10}},
    ],
}


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(SCENE))
    return path


def test_streak_only_scene(scene_file, tmp_path):
    out = tmp_path / "out.fits"
    assert main(["simulate", str(scene_file), "-o", str(out)]) == 0
    with fits.open(out) as hdus:
        assert [h.name for h in hdus] == ["PRIMARY", "IMAGE", "MASK", "VARIANCE",
                                          "STREAK_MODEL", "TRUTH", "TRUTH_VERTICES"]
        image, model = hdus["IMAGE"].data, hdus["STREAK_MODEL"].data
        assert image.dtype.newbyteorder("=") == np.float32 and image.shape == (300, 400)
        np.testing.assert_array_equal(image, model)  # no sky, stars or noise: model alone
        assert hdus["IMAGE"].header["BUNIT"] == "electron"
        assert hdus["MASK"].header["MP_STREAK"] == 10  # afw default bits, STREAK next
        assert hdus[0].header["SEED"] == 3
        streak_bit = 1 << hdus["MASK"].header["MP_STREAK"]
        assert (hdus["MASK"].data & streak_bit).any()
    truth = Table.read(out, hdu="TRUTH")
    assert len(truth) == 3
    first = truth[0]
    expected = StreakModel(550, 70).flux_per_px * 60.0
    assert first["flags"] == 0
    assert first["charge_in_image_e"] == pytest.approx(expected, rel=1e-4)
    assert first["x1"] == pytest.approx(150.3 + 60 * np.cos(np.radians(23)))
    assert truth[1]["flags"] & 2  # crosses the image: its ends are outside
    assert truth[1]["x0"] < -0.5 and truth[1]["x1"] > 399.5
    assert truth[2]["flags"] & 1 and truth[2]["charge_in_image_e"] == 0  # misses the image
    for key in ("x0", "y0", "x1", "y1", "angle_deg", "height_km", "range_km", "nadir_angle_deg",
                "angular_speed_rad_s", "t_eff_s", "apparent_mag", "flux_per_px_e",
                "fwhm_arcsec", "peak_e_per_px", "flags"):
        assert key in truth.colnames


def test_existing_output_needs_overwrite(scene_file, tmp_path, capsys):
    out = tmp_path / "out.fits"
    out.write_text("precious")
    assert main(["simulate", str(scene_file), "-o", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_text() == "precious"
    assert main(["simulate", str(scene_file), "-o", str(out), "--overwrite"]) == 0
    assert fits.getdata(out, "IMAGE").shape == (300, 400)


def test_unwritable_directory(scene_file, tmp_path, capsys):
    out = tmp_path / "missing_dir" / "out.fits"
    assert main(["simulate", str(scene_file), "-o", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_override_on_command_line(scene_file, tmp_path):
    out = tmp_path / "out.fits"
    assert main(["simulate", str(scene_file), "-o", str(out), "satellites.0.mag=7.5",
                 "detector.nx=200"]) == 0
    truth = Table.read(out, hdu="TRUTH")
    assert fits.getdata(out, "IMAGE").shape == (300, 200)
    assert truth[0]["apparent_mag"] == pytest.approx(StreakModel(550, 70, mag=7.5).apparent_mag)


def test_polyline_track_in_a_scene(tmp_path):
    """A track through vertices that override height and magnitude along it."""
    scene = dict(SCENE)
    scene["detector"] = {"type": "itl", "nx": 700, "ny": 600}
    scene["satellites"] = [SCENE["satellites"][0] | {"track": {"vertices": [
        {"x": 250, "y": 200}, {"x": 350, "y": 260, "mag": 4.5},
        {"x": 450, "y": 280, "height": 450, "mag": 4.0}]}}]
    path = tmp_path / "poly.yaml"
    path.write_text(yaml.safe_dump(scene))
    out = tmp_path / "poly.fits"
    assert main(["simulate", str(path), "-o", str(out)]) == 0
    truth = Table.read(out, hdu="TRUTH")
    row = truth[0]
    assert row["n_vertices"] == 3 and row["flags"] == 0
    assert (row["x0"], row["y0"], row["x1"], row["y1"]) == (250, 200, 450, 280)
    f = [StreakModel(550, 70, mag=5.0).flux_per_px, StreakModel(550, 70, mag=4.5).flux_per_px,
         StreakModel(450, 70, mag=4.0).flux_per_px]
    lengths = [np.hypot(100, 60), np.hypot(100, 20)]
    expected = 0.5 * (f[0] + f[1]) * lengths[0] + 0.5 * (f[1] + f[2]) * lengths[1]
    assert row["charge_in_image_e"] == pytest.approx(expected, rel=1e-4)
    assert fits.getdata(out, "STREAK_MODEL").sum() == pytest.approx(expected, rel=1e-4)


def test_pointing_gives_a_celestial_wcs(tmp_path):
    from astropy.wcs import WCS

    scene = dict(SCENE) | {"pointing": {"ra": 150.0, "dec": -30.0, "rotation": 20.0}}
    path = tmp_path / "wcs.yaml"
    path.write_text(yaml.safe_dump(scene))
    out = tmp_path / "wcs.fits"
    assert main(["simulate", str(path), "-o", str(out)]) == 0
    wcs = WCS(fits.getheader(out, "IMAGE"))
    assert wcs.has_celestial
    ra, dec = wcs.pixel_to_world_values(199.5, 149.5)  # the centre of the 400 x 300 cut-out
    assert (float(ra), float(dec)) == pytest.approx((150.0, -30.0), abs=1e-9)
    scales = wcs.proj_plane_pixel_scales()
    assert [s.to_value("arcsec") for s in scales] == pytest.approx([0.2, 0.2], rel=1e-9)
