"""A cut-out (pixels [0, ny) x [0, nx) of a sensor) is the larger image's corner byte for
byte, noise included: every random number is drawn for a fixed block of the whole sensor.

The relation holds between any cut-out and any larger one (the whole CCD is the largest).
The one exception is saturation: charge bleeds along a column and stops at the image's top
edge, so a bleed trail crossing the cut-out's top row differs there; it is tested as a rule.
"""
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

import inject.scene as scene_module
from inject import DEFAULT_SCENE, apply_overrides, parse_scene, simulate
from inject.camera.detector import ITL, add_cosmic_rays
from inject.maskplanes import MASK_PLANES
from inject.scene import AmplifierNoise, poisson_inverse

PLANES = ("image", "variance", "mask", "streak_model")
SAT = 1 << MASK_PLANES["SAT"]


def _scene(*overrides):
    return parse_scene(apply_overrides(DEFAULT_SCENE, list(overrides)))


def _assert_corner(large, small, planes=PLANES):
    ny, nx = small.image.shape
    for name in planes:
        a, b = getattr(large, name)[:ny, :nx], getattr(small, name)
        if name == "streak_model":  # written as float32 (a CCD without a streak has zeros)
            a, b = a.astype(np.float32), b.astype(np.float32)
        assert a.dtype == b.dtype, name
        assert a.tobytes() == b.tobytes(), (name, int(np.count_nonzero(a != b)))


# --- the draws themselves -------------------------------------------------------------------

@pytest.mark.parametrize("mean", [1e-4, 0.02, 0.3, 3.7, 9.99, 10.0, 52.5, 1e3, 2.5e5, 3e6])
def test_poisson_inverse_is_the_inverse_cdf(mean):
    """Each draw is the plain inversion of its uniform through scipy's Poisson CDF (smallest
    k with CDF(k) > u): exactly Poisson(mean), whichever branch draws it."""
    u = np.random.default_rng(7).random(100_000)
    k = poisson_inverse(u, np.full(u.size, mean))
    kmax = int(mean + 40 * np.sqrt(mean) + 40)
    cdf = stats.poisson.cdf(np.arange(kmax + 1), mean)
    np.testing.assert_array_equal(k, np.searchsorted(cdf, u, side="right"))
    assert abs(k.mean() - mean) < 5 * np.sqrt(mean / k.size)


@pytest.mark.parametrize("shift", [-3.0, 2.5])
def test_poisson_inverse_search_ends_at_the_inverse_whatever_its_start(monkeypatch, shift):
    """The search from the normal approximation steps up and down to the inverse: started
    a few sigma off, it still lands on scipy's inversion."""
    import scipy.special

    ndtri = scipy.special.ndtri
    monkeypatch.setattr(scipy.special, "ndtri", lambda u: ndtri(u) + shift)
    u = np.random.default_rng(8).random(20_000)
    for mean in (10.0, 52.5, 4e4):
        k = poisson_inverse(u, np.full(u.size, mean))
        kmax = int(mean + 40 * np.sqrt(mean) + 40)
        cdf = stats.poisson.cdf(np.arange(kmax + 1), mean)
        np.testing.assert_array_equal(k, np.searchsorted(cdf, u, side="right"))


def test_poisson_inverse_mixes_means_element_by_element():
    gen = np.random.default_rng(3)
    mean = np.concatenate([np.zeros(50), gen.exponential(0.05, 400), gen.uniform(1, 9.9, 300),
                           gen.uniform(10, 1e4, 300), [-1e-6, 5e5]])
    order = gen.permutation(mean.size)
    u = gen.random(mean.size)
    k = poisson_inverse(u[order], mean[order])
    alone = [poisson_inverse(u[i:i + 1], mean[i:i + 1])[0] for i in order]
    np.testing.assert_array_equal(k, alone)
    assert not k[mean[order] <= 0].any()


#: A small sensor: 2 x 8 amplifiers of 64 x 50 pixels, each with its own read noise.
DET = replace(ITL, nx=8 * 64, ny=2 * 50, amp_nx=64, amp_ny=50,
              amp_read_noise=tuple(3.0 + 0.5 * k for k in range(16)))


def _varying(shape, seed=2):
    """Streak-like and star-like expected charge: wings of 1e-3 e-, cores of 1e4 e-, dips."""
    y, x = np.mgrid[:shape[0], :shape[1]]
    gen = np.random.default_rng(seed)
    varying = 2e4 * np.exp(-0.5 * ((y - 0.15 * x - 20) / 3.0) ** 2)
    for cx, cy in gen.uniform((0, 0), (shape[1], shape[0]), (12, 2)):
        varying += 5e3 * np.exp(-0.5 * ((x - cx) ** 2 + (y - cy) ** 2) / 2.0 ** 2)
    varying[varying < 1e-3] = 0.0
    varying[5, :] = -1e-6
    return varying


@pytest.mark.parametrize("level", [0.0, 465.0, 2e6])
@pytest.mark.parametrize("shape", [(37, 100), (50, 64), (77, 130), (100, 511), (99, 512)])
def test_noise_of_a_cutout_is_the_sensors_corner(monkeypatch, level, shape):
    """Poisson (the level's, the varying charge's) and read noise of a cut-out: the whole
    sensor's at its pixels, for cut-outs ending inside a strip, on an amplifier's edge,
    across the amplifier rows and inside the last column of amplifiers; any threads."""
    monkeypatch.setattr(scene_module, "BLOCK_ROWS", 16)  # several strips per amplifier
    varying = _varying(DET.shape)
    whole = AmplifierNoise(DET, 11, detector_index=5, threads=1)
    image, variance = whole.draw(level, varying)
    whole.add_read_noise(image)
    ny, nx = shape
    cut = AmplifierNoise(DET.cutout(nx, ny), 11, detector_index=5, threads=3)
    small, small_var = cut.draw(level, np.ascontiguousarray(varying[:ny, :nx]))
    cut.add_read_noise(small)
    assert small.tobytes() == image[:ny, :nx].tobytes()
    assert small_var.tobytes() == variance[:ny, :nx].tobytes()
    # Another detector draws other numbers.
    other, _ = AmplifierNoise(DET.cutout(nx, ny), 11, detector_index=6).draw(level, None)
    assert level == 0 or not np.array_equal(other, small)


def test_split_draw_is_poisson_in_the_wings():
    """The varying charge's draws by inversion at each pixel's mean, on top of the level's:
    Poisson of the sum, for a faint wing (most pixels decided by u < 1 - mean) and a core."""
    from test_noise_split import chi_square_pvalue

    varying = np.zeros(DET.shape)
    varying[:, :256], varying[:, 256:] = 0.04, 731.0
    draws = np.concatenate([AmplifierNoise(DET, seed, threads=2).draw(2.5, varying,
                                                                      np.float64)[0][None]
                            for seed in range(8)])
    for where, mean in ((np.s_[:, :, :256], 2.54), (np.s_[:, :, 256:], 733.5)):
        counts = draws[where].ravel()
        assert abs(counts.mean() - mean) < 5 * np.sqrt(mean / counts.size)
        assert chi_square_pvalue(counts, mean) > 1e-4


# --- cosmic rays ----------------------------------------------------------------------------

def test_cosmic_rays_of_a_cutout_are_the_sensors():
    """Rays are drawn over the whole sensor: a cut-out gets the whole sensor's rays on its
    pixels, those starting outside it included, and a share of them by its area."""
    full = np.zeros((400, 500), np.float32)
    rows, cols = add_cosmic_rays(full, 20000.0, np.random.default_rng(4))
    cut = np.zeros((150, 170), np.float32)
    r, c = add_cosmic_rays(cut, 20000.0, np.random.default_rng(4), full_shape=(400, 500))
    assert cut.tobytes() == full[:150, :170].tobytes()
    inside = (rows < 150) & (cols < 170)
    np.testing.assert_array_equal(np.sort(r * 170 + c),
                                  np.sort(rows[inside] * 170 + cols[inside]))
    # Rays crossing in from outside: lit pixels on the cut-out's top and right edges.
    assert cut[-1].any() and cut[:, -1].any()
    # The rate is the sensor's: the cut-out holds ~its area's share of the charge (150 x 170
    # of 400 x 500: 12.75%; a few % less, as rays run upwards, none from below row 0).
    share = cut.sum() / full.sum()
    assert share == pytest.approx(150 * 170 / (400 * 500), rel=0.1)


# --- whole scenes ---------------------------------------------------------------------------

def test_700_x_900_cutout_is_the_full_ccds_corner():
    """The default CCD (sky, a Bahcall-Soneira star field, the paper's satellite, noise) with
    dark current and cosmic rays: its 700 x 900 cut-out is the full CCD's corner, byte for
    byte, in IMAGE, VARIANCE, MASK and the streak model."""
    keys = ("cosmic_rays=10", "dark_current=0.1")
    full = simulate(_scene(*keys))
    cut = simulate(_scene(*keys, "detector.nx=700", "detector.ny=900"))
    assert cut.image.shape == (900, 700)
    _assert_corner(full, cut)
    # Every part is there: the streak, cosmic rays, stars, noise.
    assert (cut.mask & (1 << MASK_PLANES["STREAK"])).any()
    assert (cut.mask & (1 << MASK_PLANES["CR"])).any()
    background = cut.variance.min()
    assert np.count_nonzero(cut.variance > background + 100) > 1000  # stars and the streak
    assert cut.image.std() > 10


@pytest.mark.filterwarnings("ignore:cosmic_rays=20")
@pytest.mark.parametrize("keys, large, small", [
    (("detector.type=itl",), (1024, 1024), (300, 200)),
    # e2v: across the amplifier rows (2002), inside the second amplifier column, in ADU,
    # with the amplifiers' raw readout.
    (("detector.type=e2v", "units=adu", "detector.layout=raw"), (1100, 2100), (600, 2050)),
])
def test_a_cutout_of_a_cutout_is_its_corner(keys, large, small):
    """The relation holds between any cut-out and a larger one, with a dense star field."""
    keys = (*keys, "stars.density_per_deg2=1e5", "cosmic_rays=20", "satellites.0.track.x0=100",
            "satellites.0.track.y0=50")
    a = simulate(_scene(*keys, f"detector.nx={large[0]}", f"detector.ny={large[1]}"))
    b = simulate(_scene(*keys, f"detector.nx={small[0]}", f"detector.ny={small[1]}"))
    _assert_corner(a, b)
    assert (b.mask & (1 << MASK_PLANES["CR"])).any()
    if a.raw is not None:
        # Each amplifier's readout noise is its own: the first (whole in both) is the same
        # segment byte for byte; the second, clipped, the same up to the cut-out's columns.
        det = _scene(*keys).detector
        seg_h = det.amp_ny + det.parallel_overscan
        seg_w = det.prescan + det.amp_nx + det.serial_overscan
        first = np.s_[:seg_h, :seg_w]
        assert a.raw[first].tobytes() == b.raw[first].tobytes()
        second = np.s_[:seg_h, seg_w:seg_w + det.prescan + small[0] - det.amp_nx]
        assert a.raw[second].tobytes() == b.raw[second].tobytes()
        # An upper amplifier's serial overscan (its rows sit elsewhere in a clipped segment).
        upper = np.s_[seg_h:, det.prescan + det.amp_nx:seg_w]
        assert a.raw[upper].tobytes() == b.raw[upper].tobytes()


def _catalog(tmp_path, stars):
    path = tmp_path / "stars.csv"
    path.write_text("x,y,mag\n" + "".join(f"{x},{y},{m}\n" for x, y, m in stars))
    return str(path)


def test_bleeding_across_the_cutouts_top_edge(tmp_path):
    """The rule where a cut-out cannot be its larger image's corner: charge bleeds along a
    column and stops at the image's edges, and a cut-out's top row is one. Saturated stars
    just above (bleeding down) and just below (bleeding up) the cut-out's top edge change
    only the columns whose trail crosses that edge in the larger image; there the cut-out's
    trail ends at its top row, as at a CCD's edge. A saturated star inside is identical."""
    ny = 300
    catalog = _catalog(tmp_path, [(150.3, ny + 25.2, 13.0), (300.6, ny - 20.4, 13.0),
                                  (450.2, 100.7, 13.0), (80.0, 150.0, 19.0)])
    keys = (f"stars.catalog={catalog}", "satellites=[]", "cosmic_rays=0")
    large = simulate(_scene(*keys, "detector.nx=600", "detector.ny=500"))
    small = simulate(_scene(*keys, "detector.nx=600", f"detector.ny={ny}"))
    sat_large = (large.mask & SAT) != 0
    sat_small = (small.mask & SAT) != 0
    # Columns whose trail crosses between rows ny - 1 and ny in the larger image.
    crossing = np.flatnonzero(sat_large[ny - 1] | sat_large[ny])
    differ = np.flatnonzero(np.any(large.image[:ny] != small.image, axis=0)
                            | np.any(large.mask[:ny] != small.mask, axis=0)
                            | np.any(large.variance[:ny] != small.variance, axis=0))
    assert differ.size and set(differ) <= set(crossing)
    # Both edge stars are concerned, not the one inside.
    assert np.any(abs(differ - 150) < 5) and np.any(abs(differ - 300) < 5)
    assert not np.any(abs(differ - 450) < 30) and sat_small[:, 440:460].any()
    # In the cut-out those trails end at its top row, and no pixel is above full well.
    full_well = _scene().detector.full_well
    assert sat_small[ny - 2:, differ].any()  # its last pixel may hold the remainder
    assert small.image[:, differ].max() <= full_well + 10 * 6.4
    # Everywhere else: byte for byte.
    keep = np.setdiff1d(np.arange(600), differ)
    for name in PLANES:
        a, b = getattr(large, name)[:ny][:, keep], getattr(small, name)[:, keep]
        assert a.tobytes() == b.tobytes(), name


FOCAL = {"seed": 5, "band": "g", "zenith": 70, "cosmic_rays": 10,
         "pointing": {"ra": 50, "dec": -30, "rotation": 10},
         "sky": True, "stars": {"galactic_b": 30, "mag_limit": 23}, "noise": True}


def _focal_pair(y0_mm=None, name="R22_S11", cutout=(700, 900), track=None):
    """The full CCD and its cut-out in a focal-plane scene with a streak at ``y0_mm`` (or
    along ``track``)."""
    from inject import make_plan, parse_focal_scene, simulate_ccd
    from inject.camera import layout as fp

    track = track or {"x0_mm": -19.0, "y0_mm": y0_mm, "angle": 3.0}
    raw = dict(FOCAL, satellites=[{"height": 550, "mag": 5.0,
                                   "shape": {"type": "box", "length": 7.25, "width": 2.65},
                                   "track": track}])
    ccd = fp.ccd(name)
    results = []
    for keys in ({}, {"cutout": {"nx": cutout[0], "ny": cutout[1]}}):
        fscene = parse_focal_scene({**raw, **keys})
        results.append(simulate_ccd(fscene, ccd, make_plan(fscene).streaks(ccd))[1])
    return results


def test_focal_plane_cutout_is_the_ccds_corner():
    """``cutout: {nx: 700, ny: 900}`` of a focal-plane scene with sky, stars, noise and
    cosmic rays, the streak crossing the CCD higher up: the full CCD's corner byte for
    byte."""
    full, cut = _focal_pair(y0_mm=5.0)
    assert cut.image.shape == (900, 700) and full.streak_model.max() > 1e3
    _assert_corner(full, cut)
    assert (cut.mask & (1 << MASK_PLANES["CR"])).any()
    assert np.count_nonzero(cut.variance > cut.variance.min() + 100) > 100  # stars


#: A polyline across R22_S11 (pixel x = 100 (x_mm + 20.475), y ~ 300): B inside the
#: 700 x 900 cut-out, C (whose profile draws the second half of B-C, inside it) and D beyond.
POLYLINE = {"vertices": [{"x_mm": -40.0, "y_mm": -17.1, "height": 500},
                         {"x_mm": -18.5, "y_mm": -17.05, "height": 520},
                         {"x_mm": -10.5, "y_mm": -16.98, "height": 560, "mag": 5.0},
                         {"x_mm": -5.5, "y_mm": -16.95, "height": 580, "mag": 6.0},
                         {"x_mm": 30.0, "y_mm": -16.8, "height": 700}]}
#: The same with C and D sharing a profile (same height, other magnitudes): the whole CCD
#: builds C's on its orientation grid, as it recurs, so the cut-out keeps D too.
SHARED = {"vertices": [*POLYLINE["vertices"][:3], {**POLYLINE["vertices"][3], "height": 560},
                       POLYLINE["vertices"][4]]}


@pytest.mark.parametrize("track, vertices", [
    ({"x0_mm": -19.0, "y0_mm": -17.0, "angle": 3.0}, (2, 2)),
    (POLYLINE, (5, 3)),  # the cut-out keeps the pieces that reach it: entry-B, B-C
    (SHARED, (5, 5)),
], ids=["line", "polyline", "shared-profile"])
def test_focal_plane_streak_on_a_cutout_is_the_ccds_corner(track, vertices):
    """A streak crossing a focal-plane cut-out is the full CCD's, byte for byte with noise
    on: its plate scale, model and vertices come from the track's part on the whole CCD (a
    cut-out's own part is shorter, and its middle, where the scale was taken, ~1e-5 of the
    peak away). The TRUTH row still describes the part the cut-out receives: it starts where
    the whole CCD's does (both enter by the left edge) and ends at the cut-out's right edge
    grown by the profile's reach, on the same track."""
    full, cut = _focal_pair(track=track)
    assert cut.streak_model.max() > 1e3
    _assert_corner(full, cut)
    (a,), (b,) = full.truth, cut.truth
    assert b["pixel_scale_arcsec"] == a["pixel_scale_arcsec"] != 0.2
    assert (b["x0"], b["y0"]) == (a["x0"], a["y0"])
    reach = -0.5 - a["x0"]  # the whole CCD's part begins that far left of its edge
    assert b["x1"] == pytest.approx(700 - 0.5 + reach, abs=1e-6) and b["x1"] < a["x1"] - 3000
    assert b["length_px"] == pytest.approx(np.hypot(b["x1"] - b["x0"], b["y1"] - b["y0"]),
                                           rel=1e-3)
    assert b["flags"] & 2 and b["charge_in_image_e"] < a["charge_in_image_e"] / 3
    assert (a["n_vertices"], b["n_vertices"]) == vertices
