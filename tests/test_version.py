"""inject's version: the checkout's commit from git, a dirty tree marked, the installed
metadata without git, ``0+unknown`` without either; ``inject --version`` and INJVER.

The expected versions are worked out here with git itself, not with :mod:`inject._version`.
Each other copy of the package is imported in a fresh interpreter (``python -S``: no
site-packages, so no installed inject's metadata answers for it).
"""
import datetime
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest
from astropy.io import fits

import inject
from inject.cli.main import main
from inject.io.fits import CARD_STRING_MAX, primary_header, truth_table, version_card

PACKAGE = pathlib.Path(inject.__file__).parent
ROOT = PACKAGE.parent

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="no git program")


def _git(cwd, *args):
    """stdout of ``git args`` in ``cwd``, stripped (CalledProcessError if it fails)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    return subprocess.run(
        ["git", "-c", "user.name=test", "-c", "user.email=test@example.org",
         "-c", "commit.gpgsign=false", "-c", "tag.gpgsign=false", *args],
        cwd=cwd, env=env, capture_output=True, text=True, check=True).stdout.strip()


def _version_of(folder, *more_path, **env):
    """``inject.__version__`` of the package in ``folder``, in a fresh ``python -S`` with
    ``more_path`` before it on ``sys.path`` and ``env`` over the environment, less PYTHONPATH
    (a checkout on it may hold an egg-info)."""
    code = ("import sys; sys.path[:0] = sys.argv[1:]; import inject; "
            "print(inject.__version__)")
    env = {**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, **env}
    done = subprocess.run([sys.executable, "-S", "-c", code, *map(str, more_path), str(folder)],
                          cwd=folder, env=env, capture_output=True, text=True, check=True)
    return done.stdout.strip()


def _today():
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d")


def _copy_package(folder):
    """The package under test copied into ``folder``, with a pyproject.toml naming it."""
    shutil.copytree(PACKAGE, folder / "inject", ignore=shutil.ignore_patterns("__pycache__"))
    (folder / "pyproject.toml").write_text('[project]\nname = "satstreak-inject"\n')
    return folder


@pytest.fixture
def repo(tmp_path):
    """A git repository of one commit holding a copy of the package under test."""
    folder = _copy_package(tmp_path / "repo")
    _git(folder, "init", "-q")
    _git(folder, "add", ".")
    _git(folder, "commit", "-q", "-m", "one")
    return folder


def _checkout_root():
    """The top of the git work tree the package under test runs from, or None."""
    if shutil.which("git") is None:
        return None
    try:
        top = _git(ROOT, "rev-parse", "--show-toplevel")
    except subprocess.CalledProcessError:
        return None
    return ROOT if pathlib.Path(top).resolve() == ROOT.resolve() else None


def test_the_version_names_the_checkouts_commit():
    if _checkout_root() is None:
        pytest.skip("the package does not run from a git work tree")
    day = _today()
    head = _git(ROOT, "rev-parse", "HEAD")
    dirty = bool(_git(ROOT, "status", "--porcelain", "--untracked-files=no"))
    version = _version_of(ROOT)
    node = re.search(r"\+g([0-9a-f]+)", version)
    assert node and len(node[1]) >= 7 and head.startswith(node[1]), version
    assert version.endswith((f".d{day}", f".d{_today()}")) == dirty, version
    if not _git(ROOT, "tag", "--list", "*[0-9]*"):  # untagged: 0.1.dev<number of commits>
        assert version.startswith(f"0.1.dev{_git(ROOT, 'rev-list', '--count', 'HEAD')}+g")


@needs_git
def test_the_version_follows_later_commits_and_tags(repo):
    first = _git(repo, "rev-parse", "HEAD")
    assert _version_of(repo) == f"0.1.dev1+g{first[:9]}"
    (repo / "pyproject.toml").write_text((repo / "pyproject.toml").read_text() + "\n")
    _git(repo, "commit", "-q", "-am", "two")
    second = _git(repo, "rev-parse", "HEAD")
    assert _version_of(repo) == f"0.1.dev2+g{second[:9]}"
    _git(repo, "tag", "v1.4.0")
    assert _version_of(repo) == "1.4.0"


@needs_git
def test_a_dirty_tree_is_marked(repo):
    head = _git(repo, "rev-parse", "HEAD")[:9]
    (repo / "new_untracked_file.txt").write_text("not tracked: not dirty\n")
    assert _version_of(repo) == f"0.1.dev1+g{head}"
    with open(repo / "inject" / "errors.py", "a") as stream:
        stream.write("\n")
    day = _today()
    assert _version_of(repo) in {f"0.1.dev1+g{head}.d{d}" for d in (day, _today())}


def _metadata(folder, version):
    """A distribution's metadata for ``version`` in ``folder``, as pip installs it."""
    info = folder / f"satstreak_inject-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: satstreak-inject\nVersion: {version}\n\nREADME\n")


def test_without_git_the_metadata_beside_the_package_is_the_version(tmp_path):
    site = _copy_package(tmp_path / "site")
    _metadata(site, "2.5.1")
    _metadata(tmp_path / "other", "9.9")  # another install's, earlier on sys.path
    assert _version_of(site, tmp_path / "other") == "2.5.1"


def test_without_git_an_editable_installs_metadata_on_the_path_is_the_version(tmp_path):
    """Its metadata lies in site-packages, not beside the package."""
    _metadata(tmp_path / "site-packages", "3.0.dev4+gabcdef123")
    assert _version_of(_copy_package(tmp_path / "src"), tmp_path / "site-packages") == \
        "3.0.dev4+gabcdef123"


def test_with_neither_git_nor_metadata_the_version_is_unknown(tmp_path):
    assert _version_of(_copy_package(tmp_path / "plain")) == "0+unknown"


@needs_git
def test_a_checkout_without_the_git_program_falls_back(repo):
    assert _version_of(repo, PATH="") == "0+unknown"


def test_inject_version_prints_it(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"inject {inject.__version__}\n"


def test_every_header_carries_the_version(small_scene):
    assert primary_header(small_scene())["INJVER"] == inject.__version__
    assert truth_table([]).header["INJVER"] == inject.__version__


@pytest.mark.parametrize("length", [30, 51, 52, CARD_STRING_MAX, 90])
def test_a_long_version_stays_on_one_card(monkeypatch, length):
    monkeypatch.setattr(inject, "__version__", "1" + "a" * (length - 1))
    header = fits.Header()
    header["INJVER"] = version_card()
    card = str(header.cards["INJVER"])
    assert len(card) == 80  # no CONTINUE card
    assert header["INJVER"] == inject.__version__[:CARD_STRING_MAX]
    assert ("/ inject version" in card) == (length <= 51)
