"""The command line answers --help and a bad option before it imports the engine: no GalSim,
astropy or (for --help) NumPy, each checked in a fresh interpreter."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Runs ``main(argv)`` and prints which of the heavy libraries were imported by then.
CODE = """
import sys
from inject.cli.main import main
try:
    status = main(sys.argv[1:])
except SystemExit as stop:
    status = stop.code
heavy = ("galsim", "astropy", "scipy", "batoid", "cv2", "matplotlib", "numpy")
print("imported:", *(m for m in heavy if m in sys.modules))
sys.exit(status)
"""


def _inject(*argv, cwd):
    """Exit status, the heavy modules imported, the help printed and stderr's lines of
    ``inject ARGV`` run in ``cwd`` (this checkout's package)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = subprocess.run([sys.executable, "-c", CODE, *argv], capture_output=True, text=True,
                         cwd=cwd, env=env)
    *printed, imported = run.stdout.splitlines()
    assert imported.startswith("imported:")
    return run.returncode, imported.split()[1:], printed, run.stderr.splitlines()


@pytest.mark.parametrize("argv, message", [
    (["survey", "night.csv", "-o", "out", "--constellation", "c.yaml", "--workers", "0"],
     "inject survey: error: --workers=0: must be >= 1"),
    (["survey", "night.csv", "-o", "out", "--constellation", "c.yaml", "--job", "2",
      "--njobs", "2"], "inject survey: error: --job=2: must be in 0 .. 1"),
    (["survey", "night.csv", "-o", "out", "--constellation", "c.yaml", "--render",
      "--cutout-size", "64"], "inject survey: error: --cutout-size=64: only with --cutouts"),
    (["focalplane", "scene.yaml", "-o", "out", "--workers", "0"],
     "inject focalplane: error: --workers=0: must be >= 1"),
    (["focalplane", "scene.yaml", "-o", "out", "--retries", "-1"],
     "inject focalplane: error: --retries=-1: must be >= 0"),
    (["focalplane", "scene.yaml", "-o", "out", "--job", "3", "--njobs", "2"],
     "inject focalplane: error: --job=3: must be in [0, 1] (0-based)"),
    (["mask", "image.fits", "--max-streaks", "0"],
     "inject mask: error: --max-streaks=0: must be an integer >= 1"),
    (["evaluate", "-o", "out", "--seeds", "0"], "inject evaluate: error: --seeds=0: must be >= 1"),
    (["survey", "night.csv", "-o", "out", "--constellation", "c.yaml", "--workers", "two"],
     "inject survey: error: argument --workers: invalid int value: 'two'"),
])
def test_a_bad_option_is_answered_before_the_engine_is_imported(tmp_path, argv, message):
    """None of the files named exist: the option is refused first, exit status 2."""
    status, imported, _, err = _inject(*argv, cwd=tmp_path)
    assert status == 2 and err == [message]
    assert "galsim" not in imported and "astropy" not in imported
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize("argv", [["--help"], ["survey", "--help"], ["focalplane", "--help"]])
def test_help_imports_no_numerical_library(tmp_path, argv):
    status, imported, printed, err = _inject(*argv, cwd=tmp_path)
    assert status == 0 and err == [] and printed[0].startswith("usage: inject")
    assert imported == []
