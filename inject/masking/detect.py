"""Streak detection that works on realistic CCD images.

The search runs on a binned copy of the image, where a streak a few pixels wide becomes a thin
line and a full CCD costs milliseconds per transform:

1. **Background**: sigma-clipped medians in boxes of :data:`BACKGROUND_BOX` pixels, a 3 x 3
   median filter over the boxes (a bright star or streak cannot pull one box), bilinear
   interpolation between box centres.
2. **Binning** :data:`BIN` x :data:`BIN` (mean of the usable pixels), in units of the binned
   noise.
3. **Star suppression**: connected regions above :data:`STAR_LOW_SIGMA` that reach
   :data:`STAR_SIGMA` and are compact (short, or round) are set to zero with a margin growing
   with their peak; a streak is a long, thin region and survives. What is left is clipped to +-:data:`CLIP_SIGMA`, so that no faint
   star, cosmic ray or bright streak dominates a line sum.
4. **Matched filter**: Gaussian smoothing at the widths :data:`FILTER_SIGMAS` (binned pixels).
   Smoothing a line isotropically is the same as smoothing its cross-section, so this is the
   matched filter across the track, whatever the angle; the transform does the sum along it.
5. **Fast Hough transform** (OpenCV ``ximgproc``): every line sum, divided by the square root
   of its pixel count and standardised per angle (median and interquartile range over
   offsets), is a significance ``z`` with unit noise.
6. **Peaks**: the best ``z`` over widths is compared with :data:`FALSE_ALARM_Z`. Above it, the
   line is refined and its extent found (:mod:`.measure`), the streak is erased from the
   binned image, and the search repeats, so several streaks are found one after the other.
"""
import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from . import MaskingError
from .geometry import Line, band_pixels

#: Binning factor of the search image (4: a 7-10 px wide LSSTCam streak is ~2 binned px).
BIN = 4

#: Background box size, image pixels. Large compared with a streak's width so that a box's
#: clipped median is not pulled by it; small compared with a CCD so sky gradients are followed.
BACKGROUND_BOX = 256

#: Gaussian matched-filter widths (sigma, binned pixels): streak FWHMs of ~7, 13 and 26 image
#: pixels (1.3", 2.6" and 5.3" at 0.2"/px), from far orbits to low ones near zenith. Adjacent
#: widths differ by a factor of 2, which costs at most ~6% of the matched-filter S/N.
FILTER_SIGMAS = (0.7, 1.4, 2.8)

#: Connected regions above :data:`STAR_LOW_SIGMA` (binned-noise sigma) that reach
#: :data:`STAR_SIGMA` are star candidates.
STAR_SIGMA = 5.0
STAR_LOW_SIGMA = 2.5

#: The binned image is clipped at +-this many sigma before the transform.
CLIP_SIGMA = 3.0

#: A region whose major axis is shorter than this (binned px), or whose axis ratio is below
#: :data:`STAR_AXIS_RATIO`, is compact: a star, a galaxy or a cosmic ray, not a streak. The
#: ratio allows for a star cut by the image edge (a half disk is 1.9 times longer than wide)
#: and for two overlapping stars (up to 2).
STAR_MAX_LENGTH = 6.0
STAR_AXIS_RATIO = 3.0

#: Hough cells summing fewer binned pixels than this are ignored (short corner lines carry
#: little signal and their noise is far from Gaussian).
MIN_LINE_BINNED = 32

#: False-alarm threshold on the Hough significance ``z`` (see the module docstring).
#:
#: How it was obtained: ``scripts/bench_mask.py --calibrate`` runs :func:`detect_streaks` with
#: no threshold on streak-free simulated ITL images (g band, 30 s, dark sky at zenith 70 deg,
#: 0.67" seeing, Poisson and read noise, stars to mag 24 where :mod:`inject.stars` provides
#: them) and records the largest ``z`` of each image. Over 40 full 4072 x 4000 CCDs (seeds
#: 1-40) and 100 1024 x 1024 cut-outs (seeds 1-100) the largest value was 5.83 (full CCD; the
#: 99th percentile 5.71; cut-outs: 5.36 max). The threshold adds a margin of 0.5 to the largest
#: value, so a false alarm needs a noise excursion well beyond anything seen in 140 images.
FALSE_ALARM_Z = 6.3

#: Most streaks searched for in one image.
MAX_STREAKS = 8

#: Planes of an LSST-style mask whose pixels are not used (as LSST ``maskStreaks`` does).
BAD_PLANES = ("BAD", "SAT", "CR", "EDGE", "NO_DATA", "INTRP", "SUSPECT")

_FHT_OPTIONS = {}  # filled on first use: OpenCV constants


def _fht_options():
    # OpenCV 5 silently puts positional angleRange/op/makeSkew into the output argument:
    # always pass them by keyword.
    if not _FHT_OPTIONS:
        x = cv2.ximgproc
        _FHT_OPTIONS.update(angleRange=x.ARO_315_135, makeSkew=x.HDO_DESKEW)
    return _FHT_OPTIONS


def fast_hough(image):
    """Fast Hough transform (sums along all digital lines) of a float image.

    Rows of the result run over angles (all 180 deg), columns over offsets.
    """
    return cv2.ximgproc.FastHoughTransform(np.ascontiguousarray(image, dtype=np.float32),
                                           cv2.CV_32F, op=cv2.ximgproc.FHT_ADD,
                                           **_fht_options())


@dataclass
class Prepared:
    """An image made ready for the search and for measurements.

    Attributes
    ----------
    residual : ndarray
        Image minus background, float32, NaN where a pixel is not usable.
    sigma : float
        Robust per-pixel noise of ``residual`` (image units).
    stars : ndarray
        Bool, pixels of compact bright sources (excluded from measurements).
    binned : ndarray
        Binned residual in units of its own noise, stars removed, clipped (the search image).
    bin : int
        Binning factor.
    """

    residual: np.ndarray
    sigma: float
    stars: np.ndarray
    binned: np.ndarray
    bin: int

    @property
    def shape(self):
        return self.residual.shape

    def to_binned(self, line):
        """The same line in binned-pixel coordinates."""
        b, o = self.bin, (self.bin - 1) / 2
        return Line((line.x0 - o) / b, (line.y0 - o) / b, (line.x1 - o) / b, (line.y1 - o) / b)

    def from_binned(self, x, y):
        """Image-pixel coordinates of binned-pixel coordinates."""
        return self.bin * np.asarray(x, float) + (self.bin - 1) / 2, \
            self.bin * np.asarray(y, float) + (self.bin - 1) / 2


def robust_sigma(values):
    """Gaussian-equivalent standard deviation from the median absolute deviation."""
    values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def _bin(image, valid, factor):
    ny, nx = (n // factor * factor for n in image.shape)
    shape = (ny // factor, factor, nx // factor, factor)
    total = image[:ny, :nx].reshape(shape).sum(axis=(1, 3), dtype=np.float64)
    count = valid[:ny, :nx].reshape(shape).sum(axis=(1, 3))
    out = np.full(count.shape, np.nan, dtype=np.float32)
    np.divide(total, count, out=out, where=count > 0, casting="unsafe")
    return out


def _box_medians(binned, box):
    """Sigma-clipped median of each ``box x box`` block of a binned image (NaN = unusable)."""
    ny, nx = binned.shape
    gy, gx = max(1, round(ny / box)), max(1, round(nx / box))
    by, bx = -(-ny // gy), -(-nx // gx)
    padded = np.full((gy * by, gx * bx), np.nan, dtype=np.float32)
    padded[:ny, :nx] = binned
    blocks = padded.reshape(gy, by, gx, bx).transpose(0, 2, 1, 3).reshape(gy, gx, by * bx)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN boxes: filled below
        med = np.nanmedian(blocks, axis=2)
        for _ in range(2):
            spread = 1.4826 * np.nanmedian(np.abs(blocks - med[..., None]), axis=2)
            clipped = np.where(np.abs(blocks - med[..., None]) <= 3 * spread[..., None],
                               blocks, np.nan)
            med = np.nanmedian(clipped, axis=2)
    if np.all(np.isnan(med)):
        raise MaskingError("no usable pixels for the background")
    med[np.isnan(med)] = np.nanmedian(med)
    if gy >= 3 and gx >= 3:
        med = ndimage.median_filter(med, size=3, mode="nearest")
    # Box centres, binned pixels.
    return med, (np.arange(gy) + 0.5) * by - 0.5, (np.arange(gx) + 0.5) * bx - 0.5


def _interpolation_matrix(centres, positions):
    """Weights ``W`` such that ``W @ values`` interpolates linearly (flat beyond the ends)."""
    eye = np.eye(len(centres))
    return np.stack([np.interp(positions, centres, col) for col in eye], axis=1)


def _background(grid, cy, cx, ys, xs):
    """Bilinear interpolation of a box grid at the rows ``ys`` and columns ``xs``."""
    return (_interpolation_matrix(cy, ys) @ grid @ _interpolation_matrix(cx, xs).T)


def _star_mask(z):
    """Compact sources in a significance image: regions above :data:`STAR_LOW_SIGMA` holding a
    pixel above :data:`STAR_SIGMA` (hysteresis: a streak of moderate brightness stays one long
    region instead of breaking into compact fragments), with margins growing with their
    peak."""
    zp = z
    labels, n = ndimage.label(zp > STAR_LOW_SIGMA, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros(z.shape, dtype=bool)
    yy, xx = np.nonzero(labels)
    lab = labels[yy, xx]
    peak = np.zeros(n + 1)
    np.maximum.at(peak, lab, zp[yy, xx])
    bright = peak > STAR_SIGMA
    bright[0] = False
    keep = bright[lab]
    yy, xx, lab = yy[keep], xx[keep], lab[keep]
    count = np.maximum(np.bincount(lab, minlength=n + 1), 1).astype(float)
    mean_x = np.bincount(lab, xx, n + 1) / count
    mean_y = np.bincount(lab, yy, n + 1) / count
    dx, dy = xx - mean_x[lab], yy - mean_y[lab]
    # 1/12 px^2: a pixel's own extent, so single pixels have a non-zero size.
    cxx = np.bincount(lab, dx * dx, n + 1) / count + 1 / 12
    cyy = np.bincount(lab, dy * dy, n + 1) / count + 1 / 12
    cxy = np.bincount(lab, dx * dy, n + 1) / count
    root = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy ** 2)
    major = np.sqrt(0.5 * (cxx + cyy) + root)
    minor = np.sqrt(np.maximum(0.5 * (cxx + cyy) - root, 1 / 12))
    # A uniform bar of length L has an rms of L / sqrt(12) along it.
    compact = bright & ((np.sqrt(12) * major <= STAR_MAX_LENGTH)
                        | (major <= STAR_AXIS_RATIO * minor))
    # Margin grows with the peak: a bright star's wings stay above the noise further out.
    margin = np.clip(1 + np.round(2 * np.log10(np.maximum(peak, STAR_SIGMA) / STAR_SIGMA)),
                     1, 8).astype(int)
    stars = np.zeros(zp.shape, dtype=bool)
    for r in np.unique(margin[compact]):
        region = (compact & (margin == r))[labels].astype(np.uint8)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        stars |= cv2.dilate(region, kernel).astype(bool)
    return stars


def prepare(image, bad=None, bin_factor=BIN, box=BACKGROUND_BOX):
    """Background-subtract, bin and clean an image for the search.

    Parameters
    ----------
    image : array_like
        2-D image (any units; any byte order: it is copied to native float32, as OpenCV
        miscomputes on big-endian astropy arrays).
    bad : array_like of bool, optional
        Pixels not to use (e.g. SAT, BAD, CR planes of an LSST mask); non-finite pixels are
        never used.
    bin_factor : int
    box : int
        Background box size, image pixels.

    Returns
    -------
    Prepared

    Raises
    ------
    MaskingError
        If the image is not 2-D, is smaller than 16 binned pixels a side or has no usable
        pixels.
    """
    img = np.array(image, dtype=np.float32)
    if img.ndim != 2:
        raise MaskingError(f"image has {img.ndim} dimensions; need a 2-D image")
    if min(img.shape) < 16 * bin_factor:
        raise MaskingError(f"image {img.shape[1]} x {img.shape[0]} px is too small to search "
                           f"(needs >= {16 * bin_factor} px a side)")
    valid = np.isfinite(img)
    if bad is not None:
        valid &= ~np.asarray(bad, dtype=bool)
    if valid.sum() < 0.1 * valid.size:
        raise MaskingError(f"only {valid.sum()} of {valid.size} pixels are usable")
    img[~valid] = 0
    binned = _bin(img, valid, bin_factor)
    grid, cy, cx = _box_medians(binned, max(4, box // bin_factor))
    ny, nx = img.shape
    o = (bin_factor - 1) / 2
    residual = img - _background(grid, cy, cx, (np.arange(ny) - o) / bin_factor,
                                 (np.arange(nx) - o) / bin_factor).astype(np.float32)
    residual[~valid] = np.nan
    # Every 7th pixel is plenty for the noise and keeps this fast on a full CCD.
    sigma = robust_sigma(residual.ravel()[::7])
    if not sigma > 0:
        raise MaskingError("image noise is zero: nothing to detect against")
    rb = binned - _background(grid, cy, cx, np.arange(binned.shape[0]),
                              np.arange(binned.shape[1])).astype(np.float32)
    z = rb / robust_sigma(rb.ravel())
    z[~np.isfinite(z)] = 0
    stars_b = _star_mask(z)
    work = np.where(stars_b, 0, np.clip(z, -CLIP_SIGMA, CLIP_SIGMA)).astype(np.float32)
    stars = np.zeros(img.shape, dtype=bool)
    up = np.repeat(np.repeat(stars_b, bin_factor, axis=0), bin_factor, axis=1)
    stars[:up.shape[0], :up.shape[1]] = up
    return Prepared(residual=residual, sigma=sigma, stars=stars, binned=work, bin=bin_factor)


def _standardise_rows(h, usable, every=8):
    """Subtract each row's median and divide by its robust spread (over usable cells).

    Sampled every ``every`` rows and interpolated: the spread changes smoothly with angle.
    """
    rows = np.arange(0, h.shape[0], every)
    # Quartiles of the usable cells of each sampled row: unusable cells sort to the end as
    # +inf, and each row's quartiles are read at its own count (nanpercentile loops in Python).
    sample = np.sort(np.where(usable[rows], h[rows], np.inf), axis=1)
    n = usable[rows].sum(axis=1)
    ok = n >= 8
    idx = np.arange(rows.size)

    def quantile(q):
        return sample[idx, np.clip((q * (n - 1)).round().astype(int), 0, h.shape[1] - 1)]

    q1, med, q3 = quantile(0.25), quantile(0.5), quantile(0.75)
    ok &= q3 > q1
    if not ok.any():
        return np.zeros_like(h)
    all_rows = np.arange(h.shape[0])
    med = np.interp(all_rows, rows[ok], med[ok])
    spread = np.interp(all_rows, rows[ok], (q3 - q1)[ok] / 1.349)
    return (h - med[:, None]) / spread[:, None]


_COUNTS = {}


def hough_significance(work, sigmas=FILTER_SIGMAS, min_length=MIN_LINE_BINNED):
    """Significance of every line in the binned image, best over the matched-filter widths.

    Returns
    -------
    z : ndarray
        Hough-space significance (float32); cells of short lines are 0.
    width_index : ndarray
        Index into ``sigmas`` of the best width of each cell.
    """
    key = work.shape
    if key not in _COUNTS:
        _COUNTS.clear()  # one shape at a time is what a run needs
        _COUNTS[key] = fast_hough(np.ones(work.shape, dtype=np.float32))
    counts = _COUNTS[key]
    usable = counts >= min_length
    norm = 1 / np.sqrt(np.maximum(counts, 1))
    best = np.zeros(counts.shape, dtype=np.float32)
    which = np.zeros(counts.shape, dtype=np.int8)
    for k, s in enumerate(sigmas):
        z = _standardise_rows(fast_hough(cv2.GaussianBlur(work, (0, 0), s)) * norm, usable)
        better = (z > best) & usable
        best[better], which[better] = z[better], k
    return best, which


def _peak_line(prep, zmap):
    """Image-pixel chord of the line of the highest cell, and its (row, col)."""
    row, col = np.unravel_index(int(np.argmax(zmap)), zmap.shape)
    x1, y1, x2, y2 = cv2.ximgproc.HoughPoint2Line((int(col), int(row)), prep.binned,
                                                  **_fht_options())
    (xa, xb), (ya, yb) = prep.from_binned([x1, x2], [y1, y2])
    angle = np.degrees(np.arctan2(yb - ya, xb - xa))
    return Line.crossing(prep.shape, xa, ya, angle), (row, col)


def erase(prep, work, line, half_width):
    """Zero the binned pixels within ``half_width`` image pixels of a found streak."""
    hw = half_width / prep.bin + 1.0
    yy, xx = band_pixels(work.shape, prep.to_binned(line), hw, extend=hw)
    work[yy, xx] = 0


#: The search image is erased out to where a found streak's stacked profile drops below this
#: (binned-noise sigma): a bright streak's wings, tens of pixels out, would otherwise add up
#: along its length to a second, parallel detection.
ERASE_LEVEL = 0.1

#: Widest erased band, image pixels (each side).
MAX_ERASE = 300.0


def erase_half_width(prep, line, fwhm_px):
    """Image-pixel half-width of the band to erase around a found streak (see
    :data:`ERASE_LEVEL`), plus one FWHM of margin."""
    from .measure import stack_samples, wing_half_width

    b = prep.to_binned(line)
    reach = MAX_ERASE / prep.bin
    yy, xx = band_pixels(prep.binned.shape, b, reach)
    _, d = b.coordinates(xx, yy)
    profile, _ = stack_samples(d, prep.binned[yy, xx].astype(np.float64), reach, 0.5, 1.0,
                               b.angle_deg)
    wing = wing_half_width(profile, ERASE_LEVEL)
    wing = reach if wing is None else wing
    return float(min(MAX_ERASE, prep.bin * wing + fwhm_px))


@dataclass
class Detection:
    """A streak found by :func:`detect_streaks`.

    Attributes
    ----------
    line : Line
        Refined central line; its endpoints are the streak's extent in the image.
    significance : float
        Hough significance ``z`` of the detection.
    filter_fwhm_px : float
        FWHM of the best matched filter, image pixels (a first width estimate).
    trace : measure.Trace
        Refinement products (template profile, amplitude, S/N along the line).
    """

    line: Line
    significance: float
    filter_fwhm_px: float
    trace: object


def detect_streaks(prep, threshold=FALSE_ALARM_Z, max_streaks=MAX_STREAKS):
    """Find streaks one after another: peak, refine, erase, repeat.

    Parameters
    ----------
    prep : Prepared
    threshold : float
        Least Hough significance of a detection (default: the calibrated false-alarm level).
    max_streaks : int

    Returns
    -------
    list of Detection
        In order of decreasing significance.
    """
    from .measure import trace_streak

    work = prep.binned.copy()
    found = []
    # Candidates that refinement rejects are erased too; a few spare rounds allow for them.
    for _ in range(max_streaks + 4):
        zmap, which = hough_significance(work)
        coarse, cell = _peak_line(prep, zmap)
        z = float(zmap[cell])
        if not z >= threshold:
            break
        width = 2.3548 * FILTER_SIGMAS[which[cell]] * prep.bin
        if coarse is None:  # cannot happen for a cell of this image's transform
            break
        tr = trace_streak(prep, coarse, width)
        if tr is None:
            erase(prep, work, coarse, 2 * width)
            continue
        hw = erase_half_width(prep, tr.line, tr.fwhm_px)
        erase(prep, work, tr.line, hw)
        if any(_same_streak(tr.line, d.line, hw) for d in found):
            continue  # leftover light of a streak already found
        found.append(Detection(line=tr.line, significance=z, filter_fwhm_px=width, trace=tr))
        if len(found) == max_streaks:
            break
    return found


def _same_streak(a, b, half_width):
    """Whether line ``a`` runs along ``b`` within ``half_width`` (wings of one streak)."""
    from .geometry import angle_difference

    return (angle_difference(a.angle_deg, b.angle_deg) < 1.0
            and abs(a.offset_from(b)) < half_width)


def max_significance(prep):
    """Largest Hough significance of an image (for calibrating :data:`FALSE_ALARM_Z`)."""
    zmap, _ = hough_significance(prep.binned)
    return float(zmap.max())
