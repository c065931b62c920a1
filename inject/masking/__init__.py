"""Streak masking: detect satellite streaks in a CCD image, measure them, mask them.

- :mod:`~inject.masking.detect`: background, star suppression, binning, matched filter, fast
  Hough transform, iterative peak finding with a calibrated false-alarm threshold.
- :mod:`~inject.masking.measure`: line refinement from cross-track offsets of segments, the
  extent along the line, a model-free FWHM from a robust stacked profile (with bootstrap error).
- :mod:`~inject.masking.mask`: mask-width rules (surface brightness against the sky noise,
  k x FWHM, the LSST ``maskStreaks`` and acstools ``findsat_mrt`` rules) and lost-pixel counts
  from the rasterised mask.
- :mod:`~inject.masking.run`: :func:`mask_image`, :func:`analyse` and :func:`write_masked`
  (the engine of ``inject mask``, whose command line is :mod:`inject.cli.mask`).
- :mod:`~inject.masking.evaluate`: scoring any masking function against injected truth
  (the ``inject evaluate`` campaign is :mod:`inject.cli.evaluate`);
  :mod:`~inject.masking.external`: the acstools ``findsat_mrt`` adapter (optional).

This module holds what they all share: :class:`MaskingError` and :class:`MaskerOutput`.
Submodules are imported on first use, so that building the command-line parser stays cheap.
"""
import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

from inject.errors import InjectError

if TYPE_CHECKING:  # NumPy is not imported at run time: the command line's parser imports this
    import numpy


class MaskingError(InjectError, ValueError):
    """An image cannot be searched for streaks (not 2-D, too small, no usable pixels...).

    Also a :class:`ValueError`, as the input errors of :mod:`inject.errors` are."""


@dataclass
class MaskerOutput:
    """What a masking function returns: a boolean mask, and its streaks when it reports them.

    Attributes
    ----------
    mask : ndarray of bool
        Pixels masked, same shape as the image.
    streaks : list of dict or None
        Lines found (``x0, y0, x1, y1``; ``fwhm_arcsec`` where measured), or None for a
        masker that gives only a mask (its angle, offset and FWHM errors are then NaN).
    """

    mask: "numpy.ndarray"
    streaks: list | None = None


_LAZY = {"mask_image": "run", "analyse": "run", "write_masked": "run",
         "detect_streaks": "detect", "prepare": "detect",
         "measure_streak": "measure", "mask_widths": "mask", "lost_pixels": "mask",
         "load_masker": "evaluate", "Masker": "evaluate", "findsat_mrt_mask": "external"}

__all__ = ["MaskingError", "MaskerOutput", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
