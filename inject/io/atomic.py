"""Atomic output: write to a temporary file beside the target, then rename it into place."""
import contextlib
import os
import tempfile

from ..errors import OutputError


def check_writable(path, overwrite):
    """Raise :class:`OutputError` if ``path`` exists (without ``overwrite``) or its directory
    cannot be written."""
    if os.path.exists(path) and not overwrite:
        raise OutputError(f"{path}: exists; pass --overwrite to replace it")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise OutputError(f"{path}: directory {directory} does not exist")
    if not os.access(directory, os.W_OK):
        raise OutputError(f"{path}: directory {directory} is not writable")


@contextlib.contextmanager
def atomic_path(path, overwrite=False):
    """Yield a temporary path in the target's directory; on success rename it to ``path``.

    On any error (a full disk included) the temporary file is removed and the target is
    left as it was.
    """
    check_writable(path, overwrite)
    directory = os.path.dirname(os.path.abspath(path))
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=".inject-", suffix=suffix, dir=directory)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as err:
        raise OutputError(f"{path}: cannot write ({err.strerror or err})") from None
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
