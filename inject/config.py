"""Scene files: a scene mapping validated into a :class:`Scene`.

A CCD scene (:func:`parse_scene`) and a focal-plane scene (:func:`parse_focal_parts`, which
:func:`inject.exposure.parse_focal_scene` completes) share :func:`parse_common` (seed, band,
exposure, seeing, sky, stars, noise, pointing, time, site) and :func:`parse_satellite` (a
satellite's shape and brightness); each has its own tracks: in a CCD's pixels or in
focal-plane mm. Every problem is reported as a :class:`~inject.errors.SceneError` naming the
key path (``satellites[0].height``) and the bad value.
"""
from dataclasses import dataclass, field, replace

import numpy as np

from inject.camera import layout as fp
from inject.camera.detector import DETECTORS, Detector, detector_from_spec
from inject.camera.wcs import Pointing
from inject.errors import InjectError, InputError, SceneError
from inject.instrument import LSST
from inject.optics import (
    FIELD_MAX_DEG,
    SUN_TEMPERATURE_K,
    check_focus_offset,
    check_sed_temperature,
    colour_temperature,
)
from inject.photometry import band, electron_rate, sky_per_pixel
from inject.satellite import Shape, shape_from_dict
from inject.schema import check_keys, number, ranged
from inject.stars import StarFieldSpec, star_field_spec
from inject.streak import PUPILS, StreakModel
from inject.trajectory import FocalTrack, Track
from inject.validate import RANGES, check_memory, check_pointing, parse_time, positive

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

#: Keys every scene shares (a CCD scene adds ``detector``, a focal-plane scene ``detectors``
#: and ``cutout``).
COMMON_KEYS = frozenset({"seed", "band", "exptime", "seeing", "zenith", "sky", "stars", "noise",
                         "satellites", "pointing", "dark_current", "cosmic_rays", "units", "time",
                         "site", "shadow_atmosphere_km", "pupil", "focus_offset_um",
                         "rotator_deg"})
SCENE_KEYS = COMMON_KEYS | {"detector", "field"}
#: Keys of a focal-plane scene.
FOCAL_KEYS = COMMON_KEYS | {"detectors", "cutout"}
#: A satellite's model keys, whatever its track is given as.
SATELLITE_MODEL_KEYS = frozenset({"height", "phi", "shape", "mag", "ref_range", "sed"})
#: Keys of a straight pixel track.
TRACK_KEYS = frozenset({"x0", "y0", "angle", "length"})
#: Keys of a polyline vertex that vary the streak model along it.
VERTEX_MODEL_KEYS = ("height", "zenith", "phi", "mag")
#: Vertex keys of an orbit's track only: the pass's exact range (km) and angular speed across
#: the star field (rad/s), in place of the spherical-Earth ones of (height, zenith, phi).
PASS_KEYS = ("range", "angular_speed")
#: Keys of a straight track in focal-plane mm.
TRACK_KEYS_MM = frozenset({"x0_mm", "y0_mm", "angle", "length_mm"})
#: ``sky:`` mapping keys.
SKY_KEYS = ("level", "mag", "airmass_scaling")


#: Keys of a satellite given by its orbit (its height and phi come from the pass).
ORBIT_SATELLITE_KEYS = (SATELLITE_MODEL_KEYS - {"height", "phi"}) | {"orbit", "lumos"}


@dataclass(frozen=True)
class SatelliteSpec:
    """One satellite of a scene: its model and, in a CCD scene, its track in pixels.

    ``height`` is None for a satellite whose height comes from its orbit, vertex by vertex;
    ``track`` is None in a focal-plane scene, which keeps its tracks in focal-plane mm.
    """

    height: float | None
    shape: Shape
    mag: float
    track: Track | None = None
    phi: float = 90.0
    ref_range: float = 550.0
    #: The spectrum the traced pupil's kernel is taken over, as a blackbody temperature, K
    #: (``sed:``; default: the Sun's).
    sed_temperature_k: float = SUN_TEMPERATURE_K


@dataclass(frozen=True)
class SkySpec:
    """The sky background: ``level`` (e-/px) or the band's dark sky at zenith, optionally
    ``mag`` (mag/arcsec^2) instead, brighter by the airmass with ``airmass_scaling``."""

    level: float | None = None
    mag: float | None = None
    airmass_scaling: bool = False


@dataclass(frozen=True)
class Scene:
    """A validated scene.

    ``sky`` and ``stars`` are None when the scene turns them off. In a CCD scene ``detector``
    is the sensor (or its cut-out) and each satellite has its pixel track; the common part of
    a focal-plane scene (:class:`inject.exposure.scene.FocalScene`) has no detector, and its
    satellites no track.
    """

    seed: int
    band: str
    exptime: float
    seeing: float
    zenith: float
    detector: Detector | None
    sky: SkySpec | None
    stars: StarFieldSpec | None
    noise: bool
    satellites: tuple = field(default_factory=tuple)
    pointing: Pointing | None = None
    dark_current: float = 0.0
    cosmic_rays: float = 0.0
    units: str = "electron"
    raw: dict = field(default_factory=dict, compare=False, repr=False)
    #: Exposure start, UTC (ISO 8601), when the scene gives ``time:``.
    time: str | None = None
    #: The observatory, as the scene's ``site:`` gives it (None: Rubin); read by the orbits.
    site: object = None
    #: Height (km) of the atmosphere that grazing sunlight must clear (None: the orbits'
    #: default).
    shadow_atmosphere_km: float | None = None
    #: The defocus kernel, ``annulus`` or ``rubin`` (:data:`inject.streak.PUPILS`).
    pupil: str = "annulus"
    #: A CCD scene's ``field:``, ``(angle, position_angle)`` in deg: where the CCD sits in
    #: the field for ``pupil: rubin`` (None: on the optical axis); the position angle is the
    #: outward field radius's direction on the image, from the pixel rows' +x.
    field: tuple | None = None
    #: ``focus_offset_um``: the detector's shift from the design's focus along
    #: the optical axis for ``pupil: rubin``, micron (0: focused at infinity; negative: towards
    #: the camera's last lens, where a star is defocused as a point at finite range is).
    focus_offset_um: float = 0.0
    #: ``rotator_deg``: the camera rotator's angle (opsim's rotTelPos), deg, which turns the
    #: focal plane against the spider vanes for ``pupil: rubin``; None: not given (the field
    #: radius is taken 22.5 deg from a vane, :data:`inject.optics.VANE_OFFSET_DEG`).
    rotator_deg: float | None = None


def _check_detector(spec):
    """Range checks of a detector mapping's numbers (its keys and types are checked by
    :func:`inject.camera.detector.detector_from_spec`)."""
    if not isinstance(spec, dict):
        return
    sensor = DETECTORS.get(spec.get("type", "itl"))
    for key, size in (("nx", sensor and sensor.nx), ("ny", sensor and sensor.ny)):
        if key in spec:
            n = ranged(f"detector.{key}", f"detector.{key}", spec[key], int)
            if sensor is not None and n > size:
                raise SceneError(f"detector.{key}={n}: must be <= {size} px (the {sensor.kind} "
                                 f"sensor's size; a scene is one CCD or a cut-out of it)")
    for key in ("gains", "read_noise"):
        values = spec.get(key)
        if isinstance(values, list):
            for j, v in enumerate(values):
                ranged(f"detector.{key}", f"detector.{key}[{j}]", v)
        elif values is not None:
            ranged(f"detector.{key}", f"detector.{key}", values)
    for key in ("full_well", "bias"):
        if key in spec:
            ranged(f"detector.{key}", f"detector.{key}", spec[key])


def parse_sky(value):
    """The :class:`SkySpec` of a scene's ``sky:`` (``true``, ``false`` or a mapping); None
    when off."""
    if value is False:
        return None
    if value is True:
        return SkySpec()
    if not isinstance(value, dict):
        raise SceneError(f"sky={value!r}: must be true, false or a mapping")
    unknown = set(value) - set(SKY_KEYS)
    if unknown:
        raise SceneError(f"sky: unknown keys {sorted(unknown)} (allowed: level, mag, "
                         f"airmass_scaling)")
    level = value.get("level")
    if level is not None:
        level = ranged("sky.level", "sky.level", level)
        if not level >= 0:
            raise SceneError(f"sky.level={level!r}: must be a number >= 0 (e-/px)")
    mag = value.get("mag")
    if mag is not None:
        mag = ranged("sky.mag", "sky.mag", mag)
    scaling = value.get("airmass_scaling", False)
    if not isinstance(scaling, bool):  # "no" or "maybe" would count as true
        raise SceneError(f"sky.airmass_scaling={scaling!r}: must be true or false")
    return SkySpec(level=level, mag=mag, airmass_scaling=scaling)


def parse_stars(value, pointing=None):
    """The :class:`~inject.stars.StarFieldSpec` of a scene's ``stars:`` (``true``, ``false`` or
    a mapping); None when off. Galactic coordinates not given come from the pointing."""
    if value is False:
        return None
    if not isinstance(value, (bool, dict)):
        raise SceneError(f"stars={value!r}: must be true, false or a mapping")
    if isinstance(value, dict):
        for key in ("galactic_l", "galactic_b", "mag_limit", "mag_bright", "density_per_deg2"):
            if key in value:
                ranged(f"stars.{key}", f"stars.{key}", value[key])
    radec = None if pointing is None else (pointing.ra_deg, pointing.dec_deg)
    try:
        return star_field_spec({} if value is True else value, radec)
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(f"stars: {err}") from None


def parse_pointing(value):
    """A scene's ``pointing: {ra, dec, rotation}`` as a :class:`~inject.camera.wcs.Pointing`
    (None when absent)."""
    if value is None:
        return None
    check_keys("pointing", value, {"ra", "dec", "rotation"}, {"ra", "dec"})
    try:
        return Pointing(*check_pointing(value))
    except InjectError as err:
        raise SceneError(str(err)) from None


def parse_common(raw):
    """The keys every scene shares, checked: a mapping of :class:`Scene`'s fields but
    ``detector``, ``satellites`` and ``field`` (defaults from :data:`DEFAULT_SCENE`)."""
    merged = {k: v for k, v in DEFAULT_SCENE.items() if k not in ("satellites", "detector")} | raw
    try:
        band(merged["band"])
    except InjectError as err:
        raise SceneError(str(err)) from None
    if not isinstance(merged["noise"], bool):
        raise SceneError(f"noise={merged['noise']!r}: must be true or false")
    if not isinstance(merged["sky"], (bool, dict)):
        raise SceneError(f"sky={merged['sky']!r}: must be true, false or a mapping")
    pointing = parse_pointing(merged.get("pointing"))
    sky = parse_sky(merged["sky"])
    stars = parse_stars(merged["stars"], pointing)
    atmosphere = merged.get("shadow_atmosphere_km")
    if atmosphere is not None:
        atmosphere = ranged("shadow_atmosphere_km", "shadow_atmosphere_km", atmosphere)
    units = merged.get("units", "electron")
    if units not in ("electron", "adu"):
        raise SceneError(f"units={units!r}: choose electron or adu")
    pupil = merged.get("pupil", "annulus")
    if not isinstance(pupil, str) or pupil not in PUPILS:
        raise SceneError(f"pupil={pupil!r}: choose " + " or ".join(PUPILS))
    return dict(
        seed=ranged("seed", "seed", merged["seed"], int), band=merged["band"],
        **{k: ranged(k, k, merged[k]) for k in ("exptime", "seeing", "zenith")},
        sky=sky, stars=stars, noise=merged["noise"], pointing=pointing, units=units,
        **{k: ranged(k, k, merged.get(k, 0.0)) for k in ("dark_current", "cosmic_rays")},
        time=None if merged.get("time") is None else exposure_start(merged["time"]),
        site=merged.get("site"), shadow_atmosphere_km=atmosphere, pupil=pupil,
        focus_offset_um=parse_focus_offset(merged.get("focus_offset_um"), pupil),
        rotator_deg=parse_rotator(merged.get("rotator_deg"), pupil), raw=raw)


def parse_rotator(value, pupil="rubin"):
    """A scene's ``rotator_deg``: the camera rotator's angle rotTelPos, deg (None when absent).

    Raises
    ------
    SceneError
        Not a number, or given with a ``pupil`` other than ``rubin`` (the annulus has no
        spider vanes).
    """
    if value is None:
        return None
    rotator = number("rotator_deg", value)
    if pupil != "rubin":
        raise SceneError(f"rotator_deg={rotator}: only with pupil: rubin (pupil: {pupil} has no "
                         "spider vanes)")
    return rotator


def parse_field(value, pupil="rubin"):
    """A CCD scene's ``field: {angle, position_angle}`` as ``(angle, position_angle)`` deg.

    ``angle`` is the CCD's (the streak's) angle from the optical axis, 0 to 2.05 deg;
    ``position_angle`` the direction of the outward field radius on the image, deg
    counter-clockwise from the pixel rows' +x (default 0), whatever the tracks' directions.
    (TRUTH's ``field_position_angle_deg`` is that radius measured from each streak's direction
    of motion instead.) None when absent.

    Raises
    ------
    SceneError
        A key or value is wrong, or ``field:`` is given with a ``pupil`` other than ``rubin``
        (the annulus is the same everywhere in the field).
    """
    if value is None:
        return None
    check_keys("field", value, {"angle", "position_angle"}, {"angle"})
    angle = number("field.angle", value["angle"])
    if not 0 <= angle <= FIELD_MAX_DEG:
        raise SceneError(f"field.angle={angle}: must be within [0, {FIELD_MAX_DEG}] deg "
                         "(LSSTCam's CCDs reach 2.048)")
    if pupil != "rubin":
        raise SceneError(f"field.angle={angle}: only with pupil: rubin (pupil: {pupil} is the "
                         "same everywhere in the field)")
    return (angle, number("field.position_angle", value.get("position_angle", 0.0)))


def parse_focus_offset(value, pupil="rubin"):
    """A scene's (or a constellation's) ``focus_offset_um``, micron (0 when not given).

    Raises
    ------
    SceneError
        Not a number, beyond :data:`inject.optics.FOCUS_MAX_UM` micron, or not 0 with a ``pupil``
        other than ``rubin`` (the annulus is the design's focus).
    """
    if value is None:
        return 0.0
    focus = number("focus_offset_um", value)
    try:
        check_focus_offset(focus)
    except InjectError as err:
        raise SceneError(str(err)) from None
    if focus and pupil != "rubin":
        raise SceneError(f"focus_offset_um={focus}: only with pupil: rubin (pupil: {pupil} is "
                         "the design's focus)")
    return focus


def satellite_list(raw):
    """A scene's ``satellites:`` list (empty when absent)."""
    satellites = raw.get("satellites", [])
    if not isinstance(satellites, list):
        raise SceneError(f"satellites={satellites!r}: must be a list")
    return satellites


def parse_satellite(where, spec, track=None, height_from_orbit=False):
    """A satellite's model (shape, brightness, height, phi, reference range) and ``track``.

    With ``height_from_orbit`` the satellite has no ``height`` or ``phi`` of its own (its
    orbit gives them, vertex by vertex)."""
    try:
        shape = shape_from_dict(spec["shape"])
        height = None
        if not height_from_orbit:
            height = number(f"{where}.height", spec["height"])
            positive("height_km", height)
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(f"{where}: {err}") from None
    ref_range = number(f"{where}.ref_range", spec.get("ref_range", 550.0))
    if not ref_range > 0:
        raise SceneError(f"{where}.ref_range={ref_range}: must be > 0 (km)")
    ranged("size", f"{where}.shape size", round(shape.size_m, 3))
    _check_parts(f"{where}.shape", spec["shape"])
    return SatelliteSpec(
        height=None if height is None else ranged("height", f"{where}.height", height),
        shape=shape, mag=ranged("mag", f"{where}.mag", spec["mag"]),
        phi=ranged("phi", f"{where}.phi", spec.get("phi", 90.0)),
        ref_range=ranged("ref_range", f"{where}.ref_range", ref_range), track=track,
        sed_temperature_k=parse_sed(f"{where}.sed", spec.get("sed", "sun")))


def parse_sed(where, value):
    """A satellite's ``sed:``, as the blackbody temperature (K) the traced pupil's kernel is
    taken over.

    ``sun`` (the default: sunlight reflected without colour, the Sun as a blackbody of
    :data:`inject.optics.SUN_TEMPERATURE_K`), ``{blackbody_k: T}``, or one AB colour through
    LSST's bands, ``{g-r: 0.6}`` (any two bands, the bluer first: the blackbody of that
    colour, :func:`inject.optics.colour_temperature`).
    """
    if value == "sun":
        return SUN_TEMPERATURE_K
    if not isinstance(value, dict) or len(value) != 1:
        raise SceneError(f"{where}={value!r}: give sun, {{blackbody_k: 5000}} or one colour "
                         "such as {g-r: 0.6}")
    [(key, number_)] = value.items()
    try:
        if key == "blackbody_k":
            return check_sed_temperature(number(f"{where}.blackbody_k", number_))
        blue, dash, red = str(key).partition("-")
        if not dash:
            raise SceneError(f"{where}.{key}: not blackbody_k or a colour such as g-r")
        return colour_temperature(blue, red, number(f"{where}.{key}", number_))
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(f"{where}: {err}") from None


def check_sed_pupil(satellites, pupil, names=None):
    """Refuse a satellite's ``sed:`` without the traced pupil (the annulus is achromatic);
    ``names``: where each satellite is (default ``satellites[i]``)."""
    for i, sat in enumerate(satellites):
        if pupil != "rubin" and sat.sed_temperature_k != SUN_TEMPERATURE_K:
            where = f"satellites[{i}]" if names is None else names[i]
            raise SceneError(f"{where}.sed: only with pupil: rubin (pupil: {pupil} is the "
                             "same at every wavelength)")


def _check_parts(where, shape):
    """Range checks of a composite shape's parts (their reflectances), at any depth."""
    for j, part in enumerate(shape.get("parts", ()) if isinstance(shape, dict) else ()):
        if isinstance(part, dict):
            if "reflectance" in part:
                ranged("reflectance", f"{where}.parts[{j}].reflectance", part["reflectance"])
            _check_parts(f"{where}.parts[{j}]", part)


def parse_vertices(where, vertices, position=("x", "y"), extra=PASS_KEYS):
    """Check a polyline's ``vertices``: each a mapping with the ``position`` keys and optional
    :data:`VERTEX_MODEL_KEYS` (and ``extra``) overriding the satellite's values there.

    Returns
    -------
    tuple of dict
        The vertices with their numbers checked (the position keys as ``track.x0``/``y0``).
    """
    if not isinstance(vertices, list) or len(vertices) < 2:
        raise SceneError(f"{where}.vertices: needs a list of at least two vertices")
    quantity = dict(zip(position, ("track.x0", "track.y0")))
    checked = []
    for j, vertex in enumerate(vertices):
        here = f"{where}.vertices[{j}]"
        check_keys(here, vertex, {*position, *VERTEX_MODEL_KEYS, *extra}, set(position))
        values = {k: number(f"{here}.{k}", v) for k, v in vertex.items()}
        if "height" in values and not values["height"] > 0:
            raise SceneError(f"{here}.height={values['height']}: must be > 0 (km)")
        if "zenith" in values and not 0 <= values["zenith"] < 90:
            raise SceneError(f"{here}.zenith={values['zenith']}: must be >= 0 and < 90")
        checked.append({k: ranged(quantity.get(k, k), f"{here}.{k}", v)
                        for k, v in values.items()})
    return tuple(checked)


def parse_track(where, track):
    """A pixel track: ``{x0, y0, angle[, length]}`` or ``{vertices: [{x, y, ...}, ...]}``."""
    if isinstance(track, dict) and "vertices" in track:
        check_keys(where, track, {"vertices"}, {"vertices"})
        vertices = parse_vertices(where, track["vertices"])
        first, second = vertices[0], vertices[1]
        angle = float(np.degrees(np.arctan2(second["y"] - first["y"], second["x"] - first["x"])))
        return Track(first["x"], first["y"], angle, None, vertices)
    check_keys(where, track, TRACK_KEYS, {"x0", "y0", "angle"})
    length = track.get("length")
    if length is not None:
        if not number(f"{where}.length", length) >= 0:
            raise SceneError(f"{where}.length={length}: must be >= 0 (px)")
        length = ranged("track.length", f"{where}.length", length)
    return Track(*(ranged(f"track.{k}", f"{where}.{k}", track[k]) for k in ("x0", "y0", "angle")),
                 length)


def parse_scene(raw, charge_check=True):
    """Validate a CCD scene mapping (defaults filled from :data:`DEFAULT_SCENE`).

    A satellite given by an ``orbit:`` is turned into a pixel track by
    :func:`inject.orbits.tracks.resolve_ccd_orbits` first (``inject simulate`` does so).
    ``charge_check=False`` leaves out :func:`check_charge`.
    """
    check_keys("scene", raw, SCENE_KEYS)
    detector_spec = raw.get("detector", DEFAULT_SCENE["detector"])
    _check_detector(detector_spec)
    try:
        detector = detector_from_spec(detector_spec)
    except InjectError as err:
        raise SceneError(str(err)) from None
    satellites = satellite_list(raw)
    common = parse_common(raw)
    parsed = []
    for i, spec in enumerate(satellites):
        where = f"satellites[{i}]"
        if isinstance(spec, dict) and "orbit" in spec:
            raise SceneError(f"{where}.orbit: resolve orbits into tracks first "
                             "(inject.orbits.tracks.resolve_ccd_orbits; inject simulate does)")
        check_keys(where, spec, SATELLITE_MODEL_KEYS | {"track"},
                   {"height", "shape", "mag", "track"})
        track = parse_track(f"{where}.track", spec["track"])
        parsed.append(parse_satellite(where, spec, track))
    check_sed_pupil(parsed, common["pupil"])
    scene = Scene(detector=detector, satellites=tuple(parsed),
                  field=parse_field(raw.get("field"), common["pupil"]), **common)
    if charge_check:
        check_charge(scene)
    ny, nx = detector.shape
    check_memory(nx * ny * SIMULATE_BYTES_PER_PIXEL, f"detector {nx} x {ny}")
    return scene


def exposure_start(value):
    """A scene's ``time:`` (a YAML timestamp or an ISO 8601 string, UTC) as ISO 8601 UTC."""
    try:
        return parse_time(value, "time").utc.isot
    except InjectError as err:
        raise SceneError(str(err)) from None


def sky_level(scene):
    """Sky background in e-/px for the scene (0 when ``sky`` is off).

    ``sky: true`` is the band's dark sky at zenith (SMTN-002); a mapping may give ``level``
    (e-/px), ``mag`` (mag/arcsec^2) and ``airmass_scaling: true`` (brighter by the
    plane-parallel airmass ``sec z``, as the sky glow comes from a longer path).
    """
    sky = scene.sky
    if sky is None:
        return 0.0
    if sky.level is not None:
        return float(sky.level)
    level = sky_per_pixel(scene.band, scene.exptime, LSST.pixel_scale_arcsec, sky.mag)
    if sky.airmass_scaling:
        level /= np.cos(np.radians(scene.zenith))
    return float(level)


def check_charge(scene, vertex_values=None):
    """Refuse a scene whose brightest pixel would hold more charge than can be drawn.

    An upper bound, from numbers alone (no profile is built): the sky, the dark current, the
    brightest random star's whole flux and each satellite's charge per pixel of track (no
    pixel of a streak gets more than that) at each of its vertices.

    Parameters
    ----------
    scene : Scene
    vertex_values : sequence of sequence of mapping, optional
        Per satellite, the values along its track that override its own (a focal-plane
        scene's tracks, an orbit's pass); default: each CCD track's vertices.
    """
    base = sky_level(scene) + scene.dark_current * scene.exptime
    if scene.stars is not None and scene.stars.catalog is None:
        base += float(electron_rate(scene.stars.mag_bright, scene.band)) * scene.exptime
    worst, where = base, "the sky, dark current and stars"
    if vertex_values is None:
        vertex_values = [sat.track.vertices or ({},) for sat in scene.satellites]
    for i, (sat, values) in enumerate(zip(scene.satellites, vertex_values)):
        for vertex in values:
            model = StreakModel(vertex.get("height", sat.height),
                                vertex.get("zenith", scene.zenith),
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


def with_detector(scene, detector, satellites=()):
    """A CCD scene from a scene's common part: its sensor and satellites with pixel tracks."""
    return replace(scene, detector=detector, satellites=tuple(satellites))


def parse_focal_parts(raw, orbit_track):
    """Validate a focal-plane scene mapping in one pass.

    Parameters
    ----------
    raw : dict
        The scene mapping.
    orbit_track : callable
        ``orbit_track(where, orbit, satellite, scene, lumos)`` -> FocalTrack: a satellite's
        pass as a track (the orbits wing's, handed in so that this module imports no wing).

    Returns
    -------
    scene : Scene
        The common part (no detector) and the satellites' models (no pixel tracks).
    tracks : tuple of FocalTrack
        One per satellite, in focal-plane mm.
    ccds : tuple of inject.camera.layout.CCD
        The ``detectors:`` (default the 189 science CCDs).
    cutout : tuple or None
        ``(ny, nx)`` of ``cutout:``.

    Raises
    ------
    SceneError
        A key every scene shares is wrong (as :func:`parse_scene` reports it), ``detector``
        is given, ``pointing`` is missing, or a track, detector list or cut-out is bad.
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
        tracks.append(orbit_track(f"{where}.orbit", sat["orbit"], spec, common, sat.get("lumos"))
                      if "orbit" in sat else
                      parse_focal_track(f"{where}.track", sat["track"], spec, common))
    check_sed_pupil(specs, common.pupil)
    scene = replace(common, satellites=tuple(specs))
    # The charge of every satellite's own vertex values (an orbit's pass, a polyline's
    # overrides; the satellite's for a line or segment), at the nominal plate scale; a pass
    # with no streak has no charge.
    check_charge(scene, [tuple(v for v in t.values if v is not None) if t.kind == "polyline"
                         else ({},) for t in tracks])
    return scene, tuple(tracks), ccds, parse_cutout(raw.get("cutout"))


def parse_cutout(spec):
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


def parse_focal_track(where, track, spec, scene):
    """A track in focal-plane mm: a line ``{x0_mm, y0_mm, angle}``, a segment (with
    ``length_mm``) or a polyline ``{vertices: [{x_mm, y_mm, ...}, ...]}`` whose vertices may
    override the satellite's height, zenith, phi and mag."""
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
