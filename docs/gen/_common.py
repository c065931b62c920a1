"""Helpers shared by the build-time page generators (run by mkdocs-gen-files)."""
import sys
from pathlib import Path

#: The repository's root (this file is docs/gen/_common.py).
ROOT = Path(__file__).resolve().parents[2]


def importable():
    """Put the repository's own ``inject`` first on ``sys.path``, so that the pages describe
    the code being documented rather than some other installed copy."""
    root = str(ROOT)
    if root not in sys.path:
        sys.path.insert(0, root)


def module_exists(dotted):
    """True if the module ``dotted`` (``inject.camera.layout``) has a source file here."""
    path = ROOT.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()
