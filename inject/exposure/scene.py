"""Focal-plane scenes: the keys every scene shares, a pointing, and tracks in focal-plane mm
(checked by :func:`inject.config.parse_focal_parts`).

A track is a line across the whole focal plane (``{x0_mm, y0_mm, angle}``), a segment (with
``length_mm``) or a polyline (``{vertices: [{x_mm, y_mm, height, zenith, phi, mag}, ...]}``,
overrides as in CCD scenes), or comes from the satellite's ``orbit:`` (its pass during the
exposure, :mod:`inject.orbits.tracks`). What each CCD receives is the plan's job
(:mod:`inject.exposure.plan`), simulating one CCD :mod:`inject.exposure.ccd`'s.
"""
import hashlib
import json
from dataclasses import dataclass

from inject.config import parse_focal_parts
from inject.orbits.tracks import orbit_focal_track


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
    """Validate a focal-plane scene mapping (:func:`inject.config.parse_focal_parts`), with
    each ``orbit:`` satellite's pass during the exposure as its track.

    Raises
    ------
    SceneError
        As :func:`inject.config.parse_focal_parts`, or an orbit that cannot be resolved.
    """
    scene, tracks, ccds, cutout = parse_focal_parts(raw, orbit_focal_track)
    return FocalScene(scene=scene, tracks=tracks, ccds=ccds, cutout=cutout,
                      # The resolved tracks too: an orbit's TLE file may change under its name.
                      digest=scene_digest({"scene": raw, "tracks": [
                          (t.kind, t.xs, t.ys, t.values) for t in tracks]}), raw=raw)
