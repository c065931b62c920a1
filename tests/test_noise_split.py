"""The noise path: the split Poisson draw is Poisson, the variance is the drawn mean plus read
noise, the draws do not depend on the threads, and a CCD without streaks has a STREAK_MODEL
that costs nothing yet reads back as float32 zeros (with astropy and with inject's reader)."""
import hashlib
from dataclasses import replace

import numpy as np
import pytest
from astropy.io import fits
from scipy import stats

import inject
from inject import (
    DEFAULT_SCENE,
    apply_overrides,
    parse_scene,
    read_exposure,
    simulate,
    write_exposure,
)
from inject.camera.detector import ITL
from inject.scene import AmplifierNoise, PoissonTable, draw_poisson
from inject.truth import TRUTH_COLUMNS, VERTEX_COLUMNS

#: A small sensor: 2 x 8 amplifiers of 64 x 50 pixels, each with its own read noise.
READ_NOISE = tuple(3.0 + 0.5 * k for k in range(16))
DET = replace(ITL, nx=8 * 64, ny=2 * 50, amp_nx=64, amp_ny=50, amp_read_noise=READ_NOISE)


def pixel_classes(shape):
    """Varying expected charge by column band: 0, a few e-, tens of e-, and a slight negative
    (an interpolation dip: collects nothing)."""
    varying = np.zeros(shape)
    varying[:, 128:256] = 3.7
    varying[:, 256:384] = 52.5
    varying[:, 384:448] = -1e-6
    return varying, {"zero": np.s_[:, :128], "few": np.s_[:, 128:256],
                     "tens": np.s_[:, 256:384], "dip": np.s_[:, 384:448]}


def chi_square_pvalue(counts, mean):
    """p-value of the counts' histogram against Poisson(mean) (bins with >= 5 expected)."""
    lo, hi = int(stats.poisson.ppf(1e-4, mean)), int(stats.poisson.ppf(1 - 1e-4, mean))
    edges = np.arange(lo, hi + 2)
    observed = np.array([(counts < lo).sum(), *np.histogram(counts, edges)[0],
                         (counts > hi).sum()])
    probs = np.diff(stats.poisson.cdf(edges - 1, mean))
    expected = len(counts) * np.array([stats.poisson.cdf(lo - 1, mean), *probs,
                                       stats.poisson.sf(hi, mean)])
    # Merge sparse bins into their neighbours so the chi-square approximation holds.
    obs, exp, o, e = [], [], 0.0, 0.0
    for a, b in zip(observed, expected):
        o, e = o + a, e + b
        if e >= 5:
            obs.append(o), exp.append(e)
            o, e = 0.0, 0.0
    obs[-1] += o
    exp[-1] += e
    return stats.chisquare(obs, np.array(exp) * sum(obs) / sum(exp)).pvalue


@pytest.mark.parametrize("level", [0.0, 2.5, 465.0])
def test_split_draw_is_poisson_of_the_summed_mean(level):
    """Poisson(level) everywhere plus Poisson(varying) where varying > 0 is Poisson(level +
    max(varying, 0)) per pixel: mean, variance and the whole distribution per class."""
    varying, classes = pixel_classes(DET.shape)
    draws = np.concatenate([AmplifierNoise(DET, seed, threads=2).draw(level, varying,
                                                                      np.float64)[0][None]
                            for seed in range(6)])
    assert draws.dtype == np.float64 and np.all(draws == np.rint(draws))
    for name, where in classes.items():
        mean = level + max(float(varying[where][0, 0]), 0.0)
        counts = draws[(slice(None), *where)].ravel()
        if mean == 0:
            assert not counts.any()
            continue
        n = counts.size
        assert abs(counts.mean() - mean) < 5 * np.sqrt(mean / n), name
        # The sample variance of n Poisson draws has a standard error ~ mean * sqrt(2 / n).
        assert counts.var() == pytest.approx(mean, abs=5 * mean * np.sqrt(2.0 / n) + 0.05)
        assert chi_square_pvalue(counts, mean) > 1e-4, name
        # A second, independent check of the shape: KS against a large direct Poisson sample.
        reference = np.random.default_rng(99).poisson(mean, 200_000)
        assert stats.ks_2samp(counts, reference).pvalue > 1e-4, name


def test_draws_do_not_depend_on_threads_and_differ_by_seed():
    varying, _ = pixel_classes(DET.shape)
    one = AmplifierNoise(DET, 5, detector_index=3, threads=1)
    four = AmplifierNoise(DET, 5, detector_index=3, threads=4)
    (a, _), (b, _) = one.draw(100.0, varying, np.float64), four.draw(100.0, varying, np.float64)
    np.testing.assert_array_equal(a, b)
    as32 = AmplifierNoise(DET, 5, detector_index=3).draw(100.0, varying)[0]
    np.testing.assert_array_equal(as32, a)  # float32 holds the counts exactly
    np.testing.assert_array_equal(one.add_read_noise(a), four.add_read_noise(b))
    other = AmplifierNoise(DET, 5, detector_index=4, threads=1).draw(100.0, varying)[0]
    assert not np.array_equal(a, other)


def test_a_scene_is_the_same_whether_its_streaks_render_beside_the_stars(monkeypatch,
                                                                          small_scene):
    """With threads to spare, the streaks render on a second thread while the stars are
    placed: the planes and the truth are those of the one-thread order."""
    import inject.scene

    sc = small_scene("stars.density_per_deg2=1e5", nx=300, ny=260)
    results = []
    for threads in (1, 2):
        monkeypatch.setattr(inject.scene, "NOISE_THREADS", threads)
        results.append(simulate(sc))
    one, two = results
    for plane in ("image", "mask", "variance", "streak_model"):
        np.testing.assert_array_equal(getattr(one, plane), getattr(two, plane))
    assert one.streak_model.max() > 0 and one.truth[0]["charge_in_image_e"] > 0
    assert [row["charge_in_image_e"] for row in one.truth] == \
        [row["charge_in_image_e"] for row in two.truth]


@pytest.mark.parametrize("chunk", [1, 64, 64 * 7 + 3])
def test_chunked_draw_takes_the_same_uniforms(monkeypatch, chunk):
    """Drawing an amplifier a few rows at a time (to keep the temporaries in cache) gives
    the image of one draw per amplifier: the uniforms are taken in the same order."""
    varying, _ = pixel_classes(DET.shape)
    whole, whole_var = AmplifierNoise(DET, 8, threads=1).draw(30.0, varying)
    monkeypatch.setattr(AmplifierNoise, "CHUNK_PX", chunk)
    chunked, chunked_var = AmplifierNoise(DET, 8, threads=1).draw(30.0, varying)
    np.testing.assert_array_equal(chunked, whole)
    np.testing.assert_array_equal(chunked_var, whole_var)
    # The reference: every block's Poisson(level) by one table draw of its whole block.
    noise = AmplifierNoise(DET, 8, threads=1)
    for block in noise.blocks:
        expected = draw_poisson(noise.generator("noise", block), 30.0,
                                whole[block.region].shape)
        part = varying[block.region]
        np.testing.assert_array_equal(whole[block.region][part <= 0], expected[part <= 0])


def test_variance_and_read_noise_per_amplifier():
    varying, _ = pixel_classes(DET.shape)
    noise = AmplifierNoise(DET, 1, threads=2)
    variance = noise.draw(40.0, varying)[1]
    assert variance.dtype == np.float32
    amp = DET.amp_index()
    rn2 = np.asarray(READ_NOISE)[amp] ** 2
    np.testing.assert_allclose(variance, 40.0 + np.maximum(varying, 0) + rn2, rtol=1e-6)
    np.testing.assert_allclose(noise.draw(40.0)[1], 40.0 + rn2, rtol=1e-6)
    # Read noise alone (no charge): each amplifier's own sigma.
    read = np.concatenate([AmplifierNoise(DET, s, threads=2).add_read_noise(
                               np.zeros(DET.shape, np.float32))[None]
                           for s in range(8)])
    assert read.dtype == np.float32
    for k, sigma in enumerate(READ_NOISE):
        values = read[:, amp == k]
        assert values.std() == pytest.approx(sigma, rel=5 * np.sqrt(0.5 / values.size))
        assert abs(values.mean()) < 5 * sigma / np.sqrt(values.size)


def test_scene_without_streaks_matches_its_variance(small_scene):
    """Sky, stars and noise with no satellite: the image scatters as its VARIANCE says."""
    res = simulate(small_scene("satellites=[]", "cosmic_rays=0", nx=300, ny=260))
    assert res.image.dtype == np.float32 and res.variance.dtype == np.float32
    pulls = (res.image - (res.variance - ITL.read_noise ** 2)) / np.sqrt(res.variance)
    assert abs(pulls.mean()) < 5 / np.sqrt(pulls.size)
    assert pulls.std() == pytest.approx(1.0, abs=0.02)


def test_variance_holds_the_stars_expected_charge(small_scene):
    """The stars' charge is drawn with the streaks', pixel by pixel; VARIANCE is the whole
    expected charge: the noise-free image of the same scene (same star field) plus the read
    noise squared."""
    # Dense enough that this corner of the CCD's star field holds stars.
    keys = ("cosmic_rays=0", "satellites=[]", "stars.density_per_deg2=1e5")
    noisy = simulate(small_scene(*keys, nx=300, ny=260))
    clean = simulate(small_scene(*keys, "noise=false", nx=300, ny=260))
    assert clean.image.max() - clean.image.min() > 1e3  # stars are there
    np.testing.assert_allclose(noisy.variance, clean.image + ITL.read_noise ** 2, rtol=2e-6)


def test_streak_free_model_is_not_allocated_and_reads_back_as_zeros(tmp_path, small_scene):
    sc = small_scene("satellites=[]", nx=300, ny=260)
    res = simulate(sc)
    assert res.streak_model.shape == sc.detector.shape
    assert res.streak_model.strides == (0, 0) and not res.streak_model.any()  # no memory
    path = tmp_path / "ccd.fits"
    digest = write_exposure(path, sc, res, sc.detector.gain)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    with fits.open(path) as hdus:
        assert [h.name for h in hdus][1:7] == ["IMAGE", "MASK", "VARIANCE", "STREAK_MODEL",
                                               "TRUTH", "TRUTH_VERTICES"]
        model = hdus["STREAK_MODEL"]
        assert type(model) is fits.ImageHDU and model.header["BITPIX"] == -32
        assert model.data.shape == sc.detector.shape and not model.data.any()
        assert model.header["BUNIT"] == "electron"
        np.testing.assert_array_equal(hdus["IMAGE"].data, res.image)
        np.testing.assert_array_equal(hdus["MASK"].data, res.mask)
    exposure = read_exposure(str(path))  # inject's own reader
    np.testing.assert_array_equal(exposure.image, res.image)


@pytest.mark.parametrize("overrides", [
    ["satellites=[]", "stars=false"],
    ["detector.layout=raw", "units=adu"],  # a streak (float64 model), RAW, ADU planes
])
def test_streamed_planes_give_the_bytes_of_astropys_write(tmp_path, overrides):
    """The planes' data streamed a MiB at a time (converted in a small buffer, runs of
    zeros such as a zero STREAK_MODEL left as holes) give the bytes of the same HDUs written
    the ordinary way, through astropy alone (dense arrays); the planes are large enough for
    several MiB pieces and holes."""
    sc = parse_scene(apply_overrides(DEFAULT_SCENE, ["detector.nx=1200", "detector.ny=1000",
                                                     *overrides]))
    res = simulate(sc)
    streamed = tmp_path / "streamed.fits"
    digest = write_exposure(streamed, sc, res, sc.detector.gain, xy0=(5, 7))
    assert digest == hashlib.sha256(streamed.read_bytes()).hexdigest()
    dense = tmp_path / "dense.fits"
    with fits.open(streamed) as hdus:
        copy = fits.HDUList([h.copy() for h in hdus])
        names = [h.name for h in copy]
        copy["STREAK_MODEL"].data = np.array(res.streak_model, np.float32)
        copy["IMAGE"].data = np.array(res.image, np.float32)
        copy.writeto(dense)
    assert names[1:7] == ["IMAGE", "MASK", "VARIANCE", "STREAK_MODEL", "TRUTH",
                          "TRUTH_VERTICES"]
    assert ("RAW" in names) == ("detector.layout=raw" in overrides)
    assert streamed.read_bytes() == dense.read_bytes()


def test_empty_truth_tables_carry_the_version_they_are_written_with(tmp_path, monkeypatch):
    """A CCD no streak reaches writes its empty tables from bytes built once per process:
    a run of another version (a worker writing as its run) still gets its own INJVER there,
    and tables of no rows with every column."""
    sc = parse_scene(apply_overrides(DEFAULT_SCENE, ["detector.nx=300", "detector.ny=200",
                                                     "satellites=[]", "stars=false"]))
    res = simulate(sc)
    for version in ("1.2.3", "4.5.6"):
        monkeypatch.setattr(inject, "__version__", version)
        path = tmp_path / f"{version}.fits"
        write_exposure(path, sc, res, sc.detector.gain)
        with fits.open(path) as hdus:
            assert hdus[0].header["INJVER"] == version
            for name, spec in (("TRUTH", TRUTH_COLUMNS), ("TRUTH_VERTICES", VERTEX_COLUMNS)):
                assert hdus[name].header["INJVER"] == version
                assert len(hdus[name].data) == 0
                assert hdus[name].columns.names == list(spec)


def test_with_a_streak_the_model_is_written_and_masked(small_scene):
    res = simulate(small_scene(nx=300, ny=260))
    assert res.streak_model.strides != (0, 0) and res.streak_model.max() > 0
    assert (res.mask & (1 << 10)).any()


@pytest.mark.parametrize("mean", [0.0, 0.3, 7.0, 465.0, 2.5e4])
def test_poisson_table_is_the_inverse_cdf(mean):
    """The guide-table draw equals the plain inversion (smallest k with CDF(k) > u) of the
    same uniforms, the CDF being scipy's; and its sample matches Poisson(mean)."""
    table = PoissonTable(mean)
    k = table.draw(np.random.default_rng(4), 300_000)
    u = np.random.default_rng(4).random(300_000)
    cdf = stats.poisson.cdf(np.arange(table.cdf.size), mean)
    np.testing.assert_array_equal(k, np.minimum(np.searchsorted(cdf, u, side="right"),
                                                table.cdf.size - 1))
    if mean == 0:
        assert not k.any()
        return
    assert abs(k.mean() - mean) < 5 * np.sqrt(mean / k.size)
    assert chi_square_pvalue(k, mean) > 1e-4


@pytest.mark.parametrize("mean", [0.3, 50.0, 465.0, 3000.5, 9e5])
def test_poisson_table_at_the_edges_of_its_slices_and_in_its_tails(mean):
    """Uniforms on and beside every slice edge of the guide table's tails, and at the ends of
    [0, 1), draw the plain inversion of scipy's CDF (where the table's search takes over)."""
    table = PoissonTable(mean)
    edges = np.concatenate([np.arange(64), table.GUIDE - 64 + np.arange(64)]) / table.GUIDE
    u = np.concatenate([edges, np.nextafter(edges, 0), np.nextafter(edges, 1),
                        [1e-300, 1e-17, 0.5, 1 - 2 ** -53]])
    u = np.clip(u, 0.0, 1 - 2 ** -53)

    class Fixed:
        def random(self, shape):
            return u.reshape(shape)

    cdf = stats.poisson.cdf(np.arange(table.cdf.size), mean)
    np.testing.assert_array_equal(table.draw(Fixed(), u.shape),
                                  np.minimum(np.searchsorted(cdf, u, side="right"),
                                             table.cdf.size - 1))


def test_means_beyond_the_table_use_numpys_sampler():
    mean = 2 * PoissonTable.MAX_MEAN
    k = draw_poisson(np.random.default_rng(1), mean, 20_000)
    assert k.dtype == np.int64
    assert abs(k.mean() - mean) < 5 * np.sqrt(mean / k.size)
    assert k.var() == pytest.approx(mean, rel=5 * np.sqrt(2 / k.size))


def test_digest_stream_holes_keep_the_bytes(tmp_path):
    """Zero runs of every length and place (one ending the file) are read back as zeros."""
    from inject.io.fits import _DigestStream, _Hasher

    hole = _DigestStream.HOLE
    gen = np.random.default_rng(2)
    pieces = [gen.integers(0, 255, 1000, dtype=np.uint8), np.zeros(3 * hole + 17, np.uint8),
              gen.integers(0, 255, hole + 5, dtype=np.uint8), np.zeros(hole - 1, np.uint8),
              np.zeros(2 * hole, np.uint8)]
    path = tmp_path / "f.bin"
    with _Hasher() as hasher, open(path, "wb") as out:
        stream = _DigestStream(out, hasher)
        for piece in pieces:
            stream.write(piece.data)
        out.truncate()
    data = np.concatenate(pieces).tobytes()
    assert path.read_bytes() == data
    assert hasher.hexdigest() == hashlib.sha256(data).hexdigest()


def test_digest_of_a_plane_hashed_behind_its_writer(tmp_path):
    """A plane of many MiB with a hash that lags far behind the writer: the writer reuses
    its buffers only once hashed, so the digest is that of the bytes on disk."""
    import time

    from inject.io.fits import _DigestStream, _Hasher, _write_image_data

    plane = np.random.default_rng(3).random((1500, 1000)).astype(np.float32)  # 6 MB
    plane[:600] = 0  # a hole too

    class Slow:
        def __init__(self):
            self.real = hashlib.sha256()

        def update(self, data):
            time.sleep(0.002)
            self.real.update(data)

        def hexdigest(self):
            return self.real.hexdigest()

    path = tmp_path / "plane.bin"
    hasher = _Hasher()
    hasher._digest = Slow()
    with hasher, open(path, "wb") as out:
        _write_image_data(_DigestStream(out, hasher), np.tile(plane, (3, 1)), np.float32)
        out.truncate()
    data = path.read_bytes()
    assert data[:plane.nbytes * 3] == np.tile(plane, (3, 1)).astype(">f4").tobytes()
    assert hasher.hexdigest() == hashlib.sha256(data).hexdigest()


def test_a_write_without_its_digest_gives_the_same_bytes(tmp_path, small_scene):
    sc = small_scene(nx=300, ny=260)
    res = simulate(sc)
    hashed, plain = tmp_path / "hashed.fits", tmp_path / "plain.fits"
    digest = write_exposure(hashed, sc, res, sc.detector.gain)
    assert write_exposure(plain, sc, res, sc.detector.gain, digest=False) is None
    assert plain.read_bytes() == hashed.read_bytes()
    assert digest == hashlib.sha256(plain.read_bytes()).hexdigest()


@pytest.mark.parametrize("shape, dtype", [((3, 5), np.float64), ((1100, 1024), np.int32),
                                          ((600, 1000), np.float64)])
def test_sparse_zeros_are_zeros_of_the_shape_and_type(shape, dtype):
    import pickle

    from inject.scene import sparse_zeros

    a = sparse_zeros(shape, dtype)
    assert a.shape == shape and a.dtype == dtype and a.flags.writeable
    assert not a.any()
    a[-1, -1] = 7
    assert a.sum() == 7 and np.count_nonzero(a) == 1
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(a)), a)


@pytest.mark.parametrize("rows", [1, 7, 8, 9, 256, 257])
def test_last_lit_row_is_the_last_row_with_charge(rows):
    """Against the plain scan, for every single lit row, none, and zero or negative values."""
    from inject.scene import _last_lit_row

    gen = np.random.default_rng(rows)
    for lit in [None, *range(rows)]:
        part = np.where(gen.random((rows, 13)) < 0.5, -1e-6, 0.0)
        if lit is not None:
            part[lit, gen.integers(13)] = 1e-9
            part[:lit, 5] = 3.0  # rows above it lit too
        expected = np.flatnonzero(part.max(axis=1) > 0)
        assert _last_lit_row(part) == (expected[-1] if expected.size else -1)
