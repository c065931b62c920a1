"""Focal-plane scenes: a CCD scene's keys with a pointing and tracks in focal-plane mm, planned
and simulated one CCD at a time (CONTRACT.md, ``inject focalplane``).

A track is a line across the whole focal plane (``{x0_mm, y0_mm, angle}``), a segment (with
``length_mm``) or a polyline (``{vertices: [{x_mm, y_mm, height, zenith, phi, mag}, ...]}``,
overrides as in CCD scenes). Each satellite reaches the CCDs whose pixel area, grown by its
swept profile's footprint (support across the track plus end cap along it), the track
crosses; on each, the track is clipped to that grown area and put in the CCD's pixels (the
layout has no yaw, so lines stay lines), the polyline's vertex values are interpolated where
the clipped track enters and leaves, and the charge per pixel of track uses the local plate
scale along the track. Light that falls between CCDs is lost, as in the camera.

Random streams are keyed on (scene seed, detector id, purpose) (:func:`inject.scene.rng`);
stars on (scene seed, star tile, ``"stars"``): stars are drawn per fixed 10 mm tile of the
focal plane, and each CCD draws the tiles its pixels and stamps reach, so a star is where the
scene puts it whichever CCDs are rendered.
"""
import hashlib
import json
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from inject.camera import layout as fp
from inject.config import Track, _check_keys, _number, _polyline_track, _TOP_KEYS, parse_scene
from inject.errors import InjectError, SceneError
from inject.instrument import LSST
from inject.profile import Seeing
from inject.render import Budget, swept_profile
from inject.scene import pixel_noise, render_tracks, rng, simulate
from inject.streak import StreakModel
from inject.validate import check_pointing

FOCAL_KEYS = (_TOP_KEYS - {"detector"}) | {"detectors", "cutout"}
#: Keys of a satellite's ``orbit:`` (a TLE, or circular-orbit elements).
_TRACK_KEYS = {"x0_mm", "y0_mm", "angle", "length_mm"}
#: Star tiles: squares of this side (mm) on a fixed grid over the focal plane.
STAR_TILE_MM = 10.0
_TILE_GRID = 80  # tiles per side, centred on the boresight (covers +-400 mm)
#: Star tiles' random streams start here (detector ids are 0-188).
STAR_TILE_KEY = 1000
#: Vertex keys that vary the streak model along a polyline.
VERTEX_MODEL_KEYS = ("height", "zenith", "phi", "mag")
#: Vertex keys of an orbit's track only: the pass's exact range (km) and angular speed across
#: the star field (rad/s), in place of the spherical-Earth ones of (height, zenith, phi).
PASS_KEYS = ("range", "angular_speed")


@dataclass(frozen=True)
class FocalTrack:
    """A satellite's track in focal-plane mm, as a polyline.

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


@dataclass(frozen=True)
class FocalScene:
    """A validated focal-plane scene.

    Attributes
    ----------
    scene : inject.config.Scene
        The CCD-scene part (its ``detector`` and satellites' pixel tracks are placeholders).
    tracks : tuple of FocalTrack
        One per satellite.
    ccds : tuple of inject.camera.layout.CCD
        The CCDs of the exposure (``detectors:``, default the 189 science CCDs).
    cutout : tuple or None
        ``(ny, nx)``: simulate only pixels ``[0, ny) x [0, nx)`` of each CCD (tests, quick
        looks); pixel coordinates and WCS stay those of the full CCD.
    digest : str
        SHA-256 of the scene mapping (canonical JSON): what the manifest records.
    """

    scene: object
    tracks: tuple
    ccds: tuple
    cutout: tuple | None
    digest: str
    raw: dict

    @property
    def pointing(self):
        return self.scene.pointing


def scene_digest(raw):
    """SHA-256 of a scene mapping, independent of key order."""
    text = json.dumps(raw, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def parse_focal_scene(raw):
    """Validate a focal-plane scene mapping.

    Raises
    ------
    SceneError
        A key of the CCD scene is wrong (as :func:`inject.config.parse_scene` reports it),
        ``detector`` is given, ``pointing`` is missing, or a track, detector list or cut-out
        is bad.
    """
    if isinstance(raw, dict) and "detector" in raw:
        raise SceneError("detector: a focal-plane scene has no 'detector' key (use "
                         "'detectors: [R22_S11, ...]' to choose CCDs, 'cutout: {nx, ny}' "
                         "to shrink them)")
    _check_keys("scene", raw, FOCAL_KEYS)
    if raw.get("pointing") is None:
        raise SceneError("pointing: required for a focal-plane scene ({ra, dec, rotation})")
    satellites = raw.get("satellites", [])
    if not isinstance(satellites, list):
        raise SceneError(f"satellites={satellites!r}: must be a list")
    placeholders = []
    for i, sat in enumerate(satellites):
        if isinstance(sat, dict) and "orbit" in sat:
            if "track" in sat:
                raise SceneError(f"satellites[{i}]: give 'track' or 'orbit', not both")
            for key in ("height", "phi"):
                if key in sat:
                    raise SceneError(f"satellites[{i}].{key}: comes from the orbit (remove it)")
            # Placeholders: every vertex of the orbit's track carries its own height and phi
            # (the charge is checked below, on the vertices).
            sat = {k: v for k, v in sat.items() if k not in ("orbit", "lumos")} | {
                "height": 550.0}
        elif isinstance(sat, dict) and "lumos" in sat:
            raise SceneError(f"satellites[{i}].lumos: only with an orbit (its pass's geometry)")
        elif not isinstance(sat, dict) or "track" not in sat:
            _check_keys(f"satellites[{i}]", sat, {"track"}, {"track"})
        placeholders.append({**sat, "track": {"x0": 0.0, "y0": 0.0, "angle": 0.0}})
    ccd_part = {k: v for k, v in raw.items() if k not in ("detectors", "cutout")}
    scene = parse_scene({**ccd_part, "satellites": placeholders, "detector": {"type": "itl"}},
                        charge_check=False)
    try:
        check_pointing(scene.pointing)  # required here (optional in a CCD scene)
        ccds = fp.select(raw.get("detectors"))
    except InjectError as err:
        raise SceneError(str(err)) from None
    tracks = tuple(
        _orbit_track(f"satellites[{i}].orbit", sat["orbit"], spec, scene, raw, sat.get("lumos"))
        if "orbit" in sat else _focal_track(f"satellites[{i}].track", sat["track"], spec, scene)
        for i, (sat, spec) in enumerate(zip(satellites, scene.satellites)))
    _check_track_charge(scene, tracks)
    return FocalScene(scene=scene, tracks=tracks, ccds=ccds,
                      cutout=_cutout(raw.get("cutout")),
                      # The resolved tracks too: an orbit's TLE file may change under its name.
                      digest=scene_digest({"scene": raw, "tracks": [
                          (t.kind, t.xs, t.ys, t.values) for t in tracks]}), raw=raw)


def _check_track_charge(scene, tracks):
    """:func:`inject.config.check_charge` on every satellite's own vertex values (an orbit's
    pass, a polyline's overrides; the satellite's for a line or segment), at the nominal
    plate scale; a pass with no streak has no charge."""
    from inject.config import check_charge

    sats = tuple(replace(spec, track=Track(0.0, 0.0, 0.0, None, tuple(
        v for v in track.values if v is not None) if track.kind == "polyline" else None))
        for spec, track in zip(scene.satellites, tracks) if track.values)
    check_charge(replace(scene, satellites=sats))


def _cutout(spec):
    if spec is None:
        return None
    _check_keys("cutout", spec, {"nx", "ny"}, {"nx", "ny"})
    nx, ny = (_number(f"cutout.{k}", spec[k], int) for k in ("nx", "ny"))
    if not (1 <= nx <= fp.ITL.nx and 1 <= ny <= fp.ITL.ny):
        raise SceneError(f"cutout={spec!r}: nx must be in [1, {fp.ITL.nx}], ny in "
                         f"[1, {fp.ITL.ny}] (the smaller sensor)")
    return (ny, nx)


def _focal_track(where, track, spec, scene):
    base = {"height": spec.height, "zenith": scene.zenith, "phi": spec.phi, "mag": spec.mag}
    if isinstance(track, dict) and "vertices" in track:
        _check_keys(where, track, {"vertices"}, {"vertices"})
        vertices = track["vertices"]
        if not isinstance(vertices, list):
            raise SceneError(f"{where}.vertices: needs a list of at least two vertices")
        converted = []
        for j, vertex in enumerate(vertices):
            here = f"{where}.vertices[{j}]"
            _check_keys(here, vertex, {"x_mm", "y_mm", *VERTEX_MODEL_KEYS}, {"x_mm", "y_mm"})
            converted.append({("x" if k == "x_mm" else "y" if k == "y_mm" else k): v
                              for k, v in vertex.items()})
        checked = _polyline_track(where, {"vertices": converted})["vertices"]
        xs = tuple(v["x"] for v in checked)
        ys = tuple(v["y"] for v in checked)
        if all(np.hypot(x1 - x0, y1 - y0) == 0
               for x0, y0, x1, y1 in zip(xs[:-1], ys[:-1], xs[1:], ys[1:])):
            raise SceneError(f"{where}.vertices: all vertices at one point")
        values = tuple({k: v.get(k, base[k]) for k in VERTEX_MODEL_KEYS} for v in checked)
        angle = float(np.degrees(np.arctan2(ys[1] - ys[0], xs[1] - xs[0])))
        return FocalTrack("polyline", xs, ys, values, angle)
    _check_keys(where, track, _TRACK_KEYS, {"x0_mm", "y0_mm", "angle"})
    x0, y0, angle = (_number(f"{where}.{k}", track[k]) for k in ("x0_mm", "y0_mm", "angle"))
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    if track.get("length_mm") is None:
        reach = 1000.0 + np.hypot(x0, y0)  # far beyond the focal plane on both sides
        return FocalTrack("line", (x0 - reach * c, x0 + reach * c),
                          (y0 - reach * s, y0 + reach * s), (base, base), angle)
    length = _number(f"{where}.length_mm", track["length_mm"])
    if not length > 0:
        raise SceneError(f"{where}.length_mm={length}: must be > 0 (mm)")
    return FocalTrack("segment", (x0, x0 + length * c), (y0, y0 + length * s), (base, base),
                      angle)


def _orbit_track(where, spec, sat, scene, raw, lumos=None):
    """A satellite's track from its orbit during the exposure: the apparent, sunlit parts of
    the pass inside the field (all of them, in time order) as a polyline in mm (:func:`inject.orbits.passes.track_runs` on a pass
    sampled every 0.1 s: a vertex at least every second and wherever the path bends by more
    than 0.05 px), each vertex with the orbit's height, zenith (90 - alt), phi and the
    satellite's ``mag`` dimmed by the penumbra (the streak model scales it with range and
    nadir angle itself, as :meth:`inject.orbits.passes.Pass.magnitude` does), and the pass's exact
    ``range`` and ``angular_speed`` (so t_eff, the charge per pixel and the defocus are the
    pass's, not those of the paper's spherical Earth at that height and zenith). A pass that never
    enters the field or is in shadow there has no vertices, and says why (OrbitWarning)."""
    dense = _orbit_pass(where, spec, raw, scene.exptime, scene.pointing)
    runs, message = _orbit_vertices(where, dense, sat.mag, lumos, sat.ref_range)
    about = {"name": dense.orbit.name or "", "in_field": bool(dense.in_field),
             "sunlit": bool(dense.visible)}
    if not runs:
        return FocalTrack("polyline", (), (), (), 0.0, message, **about)
    xd, yd = dense.focal_mm()
    xs, ys, values = [], [], []
    for run, vals in runs:
        if xs:  # a break between sunlit parts
            xs.append(np.nan), ys.append(np.nan), values.append(None)
        xs += [float(v) for v in xd[run]]
        ys += [float(v) for v in yd[run]]
        values += vals
    angle = float(np.degrees(np.arctan2(ys[1] - ys[0], xs[1] - xs[0])))
    return FocalTrack("polyline", tuple(xs), tuple(ys), tuple(values), angle, message, **about)


def _orbit_pass(where, spec, raw, exptime, pointing):
    """The pass (every 0.1 s) of a satellite's ``orbit:`` in a scene, errors as SceneError."""
    from inject.orbits.passes import (TRACK_STEP_S, Exposure, Pointing, compute_pass, orbit_from_spec,
                         parse_time, site_from_spec)

    if raw.get("time") is None:
        raise SceneError(f"time: required with {where} (exposure start, ISO 8601 UTC)")
    try:
        time = parse_time(raw["time"], "time")
        orbit = orbit_from_spec(spec, time, where)
        site = site_from_spec(raw.get("site"))
        point = Pointing(pointing["ra"], pointing["dec"], pointing.get("rotation", 0.0))
        return compute_pass(orbit, Exposure(time, exptime), point, site, step_s=TRACK_STEP_S)
    except SceneError:
        raise
    except InjectError as err:
        text = str(err)
        raise SceneError(text if text.startswith(("site", where)) else f"{where}: {text}") \
            from None


def _no_streak(where, dense):
    """Why a pass renders no streak (the message, also warned as an OrbitWarning)."""
    import warnings

    from inject.errors import OrbitWarning

    if not dense.in_field:
        why = dense.message
    elif dense.visible:
        why = "crosses the field only outside the camera's reach"
    else:
        why = "crosses the field in Earth's shadow"
    message = f"{where}: no streak: {why}"
    warnings.warn(message, OrbitWarning, stacklevel=3)
    return message


def _orbit_vertices(where, dense, mag, lumos=None, ref_range=550.0):
    """The sunlit runs of a pass's track, in time order: a list of (sample indices, vertex
    values), and a message; no runs when there is no streak (the message says why).

    ``lumos`` (a satellite's ``lumos:`` mapping): each vertex's brightness from lumos-sat
    (:mod:`inject.orbits.lumos`) instead of ``mag`` scaled by the paper's law."""
    from inject.orbits.passes import track_runs

    xd, yd, runs = track_runs(dense, lit_only=True)
    if not runs:
        return [], _no_streak(where, dense)
    lit = np.concatenate(runs)
    message = "crosses the field, sunlit" if dense.sun_fraction[lit].min() >= 1 else \
        "crosses the field, partly in Earth's shadow (the streak ends or fades there)"
    if len(runs) > 1:
        message += f"; {len(runs)} sunlit parts (out of and back into the shadow), all rendered"
    out = []
    for run in runs:
        dim = -2.5 * np.log10(dense.sun_fraction[run])
        base = np.full(len(run), float(mag))
        if lumos is not None:
            from inject.geometry import nadir_angle
            from inject.orbits.passes.lumos import magnitudes
            from inject.photometry import apparent_magnitude

            # The mag at ref_range, face-on, that the streak model's cos/r^2 scaling turns
            # into lumos's apparent magnitude here.
            zenith = 90.0 - dense.alt_deg[run]
            base = magnitudes(where.replace(".orbit", ".lumos"), lumos, dense, run) - \
                apparent_magnitude(0.0, dense.range_km[run],
                                   nadir_angle(dense.height_km[run], zenith), ref_range)
        phi = np.where(np.isfinite(dense.phi_deg[run]), dense.phi_deg[run], 90.0)  # at zenith
        values = [{"height": float(h), "zenith": float(90.0 - a), "phi": float(f),
                   "mag": float(m + d), "range": float(r), "angular_speed": float(w)}
                  for h, a, f, m, d, r, w in zip(dense.height_km[run], dense.alt_deg[run], phi,
                                                 base, dim, dense.range_km[run],
                                                 dense.angular_speed_rad_s[run])]
        out.append((run, values))
    return out, message


def ccd_orbit_satellites(raw, satellites, shape, pointing):
    """A CCD scene's satellites with each ``orbit:`` replaced by its track in the CCD's pixels.

    The CCD scene's WCS (:func:`inject.camera.wcs.pointing_wcs`: TAN about the pointing at the image
    centre, LSST's plate scale, no distortion) maps the pass's field angles (ICRS gnomonic
    offsets, rotated as the WCS's CD matrix) linearly to pixels. A pass with no streak gets a
    track far off the image (its TRUTH row is flagged off-image) and a warning saying why.
    """
    from inject.instrument import LSST

    if pointing is None:
        raise SceneError("pointing: required with an orbit ({ra, dec, rotation})")
    exptime = _number("exptime", raw["exptime"])
    ny, nx = shape
    scale_deg = LSST.pixel_scale_arcsec / 3600.0
    out = []
    for i, sat in enumerate(satellites):
        if not (isinstance(sat, dict) and "orbit" in sat):
            out.append(sat)
            continue
        where = f"satellites[{i}].orbit"
        for key in ("track", "height", "phi"):
            if key in sat:
                raise SceneError(f"satellites[{i}].{key}: comes from the orbit (remove it)")
        dense = _orbit_pass(where, sat["orbit"], raw, exptime, pointing)
        runs, _ = _orbit_vertices(where, dense, _number(f"satellites[{i}].mag", sat.get("mag")),
                                  sat.get("lumos"), _number(f"satellites[{i}].ref_range",
                                                            sat.get("ref_range", 550.0)))
        rest = {k: v for k, v in sat.items() if k not in ("orbit", "lumos")}
        if not runs:
            far = -9e5  # 50 deg off: nothing of it on the image
            vertices = [{"x": far, "y": far}, {"x": far + 1.0, "y": far}]
            out.append({**rest, "height": float(np.nanmean(dense.height_km)),
                        "track": {"vertices": vertices}})
            continue
        for run, values in runs:  # one streak (and TRUTH row) per sunlit part
            x = (nx - 1) / 2 + dense.field_x_deg[run] / scale_deg
            y = (ny - 1) / 2 + dense.field_y_deg[run] / scale_deg
            vertices = [{"x": float(a), "y": float(b), **v} for a, b, v in zip(x, y, values)]
            out.append({**rest, "height": values[0]["height"], "track": {"vertices": vertices}})
    return out


# -------------------------------------------------------------------------------------------
# Models and margins

def vertex_model(fscene, i, values, pixel_scale=None):
    """The :class:`StreakModel` of satellite ``i`` with vertex ``values``, at a plate scale."""
    scene, spec = fscene.scene, fscene.scene.satellites[i]
    telescope = LSST if pixel_scale is None else LSST.with_pixel_scale(pixel_scale)
    return StreakModel(height_km=values["height"], zenith_deg=values["zenith"],
                       phi_deg=values["phi"], shape=spec.shape, mag=values["mag"],
                       band_name=scene.band, seeing=Seeing(scene.seeing), telescope=telescope,
                       ref_range_km=spec.ref_range, range_km=values.get("range"),
                       angular_speed_rad_s=values.get("angular_speed"))


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
    from inject.scene import _own_budget

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
            budgets = [_own_budget(Budget(), m, noise) for m in models]
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
    interpolated vertex values); ``ends`` the clipped track's first and last points;
    ``pixel_scale`` the plate scale along the track where it crosses the CCD.
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


def ccd_streaks(fscene, ccd, margins=None):
    """The parts of every satellite's track that reach a CCD (its area grown by the margin).

    Returns
    -------
    list of CCDStreak
        In satellite order; a polyline leaving and re-entering the CCD gives one per run.
    """
    margins = margins_px(fscene) if margins is None else margins
    shape = ccd_shape(fscene, ccd)
    out = []
    for i, (whole, margin) in enumerate(zip(fscene.tracks, margins)):
        for track in whole.parts():
            pieces = fp.clip_path(track.xs, track.ys, ccd.bounds_mm(margin, shape))
            for run in _runs(pieces):
                out.append(_ccd_streak(i, track, run, ccd))
    return out


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


def _ccd_streak(i, track, run, ccd):
    points = [_interpolate(track, run[0][0], run[0][1])]
    for k, _, t1 in run:
        points.append(_interpolate(track, k, t1))
    # Path midpoint of the clipped part: where the CCD sits on the track.
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
    scale = fp.pixel_scale_along(xm, ym, angle_here)
    px, py = ccd.focal_to_pixel(xs_mm, ys_mm)
    px, py = [float(v) for v in px], [float(v) for v in py]
    ends = (px[0], py[0], px[-1], py[-1])
    if track.kind == "line":
        ct = Track(px[0], py[0], track.angle, None)
        values = (points[0][2],)
    elif track.kind == "segment":
        x0, y0 = ccd.focal_to_pixel(track.xs[0], track.ys[0])
        length = np.hypot(track.xs[1] - track.xs[0], track.ys[1] - track.ys[0]) / fp.PIXEL_MM
        ct = Track(float(x0), float(y0), track.angle, float(length))
        values = (points[0][2],)
    else:
        vertices = tuple({"x": x, "y": y, **p[2]} for x, y, p in zip(px, py, points))
        angle0 = float(np.degrees(np.arctan2(py[1] - py[0], px[1] - px[0])))
        ct = Track(px[0], py[0], angle0, None, vertices)
        values = tuple(p[2] for p in points)
    return CCDStreak(i, ct, ends, values, scale)


def plan(fscene, ccds=None, margins=None):
    """What would be rendered: every CCD (of ``ccds``, default the scene's) that a streak's
    footprint reaches, with the streaks' end points in its pixels (``--plan --json``)."""
    margins = margins_px(fscene) if margins is None else margins
    out = []
    for ccd in fscene.ccds if ccds is None else ccds:
        streaks = ccd_streaks(fscene, ccd, margins)
        if streaks:
            out.append({"name": ccd.name, "id": ccd.id, "vendor": ccd.vendor,
                        "streaks": [{"x0": s.ends[0], "y0": s.ends[1], "x1": s.ends[2],
                                     "y1": s.ends[3], "satellite": s.satellite}
                                    for s in streaks]})
    return {"detectors": out, "satellites": satellite_records(fscene, margins)}


#: Columns of OUTDIR/satellites.csv (:func:`satellite_records`).
SATELLITE_FIELDS = ("satellite", "name", "source", "in_field", "sunlit", "ccds", "n_ccds",
                    "flags", "message", "scene_sha256")


def satellite_records(fscene, margins=None):
    """One record per satellite of the exposure, whether it left a streak or not.

    ``satellite`` (index in the scene), ``name`` (an orbit's), ``source`` (``track`` or
    ``orbit``), ``in_field`` and ``sunlit`` (an orbit's pass; for a track, whether it reaches
    a CCD, and None), ``ccds`` (space-separated names of the scene's CCDs its footprint
    reaches: where it is rendered, whichever CCDs a run or ``--job`` slice asks for),
    ``n_ccds``, ``flags`` (TRUTH's bits: ``FLAG_OFF_IMAGE`` when no CCD is reached),
    ``message`` (why there is no streak, or how the pass goes) and the scene digest.
    """
    from inject.maskplanes import FLAG_OFF_IMAGE

    margins = margins_px(fscene) if margins is None else margins
    reached = [[] for _ in fscene.tracks]
    for ccd in fscene.ccds:
        for i in sorted({s.satellite for s in ccd_streaks(fscene, ccd, margins)}):
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


# -------------------------------------------------------------------------------------------
# Simulating one CCD

def ccd_scene(fscene, ccd, streaks=()):
    """The CCD scene of one detector: its sensor (cut-out), the satellites that reach it with
    their tracks in its pixels."""
    ny, nx = ccd_shape(fscene, ccd)
    det = ccd.detector if (ny, nx) == ccd.shape else ccd.detector.cutout(nx, ny)
    sats = tuple(replace(fscene.scene.satellites[s.satellite], track=s.track) for s in streaks)
    return replace(fscene.scene, detector=det, satellites=sats)


def _star_tiles(box):
    """Indices of the star tiles overlapping a box (mm)."""
    lo = -_TILE_GRID / 2 * STAR_TILE_MM
    ix = range(max(0, int(np.floor((box[0] - lo) / STAR_TILE_MM))),
               min(_TILE_GRID, int(np.floor((box[1] - lo) / STAR_TILE_MM)) + 1))
    iy = range(max(0, int(np.floor((box[2] - lo) / STAR_TILE_MM))),
               min(_TILE_GRID, int(np.floor((box[3] - lo) / STAR_TILE_MM)) + 1))
    return [(i, j) for j in iy for i in ix]


def tile_stars(scene, spec, tile):
    """The stars of one focal-plane tile: ``x_mm, y_mm, mag`` (its own random stream)."""
    from inject.stars import sample_stars

    i, j = tile
    lo = -_TILE_GRID / 2 * STAR_TILE_MM
    gen = rng(scene.seed, "stars", STAR_TILE_KEY + j * _TILE_GRID + i)
    side_deg = STAR_TILE_MM * fp.PLATE_SCALE_ARCSEC_PER_MM / 3600.0
    mag = sample_stars(spec, side_deg ** 2, scene.band, gen)
    x = lo + STAR_TILE_MM * (i + gen.uniform(0.0, 1.0, mag.size))
    y = lo + STAR_TILE_MM * (j + gen.uniform(0.0, 1.0, mag.size))
    return x, y, mag


def add_focal_stars(image, fscene, ccd, wcs=None, noise=None, variance=None):
    """Add the scene's stars that light a CCD (in place): those of every tile its pixels, grown
    by the bright-star stamp, overlap. A catalog in ra, dec goes through the CCD's WCS.
    ``noise`` and ``variance``: see :func:`inject.stars.draw_stars`."""
    from inject.photometry import electron_rate
    from inject.stars import add_star_field, draw_stars, psf_stamps, spec_from_scene

    scene = fscene.scene
    spec = spec_from_scene(scene)
    if spec.catalog is not None:
        return add_star_field(image, scene, None, wcs=wcs, noise=noise, variance=variance)
    if scene.seeing <= 0:
        raise SceneError("stars: need seeing > 0 (stars share the atmospheric PSF)")
    pixel_scale = LSST.pixel_scale_arcsec
    stamps = psf_stamps(Seeing(scene.seeing).profile(), pixel_scale)
    box = ccd.bounds_mm(stamps.bright_half + 1, image.shape)
    parts = [tile_stars(scene, spec, tile) for tile in _star_tiles(box)]
    if not parts:
        return None
    x_mm, y_mm, mag = (np.concatenate(v) for v in zip(*parts))
    x, y = ccd.focal_to_pixel(x_mm, y_mm)
    flux = electron_rate(mag, scene.band) * scene.exptime
    return draw_stars(image, x, y, flux, stamps, pixel_scale, noise=noise, variance=variance)


def simulate_ccd(fscene, ccd, margins=None, budget=Budget()):
    """Simulate one CCD of a focal-plane scene.

    Returns
    -------
    scene : inject.config.Scene
        The CCD's scene (for the file's headers).
    result : inject.scene.SceneResult
    streaks : list of CCDStreak
    wcs : astropy.wcs.WCS
    """
    streaks = ccd_streaks(fscene, ccd, margins)
    scene = ccd_scene(fscene, ccd, streaks)
    wcs = fp.ccd_wcs(ccd, fscene.pointing)
    models = [vertex_model(fscene, s.satellite, s.values[0], s.pixel_scale) for s in streaks]
    rendered = render_tracks(scene.detector.shape, models, [s.track for s in streaks], budget,
                             pixel_noise(scene))
    for row, s in zip(rendered[1], streaks):
        row["satellite"] = s.satellite
        row["pixel_scale_arcsec"] = s.pixel_scale
    result = simulate(scene, budget, detector_index=ccd.id, wcs=wcs, rendered=rendered,
                      add_stars=lambda image, **noise: add_focal_stars(image, fscene, ccd, wcs,
                                                                       **noise))
    return scene, result, streaks, wcs
