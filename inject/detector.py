"""LSSTCam CCD models (obs_lsst values, DESIGN.md section 3).

A :class:`Detector` is the imaging area of one sensor with its amplifier grid; a cut-out of any
size keeps the sensor's electronics.
"""
from dataclasses import dataclass, replace

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class Detector:
    """One CCD's imaging area.

    Parameters
    ----------
    kind : str
        ``"itl"`` or ``"e2v"``.
    nx, ny : int
        Imaging pixels along x (columns) and y (rows).
    amp_nx, amp_ny : int
        Amplifier segment size; the sensor has ``(nx / amp_nx) x (ny / amp_ny)`` amplifiers.
    gain : float
        Median gain, e-/ADU.
    read_noise : float
        Median read noise, e-.
    full_well : float
        Full-well capacity, e-.
    """

    kind: str
    nx: int
    ny: int
    amp_nx: int
    amp_ny: int
    gain: float
    read_noise: float
    full_well: float = 170_000.0

    @property
    def shape(self):
        """``(ny, nx)``, as numpy arrays are indexed."""
        return (self.ny, self.nx)

    def cutout(self, nx, ny):
        """The same sensor, cut to ``nx x ny`` pixels (amplifiers clipped to it)."""
        for name, value in (("nx", nx), ("ny", ny)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise InputError(f"detector.{name}", value, "must be a positive integer")
        return replace(self, nx=nx, ny=ny)


#: ITL STA3800: 4072 x 4000, 16 amplifiers of 509 x 2000.
ITL = Detector("itl", 4072, 4000, 509, 2000, gain=1.671, read_noise=6.40)
#: e2v CCD250: 4096 x 4004, 16 amplifiers of 512 x 2002.
E2V = Detector("e2v", 4096, 4004, 512, 2002, gain=1.476, read_noise=5.41)
DETECTORS = {"itl": ITL, "e2v": E2V}


def detector_from_spec(spec):
    """``"itl"``, ``{type: e2v}`` or ``{type: itl, nx: 512, ny: 400}`` -> :class:`Detector`."""
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, dict):
        raise InputError("detector", spec, "must be itl, e2v or a mapping with a type")
    unknown = set(spec) - {"type", "nx", "ny"}
    if unknown:
        raise InputError("detector", spec, f"unknown keys {sorted(unknown)}")
    kind = spec.get("type", "itl")
    if kind not in DETECTORS:
        raise InputError("detector.type", kind, "choose itl or e2v")
    det = DETECTORS[kind]
    if "nx" in spec or "ny" in spec:
        det = det.cutout(spec.get("nx", det.nx), spec.get("ny", det.ny))
    return det


def bleed_saturation(image, full_well, midline=None):
    """Spread charge above full well along columns, conserving it (in place).

    Each run of saturated pixels in a column grows up and down, alternately, until the
    column's capacity there holds its charge; the outermost pixels get the remainder.
    Charge reaching the top or bottom edge is lost off the array, as in a real CCD. For e2v
    sensors the channel stop between the two amplifier rows (``midline``, the first row of
    the upper half) stops bleeding: a run never crosses it.

    Returns
    -------
    ndarray of bool
        Pixels at full well (the SAT mask).
    """
    ny = image.shape[0]
    for x in np.flatnonzero((image > full_well).any(axis=0)):
        column = image[:, x]
        while True:
            over = np.flatnonzero(column > full_well)
            if len(over) == 0:
                break
            lo = hi = over[0]
            floor, ceiling = 0, ny - 1
            if midline is not None:
                floor, ceiling = (0, midline - 1) if lo < midline else (midline, ny - 1)
            charge = column[lo]
            # Grow [lo, hi] until it can hold its charge at full well.
            while charge > full_well * (hi - lo + 1):
                # Alternate up and down; go the other way once a side is blocked.
                grow_down = hi >= ceiling or ((hi - lo) % 2 == 1 and lo > floor)
                if grow_down and lo > floor:
                    lo -= 1
                    charge += column[lo]
                elif hi < ceiling:
                    hi += 1
                    charge += column[hi]
                else:  # the run fills its whole half or column: the rest is lost
                    break
            n = hi - lo + 1
            filled = min(charge, full_well * n)
            # Full pixels in the middle, the remainder split between the two ends.
            column[lo:hi + 1] = full_well
            spare = full_well * n - filled
            if spare > 0:
                ends = [lo, hi] if n > 1 else [lo]
                column[ends] -= spare / len(ends)
    return image >= full_well
