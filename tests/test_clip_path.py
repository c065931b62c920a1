"""Clipping polylines to boxes (:func:`inject.trajectory.clip_path_boxes`) and its users in the
survey plan, against exact rational arithmetic and a one-piece-at-a-time Liang-Barsky."""
import math
import os
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from inject.camera import layout as fp
from inject.survey import plan
from inject.trajectory import clip_path, clip_path_boxes

BOX = (-1.0, 2.0, -0.5, 1.5)


def exact_part(x0, y0, x1, y1, box):
    """``(t0, t1)`` of a segment inside a closed box in exact rational arithmetic, None when
    the part inside is empty or a single point (a zero-length segment has none)."""
    if (max(x0, x1) < box[0] or min(x0, x1) > box[1] or max(y0, y1) < box[2]
            or min(y0, y1) > box[3]):  # apart (the comparisons of floats are exact)
        return None
    x0, y0, x1, y1 = map(Fraction, (x0, y0, x1, y1))
    xmin, xmax, ymin, ymax = map(Fraction, box)
    if (x0, y0) == (x1, y1):
        return None
    lo, hi = Fraction(0), Fraction(1)
    for start, step, vmin, vmax in ((x0, x1 - x0, xmin, xmax), (y0, y1 - y0, ymin, ymax)):
        if step == 0:
            if not vmin <= start <= vmax:
                return None
            continue
        ta, tb = sorted(((vmin - start) / step, (vmax - start) / step))
        lo, hi = max(lo, ta), min(hi, tb)
    return (lo, hi) if hi > lo else None


def scalar_clip_path(xs, ys, box):
    """Liang-Barsky one piece at a time along the line's unit direction, from its angle."""
    out = []
    for k in range(len(xs) - 1):
        dx, dy = xs[k + 1] - xs[k], ys[k + 1] - ys[k]
        length = math.hypot(dx, dy)
        if length == 0:
            continue
        a = math.atan2(dy, dx)
        lo, hi = -math.inf, math.inf
        for start, d, vmin, vmax in ((xs[k], math.cos(a), box[0], box[1]),
                                     (ys[k], math.sin(a), box[2], box[3])):
            if abs(d) < 1e-15:
                if not vmin <= start <= vmax:
                    lo, hi = 1.0, 0.0
                continue
            ta, tb = sorted(((vmin - start) / d, (vmax - start) / d))
            lo, hi = max(lo, ta), min(hi, tb)
        t0, t1 = max(lo / length, 0.0), min(hi / length, 1.0)
        if hi > lo and t1 > t0:
            out.append((k, t0, t1))
    return out


def random_polyline(rng, n):
    """A walk around and across :data:`BOX` with the cases a clip gets wrong: zero-length
    pieces, pieces along the box's edges, vertical and horizontal ones, vertices on the
    edges and corners."""
    xs, ys = [rng.uniform(-3, 4)], [rng.uniform(-3, 3)]
    for _ in range(n - 1):
        kind = rng.integers(7)
        x, y = xs[-1], ys[-1]
        if kind == 0:  # stays put
            pass
        elif kind == 1:  # vertical
            y = rng.uniform(-3, 3)
        elif kind == 2:  # horizontal
            x = rng.uniform(-3, 4)
        elif kind == 3:  # onto an edge line, or along one
            if rng.random() < 0.5:
                x = BOX[rng.integers(2)]
                y = rng.uniform(-3, 3) if rng.random() < 0.5 else y
            else:
                y = BOX[2 + rng.integers(2)]
                x = rng.uniform(-3, 4) if rng.random() < 0.5 else x
        elif kind == 4:  # onto a corner
            x, y = BOX[rng.integers(2)], BOX[2 + rng.integers(2)]
        else:
            x, y = rng.uniform(-3, 4), rng.uniform(-3, 3)
        xs.append(float(x))
        ys.append(float(y))
    return xs, ys


@pytest.mark.parametrize("seed", range(40))
def test_pieces_inside_are_the_exact_ones(seed):
    rng = np.random.default_rng(seed)
    xs, ys = random_polyline(rng, 30)
    got = clip_path(xs, ys, BOX)
    want = [(k, part) for k in range(len(xs) - 1)
            if (part := exact_part(xs[k], ys[k], xs[k + 1], ys[k + 1], BOX)) is not None]
    assert [k for k, _, _ in got] == [k for k, _ in want]
    for (_, t0, t1), (_, (e0, e1)) in zip(got, want):
        assert 0.0 <= t0 < t1 <= 1.0
        # (v - x0) / dx: two roundings, within 2 units of the last place of t <= 1
        assert abs(t0 - float(e0)) <= 4.5e-16 and abs(t1 - float(e1)) <= 4.5e-16


@pytest.mark.parametrize("seed", range(40))
def test_as_the_scalar_clip_one_piece_at_a_time(seed):
    rng = np.random.default_rng(100 + seed)
    xs, ys = random_polyline(rng, 30)
    got, want = clip_path(xs, ys, BOX), scalar_clip_path(xs, ys, BOX)
    # Through the angle, a piece that ends on a corner keeps a sliver of a unit in the last
    # place (the exact part is a point, test_pieces_inside_are_the_exact_ones).
    got, want = ([p for p in parts if p[2] - p[1] > 1e-15] for parts in (got, want))
    assert [k for k, _, _ in got] == [k for k, _, _ in want]
    np.testing.assert_allclose([g[1:] for g in got], [w[1:] for w in want], rtol=0,
                               atol=1e-14)


@pytest.mark.parametrize("xs, ys, want", [
    ([0.0, 1.0], [0.0, 0.0], [(0, 0.0, 1.0)]),               # inside, horizontal
    ([0.0, 0.0], [2.0, -2.0], [(0, 0.125, 0.625)]),          # vertical, across
    ([-3.0, 4.0], [1.5, 1.5], [(0, 2 / 7, 5 / 7)]),          # along the top edge
    ([2.0, 2.0], [-3.0, 3.0], [(0, 2.5 / 6, 4.5 / 6)]),      # along the right edge
    ([3.0, 1.0], [0.5, 2.5], []),                            # touches the corner (2, 1.5)
    ([3.0, 2.0], [0.0, 0.0], []),                            # ends on the edge
    ([2.0, 3.0], [0.0, 0.0], []),                            # leaves from the edge
    ([2.0, 1.0], [0.0, 0.0], [(0, 0.0, 1.0)]),               # enters from the edge
    ([0.5, 0.5, 0.5, 1.0], [0.0, 0.0, 0.0, 0.0], [(2, 0.0, 1.0)]),  # zero-length pieces
    ([0.0, 5.0, 5.0, 0.0], [0.0, 0.0, 1.0, 1.0], [(0, 0.0, 0.4), (2, 0.6, 1.0)]),
    ([np.nan, 0.0, 1.0], [0.0, 0.0, 0.0], [(1, 0.0, 1.0)]),  # a non-finite vertex
    ([1.0], [1.0], []),                                      # no piece
])
def test_cases_by_hand(xs, ys, want):
    got = clip_path(xs, ys, BOX)
    assert [k for k, _, _ in got] == [k for k, _, _ in want]
    np.testing.assert_allclose([g[1:] for g in got], [w[1:] for w in want], atol=1e-15)


def test_many_boxes_at_once_as_one_at_a_time():
    rng = np.random.default_rng(7)
    xs, ys = random_polyline(rng, 60)
    boxes = np.sort(rng.uniform(-3, 4, (25, 2)), axis=1)
    boxes = np.column_stack([boxes, np.sort(rng.uniform(-3, 3, (25, 2)), axis=1)])
    boxes = np.vstack([boxes, BOX])
    box, k, t0, t1 = clip_path_boxes(xs, ys, boxes)
    want = [(b, *part) for b, row in enumerate(boxes) for part in clip_path(xs, ys, row)]
    assert list(zip(box.tolist(), k.tolist(), t0.tolist(), t1.tolist())) == want
    assert len(clip_path_boxes(xs, ys, np.empty((0, 4)))[0]) == 0


def test_layout_boxes_are_each_ccds_pixel_area():
    """Each box's corners are pixel_to_focal of the pixel area's corners (-0.5 and n - 0.5
    px, grown by the margin), to the last bit; bounds_mm is the CCD's own row."""
    for margin, shape in ((0.0, None), (65.0, None), (3.7, (200, 300))):
        want = []
        for c in fp.CCDS:
            ny, nx = c.shape if shape is None else shape
            x0, y0 = c.pixel_to_focal(-0.5 - margin, -0.5 - margin)
            x1, y1 = c.pixel_to_focal(nx - 0.5 + margin, ny - 0.5 + margin)
            want.append((x0, x1, y0, y1))
        boxes = fp.boxes_mm(fp.CCDS, margin, shape)
        assert np.array_equal(boxes, np.array(want, float))
        assert [c.bounds_mm(margin, shape) for c in fp.CCDS] == [tuple(b) for b in boxes]


def focal_polylines(seed, count=30, n=300):
    """Tracks across the focal plane as the survey has them: gently curved, ~300 samples."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        start = rng.uniform(-330, 330, 2)
        heading = rng.uniform(0, 2 * np.pi)
        s = np.linspace(0, rng.uniform(20, 700), n)
        turn = rng.normal(0, 3e-4) * s ** 2
        xs = start[0] + s * np.cos(heading) - turn * np.sin(heading)
        ys = start[1] + s * np.sin(heading) + turn * np.cos(heading)
        out.append((xs, ys))
    return out


@pytest.mark.parametrize("margin", [0.0, 12.5, 80.0])
def test_ccds_reached_as_each_ccd_on_its_own(margin):
    for xs, ys in focal_polylines(1, count=8, n=100):
        want = tuple(c for c in fp.CCDS
                     if scalar_clip_path(xs, ys, c.bounds_mm(margin)))
        assert fp.ccds_reached(xs, ys, margin) == want


def test_crossed_length_is_the_exact_length_on_each_ccd():
    for xs, ys in focal_polylines(2, count=10, n=100):
        got = plan.crossed_ccds(xs, ys)
        for c in fp.CCDS:
            box = c.bounds_mm()
            mm = sum(float(t1 - t0) * math.hypot(xs[k + 1] - xs[k], ys[k + 1] - ys[k])
                     for k in range(len(xs) - 1)
                     if (part := exact_part(xs[k], ys[k], xs[k + 1], ys[k + 1], box))
                     for t0, t1 in [part])
            if mm:
                assert got[c] == pytest.approx(mm, rel=1e-13, abs=1e-12)
            else:
                assert c not in got
        assert list(got) == sorted(got, key=lambda c: c.id)


def test_angular_length_is_the_sum_over_the_ccds_of_the_field_angle_chords():
    for xs, ys in focal_polylines(3, count=10):
        hit = plan.crossed_ccds(xs, ys)
        want = 0.0
        for c in hit:
            for k, t0, t1 in scalar_clip_path(xs, ys, c.bounds_mm()):
                ends = [(xs[k] + t * (xs[k + 1] - xs[k]), ys[k] + t * (ys[k + 1] - ys[k]))
                        for t in (t0, t1)]
                (ax0, ay0), (ax1, ay1) = (fp.field_angle(*e) for e in ends)
                want += math.hypot(ax1 - ax0, ay1 - ay0)
        assert plan._angular_length_deg(xs, ys, hit) == pytest.approx(math.degrees(want),
                                                                       rel=1e-13)


def test_samples_inside_are_those_on_a_ccd():
    for xs, ys in focal_polylines(4, count=10):
        hit = plan.crossed_ccds(xs, ys)
        want = [any(b[0] <= x <= b[1] and b[2] <= y <= b[3]
                    for b in (c.bounds_mm() for c in hit)) for x, y in zip(xs, ys)]
        assert plan._inside(hit, xs, ys).tolist() == want


def brute_mask(px, py, width, shape, tol=1e-6):
    """Pixel centres of an image of ``shape`` in a polyline's mask (pixel coordinates): a
    rectangle ``width`` wide along each segment, half the width beyond the first and last
    vertices, from each segment's own unit vectors. ``sure``: inside by ``tol``; ``maybe``:
    inside or within ``tol`` of an edge (rounding decides those)."""
    ny, nx = shape
    half = 0.5 * width
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
    sure, maybe = np.zeros(shape, bool), np.zeros(shape, bool)
    last = len(px) - 2
    for k in range(last + 1):
        ax, ay, bx, by = px[k], py[k], px[k + 1], py[k + 1]
        length = math.hypot(bx - ax, by - ay)
        if length == 0:
            continue
        ux, uy = (bx - ax) / length, (by - ay) / length
        along = (x - ax) * ux + (y - ay) * uy
        across = np.abs((y - ay) * ux - (x - ax) * uy)
        t0, t1 = (-half if k == 0 else 0.0), (length + half if k == last else length)
        sure |= (along >= t0 + tol) & (along <= t1 - tol) & (across <= half - tol)
        maybe |= (along >= t0 - tol) & (along <= t1 + tol) & (across <= half + tol)
    return sure, maybe


#: Where a track starts on a CCD's pixel grid: by an edge (either side of it) or anywhere.
def _near_edge(n):
    return st.one_of(st.floats(-120.0, 120.0), st.floats(n - 120.0, n + 120.0),
                     st.floats(0.0, n - 1.0))


@st.composite
def tracks_by_ccd_edges(draw):
    """A short polyline (mm) starting by the edge or corner of a CCD, with the mask's widths."""
    ccd = draw(st.sampled_from(fp.CCDS))
    ny, nx = ccd.shape
    x, y = draw(_near_edge(nx)), draw(_near_edge(ny))
    steps = draw(st.lists(st.tuples(st.floats(-90.0, 90.0), st.floats(-90.0, 90.0)),
                          min_size=1, max_size=5))
    px = np.cumsum([x] + [s[0] for s in steps])
    py = np.cumsum([y] + [s[1] for s in steps])
    xs, ys = ccd.pixel_to_focal(px, py)
    widths = {"e2v": draw(st.floats(0.5, 60.0)), "itl": draw(st.floats(0.5, 60.0))}
    return np.asarray(xs, float), np.asarray(ys, float), widths


@settings(max_examples=4 * int(os.environ.get("INJECT_TEST_EXAMPLES", "6")), deadline=None)
@given(track=tracks_by_ccd_edges())
def test_mask_pixels_are_the_pixel_centres_in_the_rectangles(track):
    """mask_spans and ccd_pixels (every segment of every CCD rasterised at once) against a
    pixel-centre-in-rectangle brute force on each CCD near the track, and union_pixels of
    run_spans against the same."""
    xs, ys, widths = track
    got = plan.ccd_pixels(plan.mask_spans(xs, ys, [np.arange(len(xs))], widths))
    ccd_of_run, rows, start, stop = plan.mask_spans(xs, ys, [np.arange(len(xs))], widths)
    for ccd in fp.CCDS:
        px, py = ccd.focal_to_pixel(xs, ys)
        width = widths[ccd.vendor]
        # Only the window the track and its mask can reach: pixels beyond it are in no
        # rectangle.
        x0 = max(0, math.floor(px.min() - width))
        x1 = min(ccd.shape[1] - 1, math.ceil(px.max() + width))
        y0 = max(0, math.floor(py.min() - width))
        y1 = min(ccd.shape[0] - 1, math.ceil(py.max() + width))
        if x1 < x0 or y1 < y0:
            assert ccd.name not in got
            continue
        sure, maybe = brute_mask(px - x0, py - y0, width, (y1 - y0 + 1, x1 - x0 + 1))
        painted = np.zeros(ccd.shape, bool)
        mine = ccd_of_run == ccd.id
        for r, a, b in zip(rows[mine].tolist(), start[mine].tolist(), stop[mine].tolist()):
            painted[r, a:b] = True
        window = painted[y0:y1 + 1, x0:x1 + 1]
        assert window.sum() == painted.sum()  # nothing outside the window
        assert np.all(window[sure]) and not np.any(window & ~maybe)
        assert got.get(ccd.name, 0) == painted.sum()
        assert plan.union_pixels(plan.run_spans(xs, ys, width, ccd)) == painted.sum()
