"""LSSTCam CCD models (obs_lsst values).

A :class:`Detector` is the imaging area of one sensor with its amplifier grid; a cut-out of any
size keeps the sensor's electronics.
"""
from dataclasses import dataclass, replace

import numpy as np

from inject.errors import InputError


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
    prescan, serial_overscan, parallel_overscan : int
        Pixels the raw layout adds to each amplifier segment (obs_lsst).
    gain : float
        Median gain, e-/ADU.
    read_noise : float
        Median read noise, e-.
    full_well : float
        Full-well capacity, e-.
    amp_gains, amp_read_noise : tuple of float, optional
        Per-amplifier values (16, amplifier 0 at the origin, row-major over the 2 x 8 grid);
        every amplifier takes the median value when not given.
    layout : str
        ``"assembled"`` (the imaging area) or ``"raw"``: also write the amplifiers' readout
        with prescan, overscan and ``bias`` (ADU); see :func:`raw_layout`.
    """

    kind: str
    nx: int
    ny: int
    amp_nx: int
    amp_ny: int
    prescan: int
    serial_overscan: int
    parallel_overscan: int
    gain: float
    read_noise: float
    full_well: float = 170_000.0
    amp_gains: tuple | None = None
    amp_read_noise: tuple | None = None
    layout: str = "assembled"
    bias: float = 1000.0

    N_AMP_ROWS, N_AMP_COLS = 2, 8

    def __post_init__(self):
        for name in ("amp_gains", "amp_read_noise"):
            values = getattr(self, name)
            if values is None:
                continue
            values = tuple(float(v) for v in np.atleast_1d(values))
            if len(values) != self.N_AMP_ROWS * self.N_AMP_COLS or not all(
                    np.isfinite(v) and v > 0 for v in values):
                raise InputError(f"detector.{name}", values, "needs 16 positive numbers")
            object.__setattr__(self, name, values)
        if not self.full_well > 0:
            raise InputError("detector.full_well", self.full_well, "must be > 0")
        if self.layout not in ("assembled", "raw"):
            raise InputError("detector.layout", self.layout, "choose assembled or raw")

    @property
    def shape(self):
        """``(ny, nx)``, as numpy arrays are indexed."""
        return (self.ny, self.nx)

    def amp_index(self):
        """Amplifier number of every pixel, ``(ny, nx)`` int array."""
        rows = np.minimum(np.arange(self.ny) // self.amp_ny, self.N_AMP_ROWS - 1)
        cols = np.minimum(np.arange(self.nx) // self.amp_nx, self.N_AMP_COLS - 1)
        return rows[:, None] * self.N_AMP_COLS + cols[None, :]

    def per_pixel(self, name):
        """``gain`` or ``read_noise`` of every pixel's amplifier, ``(ny, nx)`` float array
        (a read-only broadcast view when every amplifier has the median value)."""
        values = getattr(self, f"amp_{'gains' if name == 'gain' else name}")
        if values is None:
            return np.broadcast_to(np.float64(getattr(self, name)), self.shape)
        return np.asarray(values)[self.amp_index()]

    def amp_value(self, name, y, x):
        """``gain`` or ``read_noise`` of the amplifier holding pixel ``(y, x)``."""
        values = getattr(self, f"amp_{'gains' if name == 'gain' else name}")
        if values is None:
            return float(getattr(self, name))
        row = min(y // self.amp_ny, self.N_AMP_ROWS - 1)
        col = min(x // self.amp_nx, self.N_AMP_COLS - 1)
        return float(values[row * self.N_AMP_COLS + col])

    def median(self, name):
        """Median ``gain`` or ``read_noise`` over the amplifiers."""
        values = getattr(self, f"amp_{'gains' if name == 'gain' else name}")
        return float(getattr(self, name) if values is None else np.median(values))

    @property
    def full_shape(self):
        """``(ny, nx)`` of the whole sensor a cut-out is taken from: its 2 x 8 amplifier grid
        (never smaller than the image itself). The random draws are keyed on blocks of this
        grid, so a cut-out draws its pixels' numbers as the whole CCD does."""
        return (max(self.ny, self.N_AMP_ROWS * self.amp_ny),
                max(self.nx, self.N_AMP_COLS * self.amp_nx))

    @property
    def midline(self):
        """First row of the upper amplifier half: e2v channel stops block bleeding across it."""
        return self.amp_ny if self.kind == "e2v" else None

    def cutout(self, nx, ny):
        """The same sensor, cut to ``nx x ny`` pixels (amplifiers clipped to it)."""
        for name, value in (("nx", nx), ("ny", ny)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise InputError(f"detector.{name}", value, "must be a positive integer")
        return replace(self, nx=nx, ny=ny)


#: ITL STA3800: 4072 x 4000, 16 amplifiers of 509 x 2000.
ITL = Detector("itl", 4072, 4000, 509, 2000, 3, 64, 48, gain=1.671, read_noise=6.40)
#: e2v CCD250: 4096 x 4004, 16 amplifiers of 512 x 2002.
E2V = Detector("e2v", 4096, 4004, 512, 2002, 10, 54, 46, gain=1.476, read_noise=5.41)
DETECTORS = {"itl": ITL, "e2v": E2V}


def detector_from_spec(spec):
    """``"itl"``, ``{type: e2v}`` or ``{type: itl, nx: 512, ny: 400}`` -> :class:`Detector`."""
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, dict):
        raise InputError("detector", spec, "must be itl, e2v or a mapping with a type")
    unknown = set(spec) - {"type", "nx", "ny", "gains", "read_noise", "full_well", "layout",
                           "bias"}
    if unknown:
        raise InputError("detector", spec, f"unknown keys {sorted(unknown)}")
    kind = spec.get("type", "itl")
    if kind not in DETECTORS:
        raise InputError("detector.type", kind, "choose itl or e2v")
    det = DETECTORS[kind]
    if "nx" in spec or "ny" in spec:
        det = det.cutout(spec.get("nx", det.nx), spec.get("ny", det.ny))
    changes = {}
    for key, field in (("gains", "amp_gains"), ("read_noise", "amp_read_noise")):
        if key in spec:
            value = spec[key]
            changes[field] = tuple([value] * 16) if isinstance(value, (int, float)) else value
    for key in ("full_well", "layout", "bias"):
        if key in spec:
            changes[key] = spec[key]
    try:
        return replace(det, **changes) if changes else det
    except (TypeError, ValueError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError("detector", spec,
                         "gains, read_noise and full_well must be numbers") from None


def bleed_saturation(image, full_well, midline=None):
    """Spread charge above full well along columns, conserving it (in place).

    Each run of saturated pixels in a column grows up and down, alternately, until the
    column's capacity there holds its charge; the outermost pixels get the remainder.
    Charge reaching the top or bottom edge is lost off the array, as in a real CCD. For e2v
    sensors the channel stop between the two amplifier rows (``midline``, the first row of
    the upper half) stops bleeding: a run never crosses it.

    Returns
    -------
    tuple of ndarray
        Row and column indices of the pixels at full well (the SAT mask), as ``np.nonzero``
        gives them: only the columns that reach full well are searched.
    """
    ny = image.shape[0]
    peak = image.max(axis=0) if image.size else np.zeros(image.shape[1])
    for x in np.flatnonzero(peak > full_well):
        column = image[:, x]
        while True:
            over = np.flatnonzero(column > full_well)
            if len(over) == 0:
                break
            lo = hi = over[0]
            floor, ceiling = 0, ny - 1
            if midline is not None and midline < ny:
                floor, ceiling = (0, midline - 1) if lo < midline else (midline, ny - 1)
            charge = float(column[lo])  # a Python float: exact sums in a float32 image too
            # Grow [lo, hi] until it can hold its charge at full well.
            while charge > full_well * (hi - lo + 1):
                # Alternate up and down; go the other way once a side is blocked.
                grow_down = hi >= ceiling or ((hi - lo) % 2 == 1 and lo > floor)
                if grow_down and lo > floor:
                    lo -= 1
                    charge += float(column[lo])
                elif hi < ceiling:
                    hi += 1
                    charge += float(column[hi])
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
    # Bleeding fills only columns that reached full well: the others cannot hold any.
    columns = np.flatnonzero(peak >= full_well)
    rows, where = np.nonzero(image[:, columns] >= full_well)
    return rows, columns[where]


#: Cosmic-ray tracks deposited at a time (bounds the temporary arrays at any rate).
_CR_BATCH = 20_000


def add_cosmic_rays(image, n_expected, rng, charge_per_px=1500.0, mean_length_px=6.0,
                    full_shape=None):
    """Add cosmic-ray tracks (in place) and return their pixels (row and column indices).

    A simple model for mask and detection tests, not a physical one: ``Poisson(n_expected)``
    straight tracks at uniform positions and angles, exponential lengths, a log-normal
    charge per pixel of track around ``charge_per_px``, deposited at quarter-pixel steps.
    imSim uses ~0.2 per s per CCD.

    The tracks are drawn over the whole sensor, ``full_shape`` (default the image's), and
    each deposits the part that falls on the image: a cut-out (pixels ``[0, ny) x [0, nx)``
    of the sensor) draws the same numbers as the whole CCD and gets exactly its rays there,
    those that start outside it and cross in included.
    """
    ny, nx = image.shape
    fy, fx = image.shape if full_shape is None else full_shape
    n = rng.poisson(n_expected)
    x0, y0 = rng.uniform(0, fx, n), rng.uniform(0, fy, n)
    angle = rng.uniform(0, np.pi, n)
    length = rng.exponential(mean_length_px, n) + 1.0
    charge = charge_per_px * rng.lognormal(0.0, 0.5, n)
    # Only tracks whose box reaches the image (the rest cannot deposit on it).
    reach = length + 1.0
    near = np.flatnonzero((x0 - reach < nx) & (y0 - reach < ny))
    rows, cols = [], []
    for start in range(0, near.size, _CR_BATCH):
        k = near[start:start + _CR_BATCH]
        # Steps s = 0, 0.25, ... < length per track, as np.arange(0, length, 0.25) gives them.
        steps = np.ceil(length[k] / 0.25).astype(np.intp)
        track = np.repeat(np.arange(k.size), steps)
        s = (np.arange(track.size) - np.repeat(np.cumsum(steps) - steps, steps)) * 0.25
        x = np.rint(x0[k][track] + s * np.cos(angle[k])[track]).astype(int)
        y = np.rint(y0[k][track] + s * np.sin(angle[k])[track]).astype(int)
        inside = (x >= 0) & (x < nx) & (y >= 0) & (y < ny)
        # In track order, step by step: each pixel sums its deposits in the whole CCD's order.
        np.add.at(image, (y[inside], x[inside]), (charge[k] * 0.25)[track[inside]])
        rows.append(y[inside])
        cols.append(x[inside])
    if not rows:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(rows), np.concatenate(cols)


def raw_layout(image_e, detector, rng, bias=1000.0):
    """The CCD as its amplifiers read it out: ADU with bias, prescan and overscan.

    Each amplifier's segment (``amp_ny`` rows by ``amp_nx`` columns of the image, in
    electrons) becomes ``prescan + amp_nx + serial_overscan`` columns by ``amp_ny +
    parallel_overscan`` rows, divided by the amplifier's gain, plus ``bias`` ADU and read
    noise everywhere (the overscan holds bias and read noise only). Segments are laid out
    in sensor orientation, 2 rows of 8: the lower amplifiers read out through the bottom
    edge and the upper ones through the top edge, so every segment's parallel overscan rows
    lie towards the midline, after its last data row in readout order. Cut-outs keep the
    amplifiers they overlap, clipped.

    ``rng`` is a generator, or a function giving each amplifier's own, ``rng(amp)``: each
    segment's noise is then that of the same segment of the whole CCD, whatever the cut-out
    (a clipped upper amplifier puts its rows at its readout edge, where the whole CCD has
    others: those pixels' noise differs).

    Returns
    -------
    raw : ndarray
        float32 ADU mosaic.
    sections : list of dict
        Per amplifier: ``amp``, ``datasec`` (FITS ``[x1:x2,y1:y2]`` in the mosaic, 1-based),
        ``imagesec`` (the same pixels in the image), ``gain``, ``read_noise``.
    """
    gains = detector.per_pixel("gain")
    noise = detector.per_pixel("read_noise")
    seg_w = detector.prescan + detector.amp_nx + detector.serial_overscan
    seg_h = detector.amp_ny + detector.parallel_overscan
    ny, nx = image_e.shape
    rows = -(-ny // detector.amp_ny)
    cols = -(-nx // detector.amp_nx)
    raw = np.empty((rows * seg_h, cols * seg_w), dtype=np.float32)
    sections = []
    for r in range(rows):
        for c in range(cols):
            y0, x0 = r * detector.amp_ny, c * detector.amp_nx
            block = image_e[y0:y0 + detector.amp_ny, x0:x0 + detector.amp_nx]
            h, w = block.shape
            amp = r * detector.N_AMP_COLS + c
            gain, sigma = float(gains[y0, x0]), float(noise[y0, x0])
            upper = r % 2 == 1  # read out through the top edge: overscan rows below the data
            first_row = seg_h - h if upper else 0
            segment = np.zeros((seg_h, seg_w))
            segment[first_row:first_row + h, detector.prescan:detector.prescan + w] = block / gain
            gen = rng(amp) if callable(rng) else rng
            segment += bias + gen.standard_normal(segment.shape) * sigma / gain
            raw[r * seg_h:(r + 1) * seg_h, c * seg_w:(c + 1) * seg_w] = segment
            data_y0 = r * seg_h + first_row
            data_x0 = c * seg_w + detector.prescan
            sections.append({
                "amp": amp, "gain": gain, "read_noise": sigma,
                "datasec": f"[{data_x0 + 1}:{data_x0 + w},{data_y0 + 1}:{data_y0 + h}]",
                "imagesec": f"[{x0 + 1}:{x0 + w},{y0 + 1}:{y0 + h}]"})
    return raw, sections
