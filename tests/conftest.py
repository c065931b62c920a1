"""Fixtures shared by the test files: the command line, file digests and small scenes."""
import hashlib
import os
import re

import pytest

from inject import DEFAULT_SCENE, apply_overrides, parse_scene
from inject.cli.main import main


@pytest.fixture
def cheap_grid(monkeypatch):
    """``pupil: rubin``'s grid kernels of few rays (40 000) and wavelengths (2), in memory
    only: for tests of where a kernel goes, not of its accuracy."""
    from inject import optics

    monkeypatch.setenv("INJECT_CACHE_DIR", "")
    monkeypatch.setattr(optics, "GRID_RAYS", 40_000)
    monkeypatch.setattr(optics, "N_WAVELENGTHS", 2)
    optics._grid_kernel.cache_clear()
    yield
    optics._grid_kernel.cache_clear()


@pytest.fixture
def no_lumos(monkeypatch):
    """A process without lumos-sat: importing it (or any of its modules) fails."""
    import builtins

    real = builtins.__import__

    def refuse(name, *args, **kwargs):
        if name == "lumos" or name.startswith("lumos."):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", refuse)


@pytest.fixture(scope="session")
def skyfield_timescale(tmp_path_factory):
    """A skyfield timescale on the IERS table astropy ships (UT1 and polar motion, as inject's
    frames take them; nothing downloaded)."""
    api = pytest.importorskip("skyfield.api")
    import shutil

    import astropy_iers_data
    from skyfield.data import iers

    folder = tmp_path_factory.mktemp("skyfield")
    shutil.copy(astropy_iers_data.IERS_A_FILE, os.path.join(folder, "finals2000A.all"))
    load = api.Loader(str(folder), verbose=False)
    scale = load.timescale(builtin=False)
    with load.open("finals2000A.all") as f:
        iers.install_polar_motion_table(scale, iers.parse_x_y_dut1_from_finals_all(f))
    return scale


def _sha256(path):
    with open(path, "rb") as stream:
        return hashlib.sha256(stream.read()).hexdigest()


@pytest.fixture(autouse=True, scope="session")
def kernel_cache(tmp_path_factory):
    """Traced kernels (``pupil: rubin``) go to a folder of the test session, not the user's
    cache: the tests trace the kernels they use (and the commands they run inherit it)."""
    folder = tmp_path_factory.mktemp("kernel-cache")
    old = os.environ.get("INJECT_CACHE_DIR")
    os.environ["INJECT_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("INJECT_CACHE_DIR", None)
    else:
        os.environ["INJECT_CACHE_DIR"] = old


@pytest.fixture
def digest():
    """``digest(path)``: SHA-256 of a file's bytes (hex), to tell whether a file changed."""
    return _sha256


@pytest.fixture
def cli(capsys):
    """``cli(command, *args)``: run ``inject`` in-process; return ``(status, out, err)``.

    A failure must end in one clean line, ``inject <command>: error: ...``, after nothing but
    one-line warnings, progress lines and the run's workers (``inject <command>: N workers
    (bound by ...)``), no traceback; ``strict=True`` allows nothing before it.
    """
    def run(*argv, strict=False):
        status = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        if status != 0:
            lines = err.splitlines()
            assert "Traceback" not in err, err
            assert lines and lines[-1].startswith(f"inject {argv[0]}: error: "), err
            if strict:
                assert len(lines) == 1, err
            else:
                assert all(line.startswith((f"inject {argv[0]}: warning: ", "["))
                           or re.match(rf"inject {argv[0]}( --render)?: \d+ workers? \(bound "
                                       r"by ", line)
                           for line in lines[:-1]), err
        return status, out, err

    return run


@pytest.fixture
def small_scene():
    """``small_scene(*overrides, nx=256, ny=256)``: the default scene on a cut-out of the CCD,
    with ``key.path=value`` overrides, parsed."""
    def build(*overrides, nx=256, ny=256):
        return parse_scene(apply_overrides(
            DEFAULT_SCENE, [f"detector.nx={nx}", f"detector.ny={ny}", *overrides]))

    return build
