"""Progress of long loops (inject.progress): a line per tenth of the work where no bar can be
drawn, a bar on a terminal, nothing under -q or below INFO."""
import io
import logging
import os
import subprocess
import sys

import pytest

from inject import progress as progress_module
from inject.progress import Progress

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: A loop of ``N`` items reported under the command line's logging, in a fresh interpreter
#: whose stderr is a pipe (as in a batch job's log): argv[1] is the level, argv[2] N.
LOOP = """
import logging, sys
from inject.cli.logs import command_logging
from inject.progress import Progress
with command_logging("inject test", int(sys.argv[1])):
    with Progress(int(sys.argv[2]), "rendering CCDs", "CCD",
                  logging.getLogger("inject.test")) as progress:
        for k in range(int(sys.argv[2])):
            progress.update(f"item {k + 1}")
"""


def _loop(level, n):
    run = subprocess.run([sys.executable, "-c", LOOP, str(level), str(n)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, check=True,
                         env=dict(os.environ, PYTHONPATH=ROOT))
    return run.stderr.splitlines()


def test_a_pipe_gets_a_line_per_tenth_not_one_per_item():
    """189 CCDs, as a whole focal plane: before, 189 lines in a log or a notebook."""
    lines = _loop(logging.INFO, 189)
    assert len(lines) == 10
    # Each line is the first item past a tenth of 189: ceil(189 k / 10).
    assert [line.split("]")[0] + "]" for line in lines] == [
        f"[{-(-189 * k // 10)}/189]" for k in range(1, 11)]
    assert lines[-1] == "[189/189] rendering CCDs: item 189"


@pytest.mark.parametrize("n", [1, 4, 9])
def test_a_short_loop_reports_each_item(n):
    assert _loop(logging.INFO, n) == [f"[{k}/{n}] rendering CCDs: item {k}"
                                      for k in range(1, n + 1)]


def test_quiet_shows_no_progress():
    assert _loop(logging.WARNING, 189) == []


def test_below_info_the_library_reports_nothing(capsys, caplog):
    """A program that has not asked for INFO (logging's default is WARNING) gets no lines."""
    caplog.set_level(logging.WARNING, logger="inject")
    with Progress(50, "rendering streaks", "streak", logging.getLogger("inject.x")) as p:
        for _ in range(50):
            p.update()
    assert caplog.records == [] and capsys.readouterr().err == ""


def test_disabled_progress_is_silent(caplog):
    caplog.set_level(logging.INFO, logger="inject")
    with Progress(30, "rendering streaks", "streak", logging.getLogger("inject.x"),
                  enabled=False) as p:
        for _ in range(30):
            p.update()
    assert caplog.records == []


def test_a_terminal_gets_a_bar_and_no_lines(monkeypatch, caplog):
    pytest.importorskip("tqdm")
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    monkeypatch.setattr(progress_module, "_stderr_is_terminal", lambda: True)
    caplog.set_level(logging.INFO, logger="inject")
    with Progress(40, "rendering CCDs", "CCD", logging.getLogger("inject.x")) as p:
        for _ in range(40):
            p.update("R22_S11 done")
    assert caplog.records == []  # the bar, not the lines
    text = stream.getvalue()
    assert "rendering CCDs" in text and "40/40" in text and "R22_S11 done" in text


def test_no_notebook_outside_a_kernel():
    assert progress_module.in_notebook() is False
