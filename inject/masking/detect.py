"""Streak detection that works on realistic CCD images.

The search runs on a binned copy of the image, where a streak a few pixels wide becomes a thin
line and a full CCD costs milliseconds per transform:

1. **Background**: sigma-clipped medians in boxes of :data:`BACKGROUND_BOX` pixels, a 3 x 3
   median filter over the boxes (a bright star or streak cannot pull one box), bilinear
   interpolation between box centres.
2. **Binning** :data:`BIN` x :data:`BIN` (mean of the usable pixels), in units of the binned
   noise.
3. **Star suppression**: connected regions above :data:`STAR_LOW_SIGMA` that reach
   :data:`STAR_SIGMA` and are compact (short, or round and filled) are set to zero with a
   margin growing with their peak; a streak is a long, thin region and survives. What is left
   is clipped to +-:data:`CLIP_SIGMA`, so that no faint star, cosmic ray or bright streak
   dominates a line sum.
4. **Matched filter**: Gaussian smoothing (sigma :data:`FILTER_SIGMA` binned pixels) on a
   pyramid of the binned image (:data:`LEVELS` levels, each binned 2 x 2 more). Smoothing a
   line isotropically is the same as smoothing its cross-section, so this is the matched
   filter across the track, whatever the angle, for streak FWHMs of ~7, 13 and 26 image
   pixels; the wider filters run on smaller images, so all three cost 1.3 times the first.
5. **Fast Hough transform** (OpenCV ``ximgproc``) of each level: every line sum, divided by
   the square root of its pixel count and standardised per angle (median and interquartile
   range over offsets), is a significance ``z`` with unit noise. Blocks with some unusable
   pixels are in units of their own noise; in an image with holes (NaN, flagged or constant
   regions) the holes are guarded like the image edges and the count is that of the usable
   cells each line crosses (:func:`hole_norms`), so the false-alarm level holds on what is
   left.
6. **Peaks**: the best ``z`` over levels (the outer :data:`EDGE_GUARD` binned pixels left
   out) is compared with :data:`FALSE_ALARM_Z` (higher for images under 512 px:
   :func:`threshold_for`). Above it, the line is refined and its extent found
   (:mod:`.measure`), the streak is erased from the binned image (out to its wings, or to a
   valley before a parallel neighbour), and the search repeats (standardised with the first
   round's scales), so several streaks are found one after the other; near-parallel ones
   are then retraced without each other's pixels (:func:`_retrace_neighbours`).
"""
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy import ndimage

from inject.errors import InputError
from inject.masking import MaskingError
from inject.masking.geometry import Line, angle_difference, band_pixels
from inject.masking.measure import DIP_LEVEL, profile_fwhm, stack_samples, trace_streak, wing_reach

#: Largest binning factor of the search image (4: a 7-10 px wide LSSTCam streak is ~2 binned
#: px). A smaller image is binned less (:func:`search_bin`): binning a 1-2 px wide streak 4 x 4
#: costs half its matched-filter S/N, and a small image's transform is cheap unbinned.
BIN = 4

#: :func:`search_bin` bins an image as little as keeps the larger side of its search image at
#: or under this many binned pixels (a full LSSTCam CCD, 4072 px: 4).
SEARCH_SIDE = 1024


def search_bin(shape, largest=BIN):
    """Binning factor of the search image of an image of ``shape``: the smallest power of 2
    (at most ``largest``) that keeps its larger side within :data:`SEARCH_SIDE` binned pixels.

    A 4072 x 4000 CCD is binned 4 (as before), a 2048 px image 2, a 1024 px or smaller one
    not at all: the search cost stays that of a full CCD or less, and a narrow streak (FWHM
    1-2 px, small telescopes, wide-field cameras) keeps its S/N.
    """
    side = max(shape)
    b = 1
    while b < largest and side > SEARCH_SIDE * b:
        b *= 2
    return b


def search_levels(bin_factor):
    """Pyramid levels for a base binning: :data:`LEVELS` at :data:`BIN`, one more per halving
    of the binning, so that the widest matched filter (~26 px FWHM) is searched at any base."""
    return LEVELS + max(0, int(round(np.log2(BIN / bin_factor))))

#: Background box size, image pixels. Large compared with a streak's width so that a box's
#: clipped median is not pulled by it; small compared with a CCD so sky gradients are followed.
BACKGROUND_BOX = 256

#: Gaussian matched-filter sigma, in pixels of each pyramid level. At binnings 4, 8 and 16 it
#: matches streak FWHMs of ~7, 13 and 26 image pixels (1.3", 2.6" and 5.3" at 0.2"/px), from
#: far orbits to low ones near zenith; neighbouring levels differ by 2 in width, which costs
#: at most ~6% of the matched-filter S/N.
FILTER_SIGMA = 0.7
LEVELS = 3

#: Smallest side of a pyramid level: on fewer cells the per-angle standardisation of the
#: transform rests on too few offsets and its tail grows (a 1024 px cut-out keeps 2 levels).
MIN_LEVEL_SIZE = 128

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

#: A round region must also fill this fraction of the ellipse of its second moments to be
#: compact: a star fills ~1 (a noisy edge ~0.7), two crossing streaks ~12 w / (pi L).
STAR_MIN_FILL = 0.4

#: A part of a long region (a streak that runs into a star or a galaxy) is a blob when its
#: pixels lie further than this many times the region's median distance to its edge (the
#: line's typical half-thickness), and at least :data:`BLOB_RADIUS` binned px (see
#: :func:`_star_mask`): a line of any width has none, a galaxy or a saturated star on it does.
BLOB_THICKNESS = 3.0
BLOB_RADIUS = 2

#: A compact region is grown by at least this fraction of its radius (binned px), at most
#: :data:`MAX_MARGIN`: see :func:`_compact_regions`.
BLOB_MARGIN = 0.5
MAX_MARGIN = 32

#: Hough cells of lines shorter than this (image pixels; at least 16 cells) are ignored: short
#: corner lines carry little signal and their noise is far from Gaussian.
MIN_LINE_PX = 128

#: Smallest image side searched, px.
MIN_SIDE = 64


def min_line_cells(shape, factor):
    """Shortest line searched (cells) in a pyramid level of ``shape`` binned ``factor`` times
    from the image: :data:`MIN_LINE_PX`, at least 16 cells, and at most three quarters of
    the level's smaller side (an image under ~170 px has no 128 px line in every direction)."""
    return max(16, min(MIN_LINE_PX // factor, int(0.75 * min(shape))))

#: The outermost this many binned pixels of every side are left out of the search (set to 0):
#: a line running along an image edge sums pixels whose matched filter sees a mirrored noise
#: (twice the weight of the inner neighbours) and the wings of stars just outside the image.
#: On a small image such lines are a large share of all lines, and they made most of its false
#: alarms (2 of 60 held-out 512 x 512 cut-outs, z 6.6 and 7.6; see
#: :data:`SMALL_SEARCH_EXTRA_Z`). A streak is missed only if it runs within ~8 image pixels of
#: an edge over its whole length.
EDGE_GUARD = 2

#: The guard is at least this many image pixels wide whatever the binning (an image binned
#: less than :data:`BIN` guards as many image pixels as a full CCD does).
EDGE_GUARD_PX = 8

#: False-alarm threshold on the Hough significance ``z``.
#:
#: How it was obtained: ``python scripts/bench_mask.py --calibrate --full 40 --cutouts 100``
#: simulates streak-free scenes (the default field: ITL CCD, g band, 30 s, dark sky, zenith
#: 70 deg, 0.67" seeing, Poisson and read noise, stars to mag 24 with saturated cores flagged)
#: and records the largest ``z`` of each image (:func:`max_significance`). Over 40 full
#: 4072 x 4000 CCDs (seeds 1-40) the largest was 6.04 (99th percentile 5.93, median 5.10);
#: over 100 1024 x 1024 cut-outs (seeds 1-100) 5.83 (median 4.76). The threshold is the
#: largest value plus 0.5: a false alarm needs a noise excursion beyond anything seen in those
#: 140 images (and must then survive the refinement of :func:`.measure.trace_streak`).
FALSE_ALARM_Z = 6.5

#: Added to the threshold when the search image (binned pixels, smaller side) is smaller than
#: :data:`MIN_LEVEL_SIZE`, i.e. for images under 512 px a side, which search a single level of
#: fewer than 128 binned pixels: ``(least side, extra z)``, first match.
#:
#: How it was obtained: streak-free images of the field above (seeds 1-400 or 1-200; the
#: held-out check, ``python scripts/bench_mask.py --sections small_false_positives``, uses
#: 3001-3060), searched with :data:`EDGE_GUARD` by :func:`detect_streaks` down to z = 5, the
#: largest ``z`` of a line that survives refinement being recorded. From 128 binned pixels up
#: it was 6.14 on 400 512 x 512 cut-outs, 5.47 on 100 768 x 768 and 5.55 on 100 1024 x 1024:
#: below :data:`FALSE_ALARM_Z`, no extra. (Before refinement one 512 px image reached 10.3:
#: a star just beyond the edge, which refinement rejects.) Searches of 64-120 binned pixels
#: (images of 256-480 px; 1400 images) reached 7.05 (7.20 before refinement): threshold 7.6.
#: Searches of 32 and 48 (128 and 192 px; 400 images), where the shortest usable line spans
#: the image and a row's standardisation rests on few cells, reached 10.49: threshold 11.
SMALL_SEARCH_EXTRA_Z = ((MIN_LEVEL_SIZE, 0.0), (64, 1.1), (0, 4.5))


#: Added to the threshold when the image is binned less than :data:`BIN` (images of 2048 px
#: or less, :func:`search_bin`): a search at a finer binning has more lines and more pyramid
#: levels (more trials) and a heavier tail. Streak-free 512 x 512 LSSTCam cut-outs searched
#: unbinned (seeds 3001-3040, plain, with vignetted corners and with a NaN half plane: 120
#: images) reached 6.50 after refinement, and 7.04 on one of the six of the hole tests
#: (vignetted corners, seed 5): the largest plus 0.5 is 7.5, 1.0 over :data:`FALSE_ALARM_Z`.
FINE_SEARCH_EXTRA_Z = 1.0


def threshold_for(shape, threshold=FALSE_ALARM_Z, bin_factor=BIN):
    """Detection threshold for a search image of ``shape`` (binned pixels, binned
    ``bin_factor`` times): ``threshold`` plus the :data:`SMALL_SEARCH_EXTRA_Z` of its smaller
    side, plus :data:`FINE_SEARCH_EXTRA_Z` when binned less than :data:`BIN`."""
    side = min(shape)
    extra = next(extra for least, extra in SMALL_SEARCH_EXTRA_Z if side >= least)
    return threshold + extra + (FINE_SEARCH_EXTRA_Z if bin_factor < BIN else 0.0)


#: Most streaks searched for in one image.
MAX_STREAKS = 8

#: Planes of an LSST-style mask whose pixels are not used (as LSST ``maskStreaks`` does).
BAD_PLANES = ("BAD", "SAT", "CR", "EDGE", "NO_DATA", "INTRP", "SUSPECT")

def _fht_options():
    # OpenCV 5 silently puts positional angleRange/op/makeSkew into the output argument:
    # always pass them by keyword.
    return {"angleRange": cv2.ximgproc.ARO_315_135, "makeSkew": cv2.ximgproc.HDO_DESKEW}


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
    stars_binned : ndarray
        Bool, binned pixels of compact bright sources (excluded from measurements; see
        :attr:`stars` and :meth:`star_at`).
    binned : ndarray
        Binned residual in units of its own noise, stars removed, clipped (the search image).
    bin : int
        Binning factor.
    levels : int
        Levels of the matched-filter pyramid (:func:`search_levels`).
    zbinned : ndarray or None
        The same before clipping (profiles of found streaks, to erase them).
    holes : ndarray or None
        Bool, binned pixels with no usable pixel (NaN, flagged bad or dead) outside stars;
        None if there are none.
    halos : ndarray or None
        Bool, binned pixels of the compact sources of the image binned :data:`BIN` x
        :data:`BIN` that the star mask leaves (their faint halos), left out of the pyramid
        levels binned :data:`BIN` or more from the image (:func:`level_images`); None for
        an image searched at :data:`BIN` or with none.
    """

    residual: np.ndarray
    sigma: float
    stars_binned: np.ndarray
    binned: np.ndarray
    bin: int
    zbinned: np.ndarray | None = None
    holes: np.ndarray | None = None
    levels: int = LEVELS
    halos: np.ndarray | None = None

    @property
    def shape(self):
        return self.residual.shape

    @property
    def stars(self):
        """Bool image of the star pixels (full resolution; built on demand)."""
        yy, xx = np.indices(self.shape, sparse=True)
        return self.star_at(yy, xx)

    def star_at(self, yy, xx):
        """Whether pixels ``(yy, xx)`` belong to a compact bright source (a star's binned
        block; pixels beyond the last whole block are never stars)."""
        b = self.bin
        nyb, nxb = self.stars_binned.shape
        yy, xx = np.asarray(yy), np.asarray(xx)
        if b & (b - 1) == 0:  # a power of 2: shifts, several times faster than divisions
            by, bx = yy >> (b.bit_length() - 1), xx >> (b.bit_length() - 1)
        else:
            by, bx = yy // b, xx // b
        if self.shape == (nyb * b, nxb * b):  # whole blocks cover the image
            return self.stars_binned[by, bx]
        inside = (by < nyb) & (bx < nxb)
        return inside & self.stars_binned[np.minimum(by, nyb - 1), np.minimum(bx, nxb - 1)]

    def to_binned(self, line, factor=None):
        """The same line in the coordinates of an image binned ``factor`` (default ``bin``)."""
        b = self.bin if factor is None else factor
        o = (b - 1) / 2
        return Line((line.x0 - o) / b, (line.y0 - o) / b, (line.x1 - o) / b, (line.y1 - o) / b)

    def from_binned(self, x, y, factor=None):
        """Image-pixel coordinates of coordinates in an image binned ``factor``."""
        b = self.bin if factor is None else factor
        o = (b - 1) / 2
        return b * np.asarray(x, float) + o, b * np.asarray(y, float) + o


def robust_sigma(values):
    """Gaussian-equivalent standard deviation from the median absolute deviation."""
    v = values[np.isfinite(values)]  # a copy: partitioned in place below
    if v.size == 0:
        return float("nan")
    mid = [(v.size - 1) // 2, v.size // 2]
    v.partition(mid)
    np.abs(np.subtract(v, 0.5 * (v[mid[0]] + v[mid[1]]), out=v), out=v)
    v.partition(mid)
    return float(1.4826 * 0.5 * (v[mid[0]] + v[mid[1]]))


def _bin(image, bad, bad_index, factor):
    """Mean of the usable pixels (finite, not ``bad``) of every ``factor x factor`` block
    (NaN if none); a partial last row or column of blocks is left out.

    OpenCV's area resampling (a block mean, ~20x faster than a NumPy reshape-sum) runs on the
    image as given; the few blocks holding bad pixels (flat indices ``bad_index``) have those
    pixels' sum taken out, and blocks whose sum is not finite (NaN or infinite pixels) are
    recomputed from their pixels.

    Returns
    -------
    binned : ndarray
        float32.
    nonfinite : ndarray of int
        Flat indices of the non-finite pixels of whole blocks that ``bad`` does not flag.
    count : ndarray
        Usable pixels of each block (float64, the binned shape).

    Raises
    ------
    InputError
        If a block's mean is beyond :data:`MAX_ABS_VALUE`.
    """
    ny, nx = (n // factor for n in image.shape)
    crop = image[:ny * factor, :nx * factor]
    area = factor * factor
    total = cv2.resize(crop, (nx, ny), interpolation=cv2.INTER_AREA).astype(np.float64)
    total = total.reshape(-1) * area
    count = np.full(ny * nx, float(area))
    yy, xx = np.divmod(bad_index, image.shape[1])
    inside = (yy < ny * factor) & (xx < nx * factor)
    block = (yy[inside] // factor) * nx + xx[inside] // factor
    values = image.reshape(-1)[bad_index[inside]].astype(np.float64)
    finite = np.isfinite(values)
    count -= np.bincount(block, minlength=ny * nx)
    total -= np.bincount(block[finite], weights=values[finite], minlength=ny * nx)
    broken = np.flatnonzero(~np.isfinite(total))
    nonfinite = np.zeros(0, dtype=np.intp)
    if broken.size:
        by, bx = np.divmod(broken, nx)
        r = np.arange(factor)
        ry = (by[:, None] * factor + r)[:, :, None]
        rx = (bx[:, None] * factor + r)[:, None, :]
        pix = crop[ry, rx].astype(np.float64)
        ok = np.isfinite(pix)
        flagged = bad[ry, rx] if bad is not None else np.zeros(ok.shape, dtype=bool)
        k = np.nonzero(~ok & ~flagged)
        nonfinite = np.ravel_multi_index((np.broadcast_to(ry, ok.shape)[k],
                                          np.broadcast_to(rx, ok.shape)[k]), image.shape)
        ok &= ~flagged
        total[broken] = np.where(ok, pix, 0.0).sum(axis=(1, 2))
        count[broken] = ok.sum(axis=(1, 2))
    mean = np.divide(total, count, out=np.full(ny * nx, np.nan), where=count > 0)
    top = np.nanmax(np.abs(mean)) if (count > 0).any() else 0.0
    if not top <= MAX_ABS_VALUE:
        raise InputError("image", f"values up to {_largest(image):.3g}",
                         f"the search works in float32 and needs |value| <= "
                         f"{MAX_ABS_VALUE:.0e}: rescale the image or flag those pixels bad")
    return mean.astype(np.float32).reshape(ny, nx), nonfinite, count.reshape(ny, nx)


def _largest(image):
    """Largest finite ``|value|`` of an image (for the error message)."""
    a = np.abs(np.asarray(image, dtype=np.float64))
    return float(np.max(a, where=np.isfinite(a), initial=0.0))


#: Largest usable ``|value|`` of an image (image units): the search runs in float32 (largest
#: 3.4e38), and sums and squares of the residual over a CCD must stay finite. An infinite
#: pixel is unusable, like NaN; a finite one beyond this is refused.
MAX_ABS_VALUE = 1e30


def _dead_blocks(crop, factor, binned):
    """Blocks whose pixels are all equal (a gap of a mosaic filled with 0, a dead region):
    a noisy sky never gives ``factor^2`` equal values. Bool, the binned shape.

    Candidates are the blocks whose mean (``binned``) equals a neighbour's bit for bit, as
    the blocks of a dead region do and noisy ones never (two comparisons of the binned
    image, cheap); only these are checked in full. A lone dead block is missed, which no
    line notices.
    """
    ny, nx = binned.shape
    same = np.zeros((ny, nx), dtype=bool)
    for axis in (0, 1):
        a, b = [slice(None)] * 2, [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        eq = binned[tuple(a)] == binned[tuple(b)]
        same[tuple(a)] |= eq
        same[tuple(b)] |= eq
    by, bx = np.nonzero(same)
    if by.size:
        r = np.arange(factor)
        pix = crop[(by[:, None] * factor + r)[:, :, None], (bx[:, None] * factor + r)[:, None, :]]
        same[by, bx] = (pix == pix[:, :1, :1]).all(axis=(1, 2))
    return same


#: Side (image px) of the blocks checked for a dead region: 16 equal pixels never come from
#: a noisy sky, while 1 or 4 do in an integer image of low noise.
DEAD_BLOCK = 4


def _dead_region(img, bin_factor, binned):
    """:func:`_dead_blocks` of an image binned ``bin_factor``, checked on blocks of at least
    :data:`DEAD_BLOCK` px (bool, the binned shape)."""
    ny, nx = binned.shape
    if bin_factor >= DEAD_BLOCK:
        return _dead_blocks(img[:ny * bin_factor, :nx * bin_factor], bin_factor, binned)
    f = DEAD_BLOCK
    my, mx = img.shape[0] // f, img.shape[1] // f
    crop = img[:my * f, :mx * f]
    coarse = cv2.resize(crop, (mx, my), interpolation=cv2.INTER_AREA)
    dead = _dead_blocks(crop, f, coarse)
    r = f // bin_factor
    out = np.zeros((ny, nx), dtype=bool)
    up = np.repeat(np.repeat(dead, r, axis=0), r, axis=1)
    out[:up.shape[0], :up.shape[1]] = up[:ny, :nx]
    return out


def clipped_row_medians(a, passes=2, k=3.0):
    """Median of the finite values of each row after ``passes`` rounds of ``k``-sigma
    clipping about the median (sigma from the median absolute deviation): a star or a streak
    in a box does not pull it.

    Each row is sorted once: a clipped set is then a contiguous run of the sorted row, its
    median is read at the run's middle, and the median of the distances ``|x - median|`` is
    an order statistic of two sorted sequences (the distances below and above the median),
    found by a binary search. The same values as re-sorting after every clip, 2-3x faster.
    """
    s = np.sort(a, axis=1)  # NaNs last
    m = s.shape[1]
    rows = np.arange(s.shape[0])

    def at(i):
        return s[rows, np.clip(i, 0, m - 1)]

    def run_median(lo, hi):
        n = hi - lo
        return np.where(n > 0, 0.5 * (at(lo + np.maximum((n - 1) // 2, 0))
                                      + at(lo + np.maximum(n // 2, 0))), np.nan)

    lo = np.zeros(s.shape[0], dtype=np.intp)
    hi = np.isfinite(s).sum(axis=1)
    med = run_median(lo, hi)
    for _ in range(passes):
        # Distances below the median, ascending: med - s[p-1], med - s[p-2], ... (p - lo of
        # them); above: s[p] - med, s[p+1] - med, ... (hi - p).
        p = np.clip((s < med[:, None]).sum(axis=1), lo, hi)
        below, above = p - lo, hi - p

        def kth(q):
            # q-th smallest distance: i of the q + 1 smallest come from below, by bisection.
            left, right = np.maximum(0, q + 1 - above), np.minimum(q + 1, below)
            while (left < right).any():
                act = left < right
                mid = (left + right) // 2
                j = q - mid
                from_below = med - at(p - 1 - mid)
                from_above = np.where(j < above, at(p + j) - med, np.inf)
                take = from_below <= from_above
                left = np.where(act & take, mid + 1, left)
                right = np.where(act & ~take, mid, right)
            lv = np.where(left > 0, med - at(p - left), -np.inf)
            rv = np.where((q - left >= 0) & (q - left < above), at(p + q - left) - med, -np.inf)
            return np.maximum(lv, rv)

        n = hi - lo
        mad = np.where(n > 0, 0.5 * (kth(np.maximum((n - 1) // 2, 0))
                                     + kth(np.maximum(n // 2, 0))), np.nan)
        limit = k * (1.4826 * mad)
        lo = (s < (med - limit)[:, None]).sum(axis=1)
        hi = (s <= (med + limit)[:, None]).sum(axis=1)
        med = run_median(lo, hi)
    return med


def _box_medians(binned, box):
    """Sigma-clipped median of each ``box x box`` block of a binned image (NaN = unusable)."""
    ny, nx = binned.shape
    gy, gx = max(1, round(ny / box)), max(1, round(nx / box))
    by, bx = -(-ny // gy), -(-nx // gx)
    padded = np.full((gy * by, gx * bx), np.nan, dtype=np.float32)
    padded[:ny, :nx] = binned
    blocks = padded.reshape(gy, by, gx, bx).transpose(0, 2, 1, 3).reshape(gy * gx, by * bx)
    med = clipped_row_medians(blocks).reshape(gy, gx)
    if np.all(np.isnan(med)):
        raise MaskingError("no usable pixels for the background")
    med[np.isnan(med)] = np.nanmedian(med)
    if gy >= 3 and gx >= 3:
        med = ndimage.median_filter(med, size=3, mode="nearest")
    return med.astype(np.float32), (by, bx)


def _background(grid, box, shape, factor=1):
    """Bilinear interpolation between box centres (flat beyond the outer ones) on an image of
    ``shape`` binned ``factor`` times less than the grid's boxes of ``box`` binned pixels.

    OpenCV's linear resize puts source pixel ``k`` at ``(k + 0.5) * scale - 0.5``, exactly
    where box ``k``'s centre falls; the boxes may overhang the image, which is cropped. The
    rows and columns of an image beyond its last whole binned pixel, if the boxes stop there,
    repeat the last ones (the background is flat beyond the outer box centres anyway).
    """
    (gy, gx), (by, bx) = grid.shape, box
    full = cv2.resize(grid, (gx * bx * factor, gy * by * factor),
                      interpolation=cv2.INTER_LINEAR)
    short = (max(0, shape[0] - full.shape[0]), max(0, shape[1] - full.shape[1]))
    if any(short):
        full = np.pad(full, ((0, short[0]), (0, short[1])), mode="edge")
    return full[:shape[0], :shape[1]]


def _star_mask(z):
    """Compact sources in a significance image: regions above :data:`STAR_LOW_SIGMA` holding a
    pixel above :data:`STAR_SIGMA` (hysteresis: a streak of moderate brightness stays one long
    region instead of breaking into compact fragments), with margins growing with their
    peak; and the compact blobs (:data:`BLOB_RADIUS`) of regions a streak has joined."""
    above = z > STAR_LOW_SIGMA
    labels, n = ndimage.label(above, structure=np.ones((3, 3)))
    stars = _compact_regions(z, above, (labels, n))
    # A streak crossing a star or a galaxy joins it into one long region, which stays
    # unsuppressed: the galaxy, clipped but wide, then outweighs a faint line. The blob is
    # where the region is much thicker than its typical thickness (the line's): its pixels
    # further from the region's edge than BLOB_THICKNESS times the region's median distance,
    # grown back by that distance, are judged as a region of their own.
    rest = above & ~stars
    dist = cv2.distanceTransform(rest.view(np.uint8), cv2.DIST_L2, 3)
    seeds = dist > BLOB_RADIUS + 0.5
    # Only regions thicker somewhere than BLOB_RADIUS can hold a blob: a few, each handled in
    # its own box (a CCD's thousands of small noise regions are never looked at; whole-image
    # passes per step cost ~50 ms a CCD). A region is what is left of one above
    # STAR_LOW_SIGMA once the compact ones and their margins are taken out.
    if not seeds.any():
        return stars
    blob = np.zeros(z.shape, dtype=bool)
    for lab in np.unique(labels[seeds]):
        x, y, w, h = cv2.boundingRect((labels == lab).view(np.uint8))
        box = (slice(y, y + h), slice(x, x + w))
        own = (labels[box] == lab) & rest[box]
        d = dist[box]
        thr = max(BLOB_RADIUS + 0.5, BLOB_THICKNESS * float(np.median(d[own])))
        core = own & (d > thr)
        cx, cy, cw, ch = cv2.boundingRect(core.view(np.uint8))
        if cw == 0:
            continue
        r = int(min(np.ceil(thr), MAX_MARGIN, np.ceil(d[core].max())))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        # Grown within the core's box widened by r (not the whole region's, a CCD's width
        # for a streak).
        sub = (slice(max(0, cy - r), cy + ch + r), slice(max(0, cx - r), cx + cw + r))
        grown = cv2.dilate(np.ascontiguousarray(core[sub]).view(np.uint8), disc)
        blob[box][sub] |= grown.view(bool) & own[sub]
    x, y, w, h = cv2.boundingRect(blob.view(np.uint8))
    if w > 0:
        # The blobs' compact parts, margins included, lie within MAX_MARGIN of their box.
        pad = MAX_MARGIN + 1
        win = (slice(max(0, y - pad), y + h + pad), slice(max(0, x - pad), x + w + pad))
        stars[win] |= _compact_regions(z[win], blob[win])
    return stars


def _coarse_star_mask(z, f):
    """:func:`_star_mask` of significance image ``z`` binned ``f`` x ``f`` (back in units of
    its own noise), blown up to ``z``'s shape (bool)."""
    ny, nx = z.shape[0] // f, z.shape[1] // f
    zc = cv2.resize(np.ascontiguousarray(z[:ny * f, :nx * f]), (nx, ny),
                    interpolation=cv2.INTER_AREA) * np.float32(f)
    out = np.zeros(z.shape, dtype=bool)
    out[:ny * f, :nx * f] = np.repeat(np.repeat(_star_mask(zc), f, axis=0), f, axis=1)
    return out


def _compact_regions(z, above, labelled=None):
    """The compact regions of bool image ``above`` that reach :data:`STAR_SIGMA` in ``z``,
    grown by margins that increase with their peak (see :func:`_star_mask`); ``labelled``:
    ``above``'s 8-connected labels and their count, if already known."""
    zp = z
    labels, n = (ndimage.label(above, structure=np.ones((3, 3))) if labelled is None
                 else labelled)
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
    # A uniform bar of length L has an rms of L / sqrt(12) along it; a uniform ellipse of rms
    # a, b covers 4 pi a b. Two crossing streaks make a round region too, but a hollow one.
    fill = count / (4 * np.pi * major * minor)
    compact = bright & ((np.sqrt(12) * major <= STAR_MAX_LENGTH)
                        | ((major <= STAR_AXIS_RATIO * minor) & (fill >= STAR_MIN_FILL)))
    # Margin grows with the peak: a bright star's wings stay above the noise further out;
    # and with the size: a galaxy's (or a bright star's) wings fall from the region's edge
    # (STAR_LOW_SIGMA) to a tenth of the noise over ~half its radius (exponential and Moffat
    # profiles alike), and a ring of faint wings adds up along a tangent line.
    radius = np.sqrt(count / np.pi)
    margin = np.maximum(np.clip(1 + np.round(2 * np.log10(np.maximum(peak, STAR_SIGMA)
                                                             / STAR_SIGMA)), 1, 8),
                        np.minimum(np.ceil(BLOB_MARGIN * radius), MAX_MARGIN)).astype(int)
    stars = np.zeros(zp.shape, dtype=bool)
    # One gather of each pixel's margin (0: not a compact source), then one dilation per
    # margin value.
    margins = np.where(compact, margin, 0).astype(np.uint8)[labels]
    for r in np.unique(margin[compact]):
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        grown = cv2.dilate((margins == r).view(np.uint8), kernel)
        np.logical_or(stars, grown.view(bool), out=stars)
    return stars


def prepare(image, bad=None, bin_factor=None, box=BACKGROUND_BOX):
    """Background-subtract, bin and clean an image for the search.

    Parameters
    ----------
    image : array_like
        2-D image (any units). A native-order, C-contiguous float32 or float64 array is used
        as it is (not modified); anything else is first copied to native float32, as OpenCV
        miscomputes on big-endian astropy arrays.
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
    InputError
        If the image does not hold real numbers, or ``bad`` differs from it in shape.
    """
    img = np.asarray(image)
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise InputError("image", f"{img.dtype} array", "must hold real numbers")
    if img.ndim != 2:
        raise MaskingError(f"image has {img.ndim} dimensions; need a 2-D image")
    if bin_factor is None:
        bin_factor = search_bin(img.shape)
    least = max(MIN_SIDE, 16 * bin_factor)
    if min(img.shape) < least:
        raise MaskingError(f"image {img.shape[1]} x {img.shape[0]} px is too small to search "
                           f"(needs >= {least} px a side)")
    if (img.dtype not in (np.float32, np.float64) or not img.dtype.isnative
            or not img.flags.c_contiguous):
        img = np.ascontiguousarray(img, dtype=np.float32)
    # The image itself is not copied: it is binned as it is, and the residual is written by
    # the background subtraction.
    if bad is not None:
        bad = np.asarray(bad, dtype=bool)
        if bad.shape != img.shape:
            raise InputError("mask", f"shape {bad.shape}",
                             f"must match the image's shape {img.shape}")
        bad_index = np.flatnonzero(bad)  # few on a real image
    else:
        bad_index = np.zeros(0, dtype=np.intp)
    binned, nonfinite, count = _bin(img, bad, bad_index, bin_factor)
    dead = _dead_region(img, bin_factor, binned)
    if dead.any():
        binned[dead] = np.nan
        count[dead] = 0
    unusable = img.size - int(count.sum())
    if unusable > 0.9 * img.size:
        raise MaskingError(f"only {img.size - unusable} of {img.size} pixels are usable")
    grid, boxes = _box_medians(binned, max(4, box // bin_factor))
    # One pass: float32 residual = image - background; unusable pixels become NaN (a
    # non-finite pixel beyond the last whole block stays as it is: never used either).
    residual = cv2.subtract(img, _background(grid, boxes, img.shape, bin_factor),
                            dtype=cv2.CV_32F)
    flat = residual.reshape(-1)
    flat[bad_index] = np.nan
    flat[nonfinite] = np.nan
    if dead.any():
        by, bx = np.nonzero(dead)
        r = np.arange(bin_factor)
        residual[(by[:, None] * bin_factor + r)[:, :, None],
                 (bx[:, None] * bin_factor + r)[:, None, :]] = np.nan
    # Half a million pixels pin the noise to ~0.2% and keep this fast on a full CCD: whole
    # rows, evenly spaced (contiguous memory, ~3x faster than every n-th pixel).
    sigma = robust_sigma(residual[::max(1, residual.size // 500_000)].ravel())
    if not sigma > 0:
        raise MaskingError("image has no noise (median absolute deviation 0): detection "
                           "thresholds and mask widths are set against the sky noise")
    rb = binned - _background(grid, boxes, binned.shape)
    z = rb / robust_sigma(rb.ravel()[::max(1, rb.size // 300_000)])
    area = bin_factor * bin_factor
    partial = (count < area) & (count > 0)
    if partial.any():
        # A block of n usable pixels has sqrt(area / n) times the noise of a whole one: in
        # units of its own noise, a bad column or a hole's edge raises no false line.
        z[partial] *= np.sqrt(count[partial] / area)
    z[~np.isfinite(z)] = 0
    stars_b = _star_mask(z)
    halos = None
    if bin_factor < BIN:
        # A bright star's halo lies below STAR_LOW_SIGMA in the pixels of a finely binned
        # image, outside its star mask, yet adds up along a tangent line at the pyramid's
        # coarse levels (streak-free 1024 px LSSTCam cut-outs searched unbinned reached z
        # 7.6-8.3 so, 5.1-5.6 with these halos left out): the coarse levels leave out the
        # compact sources of the image binned BIN, as a search binned BIN does. The fine
        # levels and the measurements keep them (a narrow streak beside a star).
        halos = _coarse_star_mask(z, BIN // bin_factor) & ~stars_b
        halos = halos if halos.any() else None
    work = np.where(stars_b, 0, np.clip(z, -CLIP_SIGMA, CLIP_SIGMA)).astype(np.float32)
    # Holes: unusable blocks that no star covers (a star's saturated core is a star's).
    holes = (count == 0) & ~stars_b
    return Prepared(residual=residual, sigma=sigma, stars_binned=stars_b, binned=work,
                    bin=bin_factor, zbinned=np.where(stars_b, 0, z).astype(np.float32),
                    holes=holes if holes.any() else None, levels=search_levels(bin_factor),
                    halos=halos)


def _row_scales(h, n_usable, every=8):
    """Median and robust spread (interquartile range / 1.349) of the usable cells of each row
    of a normalised transform (unusable cells are NaN), or None if no row has enough cells.

    Sampled every ``every`` rows and interpolated: the spread changes smoothly with angle.
    """
    rows = np.arange(0, h.shape[0], every)
    # NaNs sort last, so each row's quartiles are read at its own count (nanpercentile loops
    # over rows in Python).
    sample = np.sort(h[rows], axis=1)
    n = n_usable[rows]
    idx = np.arange(rows.size)

    def quantile(q):
        return sample[idx, np.clip((q * (n - 1)).round().astype(int), 0, h.shape[1] - 1)]

    q1, med, q3 = quantile(0.25), quantile(0.5), quantile(0.75)
    ok = (n >= 8) & (q3 > q1)
    if not ok.any():
        return None
    all_rows = np.arange(h.shape[0])
    med = np.interp(all_rows, rows[ok], med[ok]).astype(np.float32)
    spread = np.interp(all_rows, rows[ok], (q3 - q1)[ok] / 1.349).astype(np.float32)
    return med, spread


_NORM: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _line_norm(shape, min_length):
    """``1 / sqrt(pixels)`` of every Hough cell (NaN for lines shorter than ``min_length``),
    which cells are usable, and how many per row."""
    key = (shape, min_length)
    if key not in _NORM:
        if len(_NORM) >= 3 * (LEVELS + 2):  # a run needs one image shape per level
            _NORM.clear()
        counts = fast_hough(np.ones(shape, dtype=np.float32))
        usable = counts >= min_length
        _NORM[key] = (np.where(usable, 1 / np.sqrt(np.maximum(counts, 1)), np.nan)
                      .astype(np.float32), usable, usable.sum(axis=1))
    return _NORM[key]


def _hole_norm(valid, min_length):
    """As :func:`_line_norm` for an image with holes: a line's count is the sum of the
    usable fraction ``valid`` of its cells, so a line sum of unit-noise cells has unit noise
    whatever part of it crosses a hole, and lines with fewer than ``min_length`` usable cells
    are not searched (their row's median and spread are those of real lines)."""
    counts = fast_hough(valid)
    usable = counts >= min_length
    return (np.where(usable, 1 / np.sqrt(np.maximum(counts, 1)), np.nan).astype(np.float32),
            usable, usable.sum(axis=1))


def _normalised_transform(image, min_length, norm=None):
    """Filtered transform divided by the square root of each line's pixel count (NaN for
    unusable cells), and its row scales (or None); see :func:`hough_significance`.
    ``norm``: the :func:`_hole_norm` of an image with holes (default :func:`_line_norm`)."""
    norm, usable, n_usable = _line_norm(image.shape, min_length) if norm is None else norm
    h = fast_hough(cv2.GaussianBlur(image, (0, 0), FILTER_SIGMA))
    h *= norm
    return h, usable, _row_scales(h, n_usable)


def pyramid(work, levels=LEVELS):
    """The search image and its 2 x 2 block means, ``levels`` images in all, with their
    binning relative to the first."""
    images = [(work, 1)]
    for _ in range(levels - 1):
        img, f = images[-1]
        ny, nx = img.shape[0] // 2, img.shape[1] // 2
        if min(ny, nx) < MIN_LEVEL_SIZE:
            break
        images.append((cv2.resize(img[:2 * ny, :2 * nx], (nx, ny),
                                  interpolation=cv2.INTER_AREA), 2 * f))
    return images


def level_images(prep, work):
    """The :func:`pyramid` of search image ``work`` of ``prep``, its levels binned
    :data:`BIN` or more from the image built from ``work`` without the
    :attr:`Prepared.halos`."""
    levels = pyramid(work, prep.levels)
    if prep.halos is None:
        return levels
    coarse = pyramid(np.where(prep.halos, np.float32(0), work), prep.levels)
    return [c if prep.bin * c[1] >= BIN else fine for fine, c in zip(levels, coarse)]


def hough_significance(image, min_length):
    """Significance ``z`` of every line of one (already binned) image.

    Every line sum of the filtered image, divided by the square root of its pixel count, is
    standardised per angle (row): minus the row's median, over its robust spread.

    Returns
    -------
    ndarray
        float32, rows = angles, columns = offsets; cells of lines shorter than
        ``min_length`` cells are 0.
    """
    h, usable, scales = _normalised_transform(image, min_length)
    if scales is None:
        return np.zeros_like(h)
    med, spread = scales
    h -= med[:, None]
    h /= spread[:, None]
    h[~usable] = 0
    return h


def hough_peak(image, min_length, scales=None, norm=None):
    """Largest significance of :func:`hough_significance` and its cell, without forming the
    map: the standardisation is monotonic within a row, so each row's largest normalised sum
    gives its largest ``z``.

    ``scales`` (median and spread of every row, as :func:`_row_scales` returns them), if
    given, standardise instead of this image's own: after a streak is erased, the zeroed band
    would shrink the spread (on a small image, to nothing), while the noise is unchanged.

    Returns
    -------
    z : float
    row, col : int
    scales : tuple or None
        The scales used.
    """
    h, _, own = _normalised_transform(image, min_length, norm)
    if scales is None:
        scales = own
    if scales is None:
        return 0.0, 0, 0, None
    med, spread = scales
    top = np.fmax.reduce(h, axis=1)  # NaN (unusable) cells ignored
    z = (top - med) / spread
    z[~np.isfinite(z)] = -np.inf
    row = int(np.argmax(z))
    if not np.isfinite(z[row]):
        return 0.0, 0, 0, scales
    return float(z[row]), row, int(np.nanargmax(h[row])), scales


@dataclass
class Candidate:
    """The most significant line of the search image.

    Attributes
    ----------
    z : float
        Its significance.
    line : Line or None
        Its chord across the image (image pixels).
    fwhm_px : float
        FWHM of the matched filter that found it (image pixels).
    scales : list or None
        Per pyramid level, the row scales (median and spread) that standardised it.
    """

    z: float
    line: Line | None
    fwhm_px: float
    scales: list | None = field(default=None, repr=False)


def best_line(prep, work, scales=None, norms=None):
    """The most significant line over all pyramid levels of ``work`` (a binned image).

    ``scales``: per level, the row scales to standardise with (the :attr:`Candidate.scales`
    of the search before any streak was erased); default each level's own. ``norms``: per
    level, the line counts of an image with holes (:func:`hole_norms`).
    """
    best = None
    used = []
    for k, (image, f) in enumerate(level_images(prep, work)):
        factor = prep.bin * f
        z, row, col, sc = hough_peak(image, min_line_cells(image.shape, factor),
                                     None if scales is None else scales[k],
                                     None if norms is None else norms[k])
        used.append(sc)
        if best is None or z > best[0]:
            best = (z, (row, col), image, factor)
    z, (row, col), image, factor = best
    x1, y1, x2, y2 = cv2.ximgproc.HoughPoint2Line((int(col), int(row)), image,
                                                  **_fht_options())
    (xa, xb), (ya, yb) = prep.from_binned([x1, x2], [y1, y2], factor)
    angle = np.degrees(np.arctan2(yb - ya, xb - xa))
    return Candidate(z=z, line=Line.crossing(prep.shape, xa, ya, angle),
                     fwhm_px=2.3548 * FILTER_SIGMA * factor, scales=used)


def erase(prep, work, line, half_width):
    """Zero the binned pixels within ``half_width`` image pixels of a found streak, or, for a
    pair ``(negative side, positive side)``, that far on each side (plus a binned pixel)."""
    neg, pos = (half_width, half_width) if np.ndim(half_width) == 0 else half_width
    centre = prep.to_binned(line.shifted(0.5 * (pos - neg)))
    hw = 0.5 * (neg + pos) / prep.bin + 1.0
    yy, xx = band_pixels(work.shape, centre, hw, extend=hw)
    work[yy, xx] = 0


#: The search image is erased out to where a found streak's stacked profile drops below this
#: (binned-noise sigma): a bright streak's wings, tens of pixels out, would otherwise add up
#: along its length to a second, parallel detection.
ERASE_LEVEL = 0.1

#: Widest erased band, image pixels (each side).
MAX_ERASE = 300.0

#: A side of the erased band also stops at a valley of the (unclipped) stacked profile, below
#: :data:`~.measure.DIP_LEVEL` of its peak, beyond which the profile rises again by this many
#: times its bin noise: a close parallel streak, which must survive to be found next.
VALLEY_RISE = 6.0


def erase_half_width(prep, line, fwhm_px):
    """Image-pixel half-widths ``(negative side, positive side)`` of the band to erase around
    a found streak: out to where its stacked profile drops below :data:`ERASE_LEVEL`, plus one
    FWHM of margin, or to a valley before a neighbour (:data:`VALLEY_RISE`), without margin;
    :data:`MAX_ERASE` where the profile is cut (an image edge) or still above the level."""
    b = prep.to_binned(line)
    reach = MAX_ERASE / prep.bin
    yy, xx = band_pixels(prep.binned.shape, b, reach)
    _, d = b.coordinates(xx, yy)
    image = prep.binned if prep.zbinned is None else prep.zbinned
    profile, _ = stack_samples(d, image[yy, xx].astype(np.float64), reach, 0.5, 1.0,
                               b.angle_deg)
    sides = []
    near = fwhm_px / prep.bin
    for valley, level in zip(wing_reach(profile, ERASE_LEVEL, valley=VALLEY_RISE, near=near),
                             wing_reach(profile, ERASE_LEVEL, near=near)):
        if valley is not None and np.isfinite(valley) and level is not None and \
                np.isfinite(level) and valley < level - 1e-9:
            sides.append(float(prep.bin * valley))  # stops at the valley
        elif level is None or not np.isfinite(level):
            sides.append(MAX_ERASE)
        else:
            sides.append(float(min(MAX_ERASE, prep.bin * level + fwhm_px)))
    return tuple(sides)


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
        Least Hough significance of a detection (default: the calibrated false-alarm level)
        in a search image of at least :data:`MIN_LEVEL_SIZE` binned pixels a side; a smaller
        one (an image under 512 px) needs more (:func:`threshold_for`).
    max_streaks : int

    Returns
    -------
    list of Detection
        In order of decreasing significance.
    """
    if not (isinstance(threshold, (int, float, np.integer, np.floating))
            and np.isfinite(threshold) and threshold > 0):
        # A significance <= 0 passes every line of the noise.
        raise InputError("threshold", threshold, "must be a finite number > 0")
    work, valid = search_image(prep)
    norms = None if valid is None else hole_norms(valid, prep.bin, prep.levels)
    limit = threshold_for(work.shape, threshold, prep.bin)
    scales = None
    found, erased = [], []
    # Candidates that refinement rejects are erased too; a few spare rounds allow for them.
    for _ in range(max_streaks + 4):
        # Later rounds keep the first round's noise scales (see :func:`hough_peak`).
        cand = best_line(prep, work, scales, norms)
        scales = cand.scales
        if not cand.z >= limit:
            break
        coarse, width, z = cand.line, cand.fwhm_px, cand.z
        if coarse is None:  # cannot happen for a cell of this image's transform
            break
        # Pixels nearer to a streak already found are not this one's (a close neighbour).
        tr = trace_streak(prep, coarse, width, exclude=[d.line for d in found])
        if tr is None:
            erase(prep, work, coarse, 2 * width)
            continue
        sides = erase_half_width(prep, tr.line, tr.fwhm_px)
        erase(prep, work, tr.line, sides)
        if (any(_same_streak(tr.line, d.line, band) for d, band in zip(found, erased))
                and not _own_peak(tr)):
            continue  # leftover light of a streak already found
        found.append(Detection(line=tr.line, significance=z, filter_fwhm_px=width, trace=tr))
        erased.append(sides)
        if len(found) == max_streaks:
            break
    return _retrace_neighbours(prep, found)


#: Streaks within this angle (deg) and :data:`MAX_ERASE` of each other are neighbours.
NEIGHBOUR_ANGLE = 2.0


def _retrace_neighbours(prep, found):
    """Trace again, each without the other's pixels, the streaks that have a near-parallel
    neighbour: the first of a close pair was traced before the second was known, and the
    Hough line of two parallel ridges can run across both (a degree off), which refinement
    alone follows. A retrace that lands on another streak is dropped."""
    def near(a, b):
        return (angle_difference(a.angle_deg, b.angle_deg) < NEIGHBOUR_ANGLE
                and abs(a.offset_from(b)) < MAX_ERASE)

    out = list(found)
    for i, det in enumerate(found):
        others = [d.line for j, d in enumerate(out) if j != i]
        if not any(near(det.line, o) for o in others):
            continue
        tr = trace_streak(prep, det.line, det.trace.fwhm_px, exclude=others)
        if tr is None:
            continue
        if any(_same_streak(tr.line, o, (tr.fwhm_px, tr.fwhm_px)) for o in others):
            continue
        out[i] = replace(det, line=tr.line, trace=tr)
    return out


def search_image(prep):
    """A copy of the binned search image with the outer :data:`EDGE_GUARD` pixels set to 0,
    and, if the image has holes, every pixel within :data:`EDGE_GUARD` of one (a hole's edge
    is guarded as the image's are).

    Returns
    -------
    work : ndarray
    valid : ndarray or None
        float32, 1 where ``work`` holds data, 0 in holes and guards (None without holes).
    """
    work = prep.binned.copy()
    g = min(max(EDGE_GUARD, -(-EDGE_GUARD_PX // prep.bin)), min(work.shape) // 4)
    if g > 0:
        work[:g] = 0
        work[-g:] = 0
        work[:, :g] = 0
        work[:, -g:] = 0
    if prep.holes is None:
        return work, None
    valid = (~prep.holes).view(np.uint8)
    if g > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * g + 1, 2 * g + 1))
        valid = cv2.erode(valid, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    valid = valid.astype(np.float32)
    work *= valid
    return work, valid


def hole_norms(valid, bin_factor=BIN, levels=LEVELS):
    """Per pyramid level, the line counts of an image with holes (:func:`_hole_norm`): the
    usable fraction of each level's cells is the block mean of ``valid``, as the level's
    values are block means of the search image."""
    out = []
    for image, f in pyramid(valid, levels):
        out.append(_hole_norm(image, min_line_cells(image.shape, bin_factor * f)))
    return out


def _own_peak(trace):
    """Whether a traced line, its pixels nearer to the streaks already found left out, has a
    profile of its own (both half-maximum crossings measured): a close neighbour does, the
    wing of a found streak (rising to the cut at the midline) does not."""
    return bool(np.isfinite(profile_fwhm(trace.template, dip=DIP_LEVEL)[0]))


def _same_streak(a, b, band):
    """Whether line ``a`` runs along ``b`` inside the band erased around it (``(negative
    side, positive side)`` half-widths, px): the wings of one streak, not a neighbour."""
    if angle_difference(a.angle_deg, b.angle_deg) >= 1.0:
        return False
    offset = a.offset_from(b)
    return -band[0] < offset < band[1]


def max_significance(prep):
    """Largest Hough significance of an image (for calibrating :data:`FALSE_ALARM_Z`)."""
    work, valid = search_image(prep)
    norms = None if valid is None else hole_norms(valid, prep.bin, prep.levels)
    return best_line(prep, work, norms=norms).z
