"""Streak masking: detect satellite streaks in a CCD image, measure them, mask them.

- :mod:`~inject.masking.detect`: background, star suppression, binning, matched filter, fast
  Hough transform, iterative peak finding with a calibrated false-alarm threshold.
- :mod:`~inject.masking.measure`: line refinement from cross-track offsets of segments, the
  extent along the line, a model-free FWHM from a robust stacked profile (with bootstrap error).
- :mod:`~inject.masking.mask`: mask-width rules (surface brightness against the sky noise,
  k x FWHM, the LSST ``maskStreaks`` and acstools ``findsat_mrt`` rules) and lost-pixel counts
  from the rasterised mask.
- :mod:`~inject.masking.run`: :func:`mask_image`, :func:`write_masked` and the ``inject mask``
  command.
- :mod:`~inject.masking.evaluate`: scoring any masking function against injected truth;
  :mod:`~inject.cli.evaluate`: the ``inject evaluate`` campaign;
  :mod:`~inject.masking.external`: the acstools ``findsat_mrt`` adapter (optional).

Submodules are imported on first use, so that building the command-line parser stays cheap.
"""
import importlib

from inject.errors import InjectError


class MaskingError(InjectError, ValueError):
    """An image cannot be searched for streaks (not 2-D, too small, no usable pixels...).

    Also a :class:`ValueError`, as the input errors of :mod:`inject.errors` are."""


_LAZY = {"mask_image": "run", "analyse": "run", "write_masked": "run", "run_mask": "run",
         "add_mask_parser": "run", "detect_streaks": "detect", "prepare": "detect",
         "measure_streak": "measure", "mask_widths": "mask", "lost_pixels": "mask",
         "load_masker": "evaluate", "Masker": "evaluate",
         "add_evaluate_parser": "cli_evaluate", "findsat_mrt_mask": "external"}

__all__ = ["MaskingError", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
