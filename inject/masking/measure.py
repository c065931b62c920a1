"""Measuring a detected streak: its line, its extent and a model-free FWHM.

Everything here works on pixels gathered in a rectangle around the line (exact rasterisation,
:func:`~inject.masking.geometry.band_pixels`), each with its along-track ``t`` and cross-track
``d`` coordinate, and on **robust statistics per bin**: the interquartile mean (default) or the
median. A star on the track, a cosmic ray or a hot pixel moves them by a fraction of the noise
where it would move a mean by its whole flux; the interquartile mean has 13% less noise than
the median on Gaussian noise, which matters for the FWHM of a faint streak.

- :func:`refine_line`: the track is cut into segments; each segment's profile is matched to the
  stacked one to find its cross-track offset, and a weighted, clipped straight-line fit of the
  offsets against ``t`` corrects the line's position and angle (a 0.1 deg error would widen a
  stacked profile of a long streak by several percent); the stack's half-maximum midpoint
  fixes the absolute position.
- :func:`find_extent`: robust means along the line in bins, the most significant run of bins
  (streaks that end inside the image), then a step fit at each end on finer bins.
- :func:`measure_streak`: the profile stacked at sub-pixel cross-track distance (0.1-px bins),
  smoothed (quadratic Savitzky-Golay, which keeps the second moment), its outermost
  half-maximum crossings, with the pixel response removed, and a bootstrap over along-track
  segments for the error.
"""
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import curve_fit
from scipy.signal import savgol_coeffs, savgol_filter

from inject.masking.geometry import Line, band_pixels

#: The median of N Gaussian values scatters by sqrt(pi / 2) sigma / sqrt(N).
MEDIAN_NOISE = float(np.sqrt(np.pi / 2))

#: Scatter of a bin's statistic in units of sigma / sqrt(N), for Gaussian noise (the
#: interquartile mean has an efficiency of 0.837).
STAT_NOISE = {"median": MEDIAN_NOISE, "trimmed": float(1 / np.sqrt(0.837))}

#: Robust statistic of every stack (see :meth:`BinnedStack.trimmed_mean`).
STATISTIC = "trimmed"

#: Along-track bin of the extent search, px.
EXTENT_BIN = 16.0

#: Least S/N of the most significant run of bins along a candidate line.
MIN_TRACE_SNR = 3.0

#: Shortest streak accepted, px.
MIN_LENGTH = 2 * EXTENT_BIN

#: :func:`trace_streak` refines a line crossing the image a second time if the first
#: refinement's last step still moved it by this much (px) or turned it by this much (deg).
SETTLED_PX = 2.0
SETTLED_DEG = 0.05

#: Largest half-width of the window of a stacked profile, px.
MAX_WINDOW = 400.0

#: A profile bin holding fewer pixels than this fraction of the fullest bin's (or fewer than
#: 3) is not measured (see :func:`stack_samples`).
SPARSE_BIN = 0.05

#: Moffat index of the LSST ``maskStreaks`` line profile.
MOFFAT_BETA = 2.5


class BinnedStack:
    """Medians (or trimmed means) of values grouped in integer bins, for any weights, from a
    single sort.

    The values are sorted by (bin, value) once; a weighted median or trimmed mean of every bin
    is then a cumulative sum and a binary search, so a bootstrap replicate costs O(N).

    Parameters
    ----------
    bins : ndarray of int
        Bin of each value, ``0 <= bins < nbins``.
    values : ndarray
    nbins : int
    """

    def __init__(self, bins, values, nbins):
        bins = np.asarray(bins)
        values = np.asarray(values, dtype=np.float64)
        order = bin_value_order(bins, values)
        self.order = order
        self.values = values[order]
        counts = np.bincount(bins.ravel(), minlength=nbins)[:nbins] if bins.size else \
            np.zeros(nbins, dtype=np.intp)
        self.stop = np.cumsum(counts)
        self.start = self.stop - counts
        self._sums = self._top = self._fixed = None

    @classmethod
    def _from_sorted(cls, order, values, start, stop):
        new = cls.__new__(cls)
        new.order, new.values, new.start, new.stop = order, values, start, stop
        new._sums = new._top = new._fixed = None
        return new

    def subset(self, first, last):
        """The stack of bins ``first`` to ``last - 1`` alone (views, no new sort): their
        elements are contiguous in the sorted order."""
        a, b = self.start[first], self.stop[last - 1]
        return self._from_sorted(self.order[a:b], self.values[a:b],
                                 self.start[first:last] - a, self.stop[first:last] - a)

    def split(self, groups, ngroups):
        """The same values in bins ``group * nbins + bin`` (e.g. segments along the track
        times distance bins), ``groups`` given in the order of the values passed at
        construction: a stable radix sort of the groups in this stack's order, no new sort of
        the values."""
        nbins = self.start.size
        g = np.asarray(groups)[self.order]
        g = g.astype(np.uint8 if ngroups <= 256 else np.uint16 if ngroups <= 65536 else np.int64)
        perm = np.argsort(g, kind="stable")
        bins = np.repeat(np.arange(nbins), self.counts)[perm]
        counts = np.bincount(g[perm].astype(np.intp) * nbins + bins, minlength=ngroups * nbins)
        stop = np.cumsum(counts)
        return self._from_sorted(self.order[perm], self.values[perm], stop - counts, stop)

    @property
    def counts(self):
        return self.stop - self.start

    def median(self, weights=None, sorted_weights=None):
        """Weighted median of each bin (NaN for a bin of zero weight).

        ``weights`` are given in the order of the values passed at construction,
        ``sorted_weights`` in the sorted order.
        """
        cum = (self._cumulative(weights) if sorted_weights is None
               else _running_sum(np.asarray(sorted_weights, float)))
        total = cum[self.stop] - cum[self.start]
        target = cum[self.start] + 0.5 * total
        n = self.values.size
        # Element j carries the weight (cum[j], cum[j + 1]]: the lower median is the first
        # element reaching the target, the upper one the first exceeding it.
        lower = np.clip(np.searchsorted(cum, target, "left") - 1, 0, max(n - 1, 0))
        upper = np.clip(np.searchsorted(cum, target * (1 + 1e-12) + 1e-12, "left") - 1,
                        0, max(n - 1, 0))
        upper = np.minimum(upper, np.maximum(self.stop - 1, 0))
        out = np.full(total.shape, np.nan)
        ok = total > 0
        out[ok] = 0.5 * (self.values[lower[ok]] + self.values[upper[ok]])
        return out

    def trimmed_mean(self, weights=None, trim=0.25, sorted_weights=None):
        """Weighted mean of each bin's values between its ``trim`` and ``1 - trim`` quantiles.

        ``trim = 0.25`` is the interquartile mean: as robust as the median to a star covering
        less than a quarter of a bin, with 84% of the mean's efficiency on Gaussian noise
        (the median has 64%), i.e. 13% less noise than the median. ``trim -> 0.5`` tends to
        the median. ``weights`` are in the order of the values passed at construction,
        ``sorted_weights`` (faster, for bootstrap replicates) in the sorted order.
        """
        n = self.values.size
        unit = 1.0
        if weights is None and sorted_weights is None:
            cum = np.arange(n + 1, dtype=np.int64)
            if self._sums is None:  # unit weights: the running sum is computed once
                self._sums = _running_sum(self.values)
            sums = self._sums
        else:
            w = (np.asarray(weights)[self.order] if sorted_weights is None
                 else np.asarray(sorted_weights))
            if w.dtype.kind in "iu" and (w >= 0).all():
                # Counts (bootstrap draws): integer running sums, ~10x faster than float.
                cum = _running_sum(w.astype(np.int64, copy=False))
                sums, unit = self._fixed_point_sums(w, cum[-1])
            else:
                w = w.astype(float, copy=False)
                cum = _running_sum(w)
                sums = _running_sum(w * self.values)
        total = cum[self.stop] - cum[self.start]
        lo = cum[self.start] + trim * total
        hi = cum[self.start] + (1 - trim) * total

        def partial(q):
            # Weighted sum of the values up to cumulative weight q (a fraction of an element
            # counted where q falls inside it). For integer cum, cum[j] < q <=> cum[j] <
            # ceil(q): the search stays in integers (no float copy of cum).
            key = np.ceil(q).astype(np.int64) if cum.dtype.kind == "i" else q
            j = np.clip(np.searchsorted(cum, key, "left") - 1, 0, max(n - 1, 0))
            return sums[j] * unit + (q - cum[j]) * self.values[j]

        out = np.full(total.shape, np.nan)
        ok = total > 0
        out[ok] = (partial(hi[ok]) - partial(lo[ok])) / (hi[ok] - lo[ok])
        return out

    def _fixed_point_sums(self, counts, total):
        """Running sums of ``counts * values`` in int64 fixed point and the value of one unit.

        The values are rounded to ``2^-bits``, with ``bits`` (at most 40) as large as lets no
        sum of a total weight ``total`` overflow; float sums (unit 1) if that leaves fewer
        than 16 bits.
        """
        if self._top is None:
            self._top = float(np.abs(self.values).max()) if self.values.size else 0.0
        if not self._top > 0:
            return np.zeros(counts.size + 1, dtype=np.int64), 1.0
        bits = int(np.floor(61 - np.log2(self._top) - np.log2(max(int(total), 1))))
        if bits < 16:
            return _running_sum(counts * self.values), 1.0
        if self._fixed is None or self._fixed[0] > bits:
            # Two bits to spare, so that replicates with a larger total reuse these values.
            keep = min(bits - 2, 40) if bits >= 18 else bits
            self._fixed = (keep, np.rint(self.values * 2.0 ** keep).astype(np.int64))
        bits = self._fixed[0]
        return _running_sum(counts.astype(np.int64, copy=False) * self._fixed[1]), 2.0 ** -bits

    def _cumulative(self, weights):
        if weights is None:
            return np.arange(self.values.size + 1, dtype=np.float64)
        return _running_sum(np.asarray(weights, float)[self.order])


def _running_sum(x):
    """``[0, x0, x0 + x1, ...]`` (int64 for integers, else float64)."""
    out = np.empty(x.size + 1, dtype=np.int64 if x.dtype.kind in "iub" else np.float64)
    out[0] = 0
    np.cumsum(x, out=out[1:])
    return out


def bin_value_order(bins, values):
    """Permutation sorting by bin, then by value.

    One sort of int64 keys ``bin | value quantised | index`` (the index comes back out of
    the low bits): the value is quantised to ``2^-b`` of its range with ``b >= 24`` bits left
    by the bin and the index, so only values closer than that (ties, as far as any statistic
    is concerned) may come out of order. Twice as fast as an argsort of a float key, and 5
    times as fast as an argsort by value followed by a stable argsort by bin. Falls back to
    the float key ``bin + (value - min) / (2 (max - min))`` when fewer bits are left, and to
    the two argsorts for non-finite values.
    """
    n = values.size
    if n == 0:
        return np.zeros(0, dtype=np.intp)
    lo, hi = float(values.min()), float(values.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):  # NaN or inf: the general (slower) way
        by_value = np.argsort(values)
        return by_value[np.argsort(bins[by_value], kind="stable")]
    index_bits = max(1, (n - 1).bit_length())
    bin_bits = max(1, int(bins.max()).bit_length())
    value_bits = min(63 - index_bits - bin_bits, 52)  # 52: exact in a float64
    if value_bits >= 24:
        top = 2 ** value_bits - 1
        scale = top / (hi - lo) if hi > lo else 0.0
        key = ((values - lo) * scale).astype(np.int64)
        np.minimum(key, top, out=key)  # rounding must not carry into the bin's bits
        key <<= index_bits
        key |= np.arange(n, dtype=np.int64)
        key |= bins.astype(np.int64) << (value_bits + index_bits)
        key.sort()
        key &= (1 << index_bits) - 1
        return key.astype(np.intp, copy=False)
    key = bins.astype(np.float64)
    if hi > lo:
        key += (values - lo) * (0.5 / (hi - lo))
    return np.argsort(key)


def samples(prep, line, half_width, extend=0.0, exclude=()):
    """Usable pixels within ``half_width`` of ``line`` (between its ends, plus ``extend``).

    ``exclude``: lines of other streaks; a pixel nearer to one of them (within its extent)
    than to ``line`` is left out, so that a close parallel neighbour is not stacked into this
    streak's profile (its side of the profile is then cut at the midline, as at an image edge).

    Returns
    -------
    t, d, v : ndarray
        Along-track position from the line's centre, cross-track distance, residual value.
    """
    yy, xx = band_pixels(prep.shape, line, half_width, extend)
    v = prep.residual[yy, xx]
    ok = np.isfinite(v) & ~prep.star_at(yy, xx)
    t, d = line.coordinates(xx[ok], yy[ok])
    v = v[ok]
    if len(exclude):
        keep = np.ones(t.size, dtype=bool)
        xs, ys = xx[ok], yy[ok]
        for other in exclude:
            to, do = other.coordinates(xs, ys)
            # Beyond the other's ends by as much as the distance: its end caps.
            keep &= ~((np.abs(do) < np.abs(d)) & (np.abs(to) <= 0.5 * other.length + np.abs(d)))
        t, d, v = t[keep], d[keep], v[keep]
    return t, d, v.astype(np.float64)


@dataclass
class Profile:
    """A cross-track profile stacked over a streak (a robust statistic per distance bin).

    Attributes
    ----------
    distance : ndarray
        Bin centres, px from the line (positive on its left).
    value : ndarray
        Statistic per bin, baseline subtracted (image units per pixel), NaN for empty bins.
    count : ndarray
        Pixels per bin.
    noise : float
        Per-pixel noise (image units).
    baseline : float
        Local background subtracted (the statistic over the outer quarter of the window).
    angle_deg : float
        Track angle (for the pixel response).
    statistic : str
        ``"trimmed"`` (interquartile mean) or ``"median"`` per bin.
    """

    distance: np.ndarray
    value: np.ndarray
    count: np.ndarray
    noise: float
    baseline: float
    angle_deg: float
    statistic: str = STATISTIC

    @property
    def step(self):
        return float(self.distance[1] - self.distance[0])

    @property
    def bin_noise(self):
        """Noise of each bin's value."""
        return STAT_NOISE[self.statistic] * self.noise / np.sqrt(np.maximum(self.count, 1))

    @property
    def measured(self):
        """Bins between the first and the last that hold pixels: beyond them the window runs
        off the image, into a hole or past a neighbour's midline, and nothing is measured."""
        full = np.flatnonzero(self.count > 0)
        out = np.zeros(self.count.shape, dtype=bool)
        if full.size:
            out[full[0]:full[-1] + 1] = True
        return out

    def filled(self):
        """Values with empty bins interpolated from their neighbours (held constant beyond
        the measured bins: see :attr:`measured`)."""
        ok = np.isfinite(self.value)
        if ok.all():
            return self.value.copy()
        if not ok.any():
            return np.zeros_like(self.value)
        return np.interp(self.distance, self.distance[ok], self.value[ok])

    def smoothed(self, window_px=1.0):
        """Quadratic Savitzky-Golay smoothing over ``window_px``: it keeps the second moment,
        hence the width, of what it smooths."""
        f = self.filled()
        n = max(5, 2 * int(round(window_px / self.step / 2)) + 1)
        return savgol_filter(f, n, 2, mode="interp") if n < f.size else f


def pixel_response(step, angle_deg):
    """Kernel of the pixel response across a track, sampled every ``step`` px.

    A unit square pixel projects onto the normal of a track at angle ``a`` as the convolution
    of boxes ``|cos a|`` and ``|sin a|`` wide: a trapezoid (a box at 0 and 90 deg, a triangle at
    45 deg). Each sample is the trapezoid's mean over its bin; the kernel sums to 1.
    """
    a = np.radians(angle_deg)
    w1, w2 = abs(np.cos(a)), abs(np.sin(a))
    inner, outer = abs(w1 - w2) / 2, (w1 + w2) / 2
    n = int(np.ceil(outer / step)) + 1
    x = (np.arange(-n, n + 1)[:, None] + np.linspace(-0.5, 0.5, 33)[None, :]) * step
    u = np.abs(x)
    if outer - inner < 1e-9:
        density = (u <= outer).astype(float)
    else:
        density = np.clip((outer - u) / (outer - inner), 0, 1)
    kernel = density.mean(axis=1)
    return kernel / kernel.sum()


def remove_pixel_response(values, step, angle_deg):
    """One Van Cittert step, ``2 f - f * K``: the pixel response removed to second order.

    The pixel response widens a streak's FWHM by only ~0.2% (1.46"), and this step takes the
    stacked profile's FWHM to within 0.01% of the line-spread function's.
    """
    return 2 * values - np.convolve(values, pixel_response(step, angle_deg), mode="same")


#: A profile's half-maximum region is followed across dips down to this fraction of the peak
#: (the horns of a defocused streak, :func:`half_max_width`), but not across deeper ones,
#: which separate a close parallel neighbour: the horns of LSST streaks from 160 to 550 km
#: never dip below 0.51 of the peak, the valley between two streaks two mask widths apart
#: is below ~0.2.
DIP_LEVEL = 0.25


def half_max_width(distance, values, valid=None, dip=None):
    """Distance between the outermost half-maximum crossings of a smooth profile.

    A defocused cross-section can have two horns (and dip between them), so the crossings are
    the outermost ones, searched within 1.5 equivalent widths of the peak (further out, only
    noise can cross).

    Parameters
    ----------
    distance, values : ndarray
    valid : ndarray of bool, optional
        Bins where the profile is measured (see :attr:`Profile.measured`); the peak is looked
        for there, and a crossing whose bins are not valid is no crossing (the profile was cut
        by an image edge, a hole or a neighbour's midline).
    dip : float, optional
        Follow the region above half maximum only across dips that stay above ``dip`` times
        the peak (:data:`DIP_LEVEL`), so that a close neighbour's crossings are not taken;
        default: the outermost crossings within the reach, whatever the dips.

    Returns
    -------
    fwhm, centre, peak : float
        NaN when the profile has no positive peak or the crossings are outside the window
        (or outside the valid bins).
    """
    nan = (float("nan"),) * 3
    valid = np.ones(values.shape, dtype=bool) if valid is None else np.asarray(valid, bool)
    if not valid.any():
        return nan
    i = int(np.argmax(np.where(valid, values, -np.inf)))
    peak = float(values[i])
    if not peak > 0:
        return nan
    step = distance[1] - distance[0]
    reach = 1.5 * np.clip(np.where(valid, values, 0), 0, None).sum() * step / peak
    near = np.abs(distance - distance[i]) <= reach
    if dip is not None:
        # The run of bins above dip x peak around the peak.
        low = np.flatnonzero(values < dip * peak)
        left_low, right_low = low[low < i], low[low > i]
        first = left_low[-1] + 1 if left_low.size else 0
        last = right_low[0] - 1 if right_low.size else len(values) - 1
        near[:first] = False
        near[last + 1:] = False
    half = 0.5 * peak
    above = np.flatnonzero(near & (values >= half))
    lo, hi = above[0], above[-1]
    if lo == 0 or hi == len(values) - 1:
        return nan
    if not (valid[lo - 1] and valid[hi + 1]):
        return nan  # cut before it drops to half: unmeasurable
    if not (values[lo - 1] < half and values[hi + 1] < half):
        return nan  # a neighbour beyond the reach is above half: noise, no clean crossing

    def crossing(a, b):  # values[a] < half <= values[b]: never 0 / 0
        x, f = distance, values
        return x[a] + (half - f[a]) * (x[b] - x[a]) / (f[b] - f[a])

    left, right = crossing(lo - 1, lo), crossing(hi + 1, hi)
    return float(right - left), float(0.5 * (left + right)), peak


def _trusted(profile, smooth_px):
    """Measured bins at least a smoothing window plus 1 px inside the measured span (nearer
    the cut, the smoothing and the pixel-response step see the values held constant beyond
    it), or None when every bin holds pixels."""
    measured = profile.measured
    if measured.all():
        return None
    margin = int(np.ceil((0.5 * smooth_px + 1.0) / profile.step))
    inner = np.flatnonzero(measured)
    out = np.zeros(measured.shape, dtype=bool)
    if inner.size:
        a = inner[0] + (margin if inner[0] > 0 else 0)
        b = inner[-1] - (margin if inner[-1] < measured.size - 1 else 0)
        out[a:b + 1] = True
    return out


def profile_fwhm(profile, value=None, smooth_px=1.0, dip=None):
    """FWHM of a stacked profile, with and without the pixel response.

    Parameters
    ----------
    profile : Profile
    value : ndarray, optional
        Replacement values (a bootstrap replicate).
    smooth_px : float
    dip : float, optional
        See :func:`half_max_width`.

    Returns
    -------
    fwhm : float
        Of the line-spread function (pixel response removed); NaN when a half-maximum
        crossing falls where the profile is cut (an image edge, a hole, a neighbour).
    fwhm_pixelated : float
        Of the stacked pixel values.
    centre : float
        Midpoint of the half-maximum crossings, px from the line.
    peak : float
        Peak of the stacked pixel values (image units per pixel).
    """
    if value is not None:
        profile = replace(profile, value=value)
    valid = _trusted(profile, smooth_px)
    smooth = profile.smoothed(smooth_px)
    pixelated, _, peak = half_max_width(profile.distance, smooth, valid, dip)
    true = remove_pixel_response(smooth, profile.step, profile.angle_deg)
    fwhm, centre, _ = half_max_width(profile.distance, true, valid, dip)
    if not np.isfinite(peak) and valid is not None and valid.any():
        peak = float(np.max(smooth[valid]))
    return fwhm, pixelated, centre, peak


def peak_offset(profile, smooth_px=1.0):
    """Distance (px from the line) of the maximum of the smoothed profile, refined by a
    parabola, if it lies inside the measured bins (not at their end); else NaN. The position
    of a streak whose half-maximum crossings are not both measured (at an image edge)."""
    valid = _trusted(profile, smooth_px)
    valid = np.ones(profile.value.shape, bool) if valid is None else valid
    f = profile.smoothed(smooth_px)
    if not valid.any():
        return float("nan")
    i = int(np.argmax(np.where(valid, f, -np.inf)))
    if not (0 < i < f.size - 1 and valid[i - 1] and valid[i + 1]) or not f[i] > 0:
        return float("nan")
    curve = f[i - 1] - 2 * f[i] + f[i + 1]
    delta = 0.5 * (f[i - 1] - f[i + 1]) / curve if curve < 0 else 0.0
    return float(profile.distance[i] + np.clip(delta, -0.5, 0.5) * profile.step)


def _smoothing_px(profile, fwhm_px):
    """Savitzky-Golay window for the FWHM: ~1 px for a bright streak, wider at low S/N, up to
    0.45 FWHM (where the quadratic filter still biases the FWHM by < 0.2%)."""
    measured = profile.measured
    widest = max(1.0, 0.45 * fwhm_px)
    if not measured.any():
        return widest
    peak = np.nanmax(profile.smoothed(1.0)[measured])
    if not peak > 0:
        return widest
    per_px = (STAT_NOISE[profile.statistic] * profile.noise
              / np.sqrt(np.median(profile.count[profile.count > 0]) / profile.step))
    # Window where the smoothed peak is known to ~0.5%: noise / sqrt(window) <= 0.005 peak.
    return float(np.clip((per_px / (0.005 * peak)) ** 2, 1.0, widest))


def _distance_bins(d, half_width, bin_width):
    """Bin index of distances ``d`` on a grid of ``bin_width`` over ``[-half_width,
    half_width]`` (extended to whole bins), the number of bins and their centres."""
    nb = int(np.ceil(half_width / bin_width))
    bins = np.clip(np.floor(d / bin_width + nb).astype(int), 0, 2 * nb - 1)
    return bins, 2 * nb, (np.arange(2 * nb) - nb + 0.5) * bin_width


def stack_samples(d, v, half_width, bin_width, noise, angle_deg, statistic=None):
    """Robust profile of values ``v`` at cross-track distances ``d`` in ``[-half_width,
    half_width]``, baseline (the outer quarter of the window) subtracted.

    Parameters
    ----------
    statistic : {"trimmed", "median"}, optional
        Interquartile mean or median per bin (default :data:`STATISTIC`).

    Returns
    -------
    profile : Profile
    stack : BinnedStack
        The sorted stack (``profile.statistic`` of it gives the profile before the baseline).
    """
    statistic = STATISTIC if statistic is None else statistic
    bins, nbins, distance = _distance_bins(d, half_width, bin_width)
    stack = BinnedStack(bins, v, nbins)
    value = stack_statistic(stack, statistic)
    counts = stack.counts
    # A bin with a few pixels only (a corner of the band, cut by an edge or a neighbour's
    # midline) is noise, not profile: not measured.
    sparse = counts < max(3.0, SPARSE_BIN * counts.max(initial=0))
    if sparse.any():
        counts = np.where(sparse, 0, counts)
        value = np.where(sparse, np.nan, value)
    # The baseline comes from the same statistic as the profile: on skewed (Poisson) noise a
    # pixel median and an interquartile mean differ by a few percent of sigma, which is a few
    # percent of the peak of a faint streak.
    outer = (np.abs(distance) >= 0.75 * half_width) & np.isfinite(value)
    baseline = float(np.average(value[outer], weights=counts[outer])) if outer.any() else 0.0
    profile = Profile(distance=distance, value=value - baseline, count=counts, noise=noise,
                      baseline=baseline, angle_deg=angle_deg, statistic=statistic)
    return profile, stack


def stack_statistic(stack, statistic, weights=None, sorted_weights=None):
    """``"median"`` or ``"trimmed"`` (interquartile mean) of every bin of a stack (weights as
    in :meth:`BinnedStack.trimmed_mean`)."""
    if statistic == "median":
        return stack.median(weights, sorted_weights=sorted_weights)
    return stack.trimmed_mean(weights, sorted_weights=sorted_weights)


def stack_profile(prep, line, half_width, bin_width, trim=(0.0, 0.0), statistic=None,
                  exclude=()):
    """Robust profile across ``line`` over ``[-half_width, half_width]``.

    Parameters
    ----------
    prep : detect.Prepared
    line : Line
    half_width, bin_width : float
        px.
    trim : tuple of float
        Along-track lengths left out at the start and end (end caps of a streak that ends
        inside the image).
    statistic : {"trimmed", "median"}, optional
    exclude : sequence of Line
        Other streaks (see :func:`samples`).

    Returns
    -------
    profile : Profile
    stack : BinnedStack
        The sorted stack behind the profile.
    t : ndarray
        Along-track position of each stacked pixel (in the order ``stack.order`` refers to).
    """
    t, d, v = samples(prep, line, half_width, exclude=exclude)
    half = 0.5 * line.length
    keep = (t >= -half + trim[0]) & (t <= half - trim[1])
    t, d, v = t[keep], d[keep], v[keep]
    profile, stack = stack_samples(d, v, half_width, bin_width, prep.sigma, line.angle_deg,
                                   statistic)
    return profile, stack, t


def _segment_shifts(profiles, weights, template, distance, max_shift):
    """Cross-track shift of each segment's profile against the template (least squares with
    a free amplitude and offset, on a grid of shifts refined by a parabola).

    Returns
    -------
    shift, amplitude : ndarray
        Per segment; NaN where no positive match exists.
    """
    step = distance[1] - distance[0]
    grid = np.arange(-max_shift, max_shift + 0.25 * step, 0.5 * step)
    shifted = np.stack([np.interp(distance - s, distance, template, left=0, right=0)
                        for s in grid])                                  # (ns, nb)
    w, p = weights, profiles                                             # (nseg, nb)
    sw, swp = w.sum(1), (w * p).sum(1)
    swpp = (w * p * p).sum(1)
    # einsum, not matmul: these products are small, and OpenBLAS threads woken right after
    # OpenCV's parallel transforms contend with them for the cores (~50 ms per call on 2).
    swt = np.einsum("ij,kj->ik", w, shifted)
    swtt = np.einsum("ij,kj->ik", w, shifted ** 2)
    swtp = np.einsum("ij,kj->ik", w * p, shifted)
    det = sw[:, None] * swtt - swt ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        amp = (sw[:, None] * swtp - swt * swp[:, None]) / det
        off = (swp[:, None] - amp * swt) / sw[:, None]
    chi2 = swpp[:, None] - amp * swtp - off * swp[:, None]
    chi2 = np.where(np.isfinite(chi2) & (amp > 0), chi2, np.inf)
    best = np.argmin(chi2, axis=1)
    rows = np.arange(len(best))
    shift = grid[best].astype(float)
    inner = (best > 0) & (best < len(grid) - 1)
    c0, c1, c2 = (chi2[rows[inner], best[inner] + k] for k in (-1, 0, 1))
    curve = c0 - 2 * c1 + c2
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(curve > 0, 0.5 * (c0 - c2) / curve, 0.0)
    shift[inner] += np.clip(np.nan_to_num(delta), -1, 1) * (grid[1] - grid[0])
    amplitude = amp[rows, best]
    bad = ~np.isfinite(chi2[rows, best]) | (best == 0) | (best == len(grid) - 1)
    shift[bad], amplitude[bad] = np.nan, np.nan
    return shift, amplitude


def _main_bump(template, smooth_px=1.0):
    """Bins of a template profile that belong to its main streak: all of them, unless the
    profile falls below :data:`DIP_LEVEL` of its peak and rises again above half of it (a
    close parallel neighbour in the window), in which case the bins beyond the valley between
    them are left out; bool."""
    f = template.smoothed(smooth_px)
    keep = np.ones(f.shape, dtype=bool)
    i = int(np.argmax(f))
    peak = f[i]
    if not peak > 0:
        return keep
    for idx in (np.arange(i, -1, -1), np.arange(i, f.size)):
        fs = f[idx]
        low = np.flatnonzero(fs < DIP_LEVEL * peak)
        if not low.size:
            continue
        again = np.flatnonzero(fs[low[0]:] > 0.5 * peak)
        if again.size:
            j = low[0] + again[0]
            valley = low[0] + int(np.argmin(fs[low[0]:j]))
            keep[idx[valley:]] = False
    return keep


#: A segment weighs at most this many times the median of the heaviest third
#: (:func:`_robust_line_fit`): the streak's own segments, unless it covers under a sixth of
#: the line.
MAX_SEGMENT_WEIGHT = 2.0


def _weighted_median(x, w):
    """Median of ``x`` with weights ``w`` (the first value reaching half the total weight)."""
    order = np.argsort(x)
    cum = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _robust_line_fit(t, s, w):
    """Offset and slope of ``s = a + b t``, weighted by ``w`` (~ 1 / error), with 3-sigma
    clipping of the weighted residuals (2 points: exact; 1: offset only).

    A segment far brighter than the rest of a streak is a star or a galaxy beside it, not a
    better measure of its position, and a single heavy outlier pulls a least-squares start so
    far that every other point looks as far off as it: the weights are capped at
    :data:`MAX_SEGMENT_WEIGHT` times the median of the heaviest third, and the first clipping
    is about a weighted Theil-Sen line (weighted medians of the pairwise slopes, pair weight
    ``w_i w_j``, and of the offsets), which segments beyond the streak's ends, of little
    weight, do not move either.
    """
    ok = np.isfinite(s) & (w > 0)
    t, s, w = t[ok], s[ok], w[ok]
    if s.size == 0:
        return 0.0, 0.0
    if s.size < 3:
        if s.size == 2 and t[1] != t[0]:
            b = (s[1] - s[0]) / (t[1] - t[0])
            return float(s[0] - b * t[0]), float(b)
        return float(np.average(s, weights=w)), 0.0
    top = np.sort(w)[-max(1, s.size // 3):]
    w = np.minimum(w, MAX_SEGMENT_WEIGHT * np.median(top))
    i, j = np.triu_indices(s.size, 1)
    dt = t[j] - t[i]
    pair = dt != 0
    b = (_weighted_median((s[j] - s[i])[pair] / dt[pair], (w[i] * w[j])[pair])
         if pair.any() else 0.0)
    a = _weighted_median(s - b * t, w)
    res = (s - (a + b * t)) * w / np.median(w)
    keep = np.abs(res) <= 3 * max(1.4826 * np.median(np.abs(res)), 0.02)
    if keep.sum() < 3:
        keep[:] = True
    for _ in range(5):
        b, a = np.polyfit(t[keep], s[keep], 1, w=w[keep])
        res = (s - (a + b * t)) * w / np.median(w[keep])
        scale = max(1.4826 * np.median(np.abs(res[keep])), 0.02)
        new = np.abs(res) <= 3 * scale
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    return float(a), float(b)


def refine_line(prep, line, width_px, iterations=3, exclude=(), converged=None):
    """Correct a line's position and angle from the cross-track offsets of its segments.

    Parameters
    ----------
    prep : detect.Prepared
    line : Line
        First estimate; its endpoints bound the pixels used.
    width_px : float
        Estimate of the streak's FWHM (sets the first window).
    iterations : int
        At most; it stops when the line moves by less than 0.05 px.
    exclude : sequence of Line
        Streaks already found (see :func:`samples`).
    converged : list, optional
        If given, the last step's move is appended: ``(offset px, rotation deg)`` (both
        small if it converged, else ``iterations`` ran out).

    Returns
    -------
    line : Line
        Same along-track extent, corrected across.
    template : Profile
        The stacked profile (0.5-px bins) about the line before the last (< 0.05 px) step.
    snr : float
        Matched-filter S/N of the whole streak (from the template).
    """
    half_width = max(2.5 * width_px, 10.0) + 4.0
    bw = 0.5
    max_shift = 0.5 * half_width
    snr, template = 0.0, None
    moved = (float("inf"), float("inf"))
    for _ in range(iterations):
        t, d, v = samples(prep, line, half_width, exclude=exclude)
        if t.size == 0:
            break
        template, stack = stack_samples(d, v, half_width, bw, prep.sigma, line.angle_deg)
        # A close neighbour in the window would pull the segments' shifts towards it.
        tpl = np.where(_main_bump(template), np.nan_to_num(template.value), 0.0)
        length = max(line.length, 1.0)
        # S/N^2 of the stack, less what the noise of the bins themselves contributes.
        per_bin = length * bw / STAT_NOISE[template.statistic] ** 2
        snr2 = float(np.sum(per_bin * (tpl / template.noise) ** 2) - tpl.size)
        snr = float(np.sqrt(max(snr2, 0.0)))
        # Segments with S/N ~ 8 each locate to ~ FWHM / 20; never shorter than the window.
        nseg = int(np.clip(snr2 / 64, 1, max(1.0, min(64, length / (2 * half_width)))))
        seg_len = length / nseg
        seg = np.clip(((t + 0.5 * length) / seg_len).astype(int), 0, nseg - 1)
        nb = template.value.size
        per_segment = stack.split(seg, nseg)
        prof = (stack_statistic(per_segment, template.statistic)
                - template.baseline).reshape(nseg, nb)
        weights = ((per_segment.counts.reshape(nseg, nb) > 0)
                   & (template.count > 0)[None, :]).astype(float)
        shifts, amplitude = _segment_shifts(np.nan_to_num(prof), weights, tpl,
                                            template.distance, max_shift)
        # A segment's offset error scales as 1 / (amplitude sqrt(pixels)): segments off the
        # streak (beyond its end) weigh nothing, and one cut by an edge or a hole weighs by
        # its share of a whole segment's pixels (its few pixels' amplitude is noisy, and a
        # high one alone would pull the fit). It stands at the mean position of its pixels.
        n = np.bincount(seg, minlength=nseg).astype(float)
        whole = np.median(n[n > 0]) if (n > 0).any() else 1.0
        centres = np.where(n > 0, np.bincount(seg, t, nseg) / np.maximum(n, 1),
                           (np.arange(nseg) + 0.5) * seg_len - 0.5 * length)
        weight = np.clip(np.nan_to_num(amplitude), 0, None) * np.sqrt(np.minimum(n / whole, 1))
        a, b = _robust_line_fit(centres, shifts, weight)
        if nseg < 3:
            b = 0.0 if nseg == 1 else b
        # Shifts are relative to the template, which sits where the line was: its own centre
        # (half-maximum midpoint) gives the absolute offset; near an image edge or a hole,
        # where one crossing is cut, the template's peak does.
        fwhm, _, centre, _ = profile_fwhm(template, dip=DIP_LEVEL)
        if not np.isfinite(centre):
            centre = peak_offset(template)
        a += centre if np.isfinite(centre) and abs(centre) < 0.5 * half_width else 0.0
        line = line.shifted(a, b)
        moved = (abs(a), float(np.degrees(np.arctan(abs(b)))))
        if abs(a) < 0.05 and abs(b) * 0.5 * length < 0.05:
            break
        # The first window allowed for a coarse line and a guessed width; now both are known.
        max_shift = min(max_shift, 3.0)
        if np.isfinite(fwhm):
            half_width = min(half_width, max(2.5 * fwhm, 8.0) + 3.0)
    if converged is not None:
        converged.append(moved)
    return line, template, snr


@dataclass
class Extent:
    """Where a streak runs along its line.

    Attributes
    ----------
    t0, t1 : float
        Start and end, px along the chord from its centre.
    at_edge : tuple of bool
        Whether each end is the image edge (the streak runs off the image there).
    amplitude : float
        Median charge per core pixel (image units).
    snr : float
        S/N of the run of bins found.
    """

    t0: float
    t1: float
    at_edge: tuple
    amplitude: float
    snr: float


def _best_run(z):
    """Indices ``(a, b)`` of the run of bins with the highest ``sum(z) / sqrt(length)``."""
    c = np.concatenate(([0.0], np.cumsum(z)))
    n = z.size
    i, j = np.triu_indices(n)
    score = (c[j + 1] - c[i]) / np.sqrt(j - i + 1)
    k = int(np.argmax(score))
    return int(i[k]), int(j[k]), float(score[k])


def _step_position(t, v, lo, hi, level, rising, bin_len):
    """Along-track position of a step from 0 to ``2 * level`` (rising) or back, in [lo, hi]:
    the split maximising the summed excess over ``level`` on the streak's side."""
    nbins = max(int(np.ceil((hi - lo) / bin_len)), 1)
    sel = (t >= lo) & (t < hi)
    if sel.sum() < 2 * nbins:
        return None
    k = np.clip(((t[sel] - lo) / bin_len).astype(int), 0, nbins - 1)
    stack = BinnedStack(k, v[sel], nbins)
    m = np.nan_to_num(stack_statistic(stack, STATISTIC) - level) * np.sqrt(stack.counts)
    # Splitting before bin e: rising keeps bins e.., falling keeps bins ..e-1.
    tail = np.concatenate((np.cumsum(m[::-1])[::-1], [0.0]))
    head = np.concatenate(([0.0], np.cumsum(m)))
    e = int(np.argmax(tail if rising else head))
    return lo + e * bin_len


def find_extent(prep, chord, core_half_width, bin_len=EXTENT_BIN, exclude=()):
    """Where along ``chord`` the streak is: most significant run of along-track bins, ends
    refined by step fits on 4x finer bins.

    Returns
    -------
    Extent or None
        None when the run is shorter than :data:`MIN_LENGTH` or below :data:`MIN_TRACE_SNR`.
    """
    t, _, v = samples(prep, chord, core_half_width, exclude=exclude)
    length = chord.length
    nk = max(1, int(np.ceil(length / bin_len)))
    k = np.clip(((t + 0.5 * length) / bin_len).astype(int), 0, nk - 1)
    stack = BinnedStack(k, v, nk)
    m = stack_statistic(stack, STATISTIC)
    n = stack.counts
    noise = STAT_NOISE[STATISTIC] * prep.sigma / np.sqrt(np.maximum(n, 1))
    z = np.where(n > 0, np.nan_to_num(m) / noise, 0.0)
    # A bright star on the line is one bin far above the streak's: clipped at the 90th
    # percentile (the streak's own level when it covers a tenth of the chord), it cannot
    # outweigh the run of the streak.
    z = np.minimum(z, max(5.0, float(np.percentile(z, 90))))
    a, b, snr = _best_run(z)
    if snr < MIN_TRACE_SNR:
        return None
    amplitude = float(np.nanmedian(m[a:b + 1]))
    # A run that stops within 3 bins of the image edge is a streak running off the image:
    # noise in the last bins should not leave its end unmasked.
    start_edge, end_edge = a <= 2, b >= nk - 3
    t0 = -0.5 * length + a * bin_len
    t1 = -0.5 * length + (b + 1) * bin_len
    fine = bin_len / 4
    if not start_edge:
        pos = _step_position(t, v, t0 - 2 * bin_len, t0 + 2 * bin_len, 0.5 * amplitude,
                             True, fine)
        t0 = t0 if pos is None else pos
    if not end_edge:
        pos = _step_position(t, v, t1 - 2 * bin_len, t1 + 2 * bin_len, 0.5 * amplitude,
                             False, fine)
        t1 = t1 if pos is None else pos
    t0 = -0.5 * length if start_edge else t0
    t1 = 0.5 * length if end_edge else t1
    if t1 - t0 < MIN_LENGTH:
        return None
    return Extent(float(t0), float(t1), (start_edge, end_edge), amplitude, snr)


@dataclass
class Trace:
    """A detected streak located: refined line over its extent and first profile.

    Attributes
    ----------
    line : Line
        Refined line from the streak's start to its end inside the image.
    at_edge : tuple of bool
        Whether the start / end is at the image edge.
    template : Profile
        Stacked profile (0.5-px bins) about ``line``.
    snr : float
        Matched-filter S/N of the streak.
    fwhm_px : float
        FWHM of the template (a first estimate).
    """

    line: Line
    at_edge: tuple
    template: Profile
    snr: float
    fwhm_px: float


def trace_streak(prep, coarse, width_px, exclude=()):
    """Locate a candidate streak: refine the line over the whole chord, find the extent,
    refine over the extent, find the extent again.

    Parameters
    ----------
    prep : detect.Prepared
    coarse : Line
        Chord of the candidate line across the image (from the Hough peak).
    width_px : float
        FWHM estimate (of the best matched filter).
    exclude : sequence of Line
        Streaks already found (see :func:`samples`).

    Returns
    -------
    Trace or None
        None if no significant streak lies along the line.
    """
    # A bright streak is a broad ridge in the clipped search image, so the Hough peak can be
    # a degree off: refine over the whole chord first (segments beyond the streak's ends
    # carry no weight), then find the extent, then refine over the extent alone.
    converged = []
    line, template, snr = refine_line(prep, coarse, width_px, exclude=exclude,
                                      converged=converged)
    if template is None:  # no usable pixel along the line
        return None
    # A coarse line a few tenths of a degree off can leave the first refinement still
    # turning it by tenths of a degree (not the jitter of a faint streak, hundredths): then a
    # second one, even for a streak crossing the image.
    settled = converged[0][0] < SETTLED_PX and converged[0][1] < SETTLED_DEG
    for attempt in range(2):
        fwhm, _, _, _ = profile_fwhm(template, dip=DIP_LEVEL)
        fwhm = float(fwhm) if np.isfinite(fwhm) else width_px
        chord = Line.crossing(prep.shape, *line.centre, line.angle_deg)
        if chord is None:
            return None
        extent = find_extent(prep, chord, max(0.5 * fwhm, 1.0), exclude=exclude)
        if extent is None:
            return None
        line = chord.trimmed(extent.t0, extent.t1)
        if attempt == 1 or (extent.at_edge == (True, True) and settled):
            break
        line, template, snr = refine_line(prep, line, fwhm, exclude=exclude)
    return Trace(line=line, at_edge=extent.at_edge, template=template, snr=snr, fwhm_px=fwhm)


def _gaussian(d, amp, mu, sigma):
    return amp * np.exp(-0.5 * ((d - mu) / sigma) ** 2)


def _moffat(d, amp, mu, alpha):
    return amp * (1 + ((d - mu) / alpha) ** 2) ** -MOFFAT_BETA


#: FWHM of the Moffat profile in units of its scale ``alpha``.
MOFFAT_FWHM_PER_ALPHA = 2 * np.sqrt(2 ** (1 / MOFFAT_BETA) - 1)
GAUSSIAN_FWHM_PER_SIGMA = 2 * np.sqrt(2 * np.log(2))


def fit_width(profile, model, fwhm_guess):
    """Least-squares scale of a Gaussian (sigma) or LSST-style Moffat (alpha) profile.

    Returns NaN if the fit fails.
    """
    func, per = {"gaussian": (_gaussian, GAUSSIAN_FWHM_PER_SIGMA),
                 "moffat": (_moffat, MOFFAT_FWHM_PER_ALPHA)}[model]
    ok = np.isfinite(profile.value) & (profile.count > 0)
    d, y, err = profile.distance[ok], profile.value[ok], profile.bin_noise[ok]
    if y.size < 5:
        return float("nan")
    p0 = (max(float(np.max(y)), 1e-30), 0.0, fwhm_guess / per)
    try:
        params, _ = curve_fit(func, d, y, p0=p0, sigma=err, absolute_sigma=True,
                              bounds=([0, -np.inf, 1e-3], [np.inf, np.inf, np.inf]),
                              maxfev=2000)
    except (RuntimeError, ValueError):
        return float("nan")
    return float(abs(params[2]))


@dataclass
class Measurement:
    """The measured streak.

    Attributes
    ----------
    line : Line
        Refined central line over the streak's extent.
    at_edge : tuple of bool
    fwhm_px : float
        FWHM of the line-spread function (pixel response removed): compare with the truth
        ``fwhm_arcsec / pixel_scale``.
    fwhm_err_px : float
        Bootstrap standard deviation over along-track segments.
    fwhm_pixelated_px : float
        FWHM of the stacked pixel values (pixel response included).
    peak : float
        Peak of the stacked profile, image units per pixel.
    profile : Profile
    gaussian_sigma_px, moffat_alpha_px : float
        Scales of Gaussian and Moffat (beta 2.5) fits, for the LSST and acstools mask rules.
    snr : float
        Matched-filter S/N of the streak.
    width_px : float
        ``fwhm_px``, or the detection's width estimate where the FWHM could not be measured
        (a streak too faint for its half-maximum crossings, or cut by an image edge, a hole or
        a neighbour): what mask floors use.
    fwhm_measured : bool
        Whether ``fwhm_px`` was measured (else it is NaN).
    """

    line: Line
    at_edge: tuple
    fwhm_px: float
    fwhm_err_px: float
    fwhm_pixelated_px: float
    peak: float
    profile: Profile
    gaussian_sigma_px: float
    moffat_alpha_px: float
    snr: float
    width_px: float
    bootstrap: np.ndarray | None = field(repr=False, default=None)
    fwhm_measured: bool = True


def measure_streak(prep, trace, wing_level=None, n_boot=50, seed=1, statistic=None,
                   exclude=()):
    """Model-free FWHM of a traced streak, with a bootstrap error.

    Parameters
    ----------
    prep : detect.Prepared
    trace : Trace
    wing_level : float, optional
        Surface brightness (image units per pixel) the window must reach below inside its
        inner 60% (so the baseline and the surface-brightness mask width are measured); by
        default 1 sigma of the sky noise.
    n_boot : int
        Bootstrap replicates (segments of the track drawn with replacement).
    seed : int
    statistic : {"trimmed", "median"}, optional
        Per-bin statistic of the stack (default :data:`STATISTIC`, the interquartile mean).
    exclude : sequence of Line
        The other streaks of the image: pixels nearer to one of them are not stacked (see
        :func:`samples`), so a close parallel neighbour cuts this profile at the midline
        between them, as an image edge does.

    Returns
    -------
    Measurement
        ``fwhm_px`` is NaN and ``fwhm_measured`` False when a half-maximum crossing is not
        measured (the streak runs within about half a FWHM of an image edge, a hole or a
        neighbour's midline).
    """
    line = trace.line
    fwhm0 = trace.fwhm_px
    level = prep.sigma if wing_level is None else wing_level
    half_width = max(6 * fwhm0, 30.0)
    length = line.length
    cap = min(2 * fwhm0, 0.2 * length)
    trim = tuple(0.0 if edge else cap for edge in trace.at_edge)
    usable = max(length - sum(trim), 1.0)
    # ~60 pixels per bin at least: a median of fewer is too noisy to place a crossing.
    bin_width = float(np.clip(60.0 / usable, 0.1, 0.5))
    while True:
        profile, stack, t = stack_profile(prep, line, half_width, bin_width, trim, statistic,
                                          exclude)
        # NaN: neither side measured (cut by edges, holes or neighbours); a wider window
        # would not help.
        reach = wing_half_width(profile, level)
        if (reach is not None and not reach > 0.6 * half_width) or half_width >= MAX_WINDOW:
            break
        half_width = min(MAX_WINDOW, 2 * half_width if reach is None else reach / 0.5)
    smooth = _smoothing_px(profile, fwhm0)
    fwhm, pixelated, _, peak = profile_fwhm(profile, smooth_px=smooth)
    replicates = _bootstrap(profile, stack, t, smooth, usable,
                            fwhm if np.isfinite(fwhm) else fwhm0, n_boot, seed)
    ok = np.isfinite(replicates)
    err = float(np.std(replicates[ok], ddof=1)) if ok.sum() > 2 else float("nan")
    guess = fwhm if np.isfinite(fwhm) else fwhm0
    return Measurement(line=line, at_edge=trace.at_edge, fwhm_px=fwhm, fwhm_err_px=err,
                       fwhm_pixelated_px=pixelated, peak=peak, profile=profile,
                       gaussian_sigma_px=fit_width(profile, "gaussian", guess),
                       moffat_alpha_px=fit_width(profile, "moffat", guess),
                       snr=trace.snr, width_px=guess, bootstrap=replicates,
                       fwhm_measured=bool(np.isfinite(fwhm)))


def _bootstrap(profile, stack, t, smooth, length, fwhm, n_boot, seed):
    """FWHMs of ``n_boot`` replicates of the stack, with along-track segments (8-40 of them,
    ~50 px long) drawn with replacement.

    Only the bins within 1 FWHM plus the smoothing window plus 3 px of the line are
    restacked (the half-maximum crossings, at half a FWHM, and the peak lie well inside); the
    outer bins and the baseline keep their values. The restacked bins are a
    contiguous slice of the sorted stack (no new sort), a replicate is two running sums over
    it, and smoothing and pixel-response removal, both linear, are applied to all replicates'
    changes at once (:func:`replicate_fwhms`).
    """
    replicates = np.full(n_boot, np.nan)
    step = profile.step
    reach = step * np.ceil((fwhm + smooth + 3) / step)
    restacked = np.flatnonzero(np.abs(profile.distance) < reach)
    if n_boot <= 0 or restacked.size == 0:
        return replicates
    first, last = int(restacked[0]), int(restacked[-1]) + 1
    sub = stack.subset(first, last)
    if sub.values.size == 0:
        return replicates
    ti = t[sub.order]
    nseg = int(np.clip(length / 50, 8, 40))
    seg = np.clip(((ti - ti.min()) / (np.ptp(ti) + 1e-9) * nseg).astype(int), 0, nseg - 1)
    rng = np.random.default_rng(seed)
    inner = np.empty((n_boot, last - first))
    for r in range(n_boot):
        draws = np.bincount(rng.integers(0, nseg, nseg), minlength=nseg)
        inner[r] = stack_statistic(sub, profile.statistic, sorted_weights=np.take(draws, seg))
    return replicate_fwhms(profile, inner - profile.baseline, first, smooth)


def replicate_fwhms(profile, inner, first, smooth_px):
    """FWHM (pixel response removed) of ``profile`` with bins ``first, first + 1, ...``
    replaced by each row of ``inner``; the same as :func:`profile_fwhm` of each replicate.

    Savitzky-Golay smoothing and the Van Cittert step are linear, so a replicate's final
    profile is the original one plus one convolution of its change, exact while the change
    stays a smoothing window away from the profile's ends; otherwise (or where a bin is empty)
    :func:`profile_fwhm` is called.
    """
    nb = profile.value.size
    last = first + inner.shape[1]
    n = max(5, 2 * int(round(smooth_px / profile.step / 2)) + 1)
    smoothing = savgol_coeffs(n, 2) if n < nb else np.ones(1)
    response = pixel_response(profile.step, profile.angle_deg)
    # 2 S - K * S (remove_pixel_response after smoothing) as one kernel; both are odd-sized
    # and centred, so padding S by half of K's extra length aligns them.
    kernel = (2 * np.pad(smoothing, (response.size - 1) // 2)
              - np.convolve(smoothing, response))
    exact = (np.isfinite(profile.value).all() and first >= n and last <= nb - n
             and kernel.size <= nb)
    out = np.full(inner.shape[0], np.nan)
    base = remove_pixel_response(profile.smoothed(smooth_px), profile.step, profile.angle_deg)
    for r, row in enumerate(inner):
        if exact and np.isfinite(row).all():
            delta = np.zeros(nb)
            delta[first:last] = row - profile.value[first:last]
            true = base + np.convolve(delta, kernel, mode="same")
            out[r] = half_max_width(profile.distance, true)[0]
        else:
            value = profile.value.copy()
            value[first:last] = row
            out[r] = profile_fwhm(profile, value, smooth_px)[0]
    return out


def wing_reach(profile, level, smooth_px=2.0, valley=None, near=None):
    """How far each side of the profile stays above ``level``, walking out from the peak.

    Parameters
    ----------
    profile : Profile
    level : float
    smooth_px : float
    valley : float, optional
        Also stop a side at a valley: a minimum beyond which the profile rises again by more
        than ``valley`` times its bin noise (a neighbouring streak), at the minimum.
    near : float, optional
        Look for the peak within this distance of the line (px) only: a brighter neighbour
        in the window is not this streak's peak. Default: anywhere.

    Returns
    -------
    left, right : float or None
        Distances (px, >= 0) from the line on the negative and positive side where the profile
        drops below ``level`` (interpolated; or the valley's); None where the window ends
        first (it is too small); NaN where the measured bins end first (the profile is cut by
        an image edge, a hole or a neighbour's midline: that side is not measured). Both 0 if
        the peak is below ``level``.
    """
    measured = profile.measured
    if not measured.any():
        return float("nan"), float("nan")
    f = profile.smoothed(smooth_px)
    d = profile.distance
    allowed = measured if near is None else measured & (np.abs(d) <= max(near, profile.step))
    if not allowed.any():
        allowed = measured
    i = int(np.argmax(np.where(allowed, f, -np.inf)))
    if not f[i] > level:
        return 0.0, 0.0
    noise = profile.bin_noise

    def side(idx):
        fs, ms = f[idx], measured[idx]
        below = np.flatnonzero(fs < level)
        stop = below[0] if below.size else None
        cut = np.flatnonzero(~ms)
        cut = cut[0] if cut.size else None
        if valley is not None:
            low = np.minimum.accumulate(fs)
            where_low = np.maximum.accumulate(np.where(fs <= low, np.arange(fs.size), 0))
            # Only below DIP_LEVEL of the peak: a defocused streak's horns dip less.
            rise = np.flatnonzero((fs - low > valley * noise[idx][where_low])
                                  & (low < DIP_LEVEL * f[i]))
            if rise.size and (stop is None or rise[0] < stop) and (cut is None
                                                                    or rise[0] < cut):
                return float(abs(d[idx[where_low[rise[0]]]]))
        if cut is not None and (stop is None or cut <= stop):
            return float("nan")
        if stop is None:
            return None
        a, b = idx[stop - 1], idx[stop]  # a above, b below
        return float(abs(d[a] + (f[a] - level) * (d[b] - d[a]) / (f[a] - f[b])))

    return side(np.arange(i, -1, -1)), side(np.arange(i, f.size))


def wing_half_width(profile, level, smooth_px=2.0, valley=None, near=None):
    """Half-width (px from the line) where the profile drops below ``level`` for good.

    Walks out from the peak on each side to the first point below ``level`` and returns the
    larger distance of the sides that are measured (:func:`wing_reach`); 0 if the peak is
    below ``level``; None if a side never drops below it inside the window (the window is too
    small); NaN if neither side is measured (both are cut by edges, holes or neighbours).
    """
    sides = wing_reach(profile, level, smooth_px, valley, near)
    if any(r is None for r in sides):
        return None
    finite = [r for r in sides if np.isfinite(r)]
    return float(max(finite)) if finite else float("nan")
