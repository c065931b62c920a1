"""What the command line shows on stderr: -q (warnings and errors only), -v (debugging too),
the default reports; and the library, which logs and never prints."""
import ast
import json
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from inject.cli.main import main
from inject.exposure import runner

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "inject"

SAT = {"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}
#: Four 64 px cut-outs; the satellite crosses R22_S11 and R22_S12 (test_runner_reliability).
DETECTORS = ["R22_S11", "R22_S12", "R01_S00", "R43_S22"]
SCENE = {"seed": 11, "band": "g", "zenith": 70, "exptime": 30,
         "pointing": {"ra": 50.0, "dec": -30.0, "rotation": 10.0}, "stars": False,
         "cutout": {"nx": 64, "ny": 64}, "detectors": DETECTORS,
         "satellites": [dict(SAT, track={"x0_mm": -21.0, "y0_mm": -19.7, "angle": 0.4})]}


@pytest.fixture
def focalplane(tmp_path, monkeypatch, capsys):
    """``focalplane(*options)``: ``inject [options] focalplane`` on the four CCDs (threads, not
    processes); returns the exit status and stderr's lines."""
    scene = tmp_path / "scene.yaml"
    scene.write_text(json.dumps(SCENE))
    monkeypatch.setattr(runner, "process_pool", lambda workers=None: ThreadPoolExecutor(2))
    runs = iter(range(100))

    def run(*before, after=()):
        out = tmp_path / f"out{next(runs)}"
        status = main([*before, "focalplane", str(scene), "-o", str(out), "--no-mosaic",
                       *after])
        assert sorted(os.listdir(out)) == sorted(
            [f"{d}.fits" for d in DETECTORS] + ["manifest.csv", "satellites.csv"])
        return status, capsys.readouterr().err.splitlines()

    return run


def test_default_shows_progress_and_the_report(focalplane, tmp_path):
    status, lines = focalplane()
    assert status == 0
    progress = [line for line in lines if line.startswith("[")]
    assert len(progress) == len(DETECTORS)  # under ten CCDs: one line each
    assert progress[-1].startswith(f"[{len(DETECTORS)}/{len(DETECTORS)}] rendering CCDs: ")
    assert lines[-1] == f"{tmp_path / 'out0'}: 4 CCDs rendered, 0 already done, 0 failed"
    assert not any("debug" in line for line in lines)


@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_shows_nothing_on_success(focalplane, where):
    status, lines = focalplane("-q") if where == "before" else focalplane(after=["--quiet"])
    assert status == 0 and lines == []


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_shows_each_ccd(focalplane, where):
    status, lines = focalplane("-v") if where == "before" else focalplane(after=["--verbose"])
    assert status == 0
    debug = [line for line in lines
             if line.startswith("inject focalplane: debug: inject.exposure.runner: ")]
    assert sorted(line.split(": ")[3].split()[0] for line in debug) == sorted(DETECTORS)
    assert lines[-1].endswith("4 CCDs rendered, 0 already done, 0 failed")


def test_quiet_keeps_warnings_and_errors(tmp_path, capsys):
    """A satellite that reaches none of the CCDs is a warning; an existing output an error."""
    scene = tmp_path / "scene.yaml"
    scene.write_text(json.dumps(dict(SCENE, detectors=["R01_S00"])))
    out = tmp_path / "out"
    assert main(["-q", "focalplane", str(scene), "-o", str(out), "--no-mosaic",
                 "--workers", "1"]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"inject focalplane: warning: satellites[0]: renders on no CCD (why: "
        f"{out / 'satellites.csv'})"]
    assert main(["-q", "focalplane", str(tmp_path / "missing.yaml"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("inject focalplane: error: ")


def test_quiet_and_verbose_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", "profile", "--height", "550", "-v"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["inject profile: error: argument -v/--verbose: not allowed with argument "
                   "-q/--quiet"]


def test_the_command_leaves_logging_as_it_found_it(focalplane):
    logger = logging.getLogger("inject")
    handlers, level = list(logger.handlers), logger.level
    focalplane("-v")
    assert logger.handlers == handlers and logger.level == level


# -- The library logs; only the command line's entry point prints to stderr -----------------

def _prints(path):
    """``(line, writes to stderr)`` of each print() call and sys.stderr.write() in a file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id == "print":
            to = next((k.value for k in node.keywords if k.arg == "file"), None)
            found.append((node.lineno, to is not None and "stderr" in ast.unparse(to)))
        elif isinstance(func, ast.Attribute) and ast.unparse(func) == "sys.stderr.write":
            found.append((node.lineno, True))
    return found


def test_the_library_never_prints():
    """Outside inject/cli no print() at all; inside it, print() is the commands' output on
    stdout, and only the entry point (inject/cli/main.py: usage and error lines) and the
    log handler (inject/cli/logs.py) write to stderr."""
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(ROOT).as_posix()
        in_cli = relative.startswith("inject/cli/")
        for line, stderr in _prints(path):
            if not in_cli or (stderr and relative not in ("inject/cli/main.py",
                                                           "inject/cli/logs.py")):
                offenders.append(f"{relative}:{line}")
    assert offenders == []


def test_the_scan_sees_prints(tmp_path):
    """The scan itself: it finds a bare print and one to stderr."""
    sample = tmp_path / "sample.py"
    sample.write_text("import sys\nprint('a')\nprint('b', file=sys.stderr)\n"
                      "sys.stderr.write('c')\n")
    assert _prints(sample) == [(2, False), (3, True), (4, True)]
