"""Field stars: Bahcall & Soneira counts, random star fields, catalogs and fast PSF drawing.

Star counts come from the analytic fit of Bahcall & Soneira (1980, ApJS 44, 73, appendix B,
eq. B1) to their Galaxy model: cumulative counts ``N(<V)`` per deg^2 at galactic ``(l, b)``,
quoted as good to ~15% for ``|b| >= 20 deg``. No download is needed.

Stars are drawn with one shared, in-focus PSF, so they are never drawn one by one with GalSim:
the pixel-convolved PSF is sampled once from its Fourier transform for every sub-pixel phase
on a ``(N + 1) x (N + 1)`` grid (:class:`PsfStamps`); each star gets the bilinear
interpolation of the four phases around its position, scaled by its flux, added into the
image with clipping at the edges. Pixel ``(0, 0)`` is the centre of the first pixel (as in
:mod:`inject.trajectory`), ``x`` along columns and ``y`` along rows.
"""
import functools
import os
from dataclasses import dataclass
from pathlib import Path

import galsim
import numpy as np

from inject.errors import FileFormatError, InputError, SceneError
from inject.instrument import LSST
from inject.photometry import band as _band
from inject.photometry import electron_rate
from inject.profile import GSPARAMS, Seeing
from inject.skytiles import sky_stars
from inject.validate import finite, positive

# -------------------------------------------------------------------------------------------
# Bahcall & Soneira (1980) appendix B, eq. B1: cumulative V counts per deg^2.
# N(<m) = C1 10^(beta (m - m*)) / [1 + 10^(alpha (m - m*))]^delta
#             / [sin b (1 - mu cot b cos l)]^(3 - 5 gamma)                 (disk)
#       + C2 10^(eta (m - m+)) / [1 + 10^(kappa (m - m+))]^lambda
#             / (1 - cos b cos l)^sigma                                    (spheroid)
# with mu, gamma linear in m between V = 12 and 20 and sigma = 1.45 - 0.20 cos b cos l.

#: Parameters of eq. B1 for the integral counts in V.
BS80 = {"C1": 925.0, "alpha": -0.132, "beta": 0.035, "delta": 3.0, "mstar": 15.75,
        "C2": 1050.0, "kappa": -0.180, "eta": 0.087, "lam": 2.5, "mdagger": 17.5}

#: Lowest |b| (deg) where the fit is used: it is singular at the plane (sin b -> 0).
MIN_LATITUDE_DEG = 20.0


def cumulative_counts(v_mag, l_deg, b_deg):
    """Stars per deg^2 brighter than ``v_mag`` (Bahcall & Soneira 1980, eq. B1).

    Parameters
    ----------
    v_mag : float or array_like
        Limiting V magnitude(s).
    l_deg, b_deg : float or array_like
        Galactic longitude and latitude, deg (broadcast against ``v_mag``). The fit holds for
        ``|b| >= 20 deg`` and is symmetric in ``b``.

    Returns
    -------
    ndarray or float
        ``N(<V)`` per deg^2; e.g. 1440 at ``V = 20``, ``b = 90`` and 5190 at ``b = 30``,
        ``l = 90``.

    Raises
    ------
    InputError
        If an input is not finite or ``|b| < 20 deg``.
    """
    m = finite("v_mag", v_mag)
    l_rad = np.radians(finite("galactic_l", l_deg))
    b_abs = np.abs(finite("galactic_b", b_deg))
    if np.any(b_abs > 90):
        raise InputError("galactic_b", b_deg, "must be in [-90, 90]")
    if np.any(b_abs < MIN_LATITUDE_DEG):
        raise InputError("galactic_b", b_deg,
                         f"the Bahcall & Soneira fit needs |b| >= {MIN_LATITUDE_DEG:g} deg; "
                         "give density_per_deg2 or a catalog instead")
    b_rad = np.radians(b_abs)
    p = BS80
    # mu and gamma run linearly from their V = 12 to their V = 20 values, constant outside.
    dm12 = np.clip(m - 12.0, 0.0, 8.0)
    mu = 0.03 + 0.0075 * dm12
    gamma = 0.36 - 0.04 * dm12
    cos_l, sin_b, cos_b = np.cos(l_rad), np.sin(b_rad), np.cos(b_rad)
    sigma = 1.45 - 0.20 * cos_b * cos_l
    x1 = m - p["mstar"]
    disk = (p["C1"] * 10.0 ** (p["beta"] * x1) / (1.0 + 10.0 ** (p["alpha"] * x1)) ** p["delta"]
            / (sin_b - mu * cos_b * cos_l) ** (3.0 - 5.0 * gamma))
    x2 = m - p["mdagger"]
    spheroid = (p["C2"] * 10.0 ** (p["eta"] * x2) / (1.0 + 10.0 ** (p["kappa"] * x2)) ** p["lam"]
                / (1.0 - cos_b * cos_l) ** sigma)
    out = disk + spheroid
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class StarFieldSpec:
    """What stars to put in a field.

    Parameters
    ----------
    galactic_l, galactic_b : float
        Galactic coordinates of the field, deg.
    mag_limit : float
        Faintest magnitude drawn.
    mag_bright : float
        Brightest magnitude drawn (brighter stars saturate an LSSTCam CCD in 15-30 s and are
        left out).
    density_per_deg2 : float, optional
        Stars per deg^2 brighter than ``mag_limit``, replacing the model's ``N(<mag_limit)``:
        the model curve at ``(l, b)`` is scaled by this factor, so the magnitude distribution
        keeps its shape. Below ``|b| = 20 deg`` the shape of ``|b| = 20 deg`` is used.
    catalog : str or os.PathLike, optional
        A star list to use instead of random stars (see :func:`read_catalog`).
    """

    galactic_l: float = 90.0
    galactic_b: float = 90.0
    mag_limit: float = 24.0
    mag_bright: float = 12.0
    density_per_deg2: float | None = None
    catalog: str | os.PathLike | None = None

    def __post_init__(self):
        finite("galactic_l", self.galactic_l)
        b = float(finite("galactic_b", self.galactic_b))
        if abs(b) > 90:
            raise InputError("galactic_b", self.galactic_b, "must be in [-90, 90]")
        finite("mag_limit", self.mag_limit)
        finite("mag_bright", self.mag_bright)
        if not self.mag_bright < self.mag_limit:
            raise InputError("mag_bright", self.mag_bright,
                             f"must be < mag_limit ({self.mag_limit})")
        if self.density_per_deg2 is not None:
            positive("density_per_deg2", self.density_per_deg2)
        elif self.catalog is None and abs(b) < MIN_LATITUDE_DEG:
            raise InputError("galactic_b", self.galactic_b,
                             f"the Bahcall & Soneira fit needs |b| >= {MIN_LATITUDE_DEG:g} "
                             "deg; give density_per_deg2 or a catalog instead")

    def counts(self, mag):
        """Stars per deg^2 brighter than ``mag`` in this field (model, or scaled model)."""
        b = float(self.galactic_b)
        if abs(b) < MIN_LATITUDE_DEG:  # only reached with a density override
            b = float(np.copysign(MIN_LATITUDE_DEG, b))
        n = cumulative_counts(mag, self.galactic_l, b)
        if self.density_per_deg2 is not None:
            n = n * (self.density_per_deg2
                     / cumulative_counts(self.mag_limit, self.galactic_l, b))
        return n


def sample_stars(spec, area_deg2, band, rng):
    """Random star magnitudes over ``area_deg2`` between ``spec.mag_bright`` and ``mag_limit``.

    The number of stars is Poisson with mean ``area * (N(<mag_limit) - N(<mag_bright))`` and
    the magnitudes follow ``dN/dm`` by inverse-transform sampling of the tabulated cumulative
    counts (0.001 mag steps). The V magnitude of the model is used as the magnitude in
    ``band``: there are no colour terms.

    Parameters
    ----------
    spec : StarFieldSpec
    area_deg2 : float
        Sky area, deg^2.
    band : str
        LSST band name (checked; no colour terms are applied).
    rng : numpy.random.Generator
        E.g. ``inject.scene.rng(seed, "stars")``.

    Returns
    -------
    ndarray
        Magnitudes, float64, in random order.
    """
    _band(band)
    area = float(positive("area_deg2", area_deg2))
    grid, cdf = _cumulative_counts_grid(spec)
    n = rng.poisson(area * cdf[-1])
    # N(<m) increases strictly with m, so interpolating the inverse is well posed.
    return np.interp(rng.uniform(0.0, cdf[-1], n), cdf, grid)


@functools.lru_cache(maxsize=16)
def _cumulative_counts_grid(spec):
    """Magnitudes every 0.001 mag from ``mag_bright`` to ``mag_limit`` and the counts per
    deg^2 brighter than each, less those brighter than ``mag_bright`` (read-only; once per
    spec: a focal plane samples its ~100 star tiles from one field's counts)."""
    grid = np.linspace(spec.mag_bright, spec.mag_limit,
                       int(np.ceil((spec.mag_limit - spec.mag_bright) / 1e-3)) + 1)
    cdf = spec.counts(grid)
    cdf = cdf - cdf[0]
    grid.flags.writeable = cdf.flags.writeable = False
    return grid, cdf


def star_field(spec, shape, pixel_scale, band, rng, *, margin_px=0.0, wcs=None):
    """Stars over an image: random ones from the counts, or those of ``spec.catalog``.

    Random stars are uniform over the image plus ``margin_px`` on each side (stars just off
    the edge still put light on it), with ``x`` in ``[-0.5 - margin, nx - 0.5 + margin)``.

    Parameters
    ----------
    spec : StarFieldSpec
    shape : tuple of int
        ``(ny, nx)``.
    pixel_scale : float
        Arcsec per pixel.
    band : str
    rng : numpy.random.Generator
    margin_px : float, optional
    wcs : astropy.wcs.WCS, optional
        Needed only for a catalog given in ra, dec.

    Returns
    -------
    dict
        ``x``, ``y`` (pixels, 0-based) and ``mag`` arrays of equal length.
    """
    if spec.catalog is not None:
        return read_catalog(spec.catalog, wcs)
    ny, nx = (int(v) for v in shape)
    if ny <= 0 or nx <= 0:
        raise InputError("shape", shape, "must be two positive integers (ny, nx)")
    p = float(positive("pixel_scale", pixel_scale))
    margin = float(finite("margin_px", margin_px))
    if margin < 0:
        raise InputError("margin_px", margin_px, "must be >= 0")
    w, h = nx + 2 * margin, ny + 2 * margin
    mag = sample_stars(spec, w * h * (p / 3600.0) ** 2, band, rng)
    x = rng.uniform(-0.5 - margin, nx - 0.5 + margin, mag.size)
    y = rng.uniform(-0.5 - margin, ny - 0.5 + margin, mag.size)
    return {"x": x, "y": y, "mag": mag}


# -------------------------------------------------------------------------------------------
# Catalogs

_FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz", ".fts.gz")


def read_catalog(path, wcs=None):
    """Read a star list: columns ``x, y, mag`` (pixels) or ``ra, dec, mag`` (deg).

    Column names are case-insensitive; if both are present, ``x, y`` win. Pixel coordinates
    are 0-based with ``(0, 0)`` at the centre of the first pixel; ``ra, dec`` go through
    ``wcs.world_to_pixel_values``, which uses the same convention.

    Parameters
    ----------
    path : str or os.PathLike
        A CSV file (header row with the column names) or a FITS binary table (the first
        table HDU).
    wcs : astropy.wcs.WCS, optional
        Celestial WCS of the image; required for ``ra, dec``.

    Returns
    -------
    dict
        ``x``, ``y``, ``mag`` as float64 arrays.

    Raises
    ------
    FileFormatError
        If the file is missing or unreadable, lacks the columns, or has non-numeric or
        non-finite values.
    InputError
        If the catalog is in ``ra, dec`` and no ``wcs`` is given.
    """
    from astropy.table import Table  # astropy.table is slow to import; only catalogs need it

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"star catalog {str(path)!r}: no such file")
    is_fits = path.name.lower().endswith(_FITS_SUFFIXES) or _looks_like_fits(path)
    kind = "FITS table" if is_fits else "CSV file"
    try:
        table = Table.read(path, format="fits" if is_fits else "ascii.csv")
    except Exception as exc:  # astropy raises many kinds for malformed files
        raise FileFormatError(f"star catalog {str(path)!r}: cannot read it as a {kind} "
                              f"({type(exc).__name__}: {exc})") from None
    names = {name.lower(): name for name in table.colnames}
    if {"x", "y", "mag"} <= names.keys():
        x = _column(table, names["x"], path)
        y = _column(table, names["y"], path)
    elif {"ra", "dec", "mag"} <= names.keys():
        if wcs is None:
            raise InputError("wcs", None, f"star catalog {str(path)!r} gives ra, dec: "
                             "an image WCS is needed to place the stars")
        if not hasattr(wcs, "world_to_pixel_values"):
            raise InputError("wcs", wcs, "must be an astropy WCS")
        ra = _column(table, names["ra"], path, unit="deg")
        dec = _column(table, names["dec"], path, unit="deg")
        celestial = wcs.celestial if getattr(wcs, "has_celestial", False) else wcs
        x, y = (np.asarray(v, dtype=np.float64)
                for v in celestial.world_to_pixel_values(ra, dec))
    else:
        raise FileFormatError(
            f"star catalog {str(path)!r}: needs columns x, y, mag (pixels) or ra, dec, mag "
            f"(deg); found {', '.join(table.colnames) or 'no columns'}")
    mag = _column(table, names["mag"], path)
    return {"x": x, "y": y, "mag": mag}


def _looks_like_fits(path):
    with open(path, "rb") as f:
        return f.read(9) == b"SIMPLE  ="


def _column(table, name, path, unit=None):
    """A table column as finite float64 values (converted to ``unit`` if it has a unit)."""
    col = table[name]
    try:
        if unit is not None and col.unit is not None:
            values = col.quantity.to_value(unit)
        else:
            values = np.ma.filled(np.ma.asarray(col, dtype=np.float64), np.nan)
    except Exception:  # strings, incompatible units
        raise FileFormatError(f"star catalog {str(path)!r}: column {name!r} must be numeric"
                              + (f" in {unit}" if unit else "")) from None
    values = np.asarray(values, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        rows = ", ".join(str(i + 1) for i in bad[:5]) + (", ..." if bad.size > 5 else "")
        raise FileFormatError(f"star catalog {str(path)!r}: column {name!r} has missing or "
                              f"non-finite values in data row(s) {rows}")
    return values


# -------------------------------------------------------------------------------------------
# Drawing

#: Phases per pixel of the ring that bright stars add outside the core stamp. The PSF is
#: smooth there (r >~ 9" for 0.67" seeing), so the nearest of these phases (<= 1/4 px off)
#: is within ~2% of the local value, itself ~1e-7 of the flux per pixel.
_RING_OVERSAMPLE = 2


class PsfStamps:
    """Pixel-convolved PSF stamps on a grid of sub-pixel phases, sized from the PSF.

    Stamps are ``(2h + 1)^2`` pixels around ``floor(x), floor(y)``; the half size ``h`` is
    the smallest for which the flux outside the stamp is below a tolerance for a star
    anywhere in its pixel: ``faint_tolerance`` for the core stamps used by every star and
    ``bright_tolerance`` for the larger stamps of bright stars, which add a ring (the large
    stamp with the core box zeroed, at the nearest half-pixel phase) to their core stamp.

    Parameters
    ----------
    psf : galsim.GSObject
        The PSF in arcsec, centred at the origin; it is normalised to unit flux.
    pixel_scale : float
        Arcsec per pixel.
    oversample : int
        Phases per pixel ``N`` along each axis of the core stamps (``N + 1`` stamps per axis,
        both ends included, so interpolation needs no wrap-around).
    faint_tolerance, bright_tolerance : float
        Largest fraction of a star's flux that may fall outside its stamp.
    max_half_size : int
        Cap on ``h``; if a tolerance cannot be met within it, the lost fraction is recorded
        in :attr:`core_lost` / :attr:`bright_lost`.

    Attributes
    ----------
    core_half, bright_half : int
        Half sizes ``h`` of the core and bright stamps.
    core_lost, bright_lost : float
        Largest fraction of flux outside the stamp over sub-pixel positions.
    core : ndarray
        ``(N + 1, N + 1, 2 h + 1, 2 h + 1)``: ``core[j, i]`` is the stamp of a star at
        ``(floor(x) + i / N, floor(y) + j / N)``.
    ring : ndarray
        The same for the bright stamps at 2 phases per pixel, zero inside the core box.
    """

    def __init__(self, psf, pixel_scale, oversample=16, faint_tolerance=1e-3,
                 bright_tolerance=1e-4, max_half_size=512):
        self.pixel_scale = float(positive("pixel_scale", pixel_scale))
        if int(oversample) != oversample or oversample < 1:
            raise InputError("oversample", oversample, "must be an integer >= 1")
        self.oversample = int(oversample)
        positive("faint_tolerance", faint_tolerance)
        positive("bright_tolerance", bright_tolerance)
        if not isinstance(psf, galsim.GSObject):
            raise InputError("psf", psf, "must be a GalSim profile (galsim.GSObject)")
        if not psf.flux > 0:
            raise InputError("psf", psf, "must have a positive flux")
        # Stamps are drawn once, so draw them at least as accurately as the project's profiles:
        # GalSim's default folding_threshold (5e-3) aliases that much flux into a stamp.
        self.psf = psf.withFlux(1.0).withGSParams(
            galsim.GSParams.combine([psf.gsparams, GSPARAMS]))
        lost = self._lost_by_half_size(min(bright_tolerance, faint_tolerance), max_half_size)
        self.core_half, self.core_lost = _half_size(lost, faint_tolerance)
        self.bright_half, self.bright_lost = _half_size(lost, bright_tolerance)
        self.bright_half = max(self.bright_half, self.core_half)
        self.core = self._phase_stamps(self.core_half, self.oversample)
        self.core_sums = self.core.sum(axis=(2, 3))
        self.ring = self._phase_stamps(self.bright_half, _RING_OVERSAMPLE, period=1.5)
        c = self.bright_half - self.core_half
        self.ring[:, :, c:self.ring.shape[2] - c, c:self.ring.shape[3] - c] = 0.0
        self.ring_sums = self.ring.sum(axis=(2, 3))

    def _lost_by_half_size(self, tolerance, max_half):
        """``lost[h]``: flux outside the centred ``(2h + 1)^2`` box, grown until < tolerance."""
        half = min(max_half, max(32, self.psf.getGoodImageSize(self.pixel_scale)))
        while True:
            n = 2 * half + 1
            image = self.psf.drawImage(nx=n, ny=n, scale=self.pixel_scale, method="auto",
                                       dtype=np.float64).array
            k = np.abs(np.arange(n) - half)
            ring = np.maximum.outer(k, k)  # Chebyshev distance: the square box index
            lost = 1.0 - np.cumsum(np.bincount(ring.ravel(), image.ravel(), minlength=half + 1))
            if lost[-1] < tolerance or half >= max_half:
                return lost
            half = min(max_half, 2 * half)

    def _phase_stamps(self, half, oversample, period=2.0):
        """Stamps ``[j, i]`` of a star at ``(i / N, j / N)`` pixels from ``floor(x, y)``.

        Each phase is summed from the PSF's Fourier transform: ``psf``'s k-image out to its
        ``maxk``, times the pixel's sinc and the phase's shift, folded onto the pixel grid's
        band (exact sampling) and inverse-FFT'd with a period of ``period`` times the stamp:
        twice for the core, where the aliased wings then add ~1e-8 of the flux per pixel, and
        1.5 for the ring, whose stamp already holds all but 1e-4 of the flux. That is what
        drawImage(method="auto", offset=...) does, but with one k-image for all phases and
        a period set by the stamp (GalSim's would be ~80" for a 0.67" Kolmogorov at
        folding_threshold 1e-4: an 8192^2 FFT at 1/16 pixel).
        """
        p = self.pixel_scale
        size = 2 * half + 1
        n = galsim.Image.good_fft_size(int(np.ceil(period * (size + 1))))  # the period, px
        dk = 2.0 * np.pi / (n * p)
        nk = int(np.ceil(self.psf.maxk / dk))
        k = dk * np.arange(-nk, nk + 1)
        sinc = np.sinc(k * p / (2.0 * np.pi))  # the pixel (a box of width p)
        kimage = self.psf.drawKImage(nx=2 * nk + 1, ny=2 * nk + 1, scale=dk).array
        kimage = kimage * sinc[:, None] * sinc[None, :]
        # Fold: k index m = r + q n (0 <= r < n) goes to block q, row r. On a padded axis
        # where m = -nk sits at index first = -nk mod n, block q holds [q n, (q + 1) n).
        first = (-nk) % n
        n_blocks = -(-(first + 2 * nk + 1) // n)
        q = np.arange(n_blocks) - (first + nk) // n
        n_half = n // 2 + 1  # irfft2 reads columns r <= n/2 only
        blocks = np.zeros((n_blocks, n, n_blocks, n_half), np.complex128)
        for by in range(n_blocks):
            (y0, y1), (ky0, ky1) = _overlap(by * n, (by + 1) * n, first, 2 * nk + 1)
            for bx in range(n_blocks):
                (x0, x1), (kx0, kx1) = _overlap(bx * n, bx * n + n_half, first, 2 * nk + 1)
                if y1 > y0 and x1 > x0:
                    blocks[by, y0:y1, bx, x0:x1] = kimage[ky0:ky1, kx0:kx1]
        # A star at +f has transform K(k) exp(-i k f p); for k = (r + q n) dk that is
        # exp(-i r dk f p) exp(-2 pi i q f): a ramp in r times a phase per alias block.
        f = np.arange(oversample + 1) / oversample
        alias = np.exp(-2j * np.pi * np.outer(f, q))               # (phase, block)
        r = np.arange(n)
        ramp_y = np.exp(-1j * np.outer(f, r) * dk * p)              # (phase, row)
        ramp_x = ramp_y[:, :n_half]
        # Pixel k of the stamp is sample k of the period, wrapped.
        idx = np.arange(-half, half + 1) % n
        stamps = np.empty((oversample + 1, oversample + 1, size, size))
        for j in range(oversample + 1):
            by_x = np.einsum("b,bycx->cyx", alias[j], blocks)       # fold in y
            folded = np.einsum("ic,cyx->iyx", alias, by_x)          # fold in x, each phase
            folded *= ramp_y[j][None, :, None] * ramp_x[:, None, :]
            # I(x) = (dk / 2 pi)^2 sum_k K e^{ikx}: with the inverse FFT's 1/n^2 and the
            # pixel area p^2, the factor is (n dk p / 2 pi)^2 = 1.
            # irfft2 in its two steps (as numpy does them), the real transform only for the
            # stamp's rows: the same numbers, for half the work.
            rows = np.fft.ifft(folded, n, axis=1)[:, idx]
            stamps[j] = np.fft.irfft(rows, n, axis=2)[:, :, idx]
        return stamps


def _overlap(start, stop, first, length):
    """Overlap of ``[start, stop)`` with ``[first, first + length)``, in both frames."""
    lo, hi = max(start, first), min(stop, first + length)
    return (lo - start, hi - start), (lo - first, hi - first)


def _half_size(lost, tolerance):
    """Smallest ``h`` whose stamp keeps all but ``tolerance`` for any sub-pixel position.

    A star at ``floor(x) + f``, ``0 <= f < 1``, is at least ``h - 1/2`` pixels from the
    edges of its stamp, so the stamp holds the centred box of half size ``h - 1``.
    """
    ok = np.flatnonzero(lost[:-1] < tolerance)
    h = int(ok[0]) + 1 if ok.size else len(lost) - 1
    h = max(h, 2)
    return h, float(max(lost[h - 1], 0.0))


@functools.lru_cache(maxsize=4)
def psf_stamps(psf, pixel_scale, oversample=16, faint_tolerance=1e-3, bright_tolerance=1e-4):
    """Cached :class:`PsfStamps` (GalSim profiles are immutable and hashable)."""
    return PsfStamps(psf, pixel_scale, oversample, faint_tolerance, bright_tolerance)


def _interpolate(stamps, oversample, fx, fy):
    """Bilinear interpolation between the four phases around fractional positions ``fx, fy``.

    Returns ``(n, S, S)`` stamps; the interpolation weights sum to one.
    """
    px, py = fx * oversample, fy * oversample
    i0 = np.minimum(px.astype(np.intp), oversample - 1)
    j0 = np.minimum(py.astype(np.intp), oversample - 1)
    t = (px - i0)[:, None, None]
    u = (py - j0)[:, None, None]
    low = stamps[j0, i0]
    low *= 1.0 - t
    low += t * stamps[j0, i0 + 1]
    high = stamps[j0 + 1, i0]
    high *= 1.0 - t
    high += t * stamps[j0 + 1, i0 + 1]
    low *= 1.0 - u
    high *= u
    low += high
    return low


def _interpolate_sums(sums, oversample, fx, fy):
    """The same interpolation applied to the stamps' totals (exact: it is linear)."""
    px, py = fx * oversample, fy * oversample
    i0 = np.minimum(px.astype(np.intp), oversample - 1)
    j0 = np.minimum(py.astype(np.intp), oversample - 1)
    t, u = px - i0, py - j0
    return ((1 - u) * ((1 - t) * sums[j0, i0] + t * sums[j0, i0 + 1])
            + u * ((1 - t) * sums[j0 + 1, i0] + t * sums[j0 + 1, i0 + 1]))


#: Stars per vectorised batch: small enough that a batch of stamps stays in cache.
_BATCH = 16


def draw_stars(image, x, y, fluxes_e, psf, pixel_scale, oversample=16, *,
               faint_tolerance=1e-3, bright_tolerance=1e-4, bright_flux_e=1e6,
               noise=None, variance=None):
    """Add point sources with a shared PSF to ``image`` (in place), without per-star GalSim.

    Each star's core stamp is the bilinear interpolation, in sub-pixel position, of the four
    nearest pre-drawn phases (``oversample`` per pixel), times its flux, added over the part
    inside the image; it holds all but ``faint_tolerance`` of the flux. Stars of at least
    ``bright_flux_e`` also get the ring out to the stamp size of ``bright_tolerance``.

    Parameters
    ----------
    image : ndarray
        2-D float array, ``(ny, nx)``, e-; modified in place. Sums are float64 (a float32
        image gets a float64 buffer added once at the end).
    x, y : array_like
        Star positions, pixels (0-based, pixel centres at integers).
    fluxes_e : array_like
        Star fluxes, e- (>= 0).
    psf : galsim.GSObject or PsfStamps
        Unit-flux PSF in arcsec (e.g. ``galsim.Kolmogorov(fwhm=0.67)``), or stamps already
        made; the stamps are cached per ``(psf, pixel_scale, oversample, tolerances)``.
    pixel_scale : float
        Arcsec per pixel.
    oversample : int
        Sub-pixel phases per pixel along each axis. 16 puts pixels within 5e-4 of the peak of
        an exact drawing (0.67" Kolmogorov, 0.2" pixels), 32 within 1.2e-4 (error ~ 1/N^2).
    faint_tolerance, bright_tolerance : float
        Largest fraction of flux outside the stamp of faint and bright stars.
    bright_flux_e : float
        Flux from which a star gets the bright stamp. The default, 1e6 e- (r ~ 17.3 in
        30 s), leaves the faint stamps' lost wings below ~0.1 e- per pixel.
    noise : numpy.random.Generator, optional
        Collect the stars' charge instead: each stamp pixel adds Poisson(its expected charge)
        to ``image`` (a sum of independent Poisson draws is Poisson of the summed mean, so
        overlapping stars, and a level drawn beforehand, give each pixel exactly Poisson of
        its total; a faint stamp is drawn photon by photon, see :func:`_collect`), and its
        expected charge to ``variance``. Only the stamps are touched: no image-sized buffer
        of expected charge. The draws follow the stars, so they depend on which stars and
        stamp pixels an image holds: a CCD's simulation instead adds the stars' expected
        charge to the streaks' and draws each pixel from its own block's stream
        (:class:`inject.scene.AmplifierNoise`), so that a cut-out gets the full CCD's counts.
    variance : ndarray, optional
        With ``noise``: the variance plane (same shape), modified in place.

    Returns
    -------
    ndarray
        Expected charge of each star that landed in the image, e- (its flux less what fell
        outside its stamp or off the image).
    """
    image = _check_image(image)
    x, y, flux = _check_stars(x, y, fluxes_e)
    stamps = psf if isinstance(psf, PsfStamps) else psf_stamps(
        psf, float(pixel_scale), int(oversample), float(faint_tolerance),
        float(bright_tolerance))
    target = None
    if noise is not None:
        if variance is None or np.shape(variance) != image.shape:
            raise InputError("variance", None if variance is None else np.shape(variance),
                             f"noise needs a variance plane of the image's shape {image.shape}")

        def add(region, expected):
            # A stamp's interpolated wings may dip a hair below zero: they collect nothing.
            expected = np.maximum(expected, 0.0)
            image[region] += _collect(noise, expected)  # integer counts: exact in float32
            variance[region] += expected
    else:
        target = image if image.dtype == np.float64 else np.zeros(image.shape)

        def add(region, expected):
            target[region] += expected
    drawn = np.zeros(flux.size)
    ix = np.floor(x).astype(np.intp)
    iy = np.floor(y).astype(np.intp)
    fx, fy = x - ix, y - iy

    n_core = stamps.oversample
    sel = _reaching(image.shape, ix, iy, stamps.core_half, flux > 0)
    for start in range(0, sel.size, _BATCH):
        idx = sel[start:start + _BATCH]
        batch = _interpolate(stamps.core, n_core, fx[idx], fy[idx])
        batch *= flux[idx][:, None, None]
        totals = _interpolate_sums(stamps.core_sums, n_core, fx[idx], fy[idx]) * flux[idx]
        drawn[idx] += _add_stamps(add, image.shape, batch, ix[idx], iy[idx],
                                   stamps.core_half, totals)

    # Bright stars: the ring at the nearest half-pixel phase (a view: no interpolation).
    sel = _reaching(image.shape, ix, iy, stamps.bright_half, flux >= bright_flux_e)
    i_near = np.rint(fx[sel] * _RING_OVERSAMPLE).astype(np.intp)
    j_near = np.rint(fy[sel] * _RING_OVERSAMPLE).astype(np.intp)
    for k, star in enumerate(sel):
        ring = stamps.ring[j_near[k], i_near[k]]
        total = stamps.ring_sums[j_near[k], i_near[k]] * flux[star]
        drawn[star] += _add_stamps(add, image.shape, (ring, flux[star]), ix[star:star + 1],
                                   iy[star:star + 1], stamps.bright_half, [total])[0]
    if target is not None and target is not image:
        image += target
    return drawn


#: A stamp whose expected charge is below this many e- per pixel on average collects it
#: photon by photon (:func:`_collect`); above it, pixel by pixel. The two cost the same at
#: ~0.2 e- per pixel (measured on 93 x 93 core stamps); faint stars' cores and bright
#: stars' far rings (~1e-3 of their flux over 359 x 359 pixels) are well below.
PHOTONS_PER_PIXEL_MAX = 0.1


def _collect(gen, expected):
    """Collected charge of a stamp of expected charge (>= 0): Poisson of each pixel's, as an
    int64 array of its shape.

    A faint stamp (under :data:`PHOTONS_PER_PIXEL_MAX` e- per pixel) is drawn as photons: a
    Poisson number with the stamp's total as its mean, each put in pixel ``i`` with
    probability ``expected_i / total``; a Poisson number of such multinomial photons gives
    each pixel an independent Poisson count of mean ``expected_i``, exactly the per-pixel
    draw, at the cost of the few photons instead of every pixel.
    """
    flat = expected.ravel()
    if flat.sum() >= PHOTONS_PER_PIXEL_MAX * flat.size:
        return gen.poisson(expected)
    cumulative = np.cumsum(flat)  # only faint stamps need it: not on the dense ones' path
    total = cumulative[-1]
    photons = gen.poisson(total)
    if not photons:
        return np.zeros(expected.shape, np.int64)
    pixel = np.searchsorted(cumulative, gen.random(photons) * total, side="right")
    # u * total can round up to total: such a photon belongs to the last lit pixel.
    np.minimum(pixel, np.flatnonzero(flat)[-1], out=pixel)
    return np.bincount(pixel, minlength=flat.size).reshape(expected.shape)


def _reaching(shape, ix, iy, half, wanted):
    """Indices of wanted stars whose ``(2 half + 1)^2`` stamp overlaps the image."""
    ny, nx = shape
    return np.flatnonzero(wanted & (ix + half >= 0) & (ix - half < nx)
                          & (iy + half >= 0) & (iy - half < ny))


def _add_stamps(add, shape, stamps, ix, iy, half, totals):
    """Add stamps centred on pixels ``(ix, iy)``, clipped to an image of ``shape``, by
    ``add(region, part)``; return the expected charge added by each.

    ``stamps`` is an ``(n, S, S)`` array, or one ``(stamp, scale)`` pair added as
    ``scale * stamp`` (saves copying a large shared stamp). ``totals`` are the stamps' sums,
    so only clipped stamps are summed. One slice addition per star: a stamp's rows are
    contiguous in the image, which beats a scatter with ``np.add.at`` over flattened indices
    ~3x (measured for 91^2 stamps).
    """
    ny, nx = shape
    size = 2 * half + 1
    x0, y0 = ix - half, iy - half
    xs, ys = np.maximum(x0, 0), np.maximum(y0, 0)
    xe, ye = np.minimum(x0 + size, nx), np.minimum(y0 + size, ny)
    clipped = (xs != x0) | (ys != y0) | (xe != x0 + size) | (ye != y0 + size)
    added = np.array(totals, dtype=np.float64)
    for k in range(len(ix)):
        rows = slice(ys[k] - y0[k], ye[k] - y0[k])
        cols = slice(xs[k] - x0[k], xe[k] - x0[k])
        if isinstance(stamps, tuple):
            part = stamps[0][rows, cols] * stamps[1]
        else:
            part = stamps[k, rows, cols]
        add(np.s_[ys[k]:ye[k], xs[k]:xe[k]], part)
        if clipped[k]:
            added[k] = part.sum()
    return added


def _check_image(image):
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise InputError("image", type(image).__name__, "must be a 2-D numpy array")
    if not np.issubdtype(image.dtype, np.floating):
        raise InputError("image", image.dtype, "must have a floating-point dtype")
    return image


def _check_stars(x, y, fluxes_e):
    x = np.atleast_1d(finite("x", x)).astype(np.float64)
    y = np.atleast_1d(finite("y", y)).astype(np.float64)
    flux = np.atleast_1d(finite("fluxes_e", fluxes_e)).astype(np.float64)
    if not (x.ndim == y.ndim == flux.ndim == 1 and x.shape == y.shape == flux.shape):
        raise InputError("x, y, fluxes_e", (x.shape, y.shape, flux.shape),
                         "must be 1-D arrays of the same length")
    if np.any(flux < 0):
        raise InputError("fluxes_e", fluxes_e, "must be >= 0")
    return x, y, flux


# -------------------------------------------------------------------------------------------
# Scene glue

#: Keys of a scene's ``stars:`` mapping (the fields of :class:`StarFieldSpec`).
SCENE_KEYS = ("galactic_l", "galactic_b", "mag_limit", "mag_bright", "density_per_deg2",
              "catalog")


def star_field_spec(entry, radec=None):
    """The :class:`StarFieldSpec` of a scene's ``stars:`` mapping (``{}`` for ``stars: true``).

    Galactic coordinates not given in the mapping come from ``radec`` (the scene's pointing,
    ICRS deg) when there is one, else from the :class:`StarFieldSpec` defaults.

    Raises
    ------
    SceneError
        An unknown key.
    InputError
        A value :class:`StarFieldSpec` refuses.
    """
    unknown = set(entry) - set(SCENE_KEYS)
    if unknown:
        raise SceneError(f"stars: unknown key(s) {', '.join(sorted(unknown))}; "
                         f"allowed: {', '.join(SCENE_KEYS)}")
    entry = dict(entry)
    if radec is not None and not {"galactic_l", "galactic_b"} & set(entry):
        l_deg, b_deg = _galactic(float(radec[0]), float(radec[1]))
        entry.update(galactic_l=l_deg, galactic_b=b_deg)
    return StarFieldSpec(**entry)


@functools.lru_cache(maxsize=64)
def _galactic(ra_deg, dec_deg):
    """Galactic ``(l, b)`` of an ICRS direction, deg (astropy; once per pointing, not once per
    CCD of a focal plane)."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    gal = SkyCoord(ra=ra_deg * u.deg, dec=dec_deg * u.deg).galactic
    return float(gal.l.deg), float(gal.b.deg)


def add_star_field(image, scene, rng, wcs=None, noise=None, variance=None, field_shape=None):
    """Add a scene's stars to ``image`` (expected charge, e-, in place; with ``noise``, the
    collected charge, and the expected charge to ``variance``: see :func:`draw_stars`).

    Stars are the scene's catalog, or random ones from the star counts:

    * with a celestial ``wcs``, the sky's stars (:func:`inject.skytiles.sky_stars`): those of
      the fixed RA/Dec tiles, each keyed on the scene's seed and the tile, that fall within
      the bright stars' stamp of the image, placed through the WCS. So the same sky gives the
      same stars at any rotation or pointing and on any detector: a CCD scene with a
      ``pointing`` and a focal-plane CCD share them;
    * without one, stars drawn per pixel area from ``rng`` over the image (:func:`star_field`,
      with a margin of one core stamp so stars just off the CCD still light its edge).

    The PSF is the scene's Kolmogorov seeing. Fluxes are ``electron_rate(mag, band) *
    exptime`` with the airmass-1 zero points and no further extinction, exactly as the
    satellites' fluxes (and the paper) are computed, so stars and streaks in a scene are on one
    photometric scale.

    Parameters
    ----------
    image : ndarray
        ``(ny, nx)`` float array; modified in place.
    scene : inject.config.Scene
    rng : numpy.random.Generator or None
        The scene's ``"stars"`` stream (unused with a celestial ``wcs`` or a catalog).
    wcs : astropy.wcs.WCS, optional
        The image's WCS: random stars from the sky when it has celestial axes; needed for
        catalogs in ra, dec.
    noise : numpy.random.Generator, optional
    variance : ndarray, optional
        See :func:`draw_stars`.
    field_shape : tuple of int, optional
        Without a celestial ``wcs``: ``(ny, nx)`` the random stars are drawn over, from pixel
        ``(0, 0)`` (default the image's): a cut-out passes its whole sensor's, and gets the
        whole CCD's stars. (The sky's stars are those that reach the image.)

    Returns
    -------
    dict
        ``x``, ``y``, ``mag``, ``flux_e`` and ``charge_in_image_e`` (expected) per star.
    """
    if scene.seeing <= 0:
        raise SceneError("stars: need seeing > 0 (stars share the atmospheric PSF)")
    spec = scene.stars
    pixel_scale = LSST.pixel_scale_arcsec
    stamps = psf_stamps(Seeing(scene.seeing).profile(), pixel_scale)
    sky = None if spec.catalog is not None else _celestial(wcs)
    if sky is not None:
        # The stars whose bright stamp reaches the image (a pixel's slack for the stamp's
        # centre): a cut-out's are those of the sky that reach it, whatever the whole sensor.
        field = sky_stars(spec, sky, image.shape, stamps.bright_half + 1, scene.band,
                          scene.seed, sample_stars)
    else:
        field = star_field(spec, image.shape if field_shape is None else field_shape,
                           pixel_scale, scene.band, rng, margin_px=stamps.core_half, wcs=wcs)
    flux = electron_rate(field["mag"], scene.band) * scene.exptime
    drawn = draw_stars(image, field["x"], field["y"], flux, stamps, pixel_scale, noise=noise,
                       variance=variance)
    return {**field, "flux_e": flux, "charge_in_image_e": drawn}


def _celestial(wcs):
    """The celestial part of a WCS (itself when it has only those two axes), or None."""
    if wcs is None or not getattr(wcs, "has_celestial", False):
        return None
    return wcs if wcs.naxis == 2 and wcs.wcs.lng == 0 else wcs.celestial
