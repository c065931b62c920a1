"""inject's version: from the git checkout the package runs from, else from its installed
metadata, else ``0+unknown``.

The version is what setuptools-scm makes of the repository (its default ``guess-next-dev``
and ``node-and-date`` schemes), so an editable install in a checkout and a wheel built from
the same commit say the same thing:

* untagged history: ``0.1.devN+g<hash>``, N the number of commits, ``<hash>`` the first 9
  hex digits of the commit;
* N commits after a tag ``vX.Y.Z``: ``X.Y.(Z+1).devN+g<hash>``; on the tag itself ``X.Y.Z``;
* a work tree with uncommitted changes to tracked files: ``.dYYYYMMDD`` (today, UTC) after
  the hash (on a tag too: ``X.Y.(Z+1).dev0+g<hash>.dYYYYMMDD``).

In a git checkout the version is read from git when first asked for, not when the package
was installed: an editable install follows the checkout's later commits. Anywhere else (a
wheel or sdist install) it is the installed distribution's version, which setuptools-scm
wrote when the wheel was built.
"""
import datetime
import functools
import os
import re
import subprocess

#: The distribution whose metadata holds the version of an installed (non-git) copy.
DISTRIBUTION = "satstreak-inject"

#: The version when neither git nor installed metadata can say (a PEP 440 local version).
UNKNOWN = "0+unknown"

#: The folder holding the ``inject`` package: a checkout's root when run from one.
ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))

#: Hex digits of the commit in the version (setuptools-scm's length).
HASH_DIGITS = 9

# ``git describe --long`` of a tagged history: TAG-DISTANCE-gHASH (a tag may contain dashes).
_DESCRIBE = re.compile(r"^(?P<tag>.+)-(?P<distance>\d+)-g(?P<node>[0-9a-f]+)$")
# A tag setuptools-scm reads as a version: an optional v, then digits ... ending in a number.
_TAG = re.compile(r"^[vV]?(?P<version>\d[0-9A-Za-z.]*\d)$|^[vV]?(?P<single>\d+)$")


@functools.cache
def get_version():
    """inject's version string (PEP 440), computed once per process.

    Returns
    -------
    str
        From git when the package lives in a checkout of this project
        (:func:`version_from_git`), else the installed distribution's metadata
        (:func:`version_from_metadata`), else :data:`UNKNOWN`.
    """
    return version_from_git(ROOT) or version_from_metadata(ROOT) or UNKNOWN


def version_from_metadata(root, distribution=DISTRIBUTION):
    """The version in the installed distribution's metadata.

    Parameters
    ----------
    root : str or os.PathLike
        The folder holding the ``inject`` package: a wheel install's metadata is the one
        ``*.dist-info`` folder of the distribution beside it there.
    distribution : str
        Distribution name.

    Returns
    -------
    str or None
        The ``Version`` of the metadata beside the package, or else of the distribution
        :mod:`importlib.metadata` finds on ``sys.path`` (an editable install's); None when
        the distribution is not installed.
    """
    prefix = re.sub(r"[-_.]+", "_", distribution).lower() + "-"
    try:
        beside = [entry.path for entry in os.scandir(root)
                  if entry.name.lower().startswith(prefix) and entry.name.endswith(".dist-info")]
        if len(beside) == 1:
            with open(os.path.join(beside[0], "METADATA"), encoding="utf-8") as stream:
                for line in stream:
                    if line.startswith("Version:"):
                        return line.partition(":")[2].strip()
                    if not line.strip():  # the end of the headers
                        break
    except OSError:
        pass
    import importlib.metadata  # here: some 20 ms to import and a scan of sys.path

    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def _git(root, *commands):
    """The stdout of each git command (a tuple of arguments) in ``root``, stripped, None for
    one that fails; None if git cannot be run. The commands run at the same time."""
    # The caller's GIT_DIR or GIT_WORK_TREE (a hook, a script) would point git elsewhere;
    # no optional locks: reading the version never writes the index another git is using.
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    env["GIT_OPTIONAL_LOCKS"] = "0"
    runs = []
    try:
        for args in commands:
            runs.append(subprocess.Popen(["git", *args], cwd=root, env=env, text=True,
                                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL))
        outs = [run.communicate(timeout=10)[0] for run in runs]
    except (OSError, subprocess.SubprocessError):
        for run in runs:
            run.kill()
            run.wait()
        return None
    return [out.strip() if run.returncode == 0 else None for run, out in zip(runs, outs)]


def _next_version(tag):
    """setuptools-scm's guess of the release after ``tag``: ``1.2.3`` -> ``1.2.4``,
    ``1.2.3rc1`` -> ``1.2.3rc2``, ``1.3.dev0`` -> ``1.3``."""
    if ".dev" in tag:
        return tag.rsplit(".dev", 1)[0]
    head, tail = re.match(r"(.*?)(\d+)$", tag).groups()
    return f"{head}{int(tail) + 1}"


def version_from_git(root):
    """The version of the git checkout at ``root``, as setuptools-scm would build it.

    Parameters
    ----------
    root : str or os.PathLike
        The folder holding the ``inject`` package.

    Returns
    -------
    str or None
        None unless ``root`` is the top of a git work tree of this project (a ``.git`` and a
        ``pyproject.toml`` naming :data:`DISTRIBUTION`; so an install inside someone
        else's repository is not versioned by it) and git answers.

    Notes
    -----
    Dirty means a tracked file differs from the commit (``git status --untracked-files=no``,
    as setuptools-scm): a new untracked file does not make the tree dirty.
    """
    try:
        if not os.path.exists(os.path.join(root, ".git")):
            return None
        with open(os.path.join(root, "pyproject.toml"), encoding="utf-8") as stream:
            if DISTRIBUTION not in stream.read():
                return None
    except OSError:
        return None
    # The commit count is needed only without a tag, but costs no wait beside the others.
    answers = _git(root, ("describe", "--tags", "--long", "--abbrev=40", "--match", "*[0-9]*",
                          "--always"),
                   ("status", "--porcelain", "--untracked-files=no"),
                   ("rev-list", "--count", "HEAD"))
    if answers is None or None in answers[:2]:
        return None
    described, status, count = answers
    dirty = bool(status)
    match = _DESCRIBE.match(described)
    node = match["node"] if match else described
    tag = match and _TAG.match(match["tag"])
    if tag:
        base, distance = tag["version"] or tag["single"], int(match["distance"])
    else:  # no version tag: everything counts from 0.0, as setuptools-scm does
        if count is None or not re.fullmatch(r"[0-9a-f]{40}", node):
            return None
        base, distance = "0.0", int(count)
    if distance == 0 and not dirty:
        return base
    day = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d")
    local = f"g{node[:HASH_DIGITS]}" + (f".d{day}" if dirty else "")
    return f"{_next_version(base)}.dev{distance}+{local}"
