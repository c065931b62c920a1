"""Every scene quantity and CLI option has a range checked before any work (refused outside,
warned where implausible), a memory estimate refuses what cannot fit, duplicate YAML keys are
refused, and the failures that used to be tracebacks are one line."""
import math
import os
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

import inject.validate as validate
from inject import (
    DEFAULT_SCENE,
    RANGES,
    InputError,
    InputWarning,
    ResourceError,
    SceneError,
    apply_overrides,
    load_scene_file,
    parse_scene,
)
from inject.cli.main import main
from inject.validate import check

SMALL = ["detector.nx=64", "detector.ny=64", "stars=false"]


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if a scene is simulated: the checks must come first."""
    import inject.scene

    def simulate(*args, **kwargs):
        raise AssertionError("simulated before the input was checked")
    monkeypatch.setattr(inject.scene, "simulate", simulate)


# --- The table itself ----------------------------------------------------------------------

@pytest.mark.parametrize("name", list(RANGES))
def test_bounds_are_where_the_table_says(name):
    r = RANGES[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        for bound, is_open, step in ((r.lo, r.lo_open, -1), (r.hi, r.hi_open, 1)):
            if math.isinf(bound):
                continue
            if is_open:
                with pytest.raises(InputError, match=re.escape(r.bounds())):
                    r.check(bound)
            else:
                assert r.check(bound) == bound
            beyond = bound + step * max(1.0, abs(bound)) * 1e-3 if not r.integer \
                else bound + step
            with pytest.raises(InputError, match=re.escape(f"{name}=")):
                r.check(beyond)
    for bad in (float("nan"), float("inf"), "7", None, True):
        with pytest.raises(InputError):
            r.check(bad)


def test_plausible_range_warns_and_keeps_the_value():
    r = RANGES["height"]
    with pytest.warns(InputWarning, match="beyond the Moon"):
        assert r.check(1e6, "--height") == 1e6
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert r.check(550.0) == 550.0  # inside both ranges: silent


def test_integers_must_be_whole():
    with pytest.raises(InputError, match="whole number"):
        check("seed", 2.5)
    assert check("seed", 7.0) == 7 and type(check("seed", 7.0)) is int


def test_the_documented_table_has_every_range():
    """The docs' input-ranges page is this table: one row per RANGES entry, with its bounds."""
    table = validate.ranges_markdown().splitlines()
    assert len(table) == 2 + len(validate.RANGES)
    for line, r in zip(table[2:], validate.RANGES.values()):
        assert line.startswith(f"| `{r.name}` |") and r.bounds().replace("|", "\\|") in line


# --- Scenes: refused before any work, naming the value -------------------------------------

@pytest.mark.parametrize("override,needle", [
    ("cosmic_rays=1e12", "cosmic_rays=1000000000000.0: must be >= 0 and <= 100"),
    ("exptime=1e30", "exptime=1e+30: must be > 0 and <= 3600 s"),
    ("dark_current=1e25", "dark_current=1e+25: must be >= 0 and <= 10000"),
    ("detector.nx=100000", "detector.nx=100000: must be >= 1 and <= 4096"),
    ("detector.ny=4001", "detector.ny=4001: must be <= 4000 px (the itl sensor"),
    ("detector.gains=0", "detector.gains=0.0: must be > 0"),
    ("detector.read_noise=1e6", "detector.read_noise=1000000.0"),
    ("detector.bias=-3", "detector.bias=-3.0"),
    ("detector.full_well=1e12", "detector.full_well=1000000000000.0"),
    ("sky.level=1e12", "sky.level=1000000000000.0"),
    ("sky.mag=-40", "sky.mag=-40.0"),
    ("stars.mag_limit=45", "stars.mag_limit=45.0"),
    ("stars.density_per_deg2=1e12", "stars.density_per_deg2=1000000000000.0"),
    ("stars.galactic_b=91", "stars.galactic_b=91.0"),
    ("pointing.ra=400", "pointing.ra=400.0"),
    ("pointing.dec=-91", "pointing.dec=-91.0"),
    ("seed=1e30", "seed="),
    ("seeing=31", "seeing=31.0"),
    ("satellites.0.height=50", "satellites[0].height=50.0: must be >= 100 km"),
    ("satellites.0.mag=-50", "satellites[0].mag=-50.0: must be >= -30"),
    ("satellites.0.ref_range=1e9", "satellites[0].ref_range=1000000000.0"),
    ("satellites.0.shape.length=500", "satellites[0].shape size=500.007: must be > 0 and <= 200"),
    ("satellites.0.track.x0=1e300", "satellites[0].track.x0=1e+300"),
    ("satellites.0.track.length=1e12", "satellites[0].track.length=1000000000000.0"),
    # Inside every range, but the brightest pixel would hold more than can be drawn.
    ("satellites.0.mag=-29", "expected charge per pixel from satellites[0]="),
])
def test_scene_ranges(cli, tmp_path, no_work, override, needle):
    status, _, err = cli("simulate", "sample_fields/default.yaml", "-o",
                      tmp_path / "x.fits", *SMALL, override)
    assert status == 2 and needle in err, err
    assert os.listdir(tmp_path) == []


def test_polyline_vertices_are_checked():
    raw = apply_overrides(DEFAULT_SCENE, SMALL)
    raw["satellites"][0]["track"] = {"vertices": [{"x": 0, "y": 0}, {"x": 5e6, "y": 10}]}
    with pytest.raises(SceneError, match=r"vertices\[1\]\.x=5000000\.0"):
        parse_scene(raw)
    raw["satellites"][0]["track"] = {"vertices": [{"x": 0, "y": 0}, {"x": 50, "y": 10,
                                                                     "mag": -80}]}
    with pytest.raises(SceneError, match=r"vertices\[1\]\.mag=-80\.0"):
        parse_scene(raw)


def test_composite_parts_are_checked():
    raw = apply_overrides(DEFAULT_SCENE, SMALL)
    raw["satellites"][0]["shape"] = {"type": "composite", "parts": [
        {"type": "box", "length": 2, "width": 1},
        {"type": "disk", "radius": 1, "dx": 150, "reflectance": 0.5}]}
    with pytest.raises(SceneError, match=r"satellites\[0\]\.shape size=302\.0: must be > 0"):
        parse_scene(raw)  # the span, offsets included: 2 x 150 + 2 m
    raw["satellites"][0]["shape"]["parts"][1].update(dx=3, reflectance=1e9)
    with pytest.raises(SceneError, match=r"parts\[1\]\.reflectance=1000000000\.0"):
        parse_scene(raw)


def test_extreme_but_plausible_scene_is_accepted_silently():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = parse_scene(apply_overrides(DEFAULT_SCENE, [
            "exptime=3600", "cosmic_rays=5", "dark_current=0.5", "detector.type=e2v",
            "detector.nx=4096", "detector.ny=4004", "satellites.0.height=36000"]))
    assert scene.detector.shape == (4004, 4096)


def test_implausible_scene_values_warn(recwarn):
    parse_scene(apply_overrides(DEFAULT_SCENE, SMALL + ["satellites.0.height=1e6",
                                                        "cosmic_rays=50"]))
    messages = [str(w.message) for w in recwarn if w.category is InputWarning]
    assert any("satellites[0].height=1000000.0: beyond the Moon" in m for m in messages)
    assert any("cosmic_rays=50.0" in m for m in messages)


def test_cli_warnings_are_one_line(capsys, tmp_path):
    status = main(["simulate", "sample_fields/default.yaml", "-o", str(tmp_path / "x.fits"),
                   *SMALL, "cosmic_rays=20"])
    err = capsys.readouterr().err
    assert status == 0
    assert err.startswith("inject simulate: warning: cosmic_rays=20.0: imSim uses")
    assert "InputWarning" not in err and "warnings.warn" not in err


# --- Memory --------------------------------------------------------------------------------

def test_memory_estimate_refuses_what_cannot_fit(monkeypatch):
    raw = apply_overrides(DEFAULT_SCENE, ["detector.nx=4072", "detector.ny=4000"])
    monkeypatch.setattr(validate, "available_memory", lambda: 200 * 2 ** 20)  # a small machine
    with pytest.raises(ResourceError, match=r"detector 4072 x 4000: needs about 0\.971 GiB of "
                                            r"memory, 0\.195 GiB available"):
        parse_scene(raw)
    assert parse_scene(apply_overrides(raw, SMALL)).detector.shape == (64, 64)
    monkeypatch.setattr(validate, "available_memory", lambda: None)  # unknown: not refused
    assert parse_scene(raw).detector.shape == (4000, 4072)


def test_available_memory_is_read():
    free = validate.available_memory()
    assert free is None or 0 < free < 2 ** 50


@pytest.mark.slow
def test_memory_estimate_covers_the_measured_peak(tmp_path):
    """Peak RSS of ``inject simulate`` with every output, 64 px against 1536 px square: the
    growth per pixel is below the estimate's bytes per pixel."""
    from inject.config import SIMULATE_BYTES_PER_PIXEL
    code = ("import resource, sys; from inject.cli.main import main; main(sys.argv[1:]); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")

    def peak(n):
        out = subprocess.run(
            [sys.executable, "-c", code, "simulate", "sample_fields/default.yaml", "-o",
             str(tmp_path / f"{n}.fits"), "--exr", str(tmp_path / f"{n}.exr"), "--png",
             str(tmp_path / f"{n}.png"), f"detector.nx={n}", f"detector.ny={n}"],
            capture_output=True, text=True, check=True)
        return int(out.stdout.split()[-1]) * 1024  # KiB on Linux
    per_pixel = (peak(1536) - peak(64)) / (1536 ** 2 - 64 ** 2)
    assert 10 < per_pixel < SIMULATE_BYTES_PER_PIXEL


# --- Scene files ---------------------------------------------------------------------------

@pytest.mark.parametrize("text,line", [
    ("seed: 1\nexptime: 30\nseed: 2\n", "line 3: key 'seed' given twice (first at line 1)"),
    ("detector:\n  nx: 64\n  nx: 128\n", "line 3: key 'nx' given twice (first at line 2)"),
    ("satellites:\n  - {height: 550, mag: 5, mag: 6}\n", "line 2: key 'mag' given twice"),
])
def test_duplicate_yaml_keys_are_refused(tmp_path, text, line):
    path = tmp_path / "s.yaml"
    path.write_text(text)
    with pytest.raises(SceneError, match=re.escape(f"{path}: {line}")):
        load_scene_file(path)


def test_yaml_merge_keys_may_still_override(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("sky: &dark {mag: 22.0}\ndetector:\n  <<: {type: itl, nx: 64}\n  nx: 32\n")
    assert load_scene_file(path)["detector"] == {"type": "itl", "nx": 32}


# --- profile and add-streak options --------------------------------------------------------

@pytest.mark.parametrize("argv,needle", [
    (["--height", "50"], "--height=50.0: must be >= 100 km"),
    (["--height", "550", "--mag", "-50"], "--mag=-50.0: must be >= -30 and <= 100 AB mag"),
    (["--height", "550", "--pixel-scale", "1e-4"], "--pixel-scale=0.0001"),
    (["--height", "550", "--length", "300"], "--length/--width (largest extent, m)=300.012"),
    (["--height", "550", "--shape", "disk", "--radius", "150"], "--radius (largest extent"),
    (["--height", "550", "--ref-range", "1e8"], "--ref-range=100000000.0"),
    (["--height", "550", "--seeing", "40"], "seeing=40.0"),
])
def test_profile_ranges(cli, argv, needle):
    status, _, err = cli("profile", *argv)
    assert status == 2 and needle in err, err


def test_profile_warns_on_implausible_values(capsys):
    status = main(["profile", "--height", "1e9", "--mag", "-20"])
    err = capsys.readouterr().err.splitlines()
    assert status == 0
    assert err[0].startswith("inject profile: warning: --height=1000000000.0: beyond the Moon")
    assert err[1].startswith("inject profile: warning: --mag=-20.0: brighter than any")


def test_profile_prints_inputs_with_every_digit(capsys):
    assert main(["profile", "--height", "550.25", "--zenith", "89.999999"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"zenith angle\s+89\.999999 ", out)
    assert re.search(r"orbit height\s+550\.25 ", out)


@pytest.mark.parametrize("argv,needle", [
    (["--x0", "1e9", "--y0", "3"], "--x0=1000000000.0"),
    (["--x0", "3", "--y0", "3", "--track-length", "-1"], "--track-length=-1.0"),
    (["--x0", "3", "--y0", "3", "--gain", "0"], "--gain=0.0: must be > 0"),
    (["--x0", "3", "--y0", "3", "--seed", "0"], "--seed=0: must be >= 1"),
    (["--x0", "3", "--y0", "3", "--height", "20"], "--height=20.0"),
])
def test_add_streak_ranges(cli, tmp_path, argv, needle):
    from astropy.io import fits

    image = tmp_path / "in.fits"
    fits.PrimaryHDU(np.zeros((20, 30), np.float32)).writeto(image)
    argv = ["add-streak", image, "-o", tmp_path / "out.fits", "--height", "550", "--gain", "1",
            *argv]
    status, _, err = cli(*argv)
    assert status == 2 and needle in err, err
    assert sorted(os.listdir(tmp_path)) == ["in.fits"]


# --- One line instead of a traceback -------------------------------------------------------

@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc and /sys")
@pytest.mark.parametrize("folder", ["/proc", "/sys", "/sys/kernel"])
def test_outputs_under_proc_and_sys(cli, no_work, folder):
    status, _, err = cli("simulate", "sample_fields/default.yaml", "-o",
                      f"{folder}/x.fits", *SMALL)
    assert status == 2 and f"{folder}/x.fits" in err


def test_profile_into_a_closed_pipe_ends_quietly():
    """``inject profile --json | head -c 20``: the status of a process killed by SIGPIPE (as
    ``yes | head`` gives) and nothing on stderr."""
    reader = subprocess.Popen(["head", "-c", "20"], stdin=subprocess.PIPE,
                              stdout=subprocess.DEVNULL)
    writer = subprocess.run([sys.executable, "-m", "inject", "profile", "--height", "550",
                             "--json"], stdout=reader.stdin, stderr=subprocess.PIPE)
    reader.stdin.close()
    reader.wait()
    assert writer.returncode == 141 and writer.stderr == b""


def test_traceback_after_the_subcommand():
    with pytest.raises(InputError, match="height_km=-5.0"):
        main(["profile", "--height", "-5", "--traceback"])
    with pytest.raises(InputError, match="height_km=-5.0"):
        main(["--traceback", "profile", "--height", "-5"])


@pytest.mark.parametrize("name,magic", [("q.jpg", b"\xff\xd8\xff"), ("q.JPEG", b"\xff\xd8\xff"),
                                        ("q.pdf", b"%PDF"), ("q.other", b"\x89PNG")])
def test_quicklook_format_follows_the_name(capsys, tmp_path, name, magic):
    assert main(["simulate", "sample_fields/default.yaml", "-o", str(tmp_path / "x.fits"),
                 "--png", str(tmp_path / name), *SMALL]) == 0
    assert (tmp_path / name).read_bytes().startswith(magic)


def test_quicklook_under_a_data_name_is_refused_first(cli, tmp_path, no_work):
    status, _, err = cli("simulate", "sample_fields/default.yaml", "-o",
                      tmp_path / "x.fits", "--png", tmp_path / "q.fits", *SMALL)
    assert status == 2 and "q.fits: a quicklook is a picture, not FITS data" in err
    assert os.listdir(tmp_path) == []


# --- inject evaluate ------------------------------------------------------------------------

EVALUATE = ["--seeds", "1", "--mags", "11", "--heights", "550", "--streak-free", "0",
            "--detector", "64"]


def test_evaluate_names_the_failing_masker_and_image(cli, tmp_path):
    out = tmp_path / "new" / "campaign"
    status, _, err = cli("evaluate", "-o", out, "--masker", "os.path:join", *EVALUATE)
    assert status == 2
    assert "masker os.path:join failed on image 1 (550 km, mag 11.00, seed 1): TypeError" in err
    assert os.listdir(tmp_path) == []  # neither folder is left behind


def test_evaluate_keeps_a_folder_it_did_not_make(cli, tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    status, _, _ = cli("evaluate", "--out", tmp_path, "--masker", "os.path:join", *EVALUATE)
    assert status == 2 and os.listdir(tmp_path) == ["notes.txt"]


def test_evaluate_checks_optional_maskers_before_simulating(cli, tmp_path, monkeypatch):
    import inject.cli.evaluate as cli_evaluate
    import inject.masking.external as external
    from inject import MaskingError
    def missing():
        raise MaskingError("the findsat_mrt masker needs acstools and photutils")
    monkeypatch.setattr(external, "trail_finder", missing)

    def images(*args, **kwargs):
        raise AssertionError("an image was simulated before the maskers were checked")
    monkeypatch.setattr(cli_evaluate, "campaign_images", images)
    out = tmp_path / "campaign"
    status, _, err = cli("evaluate", "--out", out, "--masker", "inject", "--masker",
                      "findsat_mrt", *EVALUATE)
    assert status == 2 and "needs acstools" in err
    assert not out.exists()


def test_masker_returning_a_wrong_shape_is_one_line(cli, tmp_path):
    status, _, err = cli("evaluate", "--out", tmp_path / "c", "--masker",
                      "numpy:ravel", *EVALUATE)
    assert status == 2 and "masker numpy:ravel" in err and "returned a mask of shape" in err


def test_evaluate_seeds_stay_clear_of_the_streak_free_seeds(cli, tmp_path):
    """The streak-free images use seeds 1001 on: a campaign of more seeds would reuse them."""
    from inject.cli.evaluate import STREAK_FREE_SEED0

    out = tmp_path / "campaign"
    status, _, err = cli("evaluate", "-o", out, "--seeds", STREAK_FREE_SEED0 + 1,
                      "--mags", "11", "--heights", "550", "--detector", "64")
    assert status == 2 and "--seeds" in err and not out.exists()
