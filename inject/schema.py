"""The scene schema's building blocks, shared by every scene parser (CCD scenes, focal-plane
scenes, orbits): YAML read safely, dotted overrides, and checks of keys and numbers that report
a :class:`~inject.errors.SceneError` naming the key path (``satellites[0].height``) and the bad
value.
"""
import numbers
import re

import yaml

from inject.errors import InputError, SceneError
from inject.validate import RANGES


class SceneLoader(yaml.SafeLoader):
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
                    raise DuplicateKeyError(key, key_node.start_mark.line + 1, first.line + 1)
        return super().construct_mapping(node, deep)


class DuplicateKeyError(yaml.YAMLError):
    def __init__(self, key, line, first):
        super().__init__(f"line {line}: key {key!r} given twice (first at line {first}); "
                         "keys must be unique")


SceneLoader.add_implicit_resolver(
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
            raw = yaml.load(stream, Loader=SceneLoader)  # safe: no Python tags
    except TypeError:  # open() says only "expected str, bytes or os.PathLike object"
        raise SceneError(f"scene file {path!r}: not a file path") from None
    except OSError as err:
        raise SceneError(f"{path}: cannot read scene file ({err.strerror})") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text (UTF-8) scene file") from None
    except DuplicateKeyError as err:
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
            value = yaml.load(text, Loader=SceneLoader)  # safe, as load_scene_file
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


def number(where, value, kind=float):
    # numbers.Real: NumPy scalars from Python callers are numbers too; bools are not.
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(f"{where}={value!r}: must be a number")
    if value != value or value in (float("inf"), float("-inf")):
        raise SceneError(f"{where}={value!r}: must be finite")
    if kind is int and value != int(value):
        raise SceneError(f"{where}={value!r}: must be an integer")
    return kind(value)


def ranged(quantity, where, value, kind=float):
    """``value`` as a number inside :data:`inject.validate.RANGES` ``[quantity]``."""
    value = number(where, value, kind)
    try:
        return RANGES[quantity].check(value, where)
    except InputError as err:
        raise SceneError(str(err)) from None


def check_keys(where, mapping, allowed, required=()):
    if not isinstance(mapping, dict):
        raise SceneError(f"{where}={mapping!r}: must be a mapping")
    unknown = set(mapping) - set(allowed)
    if unknown:
        raise SceneError(f"{where}: unknown keys {sorted(unknown)} (allowed: {sorted(allowed)})")
    missing = set(required) - set(mapping)
    if missing:
        raise SceneError(f"{where}: missing keys {sorted(missing)}")
