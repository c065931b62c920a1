"""Bad input everywhere: the CLI, scene files and the Python API.

Every bad value gives an :class:`~inject.errors.InjectError` (also a ``ValueError``); the CLI
turns it into one line on stderr naming the value and where it came from, exit status 2, no
traceback unless ``--traceback``. Outputs are written atomically, never replace an existing
file without ``--overwrite``, and inputs are never modified. Tests marked xfail(strict) show
bugs still to fix.
"""
import errno
import functools
import math
import os
import sys

import numpy as np
import pytest
from astropy.io import fits

import inject.io.atomic
from inject import (
    Box,
    Budget,
    Disk,
    FileFormatError,
    Geometry,
    InjectError,
    InputError,
    OutputError,
    Polyline,
    SceneError,
    Seeing,
    Segment,
    StreakModel,
    Track,
    add_streaks,
    apply_overrides,
    load_scene_file,
    parse_scene,
    read_exposure,
    render_brute_force,
    shape_from_dict,
    simulate,
)
from inject.cli.main import main
from inject.io.atomic import atomic_path, output_group
from inject.io.reader import InputExposure
from inject.photometry import band, sky_per_pixel
from inject.satellite import Composite, Part

SCENE = """\
seed: 1
band: g
zenith: 70
detector: {type: itl, nx: 64, ny: 48}
sky: false
stars: false
noise: false
satellites:
  - height: 550
    shape: {type: box, length: 7.25, width: 2.65}
    mag: 5.0
    track: {x0: 10.3, y0: 20.6, angle: 10.0, length: 30.0}
"""
STREAK_ARGS = ["--height", "550", "--zenith", "70", "--x0", "10.5", "--y0", "20.2",
               "--angle", "15", "--track-length", "20", "--no-noise"]


@pytest.fixture
def cli(cli):
    """The command line, and an error must be its only line (no warning before it)."""
    return functools.partial(cli, strict=True)


def leftovers(directory):
    """Temporary files of inject.io.atomic left in a directory."""
    return [name for name in os.listdir(directory) if name.startswith(".inject-")]


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(SCENE)
    return path


@pytest.fixture
def image(tmp_path):
    """A small 2-D FITS image in electrons."""
    rng = np.random.default_rng(2)
    path = tmp_path / "in.fits"
    fits.PrimaryHDU(rng.normal(100, 5, (48, 64)).astype(">f4"),
                    header=fits.Header({"BUNIT": "electron"})).writeto(path)
    return path


# --- The error hierarchy -------------------------------------------------------------------

@pytest.mark.parametrize("cls", [InputError, SceneError, FileFormatError])
def test_errors_are_value_errors(cls):
    # Bad input only: OutputError is an OSError, ResourceError a MemoryError
    # (tests/test_errors.py checks the whole hierarchy).
    assert issubclass(cls, InjectError) and issubclass(cls, ValueError)


# --- CLI: inject profile -------------------------------------------------------------------

@pytest.mark.parametrize("argv,needle", [
    (["--height", "-5"], "height_km=-5.0"),
    (["--height", "0"], "height_km=0.0"),
    (["--height", "nan"], "height_km=nan"),
    (["--height", "inf"], "height_km=inf"),
    (["--height", "550", "--zenith", "90"], "zenith_deg=90.0"),
    (["--height", "550", "--zenith", "95"], "zenith_deg=95.0"),
    (["--height", "550", "--zenith", "-1"], "zenith_deg=-1.0"),
    (["--height", "550", "--zenith", "nan"], "zenith_deg=nan"),
    (["--height", "550", "--phi", "nan"], "phi_deg=nan"),
    (["--height", "550", "--band", "w"], "band='w'"),
    (["--height", "550", "--band", ""], "band=''"),
    (["--height", "550", "--mag", "nan"], "mag=nan"),
    (["--height", "550", "--mag=-inf"], "mag=-inf"),
    (["--height", "550", "--seeing", "-1"], "seeing=-1.0"),
    (["--height", "550", "--seeing", "nan"], "seeing=nan"),
    (["--height", "550", "--length", "0"], "length=0.0"),
    (["--height", "550", "--width", "-2"], "width=-2.0"),
    (["--height", "550", "--shape", "disk", "--radius", "nan"], "radius=nan"),
    (["--height", "550", "--radius", "2"], "--radius=2.0"),
    (["--height", "550", "--shape", "disk", "--length", "2"], "--length/--width"),
    (["--height", "550", "--ref-range", "0"], "ref_range_km=0.0"),
    (["--height", "550", "--pixel-scale", "0"], "pixel_scale_arcsec=0.0"),
])
def test_profile_bad_values(cli, argv, needle):
    status, _, err = cli("profile", *argv)
    assert status == 2
    assert needle in err


def usage_error(capsys, argv):
    """Run the CLI on malformed options; return its one stderr line after checking that argparse
    exited with status 2, printed nothing on stdout and no usage block or traceback."""
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in argv])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1, captured.err
    assert "usage:" not in captured.err and "Traceback" not in captured.err
    return captured.err.rstrip("\n")


@pytest.mark.parametrize("argv,needle", [
    (["--height", "abc"], "argument --height: invalid float value: 'abc'"),
    (["--height", "550", "--shape", "cone"], "argument --shape: invalid choice: 'cone'"),
    (["--height", "550", "--seeing-model", "gauss"], "'gauss'"),
    (["--zenith", "10"], "the following arguments are required: --height"),
    (["--height"], "argument --height: expected one argument"),
    (["--height", "550", "--colour", "red"], "unrecognized arguments: --colour red"),
])
def test_profile_argparse_errors(capsys, argv, needle):
    """Malformed options: one line naming the option and the value, argparse's status 2."""
    line = usage_error(capsys, ["profile", *argv])
    assert line.startswith("inject profile: error: ") and needle in line


# Every subcommand: an unknown option, a missing argument, a value of the wrong type. The
# paths are never opened: argparse fails first.
ARGPARSE_ERRORS = {
    "simulate unknown option": (["simulate", "S.yaml", "-o", "O.fits", "--colour", "red"],
                                "unrecognized arguments: --colour red"),
    "simulate missing output": (["simulate", "S.yaml"],
                                "the following arguments are required: -o/--output"),
    "simulate nothing": (["simulate"],
                         "the following arguments are required: scene, -o/--output"),
    "simulate option without value": (["simulate", "S.yaml", "-o", "O.fits", "--exr"],
                                      "argument --exr: expected one argument"),
    "add-streak bad seed": (["add-streak", "I.fits", "-o", "O.fits", "--height", "550",
                             "--seed", "abc"], "argument --seed: invalid int value: 'abc'"),
    "add-streak bad x0": (["add-streak", "I.fits", "-o", "O.fits", "--height", "550",
                           "--x0", "left"], "argument --x0: invalid float value: 'left'"),
    "add-streak missing output": (["add-streak", "I.fits", "--height", "550"],
                                  "the following arguments are required: -o/--output"),
    "add-streak unknown option": (["add-streak", "I.fits", "-o", "O.fits", "--height", "550",
                                   "--colour", "red"], "unrecognized arguments: --colour red"),
    "add-streak bad choice": (["add-streak", "I.fits", "-o", "O.fits", "--height", "550",
                               "--shape", "cone"], "argument --shape: invalid choice: 'cone'"),
    "mask bad int": (["mask", "I.fits", "--max-streaks", "1.5"],
                     "argument --max-streaks: invalid int value: '1.5'"),
    "mask bad choice": (["mask", "I.fits", "--mask-rule", "wide"],
                        "argument --mask-rule: invalid choice: 'wide'"),
    "mask missing image": (["mask", "--json"],
                           "the following arguments are required: IMAGE.fits"),
    "mask unknown option": (["mask", "I.fits", "--colour", "red"],
                            "unrecognized arguments: --colour red"),
    "evaluate bad int": (["evaluate", "--out", "D", "--seeds", "x"],
                         "argument --seeds: invalid int value: 'x'"),
    "evaluate bad float": (["evaluate", "--out", "D", "--heights", "550", "low"],
                           "argument --heights: invalid float value: 'low'"),
    "evaluate missing out": (["evaluate", "--seeds", "2"],
                             "the following arguments are required: --out"),
    "evaluate empty list": (["evaluate", "--out", "D", "--mags"],
                            "argument --mags: expected at least one argument"),
    "evaluate unknown option": (["evaluate", "--out", "D", "--colour", "red"],
                                "unrecognized arguments: --colour red"),
}


@pytest.mark.parametrize("name", list(ARGPARSE_ERRORS))
def test_argparse_errors_are_one_line_in_every_subcommand(capsys, tmp_path, monkeypatch, name):
    argv, needle = ARGPARSE_ERRORS[name]
    monkeypatch.chdir(tmp_path)
    line = usage_error(capsys, argv)
    assert line.startswith(f"inject {argv[0]}: error: ") and needle in line
    assert os.listdir(tmp_path) == []  # nothing written, not even an output directory


@pytest.mark.parametrize("argv,needle", [
    ([], "the following arguments are required: command"),
    (["focus"], "argument command: invalid choice: 'focus'"),
])
def test_argparse_errors_without_a_subcommand(capsys, argv, needle):
    line = usage_error(capsys, argv)
    assert line.startswith("inject: error: ") and needle in line


def test_simulate_lists_only_required_arguments(capsys):
    """key.path=value overrides are optional: argparse must not call them required."""
    assert "key.path=value" not in usage_error(capsys, ["simulate"])


def test_argparse_error_in_a_real_process(tmp_path):
    import subprocess

    proc = subprocess.run([sys.executable, "-m", "inject", "add-streak", "in.fits", "-o",
                           "out.fits", "--height", "550", "--seed", "abc"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == "inject add-streak: error: argument --seed: invalid int value: 'abc'\n"


@pytest.mark.parametrize("command", ["profile", "simulate", "add-streak", "mask", "evaluate"])
def test_help_keeps_the_usage(capsys, command):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    captured = capsys.readouterr()
    assert captured.out.startswith(f"usage: inject {command} [-h]") and captured.err == ""
    assert "options:" in captured.out


def test_traceback_option_re_raises():
    with pytest.raises(InputError) as info:
        main(["--traceback", "profile", "--height", "-5"])
    assert info.value.name == "height_km" and info.value.value == -5.0


def test_traceback_option_re_raises_scene_errors(scene, tmp_path):
    with pytest.raises(SceneError):
        main(["--traceback", "simulate", str(scene), "-o", str(tmp_path / "o.fits"),
              "zenith=95"])


def test_errors_print_nothing_on_stdout(capsys):
    assert main(["profile", "--height", "-5", "--json"]) == 2
    assert capsys.readouterr().out == ""


# --- CLI: inject simulate with bad scene values (dotted overrides) -------------------------

@pytest.mark.parametrize("override,needle", [
    ("satellites.0.height=-5", "height_km=-5.0"),
    ("satellites.0.height=0", "height_km=0.0"),
    ("satellites.0.height=.nan", "satellites[0].height=nan"),
    ("satellites.0.height=high", "satellites[0].height='high'"),
    ("satellites.0.mag=.inf", "satellites[0].mag=inf"),
    ("satellites.0.mag=bright", "satellites[0].mag='bright'"),
    ("satellites.0.phi=.nan", "satellites[0].phi=nan"),
    ("satellites.0.track.x0=.inf", "satellites[0].track.x0=inf"),
    ("satellites.0.track.angle=[1]", "satellites[0].track.angle=[1]"),
    ("satellites.0.shape.type=cone", "shape.type='cone'"),
    ("satellites.0.shape.length=-1", "length=-1"),
    ("satellites.0.shape.width=.nan", "width=nan"),
    ("zenith=90", "zenith=90"),
    ("zenith=-1", "zenith=-1"),
    ("zenith=.nan", "zenith=nan"),
    ("band=w", "band='w'"),
    ("band=7", "band=7"),
    ("seed=abc", "seed='abc'"),
    ("seed=0", "seed=0"),
    ("seed=1.5", "seed=1.5"),
    ("seed=true", "seed=True"),
    ("exptime=0", "exptime=0"),
    ("seeing=-1", "seeing=-1"),
    ("seeing=.nan", "seeing=nan"),
    ("noise=maybe", "noise='maybe'"),
    ("units=volts", "units='volts'"),
    ("detector.nx=-3", "detector.nx=-3"),
    ("detector.nx=1.5", "detector.nx=1.5"),
    ("detector.type=ccd", "detector.type='ccd'"),
    ("detector.full_well=-1", "full_well=-1"),
    ("sky.level=-3", "sky.level=-3"),
    ("dark_current=-1", "dark_current=-1"),
    ("satellites=3", "satellites=3"),
    ("satellites.0=3", "satellites[0]=3"),
    ("colour=red", "unknown keys ['colour']"),
    ("satellites.0.colour=red", "satellites[0]: unknown keys ['colour']"),
    ("satellites.0.track.speed=3", "satellites[0].track: unknown keys ['speed']"),
    ("satellites.7.mag=3", "satellites.7"),
    ("=3", "'=3'"),
    ("satellites.0.mag=[5", "override 'satellites.0.mag=[5': value is not valid YAML"),
    ("pointing={ra: 10, dec: 5, roll: 3}", "pointing: unknown keys ['roll']"),
    ("pointing={ra: 10, dec: 5, rotation: .nan}", "pointing.rotation=nan"),
    ("pointing={ra: 10}", "pointing: missing keys ['dec']"),
    ("sky={airmass_scaling: maybe}", "sky.airmass_scaling='maybe'"),
])
def test_simulate_bad_values(cli, scene, tmp_path, override, needle):
    out = tmp_path / "out.fits"
    status, _, err = cli("simulate", scene, "-o", out, override)
    assert status == 2
    assert needle in err
    assert not out.exists() and not leftovers(tmp_path)


# --- Scene files ---------------------------------------------------------------------------

BAD_SCENES = {
    "missing shape": ("satellites:\n  - {height: 550, mag: 5, track: {x0: 1, y0: 1, angle: 0}}\n",
                      "satellites[0]: missing keys ['shape']"),
    "missing track x0": ("satellites:\n  - {height: 550, mag: 5, shape: {type: disk, radius: 1},"
                         " track: {y0: 1, angle: 0}}\n",
                         "satellites[0].track: missing keys ['x0']"),
    "missing box width": ("satellites:\n  - {height: 550, mag: 5, shape: {type: box, length: 1},"
                          " track: {x0: 1, y0: 1, angle: 0}}\n", "missing keys ['width']"),
    "satellites a mapping": ("satellites: {height: 550}\n", "satellites={'height': 550}"),
    "track a list": ("satellites:\n  - {height: 550, mag: 5, shape: {type: disk, radius: 1},"
                     " track: [1, 2]}\n", "satellites[0].track=[1, 2]"),
    "height a string": ("satellites:\n  - {height: low, mag: 5, shape: {type: disk, radius: 1},"
                        " track: {x0: 1, y0: 1, angle: 0}}\n", "satellites[0].height='low'"),
    "unknown top key": ("colour: red\n", "unknown keys ['colour']"),
    "unknown shape key": ("satellites:\n  - {height: 550, mag: 5, shape: {type: disk, radius: 1,"
                          " depth: 2}, track: {x0: 1, y0: 1, angle: 0}}\n",
                          "unknown keys ['depth']"),
    "unknown shape type": ("satellites:\n  - {height: 550, mag: 5, shape: {type: cone},"
                           " track: {x0: 1, y0: 1, angle: 0}}\n", "shape.type='cone'"),
    "unknown band": ("band: w\n", "band='w'"),
    "negative height": ("satellites:\n  - {height: -550, mag: 5, shape: {type: disk, radius: 1},"
                        " track: {x0: 1, y0: 1, angle: 0}}\n", "height_km=-550.0"),
    "nan height": ("satellites:\n  - {height: .nan, mag: 5, shape: {type: disk, radius: 1},"
                   " track: {x0: 1, y0: 1, angle: 0}}\n", "satellites[0].height=nan"),
    "zenith 90": ("zenith: 90\n", "zenith=90"),
    "bad YAML: unclosed bracket": ("seed: [1\n", "not valid YAML"),
    "bad YAML: tab indent": ("detector:\n\ttype: itl\n", "not valid YAML"),
    "bad YAML: duplicate anchor use": ("a: *missing\n", "not valid YAML"),
    "not a mapping: list": ("- 1\n- 2\n", "must be a mapping"),
    "not a mapping: scalar": ("42\n", "must be a mapping"),
    "not a mapping: empty": ("", "must be a mapping"),
}


@pytest.mark.parametrize("name", list(BAD_SCENES))
def test_bad_scene_files(cli, tmp_path, name, digest):
    text, needle = BAD_SCENES[name]
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    before = digest(path)
    out = tmp_path / "out.fits"
    status, _, err = cli("simulate", path, "-o", out)
    assert status == 2 and needle in err
    assert not out.exists() and digest(path) == before
    # The same through the Python API: a SceneError, which is also a ValueError.
    with pytest.raises(ValueError) as info:
        parse_scene(load_scene_file(path))
    assert isinstance(info.value, SceneError) and needle in str(info.value)


@pytest.mark.parametrize("tag", [
    "!!python/object/apply:os.system ['touch {marker}']",
    "!!python/object/apply:subprocess.call [['touch', '{marker}']]",
    "!!python/name:os.system",
    "!!python/object/new:os.system ['touch {marker}']",
    "!!python/module:os",
])
def test_unsafe_yaml_tags_are_refused_and_never_run(cli, tmp_path, tag):
    marker = tmp_path / "PWNED"
    path = tmp_path / "unsafe.yaml"
    path.write_text(f"seed: 1\nsatellites: {tag.format(marker=marker)}\n")
    status, _, err = cli("simulate", path, "-o", tmp_path / "out.fits")
    assert status == 2 and "not valid YAML" in err and str(path) in err
    assert not marker.exists()
    with pytest.raises(SceneError):
        load_scene_file(path)
    assert not marker.exists()


def test_missing_scene_file(cli, tmp_path):
    status, _, err = cli("simulate", tmp_path / "nope.yaml", "-o", tmp_path / "o.fits")
    assert status == 2 and "nope.yaml" in err and "cannot read" in err


def test_scene_file_is_a_directory(cli, tmp_path):
    status, _, err = cli("simulate", tmp_path, "-o", tmp_path / "o.fits")
    assert status == 2 and "cannot read" in err


# --- A user masking function is imported only when named explicitly ------------------------

@pytest.fixture
def booby_trapped_module(tmp_path, monkeypatch):
    """A module that leaves a marker file when imported."""
    name = "inject_test_user_masker"
    marker = tmp_path / "IMPORTED"
    (tmp_path / f"{name}.py").write_text(
        f"open({str(marker)!r}, 'w').close()\n"
        "import numpy as np\n"
        "def mask(image):\n    return np.zeros(image.shape, bool)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)
    yield name, marker
    sys.modules.pop(name, None)


def test_scene_cannot_name_a_masking_function(cli, tmp_path, booby_trapped_module):
    name, marker = booby_trapped_module
    path = tmp_path / "scene.yaml"
    path.write_text(SCENE + f"masker: {name}:mask\n")
    status, _, err = cli("simulate", path, "-o", tmp_path / "o.fits")
    assert status == 2 and "unknown keys ['masker']" in err
    assert not marker.exists()


def test_masking_function_imported_only_when_named(booby_trapped_module):
    from inject.masking import evaluate  # the project's own module: a rename must fail
    load_masker = getattr(evaluate, "load_masker", None)
    if load_masker is None:
        pytest.skip("inject.masking.evaluate has no load_masker")
    name, marker = booby_trapped_module
    load_masker("inject")  # the built-in masker imports nothing of the user's
    assert not marker.exists()
    with pytest.raises(InjectError):
        load_masker(name)  # a bare module name is not a "module:function" spec
    assert not marker.exists()
    with pytest.raises(InjectError):
        load_masker("inject_no_such_module_xyz:mask")
    masker = load_masker(f"{name}:mask")  # named explicitly: imported
    assert marker.exists() and callable(masker.func if hasattr(masker, "func") else masker)


# --- Python API: every bad value is an InjectError and a ValueError ------------------------

API_CASES = {
    "negative height": (lambda: StreakModel(-5.0), "height_km=-5.0"),
    "nan height": (lambda: StreakModel(float("nan")), "height_km=nan"),
    "zenith 90": (lambda: StreakModel(550.0, 90.0), "zenith_deg=90.0"),
    "zenith above 90": (lambda: Geometry.from_orbit(550.0, 120.0), "zenith_deg=120.0"),
    "nan phi": (lambda: StreakModel(550.0, phi_deg=float("nan")), "phi_deg=nan"),
    "unknown band": (lambda: StreakModel(550.0, band_name="w"), "band='w'"),
    "band not a string": (lambda: band(None), "band=None"),
    "height not a number": (lambda: StreakModel("high"), "height_km='high'"),
    "unknown shape": (lambda: shape_from_dict({"type": "cone"}), "shape.type='cone'"),
    "shape without type": (lambda: shape_from_dict({"radius": 1}), "shape="),
    "negative box": (lambda: Box(-1.0, 1.0), "length=-1.0"),
    "nan disk": (lambda: Disk(float("nan")), "radius=nan"),
    "negative seeing": (lambda: Seeing(-0.5), "seeing=-0.5"),
    "unknown seeing model": (lambda: Seeing(0.7, "gauss"), "seeing.model='gauss'"),
    "negative length": (lambda: Segment(0.0, 0.0, 0.0, -1.0), "length=-1.0"),
    "nan start": (lambda: Segment(float("nan"), 0.0, 0.0, 1.0), "x0=nan"),
    "one vertex": (lambda: Polyline((1.0,), (2.0,)), "polyline"),
    "zero tolerance": (lambda: Budget(tolerance=0.0), "tolerance=0.0"),
    "tolerance below the LSF accuracy": (lambda: Budget(tolerance=1e-9), "tolerance=1e-09"),
    "negative exposure": (lambda: sky_per_pixel("g", -30.0), "exptime=-30.0"),
    "brute force on an empty image": (
        lambda: render_brute_force((0, 5), StreakModel(550.0).profile, 0.2,
                                   Segment(0, 0, 0, 1), 1.0), "shape=(0, 5)"),
    "scene missing keys": (lambda: parse_scene({"satellites": [{"height": 550}]}),
                           "satellites[0]: missing keys"),
    "scene unknown key": (lambda: parse_scene({"colour": "red"}), "unknown keys ['colour']"),
    "scene wrong type": (lambda: parse_scene({"exptime": "long"}), "exptime='long'"),
    "scene file not a path": (lambda: load_scene_file(None), "scene file None"),
    "override not YAML": (lambda: apply_overrides({}, ["seed=[1"]),
                          "override 'seed=[1': value is not valid YAML"),
    "override not a string": (lambda: apply_overrides({}, [3]), "override 3"),
    "overrides a string": (lambda: apply_overrides({}, "seed=3"), "overrides='seed=3'"),
    "scene not plain data": (lambda: apply_overrides({"seed": object()}, []), "not plain data"),
    "pointing unknown key": (lambda: parse_scene({"pointing": {"ra": 1, "dec": 2, "roll": 3}}),
                             "pointing: unknown keys ['roll']"),
    "pointing not a number": (lambda: parse_scene({"pointing": {"ra": "north", "dec": 2}}),
                              "pointing.ra='north'"),
    "simulate a mapping": (lambda: simulate({"seed": 1}), "scene=dict"),
    "sky scaling not a bool": (
        lambda: simulate(parse_scene({"detector": {"type": "itl", "nx": 8, "ny": 8},
                                      "stars": False, "sky": {"airmass_scaling": "no"}})),
        "sky.airmass_scaling='no'"),
}


def exposure():
    return InputExposure(fits.HDUList([fits.PrimaryHDU(np.zeros((20, 30), np.float32))]),
                         0, None, None)


MODEL, TRACK = StreakModel(550.0), Track(2.0, 3.0, 10.0, 15.0)
ADD_STREAK_CASES = {
    "gain not a number": (dict(gain="high"), "gain='high'"),
    "gain None": (dict(gain=None), "gain=None"),
    "gain zero": (dict(gain=0.0), "gain=0.0"),
    "a track short": (dict(models=[MODEL, MODEL]), "tracks=1: need one per model (2)"),
    "track a mapping": (dict(tracks=[{"x0": 1, "y0": 2, "angle": 0}]), "tracks[0]='dict'"),
    "model a mapping": (dict(models=[{"height": 550}]), "models[0]='dict'"),
    "exposure an array": (dict(exposure=np.zeros((20, 30))), "exposure='ndarray'"),
    "rng not a generator": (dict(rng="seed"), "rng='seed'"),
}


@pytest.mark.parametrize("name", list(ADD_STREAK_CASES))
def test_add_streaks_api_errors(name):
    changes, needle = ADD_STREAK_CASES[name]
    kwargs = dict(exposure=exposure(), models=[MODEL], tracks=[TRACK], gain=1.0,
                  rng=np.random.default_rng(1)) | changes
    with pytest.raises(InputError) as info:
        add_streaks(**kwargs)
    assert needle in str(info.value)


def test_add_streaks_takes_a_seed():
    a = exposure()
    add_streaks(a, [MODEL], [TRACK], 1.0, 7)
    b = exposure()
    add_streaks(b, [MODEL], [TRACK], 1.0, np.random.default_rng(7))
    np.testing.assert_array_equal(a.image, b.image)


@pytest.mark.parametrize("name", list(API_CASES))
def test_api_errors_are_inject_and_value_errors(name):
    call, needle = API_CASES[name]
    with pytest.raises(InjectError) as info:
        call()
    assert needle in str(info.value)
    with pytest.raises(ValueError):
        call()


# --- Unreadable or truncated FITS for add-streak -------------------------------------------

def _truncated(path, image):
    path.write_bytes(image.read_bytes()[:4000])


def _garbage(path, image):
    path.write_bytes(b"\x00\xffnot a FITS file at all" * 50)


def _empty(path, image):
    path.write_bytes(b"")


def _header_only(path, image):
    path.write_bytes(image.read_bytes()[:2880])


def _table_only(path, image):
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(
        [fits.Column(name="a", format="E", array=np.zeros(3))])]).writeto(path)


def _cube(path, image):
    fits.PrimaryHDU(np.zeros((3, 4, 5), np.float32)).writeto(path)


@pytest.mark.parametrize("make,needle", [
    (_truncated, "not a readable FITS file"), (_garbage, "not a readable FITS file"),
    (_empty, "not a readable FITS file"), (_header_only, "not a readable FITS file"),
    (_table_only, "no 2-D image"), (_cube, "no 2-D image")])
def test_add_streak_unreadable_input(cli, tmp_path, image, make, needle, digest):
    bad = tmp_path / "bad.fits"
    make(bad, image)
    before = digest(bad)
    out = tmp_path / "out.fits"
    status, _, err = cli("add-streak", bad, "-o", out, *STREAK_ARGS)
    assert status == 2 and str(bad) in err and needle in err
    assert not out.exists() and not leftovers(tmp_path)
    assert digest(bad) == before
    with pytest.raises(FileFormatError):
        read_exposure(bad)


def test_add_streak_missing_input(cli, tmp_path):
    status, _, err = cli("add-streak", tmp_path / "nope.fits", "-o", tmp_path / "o.fits",
                      *STREAK_ARGS)
    assert status == 2 and "nope.fits: no such file" in err


def test_add_streak_input_is_a_directory(cli, tmp_path):
    status, _, err = cli("add-streak", tmp_path, "-o", tmp_path / "o.fits", *STREAK_ARGS)
    assert status == 2 and "not a readable FITS file" in err


@pytest.mark.parametrize("argv,needle", [
    (["--height", "-5"], "height_km=-5.0"),
    (["--zenith", "90"], "zenith_deg=90.0"),
    (["--band", "w"], "band='w'"),
    (["--gain", "0"], "gain=0.0"),
    (["--gain", "nan"], "gain=nan"),
    (["--track-length", "-5"], "length=-5.0"),
    (["--ra0", "10", "--dec0", "5"], "has no WCS"),
])
def test_add_streak_bad_values(cli, tmp_path, image, argv, needle, digest):
    base = dict(zip(STREAK_ARGS[:-1:2], STREAK_ARGS[1::2]))
    for key, value in zip(argv[::2], argv[1::2]):
        base[key] = value
    args = [item for pair in base.items() for item in pair] + ["--no-noise"]
    out = tmp_path / "out.fits"
    before = digest(image)
    status, _, err = cli("add-streak", image, "-o", out, *args)
    assert status == 2 and needle in err
    assert not out.exists() and digest(image) == before


def test_add_streak_needs_a_gain(cli, tmp_path):
    path = tmp_path / "adu.fits"
    fits.PrimaryHDU(np.zeros((20, 30), np.float32)).writeto(path)
    status, _, err = cli("add-streak", path, "-o", tmp_path / "o.fits", *STREAK_ARGS)
    assert status == 2 and "--gain" in err


# --- Outputs that cannot be written --------------------------------------------------------

def unwritable_dir(tmp_path):
    """A directory this process cannot write to; as root (chmod does not stop root) a path
    under a regular file instead."""
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    probe = locked / "probe"
    try:
        probe.write_bytes(b"")
    except OSError:
        return locked  # a normal user: the directory is really read-only
    probe.unlink()
    locked.chmod(0o700)
    plain = tmp_path / "file.txt"
    plain.write_text("a regular file, not a directory")
    return plain


@pytest.mark.parametrize("option", ["-o", "--exr", "--png", "--truth"])
def test_simulate_output_not_writable(cli, scene, tmp_path, option):
    where = unwritable_dir(tmp_path)
    target = where / "out.bin"
    argv = ["simulate", scene, "-o", tmp_path / "ok.fits"]
    if option == "-o":
        argv[3] = target
    else:
        argv += [option, target]
    status, _, err = cli(*argv)
    assert status == 2 and str(target) in err
    assert not (tmp_path / "ok.fits").exists()  # checked before any work or writing
    assert not target.exists()


def test_add_streak_output_not_writable(cli, tmp_path, image):
    target = unwritable_dir(tmp_path) / "out.fits"
    status, _, err = cli("add-streak", image, "-o", target, *STREAK_ARGS)
    assert status == 2 and str(target) in err


def test_output_directory_missing(cli, scene, tmp_path):
    target = tmp_path / "no" / "such" / "dir" / "out.fits"
    status, _, err = cli("simulate", scene, "-o", target)
    assert status == 2 and "does not exist" in err and str(target) in err


def test_output_is_a_directory(cli, scene, tmp_path):
    (tmp_path / "d").mkdir()
    status, _, err = cli("simulate", scene, "-o", tmp_path / "d", "--overwrite")
    assert status == 2 and str(tmp_path / "d") in err
    assert (tmp_path / "d").is_dir() and not leftovers(tmp_path)


# --- A full disk ---------------------------------------------------------------------------

def enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def fail_move_onto(monkeypatch, target):
    """The move of a finished temporary file onto ``target`` fails: the disk is full."""
    real_replace = os.replace

    def replace(src, dst):
        if os.fspath(dst) == str(target):
            enospc()
        real_replace(src, dst)

    monkeypatch.setattr(inject.io.atomic.os, "replace", replace)


def test_atomic_path_full_disk_leaves_target_untouched(tmp_path):
    target = tmp_path / "out.fits"
    target.write_bytes(b"the previous result")
    with pytest.raises(OutputError) as info:
        with atomic_path(str(target), overwrite=True) as tmp:
            with open(tmp, "wb") as stream:
                stream.write(b"half of the new")
            enospc()
    assert "No space left on device" in str(info.value) and str(target) in str(info.value)
    assert target.read_bytes() == b"the previous result"
    assert not leftovers(tmp_path)


def test_simulate_full_disk(capsys, monkeypatch, scene, tmp_path, cli, digest):
    out = tmp_path / "out.fits"
    assert main(["simulate", str(scene), "-o", str(out)]) == 0
    capsys.readouterr()
    before = digest(out)

    from inject.io.fits import _DigestStream

    real_write = _DigestStream.write

    def full_in_the_data(self, data, buffer=None):
        # The disk fills up once the headers and the first piece of data are written.
        if self._out.tell() > 2 * 2880:
            enospc()
        return real_write(self, data, buffer)

    monkeypatch.setattr(_DigestStream, "write", full_in_the_data)
    status, _, err = cli("simulate", scene, "-o", out, "--overwrite")
    assert status == 2 and "No space left on device" in err and str(out) in err
    assert digest(out) == before and not leftovers(tmp_path)


def test_add_streak_full_disk(cli, monkeypatch, tmp_path, image):
    out = tmp_path / "out.fits"
    out.write_bytes(b"previous")
    monkeypatch.setattr(fits.HDUList, "writeto", lambda self, *a, **k: enospc())
    status, _, err = cli("add-streak", image, "-o", out, *STREAK_ARGS, "--overwrite")
    assert status == 2 and "No space left on device" in err
    assert out.read_bytes() == b"previous" and not leftovers(tmp_path)


@pytest.mark.parametrize("option", ["--exr", "--png", "--truth"])
def test_full_disk_on_the_rename(cli, monkeypatch, scene, tmp_path, option):
    """ENOSPC as the finished temporary file is moved into place (EXR, PNG, CSV writers)."""
    fits_out, other = tmp_path / "out.fits", tmp_path / "out.other"
    other.write_bytes(b"previous")
    fail_move_onto(monkeypatch, other)
    status, _, err = cli("simulate", scene, "-o", fits_out, option, other, "--overwrite")
    assert status == 2 and "No space left on device" in err and str(other) in err
    assert other.read_bytes() == b"previous" and not leftovers(tmp_path)
    assert not fits_out.exists()  # moved into place first, then taken back


# --- Several outputs: all or nothing -------------------------------------------------------

ALL_OUTPUTS = ("out.fits", "out.exr", "out.png", "out.csv")


def simulate_all(scene, tmp_path, *extra):
    """argv of a simulate writing FITS, EXR, PNG and CSV into tmp_path."""
    paths = [tmp_path / name for name in ALL_OUTPUTS]
    return ["simulate", scene, "-o", paths[0], "--exr", paths[1], "--png", paths[2],
            "--truth", paths[3], *extra]


@pytest.fixture
def exr_writer_fails(monkeypatch):
    """OpenImageIO cannot make an EXR writer: write_exr fails after the FITS is written."""
    import OpenImageIO

    monkeypatch.setattr(OpenImageIO.ImageOutput, "create", staticmethod(lambda *a: None))


def test_simulate_failing_exr_leaves_no_fits(cli, scene, tmp_path, exr_writer_fails):
    status, _, err = cli(*simulate_all(scene, tmp_path))
    assert status == 2 and str(tmp_path / "out.exr") in err
    assert sorted(os.listdir(tmp_path)) == ["scene.yaml"]  # no FITS, no temporaries


def test_simulate_failing_exr_keeps_every_previous_output(cli, scene, tmp_path, exr_writer_fails):
    for name in ALL_OUTPUTS:
        (tmp_path / name).write_bytes(f"previous {name}".encode())
    status, _, err = cli(*simulate_all(scene, tmp_path, "--overwrite"))
    assert status == 2 and str(tmp_path / "out.exr") in err
    for name in ALL_OUTPUTS:
        assert (tmp_path / name).read_bytes() == f"previous {name}".encode()
    assert not leftovers(tmp_path)


def test_simulate_failing_last_move_restores_replaced_outputs(cli, monkeypatch, scene, tmp_path):
    """The CSV cannot be moved into place: the FITS, EXR and PNG already moved are undone
    (the replaced FITS restored, the new EXR and PNG removed)."""
    (tmp_path / "out.fits").write_bytes(b"previous FITS")
    fail_move_onto(monkeypatch, tmp_path / "out.csv")
    status, _, err = cli(*simulate_all(scene, tmp_path, "--overwrite"))
    assert status == 2 and "No space left on device" in err and str(tmp_path / "out.csv") in err
    assert sorted(os.listdir(tmp_path)) == ["out.fits", "scene.yaml"]
    assert (tmp_path / "out.fits").read_bytes() == b"previous FITS"


@pytest.mark.parametrize("existing", ALL_OUTPUTS)
def test_simulate_existing_target_writes_nothing(cli, scene, tmp_path, existing):
    (tmp_path / existing).write_bytes(b"keep me")
    status, _, err = cli(*simulate_all(scene, tmp_path))
    assert status == 2 and str(tmp_path / existing) in err and "--overwrite" in err
    assert sorted(os.listdir(tmp_path)) == sorted(["scene.yaml", existing])
    assert (tmp_path / existing).read_bytes() == b"keep me"


@pytest.mark.parametrize("second", ["out.fits", "./out.fits"])
def test_simulate_same_target_twice(cli, scene, tmp_path, monkeypatch, second):
    monkeypatch.chdir(tmp_path)
    status, _, err = cli("simulate", scene, "-o", "out.fits", "--exr", second)
    assert status == 2 and "given for two outputs" in err
    assert os.listdir(tmp_path) == ["scene.yaml"]


def test_evaluate_writes_all_its_files_or_none(cli, monkeypatch, tmp_path):
    """The campaign's tables are written, then a plot fails: no table is left behind."""
    import matplotlib.figure

    import inject.cli.evaluate as cli_evaluate

    rows = [{"masker": "inject", "height_km": h, "mag": m, "n": 1, "peak_sb": 2.0 / m,
             "int_snr": 50.0 / m, "completeness": 1.0, "fwhm_bias_pct": 1.0, "masked_px": h}
            for h in (550.0, 350.0) for m in (11.0, 12.0)]
    monkeypatch.setattr(cli_evaluate, "run_campaign", lambda *a, **k: (rows, rows))
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", enospc)
    out = tmp_path / "ev"
    status, _, err = cli("evaluate", "--out", out)
    assert status == 2 and "No space left on device" in err and "completeness.png" in err
    assert not out.exists()  # not even the folder made for the campaign


def test_evaluate_refuses_to_replace_an_earlier_campaign(cli, monkeypatch, tmp_path):
    """Existing outputs in --out stop the campaign before it runs, unless --overwrite."""
    import inject.cli.evaluate as cli_evaluate

    out = tmp_path / "ev"
    out.mkdir()
    (out / "summary.md").write_text("an earlier campaign")

    def campaign(*args, **kwargs):
        raise AssertionError("the campaign ran before its outputs were checked")
    monkeypatch.setattr(cli_evaluate, "run_campaign", campaign)
    status, _, err = cli("evaluate", "--out", out)
    assert status == 2 and "summary.md: exists; pass --overwrite" in err
    assert (out / "summary.md").read_text() == "an earlier campaign"


# --- inject.io.atomic.output_group (Python API) --------------------------------------------

def write_text(path, text, overwrite=False):
    with atomic_path(str(path), overwrite) as tmp:
        with open(tmp, "w") as stream:
            stream.write(text)


def test_output_group_moves_nothing_when_its_block_fails(tmp_path):
    (tmp_path / "b").write_text("old b")
    with pytest.raises(RuntimeError):
        with output_group([tmp_path / "a", tmp_path / "b"], overwrite=True):
            write_text(tmp_path / "a", "new a", overwrite=True)
            assert not (tmp_path / "a").exists()  # not before the group ends
            raise RuntimeError("a bug after the first output")
    assert sorted(os.listdir(tmp_path)) == ["b"] and (tmp_path / "b").read_text() == "old b"


def test_output_group_checks_every_target_on_entry(tmp_path):
    (tmp_path / "b").write_text("old b")
    ran = []
    with pytest.raises(OutputError, match="exists; pass --overwrite"):
        with output_group([tmp_path / "a", tmp_path / "b"]):
            ran.append(True)
    assert not ran


def test_output_group_refuses_a_file_made_meanwhile(tmp_path):
    """Without overwrite, a target that appeared while the outputs were being written is kept
    and nothing is moved."""
    with pytest.raises(OutputError, match="exists"):
        with output_group([tmp_path / "a", tmp_path / "b"]):
            write_text(tmp_path / "a", "new a")
            write_text(tmp_path / "b", "new b")
            (tmp_path / "b").write_text("someone else's")
    assert sorted(os.listdir(tmp_path)) == ["b"]
    assert (tmp_path / "b").read_text() == "someone else's"


def test_output_group_nested_joins_the_outer(tmp_path):
    with output_group([tmp_path / "a"]):
        with output_group([tmp_path / "b"]):
            write_text(tmp_path / "a", "a")
            write_text(tmp_path / "b", "b")
        assert not (tmp_path / "b").exists()
    assert (tmp_path / "a").read_text() == "a" and (tmp_path / "b").read_text() == "b"


@pytest.mark.parametrize("hard_links", [True, False])
def test_output_group_undoes_its_moves(monkeypatch, tmp_path, hard_links):
    """A later move fails: a replaced file (here a symlink) comes back as it was, a new one
    goes; without hard links (some file systems) the old file is kept by a copy instead."""
    (tmp_path / "real").write_text("real")
    (tmp_path / "link").symlink_to("real")
    fail_move_onto(monkeypatch, tmp_path / "c")
    if not hard_links:
        def no_link(*args, **kwargs):
            raise OSError(errno.EPERM, os.strerror(errno.EPERM))
        monkeypatch.setattr(inject.io.atomic.os, "link", no_link)
    paths = [tmp_path / "link", tmp_path / "b", tmp_path / "c"]
    with pytest.raises(OutputError, match="No space left on device") as info:
        with output_group(paths, overwrite=True):
            for path in paths:
                write_text(path, "new", overwrite=True)
    assert str(tmp_path / "c") in str(info.value)
    assert sorted(os.listdir(tmp_path)) == ["link", "real"]
    assert os.readlink(tmp_path / "link") == "real" and (tmp_path / "real").read_text() == "real"


# --- Existing outputs are not replaced without --overwrite ---------------------------------

@pytest.mark.parametrize("option", ["-o", "--exr", "--png", "--truth"])
def test_simulate_never_replaces_without_overwrite(cli, scene, tmp_path, option):
    # -o must be named as FITS; the other outputs take any name.
    existing = tmp_path / ("existing.fits" if option == "-o" else "existing.out")
    existing.write_bytes(b"keep me")
    fresh = tmp_path / "fresh.fits"
    argv = ["simulate", scene, "-o", fresh]
    if option == "-o":
        argv[3] = existing
    else:
        argv += [option, existing]
    status, _, err = cli(*argv)
    assert status == 2 and str(existing) in err and "--overwrite" in err
    assert existing.read_bytes() == b"keep me"
    assert not fresh.exists()  # every output is checked before anything is written
    assert main([str(a) for a in argv] + ["--overwrite"]) == 0
    assert existing.read_bytes() != b"keep me"


def test_add_streak_never_replaces_without_overwrite(cli, tmp_path, image):
    out = tmp_path / "out.fits"
    out.write_bytes(b"keep me")
    status, _, err = cli("add-streak", image, "-o", out, *STREAK_ARGS)
    assert status == 2 and "--overwrite" in err and out.read_bytes() == b"keep me"
    assert main(["add-streak", str(image), "-o", str(out), *STREAK_ARGS, "--overwrite"]) == 0
    with fits.open(out) as hdus:
        assert "STREAK_MODEL" in [h.name for h in hdus]


# --- Inputs are never modified -------------------------------------------------------------

def test_simulate_never_modifies_the_scene_file(capsys, scene, tmp_path, cli, digest):
    before, mtime = digest(scene), os.stat(scene).st_mtime_ns
    assert main(["simulate", str(scene), "-o", str(tmp_path / "a.fits"),
                 "satellites.0.mag=3"]) == 0
    capsys.readouterr()
    cli("simulate", scene, "-o", tmp_path / "b.fits", "zenith=95")
    assert digest(scene) == before and os.stat(scene).st_mtime_ns == mtime


def test_add_streak_never_modifies_its_input(capsys, tmp_path, image, cli, digest):
    before, mtime = digest(image), os.stat(image).st_mtime_ns
    out = tmp_path / "out.fits"
    assert main(["add-streak", str(image), "-o", str(out), *STREAK_ARGS]) == 0
    # Injecting again into our own output, and failing runs, leave inputs alone too.
    out_before = digest(out)
    assert main(["add-streak", str(out), "-o", str(tmp_path / "twice.fits"), *STREAK_ARGS]) == 0
    capsys.readouterr()
    cli("add-streak", image, "-o", tmp_path / "bad.fits", "--height", "-1",
        "--x0", "1", "--y0", "1")
    status, _, err = cli("add-streak", image, "-o", image, *STREAK_ARGS, "--overwrite")
    assert status == 2 and "never modified" in err
    assert digest(image) == before and os.stat(image).st_mtime_ns == mtime
    assert digest(out) == out_before


# --- Known bugs ----------------------------------------------------------------------------

def test_truncated_fits_gives_one_line_in_a_real_process(tmp_path, image):
    import subprocess

    bad = tmp_path / "truncated.fits"
    _truncated(bad, image)
    proc = subprocess.run([sys.executable, "-m", "inject", "add-streak", str(bad), "-o",
                           str(tmp_path / "o.fits"), *STREAK_ARGS],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr


def test_simulate_refuses_to_replace_its_scene_file(cli, scene, digest):
    before = digest(scene)
    status, _, err = cli("simulate", scene, "-o", scene, "--overwrite")
    assert status == 2 and digest(scene) == before


def test_non_utf8_scene_file(cli, tmp_path):
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"\xff\xfe\x00seed: 1\n" + bytes(range(128, 256)))
    status, _, err = cli("simulate", path, "-o", tmp_path / "o.fits")
    assert status == 2 and str(path) in err


@pytest.mark.parametrize("parts", ["5", "[5]"])
def test_composite_parts_of_the_wrong_type(cli, scene, tmp_path, parts):
    status, _, err = cli("simulate", scene, "-o", tmp_path / "o.fits",
                      f"satellites.0.shape={{type: composite, parts: {parts}}}")
    assert status == 2 and "parts" in err


@pytest.mark.parametrize("option", ["--x0", "--y0", "--angle"])
def test_add_streak_nan_track(cli, tmp_path, image, option):
    base = dict(zip(STREAK_ARGS[:-1:2], STREAK_ARGS[1::2])) | {"--angle": "0"} | {option: "nan"}
    base.pop("--track-length")  # a crossing track
    args = [item for pair in base.items() for item in pair]
    status, _, err = cli("add-streak", image, "-o", tmp_path / "o.fits", *args)
    assert status == 2 and f"{option.lstrip('-')}" in err and "nan" in err
    assert "np.float64" not in err


def test_add_streak_negative_seed(cli, tmp_path, image):
    status, _, err = cli("add-streak", image, "-o", tmp_path / "o.fits", *STREAK_ARGS,
                      "--seed", "-1")
    assert status == 2 and "seed" in err


@pytest.mark.parametrize("override,where", [
    ("satellites.0.ref_range=-1", "satellites[0].ref_range"),
    ("satellites.0.track.length=-4", "satellites[0].track.length"),
    ("satellites.0.track={vertices: [{x: 1, y: 2}, {x: 9, y: 2, height: -4}]}",
     "satellites[0].track.vertices[1].height"),
    ("satellites.0.track={vertices: [{x: 1, y: 2}, {x: 9, y: 2, zenith: 95}]}",
     "satellites[0].track.vertices[1].zenith"),
])
def test_scene_errors_name_their_key(cli, scene, tmp_path, override, where):
    status, _, err = cli("simulate", scene, "-o", tmp_path / "o.fits", override)
    assert status == 2 and where in err


def test_scene_accepts_exponent_notation(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(SCENE.replace("height: 550", "height: 5.5e2").replace("mag: 5.0",
                                                                          "mag: 5e0"))
    scene = parse_scene(load_scene_file(path))
    assert scene.satellites[0].height == 550.0 and scene.satellites[0].mag == 5.0
    # Overrides read values as scene files do.
    scene = parse_scene(apply_overrides(load_scene_file(path), ["satellites.0.height=3.5e2"]))
    assert scene.satellites[0].height == 350.0


def test_scene_accepts_numpy_numbers():
    scene = parse_scene({"seed": np.int64(3), "exptime": np.float32(15.0)})
    assert scene.seed == 3 and type(scene.seed) is int and scene.exptime == 15.0


def test_huge_values_stay_finite_or_are_refused(capsys):
    """Extreme but valid input gives finite numbers, never inf/NaN in the output."""
    import json

    assert main(["profile", "--height", "1e7", "--zenith", "89.9999", "--mag", "-30",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert all(math.isfinite(v) for v in out.values() if isinstance(v, float))


# --- Known bugs outside the CLI, config and I/O (their modules are edited elsewhere) ---------

def _image(shape=(200, 220)):
    return np.random.default_rng(1).normal(100.0, 5.0, shape)


def _mask_image(**kwargs):
    from inject import mask_image
    return mask_image(_image(), **kwargs)


def _write_masked_bad_streaks(tmp_path):
    from inject.masking import write_masked

    path = tmp_path / "in.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(_image().astype(np.float32), name="IMAGE"),
                  fits.ImageHDU(np.zeros((200, 220), np.int32), name="MASK")]).writeto(path)
    return write_masked(path, tmp_path / "out.fits", [{"angle_deg": 3.0}])


# Wrong types in the Python API: each gives an InputError naming the argument.
API_BAD_TYPES = {
    "shape type a list": (lambda: shape_from_dict({"type": ["box"]}), "shape.type=['box']"),
    "shape type a mapping": (lambda: shape_from_dict({"type": {"box": 1}}), "shape.type="),
    "seeing a string": (lambda: Seeing("good"), "seeing='good'"),
    "seeing an array": (lambda: Seeing(np.array([0.7, 0.8])), "seeing="),
    "model without a shape": (lambda: StreakModel(550.0, shape=None), "shape=None"),
    "seeing a number": (lambda: StreakModel(550.0, seeing=0.7), "seeing=0.7: must be a Seeing"),
    "model without a telescope": (lambda: StreakModel(550.0, telescope=None), "telescope=None"),
    "band a list": (lambda: StreakModel(550.0, band_name=["g"]), "band=['g']"),
    "height an array": (lambda: StreakModel(np.array([550.0, 350.0])), "height_km=array"),
    "mag None": (lambda: StreakModel(550.0, mag=None), "mag=None: must be a number"),
    "segment start an array": (lambda: Segment(np.array([1.0, 2.0]), 0.0, 0.0, 1.0),
                               "x0=array"),
    "segment length None": (lambda: Segment(0.0, 0.0, 0.0, None), "length=None"),
    "polyline of scalars": (lambda: Polyline(1.0, 2.0), "polyline x=1.0"),
    "polyline of a 2-D array": (lambda: Polyline(np.zeros((2, 2)), [0.0, 1.0]), "polyline x="),
    "crossing of a 1-D shape": (lambda: Segment.crossing((5,), 1.0, 1.0, 0.0), "shape=(5,)"),
    "crossing of None": (lambda: Segment.crossing(None, 1.0, 1.0, 0.0), "shape=None"),
    "crossing at an array": (lambda: Segment.crossing((5, 5), [1.0, 2.0], 1.0, 0.0), "x0="),
    "clip to a 3-D shape": (lambda: Segment(0.0, 0.0, 0.0, 1.0).clip((2, 5, 5)), "shape="),
    "box length an array": (lambda: Box(np.array([1.0, 2.0]), 1.0), "length="),
    "composite parts a number": (lambda: Composite(5), "parts=5: must be a sequence of Part"),
    "composite parts not parts": (lambda: Composite([Disk(1.0)]), "parts=[Disk(radius=1.0)]"),
    "part without a shape": (lambda: Part(None), "shape=None"),
}


@pytest.mark.parametrize("name", list(API_BAD_TYPES))
def test_api_bad_types(name):
    call, needle = API_BAD_TYPES[name]
    with pytest.raises(InputError) as info:
        call()
    assert needle in str(info.value)


@pytest.mark.parametrize("value,reason", [
    (None, "must be a number"), ([1.0, None], "must be a number"), ("x", "must be a number"),
    (float("nan"), "must be finite"), ([1.0, float("inf")], "must be finite"),
])
def test_validate_finite_names_the_problem(value, reason):
    from inject.validate import finite

    with pytest.raises(InputError, match=reason):
        finite("v", value)


def test_validate_scalar_accepts_numpy_numbers():
    from inject.validate import finite, positive

    for value in (2, 2.0, np.float64(2.0), np.float32(2.0), np.int64(2), np.array(2.0)):
        assert type(finite("v", value, scalar=True)) is float
        assert positive("v", value, scalar=True) == 2.0
    with pytest.raises(InputError, match="single number"):
        finite("v", np.array([2.0]), scalar=True)
    with pytest.raises(InputError, match="must be a number"):
        finite("v", "2", scalar=True)


def test_api_accepts_numpy_numbers():
    model = StreakModel(np.float64(550.0), np.float32(10.0), np.int64(90),
                        Disk(np.float64(1.0)), mag=np.float64(5.0),
                        seeing=Seeing(np.float64(0.7)))
    assert model.summary()["height_km"] == 550.0
    segment = Segment.crossing(np.array([48, 64]), np.float64(1.0), np.int64(2),
                               np.float32(0.0))
    assert segment.length == 64.0 and segment.clip((np.int64(48), 64)) == (0.0, 64.0)
    assert Polyline(np.array([1.0, 2.0]), (np.float64(3.0), 4)).xs == (1.0, 2.0)


def _mask_image_of(image):
    from inject import mask_image
    return mask_image(image)


def _write_masked_missing_input(tmp_path):
    from inject.masking import write_masked

    (tmp_path / "out.fits").write_bytes(b"")
    return write_masked(tmp_path / "missing.fits", tmp_path / "out.fits", [], overwrite=True)


MASKING_BAD_INPUT = {
    "mask of another shape": (lambda tmp_path: _mask_image(mask=np.zeros((5, 5), bool)),
                              "mask="),
    "pixel scale a string": (lambda tmp_path: _mask_image(pixel_scale="fine"),
                             "--pixel-scale"),
    "masked streak without its line": (_write_masked_bad_streaks, "streaks\\[0\\]"),
    "complex image": (lambda tmp_path: _mask_image_of(np.zeros((200, 220), complex)), "image="),
    "missing input, existing output": (_write_masked_missing_input, "missing.fits"),
}


@pytest.mark.parametrize("name", list(MASKING_BAD_INPUT))
def test_masking_api_bad_input(tmp_path, name):
    call, match = MASKING_BAD_INPUT[name]
    with pytest.raises(InjectError, match=match):
        call(tmp_path)


def test_shape_type_a_list_on_the_command_line(cli, scene, tmp_path):
    status, _, err = cli("simulate", scene, "-o", tmp_path / "o.fits",
                      "satellites.0.shape.type=[box]")
    assert status == 2 and "shape.type=['box']" in err


def test_simulate_refuses_a_field_without_the_traced_pupil(cli, scene, tmp_path):
    """``field:`` only says where the CCD sits for ``pupil: rubin``, as ``inject profile``
    refuses ``--field-angle`` without ``--pupil rubin``."""
    out = tmp_path / "out.fits"
    status, _, err = cli("simulate", scene, "-o", out, "field={angle: 1.2}", strict=True)
    assert status == 2 and "field.angle=1.2: only with pupil: rubin" in err
    assert not out.exists() and not leftovers(tmp_path)
