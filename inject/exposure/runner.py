"""The focal-plane runner: one CCD per task on any ``concurrent.futures.Executor``, for
``inject focalplane`` (:func:`run`: one output directory) and ``inject survey --render``
(:func:`run_batches`: a directory per visit, each visit's plan made on the executor).

A process pool by default; a Dask cluster through ``client.get_executor()`` (see
:func:`dask_executor`). Each task simulates one CCD, writes its FITS file atomically and
returns a small manifest row, never pixels. A CCD's bytes depend only on the scene and the
detector (every random stream is keyed on the scene seed, the detector id or star tile, and the
purpose), so the worker count, the scheduler, the order and the other CCDs asked for do not
change them.

``manifest.csv`` in the output directory has one row per CCD (``detector, id, vendor, file,
sha256, size, mtime_ns, streaks, seconds, status``, plus the scene's digest and the software
version), rewritten atomically under a lock after every CCD; each CCD's file is flushed to
disk and moved into place together with its row (:func:`commit`), so a run stopped or killed
partway, a node that crashed, or several ``--job`` slices sharing the directory leave a
manifest that says what is done. A stop signal cancels the CCDs not started and stops a
process pool's workers at once (:func:`stop_workers`). A rerun skips the CCDs whose file
matches its row (its size and modification time; its SHA-256 too with ``verify``), redoes
missing, changed or corrupt ones, and removes the temporary files a killed worker left
(:func:`inject.io.atomic.remove_stale_temporaries`). A directory
holds one scene's run by one inject version: another run, and a file in no manifest row,
are replaced only with ``overwrite``; the other run is checked at the start and again under
the lock before each CCD is committed (:func:`check_claim`), so that of two runs of
different scenes started together the second stops.

A CCD that fails does not stop the others; its row says ``failed`` with the error in one line.
Failures on the input (an :class:`~inject.errors.InjectError` that is not a condition of the
machine: :class:`~inject.errors.InputError`, ``SceneError``, ``FileFormatError``,
``OrbitError``; see :func:`deterministic`) are reported at once: the same scene and detector
would fail the same way again. They come back from the worker as a failed row, not raised, so
that Dask's own retries do not repeat them either. Anything else (a full disk, memory, a killed
worker, an unexpected exception) is retried ``retries`` times first. The run's
:class:`RunResult` lists the failed rows, and :meth:`RunResult.error` makes of them one
:class:`~inject.errors.RunError` for the command line to report (exit status 2).
"""
import contextlib
import csv
import hashlib
import io
import logging
import multiprocessing
import os
import resource
import signal
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field

from inject import __version__
from inject.errors import InjectError, InputError, OutputError, RunError
from inject.progress import Progress

log = logging.getLogger(__name__)

MANIFEST = "manifest.csv"
FIELDS = ("detector", "id", "vendor", "file", "sha256", "size", "mtime_ns", "streaks", "seconds",
          "status", "scene_sha256", "inject_version", "error")

#: Environment variables that cap the threads of BLAS/OpenMP libraries in workers.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")

#: Longest error text kept in a manifest row.
MAX_ERROR = 300

_LIMITED = False


def limit_threads():
    """One thread for BLAS/OpenMP (threadpoolctl and the environment), OpenCV, OpenImageIO
    and the noise draws in this process: the parallelism is one CCD per worker; and the
    freed memory kept for the next CCD (:func:`keep_freed_memory`). Idempotent."""
    global _LIMITED
    if _LIMITED:
        return
    for name in THREAD_ENV:
        os.environ[name] = "1"
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    with contextlib.suppress(ImportError):
        import cv2

        cv2.setNumThreads(1)
    with contextlib.suppress(ImportError):
        import OpenImageIO

        OpenImageIO.attribute("threads", 1)
    from inject import scene

    scene.NOISE_THREADS = 1  # the amplifiers' noise draws (bytes do not depend on it)
    keep_freed_memory()
    _LIMITED = True


#: glibc's ``mallopt`` parameters (``malloc.h``).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Allocations up to this size come from the heap in a worker, bytes.
HEAP_ALLOCATIONS_UP_TO = 1 << 30


def keep_freed_memory():
    """Let this process reuse the memory of one CCD's planes for the next: with glibc, every
    allocation up to :data:`HEAP_ALLOCATIONS_UP_TO` comes from the heap, which gives memory
    back only when more than that lies free at its top. By default an array over 32 MiB is
    mapped from the kernel and given back when freed, so each CCD's planes would fault in
    and zero ~260 MB of new pages again (half the system time of a CCD). The peak memory is
    the same: a worker renders one CCD at a time. Nothing is changed elsewhere (no glibc).

    Returns
    -------
    bool
        Whether the C library took both settings.
    """
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)  # the C library's, if it has one
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, HEAP_ALLOCATIONS_UP_TO)) and bool(
        mallopt(_M_TRIM_THRESHOLD, HEAP_ALLOCATIONS_UP_TO))


def sha256_file(path, chunk=1 << 22):
    """SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while block := stream.read(chunk):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class Task:
    """One CCD to render: the scene, the detector, where, its streaks from the plan, and how.

    Attributes
    ----------
    keep : bool
        False: write, hash and delete (benchmarks of whole exposures).
    box : tuple or None
        ``(x0, y0, nx, ny)``: render only those pixels of the CCD
        (:func:`inject.exposure.ccd.simulate_ccd`); None: the scene's cut-out or the CCD.
    compression : str or None
        The file's tile compression (:data:`inject.io.fits.COMPRESSIONS`).
    measure : callable or None
        ``measure(task, ccd, scene, result, streaks, part)``, called on the written file
        ``part`` before it is committed (a module-level function: a worker unpickles it);
        what it returns comes back as the result's ``measured``.
    planned : object
        What ``measure`` needs from the caller.
    version : str or None
        The inject version of the run (the caller's, read once): the worker writes it in the
        files, records it and claims with it. A checkout's version follows its commits and,
        on a dirty tree, the date, so a worker reading its own could call its run's rows
        another version's.
    lock : bool
        Lock the manifest (:func:`inject.io.atomic.set_locking`; False: ``--no-lock``, the
        run is the folder's only writer). The caller's setting, which a worker process takes.
    """

    fscene: object
    detector: str
    outdir: str
    streaks: tuple
    keep: bool = True
    box: tuple | None = None
    compression: str | None = None
    measure: object = None
    planned: object = None
    version: str | None = None
    lock: bool = True


def render_ccd(task):
    """Simulate one CCD and write ``OUTDIR/<detector>.fits``; return its manifest row.

    In a worker process threads are limited first (a thread pool in the caller's process is
    left alone). The file is written beside its name, measured (``task.measure``), then moved
    into place and its row recorded together, under the manifest's lock, once
    :func:`check_claim` finds no other run in the directory (a file present is replaced: the
    runner decided beforehand that it may be). If another run has taken the directory
    meanwhile, nothing is moved and the row says ``claimed`` (the runner stops the run).
    Without locks (``task.lock`` false) the finished file is left under its temporary name,
    given in the row's ``part``, for the runner to commit in its own process.
    """
    if _worker_process():
        limit_threads()
        if task.version is not None:
            # A worker process writes as the run it serves (INJVER too), whatever it would read.
            import inject

            inject.__version__ = task.version
    from inject.camera import layout as fp
    from inject.exposure.ccd import ccd_cards, simulate_ccd
    from inject.io.atomic import set_locking, temporary_prefix
    from inject.io.fits import write_exposure

    set_locking(task.lock)
    start = time.perf_counter()
    ccd = fp.ccd(task.detector)
    scene, result, streaks, wcs = simulate_ccd(task.fscene, ccd, task.streaks, box=task.box)
    simulated = time.perf_counter()
    path = os.path.join(task.outdir, f"{ccd.name}.fits")
    # A temporary name (removed by the clean-up of temporary files if this process dies).
    part = os.path.join(task.outdir, f"{temporary_prefix()}part-{ccd.name}.fits")
    cards = ccd_cards(ccd, task.fscene.digest)
    measured = None
    handed = None
    try:
        # The digest of the bytes as they are written: no second read of the file.
        digest = write_exposure(part, scene, result, scene.detector.gain,
                                wcs_header=wcs.to_header(relax=True), overwrite=True,
                                primary_cards=cards, compression=task.compression,
                                xy0=(0, 0) if task.box is None else task.box[:2])
        written = time.perf_counter()
        if task.measure is not None:
            measured = task.measure(task, ccd, scene, result, streaks, part)
        end = time.perf_counter()
        row = {"detector": ccd.name, "id": ccd.id, "vendor": ccd.vendor,
               "file": os.path.basename(path), "sha256": digest, "streaks": len(streaks),
               "seconds": round(end - start, 3), "status": "done",
               "scene_sha256": task.fscene.digest,
               "inject_version": task.version or __version__, "error": ""}
        if task.lock:
            claimed = commit(task.outdir, row, part if task.keep else None)
        else:  # no lock to share the manifest by: the runner commits, one CCD at a time
            claimed, handed = None, part if task.keep else None
            row = dict(row, part=handed)
    finally:
        if handed is None:
            with contextlib.suppress(FileNotFoundError):
                os.remove(part)  # not moved: a failure, a stop, another run, or keep=False
    if claimed is not None:
        return {"detector": ccd.name, "status": "claimed", "error": claimed}
    return dict(row, **{  # Not in the manifest: for benchmarks and the caller's measures.
        "simulate_s": simulated - start, "write_s": written - simulated,
        "measure_s": end - written, "measured": measured,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "pid": os.getpid()})


def _worker_process():
    """Whether this process is a worker, not the caller's own: a child process (a process
    pool's, a LocalCluster's, a nanny's) or a Dask worker started on its own (``dask worker
    --no-nanny``, which is no one's child). A worker takes its threads and the run's version
    from the task; the caller's process (a thread pool) keeps its own."""
    if multiprocessing.parent_process() is not None:
        return True
    distributed = sys.modules.get("distributed")  # never imported here: a worker has it
    if distributed is None:
        return False
    try:
        distributed.get_worker()
    except ValueError:  # not in a Dask worker's task
        return False
    return True


def commit(outdir, row, part=None):
    """Move a CCD's finished file ``part`` into place (if given) and record its row, both under
    the manifest's lock, unless another scene's run holds the directory (:func:`check_claim`).

    The file is flushed to disk before it is moved and the folder after, so that a crash does
    not leave a row saying done over an empty file; the row records the file's size and
    modification time, which a rerun checks (:func:`triage`). A stop signal arriving meanwhile
    waits until both are done: the manifest never says less than the files.

    Returns
    -------
    str or None
        None once committed; else why not (another scene's run), and nothing was changed.
    """
    from inject.io.atomic import fsync_directory, fsync_file
    from inject.signals import deferred

    if part is not None:
        fsync_file(part)  # before the lock: the other writers need not wait for the disk
        st = os.stat(part)
        row = dict(row, size=st.st_size, mtime_ns=st.st_mtime_ns)  # a rename keeps both
    with deferred(), _manifest_lock(outdir):
        rows = read_manifest(outdir)
        try:
            check_claim(outdir, rows, row["scene_sha256"], row["inject_version"])
        except OutputError as err:
            return str(err)
        if part is not None:
            os.replace(part, os.path.join(outdir, row["file"]))
            fsync_directory(outdir)  # the file's name on disk before the row that says done
        rows[row["detector"]] = {k: str(row.get(k, "")) for k in FIELDS}
        _write_manifest(outdir, rows)
    return None


def deterministic(err):
    """Whether a CCD that failed with ``err`` would fail the same way on a retry.

    True for an :class:`~inject.errors.InjectError` about the input (``InputError``,
    ``SceneError``, ``FileFormatError``, ``OrbitError``...: the CCD's bytes, and so its errors,
    depend only on the scene and the detector). False for the conditions of the machine,
    ``OutputError`` (an :class:`OSError`: a full disk) and ``ResourceError`` (a
    :class:`MemoryError`), which a retry may not meet, and for anything that is not an
    ``InjectError`` (a killed worker, a bug).
    """
    return isinstance(err, InjectError) and not isinstance(err, (OSError, MemoryError))


def error_text(err):
    """``err`` in one line for a manifest row: an :class:`~inject.errors.InjectError`'s own
    message (as the command line prints it), anything else after its class name."""
    text = str(err) if isinstance(err, InjectError) else f"{type(err).__name__}: {err}"
    return " ".join(text.split())[:MAX_ERROR]


#: Set in the process pool's workers (:func:`_init_worker`).
_POOL_WORKER = False


def _init_worker():
    """A process pool worker's start: one thread per library; the stop signals back to their
    default action (an idle worker ends at once, without a traceback), except those ignored
    (``nohup``). While a task runs, :func:`_attempt` makes them clean stops instead."""
    global _POOL_WORKER
    from inject.signals import STOP_SIGNALS

    limit_threads()
    for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
    _POOL_WORKER = True


def _attempt(function, *args):
    """``function(*args)`` in the worker (a CCD's render, or the work that makes a scene's
    plan), where a failure on the input becomes a ``failed`` result (see
    :func:`deterministic`): returned, not raised, so that no one retries it.

    In a process pool's worker a stop signal (the runner stopping the pool, or Ctrl-C) ends
    the task as it ends a command: the temporary files are removed, a file being committed is
    committed with its row (:func:`commit`), and the worker process exits.
    """
    from inject.signals import Stopped, handling

    try:
        with handling() if _POOL_WORKER else contextlib.nullcontext():
            return function(*args)
    except Stopped as stop:
        if _POOL_WORKER:
            os._exit(stop.exit_status)  # the pool is being stopped: no result to send
        raise
    except InjectError as err:
        if not deterministic(err):
            raise
        return {"status": "failed", "error": error_text(err)}


# -------------------------------------------------------------------------------------------
# The manifest

#: The manifest's lock file; it exists only while a process holds the lock.
LOCK = ".manifest.lock"


@contextlib.contextmanager
def _manifest_lock(outdir):
    """An exclusive lock on the directory's manifest (``--job`` slices and the workers share
    it).

    The lock file is removed by its holder before the lock is released, so none is left
    behind. A process that locked a file just removed (it opened the name before the removal)
    sees that the name no longer leads to its file, and tries again on a new one. With locking
    off (``--no-lock``: :func:`inject.io.atomic.set_locking`) nothing is locked.
    """
    from inject.io.atomic import lock, locking
    from inject.signals import deferred

    if not locking():  # --no-lock: the only writer
        yield
        return
    path = os.path.join(outdir, LOCK)
    fd = None
    try:
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            lock(fd, outdir)  # an OutputError on a file system without locks
            with contextlib.suppress(FileNotFoundError):
                mine, named = os.fstat(fd), os.stat(path)
                if (mine.st_dev, mine.st_ino) == (named.st_dev, named.st_ino):
                    break
            os.close(fd)
            fd = None
        yield
    finally:
        if fd is not None:
            with deferred():
                with contextlib.suppress(FileNotFoundError):
                    os.remove(path)  # while still held: no one else can hold this file
                os.close(fd)


def read_manifest(outdir):
    """The manifest's rows by detector name ({} when there is none)."""
    path = os.path.join(outdir, MANIFEST)
    if not os.path.exists(path):
        return {}
    with open(path, newline="") as stream:
        return {row["detector"]: row for row in csv.DictReader(stream)}


def _write_manifest(outdir, rows):
    from inject.io.atomic import atomic_path

    text = io.StringIO()
    writer = csv.DictWriter(text, FIELDS, extrasaction="ignore")
    writer.writeheader()
    for row in sorted(rows.values(), key=lambda r: int(r["id"])):
        writer.writerow(row)
    with atomic_path(os.path.join(outdir, MANIFEST), overwrite=True) as tmp:
        with open(tmp, "w", newline="") as stream:
            stream.write(text.getvalue())


def update_manifest(outdir, new_rows, digest=None):
    """Merge rows into the manifest, under the lock, atomically. With the scene's ``digest``,
    first check that no other scene's run has taken the directory (:func:`check_claim`)."""
    with _manifest_lock(outdir):
        rows = read_manifest(outdir)
        if digest is not None:
            check_claim(outdir, rows, digest)
        for row in new_rows:
            rows[row["detector"]] = {k: str(row.get(k, "")) for k in FIELDS}
        _write_manifest(outdir, rows)


def _other_scenes(rows, digest, version=None):
    """``{(digest, version): [row, ...]}`` of the manifest rows of another run: of another
    scene, or made by another inject version than ``version`` (default this process's: its
    files may differ from this one's)."""
    out = {}
    for row in rows.values():
        theirs = (row.get("scene_sha256") or "?", row.get("inject_version") or "?")
        if theirs != (digest, version or __version__):
            out.setdefault(theirs, []).append(row)
    return out


def _describe(other, rows, mine=None):
    counts = {}
    for row in rows:
        counts[row.get("status") or "?"] = counts.get(row.get("status") or "?", 0) + 1
    states = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
    digest, version = other
    by = f" by inject {version}" if version != (mine or __version__) else ""
    return f"the run of scene {digest[:12]}{by} ({states})"


def check_claim(outdir, rows, digest, version=None):
    """Raise :class:`~inject.errors.OutputError` if the manifest ``rows`` hold another run's
    rows: another run took the directory after this one began (the runner removed or refused
    any other run's rows at its start). ``version``: the run's (default this process's). Call
    it under the manifest's lock."""
    others = _other_scenes(rows, digest, version)
    if others:
        other, theirs = next(iter(others.items()))
        raise OutputError(f"{outdir}: {_describe(other, theirs, version)} has taken this directory "
                          f"since this run began; this run stopped and left that run's files "
                          f"as they are")


def check_free(outdir, digest, ccds, rows=None):
    """Raise :class:`~inject.errors.OutputError` if a run of the scene ``digest`` in ``outdir``
    would replace, without ``--overwrite``, another run (another scene's or another inject
    version's rows: done, failed or pending) or a CCD file in no manifest row."""
    rows = read_manifest(outdir) if rows is None else rows
    others = _other_scenes(rows, digest)
    if others:
        other, theirs = next(iter(others.items()))
        names = {r["detector"] for r in theirs}
        hit = [c.name for c in ccds if c.name in names
               and os.path.exists(os.path.join(outdir, f"{c.name}.fits"))]
        where = f"{os.path.join(outdir, hit[0] + '.fits')}: exists, of" if hit else \
            f"{outdir}: holds"
        raise OutputError(f"{where} {_describe(other, theirs)}; pass --overwrite to replace "
                          "that run")
    for ccd in ccds:
        path = os.path.join(outdir, f"{ccd.name}.fits")
        if ccd.name not in rows and os.path.exists(path):
            raise OutputError(f"{path}: exists (not in any manifest); pass --overwrite to "
                              "replace it")


def finished(row, path, verify=False):
    """Whether the file ``path`` is the one its manifest ``row`` recorded as done.

    The row's size and modification time (recorded when the file was committed) must be the
    file's; with ``verify`` its SHA-256 too (the whole file read). A row of an older manifest,
    with neither, is checked by its SHA-256. A file changed since (rewritten, cut short by a
    crash, copied without its times) differs in size or time; a change that keeps both,
    such as bytes flipped on the disk, only ``verify`` finds.
    """
    if row is None or row.get("status") != "done":
        return False
    try:
        st = os.stat(path)
    except OSError:
        return False
    size, mtime = row.get("size") or "", row.get("mtime_ns") or ""
    if size or mtime:
        if (str(st.st_size), str(st.st_mtime_ns)) != (size, mtime):
            return False
        if not verify:
            return True
    return row.get("sha256") == sha256_file(path)


def triage(digest, ccds, outdir, overwrite=False, verify=False):
    """Split CCDs into those to render and those already done; with ``overwrite``, clear the
    directory of another run.

    A directory holds one scene's run, by one inject version. Rows of another run (done,
    failed or pending: a run that is going, or was stopped) are refused without
    ``overwrite`` (:func:`check_free`); with it, they and their CCD files are removed. Then,
    for each CCD: a file matching its manifest row (this scene, ``done``, the size and
    modification time recorded, and with ``verify`` the SHA-256: :func:`finished`) is done; a
    missing file, or one whose row is this scene's but not done or that does not match
    (changed, corrupt, or a run killed before the row said done), is redone; a file in no
    manifest row is replaced only with ``overwrite``. Call it under the manifest's lock.

    Returns
    -------
    todo, done : list of CCD

    Raises
    ------
    OutputError
        Another run, or a file in no manifest, would be replaced without ``overwrite``.
    """
    rows = read_manifest(outdir)
    if not overwrite:
        check_free(outdir, digest, ccds, rows)
    others = _other_scenes(rows, digest)
    if others:
        _remove_rows_and_files(outdir, rows, [r for theirs in others.values() for r in theirs])
    todo, done = [], []
    for ccd in ccds:
        path = os.path.join(outdir, f"{ccd.name}.fits")
        if finished(rows.get(ccd.name), path, verify):
            done.append(ccd)
        else:  # missing, broken, not recorded done, or (with overwrite) in no manifest
            todo.append(ccd)
    return todo, done


def _remove_rows_and_files(outdir, rows, removed):
    """Remove rows (in place and in the manifest) and the CCD files they name."""
    from inject.camera.layout import BY_NAME

    for row in removed:
        name = row["detector"]
        if name in BY_NAME:  # never a path a manifest could smuggle in
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(outdir, f"{name}.fits"))
        rows.pop(name, None)
    _write_manifest(outdir, rows)


# -------------------------------------------------------------------------------------------
# Running

def slice_ccds(ccds, job=None, njobs=None):
    """The ``job``-th (0-based) of ``njobs`` interleaved slices of CCDs (batch arrays)."""
    if job is None and njobs is None:
        return tuple(ccds)
    if job is None or njobs is None:
        raise InputError("--job/--njobs", (job, njobs), "give both")
    if not (isinstance(njobs, int) and njobs >= 1):
        raise InputError("--njobs", njobs, "must be an integer >= 1")
    if not (isinstance(job, int) and 0 <= job < njobs):
        raise InputError("--job", job, f"must be in [0, {njobs - 1}] (0-based)")
    return tuple(ccds)[job::njobs]


class _CCDProgress:
    """The run's progress over its CCDs (:class:`inject.progress.Progress`): each CCD's row
    at DEBUG, a failed one's at WARNING (the run goes on without it)."""

    def __init__(self, total):
        self.progress = Progress(total, "rendering CCDs", "CCD", log)

    def update(self, row):
        seconds = f" {row['seconds']} s" if row.get("seconds") not in (None, "") else ""
        extra = f" ({row['error']})" if row.get("error") else ""
        note = f"{row['detector']} {row['status']}{seconds}{extra}"
        if row.get("status") == "failed":
            log.warning("%s", note)
        else:
            log.debug("%s", note)
        self.progress.update(note)

    def close(self):
        self.progress.close()


@dataclass
class RunResult:
    """What a run did: manifest rows of the CCDs rendered now, skipped and failed."""

    rendered: list
    skipped: list
    failed: list

    def error(self, outdir=None, shown=3):
        """A :class:`~inject.errors.RunError` that says which CCDs failed and why (the CCDs
        that share an error together, the first ``shown`` errors in full), or None if none
        did. ``outdir``: where the manifest is, for the message."""
        if not self.failed:
            return None
        rows = sorted(self.failed, key=lambda r: int(r["id"]))
        groups = {}
        for row in rows:
            groups.setdefault(row["error"], []).append(row["detector"])
        parts = []
        for text, names in list(groups.items())[:shown]:
            more = f" and {len(names) - 4} more" if len(names) > 4 else ""
            parts.append(f"{', '.join(names[:4])}{more}: {text}")
        if len(groups) > shown:
            parts.append(f"{len(groups) - shown} other error(s)")
        total = len(self.rendered) + len(self.skipped) + len(self.failed)
        where = f"each CCD's error is in {os.path.join(outdir, MANIFEST)}; " if outdir else ""
        return RunError(f"{len(rows)} of {total} CCDs failed ({'; '.join(parts)}); {where}"
                        f"the others are done, and a rerun redoes only the failed ones",
                        [(row["detector"], row["error"]) for row in rows])


def check_outdir(outdir):
    """Raise :class:`~inject.errors.OutputError` unless ``outdir`` is a directory, or can be
    made as one: its parent must exist (as every command's output file needs its folder:
    :func:`inject.io.atomic.check_writable`)."""
    if os.path.isdir(outdir):
        return
    if os.path.lexists(outdir):
        raise OutputError(f"{outdir}: exists and is not a directory")
    parent = os.path.dirname(os.path.abspath(outdir))
    if not os.path.isdir(parent):
        raise OutputError(f"{outdir}: directory {parent} does not exist")


def make_outdir(outdir):
    """Create the output directory if it is missing; its parent must exist (as every
    command's output file needs its folder: :func:`inject.io.atomic.check_writable`).

    Raises
    ------
    OutputError
        ``outdir`` is not a directory, or its parent is missing or not writable.
    """
    check_outdir(outdir)
    if os.path.isdir(outdir):
        return
    try:
        os.mkdir(outdir)
    except FileExistsError:
        if not os.path.isdir(outdir):  # made meanwhile by a --job slice: fine
            raise OutputError(f"{outdir}: exists and is not a directory") from None
    except OSError as err:
        raise OutputError(f"{outdir}: cannot create it ({err.strerror or err})") from None


def cancel(executor, futures):
    """Cancel the futures not yet started. A process pool cancels its own (in its manager
    thread, which may otherwise set a cancelled future's result and fail) and takes no more
    work."""
    if isinstance(executor, ProcessPoolExecutor):
        executor.shutdown(wait=False, cancel_futures=True)
    else:
        for future in futures:
            future.cancel()


#: Seconds the stopped workers of a process pool have to end on their own (they stop at
#: their next Python step, in milliseconds) before they are killed.
STOP_GRACE_S = 0.5


def stop_workers(executor, outdirs=(), grace=STOP_GRACE_S):
    """Stop a process pool's worker processes now, whatever they are doing.

    Each worker gets SIGTERM: its task ends as a command's does (its temporary files removed;
    a CCD being committed is committed with its row) and the process exits. A worker still
    alive after ``grace`` seconds is killed, and its temporary files in ``outdirs`` (the
    run's output directories) removed.
    Other executors (threads, Dask) have no processes of their own to stop: their tasks
    already under way finish (and commit) by themselves.

    Returns
    -------
    int
        The worker processes stopped.
    """
    processes = getattr(executor, "_processes", None)  # ProcessPoolExecutor's, by pid
    if not processes:
        return 0
    for _ in range(3):  # the pool's own thread may change the mapping meanwhile
        try:
            workers = list(processes.values())
            break
        except RuntimeError:
            continue
    else:
        return 0
    for worker in workers:
        with contextlib.suppress(Exception):
            worker.terminate()
    deadline = time.monotonic() + grace
    for worker in workers:
        with contextlib.suppress(Exception):
            worker.join(max(0.0, deadline - time.monotonic()))
    killed = [w for w in workers if w.is_alive()]
    for worker in killed:
        with contextlib.suppress(Exception):
            worker.kill()
            worker.join(5.0)
    if killed:
        from inject.io.atomic import remove_temporaries_of

        for outdir in outdirs:
            remove_temporaries_of(outdir, [w.pid for w in killed])
    return len(workers)


@dataclass(frozen=True)
class Batch:
    """The CCDs of one output directory, one scene's run there: a part of :func:`run_batches`.

    Attributes
    ----------
    outdir : str
        Created if missing (its parent must exist).
    digest : str
        The scene's digest (the manifest's ``scene_sha256``, the run's claim on ``outdir``);
        the plan's scene carries the same.
    ccds : tuple of CCD
    plan : inject.exposure.plan.Plan or None
        The scene's plan; None until ``prepare`` has made it.
    prepare : tuple
        ``(function, *args)``: run on the executor (retried and failed as a CCD is, for all
        the batch's CCDs) to make the plan, once a CCD is to be rendered.
    task : dict
        :class:`Task` fields for every CCD (``keep``, ``compression``, ``measure``,
        ``planned``).
    cutout : int or None
        Render each CCD as a square of this side centred on its streaks
        (:func:`inject.exposure.ccd.cutout_box`).
    done : callable or None
        ``done(ccd)``: whether a CCD whose file matches its manifest row is done (False: it is
        rendered again), for outputs beside the file.
    """

    outdir: str
    digest: str
    ccds: tuple
    plan: object = None
    prepare: tuple = ()
    task: dict = field(default_factory=dict)
    cutout: int | None = None
    done: object = None

    def make_task(self, plan, ccd):
        """The :class:`Task` of one CCD, with the batch's plan."""
        from inject.exposure.ccd import cutout_box

        streaks = tuple(plan.streaks(ccd))
        box = None if self.cutout is None else cutout_box(ccd, streaks, self.cutout)
        from inject.io.atomic import locking

        # Absolute: a worker elsewhere (a Dask cluster's) has another working directory.
        return Task(plan.fscene, ccd.name, os.path.abspath(self.outdir), streaks, box=box,
                    version=__version__, lock=locking(), **self.task)


def _claim(batch, overwrite, verify=False):
    """Triage a batch's CCDs (:func:`triage`) and claim its directory for the run: a pending
    row for each CCD to render, so that a run killed before a CCD's row says done still marks
    its file as this scene's, to be redone, and another scene's run is refused from now on.
    Temporary files a killed run left are removed first.

    Returns
    -------
    todo : list of CCD
    done : list of dict
        The manifest rows of the CCDs done.
    """
    from inject.io.atomic import remove_stale_temporaries

    outdir = batch.outdir
    with _manifest_lock(outdir):
        stale = remove_stale_temporaries(outdir)  # left by a killed run
        if stale:
            log.warning("removed %d temporary file(s) left in %s by a run that was killed",
                        len(stale), outdir)
        todo, done = triage(batch.digest, batch.ccds, outdir, overwrite, verify)
        if batch.done is not None:  # outputs beside a file missing or another run's
            redo = {c.name for c in done if not batch.done(c)}
            todo = [c for c in batch.ccds if c in todo or c.name in redo]
            done = [c for c in done if c.name not in redo]
        rows = read_manifest(outdir)
        for c in todo:
            rows[c.name] = {"detector": c.name, "id": c.id, "vendor": c.vendor,
                            "file": f"{c.name}.fits", "status": "pending",
                            "scene_sha256": batch.digest, "inject_version": __version__}
        _write_manifest(outdir, rows)
    return todo, [dict(rows[c.name], outdir=outdir) for c in done]


def run_batches(batches, executor, overwrite=False, retries=2, progress=None, verify=False):
    """Render the CCDs of several output directories (:class:`Batch`) on ``executor``,
    resumably: one loop of submissions, retries, failures and a stop for them all.

    Every directory is checked before any is claimed (a refusal leaves them all as they
    were), and all are claimed before any work starts (:func:`_claim`). Then each batch's
    plan is made (``prepare``) where it is not given, and its CCDs rendered
    (:func:`render_ccd`).

    Parameters
    ----------
    batches : sequence of Batch
    executor : concurrent.futures.Executor
        Any: a process pool, Dask's ``client.get_executor()``, a thread pool.
    overwrite : bool
        Replace the run of another scene (or inject version) in a directory (its CCD files
        and rows, whichever CCDs this run renders) and files of no recorded run.
    retries : int
        Times a failed task is resubmitted (on top of the executor's own retries) before its
        CCDs are reported as failed; the other CCDs go on regardless. A task that fails on its
        input (:func:`deterministic`) fails at once.
    progress : object, optional
        ``update(row)`` after each CCD rendered or failed, ``close()`` at the end (default:
        :mod:`inject.progress` on this module's logger, and each CCD's row at DEBUG, a
        failed one's at WARNING).
    verify : bool
        Hash each finished file again before taking it as done (default: its size and
        modification time must be those its row recorded: :func:`finished`).

    Returns
    -------
    RunResult
        Its rows carry their ``outdir``; a rendered row its ``measured``.

    Raises
    ------
    OutputError
        At the start, as :func:`triage` says; later, another run took a directory
        (:func:`check_claim`, checked under the lock at each CCD's commit).
    Stopped, KeyboardInterrupt
        A stop signal: the queued tasks are cancelled and a process pool's workers stopped
        (:func:`stop_workers`, which removes their temporary files) before it is raised; the
        CCDs committed before are ``done`` in the manifests, the others stay ``pending`` with
        no file of theirs left.
    """
    for batch in batches:
        make_outdir(batch.outdir)
    if not overwrite:
        for batch in batches:
            check_free(batch.outdir, batch.digest, batch.ccds)
    todo, skipped = [], []
    for batch in batches:
        mine, done = _claim(batch, overwrite, verify)
        todo.append(mine)
        skipped += done
    progress = progress or _CCDProgress(sum(map(len, todo)))
    plans = [batch.plan for batch in batches]
    attempts, pending = {}, {}
    rendered, failed = [], []

    def fail(k, ccds, text):
        batch = batches[k]
        for ccd in ccds:
            row = {"detector": ccd.name, "id": ccd.id, "vendor": ccd.vendor,
                   "file": f"{ccd.name}.fits", "sha256": "", "streaks": "", "seconds": "",
                   "status": "failed", "scene_sha256": batch.digest,
                   "inject_version": __version__, "error": text}
            update_manifest(batch.outdir, [row], batch.digest)
            failed.append(dict(row, outdir=batch.outdir))
            progress.update(row)

    def submit(k, ccd=None):
        """A CCD's task, or (``ccd`` None) the batch's plan."""
        try:
            if ccd is None:
                future = executor.submit(_attempt, *batches[k].prepare)
            else:
                # render_ccd as this module holds it now (tests replace it to make CCDs fail).
                future = executor.submit(_attempt, render_ccd,
                                         batches[k].make_task(plans[k], ccd))
        except Exception as err:  # a broken pool (a worker killed): report, go on
            fail(k, todo[k] if ccd is None else [ccd], error_text(err))
        else:
            pending[future] = (k, ccd)

    try:
        for k, ccds in enumerate(todo):
            if ccds and plans[k] is None:
                submit(k)
            elif ccds:
                for ccd in ccds:
                    submit(k, ccd)
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                k, ccd = pending.pop(future)
                ccds = todo[k] if ccd is None else [ccd]
                try:
                    value = future.result()
                except Exception as err:  # a worker's failure must not lose the others
                    tag = (k, None if ccd is None else ccd.name)
                    attempts[tag] = attempts.get(tag, 0) + 1
                    if attempts[tag] <= retries:
                        submit(k, ccd)
                    else:
                        fail(k, ccds, error_text(err))
                    continue
                status = value.get("status") if isinstance(value, dict) else None
                if status == "claimed":  # by another run: stop this one
                    raise OutputError(value["error"])
                if status == "failed":  # on its input (see _attempt): not retried
                    fail(k, ccds, value["error"])
                elif ccd is None:  # the batch's plan
                    plans[k] = value
                    for each in todo[k]:
                        submit(k, each)
                else:
                    if "part" in value:  # no locks: committed here, one CCD at a time
                        part = value.pop("part")
                        claimed = commit(batches[k].outdir, value, part)
                        if claimed is not None:
                            if part is not None:
                                with contextlib.suppress(FileNotFoundError):
                                    os.remove(part)
                            raise OutputError(claimed)
                    rendered.append(dict(value, outdir=batches[k].outdir))  # committed
                    progress.update(value)
    except BaseException:
        # A stop signal, another run, or a bug: nothing more is to start or finish.
        cancel(executor, pending)
        stop_workers(executor, [batch.outdir for batch in batches])
        raise
    finally:
        remove_lost_temporaries(executor, [batch.outdir for batch in batches])
        progress.close()
    return RunResult(rendered, skipped, failed)


def remove_lost_temporaries(executor, outdirs):
    """Remove the temporary files that the workers lost during the run (a Dask worker killed
    or crashed: Dask ran its tasks again on another) left in ``outdirs``.

    The executor says which worker processes it lost (``lost_pids()``, set by
    :func:`dask_executor`; other executors have none). Their files (a CCD's, when the worker
    died while writing it) would otherwise stay until a rerun finds them stale
    (:func:`inject.io.atomic.remove_stale_temporaries`). A file still locked by a live
    process is left alone (:func:`inject.io.atomic.remove_temporaries_of`).

    Returns
    -------
    list of str
        The files removed.
    """
    lost = getattr(executor, "lost_pids", None)
    if lost is None:
        return []
    try:
        pids = lost()
    except Exception:  # the cluster is gone too: a rerun's clean-up will do
        return []
    if not pids:
        return []
    from inject.io.atomic import remove_temporaries_of

    removed = [path for outdir in outdirs for path in remove_temporaries_of(outdir, pids)]
    log.warning("%d worker(s) lost during the run (their CCDs were rendered again); removed "
                "%d temporary file(s) they left", len(pids), len(removed))
    return removed


def run(plan, outdir, executor, ccds=None, overwrite=False, retries=2, progress=None,
        keep=True, verify=False):
    """Render CCDs of a focal-plane scene on ``executor``, resumably: :func:`run_batches` of
    one :class:`Batch`.

    Parameters
    ----------
    plan : inject.exposure.plan.Plan
        The exposure's plan (:func:`inject.exposure.plan.make_plan`).
    outdir : str
        Created if missing (its parent must exist).
    executor : concurrent.futures.Executor
    ccds : sequence of CCD, optional
        Default: the scene's.
    overwrite, retries, progress, verify
        As :func:`run_batches`.
    keep : bool
        False deletes each file once hashed (benchmarks).

    Returns
    -------
    RunResult
    """
    ccds = plan.fscene.ccds if ccds is None else tuple(ccds)
    batch = Batch(outdir, plan.fscene.digest, ccds, plan=plan, task={"keep": keep})
    return run_batches([batch], executor, overwrite, retries, progress, verify)


#: Modules every worker needs, imported once by the fork server the workers come from: a
#: worker then starts in milliseconds instead of importing GalSim, astropy and SciPy (~1.5 s).
WORKER_MODULES = ("inject.exposure.ccd", "inject.io.fits", "inject.exposure.runner",
                  "scipy.special")


def start_fork_server():
    """Start this process's fork server (once) with :data:`WORKER_MODULES` imported, and
    return the ``forkserver`` context.

    The server is started with BLAS/OpenMP limited to one thread in its environment, so that
    importing numpy there starts no thread pool: a process with threads must not fork.
    """
    from multiprocessing import forkserver

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(WORKER_MODULES))
    saved = {name: os.environ.get(name) for name in THREAD_ENV}
    os.environ.update(dict.fromkeys(THREAD_ENV, "1"))
    try:
        forkserver.ensure_running()
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return context


def stop_fork_server():
    """End this process's fork server now, if it runs (:func:`start_fork_server` starts a new
    one when a pool needs it): a command that stops need not wait for it to finish its
    imports, or for its own exit, which takes seconds."""
    from multiprocessing import forkserver

    pid = getattr(getattr(forkserver, "_forkserver", None), "_forkserver_pid", None)
    if pid:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)  # it holds nothing to save; its children are gone


def process_pool(workers=None):
    """The default executor: a process pool of ``workers`` (default: the CPUs this job may
    use, :func:`inject.exposure.sizing.job_resources`), each worker limited to one thread per
    library.

    Workers start from a fork server (:func:`start_fork_server`), not by forking the caller:
    a caller with threads (OpenImageIO's pool, BLAS, a thread pool) would hand its children
    locks held by threads that do not exist there, and they can hang on their first call
    into that library.
    """
    if not workers:
        from inject.exposure.sizing import job_resources

        workers = job_resources().cpus
    return ProcessPoolExecutor(max_workers=workers,
                               mp_context=start_fork_server(), initializer=_init_worker)


#: A worker's memory besides its CCD's planes (its own share of the libraries, the stars' PSF
#: stamps, the caches), bytes; and the peak bytes per pixel of a CCD, all planes and the
#: write included (``units: adu`` with its raw layout the most): a full CCD's worker peaks
#: near 0.8 GiB (scripts/bench_focalplane.py measures it).
WORKER_BASE_BYTES = 0.2 * 2**30
WORKER_BYTES_PER_PIXEL = 40


def worker_bytes(fscene, ccds):
    """Estimated peak memory of a worker rendering the largest of ``ccds``, and that CCD's
    ``(ny, nx)``."""
    from inject.exposure.plan import ccd_shape

    shape = max((ccd_shape(fscene, c) for c in ccds), key=lambda s: s[0] * s[1])
    return WORKER_BASE_BYTES + WORKER_BYTES_PER_PIXEL * shape[0] * shape[1], shape


#: Memory limit per Dask LocalCluster worker. A full-size CCD (IMAGE, MASK, VARIANCE,
#: STREAK_MODEL and the planes they come from) peaks near 0.9 GiB in a worker
#: (scripts/bench_focalplane.py measures it: 0.6-0.7 GiB for CCDs without the streak, 0.86
#: GiB over a whole exposure); Dask spills at 60-70% of the limit, pauses at 80% and
#: restarts the worker at 95%, so 3 GiB leaves room.
DASK_MEMORY_LIMIT = "3GiB"


@contextlib.contextmanager
def dask_executor(scheduler, workers=None, memory_limit=DASK_MEMORY_LIMIT, retries=2):
    """A ``concurrent.futures.Executor`` on Dask: ``scheduler="local"`` starts a LocalCluster
    of ``workers`` processes with one thread each; any other value is the address of a running
    scheduler (``tcp://host:8786``); ``workers`` defaults to the CPUs this job may use. Tasks
    are impure (``pure=False``) and retried
    ``retries`` times by Dask when they raise (a CCD that fails on its input returns a failed
    row instead: see :func:`run`).

    The workers found at the start must run this inject (:func:`_check_workers`); the
    executor's ``lost_pids()`` names those lost since, whose temporary files the runner
    removes (:func:`remove_lost_temporaries`)."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputError("--scheduler", scheduler, "needs Dask: pip install "
                         "'satstreak-inject[dask]'") from None
    cluster = None
    if scheduler == "local":
        if not workers:
            from inject.exposure.sizing import job_resources

            workers = job_resources().cpus
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                               processes=True, memory_limit=memory_limit,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout=30)
        except (OSError, TimeoutError, ValueError) as err:
            raise InputError("--scheduler", scheduler, f"cannot reach the Dask scheduler "
                                                       f"({err})") from None
    try:
        pids = _check_workers(client, scheduler)
        executor = client.get_executor(retries=retries, pure=False)
        executor.lost_pids = lambda: _lost_pids(client, pids)
        yield executor
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _worker_inject():
    """On a Dask worker: one thread per library (:func:`limit_threads`); return the version
    of the inject this worker imports (read afresh: a task may have set ``__version__``),
    where it is, and the worker's process id."""
    import inject
    from inject._version import get_version

    limit_threads()
    return (get_version(), os.path.dirname(os.path.dirname(os.path.abspath(inject.__file__))),
            os.getpid())


def _check_workers(client, scheduler):
    """Limit the threads of the cluster's workers and check that they run this inject.

    A worker started elsewhere imports whatever inject its environment holds (another
    checkout, an older install): its CCDs would not be this run's, yet bear its version.

    Returns
    -------
    dict
        ``{address: pid}`` of the workers.

    Raises
    ------
    InputError
        A worker cannot import inject, or imports another version of it.
    """
    import inject

    here = os.path.dirname(os.path.dirname(os.path.abspath(inject.__file__)))
    try:
        found = client.run(_worker_inject)
    except Exception as err:  # raised on the worker: no inject there, most likely
        raise InputError("--scheduler", scheduler,
                         f"its workers cannot run inject ({error_text(err)}); start them "
                         f"where this inject is installed (or with PYTHONPATH={here})") from None
    for address, (version, where, _) in sorted(found.items()):
        if version != __version__:
            raise InputError("--scheduler", scheduler,
                             f"worker {address} runs inject {version} from {where}, this "
                             f"command inject {__version__} from {here}; start the workers "
                             f"with this inject (e.g. PYTHONPATH={here})")
    log.info("Dask scheduler %s: %d worker%s running inject %s", scheduler, len(found),
             "s" if len(found) != 1 else "", __version__)
    return {address: pid for address, (_, _, pid) in found.items()}


def _lost_pids(client, pids):
    """The process ids of the workers ``pids`` (``{address: pid}``) no longer in the
    cluster."""
    try:
        now = client.scheduler_info(n_workers=-1)["workers"]
    except TypeError:  # a Dask before n_workers: all the workers, always
        now = client.scheduler_info()["workers"]
    return sorted(pid for address, pid in pids.items() if address not in now)
