"""Scene files: YAML parsed safely, dotted overrides, validation into a :class:`Scene`.

Every problem is reported as a :class:`~inject.errors.SceneError` naming the key path
(``satellites[0].height``) and the bad value.
"""
from dataclasses import dataclass, field

import numbers
import re

import numpy as np
import yaml

from inject.camera.detector import Detector, detector_from_spec
from inject.errors import InjectError, InputError, SceneError
from inject.photometry import band
from inject.satellite import Shape, shape_from_dict
from inject.validate import RANGES, check_memory, check_pointing, positive

#: The embedded default scene: the paper's 550 km satellite on one full ITL CCD.
DEFAULT_SCENE = {
    "seed": 1, "band": "g", "exptime": 30.0, "seeing": 0.67, "zenith": 70.0,
    "detector": {"type": "itl"}, "sky": True, "stars": True, "noise": True,
    "satellites": [{
        "height": 550.0, "phi": 90.0, "shape": {"type": "box", "length": 7.25, "width": 2.65},
        "mag": 5.0, "ref_range": 550.0, "track": {"x0": 300.0, "y0": 200.0, "angle": 33.0}}],
}

#: Peak bytes per pixel of ``inject simulate`` (all its outputs written), for the memory check:
#: 44-46 B/px measured (growth of the peak RSS from 64^2 to 1536^2-4000^2 px, stars, noise,
#: FITS + EXR + PNG), with a margin for the raw layout and ADU conversion.
SIMULATE_BYTES_PER_PIXEL = 64

_TOP_KEYS = {"seed", "band", "exptime", "seeing", "zenith", "detector", "sky", "stars", "noise",
             "satellites", "pointing", "dark_current", "cosmic_rays", "units", "time", "site"}
_SATELLITE_KEYS = {"height", "phi", "shape", "mag", "ref_range", "track"}
_TRACK_KEYS = {"x0", "y0", "angle", "length"}
_VERTEX_KEYS = {"x", "y", "height", "zenith", "phi", "mag", "range", "angular_speed"}


@dataclass(frozen=True)
class Track:
    """Where a streak goes on the pixel grid; ``length=None`` crosses the whole image.

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
    #: Exposure start, UTC (ISO 8601), when the scene gives ``time:``.
    time: str | None = None


class _SceneLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` reading floats as YAML 1.2 does: ``1e3`` and ``5e-1`` are numbers
    (YAML 1.1, PyYAML's default, needs a dot and an exponent sign), and refusing a key given
    twice in one mapping (YAML 1.2 forbids it; PyYAML keeps the last silently)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:  # the mapping's own keys: a merge (<<) may override
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # an unhashable key: the base class says so
                    continue
                if first is not key_node.start_mark:
                    raise _DuplicateKey(key, key_node.start_mark.line + 1, first.line + 1)
        return super().construct_mapping(node, deep)


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key, line, first):
        super().__init__(f"line {line}: key {key!r} given twice (first at line {first}); "
                         "keys must be unique")


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
    except _DuplicateKey as err:
        raise SceneError(f"{path}: {err}") from None
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


def _ranged(quantity, where, value, kind=float):
    """``value`` as a number inside :data:`inject.validate.RANGES` ``[quantity]``."""
    value = _number(where, value, kind)
    try:
        return RANGES[quantity].check(value, where)
    except InputError as err:
        raise SceneError(str(err)) from None


def _check_detector(spec):
    """Range checks of a detector mapping's numbers (its keys and types are checked by
    :func:`inject.camera.detector.detector_from_spec`)."""
    if not isinstance(spec, dict):
        return
    from inject.camera.detector import DETECTORS

    sensor = DETECTORS.get(spec.get("type", "itl"))
    for key, size in (("nx", sensor and sensor.nx), ("ny", sensor and sensor.ny)):
        if key in spec:
            n = _ranged(f"detector.{key}", f"detector.{key}", spec[key], int)
            if sensor is not None and n > size:
                raise SceneError(f"detector.{key}={n}: must be <= {size} px (the {sensor.kind} "
                                 f"sensor's size; a scene is one CCD or a cut-out of it)")
    for key in ("gains", "read_noise"):
        values = spec.get(key)
        if isinstance(values, list):
            for j, v in enumerate(values):
                _ranged(f"detector.{key}", f"detector.{key}[{j}]", v)
        elif values is not None:
            _ranged(f"detector.{key}", f"detector.{key}", values)
    for key in ("full_well", "bias"):
        if key in spec:
            _ranged(f"detector.{key}", f"detector.{key}", spec[key])


def _check_sky_and_stars(sky, stars):
    if isinstance(sky, dict):
        for key in ("level", "mag"):
            if key in sky:
                _ranged(f"sky.{key}", f"sky.{key}", sky[key])
    if isinstance(stars, dict):
        for key in ("galactic_l", "galactic_b", "mag_limit", "mag_bright", "density_per_deg2"):
            if key in stars:
                _ranged(f"stars.{key}", f"stars.{key}", stars[key])


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
        shape = shape_from_dict(spec["shape"])
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(f"{where}: {err}") from None
    _ranged("size", f"{where}.shape size", round(shape.size_m, 3))
    _check_parts(f"{where}.shape", spec["shape"])
    return SatelliteSpec(
        height=_ranged("height", f"{where}.height", height),
        shape=shape,
        mag=_ranged("mag", f"{where}.mag", spec["mag"]),
        phi=_ranged("phi", f"{where}.phi", spec.get("phi", 90.0)),
        ref_range=_ranged("ref_range", f"{where}.ref_range", ref_range),
        track=Track(*(_ranged(f"track.{k}", f"{where}.track.{k}", track[k])
                      for k in ("x0", "y0", "angle")),
                    None if length is None else _ranged("track.length", f"{where}.track.length",
                                                        length),
                    track.get("vertices")))


def _check_parts(where, shape):
    """Range checks of a composite shape's parts (their reflectances), at any depth."""
    for j, part in enumerate(shape.get("parts", ()) if isinstance(shape, dict) else ()):
        if isinstance(part, dict):
            if "reflectance" in part:
                _ranged("reflectance", f"{where}.parts[{j}].reflectance", part["reflectance"])
            _check_parts(f"{where}.parts[{j}]", part)


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
        quantity = {"x": "track.x0", "y": "track.y0"}
        values = {k: _ranged(quantity.get(k, k), f"{here}.{k}", v) for k, v in values.items()}
        checked.append(values)
    first, second = checked[0], checked[1]
    angle = float(np.degrees(np.arctan2(second["y"] - first["y"], second["x"] - first["x"])))
    return {"x0": first["x"], "y0": first["y"], "angle": angle, "vertices": tuple(checked)}


def parse_scene(raw, charge_check=True):
    """Validate a scene mapping (defaults filled from :data:`DEFAULT_SCENE`).

    ``charge_check=False`` leaves out :func:`check_charge` (a focal-plane scene checks its
    tracks' own vertex values once they are known, not its placeholder satellites')."""
    _check_keys("scene", raw, _TOP_KEYS)
    merged = {k: v for k, v in DEFAULT_SCENE.items() if k != "satellites"} | raw
    _check_detector(merged["detector"])
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
    if pointing is not None:  # validate.check_pointing: the one check of a pointing
        _check_keys("pointing", pointing, {"ra", "dec", "rotation"}, {"ra", "dec"})
        try:
            pointing = dict(zip(("ra", "dec", "rotation"), check_pointing(pointing)))
        except InjectError as err:
            raise SceneError(str(err)) from None
    satellites = merged.get("satellites", [])
    if not isinstance(satellites, list):
        raise SceneError(f"satellites={satellites!r}: must be a list")
    if any(isinstance(sat, dict) and "orbit" in sat for sat in satellites):
        from inject.exposure.scene import ccd_orbit_satellites# orbit: -> a polyline in this CCD's pixels

        satellites = ccd_orbit_satellites(merged, satellites, detector.shape, pointing)
    _check_sky_and_stars(merged["sky"], merged["stars"])
    seed = _ranged("seed", "seed", merged["seed"], int)
    exptime, seeing, zenith = (_ranged(k, k, merged[k]) for k in ("exptime", "seeing", "zenith"))
    rates = {key: _ranged(key, key, merged.get(key, 0.0))
             for key in ("dark_current", "cosmic_rays")}
    units = merged.get("units", "electron")
    if units not in ("electron", "adu"):
        raise SceneError(f"units={units!r}: choose electron or adu")
    start = None if merged.get("time") is None else exposure_start(merged["time"])
    scene = Scene(seed=seed, band=merged["band"], exptime=exptime, seeing=seeing, zenith=zenith,
                  detector=detector, sky=merged["sky"], stars=merged["stars"],
                  noise=merged["noise"],
                  satellites=tuple(_satellite(i, s) for i, s in enumerate(satellites)),
                  pointing=pointing, units=units, raw=raw, time=start, **rates)
    if charge_check:
        check_charge(scene)
    ny, nx = detector.shape
    check_memory(nx * ny * SIMULATE_BYTES_PER_PIXEL, f"detector {nx} x {ny}")
    return scene


def exposure_start(value):
    """A scene's ``time:`` (a YAML timestamp or an ISO 8601 string, UTC) as ISO 8601 UTC."""
    from inject.orbits.passes import parse_time

    try:
        return parse_time(value, "time").utc.isot
    except InjectError as err:
        raise SceneError(str(err)) from None


def time_cards(scene):
    """FITS cards of the exposure's time, when the scene has one (``{}`` otherwise).

    As LSSTCam's headers and afw's VisitInfo have them: ``TIMESYS = 'TAI'`` and the dates in
    TAI (the FITS standard reads DATE-* and MJD-* in TIMESYS's scale; TAI - UTC is 37 s in
    2026): ``DATE-OBS``/``MJD-OBS`` the exposure start (the UTC start in the comment),
    ``DATE-AVG``/``MJD-AVG`` its middle (what afw takes as the VisitInfo date), ``DATE-END``
    /``MJD-END`` its end.
    """
    if scene.time is None:
        return {}
    from astropy.time import Time, TimeDelta

    start = Time(scene.time, scale="utc")
    cards = {"TIMESYS": ("TAI", "time scale of DATE-* and MJD-*")}
    for key, t, what in (("OBS", start, "exposure start"),
                         ("AVG", start + TimeDelta(scene.exptime / 2, format="sec"),
                          "middle of the exposure"),
                         ("END", start + TimeDelta(scene.exptime, format="sec"),
                          "exposure end")):
        tai = t.tai
        cards[f"DATE-{key}"] = (tai.isot, f"{what} (TAI)")
        cards[f"MJD-{key}"] = (float(tai.mjd), f"[d] {what}, MJD (TAI)")
    return cards


def check_charge(scene):
    """Refuse a scene whose brightest pixel would hold more charge than can be drawn.

    An upper bound, from numbers alone (no profile is built): the sky, the dark current, the
    brightest random star's whole flux and each satellite's charge per pixel of track (no
    pixel of a streak gets more than that) at each of its vertices.
    """
    from inject.photometry import electron_rate
    from inject.scene import sky_level
    from inject.streak import StreakModel

    base = sky_level(scene) + scene.dark_current * scene.exptime
    if isinstance(scene.stars, dict) or scene.stars is True:
        bright = (scene.stars if isinstance(scene.stars, dict) else {}).get("mag_bright", 12.0)
        if not (isinstance(scene.stars, dict) and "catalog" in scene.stars):
            base += float(electron_rate(bright, scene.band)) * scene.exptime
    worst, where = base, "the sky, dark current and stars"
    for i, sat in enumerate(scene.satellites):
        for vertex in sat.track.vertices or ({},):
            model = StreakModel(vertex.get("height", sat.height), vertex.get("zenith", scene.zenith),
                                vertex.get("phi", sat.phi), sat.shape, vertex.get("mag", sat.mag),
                                scene.band, ref_range_km=sat.ref_range,
                                range_km=vertex.get("range"),
                                angular_speed_rad_s=vertex.get("angular_speed"))
            if base + model.flux_per_px > worst:
                worst, where = base + model.flux_per_px, f"satellites[{i}]"
    try:
        RANGES["charge_per_px"].check(float(f"{worst:.3g}"),
                                      f"expected charge per pixel from {where}")
    except InputError as err:
        raise SceneError(str(err)) from None
