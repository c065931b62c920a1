"""A constellation file: one satellite model and the orbits that carry it.

.. code-block:: yaml

    shape: {type: box, length: 7.25, width: 2.65}   # the model keys of a scene satellite
    mag: 5.0
    ref_range: 550
    # pupil: rubin                                  # optional, as a scene's
    # focus_offset_um: -20                          # optional, micron, with pupil: rubin
    # sed: {g-r: 0.6}                               # optional, with pupil: rubin
    # lumos: {surfaces: [...]}                      # optional, as a scene's orbit satellite
    epoch: 2026-06-15T23:00:00                      # the shells' epoch (UTC)
    shells:                                         # Walker-delta shells
      - {height: 550, inclination: 53, planes: 72, per_plane: 22, phasing: 1}
    tle: catalog.tle                                # and/or TLEs, each after a name line

The model keys are checked as a scene's satellite's (:func:`inject.config.parse_satellite`);
a shell is :func:`inject.orbits.passes.walker_shell` ``i: t/p/f`` with ``t = planes x
per_plane`` (optional ``raan0``, deg, and ``name``), its elements at the file's ``epoch``
(required with shells: the satellites' positions are part of the constellation, never taken
from the visits). A ``tle`` file (relative to the constellation file's folder, or absolute)
holds any number of TLEs, each two lines optionally after a name line; a satellite's name is its
name line (or its catalog number). No satellite may come twice, by name or by identical
elements (a shell repeated, a TLE file holding the same TLE twice).
"""
import os
import warnings
from dataclasses import dataclass, field
from functools import cached_property

from inject.config import (
    ORBIT_SATELLITE_KEYS,
    check_sed_pupil,
    parse_focus_offset,
    parse_satellite,
)
from inject.errors import InjectError, OrbitError, OrbitWarning, SceneError
from inject.orbits.passes import EPOCH_REFUSE_DAYS, EPOCH_WARN_DAYS, Orbit, walker_shell
from inject.schema import check_keys, load_scene_file, number
from inject.streak import PUPILS
from inject.survey.visits import check_mjd
from inject.validate import parse_time

#: Keys of a constellation file.
CONSTELLATION_KEYS = (ORBIT_SATELLITE_KEYS - {"orbit"}) | {"shells", "tle", "epoch", "pupil",
                                                           "focus_offset_um"}
#: Keys of a shell (``raan0`` and ``name`` optional).
SHELL_KEYS = ("height", "inclination", "planes", "per_plane", "phasing", "raan0", "name")
#: The lowest shell, km: below ~150 km a satellite re-enters within days (the atmosphere's
#: drag), so no constellation flies there.
MIN_SHELL_HEIGHT_KM = 150.0


@dataclass(frozen=True, eq=False)
class Constellation:
    """The satellites of a survey run.

    Attributes
    ----------
    satellite : inject.config.SatelliteSpec
        The model every satellite shares (shape, mag, ref_range; no height: the orbits').
    lumos : dict or None
        A ``lumos:`` mapping (brightness from lumos-sat's BRDF models).
    orbits : tuple of inject.orbits.passes.Orbit
        Every satellite, shells first, then the TLEs in file order.
    source : str
        The file, for messages.
    pupil : str
        The defocus kernel of the streaks' models, ``annulus`` or ``rubin``
        (:data:`inject.streak.PUPILS`).
    epoch : astropy.time.Time or None
        The shells' epoch (UTC); None without shells.
    sources : tuple of (str, int)
        Each shell (``shells[i] name``) and the TLE file, with its number of satellites.
    tle_files : tuple of str
        The TLE files read (absolute paths).
    focus_offset_um : float
        The detector's shift from the design's focus for ``pupil: rubin``, micron, as a
        scene's ``focus_offset_um`` (:func:`inject.config.parse_focus_offset`).
    """

    satellite: object
    lumos: dict | None
    orbits: tuple = field(repr=False)
    source: str = "constellation"
    pupil: str = "annulus"
    epoch: object = None
    sources: tuple = ()
    tle_files: tuple = ()
    focus_offset_um: float = 0.0

    def __len__(self):
        return len(self.orbits)

    @property
    def epoch_isot(self):
        """The shells' epoch as ISO 8601 UTC to the microsecond (None without shells)."""
        if self.epoch is None:
            return None
        epoch = self.epoch.copy()
        epoch.precision = 6
        return epoch.isot

    @cached_property
    def by_name(self):
        """The orbits by their names."""
        return {o.name: o for o in self.orbits}

    def check_epochs(self, visits):
        """Refuse (OrbitError) a TLE whose epoch is more than
        :data:`~inject.orbits.passes.EPOCH_REFUSE_DAYS` from a visit (the farthest visit
        named), and warn once for those more than :data:`~inject.orbits.passes.EPOCH_WARN_DAYS`
        away. The shells are exempt at any span: their elements carry no drag (SGP4's B* is
        0), so SGP4 keeps their height and turns their planes by its secular J2 terms, as a
        station-kept shell's turn; a TLE's drag and measured elements go stale within weeks.

        Parameters
        ----------
        visits : sequence of inject.survey.visits.Visit
            In start order.
        """
        first, last = visits[0], visits[-1]
        far, worst = 0, None
        tles = [o for o in self.orbits if o.kind == "tle"]
        for orbit in tles:
            gaps = [(abs((v.start - orbit.epoch).to_value("day")), v) for v in (first, last)]
            days, visit = max(gaps, key=lambda g: g[0])
            if days > EPOCH_REFUSE_DAYS:
                raise OrbitError(f"{self.source}: orbit {orbit.name!r}: epoch "
                                 f"{orbit.epoch.isot} is {days:.1f} days from visit "
                                 f"{visit.observation_id} ({visit.start.utc.iso[:19]} UTC): a TLE"
                                 f" more than {EPOCH_REFUSE_DAYS:g} days from a visit is "
                                 f"refused (its elements go stale; a Walker shell is "
                                 f"propagated over any span)")
            if days > EPOCH_WARN_DAYS:
                far += 1
                worst = max(worst or 0.0, days)
        if far:
            warnings.warn(f"{self.source}: {far} of {len(tles)} TLEs have epochs more "
                          f"than {EPOCH_WARN_DAYS:g} days from a visit (up to {worst:.1f}): "
                          f"positions may be km off", OrbitWarning, stacklevel=2)


def read_constellation(path, default_epoch=None):
    """A :class:`Constellation` from its YAML file.

    Parameters
    ----------
    path : str or os.PathLike
    default_epoch : Time or str, optional
        The shells' epoch when the file gives none; without it (as ``inject survey`` reads
        a file) a file with shells must give ``epoch``.

    Raises
    ------
    SceneError
        The file is missing, not a mapping, a key is unknown or missing (``epoch`` with
        shells), the model is out of range, a shell cannot exist (height below
        :data:`MIN_SHELL_HEIGHT_KM`, no satellites, phasing outside ``0 .. planes - 1``), or
        a satellite comes twice.
    OrbitError
        A TLE is malformed.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SceneError(f"constellation file {path!r}: no such file")
    try:
        raw = load_scene_file(path)
    except SceneError as err:
        raise SceneError(str(err).replace("scene file", "constellation file")) from None
    return parse_constellation(raw, default_epoch, os.path.dirname(os.path.abspath(path)),
                               source=path)


#: The constellation read last in this process, by the stamps of its files (:func:`_stamps`).
_READ: dict[tuple, Constellation] = {}


def _stamps(path, when, tle_files):
    """The cache key of a constellation file: the default epoch ``when`` and each file's
    path, size and modification time (ns); None if a file is gone."""
    def stamp(f):
        st = os.stat(f)
        return os.path.abspath(f), st.st_size, st.st_mtime_ns

    try:
        return when, tuple(stamp(f) for f in (path, *tle_files))
    except OSError:
        return None


def read_constellation_once(path, epoch=None):
    """:func:`read_constellation` once per process (a worker's visits share it; SGP4's
    element sets do not pickle): again when the path, ``epoch`` (the default epoch, as
    :func:`read_constellation`'s) or the size or modification time of the file or of a TLE
    file it names changes. Its OrbitWarnings are left out (the caller has warned)."""
    when = None if epoch is None else (float(epoch.utc.jd1), float(epoch.utc.jd2))
    for key, constellation in _READ.items():
        if key is not None and key == _stamps(path, when, constellation.tle_files):
            return constellation
    _READ.clear()
    # The file's stamp before it is read: an edit made meanwhile makes the next call read it.
    before = _stamps(path, when, ())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OrbitWarning)
        constellation = read_constellation(path, epoch)
    after = _stamps(path, when, constellation.tle_files)
    if before is not None and after is not None and after[1][0] == before[1][0]:
        _READ[after] = constellation
    return constellation


def file_digests(constellation):
    """SHA-256 (hex) of the constellation file and of each TLE file it names, by path."""
    from inject.exposure.runner import sha256_file

    return {os.path.abspath(p): sha256_file(p)
            for p in (constellation.source, *constellation.tle_files)}


def parse_constellation(raw, default_epoch=None, folder=".", source="constellation"):
    """A :class:`Constellation` from a mapping (the file's content); ``folder`` resolves a
    relative ``tle`` path. Raises as :func:`read_constellation`."""
    check_keys(source, raw, CONSTELLATION_KEYS, {"shape", "mag"})
    if "shells" not in raw and "tle" not in raw:
        raise SceneError(f"{source}: give shells, tle or both (the satellites)")
    satellite = parse_satellite("satellite", raw, height_from_orbit=True)
    pupil = raw.get("pupil", "annulus")
    if not isinstance(pupil, str) or pupil not in PUPILS:
        raise SceneError(f"{source}: pupil={pupil!r}: choose " + " or ".join(PUPILS))
    try:
        focus = parse_focus_offset(raw.get("focus_offset_um"), pupil)
        check_sed_pupil([satellite], pupil, ["satellite"])
    except SceneError as err:
        raise SceneError(f"{source}: {err}") from None
    lumos = raw.get("lumos")
    if lumos is not None:
        from inject.orbits.lumos import surfaces

        try:
            surfaces("lumos", lumos)  # checked now, not at the first sunlit crossing
        except SceneError as err:
            raise SceneError(f"{source}: {err}") from None
    orbits, sources, tle_files, epoch = [], [], [], None
    shells = raw.get("shells", [])
    if not isinstance(shells, list) or ("shells" in raw and not shells):
        raise SceneError(f"shells={shells!r}: must be a list of shells")
    if shells:
        if "epoch" not in raw and default_epoch is None:
            raise SceneError(f"{source}: epoch is missing: the shells' epoch (UTC), e.g. "
                             f"'epoch: 2026-06-15T23:00:00', places their satellites")
        try:
            epoch = parse_time(raw.get("epoch", default_epoch), "epoch")
            check_mjd("epoch", epoch.mjd)
        except InjectError as err:
            raise SceneError(f"{source}: {err}") from None
    for i, shell in enumerate(shells):
        name, mine = _shell(f"shells[{i}]", shell, epoch)
        orbits += mine
        sources.append((f"shells[{i}] {name}", len(mine)))
    if "tle" in raw:
        tle = raw["tle"]
        if not isinstance(tle, str) or not tle.strip():
            raise SceneError(f"tle={tle!r}: must be a file name")
        path = os.path.abspath(tle if os.path.isabs(tle) else os.path.join(folder, tle))
        mine = read_tles(path)
        orbits += mine
        sources.append((f"tle {tle}", len(mine)))
        tle_files.append(path)
    _check_unique(source, orbits)
    return Constellation(satellite, lumos, tuple(orbits), source, pupil, epoch, tuple(sources),
                         tuple(tle_files), focus)


def _elements(orbit):
    """An orbit's SGP4 elements and epoch: equal for the same satellite given twice."""
    s = orbit.satrec
    return (s.jdsatepoch, s.jdsatepochF, s.inclo, s.nodeo, s.ecco, s.argpo, s.mo, s.no_kozai,
            s.bstar)


def _check_unique(source, orbits):
    """Refuse (SceneError) two satellites of one name or of identical elements."""
    for key, what in ((lambda o: o.name, "name"), (_elements, "elements")):
        seen = {}
        for orbit in orbits:
            other = seen.setdefault(key(orbit), orbit)
            if other is not orbit:
                same = (f"{orbit.name!r} twice" if what == "name"
                        else f"{other.name!r} and {orbit.name!r}")
                raise SceneError(f"{source}: satellite {same}: the same {what} "
                                 f"(a shell or TLE given twice?): each satellite once")


def _shell(where, spec, epoch):
    """The name and the orbits of one Walker shell, its values checked."""
    check_keys(where, spec, SHELL_KEYS, SHELL_KEYS[:5])
    height = number(f"{where}.height", spec["height"])
    if height < MIN_SHELL_HEIGHT_KM:
        raise SceneError(f"{where}.height={height:g}: below {MIN_SHELL_HEIGHT_KM:g} km no "
                         f"satellite stays up (km above the Earth's surface)")
    planes = number(f"{where}.planes", spec["planes"], int)
    per_plane = number(f"{where}.per_plane", spec["per_plane"], int)
    if planes < 1 or per_plane < 1:
        raise SceneError(f"{where}: planes={planes}, per_plane={per_plane}: a shell needs at "
                         f"least one plane of at least one satellite")
    phasing = number(f"{where}.phasing", spec["phasing"], int)
    if not 0 <= phasing < planes:
        raise SceneError(f"{where}.phasing={phasing}: must be in 0 .. planes - 1 = {planes - 1}"
                         f" (Walker's F)")
    inclination = number(f"{where}.inclination", spec["inclination"])
    raan0 = number(f"{where}.raan0", spec.get("raan0", 0.0))
    name = spec.get("name", where.replace("[", "").replace("]", ""))
    if not isinstance(name, str) or not name.strip():
        raise SceneError(f"{where}.name={name!r}: must be a non-empty string")
    try:
        return name.strip(), walker_shell(planes * per_plane, planes, phasing, height,
                                          inclination, epoch, raan0, name=name.strip())
    except InjectError as err:
        raise SceneError(f"{where}: {err}") from None


def read_tles(path):
    """Every TLE of a file: two lines each, optionally after a name line.

    Raises
    ------
    OrbitError
        The file cannot be read, a line is out of place, or a TLE is malformed (named by its
        line number).
    """
    try:
        with open(path, encoding="ascii") as stream:
            lines = [(k + 1, ln.rstrip()) for k, ln in enumerate(stream) if ln.strip()]
    except (OSError, UnicodeDecodeError) as err:
        raise OrbitError(f"TLE file {str(path)!r}: cannot be read ({err})") from None
    orbits, name, k = [], None, 0
    while k < len(lines):
        number_, text = lines[k]
        if text.startswith("1 ") and k + 1 < len(lines) and lines[k + 1][1].startswith("2 "):
            source = f"TLE file {str(path)!r} line"
            orbits.append(Orbit.from_tle(text, lines[k + 1][1], name,
                                         (f"{source} {number_}", f"{source} {lines[k + 1][0]}")))
            name, k = None, k + 2
        elif name is None and not text.startswith(("1 ", "2 ")):
            name, k = text.strip().removeprefix("0 "), k + 1
        else:
            raise OrbitError(f"TLE file {str(path)!r} line {number_}: {text[:30]!r} is not "
                             f"where a name or a TLE's first line can be")
    if name is not None:
        raise OrbitError(f"TLE file {str(path)!r}: ends with a name line and no TLE")
    if not orbits:
        raise OrbitError(f"TLE file {str(path)!r}: holds no TLE")
    return orbits

