"""Tracks on the pixel grid.

Pixel (0, 0) is the centre of the first pixel; x runs along columns, y along rows (numpy index
``[y, x]``); angles are degrees counter-clockwise from +x. An image of shape ``(ny, nx)`` covers
``-0.5 <= x < nx - 0.5`` and ``-0.5 <= y < ny - 0.5``.
"""
from dataclasses import dataclass, replace

import numpy as np

from inject.errors import InputError
from inject.validate import finite


@dataclass(frozen=True)
class Segment:
    """A straight track from ``(x0, y0)`` over ``length`` pixels at ``angle_deg``.

    Use :meth:`crossing` for a track that crosses a whole image.
    """

    x0: float
    y0: float
    angle_deg: float
    length: float

    def __post_init__(self):
        for name in ("x0", "y0", "angle_deg", "length"):
            object.__setattr__(self, name, finite(name, getattr(self, name), scalar=True))
        if self.length < 0:
            raise InputError("length", self.length, "must be >= 0")

    @property
    def direction(self):
        """Unit vector ``(cos, sin)`` along the track."""
        a = np.radians(self.angle_deg)
        return np.cos(a), np.sin(a)

    @property
    def x1(self):
        return self.x0 + self.length * self.direction[0]

    @property
    def y1(self):
        return self.y0 + self.length * self.direction[1]

    @classmethod
    def crossing(cls, shape, x0, y0, angle_deg, margin=0.0):
        """The line through ``(x0, y0)`` at ``angle_deg``, from edge to edge of an image.

        ``margin`` (pixels) extends the track beyond the image edges on both sides, so that the
        end caps of the swept profile fall outside the image. Returns None if the line misses it.
        """
        ny, nx = _image_shape(shape)
        x0, y0 = finite("x0", x0, scalar=True), finite("y0", y0, scalar=True)
        angle_deg = finite("angle_deg", angle_deg, scalar=True)
        margin = finite("margin", margin, scalar=True)
        chord = clip_line(x0, y0, angle_deg, (-0.5 - margin, nx - 0.5 + margin),
                           (-0.5 - margin, ny - 0.5 + margin))
        if chord is None:
            return None
        t0, t1 = chord
        c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        return cls(x0 + t0 * c, y0 + t0 * s, angle_deg, t1 - t0)

    def clip(self, shape):
        """Part of the segment inside an image of ``shape = (ny, nx)`` as ``(t0, t1)`` distances
        along the track from ``(x0, y0)``, or None if it misses the image."""
        ny, nx = _image_shape(shape)
        chord = clip_line(self.x0, self.y0, self.angle_deg, (-0.5, nx - 0.5), (-0.5, ny - 0.5))
        if chord is None:
            return None
        t0, t1 = max(chord[0], 0.0), min(chord[1], self.length)
        return (t0, t1) if t1 > t0 else None


def _image_shape(shape):
    """``(ny, nx)`` of an image shape as floats, raising :class:`InputError` unless it is two
    numbers."""
    try:
        ny, nx = (finite("shape", n, scalar=True) for n in shape)
    except (TypeError, ValueError):  # None, a number, (ny,), (nz, ny, nx), non-numbers
        raise InputError("shape", shape, "must be two numbers (ny, nx)") from None
    return ny, nx


def clip_line(x0, y0, angle_deg, xlim, ylim):
    """Parameter interval ``(t0, t1)`` of the infinite line inside a rectangle (Liang-Barsky)."""
    a = np.radians(angle_deg)
    return _chord((x0, y0), (np.cos(a), np.sin(a)), xlim, ylim)


def _chord(origin, direction, xlim, ylim):
    """``(t0, t1)`` of the line ``origin + t direction`` inside a rectangle, or None."""
    lo, hi = -np.inf, np.inf
    for start, d, (vmin, vmax) in zip(origin, direction, (xlim, ylim)):
        if abs(d) < 1e-15:
            if not vmin <= start <= vmax:
                return None
            continue
        ta, tb = sorted(((vmin - start) / d, (vmax - start) / d))
        lo, hi = max(lo, ta), min(hi, tb)
    return (lo, hi) if hi > lo else None


def clip_segment(x0, y0, x1, y1, xlim, ylim):
    """The part ``(x0, y0, x1, y1)`` of a segment inside a rectangle, or None if it misses."""
    dx, dy = x1 - x0, y1 - y0
    chord = _chord((x0, y0), (dx, dy), xlim, ylim)  # t in units of the segment: 0 to 1
    if chord is None or chord[1] < 0 or chord[0] > 1:
        return None
    lo, hi = max(chord[0], 0.0), min(chord[1], 1.0)
    return x0 + lo * dx, y0 + lo * dy, x0 + hi * dx, y0 + hi * dy


@dataclass(frozen=True)
class Polyline:
    """A track through several vertices (pixels), e.g. a long pass across the focal plane.

    Each vertex may carry its own streak model (range, angular speed, brightness: see
    :func:`inject.render.render_polyline`).
    """

    xs: tuple
    ys: tuple

    def __post_init__(self):
        xs, ys = _coordinates("polyline x", self.xs), _coordinates("polyline y", self.ys)
        if len(xs) != len(ys) or len(xs) < 2:
            raise InputError("polyline", (self.xs, self.ys),
                             "needs at least two vertices with one x and one y each")
        object.__setattr__(self, "xs", xs)
        object.__setattr__(self, "ys", ys)

    def segments(self):
        """The straight pieces between consecutive vertices (zero-length ones skipped)."""
        out = []
        for x0, y0, x1, y1 in zip(self.xs[:-1], self.ys[:-1], self.xs[1:], self.ys[1:]):
            length = float(np.hypot(x1 - x0, y1 - y0))
            if length > 0:
                out.append(Segment(x0, y0, float(np.degrees(np.arctan2(y1 - y0, x1 - x0))),
                                   length))
        return out


def path_distance(path, x, y):
    """Distance (px) from points to the nearest point of a piecewise-linear path.

    Parameters
    ----------
    path : sequence of (float, float)
        The path's vertices, at least one (a single point's distance is to it).
    x, y : array_like
        The points.

    Returns
    -------
    ndarray
        The distances, of the points' broadcast shape.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    (ax, ay), best = path[0], None
    for bx, by in path[1:] if len(path) > 1 else path:
        dx, dy = bx - ax, by - ay
        length2 = dx * dx + dy * dy
        t = 0.0 if length2 == 0 else np.clip(((x - ax) * dx + (y - ay) * dy) / length2, 0, 1)
        d = np.hypot(x - ax - t * dx, y - ay - t * dy)
        best = d if best is None else np.minimum(best, d)
        ax, ay = bx, by
    return best


def blurred_path(xs, ys, s, offsets, weights):
    """Points of a polyline averaged along it: at each length ``s`` along the polyline ``(xs,
    ys)``, the mean of its points at ``s + offsets`` with ``weights`` (beyond its ends, its
    ends).

    A streak swept along the polyline, blurred along it by a profile whose marginal along the
    track is ``weights`` at ``offsets`` (px, summing to 1), has its ridge there (to first order
    in the turns: straight pieces are kept, corners are rounded).

    Returns
    -------
    x, y : ndarray
        Of ``s``'s shape.
    """
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(ys)))])
    at = np.asarray(s, float)[..., None] + np.asarray(offsets, float)
    return (np.interp(at, cum, xs) @ weights, np.interp(at, cum, ys) @ weights)


def _coordinates(name, values):
    """Vertex coordinates as a tuple of floats, raising :class:`InputError` unless ``values``
    is a 1-D sequence of finite numbers."""
    arr = finite(name, values)
    if arr.ndim != 1:  # a single number, or a 2-D array
        raise InputError(name, values, "must be a sequence of numbers")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class Track:
    """Where a scene puts a streak on the pixel grid; ``length=None`` crosses the whole image.

    ``vertices`` makes it a polyline: a tuple of mappings with ``x``, ``y`` (pixels) and
    optionally ``height``, ``zenith``, ``phi``, ``mag`` overriding the satellite's values at
    that vertex (so width, speed and brightness can change along the track), and ``range``
    (km), ``angular_speed`` (rad/s) replacing the spherical-Earth range and angular speed of
    (height, zenith, phi) there (an orbit's vertices carry the pass's exact values).
    """

    x0: float
    y0: float
    angle: float
    length: float | None = None
    vertices: tuple | None = None


#: A piece whose step along an axis is below this fraction of its length runs parallel to that
#: axis (the box's edges across it are never crossed).
PARALLEL_FRACTION = 1e-15


def clip_path(xs, ys, box):
    """The parts of a polyline (focal-plane mm) inside a box ``(xmin, xmax, ymin, ymax)``.

    Returns
    -------
    list of tuple
        ``(piece, t0, t1)``: the index of the polyline piece and the fractions ``0 <= t0 <
        t1 <= 1`` along it that lie inside, in order along the path (:func:`clip_path_boxes`
        for one box).
    """
    _, piece, t0, t1 = clip_path_boxes(xs, ys, [box])
    return list(zip(piece.tolist(), t0.tolist(), t1.tolist()))


def clip_path_boxes(xs, ys, boxes):
    """The parts of a polyline inside each of several boxes, every piece against every box at
    once (Liang-Barsky).

    A point of piece ``k`` is ``(xs[k], ys[k]) + t (xs[k + 1] - xs[k], ys[k + 1] - ys[k])``
    with ``0 <= t <= 1``; the boxes are closed. Pieces of zero length are never inside, nor
    are pieces with a non-finite vertex. A piece whose step along an axis is below
    :data:`PARALLEL_FRACTION` of its length is inside along that axis where its first vertex
    is.

    Parameters
    ----------
    xs, ys : array_like
        The polyline's vertices.
    boxes : array_like
        ``(n, 4)``: each box's ``(xmin, xmax, ymin, ymax)``.

    Returns
    -------
    box, piece : ndarray of int
        For each part inside a box: the box's row in ``boxes`` and the polyline piece.
    t0, t1 : ndarray of float
        The fractions ``0 <= t0 < t1 <= 1`` along the piece that lie inside the box. Parts
        are sorted by box, then along the path.
    """
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    dx, dy = np.diff(xs), np.diff(ys)
    length = np.hypot(dx, dy)
    lo = np.zeros((len(boxes), len(dx)))
    hi = np.ones((len(boxes), len(dx)))
    with np.errstate(divide="ignore", invalid="ignore"):
        for start, step, vmin, vmax in ((xs[:-1], dx, boxes[:, :1], boxes[:, 1:2]),
                                        (ys[:-1], dy, boxes[:, 2:3], boxes[:, 3:4])):
            ta, tb = (vmin - start) / step, (vmax - start) / step
            along = np.abs(step) >= PARALLEL_FRACTION * length
            # Parallel to this axis: all of the piece or none of it, by where it starts.
            level = np.where((vmin <= start) & (start <= vmax), np.inf, -np.inf)
            lo = np.maximum(lo, np.where(along, np.minimum(ta, tb), -level))
            hi = np.minimum(hi, np.where(along, np.maximum(ta, tb), level))
    box, piece = np.nonzero((hi > lo) & (length > 0))
    return box, piece, lo[box, piece], hi[box, piece]


@dataclass(frozen=True)
class FocalTrack:
    """A satellite's track across the focal plane (mm), as a polyline with the streak model's
    values at each vertex.

    ``kind`` is ``"line"`` (crossing the focal plane: the vertices are far outside it),
    ``"segment"`` or ``"polyline"``; ``values`` holds, per vertex, the model values
    (``height, zenith, phi, mag``) in effect there. A track from an ``orbit:`` is a polyline
    (or has no vertices when the pass renders no streak); ``message`` says how it went. An
    orbit's pass may be sunlit in several parts (it leaves Earth's shadow and re-enters it):
    the parts follow one another, separated by a NaN vertex (value None), so that a plot of
    ``xs, ys`` shows the gaps; :meth:`parts` gives them one by one.
    """

    kind: str
    xs: tuple
    ys: tuple
    values: tuple
    angle: float
    message: str = ""
    #: An orbit's pass: its name, whether it enters the field and is sunlit there (None for
    #: a hand-placed track).
    name: str = ""
    in_field: bool | None = None
    sunlit: bool | None = None

    def parts(self):
        """The track's continuous parts, each a :class:`FocalTrack` of at least two vertices."""
        if all(v is not None for v in self.values):
            return [self] if self.xs else []
        out, start = [], 0
        for k, v in enumerate((*self.values, None)):
            if v is None:
                if k - start >= 2:
                    out.append(replace(self, xs=self.xs[start:k], ys=self.ys[start:k],
                                       values=self.values[start:k]))
                start = k + 1
        return out
