"""Outputs that survive a crash: each file flushed to disk before its rename and its folder
after; a writer killed at random points leaves whole files or none, and a rerun takes as done
only files that match their manifest row; resume trusts a file's recorded size and time and
hashes only with --verify; a file system without locks gets one clear line and --no-lock."""
import errno
import fcntl
import hashlib
import os
import random
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from inject import make_plan, parse_focal_scene
from inject.camera import layout as fp
from inject.exposure import runner
from inject.io import atomic

RAW = {"seed": 5, "band": "g", "exptime": 30, "pointing": {"ra": 50.0, "dec": -30.0},
       "stars": False, "cutout": {"nx": 48, "ny": 40},
       "detectors": ["R22_S11", "R22_S12", "R01_S00"],
       "satellites": [{"height": 550, "mag": 5.0,
                       "shape": {"type": "box", "length": 7.25, "width": 2.65},
                       "track": {"x0_mm": -21.0, "y0_mm": -19.7, "angle": 0.4}}]}
NAMES = ["R01_S00", "R22_S11", "R22_S12"]


def sha(path):
    with open(path, "rb") as stream:
        return hashlib.sha256(stream.read()).hexdigest()


@pytest.fixture(scope="module")
def fscene():
    return parse_focal_scene(RAW)


def scene_file(tmp_path):
    import yaml

    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(RAW))
    return path


def render(fscene, out, **options):
    with ThreadPoolExecutor(2) as pool:
        return runner.run(make_plan(fscene), str(out), pool, **options)


# -------------------------------------------------------------------------------------------
# The order of the calls: data on disk, then the rename, then the folder's entry

@pytest.fixture
def calls(monkeypatch):
    """Record fsync (by the path its descriptor leads to) and os.replace, in order."""
    done = []
    fsync, replace = os.fsync, os.replace

    def recording_fsync(fd):
        done.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return fsync(fd)

    def recording_replace(src, dst, **kw):
        done.append(("replace", os.fspath(src), os.fspath(dst)))
        return replace(src, dst, **kw)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    monkeypatch.setattr(os, "replace", recording_replace)
    return done


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd")
def test_a_file_is_synced_before_its_rename_and_its_folder_after(tmp_path, calls):
    target = tmp_path / "out.txt"
    with atomic.atomic_path(target) as tmp:
        with open(tmp, "w") as stream:
            stream.write("whole")
    assert calls == [("fsync", tmp), ("replace", tmp, str(target)),
                     ("fsync", str(tmp_path))]


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd")
def test_a_group_syncs_each_file_then_each_folder_once(tmp_path, calls):
    (tmp_path / "b").mkdir()
    targets = [tmp_path / "a1", tmp_path / "a2", tmp_path / "b" / "c"]
    temporaries = []
    with atomic.output_group(targets):
        for target in targets:
            with atomic.atomic_path(target) as tmp:
                with open(tmp, "w") as stream:
                    stream.write(target.name)
                temporaries.append(tmp)
    syncs = [c[1] for c in calls if c[0] == "fsync"]
    moves = [c for c in calls if c[0] == "replace"]
    assert syncs[:3] == temporaries  # each file as it is finished, before any move
    assert moves == [("replace", t, str(p)) for t, p in zip(temporaries, targets)]
    assert calls.index(moves[-1]) < len(calls) - 2  # the folders after the last move
    assert sorted(syncs[3:]) == sorted([str(tmp_path), str(tmp_path / "b")])


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd")
def test_the_runner_syncs_a_ccd_before_its_rename_and_before_its_row(tmp_path, fscene, calls):
    render(fscene, tmp_path, ccds=[fp.ccd("R22_S12")])
    target = str(tmp_path / "R22_S12.fits")
    move = next(k for k, c in enumerate(calls) if c[0] == "replace" and c[2] == target)
    part = calls[move][1]
    assert ("fsync", part) in calls[:move]
    rows = [k for k, c in enumerate(calls)
            if c[0] == "replace" and c[2] == str(tmp_path / runner.MANIFEST)]
    folder = calls.index(("fsync", str(tmp_path)), move)
    assert move < folder < rows[-1]  # the file's entry on disk before the row saying done


# -------------------------------------------------------------------------------------------
# Resume: the recorded size and time, and --verify

def test_resume_trusts_size_and_time_and_redoes_a_changed_file(tmp_path, fscene, monkeypatch):
    render(fscene, tmp_path)
    rows = runner.read_manifest(str(tmp_path))
    for name in NAMES:
        st = os.stat(tmp_path / f"{name}.fits")
        assert (rows[name]["size"], rows[name]["mtime_ns"]) == (str(st.st_size),
                                                                str(st.st_mtime_ns))
    hashed = []
    monkeypatch.setattr(runner, "sha256_file", lambda p, f=runner.sha256_file:
                        hashed.append(p) or f(p))
    # Cut short (a crash's lost write-back), and touched: both redone, without hashing.
    short = tmp_path / "R01_S00.fits"
    with open(short, "r+b") as stream:
        stream.truncate(short.stat().st_size // 2)
    touched = tmp_path / "R22_S11.fits"
    os.utime(touched, ns=(touched.stat().st_atime_ns, touched.stat().st_mtime_ns + 10**9))
    result = render(fscene, tmp_path)
    assert sorted(r["detector"] for r in result.rendered) == ["R01_S00", "R22_S11"]
    assert [r["detector"] for r in result.skipped] == ["R22_S12"]
    assert hashed == []
    # Bytes changed under the same size and time: trusted without --verify, redone with it.
    flipped = tmp_path / "R22_S12.fits"
    st = flipped.stat()
    with open(flipped, "r+b") as stream:
        stream.seek(5000)
        stream.write(b"\x00flipped\x00")
    os.utime(flipped, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert render(fscene, tmp_path).rendered == []
    result = render(fscene, tmp_path, verify=True)
    assert [r["detector"] for r in result.rendered] == ["R22_S12"]
    assert sorted(os.path.basename(p) for p in hashed) == [f"{n}.fits" for n in NAMES]
    rows = runner.read_manifest(str(tmp_path))
    assert all(sha(tmp_path / f"{n}.fits") == rows[n]["sha256"] for n in NAMES)


def test_a_row_without_size_and_time_is_checked_by_its_hash(tmp_path, fscene):
    """A manifest written before rows recorded size and time: its files are hashed."""
    render(fscene, tmp_path)
    path = tmp_path / runner.MANIFEST
    rows = runner.read_manifest(str(tmp_path))
    for row in rows.values():
        row["size"] = row["mtime_ns"] = ""
    runner._write_manifest(str(tmp_path), rows)
    with open(tmp_path / "R22_S12.fits", "r+b") as stream:
        stream.seek(5000)
        stream.write(b"\x00flipped\x00")
    result = render(fscene, tmp_path)
    assert [r["detector"] for r in result.rendered] == ["R22_S12"]
    assert path.exists()


def test_the_command_line_resumes_by_size_and_time_and_verify_hashes(tmp_path, cli):
    scene, out = scene_file(tmp_path), tmp_path / "out"
    assert cli("focalplane", scene, "-o", out, "--no-mosaic", "--workers", 1)[0] == 0
    flipped = out / "R22_S12.fits"
    st = flipped.stat()
    with open(flipped, "r+b") as stream:
        stream.seek(5000)
        stream.write(b"\x00flipped\x00")
    os.utime(flipped, ns=(st.st_atime_ns, st.st_mtime_ns))
    status, _, err = cli("focalplane", scene, "-o", out, "--no-mosaic", "--workers", 1)
    assert status == 0 and f"{out}: 0 CCDs rendered, 3 already done, 0 failed" in err
    status, _, err = cli("focalplane", scene, "-o", out, "--no-mosaic", "--workers", 1,
                         "--verify")
    assert status == 0 and f"{out}: 1 CCDs rendered, 2 already done, 0 failed" in err
    assert sha(flipped) == runner.read_manifest(str(out))["R22_S12"]["sha256"]


# -------------------------------------------------------------------------------------------
# A file system without locks

def no_flock(monkeypatch):
    def unsupported(fd, operation):
        raise OSError(errno.ENOSYS, os.strerror(errno.ENOSYS))

    monkeypatch.setattr(fcntl, "flock", unsupported)


def test_no_flock_is_one_clear_line_and_no_lock_runs(tmp_path, monkeypatch, cli, fscene):
    no_flock(monkeypatch)
    monkeypatch.setattr(runner, "process_pool", lambda workers=None: ThreadPoolExecutor(2))
    out = tmp_path / "out"
    status, _, err = cli("focalplane", scene_file(tmp_path), "-o", out, "--no-mosaic")
    assert status == 2
    assert err.splitlines()[-1] == (
        f"inject focalplane: error: {out}: its file system does not support locking (mounted "
        f"with Lustre's noflock or NFS's nolock?): flock: Function not implemented; if this "
        f"run is the only one writing there, pass --no-lock")
    assert not (out / ".manifest.lock").exists()
    status, _, err = cli("focalplane", scene_file(tmp_path), "-o", out, "--no-mosaic",
                         "--no-lock")
    assert status == 0
    rows = runner.read_manifest(str(out))
    assert sorted(rows) == NAMES and all(r["status"] == "done" for r in rows.values())
    assert all(sha(out / f"{n}.fits") == rows[n]["sha256"] for n in NAMES)
    assert atomic.locking()  # --no-lock lasts for its command only
    assert sorted(n for n in os.listdir(out) if n.startswith(".")) == []


def test_no_lock_with_worker_processes_commits_every_ccd(tmp_path, cli):
    """Worker processes hand their files to the runner, which records every one: no row lost
    to two workers rewriting the manifest at once."""
    out = tmp_path / "out"
    status, _, err = cli("focalplane", scene_file(tmp_path), "-o", out, "--no-mosaic",
                         "--no-lock", "--workers", 2)
    assert status == 0 and f"{out}: 3 CCDs rendered" in err
    rows = runner.read_manifest(str(out))
    assert sorted(rows) == NAMES and all(r["status"] == "done" for r in rows.values())
    for name in NAMES:
        st = os.stat(out / f"{name}.fits")
        assert sha(out / f"{name}.fits") == rows[name]["sha256"]
        assert (rows[name]["size"], rows[name]["mtime_ns"]) == (str(st.st_size),
                                                                str(st.st_mtime_ns))
    assert sorted(n for n in os.listdir(out) if n.startswith(".")) == []


def test_without_flock_single_outputs_are_still_written(tmp_path, monkeypatch):
    """A temporary file's lock only marks it live: without locks it is left out."""
    no_flock(monkeypatch)
    with atomic.atomic_path(tmp_path / "one.txt") as tmp:
        with open(tmp, "w") as stream:
            stream.write("x")
    assert (tmp_path / "one.txt").read_text() == "x"


# -------------------------------------------------------------------------------------------
# A writer killed at random points of its writes

WRITER = r'''
import hashlib, os, sys
from inject.exposure import runner
from inject.io.atomic import atomic_path, temporary_prefix
from writer_content import content

outdir, version, names = sys.argv[1], sys.argv[2], sys.argv[3:]
ids = {name: k + 1 for k, name in enumerate(names)}
print("ready", flush=True)
generation = 0
while True:
    for name in names:
        data = content(name, generation)
        part = os.path.join(outdir, f"{temporary_prefix()}part-{name}.fits")
        with atomic_path(part, overwrite=True) as tmp:
            with open(tmp, "wb") as stream:
                for k in range(0, len(data), 8192):  # many writes: a wide window to be cut
                    stream.write(data[k:k + 8192])
        row = {"detector": name, "id": ids[name], "vendor": "ITL", "file": name + ".fits",
               "sha256": hashlib.sha256(data).hexdigest(), "streaks": 0, "seconds": 0,
               "status": "done", "scene_sha256": "s" * 64, "inject_version": version,
               "error": ""}
        runner.commit(outdir, row, part)
    generation += 1
'''

CONTENT = r'''
import hashlib


def content(name, generation):
    """A file that says what it is on its first line; sizes differ between generations."""
    head = f"{name} {generation}\n".encode()
    block = hashlib.sha256(head).digest()
    return head + block * (6000 + 1500 * (generation % 5))
'''


def test_a_writer_killed_anywhere_leaves_whole_files_and_a_true_manifest(tmp_path):
    """SIGKILL at random points: every visible file is a whole version of itself, and what a
    rerun takes as done matches its row; a done file cut short afterwards (what a crash that
    loses the file's last writes would leave) is not taken."""
    sys.path.insert(0, str(tmp_path))
    (tmp_path / "writer_content.py").write_text(CONTENT)
    (tmp_path / "writer.py").write_text(WRITER)
    try:
        from writer_content import content
    finally:
        sys.path.remove(str(tmp_path))
    out = tmp_path / "out"
    out.mkdir()
    names = ["R01_S00", "R01_S01", "R01_S02"]
    ccds = [fp.ccd(n) for n in names]
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([repo, str(tmp_path)]))
    rng = random.Random(20261203)
    accepted = 0
    for _ in range(8):
        proc = subprocess.Popen([sys.executable, str(tmp_path / "writer.py"), str(out),
                                 runner.__version__, *names], stdout=subprocess.PIPE, env=env)
        assert proc.stdout.readline() == b"ready\n"
        time.sleep(rng.uniform(0.0, 0.4))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        rows = runner.read_manifest(str(out))  # whole: it is renamed into place too
        for name in os.listdir(out):
            if name.startswith("."):
                continue  # the killed writer's temporaries
            data = (out / name).read_bytes()
            if name == runner.MANIFEST:
                assert data.startswith(b"detector,")
                continue
            head = data.split(b"\n", 1)[0].decode().split()
            assert head[0] == name[:-5] and data == content(head[0], int(head[1]))
        todo, done = runner.triage("s" * 64, ccds, str(out))
        for ccd in done:
            path = out / f"{ccd.name}.fits"
            assert path.stat().st_size > 0 and sha(path) == rows[ccd.name]["sha256"]
        accepted += len(done)
        for ccd in done[:1]:  # the same file cut short: its size no longer matches its row
            path = out / f"{ccd.name}.fits"
            with open(path, "r+b") as stream:
                stream.truncate(path.stat().st_size // 3)
            assert ccd in runner.triage("s" * 64, ccds, str(out))[0]
            os.remove(path)
        atomic.remove_temporaries_of(str(out), [proc.pid])
    assert accepted > 0  # the kills did not all come before the first file
