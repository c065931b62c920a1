"""Focal-plane scenes: the keys every scene shares, a pointing, and tracks in focal-plane mm.

A track is a line across the whole focal plane (``{x0_mm, y0_mm, angle}``), a segment (with
``length_mm``) or a polyline (``{vertices: [{x_mm, y_mm, height, zenith, phi, mag}, ...]}``,
overrides as in CCD scenes), or comes from the satellite's ``orbit:`` (its pass during the
exposure, :mod:`inject.orbits.tracks`). What each CCD receives is the plan's job
(:mod:`inject.exposure.plan`), simulating one CCD :mod:`inject.exposure.ccd`'s.
"""
import hashlib
import json
from dataclasses import dataclass, replace

import numpy as np

from inject.camera import layout as fp
from inject.config import (
    COMMON_KEYS,
    SATELLITE_MODEL_KEYS,
    VERTEX_MODEL_KEYS,
    Scene,
    check_charge,
    parse_common,
    parse_satellite,
    parse_vertices,
    satellite_list,
)
from inject.errors import InjectError, SceneError
from inject.orbits.tracks import orbit_focal_track
from inject.schema import check_keys, number, ranged
from inject.trajectory import FocalTrack

#: Keys of a focal-plane scene.
FOCAL_KEYS = COMMON_KEYS | {"detectors", "cutout"}
#: Keys of a straight track in focal-plane mm.
TRACK_KEYS_MM = frozenset({"x0_mm", "y0_mm", "angle", "length_mm"})
#: Keys of a satellite given by its orbit (its height and phi come from the pass).
ORBIT_SATELLITE_KEYS = (SATELLITE_MODEL_KEYS - {"height", "phi"}) | {"orbit", "lumos"}


@dataclass(frozen=True)
class FocalScene:
    """A validated focal-plane scene.

    Attributes
    ----------
    scene : inject.config.Scene
        The part every scene shares, with no detector, and the satellites' models (no pixel
        tracks: the tracks are below).
    tracks : tuple of FocalTrack
        One per satellite.
    ccds : tuple of inject.camera.layout.CCD
        The CCDs of the exposure (``detectors:``, default the 189 science CCDs).
    cutout : tuple or None
        ``(ny, nx)``: simulate only pixels ``[0, ny) x [0, nx)`` of each CCD, each side
        clipped to the CCD's own size (tests, quick looks); pixel coordinates and WCS stay
        those of the full CCD.
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
        A key every scene shares is wrong (as :func:`inject.config.parse_scene` reports it),
        ``detector`` is given, ``pointing`` is missing, or a track, detector list or cut-out
        is bad.
    """
    if isinstance(raw, dict) and "detector" in raw:
        raise SceneError("detector: a focal-plane scene has no 'detector' key (use "
                         "'detectors: [R22_S11, ...]' to choose CCDs, 'cutout: {nx, ny}' "
                         "to shrink them)")
    check_keys("scene", raw, FOCAL_KEYS)
    if raw.get("pointing") is None:
        raise SceneError("pointing: required for a focal-plane scene ({ra, dec, rotation})")
    satellites = satellite_list(raw)
    for i, sat in enumerate(satellites):  # before the common keys: as a CCD scene reports it
        where = f"satellites[{i}]"
        if isinstance(sat, dict) and "orbit" in sat:
            if "track" in sat:
                raise SceneError(f"{where}: give 'track' or 'orbit', not both")
            for key in ("height", "phi"):
                if key in sat:
                    raise SceneError(f"{where}.{key}: comes from the orbit (remove it)")
            check_keys(where, sat, ORBIT_SATELLITE_KEYS, {"shape", "mag", "orbit"})
        elif isinstance(sat, dict) and "lumos" in sat:
            raise SceneError(f"{where}.lumos: only with an orbit (its pass's geometry)")
        else:
            check_keys(where, sat, SATELLITE_MODEL_KEYS | {"track"},
                       {"height", "shape", "mag", "track"})
    common = Scene(detector=None, **parse_common(raw))
    try:
        ccds = fp.select(raw.get("detectors"))
    except InjectError as err:
        raise SceneError(str(err)) from None
    specs, tracks = [], []
    for i, sat in enumerate(satellites):
        where = f"satellites[{i}]"
        spec = parse_satellite(where, sat, height_from_orbit="orbit" in sat)
        specs.append(spec)
        tracks.append(orbit_focal_track(f"{where}.orbit", sat["orbit"], spec, common, raw,
                                        sat.get("lumos")) if "orbit" in sat
                      else _focal_track(f"{where}.track", sat["track"], spec, common))
    scene = replace(common, satellites=tuple(specs))
    # The charge of every satellite's own vertex values (an orbit's pass, a polyline's
    # overrides; the satellite's for a line or segment), at the nominal plate scale; a pass
    # with no streak has no charge.
    check_charge(scene, [tuple(v for v in t.values if v is not None) if t.kind == "polyline"
                         else ({},) for t in tracks])
    return FocalScene(scene=scene, tracks=tuple(tracks), ccds=ccds,
                      cutout=_cutout(raw.get("cutout")),
                      # The resolved tracks too: an orbit's TLE file may change under its name.
                      digest=scene_digest({"scene": raw, "tracks": [
                          (t.kind, t.xs, t.ys, t.values) for t in tracks]}), raw=raw)


def _cutout(spec):
    """``(ny, nx)`` of a ``cutout:`` mapping, in the bounds of a CCD scene's ``detector.nx``
    and ``ny``; a side not given is the largest sensor's, so that every CCD keeps its full
    size there (:func:`inject.exposure.plan.ccd_shape` clips each side to the CCD's own)."""
    if spec is None:
        return None
    check_keys("cutout", spec, {"nx", "ny"})
    if not spec:
        raise SceneError("cutout: give nx, ny or both (pixels)")
    largest = {"nx": max(d.nx for d in fp.SENSORS.values()),
               "ny": max(d.ny for d in fp.SENSORS.values())}
    nx, ny = (ranged(f"detector.{k}", f"cutout.{k}", spec.get(k, largest[k]), int)
              for k in ("nx", "ny"))
    return (ny, nx)


def _focal_track(where, track, spec, scene):
    base = {"height": spec.height, "zenith": scene.zenith, "phi": spec.phi, "mag": spec.mag}
    if isinstance(track, dict) and "vertices" in track:
        check_keys(where, track, {"vertices"}, {"vertices"})
        checked = parse_vertices(where, track["vertices"], position=("x_mm", "y_mm"), extra=())
        xs = tuple(v["x_mm"] for v in checked)
        ys = tuple(v["y_mm"] for v in checked)
        if all(np.hypot(x1 - x0, y1 - y0) == 0
               for x0, y0, x1, y1 in zip(xs[:-1], ys[:-1], xs[1:], ys[1:])):
            raise SceneError(f"{where}.vertices: all vertices at one point")
        values = tuple({k: v.get(k, base[k]) for k in VERTEX_MODEL_KEYS} for v in checked)
        angle = float(np.degrees(np.arctan2(ys[1] - ys[0], xs[1] - xs[0])))
        return FocalTrack("polyline", xs, ys, values, angle)
    check_keys(where, track, TRACK_KEYS_MM, {"x0_mm", "y0_mm", "angle"})
    x0, y0, angle = (number(f"{where}.{k}", track[k]) for k in ("x0_mm", "y0_mm", "angle"))
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    if track.get("length_mm") is None:
        reach = 1000.0 + np.hypot(x0, y0)  # far beyond the focal plane on both sides
        return FocalTrack("line", (x0 - reach * c, x0 + reach * c),
                          (y0 - reach * s, y0 + reach * s), (base, base), angle)
    length = number(f"{where}.length_mm", track["length_mm"])
    if not length > 0:
        raise SceneError(f"{where}.length_mm={length}: must be > 0 (mm)")
    return FocalTrack("segment", (x0, x0 + length * c), (y0, y0 + length * s), (base, base),
                      angle)


