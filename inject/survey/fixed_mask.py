"""A fixed-width mask: ``inject survey --mask-width``.

Studies of constellations' cost to LSST masked every streak with a band of one width whatever
its brightness or defocus. ``--mask-width 300px`` (or ``60arcsec``) counts such a band beside
the plan's own mask: a rectangle of that full width along every crossing of the science CCDs,
with end caps of half the width, rasterised and merged per CCD exactly as the physical mask
(:func:`inject.survey.plan.run_spans`, :func:`inject.survey.plan.union_pixels`). A width in
arcsec is converted at the nominal plate scale, 0.2 arcsec a pixel.
"""
import math
import re
from dataclasses import dataclass

from inject.errors import InputError
from inject.instrument import LSST

#: The widest band accepted, px: a CCD's side (4096 px); wider, the band is no streak's mask.
MAX_WIDTH_PX = 4096.0
#: The units ``--mask-width`` takes.
UNITS = ("px", "arcsec")

_SYNTAX = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z\"]*)\s*$")


@dataclass(frozen=True)
class FixedMask:
    """The band of ``--mask-width``: as given, and its full width in pixels."""

    given: str
    width_px: float

    @property
    def width_arcsec(self):
        return self.width_px * LSST.pixel_scale_arcsec


def parse_mask_width(text, option="--mask-width"):
    """A :class:`FixedMask` from ``300px`` or ``60arcsec`` (a space before the unit allowed).

    Raises
    ------
    InputError
        No unit, another unit, a width that is not a positive number or wider than
        :data:`MAX_WIDTH_PX` px.
    """
    match = _SYNTAX.match(str(text))
    if match is None:
        raise InputError(option, text, "must be a width and its unit, e.g. 300px or 60arcsec")
    value, unit = float(match.group(1)), match.group(2).lower()
    if not unit:
        raise InputError(option, text, "give its unit: e.g. 300px or 60arcsec (px or arcsec)")
    if unit not in UNITS:
        raise InputError(option, text, f"unknown unit {match.group(2)!r}: px or arcsec, "
                                       f"e.g. 300px or 60arcsec")
    width = value if unit == "px" else value / LSST.pixel_scale_arcsec
    if not math.isfinite(width) or width <= 0.0:
        raise InputError(option, text, "must be a width > 0")
    if width > MAX_WIDTH_PX:
        raise InputError(option, text, f"{width:g} px is wider than a CCD ({MAX_WIDTH_PX:g} "
                                       f"px, {MAX_WIDTH_PX * LSST.pixel_scale_arcsec:g} arcsec)")
    return FixedMask(str(text).strip(), width)
