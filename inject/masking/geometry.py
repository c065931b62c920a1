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
    ``O(rows)``, whatever the rectangle's size.

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
    ny, nx = shape
    cx, cy = line.centre
    (ux, uy), (vx, vy) = line.direction, line.normal
    half_len = 0.5 * line.length + extend
    hw = float(half_width)
    corners = [(cx + a * half_len * ux + b * hw * vx, cy + a * half_len * uy + b * hw * vy)
               for a in (-1, 1) for b in (-1, 1)]
    ys = [c[1] for c in corners]
    y = np.arange(max(0, int(np.ceil(min(ys) - _EDGE_EPS))),
                  min(ny - 1, int(np.floor(max(ys) + _EDGE_EPS))) + 1)
    lo = np.full(y.shape, -np.inf)
    hi = np.full(y.shape, np.inf)
    # Each slab |(p - c) . w| <= h limits x on a row to an interval (or to all / nothing).
    for (wx, wy), h in (((ux, uy), half_len), ((vx, vy), hw)):
        rest = (y - cy) * wy
        if abs(wx) > 1e-12:
            a, b = (-h - rest) / wx + cx, (h - rest) / wx + cx
            lo, hi = np.maximum(lo, np.minimum(a, b)), np.minimum(hi, np.maximum(a, b))
        else:
            outside = np.abs(rest) > h + _EDGE_EPS
            lo[outside], hi[outside] = np.inf, -np.inf
    start = np.clip(np.ceil(lo - _EDGE_EPS), 0, nx).astype(np.intp)
    stop = np.clip(np.floor(hi + _EDGE_EPS) + 1, 0, nx).astype(np.intp)
    keep = stop > start
    return y[keep], start[keep], stop[keep]


def span_indices(rows, start, stop):
    """Flat ``(y, x)`` index arrays of the pixels of row runs."""
    counts = stop - start
    yy = np.repeat(rows, counts)
    # Column = start of the run + position inside it.
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    xx = np.repeat(start, counts) + offsets
    return yy, xx


def band_pixels(shape, line, half_width, extend=0.0):
    """``(y, x)`` indices of the pixels in the rectangle of :func:`rectangle_spans`."""
    return span_indices(*rectangle_spans(shape, line, half_width, extend))
