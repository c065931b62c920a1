"""``--scheduler tcp://HOST:PORT`` on a real Dask cluster: a ``dask scheduler`` and two
``dask worker`` processes started on their own, as a cluster's are. They share nothing in
memory with the command: they import inject from PYTHONPATH, run in another working
directory, read the inputs by path and write to OUTDIR on the shared file system (here, the
same disk).

Checked against the process pool's outputs from the same inputs (the CCD files' bytes), the
in-process plan (the tables' bytes), and, with a worker killed (SIGKILL) while it renders a
CCD, against the uninterrupted run: its work is redone on the other worker, nothing is lost,
doubled or left behind.
"""
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from test_survey_render import _night

import inject
from inject.cli.main import main
from inject.exposure import runner
from inject.io.atomic import temporary_prefix

pytest.importorskip("dask.distributed")

#: The checkout this test runs: the workers import inject from it (PYTHONPATH).
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(inject.__file__)))
SCENE = os.path.join(ROOT, "sample_fields", "focal_paper_550km.yaml")
#: Six CCDs the paper's streak crosses and one it does not, as 256 px cut-outs.
CCDS = ("--detectors", "R21_S02,R22_S10,R22_S11,R22_S12,R22_S21,R22_S22,R33_S00",
        "cutout.nx=256", "cutout.ny=256")
#: Seconds a cluster or a command may take before the test fails (never how fast it must be).
TIMEOUT = 300.0


def _wait_for(predicate, what, limit=TIMEOUT):
    """Poll until ``predicate()``; fail (not time a test) if it never happens."""
    deadline = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.05)


def _end(proc, sig=signal.SIGTERM):
    """End a process and its group (started with a session of its own); SIGKILL if it has not
    ended 20 s after ``sig``."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


class Cluster:
    """A ``dask scheduler`` on a free port of 127.0.0.1 (``--port 0``; its address read from
    ``--scheduler-file``) and ``dask worker`` processes named ``w1``, ``w2``..., each one
    process with one thread, started in ``folder/elsewhere`` (not the command's working
    directory) with PYTHONPATH = this checkout.

    The workers run without a nanny: the process that renders is the worker itself, so a
    worker killed stays dead and its tasks must go to another one (a nanny would start it
    again, and the work might be redone on the same worker). Every process has a session of
    its own, and :meth:`close` ends each group, whatever state the test left.
    """

    def __init__(self, folder, workers=2):
        self.folder = folder
        self.elsewhere = folder / "elsewhere"
        self.elsewhere.mkdir(parents=True)
        self.procs = {}
        self.env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            p for p in (ROOT, os.environ.get("PYTHONPATH")) if p))
        info = folder / "scheduler.json"
        self._start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", "0",
                    "--no-dashboard", "--scheduler-file", str(info))
        _wait_for(lambda: info.exists() and info.stat().st_size > 0, "the scheduler file")
        self.address = json.loads(info.read_text())["address"]
        for k in range(1, workers + 1):
            self._start(f"w{k}", "worker", "--scheduler-file", str(info), "--name", f"w{k}",
                        "--nworkers", "1", "--nthreads", "1", "--no-nanny", "--host",
                        "127.0.0.1", "--no-dashboard", "--memory-limit", "2GiB")
        from dask.distributed import Client

        self.client = Client(self.address, timeout=60)
        self.client.wait_for_workers(workers, timeout=TIMEOUT)

    def _start(self, name, *command):
        log = open(self.folder / f"{name}.log", "wb")  # noqa: SIM115 (closed with the process)
        self.procs[name] = subprocess.Popen([sys.executable, "-m", "dask", *command],
                                            cwd=self.elsewhere, env=self.env, stdout=log,
                                            stderr=subprocess.STDOUT, start_new_session=True)
        log.close()

    def workers(self):
        """``{address: name}`` of the workers the scheduler has."""
        try:
            info = self.client.scheduler_info(n_workers=-1)
        except TypeError:  # a Dask before n_workers: all of them
            info = self.client.scheduler_info()
        return {address: w["name"] for address, w in info["workers"].items()}

    def worker_address(self, name):
        """The address of the worker ``name`` (``w1``...)."""
        return next(a for a, n in self.workers().items() if n == name)

    def close(self):
        with contextlib.suppress(Exception):
            self.client.close()
        for proc in reversed(self.procs.values()):  # the workers, then the scheduler
            _end(proc)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    made = Cluster(tmp_path_factory.mktemp("cluster"))
    try:
        yield made
    finally:
        made.close()


def _focalplane(*args):
    assert main(["focalplane", "focal.yaml", *map(str, args), *CCDS]) == 0


def _digests(outdir):
    """``{file: SHA-256}`` of every file in ``outdir`` but the manifest (whose times and
    seconds are the run's); no temporary file may be left."""
    assert _temporaries(outdir) == []
    return {name: runner.sha256_file(os.path.join(outdir, name))
            for name in sorted(os.listdir(outdir)) if name != runner.MANIFEST}


def _rows(outdir):
    """The manifest's rows, without what is the run's own (the files' times, the seconds)."""
    return {name: {k: v for k, v in row.items() if k not in ("mtime_ns", "seconds")}
            for name, row in runner.read_manifest(str(outdir)).items()}


@pytest.fixture(scope="module")
def pool_run(tmp_path_factory):
    """The CCDs on the process pool (2 workers): the reference. The scene file is copied
    into the command's working directory and given by a relative path, as is OUTDIR."""
    folder = tmp_path_factory.mktemp("client")
    shutil.copy(SCENE, folder / "focal.yaml")
    with contextlib.chdir(folder):
        _focalplane("-o", "pool", "--workers", "2")
    assert len(runner.read_manifest(str(folder / "pool"))) == 7
    return folder


@pytest.mark.parametrize("lock", ["locked", "nolock"])
def test_focalplane_on_the_cluster_equals_the_process_pool(cluster, pool_run, lock,
                                                           monkeypatch):
    """Relative paths, given to workers in another folder; with --no-lock the workers leave
    each finished file for the command to commit."""
    monkeypatch.chdir(pool_run)
    _focalplane("-o", lock, "--scheduler", cluster.address,
                *(["--no-lock"] if lock == "nolock" else []))
    pool, dask = pool_run / "pool", pool_run / lock
    assert _digests(dask) == _digests(pool)  # CCD files, satellites.csv, mosaic.png
    assert _rows(dask) == _rows(pool)
    assert {r["status"] for r in _rows(dask).values()} == {"done"}
    assert os.listdir(cluster.elsewhere) == []  # nothing written where the workers run


def test_workers_write_the_runs_version_whatever_they_read(cluster, pool_run, monkeypatch):
    """A worker's ``inject.__version__`` is read once, when it first asks (a checkout's
    follows its commits and edits): the files carry the command's. Before: a worker without
    a nanny (no one's child process) wrote its own in INJVER and the truth tables, while the
    manifest said the command's."""
    monkeypatch.chdir(pool_run)
    cluster.client.run(lambda: setattr(__import__("inject"), "__version__", "0.0.0+stale"))
    _focalplane("-o", "stale", "--scheduler", cluster.address)
    assert _digests(pool_run / "stale") == _digests(pool_run / "pool")


def _survey(out, *extra):
    assert main(["survey", "night.db", "-o", out, "--constellation", "const.yaml",
                 "--no-plots", *extra]) == 0


def _same_tables(one, two):
    for table in ("visits.csv", "streaks.csv"):
        assert (one / table).read_bytes() == (two / table).read_bytes()


def test_survey_plan_on_the_cluster_equals_the_plan_made_here(cluster, tmp_path, monkeypatch):
    """The night of tests/test_survey_render.py (one satellite over nine CCDs of a visit),
    its files given by relative paths."""
    monkeypatch.chdir(tmp_path)
    _night(tmp_path)
    _survey("here")
    _survey("dask", "--scheduler", cluster.address)
    _same_tables(tmp_path / "here", tmp_path / "dask")
    assert len((tmp_path / "dask" / "streaks.csv").read_text().splitlines()) == 2
    assert os.listdir(cluster.elsewhere) == []


@pytest.mark.slow  # 1-2 min on 2 busy cores: each visit's plan, nine CCDs rendered and masked
def test_survey_render_on_the_cluster_equals_the_process_pool(cluster, tmp_path, monkeypatch):
    """The render (64 px cut-outs of the nine CCDs) equals the process pool's: the tables,
    the manifests (with the files' digests) and each CCD file, byte for byte."""
    monkeypatch.chdir(tmp_path)
    _night(tmp_path)
    render = ("--render", "--cutouts", "--cutout-size", "64")
    _survey("pool", *render, "--workers", "2")
    _survey("dask", *render, "--scheduler", cluster.address)
    _same_tables(tmp_path / "pool", tmp_path / "dask")
    one, two = (tmp_path / run / "visits" / "1" for run in ("pool", "dask"))
    rows = _rows(one)
    assert len(rows) == 9 and {r["status"] for r in rows.values()} == {"done"}
    assert _rows(two) == rows
    for name in rows:
        assert (one / f"{name}.fits").read_bytes() == (two / f"{name}.fits").read_bytes()
    assert _temporaries(one) == _temporaries(two) == []
    assert os.listdir(cluster.elsewhere) == []


def _temporaries(folder):
    return [n for n in os.listdir(folder) if n.startswith(".inject-")]


def _executing(made, worker, proc):
    """True once ``worker`` runs a task (or the command ``proc`` has ended)."""
    if proc.poll() is not None:
        return True
    busy = made.client.run(lambda dask_worker: len(dask_worker.state.executing),
                           workers=[worker])
    return busy.get(worker, 0) > 0


def test_a_worker_killed_mid_run_has_its_ccds_redone_on_the_other(pool_run, tmp_path):
    """SIGKILL to worker w1 while it renders its first CCD (a fresh worker's first CCD takes
    seconds: its imports and caches). The command, in a process of its own, goes on: every
    CCD is done once, by w2, with the uninterrupted run's bytes, and no temporary file is
    left: not even one named for w1 (as a CCD it was writing would be)."""
    made = Cluster(tmp_path / "cluster")
    client = tmp_path / "client"
    client.mkdir()
    shutil.copy(SCENE, client / "focal.yaml")
    proc = None
    try:
        w1 = made.worker_address("w1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "inject", "focalplane", "focal.yaml", "-o", "out",
             "--scheduler", made.address, *CCDS], cwd=client, env=made.env,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)

        _wait_for(lambda: _executing(made, w1, proc), "worker w1 to render a CCD")
        assert proc.poll() is None, "the command ended before w1 rendered anything"
        done_before = [r for r in runner.read_manifest(str(client / "out")).values()
                       if r["status"] == "done"]
        # What w1 would leave, killed while writing a CCD: a file named for its process.
        pid = made.client.run(os.getpid, workers=[w1])[w1]
        left = client / "out" / f"{temporary_prefix(pid)}part-R22_S11.fits"
        left.write_bytes(b"\0" * 2880)
        os.killpg(made.procs["w1"].pid, signal.SIGKILL)
        made.procs["w1"].wait(60)
        err = proc.communicate(timeout=TIMEOUT)[1].decode()
        assert proc.returncode == 0, err
        assert len(done_before) < 7
        assert list(made.workers().values()) == ["w2"]
    finally:
        if proc is not None:
            _end(proc, signal.SIGKILL)
        made.close()
    out = client / "out"
    assert _digests(out) == _digests(pool_run / "pool")
    rows = _rows(out)
    assert rows == _rows(pool_run / "pool")  # each CCD once, done, the same digest
    with open(out / runner.MANIFEST) as stream:
        assert len(stream.read().splitlines()) == 1 + 7
    assert _temporaries(out) == []


class _Client:
    """What :func:`runner._check_workers` asks of a Dask client: ``run`` on every worker."""

    def __init__(self, answer):
        self.answer = answer

    def run(self, function):
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer


def test_workers_of_another_inject_are_refused_before_any_work():
    """Before: a worker started without this checkout on its PYTHONPATH imported the inject
    installed in its environment (another version) and wrote its CCDs under this run's
    version; one that had none failed every CCD."""
    mine = inject.__version__
    here = {"tcp://a:1": (mine, ROOT, 11), "tcp://b:2": (mine, "/elsewhere", 12)}
    assert runner._check_workers(_Client(here), "tcp://s:8786") == {"tcp://a:1": 11,
                                                                      "tcp://b:2": 12}
    other = dict(here, **{"tcp://b:2": ("0.0.1", "/old/site-packages", 12)})
    with pytest.raises(inject.InputError, match=r"worker tcp://b:2 runs inject 0\.0\.1 from "
                                                r"/old/site-packages, this command inject "):
        runner._check_workers(_Client(other), "tcp://s:8786")
    with pytest.raises(inject.InputError, match=r"its workers cannot run inject \("
                                                r"ModuleNotFoundError: No module named 'inj"):
        runner._check_workers(_Client(ModuleNotFoundError("No module named 'inject'")),
                              "tcp://s:8786")


@pytest.mark.slow  # a cluster of its own and four nights planned: ~30 s on 2 busy cores
def test_a_worker_killed_mid_survey_has_its_night_planned_on_the_other(tmp_path):
    """SIGKILL to worker w1 while it plans a night (its first: the imports and the orbits
    make it seconds long). The command goes on, w2 plans what w1 had, and every table (the
    nights' Parquet files, visits.csv, streaks.csv) is the uninterrupted in-process run's,
    byte for byte, with each night once in the manifest."""
    from test_survey_stream import _files, _rows
    from test_survey_trust import EPOCH, MODEL, SHELL, write_csv

    visits = write_csv(tmp_path / "nights.csv", _rows())
    const = tmp_path / "const.yaml"
    const.write_text(MODEL + f"epoch: {EPOCH}\nshells:\n  - {SHELL}\n")
    whole = tmp_path / "whole"
    assert main(["survey", str(visits), "-o", str(whole), "--constellation", str(const),
                 "--no-plots"]) == 0
    made = Cluster(tmp_path / "cluster")
    proc = None
    out = tmp_path / "dask"
    try:
        w1 = made.worker_address("w1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "inject", "survey", str(visits), "-o", str(out),
             "--constellation", str(const), "--no-plots", "--scheduler", made.address],
            env=made.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            start_new_session=True)

        _wait_for(lambda: _executing(made, w1, proc), "worker w1 to plan a night")
        assert proc.poll() is None, "the command ended before w1 planned anything"
        os.killpg(made.procs["w1"].pid, signal.SIGKILL)
        made.procs["w1"].wait(60)
        err = proc.communicate(timeout=TIMEOUT)[1].decode()
        assert proc.returncode == 0, err
        assert list(made.workers().values()) == ["w2"]
    finally:
        if proc is not None:
            _end(proc, signal.SIGKILL)
        made.close()
    tables = {name: data for name, data in _files(out).items()
              if name.endswith((".parquet", ".csv"))}
    assert tables == {name: data for name, data in _files(whole).items()
                      if name.endswith((".parquet", ".csv"))}
    assert len([n for n in tables if n.startswith("nights/visits-")]) == 4
    entries = [sorted(json.loads((run / "nights" / "manifest.json").read_text())["nights"],
                      key=json.dumps) for run in (out, whole)]
    assert entries[0] == entries[1] and len(entries[0]) == 4
    assert _temporaries(out) == _temporaries(out / "nights") == []
