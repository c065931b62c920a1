"""Atomic output: write to a temporary file beside the target, then rename it into place.

:func:`atomic_path` makes one file appear whole or not at all. :func:`output_group` does the
same for several files written by one command: inside it, every :func:`atomic_path` (whichever
writer calls it) keeps its finished temporary file, and the group moves them all into place
only when its block ends without an error, undoing the moves already made if a later one
fails. Temporary files are named ``.inject-*`` and never outlive the call, whatever stops
it: an error, Ctrl-C, or SIGTERM/SIGHUP under :func:`inject.signals.handling` (the steps that
must not be cut in two, such as creating a temporary file and registering it for removal,
hold signals until they are done). A process killed outright (SIGKILL, a lost node) cannot
clean up: :func:`remove_stale_temporaries` removes what such a process left, telling it from a
live writer's file by the lock every :func:`atomic_path` holds on its temporary file.

Each file is flushed to disk (``fsync``) before it is renamed, and its folder after: a node
that crashes just after a rename leaves the whole file under its name, not an empty one (a
file system may otherwise commit the rename before the data).

A file system mounted without ``flock`` (Lustre's ``noflock``, NFS's ``nolock``) fails each
lock with "Function not implemented". The locks on temporary files only mark them as live, and
are then left out; a lock that guards shared state (:func:`lock`) instead raises an
:class:`~inject.errors.OutputError` naming the mount options, unless locking is turned off for
the process (:func:`set_locking`: the command line's ``--no-lock``, for a run that is the only
writer of its folder).
"""
import contextlib
import contextvars
import errno
import fcntl
import os
import shutil
import tempfile
import time

from inject.errors import OutputError
from inject.signals import deferred

#: Prefix of every temporary file.
PREFIX = ".inject-"
#: A temporary file younger than this (s) is never taken for stale (it may not be locked yet).
STALE_AFTER_S = 60.0

#: The pending ``(path, temporary, overwrite)`` moves of the active :func:`output_group`.
_GROUP = contextvars.ContextVar("inject_output_group", default=None)

#: What ``flock`` fails with on a file system mounted without locks (Lustre's ``noflock``:
#: ENOSYS; NFS's ``nolock``: ENOLCK; others: EOPNOTSUPP).
NO_LOCKS = frozenset({errno.ENOSYS, errno.ENOLCK, errno.EOPNOTSUPP,
                      getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)})
#: What ``fsync`` of a folder fails with where a file system does not do it (then nothing
#: more can be done for the rename's durability).
_NO_DIR_SYNC = frozenset({errno.EINVAL, errno.EBADF, errno.EOPNOTSUPP, errno.EISDIR,
                          getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)})

_LOCKING = True


def set_locking(enabled):
    """Turn the locks of :func:`lock` on or off for this process (a worker process is told
    by its task). Off: the caller promises to be the only writer of its folders."""
    global _LOCKING
    _LOCKING = bool(enabled)


def locking():
    """Whether :func:`lock` locks (see :func:`set_locking`)."""
    return _LOCKING


@contextlib.contextmanager
def locks_off(off=True):
    """Locking off (if ``off``) for the block, as it was after it (see :func:`set_locking`)."""
    before = _LOCKING
    set_locking(before and not off)
    try:
        yield
    finally:
        set_locking(before)


def lock(fd, where, blocking=True):
    """An exclusive ``flock`` on ``fd`` (nothing if locking is off: :func:`set_locking`).

    Parameters
    ----------
    fd : int
    where : str
        The folder the lock guards, for the message.
    blocking : bool
        Wait for the lock (False: raise :class:`BlockingIOError` if it is held).

    Raises
    ------
    OutputError
        The file system does not support locks (:data:`NO_LOCKS`): one line naming the
        likely mount options and ``--no-lock``.
    """
    if not _LOCKING:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except OSError as err:
        if err.errno in NO_LOCKS:
            raise OutputError(f"{where}: its file system does not support locking (mounted "
                              f"with Lustre's noflock or NFS's nolock?): flock: "
                              f"{err.strerror or err}; if this run is the only one writing "
                              f"there, pass --no-lock") from None
        raise


def fsync_file(path):
    """Flush ``path``'s data and size to disk (before it is renamed into place)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_directory(path):
    """Flush a folder's entries (a rename into it) to disk; nothing where its file system
    cannot sync a folder."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError as err:
        if err.errno not in _NO_DIR_SYNC:
            raise
    finally:
        os.close(fd)


def check_writable(path, overwrite):
    """Raise :class:`OutputError` unless ``path`` can be written.

    Parameters
    ----------
    path : str or os.PathLike
        The output file.
    overwrite : bool
        Whether an existing file may be replaced.

    Raises
    ------
    OutputError
        ``path`` exists (without ``overwrite``) or is a directory, or its directory is missing
        or not writable (a file is created and removed there to be sure: permission bits do
        not tell, e.g. for root under /proc or on a read-only mount).
    """
    if os.path.isdir(path):
        raise OutputError(f"{path}: is a directory")
    if os.path.lexists(path) and not overwrite:
        raise OutputError(f"{path}: exists; pass --overwrite to replace it")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise OutputError(f"{path}: directory {directory} does not exist")
    if not os.access(directory, os.W_OK):
        raise OutputError(f"{path}: directory {directory} is not writable")
    try:
        with deferred():
            _remove(_temporary(path))
    except OSError as err:
        raise OutputError(f"{path}: cannot write in {directory} ({err.strerror or err})") from None


def _cannot_write(path, err):
    return OutputError(f"{path}: cannot write ({err.strerror or err})")


def _temporary(path, keep_open=False):
    """A new empty file beside ``path`` (same file system, so the final rename is atomic).

    Call it inside :func:`~inject.signals.deferred`, together with what records the name
    for removal: a signal in between would leave the file nameless. If it cannot be set up, it
    is removed and the :class:`OSError` raised. With ``keep_open``, return ``(name, fd)``: the
    descriptor holds an exclusive lock on the file (``flock``, where there are locks) until it
    is closed, which marks the file as a live writer's for :func:`remove_stale_temporaries`.
    """
    directory = os.path.dirname(os.path.abspath(path))
    # The writer's process id in the name: who stops a process tidies up after it (see
    # remove_temporaries_of).
    fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(), suffix=os.path.splitext(path)[1],
                               dir=directory)
    try:
        if keep_open:
            try:
                if _LOCKING:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno not in NO_LOCKS:  # none to be had: the age alone guards it
                    raise
        else:
            os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual mode
    except BaseException:
        _remove(tmp)
        with contextlib.suppress(OSError):
            os.close(fd)
        raise
    return (tmp, fd) if keep_open else tmp


def temporary_prefix(pid=None):
    """The prefix of the temporary files of process ``pid`` (default: this one):
    ``.inject-<pid>-``."""
    return f"{PREFIX}{os.getpid() if pid is None else pid}-"


def remove_temporaries_of(directory, pids):
    """Remove the temporary files that the processes ``pids`` left in ``directory``, whatever
    their age: for a caller that has just killed those processes (the lock test of
    :func:`remove_stale_temporaries` still guards a live writer that reused a pid).

    Returns
    -------
    list of str
        The files removed.
    """
    prefixes = tuple(temporary_prefix(pid) for pid in pids)
    return _remove_unlocked(directory, lambda name, age: name.startswith(prefixes)) \
        if prefixes else []


def remove_stale_temporaries(directory):
    """Remove the temporary files (``.inject-*``) that a killed process left in ``directory``.

    A file is stale when no process holds its lock (a live :func:`atomic_path` does, until its
    block ends; the lock dies with its process) and it is older than :data:`STALE_AFTER_S`.
    Safe while other processes write into the directory (``--job`` slices); the one file not
    locked while in use is a finished file waiting for its :func:`output_group` to end, which
    the age guards.

    Returns
    -------
    list of str
        The files removed.
    """
    return _remove_unlocked(directory, lambda name, age: age >= STALE_AFTER_S)


def _remove_unlocked(directory, wanted):
    """Remove the temporary files of ``directory`` for which ``wanted(name, age_s)`` holds and
    no process holds the lock."""
    removed = []
    try:
        names = [n for n in os.listdir(directory) if n.startswith(PREFIX)]
    except OSError:
        return removed
    now = time.time()
    for name in names:
        path = os.path.join(directory, name)
        try:
            if not wanted(name, now - os.lstat(path).st_mtime):
                continue
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError:
            continue  # gone meanwhile, or not a plain file
        try:
            if _LOCKING:  # off: this process is the folder's only writer
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue  # a live writer's (or no lock to tell by: left alone)
        else:
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
                removed.append(path)
        finally:
            os.close(fd)
    return removed


def _remove(*paths):
    for path in paths:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)


@contextlib.contextmanager
def atomic_path(path, overwrite=False):
    """Yield a temporary path in the target's directory; on success rename it to ``path``.

    On any error (a full disk included) the temporary file is removed and the target is
    left as it was. The file is flushed to disk before the rename, and the folder after it.
    Inside an :func:`output_group` the rename waits for the group's end.

    Raises
    ------
    OutputError
        ``path`` cannot be written (see :func:`check_writable`), the block fails with an
        :class:`OSError`, or ``path`` is already an output of the active group.
    """
    check_writable(path, overwrite)
    group = _GROUP.get()
    if group is not None and any(os.path.realpath(p) == os.path.realpath(path)
                                 for p, _, _ in group):
        raise OutputError(f"{path}: given for two outputs")
    tmp = fd = None
    try:
        with deferred():  # a signal here would lose the file's name before the finally
            tmp, fd = _temporary(path, keep_open=True)
        yield tmp
        fsync_file(tmp)  # by name: the writer may have made a new file under it
        with deferred():
            if group is None:
                os.replace(tmp, path)
                fsync_directory(os.path.dirname(os.path.abspath(path)))
            else:
                group.append((path, tmp, overwrite))  # the group moves it, or removes it
            tmp = None
    except OutputError:
        raise  # says what already (an OSError too: not to be wrapped again)
    except OSError as err:
        raise _cannot_write(path, err) from None
    finally:
        if tmp is not None:
            _remove(tmp)
        if fd is not None:
            os.close(fd)  # the lock goes with it


@contextlib.contextmanager
def output_group(paths=(), overwrite=False):
    """Make every output written in the block appear together, or none of them.

    ``paths`` are checked on entry (:func:`check_writable`, and that no file is named twice),
    so that a command fails before its work rather than after it. Files written in the block
    through :func:`atomic_path` go to temporary files; when the block ends without an error
    they are moved into place. If a move fails, the files already moved are put back as they
    were (new ones removed, replaced ones restored). If the block fails, no target is touched.
    A group inside another joins it.

    Parameters
    ----------
    paths : sequence of str or os.PathLike
        The outputs known in advance (others may still be written in the block).
    overwrite : bool
        Whether existing files among ``paths`` may be replaced.

    Raises
    ------
    OutputError
        A target cannot be written or a move fails.
    """
    seen = {}
    for path in paths:
        check_writable(path, overwrite)
        key = os.path.realpath(path)
        if key in seen:
            also = "" if os.fspath(seen[key]) == os.fspath(path) else f" (as {seen[key]} too)"
            raise OutputError(f"{path}: given for two outputs{also}")
        seen[key] = path
    if _GROUP.get() is not None:  # nested: the outermost group moves everything
        yield
        return
    pending = []
    token = _GROUP.set(pending)
    try:
        yield
    except BaseException:
        _remove(*(tmp for _, tmp, _ in pending))
        raise
    finally:
        _GROUP.reset(token)
    _commit(pending)


def _commit(pending):
    """Move each ``(path, temporary, overwrite)`` into place: all of them, or none."""
    moved, backups = [], []
    try:
        for path, _, overwrite in pending:  # one may have appeared while the others were written
            check_writable(path, overwrite)
        for path, tmp, _ in pending:
            # Each step and its record in one block: a signal between them would leave a
            # move that the rollback below does not know of.
            backup = None
            if os.path.lexists(path):
                backup = tmp + ".old"  # .inject-*: never mistaken for an output
                with deferred():
                    backups.append(backup)
                    _keep_copy(path, backup)
            with deferred():
                os.replace(tmp, path)
                moved.append((path, backup))
        for folder in {os.path.dirname(os.path.abspath(p)) for p, _ in moved}:
            fsync_directory(folder)
    except BaseException as err:  # an interrupt too: never leave half of the outputs moved
        for done, backup in reversed(moved):
            with contextlib.suppress(OSError):
                if backup is None:
                    os.remove(done)  # it did not exist before
                else:
                    os.replace(backup, done)
        if isinstance(err, OSError) and not isinstance(err, OutputError):
            raise _cannot_write(path, err) from None
        raise
    finally:
        _remove(*backups, *(tmp for _, tmp, _ in pending))


def _keep_copy(path, backup):
    """Keep the current ``path`` as ``backup`` (a hard link where the file system allows,
    so the target itself stays in place until replaced)."""
    try:
        os.link(path, backup, follow_symlinks=False)
    except OSError:
        shutil.copy2(path, backup, follow_symlinks=False)
