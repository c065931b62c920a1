"""Test images at any telescope's settings, with streaks whose line and FWHM are known.

The masker's own benchmarks (``scripts/bench_mask.py``) use inject's LSSTCam simulator; a
masker meant for other telescopes is checked here on images made from a few numbers per
instrument (:class:`Instrument`: pixel scale, seeing, aperture, sky, read noise, gain, full
well): Moffat stars drawn by GalSim (bright ones saturated, with bleed trails along their
columns), an optional resolved galaxy, sky and read noise, stored as integers with a
pedestal, and straight streaks whose cross-section is the line-spread function of the seeing
(a Gaussian) convolved with the defocused pupil (a uniform annulus seen from the satellite's
range), integrated over each pixel.

The truth of each streak is how it was drawn: the line (angle, a point on it) and the FWHM of
its cross-section before pixelisation, computed from the tabulated profile.
"""
from dataclasses import dataclass

import numpy as np

#: Supersampling of a pixel (per axis) when a streak is drawn: the profile is averaged over
#: ``SUPERSAMPLE^2`` points of each pixel, which integrates a 1 px FWHM Gaussian to 0.1%.
SUPERSAMPLE = 8

#: Sampling (px) of the tabulated cross-section.
PROFILE_STEP = 0.01


@dataclass(frozen=True)
class Instrument:
    """What an image of one telescope looks like.

    Attributes
    ----------
    name : str
    pixel_scale : float
        Arcsec per pixel.
    seeing : float
        FWHM of the seeing (and optics), arcsec.
    aperture_m : float
        Primary mirror diameter, m (a satellite's defocus is the pupil seen from its range).
    obscuration : float
        Central obstruction, fraction of the diameter.
    shape : tuple
        ``(ny, nx)`` of the image.
    sky_e : float
        Sky per pixel, electrons.
    read_noise_e : float
    gain : float
        Electrons per ADU.
    full_well_e : float
        Charge at which a pixel saturates (bleeding along its column).
    pedestal_adu : float
        Bias level added to every pixel.
    n_stars : int
        Stars per image (a power law in flux; the brightest saturated).
    galaxy_hlr_px : float
        Half-light radius of a bright resolved galaxy (0: none).
    range_km : float
        Satellite range (sets the defocus).
    """

    name: str
    pixel_scale: float
    seeing: float
    aperture_m: float
    obscuration: float
    shape: tuple
    sky_e: float = 500.0
    read_noise_e: float = 8.0
    gain: float = 1.5
    full_well_e: float = 80_000.0
    pedestal_adu: float = 1000.0
    n_stars: int = 150
    galaxy_hlr_px: float = 0.0
    range_km: float = 550.0

    @property
    def sigma_adu(self):
        """Per-pixel sky noise, ADU."""
        return float(np.sqrt(self.sky_e + self.read_noise_e ** 2) / self.gain)

    @property
    def seeing_px(self):
        return self.seeing / self.pixel_scale

    @property
    def defocus_px(self):
        """Diameter of the defocused pupil seen from the satellite's range, px."""
        return float(np.degrees(self.aperture_m / (self.range_km * 1e3)) * 3600
                     / self.pixel_scale)


#: The instruments of the telescope benchmark (rows of the table in the masking guide).
INSTRUMENTS = (
    Instrument("0.4 m, 1\"/px, 2\" seeing", 1.0, 2.0, 0.4, 0.35, (400, 400), sky_e=300,
               read_noise_e=10, gain=1.2, full_well_e=60_000, n_stars=120, galaxy_hlr_px=8),
    Instrument("0.4 m, 0.6\"/px, 1\" seeing", 0.6, 1.0, 0.4, 0.35, (1024, 1024), sky_e=200,
               read_noise_e=8, gain=1.0, full_well_e=50_000, n_stars=200, galaxy_hlr_px=12),
    Instrument("wide field, 6\"/px", 6.0, 5.0, 0.1, 0.0, (800, 800), sky_e=2000,
               read_noise_e=12, gain=2.0, full_well_e=40_000, n_stars=600, galaxy_hlr_px=15),
    Instrument("1.8 m, 0.4\"/px", 0.4, 1.2, 1.8, 0.3, (1024, 1024), sky_e=800,
               read_noise_e=5, gain=1.5, n_stars=200, galaxy_hlr_px=15),
    Instrument("HSC-like, 0.17\"/px, 8.2 m", 0.17, 0.7, 8.2, 0.3, (2048, 2048), sky_e=1500,
               read_noise_e=4.5, gain=3.0, full_well_e=150_000, n_stars=250, galaxy_hlr_px=25),
    Instrument("DECam, 0.263\"/px, 4 m", 0.263, 1.0, 4.0, 0.4, (2048, 2048), sky_e=1200,
               read_noise_e=7, gain=4.0, full_well_e=130_000, n_stars=250, galaxy_hlr_px=20),
    Instrument("LSSTCam, 0.2\"/px, 8.4 m", 0.2, 0.7, 8.4, 0.61, (4000, 4072), sky_e=1000,
               read_noise_e=6, gain=1.6, full_well_e=100_000, n_stars=400, galaxy_hlr_px=25),
)


def cross_section(instrument):
    """Tabulated cross-section of a streak (peak 1): the seeing's Gaussian line-spread function
    convolved with the projection of the defocused annular pupil.

    Returns
    -------
    d : ndarray
        Distance from the line, px.
    f : ndarray
        Profile, normalised to a peak of 1.
    fwhm : float
        Its FWHM, px (the truth of the streak's width).
    """
    s = instrument.seeing_px / (2 * np.sqrt(2 * np.log(2)))
    radius = 0.5 * instrument.defocus_px
    reach = 6 * s + radius + 2
    d = np.arange(-reach, reach + PROFILE_STEP / 2, PROFILE_STEP)
    f = np.exp(-0.5 * (d / s) ** 2)
    if radius > 0.05:
        inner = instrument.obscuration * radius

        def chord(r):
            return 2 * np.sqrt(np.clip(r * r - d * d, 0, None))

        pupil = chord(radius) - chord(inner)
        f = np.convolve(f, pupil / pupil.sum(), mode="same")
    f = f / f.max()
    above = np.flatnonzero(f >= 0.5)
    lo, hi = above[0], above[-1]
    left = d[lo - 1] + (0.5 - f[lo - 1]) * PROFILE_STEP / (f[lo] - f[lo - 1])
    right = d[hi] + (f[hi] - 0.5) * PROFILE_STEP / (f[hi] - f[hi + 1])
    return d, f, float(right - left)


@dataclass
class StreakTruth:
    """A streak drawn on a synthetic image.

    Attributes
    ----------
    angle_deg : float
        Orientation, ``(-90, 90]`` deg, counter-clockwise from +x.
    x, y : float
        A point of the line (pixel coordinates, pixel centres at integers).
    fwhm_px : float
        FWHM of its cross-section before pixelisation.
    peak_snr : float
        Peak pixel value over the sky noise.
    """

    angle_deg: float
    x: float
    y: float
    fwhm_px: float
    peak_snr: float

    def offset_of(self, x, y):
        """Signed distance (px) of point ``(x, y)`` from the line."""
        a = np.radians(self.angle_deg)
        return float(-(x - self.x) * np.sin(a) + (y - self.y) * np.cos(a))


def _draw_streak(image, instrument, truth, profile):
    """Add a streak (in electrons) of peak S/N ``truth.peak_snr`` to ``image``."""
    d_tab, f_tab, _ = profile
    reach = d_tab[-1]
    ny, nx = image.shape
    a = np.radians(truth.angle_deg)
    nxv, nyv = -np.sin(a), np.cos(a)
    # Distances as an outer sum of two vectors (float32: a full CCD in 64 MB).
    dist = (np.arange(ny, dtype=np.float32)[:, None] - np.float32(truth.y)) * np.float32(nyv) \
        + (np.arange(nx, dtype=np.float32)[None, :] - np.float32(truth.x)) * np.float32(nxv)
    near = np.abs(dist) < reach + 1
    dist = dist[near].astype(np.float64)
    sub = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    oy, ox = np.meshgrid(sub, sub, indexing="ij")
    shift = (ox * nxv + oy * nyv).ravel()
    values = np.interp(dist[:, None] + shift[None, :], d_tab, f_tab, left=0, right=0)
    pix = values.mean(axis=1)
    # Peak S/N per pixel refers to the pixelated peak at this angle.
    sigma_e = np.sqrt(instrument.sky_e + instrument.read_noise_e ** 2)
    centre = np.interp(shift[None, :] + np.linspace(-0.5, 0.5, 41)[:, None], d_tab, f_tab)
    peak_pix = float(centre.mean(axis=1).max())
    image[near] += pix * truth.peak_snr * sigma_e / peak_pix


def _bleed(charge, full_well):
    """Charge above the full well of a column flows along it (half up, half down)."""
    cols = np.flatnonzero((charge > full_well).any(axis=0))
    ny = charge.shape[0]
    for x in cols:
        col = charge[:, x]
        over = col > full_well
        excess = float((col[over] - full_well).sum())
        col[over] = full_well
        idx = np.flatnonzero(over)
        lo, hi = idx[0], idx[-1]
        # Fill outwards from the saturated run, alternately below and above.
        up, down = excess / 2, excess / 2
        k = hi + 1
        while up > 0 and k < ny:
            room = full_well - col[k]
            take = min(room, up)
            col[k] += take
            up -= take
            k += 1
        k = lo - 1
        while down > 0 and k >= 0:
            room = full_well - col[k]
            take = min(room, down)
            col[k] += take
            down -= take
            k -= 1


def make_image(instrument, streaks=(), seed=0, stars=True, galaxy=True, border=None):
    """A synthetic raw-like image (integer ADU with a pedestal) with known streaks.

    Parameters
    ----------
    instrument : Instrument
    streaks : sequence of (angle_deg, x, y, peak_snr)
        Lines through ``(x, y)``.
    seed : int
    stars, galaxy : bool
        Draw the star field (bright stars saturated and bleeding) and the galaxy.
    border : {None, "nan", "zero"}
        A 20 px border of NaN (the image is then float32) or of zeros.

    Returns
    -------
    image : ndarray
        int32 ADU (float32 with a NaN border).
    truths : list of StreakTruth
    """
    import galsim

    rng = np.random.default_rng(seed)
    ny, nx = instrument.shape
    charge = np.full((ny, nx), float(instrument.sky_e))
    profile = cross_section(instrument)
    truths = []
    for angle, x, y, snr in streaks:
        t = StreakTruth(float(angle), float(x), float(y), profile[2], float(snr))
        _draw_streak(charge, instrument, t, profile)
        truths.append(t)
    if stars or galaxy:
        psf = galsim.Moffat(beta=3.0, fwhm=max(instrument.seeing_px, 0.8))
        canvas = galsim.ImageD(nx, ny, scale=1.0)
        gsp = galsim.GSParams(folding_threshold=1e-2, maximum_fft_size=8192)
        if stars:
            # Fluxes from a power law: most faint, a few saturating the full well.
            peak_frac = 1 / (2 * np.pi * (max(instrument.seeing_px, 0.8) / 2.355) ** 2)
            peak_frac = min(peak_frac, 0.6)
            top = 20 * instrument.full_well_e / peak_frac
            low = 5 * np.sqrt(instrument.sky_e) / peak_frac
            u = rng.random(instrument.n_stars)
            flux = low * (top / low) ** (u ** 3)
            xs, ys = rng.uniform(-10, nx + 10, instrument.n_stars), \
                rng.uniform(-10, ny + 10, instrument.n_stars)
            # The pixelated PSF drawn once per quarter-pixel offset (a GalSim FFT per star
            # costs ~0.1 s), then scaled and added at each star's nearest offset.
            half = 48
            sub = (np.arange(4) + 0.5) / 4 - 0.5
            stamps = {}
            for i, oy in enumerate(sub):
                for j, ox in enumerate(sub):
                    stamp = galsim.ImageD(2 * half + 1, 2 * half + 1, scale=1.0)
                    psf.withGSParams(gsp).drawImage(stamp, offset=(ox, oy), method="auto")
                    stamps[i, j] = stamp.array / stamp.array.sum()
            for f, x, y in zip(flux, xs, ys):
                ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
                i = min(3, int((y - iy + 0.5) * 4))
                j = min(3, int((x - ix + 0.5) * 4))
                y0, y1 = max(0, iy - half), min(ny, iy + half + 1)
                x0, x1 = max(0, ix - half), min(nx, ix + half + 1)
                if y0 >= y1 or x0 >= x1:
                    continue
                canvas.array[y0:y1, x0:x1] += f * stamps[i, j][y0 - iy + half:y1 - iy + half,
                                                                 x0 - ix + half:x1 - ix + half]
        if galaxy and instrument.galaxy_hlr_px > 0:
            hlr = instrument.galaxy_hlr_px
            gal = galsim.Convolve(galsim.Sersic(n=1.5, half_light_radius=hlr)
                                  .shear(q=0.5, beta=rng.uniform(0, 180) * galsim.degrees),
                                  psf).withGSParams(gsp)
            # Central surface brightness ~300 sky sigma (a bright galaxy, not saturated).
            sigma_e = np.sqrt(instrument.sky_e + instrument.read_noise_e ** 2)
            gal = gal.withFlux(300 * sigma_e * 2 * np.pi * (hlr / 1.2) ** 2)
            half = int(6 * hlr + 10)
            stamp = galsim.ImageD(2 * half + 1, 2 * half + 1, scale=1.0)
            gx, gy = rng.uniform(0.25, 0.75) * nx, rng.uniform(0.25, 0.75) * ny
            stamp.setCenter(int(gx) + 1, int(gy) + 1)
            gal.drawImage(stamp, method="auto")
            bounds = stamp.bounds & canvas.bounds
            if bounds.isDefined():
                canvas[bounds] += stamp[bounds]
        charge += canvas.array
    charge = rng.poisson(np.clip(charge, 0, None)).astype(np.float64)
    charge += rng.normal(0, instrument.read_noise_e, charge.shape)
    _bleed(charge, instrument.full_well_e)
    adu = np.round(charge / instrument.gain + instrument.pedestal_adu)
    adu = np.clip(adu, 0, 65535)
    if border == "nan":
        adu = adu.astype(np.float32)
        adu[:20] = adu[-20:] = np.nan
        adu[:, :20] = adu[:, -20:] = np.nan
        return adu, truths
    adu = adu.astype(np.int32)
    if border == "zero":
        adu[:20] = adu[-20:] = 0
        adu[:, :20] = adu[:, -20:] = 0
    return adu, truths


def four_streaks(instrument, snr=30.0, seed=0):
    """The four-streak scene: three parallel streaks 100 and 150 px apart (250 px span, or
    scaled down to fit a small image) and one crossing them at 60 deg.

    Returns
    -------
    list of (angle_deg, x, y, peak_snr)
    """
    ny, nx = instrument.shape
    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(-60, 60))
    span = min(1.0, 0.6 * min(nx, ny) / 250)
    cx, cy = nx / 2 + rng.uniform(-10, 10), ny / 2 + rng.uniform(-10, 10)
    a = np.radians(angle)
    nxv, nyv = -np.sin(a), np.cos(a)
    out = []
    for off in (-130 * span, -30 * span, 120 * span):
        out.append((angle, cx + off * nxv, cy + off * nyv, snr))
    cross = angle + 60 if angle + 60 <= 90 else angle - 120
    out.append((cross, cx + rng.uniform(-20, 20), cy + rng.uniform(-20, 20), snr))
    return out


def located(streak, truth, max_px=1.0, max_deg=0.2):
    """Whether a found streak (a dict with ``angle_deg, x0, y0, x1, y1``) lies on a true one:
    both of its ends within ``max_px`` of the true line and its angle within ``max_deg``."""
    da = abs((streak["angle_deg"] - truth.angle_deg + 90) % 180 - 90)
    ends = max(abs(truth.offset_of(streak[f"x{k}"], streak[f"y{k}"])) for k in (0, 1))
    return bool(ends < max_px and da < max_deg)


def match(found, truths, max_px=5.0, max_deg=0.5):
    """Index of the found streak nearest each true one (within ``max_deg`` and ``max_px`` of
    it at the found segment's middle), or None; each found streak matches one truth at most.
    """
    used, out = set(), []
    for t in truths:
        best = None
        for j, s in enumerate(found):
            if j in used:
                continue
            da = abs((s["angle_deg"] - t.angle_deg + 90) % 180 - 90)
            off = abs(t.offset_of(0.5 * (s["x0"] + s["x1"]), 0.5 * (s["y0"] + s["y1"])))
            if da <= max_deg and off <= max_px and (best is None or off < best[1]):
                best = (j, off)
        out.append(None if best is None else best[0])
        if best is not None:
            used.add(best[0])
    return out


def masked_fraction(shape, streaks, truth):
    """Fraction of the pixels on a true line (within 0.5 px of it) that the masks of the
    found ``streaks`` cover."""
    from inject.masking.geometry import Line
    from inject.masking.mask import mask_spans, paint

    plane = np.zeros(shape, dtype=bool)
    for s in streaks:
        paint(plane, mask_spans(shape, Line(s["x0"], s["y0"], s["x1"], s["y1"]),
                                s["mask_width_px"]))
    ny, nx = shape
    a = np.radians(truth.angle_deg)
    yy, xx = np.mgrid[0:ny, 0:nx]
    on = np.abs(-(xx - truth.x) * np.sin(a) + (yy - truth.y) * np.cos(a)) <= 0.5
    return float(plane[on].mean()) if on.any() else float("nan")
