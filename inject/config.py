"""Scene files: YAML parsed safely, dotted overrides, validation into a :class:`Scene`.

Every problem is reported as a :class:`~inject.errors.SceneError` naming the key path
(``satellites[0].height``) and the bad value.
"""
from dataclasses import dataclass, field

import numbers
import re

import numpy as np
import yaml

from .detector import Detector, detector_from_spec
from .errors import InjectError, SceneError
from .photometry import band
from .satellite import Shape, shape_from_dict
from .validate import positive

#: The embedded default scene: the paper's 550 km satellite on one full ITL CCD.
DEFAULT_SCENE = {
    "seed": 1, "band": "g", "exptime": 30.0, "seeing": 0.67, "zenith": 70.0,
    "detector": {"type": "itl"}, "sky": True, "stars": True, "noise": True,
    "satellites": [{
        "height": 550.0, "phi": 90.0, "shape": {"type": "box", "length": 7.25, "width": 2.65},
        "mag": 5.0, "ref_range": 550.0, "track": {"x0": 300.0, "y0": 200.0, "angle": 33.0}}],
}

_TOP_KEYS = {"seed", "band", "exptime", "seeing", "zenith", "detector", "sky", "stars", "noise",
             "satellites", "pointing", "dark_current", "cosmic_rays", "units"}
_SATELLITE_KEYS = {"height", "phi", "shape", "mag", "ref_range", "track"}
_TRACK_KEYS = {"x0", "y0", "angle", "length"}
_VERTEX_KEYS = {"x", "y", "height", "zenith", "phi", "mag"}


@dataclass(frozen=True)
class Track:
    """Where a streak goes on the pixel grid; ``length=None`` crosses the whole image.

    ``vertices`` makes it a polyline: a tuple of mappings with ``x``, ``y`` (pixels) and
    optionally ``height``, ``zenith``, ``phi``, ``mag`` overriding the satellite's values at
    that vertex (so width, speed and brightness can change along the track).
    """

    x0: float
    y0: float
    angle: float
    length: float | None = None
    vertices: tuple | None = None


@dataclass(frozen=True)
class SatelliteSpec:
    """One satellite of a scene."""

    height: float
    shape: Shape
    mag: float
    track: Track
    phi: float = 90.0
    ref_range: float = 550.0


@dataclass(frozen=True)
class Scene:
    """A validated single-CCD scene."""

    seed: int
    band: str
    exptime: float
    seeing: float
    zenith: float
    detector: Detector
    sky: object
    stars: object
    noise: bool
    satellites: tuple = field(default_factory=tuple)
    pointing: dict | None = None
    dark_current: float = 0.0
    cosmic_rays: float = 0.0
    units: str = "electron"
    raw: dict = field(default_factory=dict, compare=False, repr=False)


class _SceneLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` reading floats as YAML 1.2 does: ``1e3`` and ``5e-1`` are numbers
    (YAML 1.1, PyYAML's default, needs a dot and an exponent sign)."""


_SceneLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)?(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def load_scene_file(path):
    """Read a YAML scene file into a mapping (``yaml.safe_load``: no code runs).

    Raises
    ------
    SceneError
        ``path`` is not a file path, cannot be read, is not UTF-8 text or valid YAML, or does
        not hold a mapping.
    """
    try:
        with open(path, encoding="utf-8") as stream:
            raw = yaml.load(stream, Loader=_SceneLoader)  # safe: no Python tags
    except TypeError:  # open() says only "expected str, bytes or os.PathLike object"
        raise SceneError(f"scene file {path!r}: not a file path") from None
    except OSError as err:
        raise SceneError(f"{path}: cannot read scene file ({err.strerror})") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text (UTF-8) scene file") from None
    except yaml.YAMLError as err:
        raise SceneError(f"{path}: not valid YAML ({err})") from None
    if not isinstance(raw, dict):
        raise SceneError(f"{path}: a scene file must be a mapping of keys to values")
    return raw


def apply_overrides(raw, overrides):
    """Apply ``key.path=value`` strings to a scene mapping (values parsed as YAML scalars).

    List items are addressed by index: ``satellites.0.mag=6``. Values are read as in scene
    files (``1e3`` is a number).

    Raises
    ------
    SceneError
        An override is not a ``key.path=value`` string, its value is not valid YAML, or its
        path does not fit the scene.
    """
    if isinstance(overrides, str):  # would be taken one character at a time
        raise SceneError(f"overrides={overrides!r}: must be a list of key.path=value strings")
    try:
        raw = yaml.safe_load(yaml.safe_dump(raw))  # a deep copy of plain data
    except yaml.YAMLError as err:
        raise SceneError(f"scene: not plain data ({err})") from None
    for item in overrides:
        if not isinstance(item, str):
            raise SceneError(f"override {item!r}: expected a key.path=value string")
        path, sep, text = item.partition("=")
        if not sep or not path:
            raise SceneError(f"override {item!r}: expected key.path=value")
        try:
            value = yaml.load(text, Loader=_SceneLoader)  # safe, as load_scene_file
        except yaml.YAMLError as err:
            raise SceneError(f"override {item!r}: value is not valid YAML ({err})") from None
        node, keys = raw, path.split(".")
        for depth, key in enumerate(keys):
            last = depth == len(keys) - 1
            where = ".".join(keys[: depth + 1])
            if isinstance(node, list):
                if not key.isdigit() or int(key) >= len(node):
                    raise SceneError(f"override {item!r}: no list item {where}")
                key = int(key)
            elif not isinstance(node, dict):
                raise SceneError(f"override {item!r}: {'.'.join(keys[:depth])} is not a mapping")
            if last:
                node[key] = value
            else:
                if isinstance(node, dict) and not isinstance(node.get(key), (dict, list)):
                    node[key] = {}
                node = node[key]
    return raw


def _number(where, value, kind=float):
    # numbers.Real: NumPy scalars from Python callers are numbers too; bools are not.
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(f"{where}={value!r}: must be a number")
    if value != value or value in (float("inf"), float("-inf")):
        raise SceneError(f"{where}={value!r}: must be finite")
    if kind is int and value != int(value):
        raise SceneError(f"{where}={value!r}: must be an integer")
    return kind(value)


def _check_keys(where, mapping, allowed, required=()):
    if not isinstance(mapping, dict):
        raise SceneError(f"{where}={mapping!r}: must be a mapping")
    unknown = set(mapping) - set(allowed)
    if unknown:
        raise SceneError(f"{where}: unknown keys {sorted(unknown)} (allowed: {sorted(allowed)})")
    missing = set(required) - set(mapping)
    if missing:
        raise SceneError(f"{where}: missing keys {sorted(missing)}")


def _satellite(i, spec):
    where = f"satellites[{i}]"
    _check_keys(where, spec, _SATELLITE_KEYS, {"height", "shape", "mag", "track"})
    track = spec["track"]
    if isinstance(track, dict) and "vertices" in track:
        track = _polyline_track(f"{where}.track", track)
    _check_keys(f"{where}.track", track, _TRACK_KEYS | {"vertices"}, {"x0", "y0", "angle"})
    length = track.get("length")
    ref_range = _number(f"{where}.ref_range", spec.get("ref_range", 550.0))
    if not ref_range > 0:
        raise SceneError(f"{where}.ref_range={ref_range}: must be > 0 (km)")
    if length is not None and not _number(f"{where}.track.length", length) >= 0:
        raise SceneError(f"{where}.track.length={length}: must be >= 0 (px)")
    try:
        height = _number(f"{where}.height", spec["height"])
        positive("height_km", height)
        return SatelliteSpec(
            height=height,
            shape=shape_from_dict(spec["shape"]),
            mag=_number(f"{where}.mag", spec["mag"]),
            phi=_number(f"{where}.phi", spec.get("phi", 90.0)),
            ref_range=_number(f"{where}.ref_range", spec.get("ref_range", 550.0)),
            track=Track(*(_number(f"{where}.track.{k}", track[k]) for k in ("x0", "y0", "angle")),
                        None if length is None else _number(f"{where}.track.length", length),
                        track.get("vertices")))
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(f"{where}: {err}") from None


def _polyline_track(where, track):
    """Validate a ``{vertices: [...]}`` track; return it with x0, y0, angle of its first piece."""
    _check_keys(where, track, {"vertices"}, {"vertices"})
    vertices = track["vertices"]
    if not isinstance(vertices, list) or len(vertices) < 2:
        raise SceneError(f"{where}.vertices: needs a list of at least two vertices")
    checked = []
    for j, vertex in enumerate(vertices):
        here = f"{where}.vertices[{j}]"
        _check_keys(here, vertex, _VERTEX_KEYS, {"x", "y"})
        values = {k: _number(f"{here}.{k}", v) for k, v in vertex.items()}
        if "height" in values and not values["height"] > 0:
            raise SceneError(f"{here}.height={values['height']}: must be > 0 (km)")
        if "zenith" in values and not 0 <= values["zenith"] < 90:
            raise SceneError(f"{here}.zenith={values['zenith']}: must be >= 0 and < 90")
        checked.append(values)
    first, second = checked[0], checked[1]
    angle = float(np.degrees(np.arctan2(second["y"] - first["y"], second["x"] - first["x"])))
    return {"x0": first["x"], "y0": first["y"], "angle": angle, "vertices": tuple(checked)}


def parse_scene(raw):
    """Validate a scene mapping (defaults filled from :data:`DEFAULT_SCENE`)."""
    _check_keys("scene", raw, _TOP_KEYS)
    merged = {k: v for k, v in DEFAULT_SCENE.items() if k != "satellites"} | raw
    try:
        band(merged["band"])
        detector = detector_from_spec(merged["detector"])
    except InjectError as err:
        raise SceneError(str(err)) from None
    for flag in ("noise",):
        if not isinstance(merged[flag], bool):
            raise SceneError(f"{flag}={merged[flag]!r}: must be true or false")
    for flag in ("sky", "stars"):
        if not isinstance(merged[flag], (bool, dict)):
            raise SceneError(f"{flag}={merged[flag]!r}: must be true, false or a mapping")
    pointing = merged.get("pointing")
    if pointing is not None:  # ranges are checked where the WCS is made (inject.wcs)
        _check_keys("pointing", pointing, {"ra", "dec", "rotation"}, {"ra", "dec"})
        pointing = {k: _number(f"pointing.{k}", v) for k, v in pointing.items()}
    satellites = merged.get("satellites", [])
    if not isinstance(satellites, list):
        raise SceneError(f"satellites={satellites!r}: must be a list")
    seed = _number("seed", merged["seed"], int)
    if seed < 1:
        raise SceneError(f"seed={seed}: must be >= 1 (0 means 'random' to GalSim)")
    exptime = _number("exptime", merged["exptime"])
    seeing = _number("seeing", merged["seeing"])
    zenith = _number("zenith", merged["zenith"])
    if not exptime > 0:
        raise SceneError(f"exptime={exptime}: must be > 0")
    if not 0 <= seeing < 30:
        raise SceneError(f"seeing={seeing}: must be >= 0 arcsec and < 30")
    if not 0 <= zenith < 90:
        raise SceneError(f"zenith={zenith}: must be >= 0 and < 90")
    rates = {}
    for key in ("dark_current", "cosmic_rays"):
        rates[key] = _number(key, merged.get(key, 0.0))
        if rates[key] < 0:
            raise SceneError(f"{key}={rates[key]}: must be >= 0 (per second)")
    units = merged.get("units", "electron")
    if units not in ("electron", "adu"):
        raise SceneError(f"units={units!r}: choose electron or adu")
    return Scene(seed=seed, band=merged["band"], exptime=exptime, seeing=seeing, zenith=zenith,
                 detector=detector, sky=merged["sky"], stars=merged["stars"],
                 noise=merged["noise"],
                 satellites=tuple(_satellite(i, s) for i, s in enumerate(satellites)),
                 pointing=pointing, units=units, raw=raw, **rates)
