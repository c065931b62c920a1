"""The focal-plane runner under stress: two scenes into one directory, a stop mid-run, the
memory guard, the refusals of the command line, nothing to render, --overwrite, and the
manifest's digest, pending and stray-file paths. Small cut-outs keep it quick."""
import csv
import json
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
import yaml
from astropy.io import fits

from inject import OutputError, make_plan, parse_focal_scene
from inject.camera import layout as fp
from inject.exposure import runner

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

SAT = {"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0}
RAW = {"seed": 11, "band": "g", "zenith": 70, "exptime": 30,
       "pointing": {"ra": 50.0, "dec": -30.0, "rotation": 10.0},
       "stars": {"galactic_b": 30, "mag_limit": 21}, "cosmic_rays": 0.2,
       "cutout": {"nx": 64, "ny": 64},
       "detectors": ["R22_S11", "R22_S12", "R01_S00", "R43_S22"],
       "satellites": [dict(SAT, track={"x0_mm": -21.0, "y0_mm": -19.7, "angle": 0.4})]}
X = parse_focal_scene(RAW)
Y = parse_focal_scene(dict(RAW, seed=12))


def _sha(path):
    return runner.sha256_file(path)


def _files(outdir):
    return sorted(n for n in os.listdir(outdir) if n.endswith(".fits") and not n.startswith("."))


def _leftovers(outdir):
    """Temporary files and the lock file: none may outlive a run."""
    return sorted(n for n in os.listdir(outdir) if n.startswith((".inject-", ".manifest")))


def _consistent(outdir, digest):
    """Every CCD file has a done row of the scene with the file's SHA-256, and every done row
    its file: the manifest says what the directory holds."""
    rows = runner.read_manifest(outdir)
    for name in _files(outdir):
        row = rows.get(name[:-5])
        assert row is not None, f"{name}: no row"
        assert (row["status"], row["scene_sha256"]) == ("done", digest), (name, row)
        assert _sha(os.path.join(outdir, name)) == row["sha256"], name
    for name, row in rows.items():
        if row["status"] == "done":
            assert os.path.exists(os.path.join(outdir, f"{name}.fits")), name
    assert _leftovers(outdir) == []
    return rows


def _alone(fscene, outdir, ccds=None):
    """The scene's CCDs rendered alone in a directory of their own: the reference bytes."""
    with ThreadPoolExecutor(2) as pool:
        runner.run(make_plan(fscene), str(outdir), pool, ccds=ccds)
    return {name: row["sha256"] for name, row in runner.read_manifest(str(outdir)).items()}


class _Between(ThreadPoolExecutor):
    """A thread pool that runs ``between()`` once, at its first submission: after the run
    has checked the directory and claimed its CCDs, before any CCD is rendered or written."""

    def __init__(self, between):
        super().__init__(2)
        self.between = between

    def submit(self, *args, **kwargs):
        if self.between is not None:
            between, self.between = self.between, None
            between()
        return super().submit(*args, **kwargs)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    base = tmp_path_factory.mktemp("reference")
    return {"X": _alone(X, base / "x"), "Y": _alone(Y, base / "y")}


# -------------------------------------------------------------------------------------------
# Two scenes into one directory at the same time

def test_a_second_scene_started_meanwhile_is_refused_and_the_first_finishes(tmp_path,
                                                                            reference):
    """Before: both runs went on (the second saw no file yet), each exited 0, and the
    directory ended with a mix of the two scenes' files under one manifest."""
    out = str(tmp_path / "out")
    caught = []

    def second():
        with ThreadPoolExecutor(2) as pool, pytest.raises(OutputError) as err:
            runner.run(make_plan(Y), out, pool)
        caught.append(str(err.value))

    with _Between(second) as pool:
        result = runner.run(make_plan(X), out, pool)
    assert len(caught) == 1 and f"the run of scene {X.digest[:12]}" in caught[0]
    assert "\n" not in caught[0]
    assert sorted(r["detector"] for r in result.rendered) == sorted(reference["X"])
    rows = _consistent(out, X.digest)
    assert {n: r["sha256"] for n, r in rows.items()} == reference["X"]


def test_a_run_overtaken_by_another_scene_stops_and_leaves_its_files(tmp_path, reference):
    """The check at each commit: a run of another scene with --overwrite took the directory
    after this run's start. Before: this run wrote its CCDs over the other's and exited 0."""
    out = str(tmp_path / "out")

    def other():
        with ThreadPoolExecutor(2) as pool:
            runner.run(make_plan(Y), out, pool, overwrite=True)

    with _Between(other) as pool, pytest.raises(OutputError) as err:
        runner.run(make_plan(X), out, pool)
    assert f"the run of scene {Y.digest[:12]}" in str(err.value)
    assert "has taken this directory since this run began" in str(err.value)
    rows = _consistent(out, Y.digest)
    assert {n: r["sha256"] for n, r in rows.items()} == reference["Y"]


def _scene_file(tmp_path, raw, name="scene.yaml"):
    path = tmp_path / name
    path.write_text(json.dumps(raw))
    return path


def _main(*args):
    from inject.cli.main import main

    return main(["focalplane", *map(str, args)])


def test_the_command_that_loses_exits_2_with_one_line(tmp_path, monkeypatch, capsys,
                                                      reference):
    out = tmp_path / "out"
    first = _scene_file(tmp_path, RAW, "x.yaml")
    second = _scene_file(tmp_path, dict(RAW, seed=12), "y.yaml")
    statuses = []

    def second_command():
        statuses.append(_main(second, "-o", out, "--no-mosaic"))
        statuses.append(capsys.readouterr().err)

    pools = iter([_Between(second_command), ThreadPoolExecutor(2)])
    monkeypatch.setattr(runner, "process_pool", lambda workers=None: next(pools))
    assert _main(first, "-o", out, "--no-mosaic") == 0
    status, err = statuses
    assert status == 2
    # Each command's workers and why (both said so far), then the refusal.
    err = [line for line in err.splitlines() if " workers (bound by " not in line]
    assert err == [f"inject focalplane: error: {out}: holds the run of scene "
                                f"{X.digest[:12]} (4 pending); pass --overwrite to replace "
                                "that run"]
    rows = _consistent(str(out), X.digest)
    assert {n: r["sha256"] for n, r in rows.items()} == reference["X"]


# -------------------------------------------------------------------------------------------
# A stop mid-run

STOP_NAMES = ["R01_S00", "R01_S01", "R22_S11", "R22_S12", "R43_S21", "R43_S22"]  # id order
QUICK, BLOCKED, QUEUED = STOP_NAMES[:2], STOP_NAMES[2:4], STOP_NAMES[4:]


def _blocking_render(task):
    """The first two CCDs render as usual; the next two start (a marker file says so), open
    their output as any writer does, and wait there; the rest say when they start."""
    marks = os.path.join(os.path.dirname(task.outdir), "started")
    with open(os.path.join(marks, task.detector), "w"):
        pass
    if task.detector in BLOCKED:
        from inject.io.atomic import atomic_path

        with atomic_path(os.path.join(task.outdir, f"{task.detector}.fits"), True) as tmp:
            with open(tmp, "wb") as stream:
                stream.write(b"half a CCD")
            for _ in range(300):  # stopped here; at worst (no stop) 15 s, then it goes on
                time.sleep(0.05)
    return _REAL_RENDER(task)


_REAL_RENDER = runner.render_ccd

#: The command in a process of its own, with _blocking_render in its workers.
_STOPPED_COMMAND = """
import sys
sys.path.insert(0, {here!r})
import test_runner_reliability as t
from inject.exposure import runner
from inject.cli.main import main
runner.render_ccd = t._blocking_render
sys.exit(main(["focalplane", {scene!r}, "-o", {out!r}, "--workers", "2", "--no-mosaic"]))
"""


def _running(pgid):
    """Pids of the live (not zombie) processes of a process group."""
    pids = []
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as stream:
                    fields = stream.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                pids.append(int(name))
    return pids


def _wait_for(predicate, what, limit=120.0):
    deadline = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.02)


def test_a_stop_ends_the_ccds_under_way_and_leaves_the_manifest_true(tmp_path):
    """SIGTERM to the command while two CCDs are done, two under way (a temporary file open)
    and two queued. Before: the command waited for the two under way, which were written
    (and the queued ones after them) while their rows stayed pending, and .manifest.lock
    stayed. Now the workers stop: the two done are done, the rest pending with no file, no
    temporary or lock file is left, and a rerun renders only the four not done."""
    raw = dict(RAW, detectors=STOP_NAMES)
    scene = _scene_file(tmp_path, raw)
    out = tmp_path / "out"
    marks = tmp_path / "started"
    marks.mkdir()
    code = _STOPPED_COMMAND.format(here=HERE, scene=str(scene), out=str(out))
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        def ready():
            rows = runner.read_manifest(str(out)) if out.is_dir() else {}
            done = sorted(n for n, r in rows.items() if r["status"] == "done")
            return (done == QUICK and all((marks / n).exists() for n in BLOCKED)) \
                or proc.poll() is not None

        _wait_for(ready, "two CCDs done and two under way")
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=120)[1].decode()
        if os.path.isdir("/proc"):
            _wait_for(lambda: not _running(proc.pid), "the workers to end", limit=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM
    assert err.strip().splitlines()[-1] == ("inject focalplane: stopped by SIGTERM; no output "
                                            "left half-written")
    assert "Traceback" not in err
    rows = _consistent(str(out), parse_focal_scene(raw).digest)
    assert {n: r["status"] for n, r in rows.items()} == {
        **dict.fromkeys(QUICK, "done"), **dict.fromkeys(BLOCKED + QUEUED, "pending")}
    assert _files(str(out)) == [f"{n}.fits" for n in QUICK]
    assert sorted(os.listdir(marks)) == QUICK + BLOCKED  # the queued ones never started
    expected = {n: r["sha256"] for n, r in rows.items() if r["status"] == "done"}
    assert _main(scene, "-o", out, "--workers", 1, "--no-mosaic") == 0
    rows = _consistent(str(out), parse_focal_scene(raw).digest)
    assert all(r["status"] == "done" for r in rows.values())
    assert {n: rows[n]["sha256"] for n in QUICK} == expected


def test_no_lock_file_is_left_and_the_lock_still_excludes(tmp_path):
    """Before: .manifest.lock stayed in every output directory."""
    out = str(tmp_path)
    with ThreadPoolExecutor(2) as pool:
        runner.run(make_plan(X), out, pool, ccds=[fp.ccd("R22_S12")])
    assert _leftovers(out) == []
    # The lock file is removed by its holder; one process still excludes the other.
    import threading

    order = []

    def second():
        with runner._manifest_lock(out):
            order.append("second")

    with runner._manifest_lock(out):
        assert os.path.exists(os.path.join(out, ".manifest.lock"))
        waiter = threading.Thread(target=second)
        waiter.start()
        waiter.join(0.2)
        order.append("first")
    waiter.join(30)
    assert order == ["first", "second"]
    assert _leftovers(out) == []


# -------------------------------------------------------------------------------------------
# Refusals of the command line

def test_workers_beyond_the_memory_are_refused_and_the_default_fits(tmp_path, monkeypatch,
                                                                    capsys):
    """Before: --workers 100 forked a worker per CCD whatever the memory. A full CCD's worker
    peaks near 0.8 GiB (scripts/bench_focalplane.py), so 2 GiB hold two of them and 1.5 GiB
    one."""
    from inject.exposure import sizing

    def job(gib, cpus=8):
        return lambda: sizing.Resources(cpus, "8 CPUs", gib * 2**30, "a test's limit")

    raw = {k: v for k, v in RAW.items() if k != "cutout"}
    raw["detectors"] = ["R22_S10", "R22_S11", "R22_S12", "R22_S20", "R22_S21", "R22_S22"]
    scene = _scene_file(tmp_path, raw)
    out = tmp_path / "out"
    monkeypatch.setattr(sizing, "job_resources", job(2))
    assert _main(scene, "-o", out, "--workers", 100) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("inject focalplane: error: --workers 100: 6 "
                                               "workers need about")
    assert err[0].endswith("(about 0.81 GiB a worker for 4096 x 4004 px CCDs), 2 GiB "
                           "available: a test's limit; use --workers 2 or fewer")
    assert not out.exists()  # refused before any work

    asked = []

    class Stop(Exception):
        pass

    def pool(workers=None):
        asked.append(workers)
        raise Stop

    monkeypatch.setattr(runner, "process_pool", pool)
    for free, workers in ((2.0, 2), (1.5, 1), (64.0, 6)):
        monkeypatch.setattr(sizing, "job_resources", job(free))
        with pytest.raises(Stop):
            _main(scene, "-o", out)
        assert asked[-1] == workers
    # The job's CPUs bound it before the CCDs and the memory do.
    monkeypatch.setattr(sizing, "job_resources", job(64.0, cpus=3))
    with pytest.raises(Stop):
        _main(scene, "-o", out)
    assert asked[-1] == 3
    assert "inject focalplane: 3 workers (bound by the CPUs; the job has 3 CPUs (8 CPUs), " \
           "64 GiB of memory (a test's limit))" in capsys.readouterr().err.splitlines()
    monkeypatch.setattr(sizing, "job_resources", job(0.5))
    assert _main(scene, "-o", out) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["inject focalplane: error: not enough memory for one worker (about 0.81 GiB "
                   "a worker for 4096 x 4004 px CCDs, 0.5 GiB available: a test's limit)"]


@pytest.mark.parametrize("limit, why", [
    ("banana", "must be a size such as 3GiB, 2500MB or 4e9"),
    ("1MB", "less than one worker needs (about 0.2 GiB for a 64 x 64 px CCD)"),
])
def test_a_bad_memory_limit_is_one_line_exit_2(tmp_path, capsys, limit, why):
    """Before: a ValueError traceback from Dask (banana), a CommClosedError traceback after
    the cluster's workers died (1MB); exit 1."""
    pytest.importorskip("dask.distributed")
    scene = _scene_file(tmp_path, RAW)
    assert _main(scene, "-o", tmp_path / "out", "--scheduler", "local", "--workers", 1,
                 "--memory-limit", limit) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"inject focalplane: error: --memory-limit={limit!r}: {why}"]


def test_the_output_folder_needs_its_parent(tmp_path, capsys):
    """Before: -o a/b/c made the whole chain, where every other command refuses a missing
    folder."""
    scene = _scene_file(tmp_path, RAW)
    deep = tmp_path / "a" / "b" / "c"
    assert _main(scene, "-o", deep, "--detectors", "R22_S12") == 2
    assert capsys.readouterr().err.splitlines() == [
        f"inject focalplane: error: {deep}: directory {tmp_path / 'a' / 'b'} does not exist"]
    assert not (tmp_path / "a").exists()
    assert _main(scene, "-o", tmp_path / "a", "--detectors", "R22_S12", "--no-mosaic") == 0
    assert _files(str(tmp_path / "a")) == ["R22_S12.fits"]


def _satellites(outdir):
    with open(os.path.join(outdir, "satellites.csv"), newline="") as stream:
        return list(csv.DictReader(stream))


@pytest.mark.parametrize("args, why", [
    (("--job", 5, "--njobs", 6), "--job 5 of --njobs 6 takes none of the 4 CCDs"),
    (("--detectors", "R01_S00,R43_S22", "--streak-ccds-only"),
     "--streak-ccds-only: no streak reaches the 2 CCDs selected"),
])
def test_nothing_to_render_is_not_a_failure(tmp_path, capsys, args, why):
    """Before: exit 2 and no satellites.csv, so a batch array with more slices than CCDs
    reported failures. (The line reaches R22_S11 and R22_S12 of these four.)"""
    scene = _scene_file(tmp_path, RAW)
    out = tmp_path / "out"
    assert _main(scene, "-o", out, *args) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (f"inject focalplane: no CCD to render ({why}); wrote "
                       f"{out / 'satellites.csv'}")
    records = _satellites(str(out))
    assert [(r["satellite"], r["ccds"], r["scene_sha256"]) for r in records] == [
        ("0", "R22_S11 R22_S12", X.digest)]
    assert runner.read_manifest(str(out)) == {} and (out / "manifest.csv").exists()
    assert _files(str(out)) == [] and _leftovers(str(out)) == []


def test_overwrite_replaces_the_whole_run(tmp_path, capsys, reference):
    """Before: --overwrite on one CCD left the other scene's other CCD file and rows, and the
    mosaic drew both scenes."""
    from inject.exposure.mosaic import binned_ccds

    out = tmp_path / "out"
    assert _main(_scene_file(tmp_path, RAW, "x.yaml"), "-o", out, "--detectors",
                 "R22_S11,R43_S22", "--no-mosaic") == 0
    assert _main(_scene_file(tmp_path, dict(RAW, seed=12), "y.yaml"), "-o", out,
                 "--detectors", "R22_S11") == 2  # another scene's run: refused
    assert _main(_scene_file(tmp_path, dict(RAW, seed=12), "y.yaml"), "-o", out,
                 "--detectors", "R22_S11", "--overwrite") == 0
    rows = _consistent(str(out), Y.digest)
    assert {n: r["sha256"] for n, r in rows.items()} == {"R22_S11": reference["Y"]["R22_S11"]}
    assert _files(str(out)) == ["R22_S11.fits"]
    assert [c.name for c in binned_ccds(Y, str(out), 8)] == ["R22_S11"]
    assert {r["scene_sha256"] for r in _satellites(str(out))} == {Y.digest}


def test_the_mosaic_draws_only_this_scenes_files(tmp_path):
    """A file of another scene (here with no manifest left) is not drawn."""
    from inject.exposure.mosaic import binned_ccds, write_mosaic

    out = str(tmp_path)
    with ThreadPoolExecutor(2) as pool:
        runner.run(make_plan(X), out, pool, ccds=[fp.ccd("R22_S11"), fp.ccd("R43_S22")])
    os.remove(os.path.join(out, "manifest.csv"))
    with open(os.path.join(out, "R01_S00.fits"), "wb") as stream:
        stream.write(b"not FITS")
    assert sorted(c.name for c in binned_ccds(X, out, 8)) == ["R22_S11", "R43_S22"]
    assert binned_ccds(Y, out, 8) == {}
    assert write_mosaic(os.path.join(out, "m.png"), Y, out, factor=64) == 0


# -------------------------------------------------------------------------------------------
# The manifest's digest, pending rows and stray files

def _checksum(line):
    """A TLE line's checksum: the digits, each minus sign counting 1, modulo 10."""
    return sum(int(c) if c.isdigit() else c == "-" for c in line[:68]) % 10


def _tle(raan):
    """The example TLE (sample_fields/pass_example.yaml) with another right ascension of the
    ascending node."""
    line1 = "1 90001U          26166.97916667  .00000000  00000-0  00000+0 0    04"
    line2 = f"2 90001  53.0000 {raan:8.4f} 0000000   0.0000 321.2313 15.05593056    0"
    return f"EXAMPLE\n{line1}\n{line2}{_checksum(line2)}\n"


def test_a_tle_file_changed_under_its_name_is_rendered_again(tmp_path):
    """The digest covers the resolved tracks, not only the scene's text: the same scene
    with another orbit in the same TLE file is another scene (the streak moves off
    R22_S12's corner)."""
    with open(os.path.join(ROOT, "sample_fields", "pass_example.yaml")) as stream:
        raw = yaml.safe_load(stream)
    tle = tmp_path / "sat.tle"
    raw["satellites"][0]["orbit"] = {"tle": str(tle)}
    raw.update(cutout={"nx": 64, "ny": 64}, detectors=["R22_S12"], stars={"mag_limit": 18})
    scene = tmp_path / "pass.yaml"
    scene.write_text(yaml.safe_dump(raw))
    out = tmp_path / "out"
    tle.write_text(_tle(208.851))
    assert _main(scene, "-o", out, "--no-mosaic") == 0
    first = _sha(out / "R22_S12.fits")
    tle.write_text(_tle(208.901))
    assert _main(scene, "-o", out, "--no-mosaic") == 2  # not taken as done: another scene
    assert _sha(out / "R22_S12.fits") == first
    assert _main(scene, "-o", out, "--no-mosaic", "--overwrite") == 0
    assert _main(scene, "-o", tmp_path / "alone", "--no-mosaic") == 0
    assert _sha(out / "R22_S12.fits") == _sha(tmp_path / "alone" / "R22_S12.fits") != first


class _Killed(BaseException):
    """The process dying where it is raised."""


def test_a_run_killed_between_a_file_and_its_row_is_redone_by_a_rerun(tmp_path, reference,
                                                                      monkeypatch):
    """Killed after its first CCD file is in place, before the row says so: the pending rows
    written at the start mark the file as this scene's, so a rerun redoes it (a file in no
    row would be refused)."""
    out = str(tmp_path)
    write = runner._write_manifest

    def dies_at_first_done(outdir, rows):
        if any(r.get("status") == "done" for r in rows.values()):
            raise _Killed
        write(outdir, rows)

    monkeypatch.setattr(runner, "_write_manifest", dies_at_first_done)
    with ThreadPoolExecutor(1) as pool, pytest.raises(_Killed):
        runner.run(make_plan(X), out, pool, ccds=[fp.ccd("R22_S12")])
    monkeypatch.setattr(runner, "_write_manifest", write)
    assert _files(out) == ["R22_S12.fits"]
    assert runner.read_manifest(out)["R22_S12"]["status"] == "pending"
    with ThreadPoolExecutor(1) as pool:
        result = runner.run(make_plan(X), out, pool, ccds=[fp.ccd("R22_S12")])
    assert [r["detector"] for r in result.rendered] == ["R22_S12"]
    assert _consistent(out, X.digest)["R22_S12"]["sha256"] == reference["X"]["R22_S12"]


@pytest.mark.parametrize("manifest", [False, True])
def test_a_stray_file_is_not_replaced_without_overwrite(tmp_path, reference, manifest):
    """A file in no manifest row is someone's: refused, left as it was; replaced with
    --overwrite. Before, it was replaced silently once the directory held any row of this
    scene (manifest=True)."""
    out = str(tmp_path)
    if manifest:
        with ThreadPoolExecutor(1) as pool:
            runner.run(make_plan(X), out, pool, ccds=[fp.ccd("R43_S22")])
    stray = os.path.join(out, "R22_S12.fits")
    with open(stray, "wb") as stream:
        stream.write(b"someone's file")
    with ThreadPoolExecutor(1) as pool:
        with pytest.raises(OutputError, match="R22_S12.fits: exists \\(not in any manifest\\); "
                                              "pass --overwrite"):
            runner.run(make_plan(X), out, pool)
        with open(stray, "rb") as stream:
            assert stream.read() == b"someone's file"
        runner.run(make_plan(X), out, pool, overwrite=True)
    rows = _consistent(out, X.digest)
    assert {n: r["sha256"] for n, r in rows.items()} == reference["X"]


def test_a_run_of_another_inject_version_is_not_resumed_without_overwrite(tmp_path,
                                                                          monkeypatch):
    """The same scene's files made by another inject version may differ from this one's: its
    run is another run. Before: its files were kept as done."""
    import inject

    out = str(tmp_path)
    one = [fp.ccd("R22_S12")]
    with ThreadPoolExecutor(2) as pool:
        runner.run(make_plan(X), out, pool, ccds=one)
    monkeypatch.setattr(runner, "__version__", inject.__version__ + ".post1")
    with ThreadPoolExecutor(2) as pool, pytest.raises(OutputError) as err:
        runner.run(make_plan(X), out, pool, ccds=one)
    assert str(err.value) == (f"{os.path.join(out, 'R22_S12.fits')}: exists, of the run of "
                              f"scene {X.digest[:12]} by inject {inject.__version__} (1 done); "
                              "pass --overwrite to replace that run")
    with ThreadPoolExecutor(2) as pool:
        result = runner.run(make_plan(X), out, pool, ccds=one, overwrite=True)
    assert [r["detector"] for r in result.rendered] == ["R22_S12"]
    assert runner.read_manifest(out)["R22_S12"]["inject_version"] == \
        inject.__version__ + ".post1"


class _WorkerOfAnotherVersion:
    """An executor whose tasks run where inject's version reads otherwise than in the caller
    (a commit during a run in a checkout, or midnight on a dirty tree)."""

    def __init__(self, version):
        self.version = version
        self.pool = ThreadPoolExecutor(1)

    def submit(self, function, *args):
        def elsewhere():
            import inject

            saved = runner.__version__, inject.__version__
            runner.__version__ = inject.__version__ = self.version
            try:
                return function(*args)
            finally:
                runner.__version__, inject.__version__ = saved
        return self.pool.submit(elsewhere)

    def shutdown(self, *args, **kwargs):
        self.pool.shutdown(*args, **kwargs)


def test_a_worker_records_and_claims_with_the_runs_version(tmp_path):
    """A worker whose own version differs from the run's writes the run's version and is not
    stopped as another run. Before: each CCD came back 'claimed' and the run stopped."""
    import inject

    out = str(tmp_path)
    executor = _WorkerOfAnotherVersion(inject.__version__ + ".d20991231")
    try:
        result = runner.run(make_plan(X), out, executor, ccds=[fp.ccd("R22_S12")])
    finally:
        executor.shutdown()
    assert [r["detector"] for r in result.rendered] == ["R22_S12"]
    assert runner.read_manifest(out)["R22_S12"]["inject_version"] == inject.__version__


def test_a_worker_process_writes_the_runs_version_in_its_files(tmp_path, monkeypatch):
    """A worker process (here this process, taken for one) writes the run's version in the
    file's INJVER, not the one it would read itself."""
    import inject

    run_version = inject.__version__
    monkeypatch.setattr(inject, "__version__", run_version + ".d20991231")
    monkeypatch.setattr(runner.multiprocessing, "parent_process", lambda: object())
    monkeypatch.setattr(runner, "limit_threads", lambda: None)  # this process's threads stay
    plan = make_plan(X)
    ccd = fp.ccd("R22_S12")
    row = runner.render_ccd(runner.Task(X, ccd.name, str(tmp_path), tuple(plan.streaks(ccd)),
                                        version=run_version))
    assert row["status"] == "done" and row["inject_version"] == run_version
    with fits.open(tmp_path / "R22_S12.fits") as hdus:
        assert hdus[0].header["INJVER"] == run_version
