"""scripts/check_truth.py: its geometry, ridge and file checks against numbers worked out by
hand (the script's full run is documented in docs/reference/file-formats.md)."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from scipy import integrate

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import check_truth as ct  # noqa: E402


def test_clipped_length_is_the_part_inside_the_pixel_area():
    # A row crossing a 100-wide image: edges at -0.5 and 99.5.
    assert ct.clipped_length(-100.0, 10.0, 200.0, 10.0, (50, 100)) == pytest.approx(100.0)
    # The diagonal of the pixel area: sqrt(100^2 + 50^2).
    assert ct.clipped_length(-0.5, -0.5, 99.5, 49.5, (50, 100)) == pytest.approx(111.80339887)
    # A segment that ends inside: its own length from the left edge, 40.5.
    assert ct.clipped_length(-20.0, 5.0, 40.0, 5.0, (50, 100)) == pytest.approx(40.5)
    assert ct.clipped_length(-20.0, 60.0, 200.0, 60.0, (50, 100)) == 0.0


def test_segment_distance_uses_the_ends_beyond_the_segment():
    d = ct.segment_distance([3.0, 13.0, -3.0], [4.0, 4.0, -4.0], 0.0, 0.0, 10.0, 0.0)
    np.testing.assert_allclose(d, [4.0, 5.0, 5.0])


def test_nearest_line_labels_split_at_the_midline():
    labels = ct.nearest_line_labels((50, 20), [(0, 10, 19, 10), (0, 40, 19, 40)], chunk=7)
    assert (labels[:25] == 0).all() and (labels[26:] == 1).all()


def test_nearest_line_labels_guard_the_crossing():
    # y = 10 and x = 50 cross at (50, 10): (52, 12) is 2 px from both, (90, 12) 2 and 40 px,
    # (52, 90) 80 and 2 px; with a 30 px guard only the first is left to neither.
    lines = [(-10.0, 10.0, 110.0, 10.0), (50.0, -10.0, 50.0, 110.0)]
    labels = ct.nearest_line_labels((100, 100), lines, guard=30.0)
    assert (labels[12, 52], labels[12, 90], labels[90, 52]) == (-1, 0, 1)


def test_nearest_on_path_to_a_box():
    box = (0.0, 100.0, 0.0, 100.0)
    assert ct.nearest_on_path([-10.0, -10.0], [5.0, 50.0], box)[0] == pytest.approx(10.0)
    assert ct.nearest_on_path([-10.0, 50.0], [50.0, 50.0], box)[0] == 0.0
    # Past the corner (0, 100) along a 45 deg line: |(-10) - (10)| / sqrt(2).
    d, k, t = ct.nearest_on_path([-30.0, -10.0, 10.0], [90.0, 110.0, 130.0], box)
    assert d == pytest.approx(20 / math.sqrt(2))
    xs, ys = [-30.0, -10.0, 10.0], [90.0, 110.0, 130.0]
    point = (xs[k] + t * (xs[k + 1] - xs[k]), ys[k] + t * (ys[k + 1] - ys[k]))
    assert point == pytest.approx((-10.0, 110.0))  # the foot of the perpendicular


def _gaussian_streak(shape, x0, y0, angle_deg, sigma, offsets=(0.0,)):
    """A streak whose cross-section is Gaussians at ``offsets`` across the line."""
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx].astype(float)
    a = math.radians(angle_deg)
    d = -(x - x0) * math.sin(a) + (y - y0) * math.cos(a)
    return sum(np.exp(-0.5 * ((d - o) / sigma) ** 2) for o in offsets)


@pytest.mark.parametrize("angle", [17.0, 80.0, 135.0])
def test_ridge_finds_the_line_and_a_shift_of_it(angle):
    model = _gaussian_streak((300, 300), 150.0, 150.0, angle, 2.0)
    a = math.radians(angle)
    reach = 400.0
    line = (150 - reach * math.cos(a), 150 - reach * math.sin(a),
            150 + reach * math.cos(a), 150 + reach * math.sin(a))
    found = ct.ridge(model, line)
    assert found["cuts"] > 200
    assert found["centroid_px"] < 0.01 and found["argmax_px"] < 0.05
    # The line moved 1.5 px across itself: the ridge is 1.5 px from it.
    n = (-math.sin(a), math.cos(a))
    moved = (line[0] + 1.5 * n[0], line[1] + 1.5 * n[1], line[2] + 1.5 * n[0],
             line[3] + 1.5 * n[1])
    assert ct.ridge(model, moved)["centroid_px"] == pytest.approx(1.5, abs=0.01)


def test_ridge_of_a_two_horned_cross_section_is_its_centre():
    # Two Gaussians 3 px either side of the line (a defocused ring): the maximum lies ~3 px
    # off, the centroid on the line.
    model = _gaussian_streak((200, 300), 150.0, 100.0, 10.0, 2.0, offsets=(-3.0, 3.0))
    a = math.radians(10.0)
    line = (150 - 400 * math.cos(a), 100 - 400 * math.sin(a),
            150 + 400 * math.cos(a), 100 + 400 * math.sin(a))
    found = ct.ridge(model, line)
    assert found["centroid_px"] < 0.01
    assert 2.5 < found["argmax_px"] < 3.1


def test_ridge_skips_the_end_caps_of_a_segment():
    # A 200 px segment at 30 deg from (60, 50): the along-track fall at its ends (an erf of
    # 3 px) pulls a slanted cut's centroid towards the inside; 20 px from each end it is gone.
    shape, angle, length = (200, 300), 30.0, 200.0
    a = math.radians(angle)
    y, x = np.mgrid[:shape[0], :shape[1]].astype(float)
    t = (x - 60.0) * math.cos(a) + (y - 50.0) * math.sin(a)
    from scipy.special import erf
    model = _gaussian_streak(shape, 60.0, 50.0, angle, 2.0) * 0.25 * (
        1 + erf(t / (3 * math.sqrt(2)))) * (1 - erf((t - length) / (3 * math.sqrt(2))))
    line = (60.0, 50.0, 60.0 + length * math.cos(a), 50.0 + length * math.sin(a))
    assert ct.ridge(model, line)["centroid_px"] > 0.1
    found = ct.ridge(model, line, skip_end_px=20.0)
    assert found["centroid_px"] < 0.01
    # The cuts left: columns whose point on the line is 20 px or more from both ends.
    assert found["cuts"] == pytest.approx((length - 40.0) * math.cos(a), abs=1.5)


def test_ridge_leaves_out_cuts_cut_by_the_image_edge():
    # The streak runs along the first rows: every cut's run touches the edge.
    model = _gaussian_streak((100, 100), 0.0, 1.0, 0.0, 2.0)
    assert ct.ridge(model, (-50.0, 1.0, 150.0, 1.0))["cuts"] == 0


def test_power_law_tail_integrates_the_lsf_beyond_the_table():
    d = np.linspace(0.0, 10.0, 1001)
    g = 1.0 / (1.0 + d ** 2) ** (4 / 3)  # ~ d^(-8/3) far out
    tail = np.cumsum(g[::-1])[::-1] * (d[1] - d[0]) + g[-1] * d[-1] * 0.6
    lsf = (d, g, tail)
    # Beyond the table: g(10) (10 / d)^(8/3), and its integral from d to infinity.
    assert ct._lsf_at(lsf, 20.0) == pytest.approx(g[-1] * 0.5 ** (8 / 3))
    exact, _ = integrate.quad(lambda x: g[-1] * (10.0 / x) ** (8 / 3), 20.0, np.inf)
    assert ct._tail_at(lsf, 20.0) == pytest.approx(exact, rel=1e-7)


#: A bent path across a 100 x 300 image: up 10 px from (-50, 40) to (150, 50), down again to
#: (350, 40); its chord, y = 40, is 10 px from its vertex.
BENT = ((-50.0, 40.0), (150.0, 50.0), (350.0, 40.0))


def _bent_streak(shape, sigma=2.0):
    """A streak whose cross-section is a Gaussian of the distance to :data:`BENT`."""
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx].astype(float)
    d = np.min([ct.segment_distance(x, y, *a, *b) for a, b in zip(BENT[:-1], BENT[1:])],
               axis=0)
    return np.exp(-0.5 * (d / sigma) ** 2)


def test_ridge_of_a_bent_streak_is_its_path_not_its_chord():
    found = ct.ridge(_bent_streak((100, 300)), BENT)
    assert found["cuts"] > 250
    assert found["centroid_px"] < 0.02
    # The chord runs 10 px below the vertex, measured across it (cos of the 2.86 deg slope
    # of the pieces does not enter: the column through the vertex is vertical).
    assert found["chord_px"] == pytest.approx(10.0, abs=0.02)


def test_truth_paths_take_the_vertices_of_each_row():
    rows = [{"x0": 0.0, "y0": 1.0, "x1": 4.0, "y1": 1.0}, {"x0": 5.0, "y0": 6.0, "x1": 7.0,
                                                          "y1": 8.0}]
    table = np.array([(0, 2, 4.0, 1.0), (0, 0, 0.0, 1.0), (0, 1, 2.0, 3.0)],
                     dtype=[("row", "i4"), ("vertex", "i4"), ("x", "f8"), ("y", "f8")])
    assert ct.truth_paths(rows, table) == [((0.0, 1.0), (2.0, 3.0), (4.0, 1.0)),
                                           ((5.0, 6.0), (7.0, 8.0))]
    assert ct.truth_paths(rows)[0] == ((0.0, 1.0), (4.0, 1.0))
    # Inside a 5 px wide image (x from -0.5 to 4.5) both pieces, sqrt(8) each; inside a 3 px
    # wide one the first and a quarter of the second (x from 2 to 2.5 of 2 to 4).
    path = ct.truth_paths(rows, table)[0]
    assert ct.path_length_inside(path, (10, 5)) == pytest.approx(2 * math.sqrt(8))
    assert ct.path_length_inside(path, (10, 3)) == pytest.approx(1.25 * math.sqrt(8))


def _write(path, model, rows, shape, vertices=None):
    columns = [fits.Column(name=k, format="D" if isinstance(v, float) else "J",
                           array=np.array([r[k] for r in rows]))
               for k, v in rows[0].items()]
    hdus = [fits.PrimaryHDU(), fits.ImageHDU(np.zeros(shape, np.float32), name="IMAGE"),
            fits.ImageHDU(model.astype(np.float32), name="STREAK_MODEL"),
            fits.BinTableHDU.from_columns(columns, name="TRUTH")]
    if vertices is not None:
        rows = [(i, k, x, y) for i, path in enumerate(vertices) for k, (x, y) in enumerate(path)]
        hdus.append(fits.BinTableHDU(np.array(rows, dtype=[
            ("row", "i4"), ("vertex", "i4"), ("x", "f8"), ("y", "f8")]), name="TRUTH_VERTICES"))
    fits.HDUList(hdus).writeto(path)


def test_check_file_measures_a_bent_streak_against_its_vertices(tmp_path):
    """The bent streak's row has its chord as x0..y1 and its path in TRUTH_VERTICES: the
    ridge is on the path, 10 px from the chord; the length inside the 300 px wide image is
    along the path, 300 / cos(atan(10 / 200))."""
    shape = (100, 300)
    model = _bent_streak(shape)
    row = {"satellite": 0, "x0": -50.0, "y0": 40.0, "x1": 350.0, "y1": 40.0,
           "flux_per_px_e": 1.0, "fwhm_arcsec": 0.94, "peak_e_per_px": 1.0,
           "pixel_scale_arcsec": 0.2, "charge_in_image_e": float(model.sum()), "n_vertices": 3}
    _write(tmp_path / "bent.fits", model, [row], shape, vertices=[BENT])
    rec = ct.check_file(tmp_path / "bent.fits", "s", "g", ["polyline"], "bent.fits")
    (s,) = rec["streaks"]
    assert rec["vertices"] and s["vertices"] == 3
    assert s["ridge_px"] < 0.02 and s["ridge_chord_px"] == pytest.approx(10.0, abs=0.02)
    assert s["length_in_px"] == pytest.approx(300.0 / math.cos(math.atan(0.05)))
    summary = ct.summarise([rec], [])
    assert summary["ridge_by_input"]["g s"]["chord_px"] == s["ridge_chord_px"]
    assert summary["ridge_by_input"]["g s"]["vertices_px"] == s["ridge_px"]
    assert not summary["ridge_failures"] and not summary["files_without_vertices"]


def test_check_file_against_a_streak_of_known_charge(tmp_path):
    # A row streak of 500 e- per pixel of track, each column's Gaussian normalised to it, over
    # 120 columns: 60000 e-. TRUTH says 1% more charge than the model holds.
    shape, flux = (60, 120), 500.0
    model = _gaussian_streak(shape, 0.0, 30.0, 0.0, 2.0)
    model *= flux / model.sum(axis=0)
    row = {"satellite": 0, "x0": -40.0, "y0": 30.0, "x1": 160.0, "y1": 30.0,
           "flux_per_px_e": flux, "flux_per_px_min_e": flux, "flux_per_px_max_e": flux,
           "fwhm_arcsec": 0.94, "peak_e_per_px": float(model.max()),
           "pixel_scale_arcsec": 0.2, "charge_in_image_e": 1.01 * 60000.0, "n_vertices": 2}
    _write(tmp_path / "a.fits", model, [row], shape)
    rec = ct.check_file(tmp_path / "a.fits", "s", "g", ["straight"], "a.fits")
    assert rec["rows"] == 1 and rec["error"] == ""
    assert rec["model_truth_rel"] == pytest.approx(1 / 1.01 - 1, rel=1e-6)
    s = rec["streaks"][0]
    assert s["length_in_px"] == pytest.approx(120.0)
    assert s["flux_length_rel"] == pytest.approx(0.0, abs=1e-6)
    assert s["ridge_px"] < 0.01 and s["in_range"] is True


def test_check_file_compares_crossing_streaks_together(tmp_path):
    # A row streak of 2000 e- per pixel of track at y = 60 across a 300-wide image (300 px of
    # track), crossed at 80 deg through (150, 100) by one of 50 e- per pixel (200 / sin 80 px
    # of track over the 200 rows): the pixels nearest each line also hold the other's core
    # near the crossing (the faint one's pixels peak at the bright one's core, 40 times its
    # own), but together the model holds 2000 x 300 + 50 x 200 / sin 80 e-.
    shape, steep = (200, 300), math.radians(80.0)
    bright = _gaussian_streak(shape, 0.0, 60.0, 0.0, 2.0)
    faint = _gaussian_streak(shape, 150.0, 100.0, 80.0, 2.0)
    model = 2000.0 * bright / bright.sum(axis=0) + \
        50.0 / math.sin(steep) * faint / faint.sum(axis=1)[:, None]
    far = 300.0
    rows = [{"satellite": 0, "x0": -40.0, "y0": 60.0, "x1": 340.0, "y1": 60.0,
             "flux_per_px_e": 2000.0, "charge_in_image_e": 600000.0},
            {"satellite": 1, "x0": 150.0 - far * math.cos(steep),
             "y0": 100.0 - far * math.sin(steep), "x1": 150.0 + far * math.cos(steep),
             "y1": 100.0 + far * math.sin(steep), "flux_per_px_e": 50.0,
             "charge_in_image_e": 10000.0 / math.sin(steep)}]
    for row in rows:
        row.update(fwhm_arcsec=0.94, peak_e_per_px=0.2 * row["flux_per_px_e"],
                   pixel_scale_arcsec=0.2, n_vertices=2)
    _write(tmp_path / "two.fits", model, rows, shape)
    rec = ct.check_file(tmp_path / "two.fits", "s", "g", [], "two.fits")
    assert rec["model_truth_rel"] == pytest.approx(0.0, abs=1e-6)
    assert rec["streaks"][1]["length_in_px"] == pytest.approx(200.0 / math.sin(steep))
    for s in rec["streaks"]:
        assert s["flux_length_rel"] == pytest.approx(0.0, abs=1e-6)
        assert s["ridge_px"] < 0.01 and s["cuts"] > 100


def test_check_file_records_what_is_missing(tmp_path):
    fits.HDUList([fits.PrimaryHDU(np.zeros((5, 5), np.float32))]).writeto(tmp_path / "p.fits")
    assert ct.check_file(tmp_path / "p.fits", "s", "g", [], "p")["error"] == "no TRUTH table"
    assert ct.check_file(tmp_path / "none.fits", "s", "g", [], "n")["error"] == "no file"


def test_schema_difference_names_missing_extra_and_formats():
    common = (("x0", "D"), ("flags", "J"), ("satellite", "J"))
    other = (("x0", "D"), ("flags", "K"), ("n_vertices", "K"))
    assert ct._schema_difference(common, other) == \
        "missing satellite; extra n_vertices; formats flags J->K"


def test_scene_kinds_and_ccd_scenes_of_the_samples():
    fields = ROOT / "sample_fields"
    assert ct.is_ccd_scene(ct.load_yaml(fields / "default.yaml"))
    assert not ct.is_ccd_scene(ct.load_yaml(fields / "focal_paper_550km.yaml"))
    assert not ct.is_ccd_scene(ct.load_yaml(fields / "constellation_550km.yaml"))
    passing = ct.load_yaml(fields / "pass_example.yaml")
    assert ct.is_ccd_scene(passing) and ct.satellite_kinds(passing) == ["orbit"]
    assert ct.satellite_kinds(ct.load_yaml(fields / "several_streaks.yaml")) == ["straight"] * 6
    assert not ct.is_ccd_scene({"detectors": ["R22_S11"], "satellites": []})


def test_the_checkout_imports_its_own_package(tmp_path):
    assert ct.Checkout(ROOT, tmp_path).package_dir() == ROOT / "inject"
