"""Type information for :mod:`inject`'s public API, which ``inject/__init__.py`` imports on
first use (its module ``__getattr__``): the same names from the same modules, for type checkers
and editors. tests/test_architecture.py keeps this stub and ``_API`` in step."""

from inject.addstreak import add_streaks
from inject.camera.wcs import Pointing, ccd_wcs, pointing_wcs
from inject.config import DEFAULT_SCENE, Scene, parse_scene
from inject.errors import (
    FileFormatError,
    InjectError,
    InputError,
    InputWarning,
    OrbitError,
    OrbitWarning,
    OutputError,
    ResourceError,
    RunError,
    SceneError,
)
from inject.exposure.ccd import simulate_ccd
from inject.exposure.plan import make_plan
from inject.exposure.scene import parse_focal_scene
from inject.geometry import Geometry
from inject.instrument import LSST, Telescope
from inject.io.exr import write_exr
from inject.io.fits import read_truth, write_exposure
from inject.io.reader import read_exposure
from inject.masking import MaskingError, mask_image
from inject.orbits.passes import Exposure, Orbit, Site, compute_pass
from inject.orbits.tracks import resolve_ccd_orbits
from inject.photometry import apparent_magnitude, electron_rate
from inject.profile import Seeing, stationary_profile
from inject.reference import render_brute_force
from inject.render import Budget, render_polyline, render_segment
from inject.satellite import Box, Disk, shape_from_dict
from inject.scene import SceneResult, render_streaks, simulate
from inject.schema import apply_overrides, load_scene_file
from inject.streak import StreakModel
from inject.trajectory import Polyline, Segment, Track
from inject.validate import RANGES

# Imports in a stub are not exports; the names listed here are.
__version__: str
__all__ = [
    "__version__", "InjectError", "InputError", "SceneError", "FileFormatError", "OutputError",
    "ResourceError", "OrbitError", "InputWarning", "OrbitWarning", "RunError", "RANGES", "LSST",
    "Telescope", "Geometry", "Box", "Disk", "shape_from_dict", "apparent_magnitude",
    "electron_rate", "Seeing", "stationary_profile", "StreakModel", "Segment", "Polyline", "Track",
    "Budget", "render_segment", "render_polyline", "render_brute_force", "load_scene_file",
    "apply_overrides", "DEFAULT_SCENE", "Scene", "parse_scene", "simulate", "render_streaks",
    "SceneResult", "add_streaks", "Pointing", "ccd_wcs", "pointing_wcs", "Orbit", "Exposure",
    "Site", "compute_pass", "resolve_ccd_orbits", "parse_focal_scene", "make_plan", "simulate_ccd",
    "read_exposure", "write_exposure", "read_truth", "write_exr", "mask_image", "MaskingError",
]
