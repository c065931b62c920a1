"""The plan of a focal-plane exposure: which CCDs each streak reaches, and where.

Each satellite reaches the CCDs whose pixel area, grown by its swept profile's footprint
(support across the track plus end cap along it), the track crosses; on each, the track is
clipped to that grown area and put in the CCD's pixels (the layout has no yaw, so lines stay
lines), the polyline's vertex values are interpolated where the clipped track enters and
leaves, and the charge per pixel of track uses the local plate scale along the track. Light
that falls between CCDs is lost, as in the camera.

A cut-out (``cutout:``) renders what the whole CCD renders on its pixels: the plate scale,
the model's values and a polyline's vertices come from the track's part on the whole sensor
(grown by the same margin), and the cut-out keeps the pieces of it that reach its own grown
area, so its streak model is the whole CCD's corner byte for byte.
"""
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from inject.camera import layout as fp
from inject.instrument import LSST
from inject.maskplanes import FLAG_OFF_IMAGE
from inject.optics import FIELD_MAX_DEG, telescope_position_angle
from inject.profile import Seeing
from inject.render import Budget, swept_profile
from inject.scene import own_budget, pixel_noise
from inject.streak import StreakModel
from inject.trajectory import Track, clip_path


def vertex_model(fscene, i, values, pixel_scale=None):
    """The :class:`StreakModel` of satellite ``i`` with vertex ``values``, at a plate scale."""
    scene, spec = fscene.scene, fscene.scene.satellites[i]
    telescope = LSST if pixel_scale is None else LSST.with_pixel_scale(pixel_scale)
    return StreakModel(height_km=values["height"], zenith_deg=values["zenith"],
                       phi_deg=values["phi"], shape=spec.shape, mag=values["mag"],
                       band_name=scene.band, seeing=Seeing(scene.seeing), telescope=telescope,
                       ref_range_km=spec.ref_range, range_km=values.get("range"),
                       angular_speed_rad_s=values.get("angular_speed"), pupil=scene.pupil,
                       field_angle_deg=values.get("field_angle", 0.0),
                       field_position_angle_deg=values.get("field_pa", 0.0),
                       focus_offset_um=scene.focus_offset_um,
                       telescope_position_angle_deg=(
                           None if scene.rotator_deg is None else telescope_position_angle(
                               scene.rotator_deg, values.get("field_radius", 0.0))),
                       sed_temperature_k=spec.sed_temperature_k)


@lru_cache(maxsize=64)
def _reach_px(model, angle, budget):
    """Support across plus end cap along the track of the renderer's swept profile, px."""
    plan = swept_profile(model, angle, budget).plan
    return float(plan.support_px + plan.cap_px)


#: Relative allowance on the sampled reach (:func:`margins_px`): the reach changes by < 0.1%
#: between the sampled vertices of a LEO pass (tests/test_pass_truth.py checks the bound).
REACH_ALLOWANCE = 0.01


def _sampled(models, angles):
    """Indices of the vertices whose reach bounds the others': the first and last, the
    nearest and farthest (defocus and shape grow as 1/range), the brightest and faintest
    charge per pixel, and the angle whose pixel projects widest across the track (45 deg)."""
    ranges = [m.geometry.range_km for m in models]
    fluxes = [m.flux_per_px for m in models]
    slant = [abs(np.sin(2 * np.radians(a))) for a in angles]
    return sorted({0, len(models) - 1, int(np.argmin(ranges)), int(np.argmax(ranges)),
                   int(np.argmax(fluxes)), int(np.argmin(fluxes)), int(np.argmax(slant))})


def margins_px(fscene, exhaustive=False):
    """Each satellite's footprint margin (px): the reach of the renderer's swept profile
    (with the tolerance :func:`inject.scene.render_tracks` uses at the quieter sensor's
    noise: tighter, so wider), plus a pixel's diagonal.

    The reach changes only where the vertex values do: for each tolerance the vertices take
    (:func:`inject.scene.render_tracks` snaps it to a grid), it is computed at a few
    vertices (:func:`_sampled`) and allowed :data:`REACH_ALLOWANCE` more, instead of at
    every vertex (``exhaustive=True``, ~0.25 s a vertex).
    """
    noise = min(pixel_noise(replace(fscene.scene, detector=det)) for det in fp.SENSORS.values())
    out = []
    for i, whole in enumerate(fscene.tracks):
        reach = 0.0
        for track in whole.parts():
            models = [vertex_model(fscene, i, values) for values in track.values]
            angles = []
            for k in range(len(models)):
                j = min(k, len(track.xs) - 2)
                angles.append(round(float(np.degrees(np.arctan2(
                    track.ys[j + 1] - track.ys[j], track.xs[j + 1] - track.xs[j]))), 9))
            budgets = [own_budget(Budget(), m, noise) for m in models]
            for budget in dict.fromkeys(budgets):
                group = [k for k, b in enumerate(budgets) if b == budget]
                picks = group if exhaustive else [group[k] for k in _sampled(
                    [models[g] for g in group], [angles[g] for g in group])]
                found = max(_reach_px(models[k], angles[k], budget) for k in picks)
                reach = max(reach, found if exhaustive else found * (1 + REACH_ALLOWANCE))
        out.append(reach + 2.0)  # a pixel's diagonal, so no pixel centre within reach is missed
    return tuple(out)


# -------------------------------------------------------------------------------------------
# Per-CCD tracks

@dataclass(frozen=True)
class CCDStreak:
    """One satellite's part of the track on one CCD (pixels of that CCD).

    ``track`` is a :class:`~inject.config.Track` (a line, a segment or a polyline with the
    interpolated vertex values); ``ends`` the clipped track's first and last points (on a
    cut-out, clipped to the cut-out grown by the margin); ``values`` the vertex values of the
    track's part on the whole CCD (the first sets the streak's model and its render budget);
    ``pixel_scale`` the plate scale along the track where it crosses the whole CCD (the
    middle of that part), so that a cut-out's streak is the whole CCD's.
    """

    satellite: int
    track: Track
    ends: tuple
    values: tuple
    pixel_scale: float


def ccd_shape(fscene, ccd):
    """``(ny, nx)`` simulated for a CCD (its cut-out, clipped to the sensor)."""
    ny, nx = ccd.shape
    if fscene.cutout is None:
        return (ny, nx)
    return (min(ny, fscene.cutout[0]), min(nx, fscene.cutout[1]))


def ccd_streaks(fscene, ccd, margins):
    """The parts of every satellite's track that reach a CCD (its area grown by the margin).

    Returns
    -------
    list of CCDStreak
        In satellite order; a polyline leaving and re-entering the CCD gives one per run.
    """
    shape = ccd_shape(fscene, ccd)
    area = ccd.bounds_mm(0.0, shape)
    out = []
    for i, (whole, margin) in enumerate(zip(fscene.tracks, margins)):
        reach_mm = margin * fp.PIXEL_MM
        for track in whole.parts():
            pieces = clip_path(track.xs, track.ys, ccd.bounds_mm(margin, shape))
            sensor_runs = None
            if shape != ccd.shape:  # a cut-out: the streak is the whole CCD's
                sensor_runs = _runs(clip_path(track.xs, track.ys,
                                              ccd.bounds_mm(margin, ccd.shape)))
            for run in _runs(pieces):
                # The grown rectangle's corners are farther than the margin from the CCD:
                # a run that only cuts a corner leaves it no light.
                if _run_distance(track, run, area) <= reach_mm:
                    sensor_run = run if sensor_runs is None else _holding(sensor_runs, run)
                    out.append(_ccd_streak(fscene, i, track, run, sensor_run, ccd))
    return out


def _holding(runs, part):
    """The run of ``runs`` (the track clipped to the whole sensor's grown area) that holds
    ``part`` (its clip to a cut-out's grown area, a subset): the one its first piece overlaps."""
    k, t0, t1 = part[0]
    for run in runs:
        if any(j == k and a <= t1 and t0 <= b for j, a, b in run):
            return run
    raise AssertionError(f"a cut-out's part of the track (piece {k} at {t0}) is outside "
                         "the whole sensor's")


def _run_distance(track, run, box):
    """Least distance (mm) from a run of clipped track pieces to a box ``(xmin, xmax, ymin,
    ymax)`` (0 where the run crosses it)."""
    xmin, xmax, ymin, ymax = box
    corners = np.array([(xmin, ymin), (xmax, ymin), (xmin, ymax), (xmax, ymax)])
    best = np.inf
    for k, t0, t1 in run:
        a = np.array([track.xs[k], track.ys[k]], float)
        d = np.array([track.xs[k + 1], track.ys[k + 1]], float) - a
        p0, p1 = a + t0 * d, a + t1 * d
        if clip_path((p0[0], p1[0]), (p0[1], p1[1]), box):
            return 0.0
        for q in (p0, p1):  # an end of the piece to the box
            best = min(best, np.hypot(max(xmin - q[0], 0.0, q[0] - xmax),
                                      max(ymin - q[1], 0.0, q[1] - ymax)))
        seg = p1 - p0
        length2 = float(seg @ seg)
        if length2 > 0:  # the box's corners to the piece
            t = np.clip((corners - p0) @ seg / length2, 0.0, 1.0)
            best = min(best, float(np.min(np.hypot(*(p0 + t[:, None] * seg - corners).T))))
    return best


def _runs(pieces):
    """Split clipped pieces into runs that are continuous along the path."""
    runs = []
    for piece in pieces:
        k, t0, _ = piece
        if runs and runs[-1][-1][0] == k - 1 and runs[-1][-1][2] == 1.0 and t0 == 0.0:
            runs[-1].append(piece)
        else:
            runs.append([piece])
    return runs


def _interpolate(track, k, t):
    """Position (mm) and vertex values a fraction ``t`` along piece ``k``."""
    x = track.xs[k] + t * (track.xs[k + 1] - track.xs[k])
    y = track.ys[k] + t * (track.ys[k + 1] - track.ys[k])
    a, b = track.values[k], track.values[k + 1]
    return x, y, {key: a[key] + t * (b[key] - a[key]) for key in a}


def _run_points(track, run):
    """Positions (mm) and vertex values of a run's ends and inner vertices."""
    points = [_interpolate(track, run[0][0], run[0][1])]
    for k, _, t1 in run:
        points.append(_interpolate(track, k, t1))
    return points


def _midpoint_scale(points):
    """The plate scale along the track at the path midpoint of a run: where the CCD sits on
    the track."""
    xs_mm = np.array([p[0] for p in points])
    ys_mm = np.array([p[1] for p in points])
    steps = np.hypot(np.diff(xs_mm), np.diff(ys_mm))
    half = steps.sum() / 2
    j = int(np.searchsorted(np.cumsum(steps), half))
    j = min(j, len(steps) - 1)
    before = steps[:j].sum()
    f = (half - before) / steps[j] if steps[j] > 0 else 0.0
    xm = xs_mm[j] + f * (xs_mm[j + 1] - xs_mm[j])
    ym = ys_mm[j] + f * (ys_mm[j + 1] - ys_mm[j])
    angle_here = float(np.degrees(np.arctan2(ys_mm[j + 1] - ys_mm[j], xs_mm[j + 1] - xs_mm[j])))
    return fp.pixel_scale_along(xm, ym, angle_here)


def _kept_pieces(fscene, i, sensor_run, run, values, scale):
    """The pieces of the whole sensor's run a cut-out renders: those of its own run (the
    others are farther from it than the margin, so add nothing to its pixels), as indices
    into ``sensor_run``; all of them where dropping some would change which vertices share a
    swept profile (:func:`inject.render.render_polyline` builds recurring profiles on its
    orientation grid, the others at their exact angle)."""
    wanted = {k for k, _, _ in run}
    kept = [n for n, (k, _, _) in enumerate(sensor_run) if k in wanted]
    keys = [vertex_model(fscene, i, v, scale).profile_key for v in values]
    inside = keys[kept[0]:kept[-1] + 2]
    if any((keys.count(key) > 1) != (inside.count(key) > 1) for key in inside):
        return list(range(len(sensor_run)))
    return kept


def _with_field(ccd, points, straight):
    """``points`` with the field keys of ``pupil: rubin`` added to their values:
    ``field_angle`` (deg from the optical axis), ``field_pa`` (direction of the outward
    field radius in the CCD's pixels, deg from the track's direction there, unwrapped along
    the track) and ``field_radius`` (that radius on the focal plane, deg from its +x). A
    straight track takes them at its middle on the CCD: one kernel per CCD."""
    xs = np.array([p[0] for p in points])
    ys = np.array([p[1] for p in points])
    where_x, where_y = ((xs[[0, -1]].mean(),), (ys[[0, -1]].mean(),)) if straight else (xs, ys)
    where_x, where_y = np.asarray(where_x), np.asarray(where_y)
    angle = np.degrees(np.hypot(*fp.field_angle(where_x, where_y)))
    r = np.hypot(where_x, where_y)
    safe = np.where(r > 0, r, 1.0)  # on the axis the radius points along +x
    ux, uy = np.where(r > 0, where_x / safe, 1.0), np.where(r > 0, where_y / safe, 0.0)
    step = 1.0  # mm outward
    px0, py0 = ccd.focal_to_pixel(where_x, where_y)
    px1, py1 = ccd.focal_to_pixel(where_x + step * ux, where_y + step * uy)
    radius = np.degrees(np.arctan2(py1 - py0, px1 - px0))
    tx, ty = ccd.focal_to_pixel(xs, ys)
    heading = np.degrees(np.arctan2(np.diff(ty), np.diff(tx)))
    heading = np.append(heading, heading[-1])  # the last vertex: its piece's direction
    if straight:
        heading = heading[:1]
    pa = np.degrees(np.unwrap(np.radians(radius - heading)))
    focal = np.degrees(np.arctan2(uy, ux))
    if straight:
        angle, pa = np.full(len(points), angle[0]), np.full(len(points), pa[0])
        focal = np.full(len(points), focal[0])
    return [(x, y, {**v, "field_angle": float(min(a, FIELD_MAX_DEG)), "field_pa": float(q),
                    "field_radius": float(f)})
            for (x, y, v), a, q, f in zip(points, angle, pa, focal)]


def _to_pixels(ccd, points):
    """Pixel ``x`` and ``y`` lists of points in mm."""
    px, py = ccd.focal_to_pixel(np.array([p[0] for p in points]),
                                np.array([p[1] for p in points]))
    return [float(v) for v in px], [float(v) for v in py]


def _ccd_streak(fscene, i, track, run, sensor_run, ccd):
    """One :class:`CCDStreak`: ``run`` is the track's part on the image, ``sensor_run`` its
    part on the whole sensor (the same run on a full CCD), from which the streak model comes."""
    points = _run_points(track, sensor_run)
    scale = _midpoint_scale(points)
    if fscene.scene.pupil != "annulus":
        points = _with_field(ccd, points, straight=track.kind != "polyline")
    values = tuple(p[2] for p in points)
    px, py = _to_pixels(ccd, points)
    ex, ey = (px, py) if run is sensor_run else _to_pixels(ccd, _run_points(track, run))
    ends = (ex[0], ey[0], ex[-1], ey[-1])
    if track.kind == "line":
        ct = Track(px[0], py[0], track.angle, None)
    elif track.kind == "segment":
        x0, y0 = ccd.focal_to_pixel(track.xs[0], track.ys[0])
        length = np.hypot(track.xs[1] - track.xs[0], track.ys[1] - track.ys[0]) / fp.PIXEL_MM
        ct = Track(float(x0), float(y0), track.angle, float(length))
    else:
        kept = (range(len(sensor_run)) if run is sensor_run
                else _kept_pieces(fscene, i, sensor_run, run, values, scale))
        first, last = kept[0], kept[-1] + 1  # vertex n starts piece n of the run
        vertices = tuple({"x": x, "y": y, **p[2]}
                         for x, y, p in zip(px[first:last + 1], py[first:last + 1],
                                            points[first:last + 1]))
        angle0 = float(np.degrees(np.arctan2(vertices[1]["y"] - vertices[0]["y"],
                                             vertices[1]["x"] - vertices[0]["x"])))
        ct = Track(vertices[0]["x"], vertices[0]["y"], angle0, None, vertices)
    return CCDStreak(i, ct, ends, values, scale)


#: Columns of OUTDIR/satellites.csv (:func:`satellite_records`).
SATELLITE_FIELDS = ("satellite", "name", "source", "in_field", "sunlit", "ccds", "n_ccds",
                    "flags", "message", "scene_sha256")


def satellite_records(plan):
    """One record per satellite of the exposure, whether it left a streak or not.

    ``satellite`` (index in the scene), ``name`` (an orbit's), ``source`` (``track`` or
    ``orbit``), ``in_field`` and ``sunlit`` (an orbit's pass; for a track, whether it reaches
    a CCD, and None), ``ccds`` (space-separated names of the scene's CCDs its footprint
    reaches: where it is rendered, whichever CCDs a run or ``--job`` slice asks for),
    ``n_ccds``, ``flags`` (TRUTH's bits: ``FLAG_OFF_IMAGE`` when no CCD is reached),
    ``message`` (why there is no streak, or how the pass goes) and the scene digest.
    """
    fscene = plan.fscene
    reached = [[] for _ in fscene.tracks]
    for ccd in fscene.ccds:
        for i in sorted({s.satellite for s in plan.streaks(ccd)}):
            reached[i].append(ccd.name)
    out = []
    for i, (track, names) in enumerate(zip(fscene.tracks, reached)):
        orbit = track.in_field is not None
        message = track.message
        if not names and (not orbit or track.xs):
            message = (f"{message}; " if message else "") + \
                "reaches none of the scene's CCDs (outside them or in a gap)"
        out.append({"satellite": i, "name": track.name, "source": "orbit" if orbit else "track",
                    "in_field": track.in_field if orbit else bool(names),
                    "sunlit": track.sunlit, "ccds": " ".join(names), "n_ccds": len(names),
                    "flags": 0 if names else FLAG_OFF_IMAGE, "message": message,
                    "scene_sha256": fscene.digest})
    return out


@dataclass(frozen=True)
class Plan:
    """What an exposure renders, worked out once: each satellite's footprint margin and, for
    every CCD of the scene, the parts of the tracks that reach it (in its pixels).

    Made by :func:`make_plan`; the command line, the runner, the mosaic and ``satellites.csv``
    all read it, so the margins and the per-CCD clipping are computed once per run.
    """

    fscene: object
    margins: tuple
    by_ccd: dict = field(repr=False)

    def streaks(self, ccd):
        """The :class:`CCDStreak` list of a CCD (empty when no footprint reaches it)."""
        return self.by_ccd.get(ccd.name, [])

    def streak_ccds(self, ccds=None):
        """The CCDs (of ``ccds``, default the scene's) that a streak's footprint reaches."""
        return tuple(c for c in (self.fscene.ccds if ccds is None else ccds) if self.streaks(c))

    def summary(self, ccds=None):
        """``--plan --json``: every CCD (of ``ccds``, default the scene's) that a streak's
        footprint reaches, with the streaks' end points in its pixels, and the satellites'
        records."""
        out = [{"name": ccd.name, "id": ccd.id, "vendor": ccd.vendor,
                "streaks": [{"x0": s.ends[0], "y0": s.ends[1], "x1": s.ends[2],
                             "y1": s.ends[3], "satellite": s.satellite}
                            for s in self.streaks(ccd)]}
               for ccd in self.streak_ccds(ccds)]
        return {"detectors": out, "satellites": satellite_records(self)}


def make_plan(fscene, margins=None):
    """The :class:`Plan` of a focal-plane scene (``margins`` default :func:`margins_px`)."""
    margins = margins_px(fscene) if margins is None else tuple(margins)
    by_ccd = {}
    for ccd in fscene.ccds:
        streaks = ccd_streaks(fscene, ccd, margins)
        if streaks:
            by_ccd[ccd.name] = streaks
    return Plan(fscene, margins, by_ccd)
