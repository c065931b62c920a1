"""``inject survey --render`` on the focal plane's runner: another run taking a visit's folder,
a CCD failing on its input, a second render into the same OUTDIR, and a stop mid-render
behave as they do in ``inject focalplane``. The night of tests/test_survey_render.py (one
satellite over nine CCDs of visit 1), rendered as 64 px cut-outs."""
import os
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
from test_focalplane_run import _wait_for
from test_runner_reliability import _Between
from test_survey_render import _night, _run

import inject
from inject.camera import layout as fp
from inject.errors import InputError
from inject.exposure import runner

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SMALL = ("--cutout-size", "64")


def _pools(monkeypatch, *pools):
    """The command's process pools, in order, replaced by ``pools``."""
    queue = iter(pools)
    monkeypatch.setattr(runner, "process_pool", lambda workers=None: next(queue))


def _counting(monkeypatch, calls, fail=None):
    """runner.render_ccd, counting its calls (and raising ``fail`` instead of rendering)."""
    real = runner.render_ccd

    def render(task):
        calls.append(task.detector)
        if fail is not None:
            raise fail
        return real(task)

    monkeypatch.setattr(runner, "render_ccd", render)


def _temporaries(out):
    return sorted(os.path.join(d, n) for d, _, names in os.walk(out) for n in names
                  if n.startswith(".inject-"))


def test_a_visit_folder_taken_by_another_run_stops_the_render_with_one_line(
        tmp_path, monkeypatch, capsys):
    """Before: each CCD's commit raised, was retried twice as a machine's fault and reported
    failed, and the command ended with 'N of N CCDs failed'."""
    db, const = _night(tmp_path)
    out = tmp_path / "out"
    folder = out / "visits" / "1"
    other = "f" * 64
    ccd = fp.CCDS[0]

    def take_over():  # another run (--overwrite) takes the folder
        runner.update_manifest(str(folder), [{
            "detector": ccd.name, "id": ccd.id, "vendor": ccd.vendor, "status": "pending",
            "scene_sha256": other, "inject_version": inject.__version__}])

    calls = []
    _counting(monkeypatch, calls)
    pool = _Between(take_over)
    _pools(monkeypatch, pool)
    assert _run(db, const, out, *SMALL) == 2
    pool.shutdown(wait=True)
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"inject survey: error: {folder}: the run of scene {other[:12]} "
                       "(1 pending) has taken this directory since this run began; this run "
                       "stopped and left that run's files as they are")
    assert calls and len(calls) == len(set(calls))  # none retried
    rows = runner.read_manifest(str(folder))
    assert "failed" not in {r["status"] for r in rows.values()}
    assert not [n for n in os.listdir(folder) if n.endswith(".fits")]


BAD = InputError("satellites[0].mag", 99.5, "must be <= 30")


def test_a_ccd_failing_on_its_input_is_failed_at_once(tmp_path, monkeypatch, capsys):
    db, const = _night(tmp_path)
    out = tmp_path / "out"
    calls = []
    _counting(monkeypatch, calls, fail=BAD)
    _pools(monkeypatch, ThreadPoolExecutor(2))
    assert _run(db, const, out, *SMALL) == 2
    rows = runner.read_manifest(str(out / "visits" / "1"))
    assert sorted(calls) == sorted(rows) and len(rows) >= 5  # each CCD once
    assert {(r["status"], r["error"]) for r in rows.values()} == {("failed", str(BAD))}
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"inject survey: error: {len(rows)} of {len(rows)} CCDs failed "
                           f"(visit 1 ")
    assert f": {BAD}); " in last


def test_a_second_render_into_the_outdir_is_refused_before_any_work(tmp_path, monkeypatch,
                                                                     capsys):
    """Another render (other options) started while the first renders. Before: both
    rendered every CCD, and the first to commit made the other's CCDs fail at the end."""
    db, const = _night(tmp_path)
    out = tmp_path / "out"
    calls, second = [], []

    def render_again():
        before = len(calls)
        second.append(_run(db, const, out, *SMALL, "--compression", "lossy"))
        second.append(capsys.readouterr().err.strip().splitlines())
        second.append(len(calls) - before)

    # The first run's CCDs fail at once (quick): what matters is that the second rendered none.
    _counting(monkeypatch, calls, fail=BAD)
    _pools(monkeypatch, _Between(render_again), ThreadPoolExecutor(2))
    assert _run(db, const, out, *SMALL) == 2
    status, err, rendered = second
    assert status == 2 and rendered == 0
    assert err[-1].startswith("inject survey: error: ") and "pass --overwrite" in err[-1]
    rows = runner.read_manifest(str(out / "visits" / "1"))
    assert sorted(calls) == sorted(rows)  # the first run's, each once
    assert {r["status"] for r in rows.values()} == {"failed"}


#: Imported by the workers' fork server: the masker waits (up to 15 s) once each CCD's file
#: is written, and says so in a file named for its process.
_BLOCKER = """
import os, time
from inject.masking import run

_analyse = run.analyse


def analyse(*args, **kwargs):
    open(os.path.join({marks!r}, str(os.getpid())), "w").close()
    for _ in range(300):
        time.sleep(0.05)
    return _analyse(*args, **kwargs)


run.analyse = analyse
"""

#: The command, its workers' fork server importing ``blocker`` (from PYTHONPATH: the server
#: does not take the caller's sys.path).
_STOPPED = """
import sys
from inject.exposure import runner
from inject.cli.main import main
runner.WORKER_MODULES = (*runner.WORKER_MODULES, "blocker")
sys.exit(main(["survey", {db!r}, "-o", {out!r}, "--constellation", {const!r}, "--no-plots",
               "--render", "--cutouts", "--cutout-size", "64", "--workers", "2"]))
"""


@pytest.mark.slow  # ~30 s: a command in a process of its own, then the rerun
def test_a_stop_leaves_no_part_file_and_a_rerun_finishes(tmp_path):
    """SIGTERM while two CCDs' files are written and being masked. Before: the workers died
    with their part files (up to 60 MB each), which the rerun within 60 s kept."""
    db, const = _night(tmp_path)
    out = tmp_path / "out"
    marks = tmp_path / "started"
    marks.mkdir()
    (tmp_path / "blocker.py").write_text(_BLOCKER.format(marks=str(marks)))
    code = _STOPPED.format(db=str(db), out=str(out), const=str(const))
    path = os.pathsep.join(p for p in (str(tmp_path), os.environ.get("PYTHONPATH")) if p)
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True,
                            env=dict(os.environ, PYTHONPATH=path))
    try:
        _wait_for(lambda: len(os.listdir(marks)) == 2 or proc.poll() is not None,
                  "two CCDs written and under the masker")
        assert proc.poll() is None
        assert len([p for p in _temporaries(out) if "-part-" in p]) == 2
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=120)[1].decode()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM
    assert err.strip().splitlines()[-1] == ("inject survey: stopped by SIGTERM; no output left "
                                            "half-written")
    assert _temporaries(out) == []
    folder = out / "visits" / "1"
    rows = runner.read_manifest(str(folder))
    assert {r["status"] for r in rows.values()} == {"pending"}
    assert _run(db, const, out, *SMALL) == 0  # at once: within the 60 s of a stale file
    assert _temporaries(out) == []
    rows = runner.read_manifest(str(folder))
    assert {r["status"] for r in rows.values()} == {"done"}
