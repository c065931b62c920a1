"""Straight streak lines on the pixel grid and the pixels of rectangles around them.

Conventions are those of :mod:`inject.trajectory`: pixel ``(0, 0)`` is the centre of the first
pixel, ``x`` along columns, ``y`` along rows (numpy index ``[y, x]``), angles in degrees
counter-clockwise from ``+x``. A pixel belongs to a rectangle when its *centre* lies inside or
on the boundary, so counts are exact and reproducible by hand.
"""
from dataclasses import dataclass

import numpy as np

from inject.trajectory import Segment

#: Slack on the rectangle test so that centres exactly on the boundary count despite rounding.
_EDGE_EPS = 1e-9


@dataclass(frozen=True)
class Line:
    """A streak's central line from ``(x0, y0)`` to ``(x1, y1)`` (pixels).

    The endpoints are where the streak starts and ends inside the image (at the image edge for a
    streak that crosses it). Distances across the track are positive on the left of the
    direction of motion (along the normal ``(-sin, cos)``).
    """

    x0: float
    y0: float
    x1: float
    y1: float

    @classmethod
    def through(cls, x, y, angle_deg, t0, t1):
        """The line through ``(x, y)`` at ``angle_deg``, from ``t0`` to ``t1`` pixels along it."""
        c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        return cls(float(x + t0 * c), float(y + t0 * s), float(x + t1 * c), float(y + t1 * s))

    @classmethod
    def crossing(cls, shape, x, y, angle_deg):
        """The chord of an image of ``shape = (ny, nx)`` along a line, or None if it misses."""
        seg = Segment.crossing(shape, x, y, angle_deg)
        return None if seg is None else cls(seg.x0, seg.y0, seg.x1, seg.y1)

    @property
    def length(self):
        return float(np.hypot(self.x1 - self.x0, self.y1 - self.y0))

    @property
    def angle_deg(self):
        """Direction angle, deg, in ``(-180, 180]``."""
        return float(np.degrees(np.arctan2(self.y1 - self.y0, self.x1 - self.x0)))

    @property
    def centre(self):
        return 0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1)

    @property
    def direction(self):
        """Unit vector along the line."""
        a = np.radians(self.angle_deg)
        return float(np.cos(a)), float(np.sin(a))

    @property
    def normal(self):
        """Unit vector across the line (the direction rotated by +90 deg)."""
        c, s = self.direction
        return -s, c

    def coordinates(self, x, y):
        """Along-track ``t`` (from the centre) and cross-track ``d`` coordinates of points."""
        cx, cy = self.centre
        (ux, uy), (nx, ny) = self.direction, self.normal
        dx, dy = np.asarray(x, dtype=float) - cx, np.asarray(y, dtype=float) - cy
        return dx * ux + dy * uy, dx * nx + dy * ny

    def shifted(self, offset, slope=0.0):
        """The line moved across by ``offset + slope * t`` (``t`` from the centre).

        This is the line a fit of cross-track offsets against ``t`` returns; the endpoints keep
        their along-track positions.
        """
        cx, cy = self.centre
        (ux, uy), (nx, ny) = self.direction, self.normal

        def point(t):
            across = offset + slope * t
            return float(cx + t * ux + across * nx), float(cy + t * uy + across * ny)

        half = 0.5 * self.length
        return Line(*point(-half), *point(half))

    def trimmed(self, t0, t1):
        """The part of this line from ``t0`` to ``t1`` (along-track, from the centre)."""
        cx, cy = self.centre
        return Line.through(cx, cy, self.angle_deg, t0, t1)

    def offset_from(self, other, at=None):
        """Cross-track distance of this line from ``other`` at point ``at`` (default: this
        line's centre), measured along ``other``'s normal."""
        x, y = self.centre if at is None else at
        # Move along this line to the point nearest ``at``, then measure against ``other``.
        t, _ = self.coordinates(x, y)
        cx, cy = self.centre
        ux, uy = self.direction
        return float(other.coordinates(cx + t * ux, cy + t * uy)[1])


def angle_difference(a_deg, b_deg):
    """Smallest difference between two line orientations, deg (lines: modulo 180)."""
    return float(abs((a_deg - b_deg + 90.0) % 180.0 - 90.0))


def rectangle_spans(shape, line, half_width, extend=0.0):
    """Pixels whose centres lie in the rectangle around ``line``, as one x-range per row.

    The rectangle has half-width ``half_width`` across the line and runs from ``extend`` pixels
    before the start to ``extend`` after the end; it is clipped to the image. A rectangle is
    convex, so each row holds one run of pixels: this is exact polygon rasterisation, in
    ``O(rows)``, whatever the rectangle's size (:func:`rectangles_spans` of one rectangle).

    Parameters
    ----------
    shape : tuple of int
        ``(ny, nx)``.
    line : Line
    half_width : float
        Pixels (>= 0).
    extend : float
        Pixels added at both ends (e.g. the half-width, to cover the end caps).

    Returns
    -------
    rows, start, stop : ndarray of int
        Row indices and the half-open column range ``[start, stop)`` of each (only rows with at
        least one pixel).
    """
    _, rows, start, stop = rectangles_spans(shape, [line.x0], [line.y0], [line.x1], [line.y1],
                                            half_width, extend)
    return rows, start, stop


def rectangles_spans(shape, x0, y0, x1, y1, half_width, extend=0.0):
    """:func:`rectangle_spans` of many rectangles at once: the rectangle of half-width
    ``half_width`` around each line from ``(x0, y0)`` to ``(x1, y1)``, ``extend`` beyond its
    ends, clipped to its image, with :class:`Line`'s arithmetic term by term.

    Parameters
    ----------
    shape : tuple
        ``(ny, nx)``: ints, or arrays of each rectangle's image.
    x0, y0, x1, y1 : array_like
        The lines' ends (pixels), one per rectangle.
    half_width, extend : float or array_like
        Pixels, for all rectangles or each.

    Returns
    -------
    which, rows, start, stop : ndarray of int
        For each row with at least one pixel: its rectangle (index into ``x0``), the row and
        the half-open column range ``[start, stop)``, by rectangle then row.
    """
    x0, y0, x1, y1 = (np.asarray(v, float).reshape(-1) for v in (x0, y0, x1, y1))
    n = len(x0)
    ny, nx = (np.broadcast_to(np.asarray(v, np.intp), (n,)) for v in shape)
    hw = np.broadcast_to(np.asarray(half_width, float), (n,))
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    angle = np.radians(np.degrees(np.arctan2(y1 - y0, x1 - x0)))
    ux, uy = np.cos(angle), np.sin(angle)
    vx, vy = -uy, ux
    half_len = 0.5 * np.hypot(x1 - x0, y1 - y0) + extend
    # Corners (a, b) = (-1, -1), (-1, 1), (1, -1), (1, 1): a along the line, b across it.
    corner_ys = np.array([cy + a * half_len * uy + b * hw * vy for a in (-1, 1) for b in (-1, 1)])
    first = np.maximum(0, np.ceil(corner_ys.min(axis=0) - _EDGE_EPS))
    last = np.minimum(ny - 1, np.floor(corner_ys.max(axis=0) + _EDGE_EPS))
    # A slab whose factor of x is 1e-12 or less runs along the rows: its rectangle's rows take
    # the general arithmetic.
    regular = (np.abs(ux) > 1e-12) & (np.abs(vx) > 1e-12)
    # The other rectangles' rows from the first to the last where they cross the image's
    # columns (a pixel more each side: the rows beyond hold no pixel of the image).
    corner_xs = np.array([cx + a * half_len * ux + b * hw * vx
                          for a in (-1, 1) for b in (-1, 1)])
    low, high = _rows_within(corner_xs, corner_ys, -1.5, nx + 0.5)
    first = np.where(regular, np.maximum(first, np.ceil(low - 1.0)), first)
    last = np.where(regular, np.minimum(last, np.floor(high + 1.0)), last)
    count = np.maximum(last - first + 1, 0).astype(np.intp)
    slabs = ((ux, uy, half_len), (vx, vy, hw))
    sides = _sides(corner_ys, slabs, first, last)
    parts = []
    rects = np.flatnonzero(count > 0)
    # Rectangles in batches of about ROWS_AT_ONCE rows: arrays small enough to stay in the
    # cache.
    batch = np.cumsum(count[rects]) // ROWS_AT_ONCE
    for k in np.split(rects, np.flatnonzero(np.diff(batch)) + 1) if len(rects) else ():
        for rect, rows_of, bounds in ((k[regular[k]], _regular_rows, sides),
                                      (k[~regular[k]], _general_rows, slabs)):
            if len(rect):
                which, rows, start, stop = rows_of(
                    first[rect], count[rect], nx[rect], cx[rect], cy[rect],
                    [tuple(v[rect] for v in bound) for bound in bounds])
                parts.append((rect[which], rows, start, stop))
    if not parts:
        return tuple(np.zeros(0, np.intp) for _ in range(4))
    which, rows, start, stop = (np.concatenate(v) for v in zip(*parts))
    if regular[rects].all() or not regular[rects].any():  # batches in order of rectangle
        return which, rows, start, stop
    order = np.lexsort((rows, which))
    return which[order], rows[order], start[order], stop[order]


def _rows_within(xs, ys, x_min, x_max):
    """The lowest and highest y of each convex quadrilateral (corners ``xs, ys``, ``(4, n)``,
    in the order of :func:`rectangles_spans`, opposite corners 0-3 and 1-2) between
    ``x_min`` and ``x_max`` (``inf, -inf`` when it misses them): its corners there and where
    its sides cross those two lines."""
    inside = (xs >= x_min) & (xs <= x_max)
    low = np.where(inside, ys, np.inf).min(axis=0)
    high = np.where(inside, ys, -np.inf).max(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, j in ((0, 1), (1, 3), (3, 2), (2, 0)):  # the sides, around
            dx, dy = xs[j] - xs[i], ys[j] - ys[i]
            for x in (x_min, x_max):
                t = (x - xs[i]) / dx
                y = ys[i] + t * dy
                on = (t >= 0) & (t <= 1) & np.isfinite(y)
                low = np.minimum(low, np.where(on, y, np.inf))
                high = np.maximum(high, np.where(on, y, -np.inf))
    return low, high


#: Rows of rectangles :func:`rectangles_spans` takes at once.
ROWS_AT_ONCE = 16384


def _sides(corner_ys, slabs, first, last):
    """Each rectangle's slabs as :func:`_regular_rows` takes them: the slab that bounds its
    middle rows and the other, each as ``(w_x, w_y, the bound below)``, with the band of rows
    where the first alone bounds a row (``band``: its first row, its last, each in the
    rectangle's rows).

    A slab's bounds on a row are ``(-h - rest) / w_x + c_x`` and ``(h - rest) / w_x + c_x``
    (``rest = (y - c_y) w_y``), the first the lower when ``w_x > 0``. Between the second and
    third corners up the rows, a row's ends are on the two sides of one slab; the other
    slab's bounds lie beyond them by 2 px for each row from those corners (the slabs are at
    right angles: their sides' slopes differ by ``|cot + tan| >= 2``), far beyond rounding,
    so that a row at least a row clear of those corners takes that slab's bounds alone.
    """
    order = np.argsort(corner_ys, axis=0, kind="stable")
    ys = np.take_along_axis(corner_ys, order, axis=0)
    # The side from the second corner up is one of constant ``a`` (a side of the slab along
    # the line) when the second corner differs from the lowest in ``a``.
    along = order[0] // 2 != order[1] // 2
    (ux, uy, hl), (vx, vy, hw) = slabs
    u = (ux, uy, np.where(ux > 0, -hl, hl))
    v = (vx, vy, np.where(vx > 0, -hw, hw))
    middle = tuple(np.where(along, a, b) for a, b in zip(u, v))
    other = tuple(np.where(along, b, a) for a, b in zip(u, v))
    band_lo = np.clip(np.ceil(ys[1] + 1.0), first, last + 1)
    band_hi = np.clip(np.floor(ys[2] - 1.0), band_lo - 1, last)
    return middle, other, (band_lo, band_hi)


def _row_positions(first, count):
    """Each rectangle's rows from ``first`` (``count`` of them), one after the other: the
    rectangle of each row and the row."""
    return np.repeat(np.arange(len(count)), count), _ranges(first, count)


def _columns(which, y, lo, hi, nx):
    """The half-open column range of the pixel centres from ``lo`` to ``hi`` (edges included)
    on each row, clipped to the image; only the rows with a pixel. ``lo`` and ``hi`` are
    overwritten."""
    width = nx[0] if np.all(nx == nx[0]) else nx[which]
    lo -= _EDGE_EPS
    start = np.ceil(lo, out=lo)
    np.maximum(start, 0, out=start)
    np.minimum(start, width, out=start)
    hi += _EDGE_EPS
    stop = np.floor(hi, out=hi)
    stop += 1
    np.maximum(stop, 0, out=stop)
    np.minimum(stop, width, out=stop)
    keep = np.flatnonzero(stop > start)
    return which[keep], y[keep], start[keep].astype(np.intp), stop[keep].astype(np.intp)


def _general_rows(first, count, nx, cx, cy, slabs):
    """The rows of rectangles (any), each slab ``(w_x, w_y, h)``."""
    which, y = _row_positions(first, count)
    lo = np.full(y.shape, -np.inf)
    hi = np.full(y.shape, np.inf)
    # Each slab |(p - c) . w| <= h limits x on a row to an interval (or to all / nothing).
    for wx, wy, h in slabs:
        wx, wy, h, c = wx[which], wy[which], h[which], cx[which]
        rest = (y - cy[which]) * wy
        across = np.abs(wx) > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = (-h - rest) / wx + c, (h - rest) / wx + c
        outside = np.abs(rest) > h + _EDGE_EPS
        lo = np.where(across, np.maximum(lo, np.minimum(a, b)), np.where(outside, np.inf, lo))
        hi = np.where(across, np.minimum(hi, np.maximum(a, b)), np.where(outside, -np.inf, hi))
    return _columns(which, y, lo, hi, nx)


def _regular_rows(first, count, nx, cx, cy, sides):
    """The rows of rectangles neither of whose slabs runs along the rows, their slabs as
    :func:`_sides` gives them: the middle slab's bounds on every row, the other's on the
    rows outside the band."""
    middle, other, (band_lo, band_hi) = sides
    which, y = _row_positions(first, count)
    d = y - np.repeat(cy, count)
    lo, hi = _slab(d, *(np.repeat(v, count) for v in (*middle, cx)))
    last = first + count - 1
    offset = np.cumsum(count) - count
    ends = np.concatenate([_ranges(offset, band_lo - first),
                           _ranges(offset + (band_hi - first + 1), last - band_hi)])
    k = which[ends]
    lo_end, hi_end = _slab(d[ends], *(v[k] for v in (*other, cx)))
    lo[ends] = np.maximum(lo[ends], lo_end)
    hi[ends] = np.minimum(hi[ends], hi_end)
    return _columns(which, y, lo, hi, nx)


def _slab(d, wx, wy, low, cx):
    """A slab's lower and upper bounds of x on rows ``d`` from the centre's row (``low``:
    the ``-h`` or ``h`` of the lower), in :func:`rectangle_spans`' arithmetic."""
    rest = d * wy
    lo = low - rest
    lo /= wx
    lo += cx
    hi = np.negative(low, out=low)
    hi -= rest
    hi /= wx
    hi += cx
    return lo, hi


def _ranges(start, count):
    """The integers ``start[i] .. start[i] + count[i] - 1`` of each ``i``, one after another."""
    start = np.asarray(start, np.intp)
    count = np.maximum(np.asarray(count), 0).astype(np.intp)
    return (np.repeat(start - (np.cumsum(count) - count), count)
            + np.arange(int(count.sum()), dtype=np.intp))


def span_indices(rows, start, stop):
    """Flat ``(y, x)`` index arrays of the pixels of row runs."""
    return np.repeat(rows, stop - start), _ranges(start, stop - start)


def band_pixels(shape, line, half_width, extend=0.0):
    """``(y, x)`` indices of the pixels in the rectangle of :func:`rectangle_spans`."""
    return span_indices(*rectangle_spans(shape, line, half_width, extend))
