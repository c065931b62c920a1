"""Scoring detections against a simulation's TRUTH rows: matches, errors, false positives."""
from dataclasses import dataclass

from ..trajectory import Segment
from .geometry import Line, angle_difference


def truth_line(row, shape):
    """The part of a TRUTH row's track inside an image of ``shape``, or None if it misses.

    The row's ``x0, y0`` and ``angle_deg`` start the track and ``length_px`` bounds it (a
    crossing track's row already runs from edge to edge, beyond the image).
    """
    seg = Segment(row["x0"], row["y0"], row["angle_deg"], row["length_px"])
    clipped = seg.clip(shape)
    if clipped is None:
        return None
    c, s = seg.direction
    t0, t1 = clipped
    return Line(seg.x0 + t0 * c, seg.y0 + t0 * s, seg.x0 + t1 * c, seg.y0 + t1 * s)


@dataclass
class Match:
    """A truth streak and the detection matched to it (None if missed).

    ``angle_error_deg`` and ``offset_px`` (cross-track distance of the detected line from the
    true one at the centre of the true streak's part in the image) are NaN when missed.
    """

    truth_index: int
    found_index: int | None
    angle_error_deg: float = float("nan")
    offset_px: float = float("nan")


def match_streaks(found, truth, shape, max_angle_deg=0.5, max_offset_px=5.0):
    """Match detected streaks (dicts with ``x0, y0, x1, y1``) to TRUTH rows, one to one.

    Each truth streak, in order, takes the closest unused detection within the tolerances.

    Returns
    -------
    matches : list of Match
        One per truth row that crosses the image.
    false_positives : list of int
        Indices of detections matched to no truth streak.
    """
    lines = [Line(s["x0"], s["y0"], s["x1"], s["y1"]) for s in found]
    used, matches = set(), []
    for i, row in enumerate(truth):
        true = truth_line(row, shape)
        if true is None:
            continue
        best = None
        for j, line in enumerate(lines):
            if j in used:
                continue
            da = angle_difference(line.angle_deg, true.angle_deg)
            off = line.offset_from(true, at=true.centre)
            if da <= max_angle_deg and abs(off) <= max_offset_px:
                if best is None or abs(off) < abs(best[2]):
                    best = (j, da, off)
        if best is None:
            matches.append(Match(i, None))
        else:
            used.add(best[0])
            matches.append(Match(i, *best))
    return matches, [j for j in range(len(found)) if j not in used]
