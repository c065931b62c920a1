"""Check that TRUTH and STREAK_MODEL match the pixels in the files inject writes (issue 20).

Users score maskers against the TRUTH table and STREAK_MODEL without looking at the pixels,
so both must agree with the noise-free model that was added to them. For a checkout (``--root
DIR``, default this repository) this script runs ``python -m inject`` with DIR first on
``PYTHONPATH`` (and checks that the package imported is DIR's), writes:

* ``inject simulate`` of every CCD scene of DIR's ``sample_fields/`` (the orbit scenes among
  them), and of the one-CCD pass of ``docs/guides/real-passes.md``;
* ``inject focalplane --streak-ccds-only`` of ``sample_fields/focal_paper_550km.yaml`` (``make
  focalplane``) and of ``sample_fields/pass_example.yaml`` (the guide's pass);
* ``inject add-streak`` into a file inject wrote (with its own streak), into a plain FITS
  image in ADU (a segment that ends on the image), and into that output again (two streaks
  that cross),

and checks, for every FITS file and every TRUTH row:

1. ``sum(STREAK_MODEL)`` against ``sum(TRUTH.charge_in_image_e)`` (relative);
2. the distance (px) from the path through the row's TRUTH_VERTICES (its line ``(x0, y0)-(x1,
   y1)`` in a file without them) to the model's ridge: along each column (or row, for steep
   tracks) the streak crosses, the centroid of the model across the streak where it is above
   :data:`RIDGE_LEVEL` of that cut's maximum (the maximum itself is reported too: a defocused
   streak's cross-section has two horns, so its maximum lies off the line by up to half the
   ring's width even when TRUTH is exact); the same centroids' distance from the row's chord
   ``(x0, y0)-(x1, y1)`` is reported beside it;
3. ``flux_per_px_e`` times the length of that path inside the image against the model's
   charge for that streak (pixels nearest its path), relative; for tracks whose model varies
   along them (polylines, orbits) also whether that charge lies between ``flux_per_px_min_e``
   and ``flux_per_px_max_e`` times the length;
4. whether every TRUTH table has the same columns (names and FITS formats);
5. for the two focal-plane runs, the CCDs rendered, and for every CCD the plan dropped the
   charge it would have received, from the model (the line-spread function of the streak at
   the track's point nearest the CCD, in e- per pixel, and the fraction of the charge per
   unit length beyond the CCD's nearest pixel), against the render tolerance the code
   documents (:class:`inject.render.Budget`: a pixel below ``tolerance / 2`` of the peak is
   not drawn, with the tolerance tightened for noise by ``inject.scene.NOISE_FRACTION``; at
   most ``flux_tolerance`` of the charge lies outside the footprint).

A command that fails, or a file or column that is missing, is recorded as that check's value
(the older code of a "before" run) rather than stopping the script. It prints one row per
file and streak and a summary of the worst values, and writes them as Markdown
(``--markdown FILE``) and JSON (``--json FILE``).

Usage::

    nice -n 10 .venv/bin/python scripts/check_truth.py [--root DIR] [--out DIR]
        [--markdown FILE] [--json FILE] [--workers N] [--reuse] [--label NAME]
"""
import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: Ridge: a cut counts where its maximum is above this fraction of the streak's peak, and its
#: centroid is taken over the pixels above this fraction of the cut's maximum.
RIDGE_LEVEL = 0.1
#: Half-width (px) of the window around a cut's maximum searched for the ridge's pixels.
RIDGE_HALF_WINDOW = 96
#: The centroid's final window, relative to the half-width of the run above RIDGE_LEVEL.
WINDOW_GROWTH = 1.5
#: In an image of several streaks, a ridge cut must lie this much (px) nearer its own line
#: than any other: near a crossing a brighter streak's wings tilt a faint one's cross-section
#: (0.43 px on several_streaks.yaml's faintest streak without it, 0.004 px with it).
RIDGE_GUARD_PX = 30.0

#: Limits of the checks (a value beyond one fails it).
LIMITS = {
    # float32 pixels summed: ~1e-7; a FITS file must not lose or gain a streak's charge.
    "model_truth_rel": 1e-5,
    # The centroid of a well-sampled symmetric cross-section lies on the line to ~0.01 px.
    "ridge_straight_px": 0.25,
    # A bent track's ridge from the path through its TRUTH_VERTICES.
    "ridge_varying_px": 0.1,
    # flux x length is exact for a line crossing straight image edges; corners add ~1e-4.
    "flux_length_straight_rel": 1e-3,
    # Slack on the [min, max] range of a varying track's charge per pixel.
    "flux_range_slack": 1e-3,
}

#: Distance (px) out to which a dropped CCD's line-spread function is computed; beyond it
#: the Kolmogorov tail's power law (LSF ~ d^(-8/3)) carries it on.
NEAR_PX = 2000.0
KOLMOGOROV_LSF_POWER = 8.0 / 3.0

#: The one-CCD orbit scene of docs/guides/real-passes.md ("A pass on one CCD").
GUIDE_PASS_CCD = """\
seed: 3
band: g
exptime: 30
time: 2026-06-15T23:29:45
pointing: {ra: 151.95, dec: -25.73, rotation: 0.0}
detector: {type: e2v, nx: 2048, ny: 2048}
stars: {mag_limit: 22}
satellites:
  - shape: {type: box, length: 7.25, width: 2.65}
    mag: 5.0
    orbit: {tle: sample_fields/example_starlink_like.tle}
"""

#: add-streak runs: (output name, input, options). ``@sim:NAME`` is the simulate output of a
#: sample scene, ``@plain`` the plain ADU image this script writes, ``@add:NAME`` an earlier
#: add-streak output.
ADD_STREAK_RUNS = (
    ("inject_plus_line.fits", "@sim:paper_550km",
     ["--height", "550", "--zenith", "70", "--mag", "8", "--x0", "100", "--y0", "50",
      "--angle", "40", "--seed", "2"]),
    ("plain_plus_segment.fits", "@plain",
     ["--height", "350", "--zenith", "60", "--mag", "9", "--x0", "120", "--y0", "80",
      "--angle", "25", "--track-length", "600", "--seed", "3"]),
    ("plain_plus_two.fits", "@add:plain_plus_segment.fits",
     ["--height", "550", "--zenith", "45", "--mag", "7", "--shape", "disk", "--radius", "1.5",
      "--x0", "450", "--y0", "350", "--angle", "120", "--seed", "4"]),
)
#: The plain image: float32 in the primary HDU, ADU with a gain, sky and Gaussian noise.
PLAIN_SHAPE = (700, 900)
PLAIN_GAIN = 1.6
PLAIN_SKY_ADU = 800.0

FOCAL_RUNS = (("paper", "sample_fields/focal_paper_550km.yaml"),
              ("pass", "sample_fields/pass_example.yaml"))


# -------------------------------------------------------------------------------------------
# Geometry (pure functions, tested in tests/test_check_truth.py)

def _inside_interval(x0, y0, x1, y1, box):
    """``(t0, t1)``: the fractions of the segment ``(x0, y0)-(x1, y1)`` inside the box
    ``(xmin, xmax, ymin, ymax)`` (Liang-Barsky; ``t0 > t1`` when it misses), or None when it
    runs parallel to an edge outside the box."""
    xmin, xmax, ymin, ymax = box
    dx, dy = x1 - x0, y1 - y0
    t0, t1 = 0.0, 1.0
    for p, q in ((-dx, x0 - xmin), (dx, xmax - x0), (-dy, y0 - ymin), (dy, ymax - y0)):
        if p == 0:
            if q < 0:
                return None
            continue
        t = q / p
        if p < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
    return t0, t1


def clipped_length(x0, y0, x1, y1, shape):
    """Length of the segment ``(x0, y0)-(x1, y1)`` inside the pixel area of an image of
    ``shape`` ``(ny, nx)`` (edges at -0.5 and n - 0.5), by Liang-Barsky clipping."""
    ny, nx = shape
    inside = _inside_interval(x0, y0, x1, y1, (-0.5, nx - 0.5, -0.5, ny - 0.5))
    if inside is None or inside[1] <= inside[0]:
        return 0.0
    return float((inside[1] - inside[0]) * math.hypot(x1 - x0, y1 - y0))


def segment_distance(px, py, x0, y0, x1, y1):
    """Distance from points ``(px, py)`` (arrays) to the segment ``(x0, y0)-(x1, y1)``."""
    px, py = np.asarray(px, float), np.asarray(py, float)
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    if length2 == 0:
        return np.hypot(px - x0, py - y0)
    t = np.clip(((px - x0) * dx + (py - y0) * dy) / length2, 0.0, 1.0)
    return np.hypot(px - (x0 + t * dx), py - (y0 + t * dy))


def as_path(line):
    """A path's vertices ``((x, y), ...)``: ``line`` itself, or its two ends when it is a
    segment ``(x0, y0, x1, y1)``."""
    if len(line) == 4 and all(np.ndim(v) == 0 for v in line):
        return ((float(line[0]), float(line[1])), (float(line[2]), float(line[3])))
    return tuple((float(x), float(y)) for x, y in line)


def path_distance(px, py, path):
    """Distance from points ``(px, py)`` to the nearest point of a path (vertices, or a
    segment ``(x0, y0, x1, y1)``)."""
    path = as_path(path)
    return np.min([segment_distance(px, py, *a, *b) for a, b in zip(path[:-1], path[1:])],
                  axis=0)


def path_length_inside(path, shape):
    """Length of a path (vertices, or a segment) inside the pixel area of an image of
    ``shape``: :func:`clipped_length` of each piece."""
    path = as_path(path)
    return sum(clipped_length(*a, *b, shape) for a, b in zip(path[:-1], path[1:]))


def nearest_line_labels(shape, lines, guard=0.0, chunk=256):
    """For every pixel of an image of ``shape``, the index of the nearest of ``lines``
    (``(x0, y0, x1, y1)`` segments or paths of vertices), int8; -1 where another line is less
    than ``guard`` px farther (the band around the boundaries, and the crossings, where both
    streaks are bright). Computed in chunks of rows."""
    ny, nx = shape
    labels = np.zeros(shape, np.int8)
    x = np.arange(nx, dtype=float)
    for start in range(0, ny, chunk):
        y = np.arange(start, min(ny, start + chunk), dtype=float)
        gx, gy = np.meshgrid(x, y)
        d = np.array([path_distance(gx, gy, line) for line in lines])
        part = np.argmin(d, axis=0).astype(np.int8)
        if guard > 0 and len(lines) > 1:
            two = np.partition(d, 1, axis=0)
            part[two[1] - two[0] < guard] = -1
        labels[start:start + len(y)] = part
    return labels


def ridge(model, line, own=None, level=RIDGE_LEVEL, half=RIDGE_HALF_WINDOW, skip_end_px=0.0):
    """Distances (px) from a streak's path to the ridge of its model.

    The image is cut across the track: along columns when the path's chord (its first vertex
    to its last) is closer to the x axis, along rows otherwise, at every column (row) between
    the path's ends. In each cut whose maximum exceeds ``level`` of the streak's peak, the
    ridge is the centroid of the contiguous pixels around the maximum that exceed ``level`` of
    it, refined over a window :data:`WINDOW_GROWTH` times as wide; cuts whose window touches
    the image's edge, the search window or another streak's pixels are left out, as are cuts
    within ``skip_end_px`` of the path's ends along its chord (an end cap's along-track fall
    shifts the centroid of a slanted cut).

    Parameters
    ----------
    model : ndarray
        The streak model, ``[y, x]``.
    line : tuple
        The path: ``((x, y), ...)`` its vertices, or ``(x0, y0, x1, y1)`` a segment, px.
    own : ndarray of bool, optional
        The pixels that belong to this streak (others' are masked out); None: all.

    Returns
    -------
    dict
        ``cuts`` (used), ``centroid_px`` and ``argmax_px`` (largest distance of the centroid
        and of the parabola-refined maximum from the path), ``chord_px`` (largest distance
        of the centroid from the path's chord), ``peak`` (the largest maximum of a cut clear
        of edges and other streaks; else the largest model value of the streak's pixels).
    """
    path = as_path(line)
    (x0, y0), (x1, y1) = path[0], path[-1]
    img = np.asarray(model, float)
    mask = own
    if abs(y1 - y0) > abs(x1 - x0):  # steep: cut along rows, as columns of the transpose
        img = img.T
        mask = None if own is None else own.T
        path = tuple((y, x) for x, y in path)
        x0, y0, x1, y1 = y0, x0, y1, x1
    n_rows, n_cols = img.shape
    data = img if mask is None else np.where(mask, img, 0.0)
    peak = float(data.max()) if data.size else 0.0
    out = {"cuts": 0, "centroid_px": math.nan, "argmax_px": math.nan, "chord_px": math.nan,
           "peak": peak}
    lo = max(0, math.ceil(min(x0, x1)))
    hi = min(n_cols - 1, math.floor(max(x0, x1)))
    if peak <= 0 or hi < lo:
        return out
    cols = np.arange(lo, hi + 1)
    if skip_end_px > 0:
        dx, dy = x1 - x0, y1 - y0
        length = math.hypot(dx, dy)
        along = (cols - x0) * length / dx  # distance along the line at the cut (|dx| > 0)
        cols = cols[(along > skip_end_px) & (along < length - skip_end_px)]
    if not len(cols):
        return out
    sub = data[:, cols]
    top = sub.argmax(axis=0)
    k = np.arange(len(cols))
    cmax = sub[top, k]
    offsets = np.arange(-half, half + 1)
    idx = top[:, None] + offsets
    inside = (idx >= 0) & (idx < n_rows)
    safe = np.clip(idx, 0, n_rows - 1)
    win = np.where(inside, img[safe, cols[:, None]], 0.0)
    above = (win >= level * cmax[:, None]) & inside
    right = np.cumprod(above[:, half + 1:], axis=1).astype(bool)
    left = np.cumprod(above[:, half - 1::-1], axis=1).astype(bool)
    run = np.zeros_like(above)
    run[:, half] = True
    run[:, half + 1:] = right
    run[:, :half] = left[:, ::-1]
    first = top - left.sum(axis=1)
    last = top + right.sum(axis=1)
    w = np.where(run, win, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):  # empty cuts are not valid
        centroid = top + (w * offsets).sum(axis=1) / w.sum(axis=1)
        # The run's centroid leans towards the side where one more pixel clears the level
        # (~0.05 px); a window 1.5 times as wide, symmetric about the centroid with its edge
        # pixels weighted by the fraction inside, converges on the centre (< 0.001 px for
        # Gaussian and two-horned cross-sections, tests/test_check_truth.py).
        reach = WINDOW_GROWTH * (np.maximum(top - first, last - top) + 0.5)
        position = top[:, None] + offsets
        for _ in range(4):
            weight = np.clip(reach[:, None] + 0.5 - np.abs(position - centroid[:, None]),
                             0.0, 1.0)
            centroid = (weight * win * position).sum(axis=1) / (weight * win).sum(axis=1)
    low = np.floor(centroid - reach - 0.5)
    high = np.ceil(centroid + reach + 0.5)
    valid = (low > 0) & (high < n_rows - 1) & np.isfinite(centroid) & (cmax > 0)
    valid &= (low > top - half) & (high < top + half)
    if mask is not None:
        used = (position >= low[:, None]) & (position <= high[:, None])
        valid &= np.all(~used | mask[safe, cols[:, None]], axis=1)
    if not valid.any():
        return out
    # The streak's peak over the clean cuts: near a crossing, the pixels nearest this line
    # can hold a brighter streak's core.
    out["peak"] = peak = float(cmax[valid].max())
    valid &= cmax >= level * peak
    a = win[:, half - 1]
    b = win[:, half]
    c = win[:, half + 1]
    curvature = a - 2 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curvature < 0, 0.5 * (a - c) / curvature, 0.0)
    argmax = top + np.clip(shift, -0.5, 0.5)
    cx = cols[valid].astype(float)
    out["cuts"] = int(valid.sum())
    out["centroid_px"] = float(path_distance(cx, centroid[valid], path).max())
    out["argmax_px"] = float(path_distance(cx, argmax[valid], path).max())
    out["chord_px"] = float(segment_distance(cx, centroid[valid], x0, y0, x1, y1).max())
    return out


# -------------------------------------------------------------------------------------------
# Running the checkout's inject

class Checkout:
    """A checkout's ``python -m inject`` (DIR first on PYTHONPATH, run from DIR)."""

    def __init__(self, root, out, python=sys.executable, reuse=False):
        self.root, self.out, self.python, self.reuse = Path(root), Path(out), python, reuse
        self.env = dict(os.environ)
        self.env["PYTHONPATH"] = os.pathsep.join(
            [str(self.root)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                if p])
        self.commands = []
        (self.out / "logs").mkdir(parents=True, exist_ok=True)

    def package_dir(self):
        """The directory of the ``inject`` package this checkout's command imports."""
        done = subprocess.run([self.python, "-c", "import inject, pathlib; "
                               "print(pathlib.Path(inject.__file__).resolve().parent)"],
                              cwd=self.root, env=self.env, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"check_truth: cannot import inject from {self.root}: "
                             f"{done.stderr.strip().splitlines()[-1:]}")
        return Path(done.stdout.strip())

    def commit(self):
        done = subprocess.run(["git", "-C", str(self.root), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True)
        return done.stdout.strip() or "unknown"

    def inject(self, args, log, outputs=()):
        """Run ``inject ARGS``; return ``(ok, message)``. With ``reuse``, outputs that exist
        are kept and the command is not run."""
        shown = "inject " + " ".join(str(a) for a in args)
        self.commands.append(shown)
        if self.reuse and outputs and all(Path(p).exists() for p in outputs):
            return True, "reused"
        started = time.time()
        done = subprocess.run([self.python, "-m", "inject", *map(str, args)], cwd=self.root,
                              env=self.env, capture_output=True, text=True)
        seconds = time.time() - started
        (self.out / "logs" / f"{log}.log").write_text(
            f"$ {shown}\nexit {done.returncode} after {seconds:.1f} s\n--- stdout\n"
            f"{done.stdout}\n--- stderr\n{done.stderr}")
        print(f"  [{seconds:6.1f} s] exit {done.returncode}: {shown}", file=sys.stderr,
              flush=True)
        if done.returncode != 0:
            lines = [x for x in done.stderr.strip().splitlines() if x.strip()]
            return False, f"exit {done.returncode}: {lines[-1] if lines else ''}"[:300]
        return True, ""

    def helper(self, args):
        """Run this script's helper mode inside the checkout's package; its JSON."""
        done = subprocess.run([self.python, str(Path(__file__).resolve()), "--helper", *args,
                               "--root", str(self.root)], cwd=self.root, env=self.env,
                              capture_output=True, text=True)
        if done.returncode != 0:
            lines = [x for x in done.stderr.strip().splitlines() if x.strip()]
            return {"error": lines[-1] if lines else f"exit {done.returncode}"}
        return json.loads(done.stdout)


# -------------------------------------------------------------------------------------------
# Scenes

def load_yaml(path):
    import yaml

    return yaml.safe_load(Path(path).read_text())


def is_ccd_scene(raw):
    """A CCD scene: no focal-plane key (``detectors``, ``cutout``), no constellation of
    ``inject survey`` (``shells``) and no track in focal-plane mm (``x0_mm``, ``length_mm``,
    vertices with ``x_mm``)."""
    if not isinstance(raw, dict) or {"detectors", "cutout", "shells"} & set(raw):
        return False
    for sat in raw.get("satellites") or []:
        track = (sat or {}).get("track") or {}
        if {"x0_mm", "y0_mm", "length_mm"} & set(track):
            return False
        if any("x_mm" in v for v in track.get("vertices") or []):
            return False
    return True


def satellite_kinds(raw):
    """Track kind per satellite of a scene: ``straight``, ``polyline`` or ``orbit``."""
    kinds = []
    for sat in (raw or {}).get("satellites") or []:
        if "orbit" in sat:
            kinds.append("orbit")
        elif (sat.get("track") or {}).get("vertices"):
            kinds.append("polyline")
        else:
            kinds.append("straight")
    return kinds


def write_plain(path, seed=5):
    """A plain FITS image: float32 ADU in the primary HDU, GAIN, sky and Gaussian noise."""
    from astropy.io import fits

    gen = np.random.default_rng(seed)
    sigma = math.sqrt(PLAIN_SKY_ADU / PLAIN_GAIN + 25.0)
    data = (PLAIN_SKY_ADU + sigma * gen.standard_normal(PLAIN_SHAPE)).astype(np.float32)
    header = fits.Header()
    header["BUNIT"] = "adu"
    header["GAIN"] = (PLAIN_GAIN, "e-/adu")
    fits.PrimaryHDU(data, header).writeto(path, overwrite=True)


# -------------------------------------------------------------------------------------------
# Checking one file

def _image_shape(hdus):
    """``(ny, nx)`` of the image: the HDU afw calls IMAGE, else the first 2-D image HDU."""
    images = [h for h in hdus if h.header.get("NAXIS") == 2
              and h.header.get("XTENSION", "IMAGE") == "IMAGE"]
    for hdu in images:
        if hdu.header.get("EXTTYPE", hdu.name) == "IMAGE":
            return (hdu.header["NAXIS2"], hdu.header["NAXIS1"])
    for hdu in images:
        if hdu.name not in ("MASK", "VARIANCE", "STREAK_MODEL", "INJECTED_MODEL"):
            return (hdu.header["NAXIS2"], hdu.header["NAXIS1"])
    return None


def schema_of(hdu):
    """``((name, TFORM), ...)`` of a binary table HDU."""
    header = hdu.header
    return tuple((header[f"TTYPE{i}"], header[f"TFORM{i}"])
                 for i in range(1, header["TFIELDS"] + 1))


def check_file(path, scene, group, kinds, rel):
    """All per-file and per-streak checks of one FITS file; failures become values."""
    from astropy.io import fits

    record = {"file": rel, "scene": scene, "group": group, "rows": None, "error": "",
              "model_truth_rel": None, "model_sum": None, "truth_sum": None, "schema": None,
              "vertices": False, "streaks": []}
    if not Path(path).exists():
        record["error"] = "no file"
        return record
    with fits.open(path) as hdus:
        names = [h.name for h in hdus]
        if "TRUTH" not in names:
            record["error"] = "no TRUTH table"
            return record
        truth = hdus["TRUTH"]
        record["schema"] = schema_of(truth)
        rows = truth.data
        record["rows"] = 0 if rows is None else len(rows)
        columns = [] if rows is None else list(rows.columns.names)
        shape = _image_shape(hdus)
        if "STREAK_MODEL" not in names:
            record["error"] = "no STREAK_MODEL"
            model = None
        else:
            model = np.asarray(hdus["STREAK_MODEL"].data, dtype=np.float64)
            shape = model.shape
        if "charge_in_image_e" not in columns:
            record["error"] = (record["error"] + "; " if record["error"] else "") + \
                "no charge_in_image_e column"
            truth_sum = None
        else:
            truth_sum = float(np.sum(rows["charge_in_image_e"], dtype=np.float64))
        record["truth_sum"] = truth_sum
        if model is not None:
            record["model_sum"] = float(model.sum())
            if truth_sum is not None:
                record["model_truth_rel"] = (record["model_sum"] - truth_sum) / truth_sum \
                    if truth_sum else (0.0 if record["model_sum"] == 0 else math.inf)
        if not record["rows"]:
            return record
        record["vertices"] = "TRUTH_VERTICES" in names
        paths = truth_paths(rows, hdus["TRUTH_VERTICES"].data if record["vertices"] else None)
        labels = guarded = None
        if model is not None and len(paths) > 1:
            labels = nearest_line_labels(shape, paths)
            guarded = nearest_line_labels(shape, paths, guard=RIDGE_GUARD_PX)
        for i, r in enumerate(rows):
            record["streaks"].append(_check_streak(r, columns, i, paths[i], model, labels,
                                                   guarded, shape, kinds))
    if model is not None and len(record["streaks"]) > 1:
        _shared_image(record)
    return record


def truth_paths(rows, table=None):
    """Each TRUTH row's path: its vertices in ``table`` (the TRUTH_VERTICES data, records
    ``row, vertex, x, y``), else (no table, or no vertices for the row) its ends."""
    paths = []
    for i, r in enumerate(rows):
        path = as_path(tuple(float(r[c]) for c in ("x0", "y0", "x1", "y1")))
        if table is not None:
            mine = table[table["row"] == i]
            mine = mine[np.argsort(mine["vertex"], kind="stable")]
            if len(mine) >= 2:
                path = tuple(zip(mine["x"].tolist(), mine["y"].tolist()))
        paths.append(path)
    return paths


def _shared_image(record):
    """Check 3 for an image of several streaks: the pixels nearest a streak's line also hold
    the others' wings (and, near a crossing, their cores), so the charge is compared for all
    the streaks together: sum of flux x length against the whole model. The split by nearest
    line is kept as ``partition_rel``."""
    streaks = record["streaks"]
    expected = sum(s["flux_per_px_e"] * s["length_in_px"] for s in streaks)
    together = expected / record["model_sum"] - 1 if record["model_sum"] else None
    for s in streaks:
        s["partition_rel"] = s["flux_length_rel"]
        s["flux_length_rel"] = together
        s["in_range"] = None  # a varying track's own charge is not separable here
        s["note"] = "; ".join(x for x in (s["note"], f"flux x length: all {len(streaks)} "
                                          "streaks together") if x)


def _value(row, columns, name):
    return float(row[name]) if name in columns else math.nan


def _check_streak(r, columns, i, path, model, labels, guarded, shape, kinds):
    sat = int(r["satellite"]) if "satellite" in columns else i
    n_vertices = int(r["n_vertices"]) if "n_vertices" in columns else None
    kind = kinds[sat] if 0 <= sat < len(kinds) else (
        "straight" if n_vertices in (None, 2) else "varying")
    s = {"row": i, "satellite": sat, "kind": kind, "charge_e": _value(r, columns,
                                                                       "charge_in_image_e"),
         "flux_per_px_e": _value(r, columns, "flux_per_px_e"),
         "flux_min_e": _value(r, columns, "flux_per_px_min_e"),
         "flux_max_e": _value(r, columns, "flux_per_px_max_e"),
         "length_in_px": path_length_inside(path, shape), "model_charge_e": None,
         "vertices": len(path), "ridge_px": None, "ridge_chord_px": None, "argmax_px": None,
         "cuts": 0, "flux_length_rel": None,
         "in_range": None, "partition_rel": None, "note": ""}
    if model is None:
        s["note"] = "no STREAK_MODEL"
        return s
    own = None if labels is None else labels == i
    s["model_charge_e"] = float(model.sum() if own is None else model[own].sum())
    peak_truth = _value(r, columns, "peak_e_per_px")
    fwhm_px = _value(r, columns, "fwhm_arcsec") / _value(r, columns, "pixel_scale_arcsec") \
        if "pixel_scale_arcsec" in columns else _value(r, columns, "fwhm_arcsec") / 0.2
    found = ridge(model, path, None if guarded is None else guarded == i,
                  skip_end_px=3 * fwhm_px + 2)
    if found["peak"] < RIDGE_LEVEL * peak_truth or s["model_charge_e"] <= 0:
        s["note"] = "wings only" if found["peak"] > 0 else "no model charge"
        return s
    s["ridge_px"], s["ridge_chord_px"], s["argmax_px"], s["cuts"] = (
        found["centroid_px"], found["chord_px"], found["argmax_px"], found["cuts"])
    if s["length_in_px"] > 0:
        expected = s["flux_per_px_e"] * s["length_in_px"]
        s["flux_length_rel"] = expected / s["model_charge_e"] - 1
        per_px = s["model_charge_e"] / s["length_in_px"]
        if not math.isnan(s["flux_min_e"]):
            slack = LIMITS["flux_range_slack"]
            s["in_range"] = bool(s["flux_min_e"] * (1 - slack) <= per_px
                                 <= s["flux_max_e"] * (1 + slack))
    else:
        s["note"] = "line outside the image"
    return s


# -------------------------------------------------------------------------------------------
# Dropped CCDs (helper mode: runs inside the checkout's package)

def _package_api():
    """The focal-plane functions of the package imported (today's layout or the older one)."""
    try:
        from inject.camera import layout as fp
        from inject.exposure.plan import margins_px, vertex_model
        from inject.exposure.scene import parse_focal_scene
        from inject.schema import load_scene_file
    except ImportError:
        from inject import focalplane as fp
        from inject.config import load_scene_file
        from inject.focalscene import margins_px, parse_focal_scene, vertex_model
    return fp, margins_px, vertex_model, parse_focal_scene, load_scene_file


def _crosses_box(ax, ay, bx, by, box):
    """Whether the segment ``(ax, ay)-(bx, by)`` meets the box ``(xmin, xmax, ymin, ymax)``."""
    inside = _inside_interval(ax, ay, bx, by, box)
    return inside is not None and inside[0] <= inside[1]


def nearest_on_path(xs, ys, box):
    """``(distance, k, t)``: the least distance from a polyline to a box ``(xmin, xmax, ymin,
    ymax)`` and where on the polyline (piece ``k``, fraction ``t``) it is reached."""
    xmin, xmax, ymin, ymax = box
    best = (math.inf, 0, 0.0)
    corners = [(xmin, ymin), (xmax, ymin), (xmin, ymax), (xmax, ymax)]
    for k in range(len(xs) - 1):
        ax, ay, bx, by = xs[k], ys[k], xs[k + 1], ys[k + 1]
        if _crosses_box(ax, ay, bx, by, box):
            return (0.0, k, 0.0)
        # Apart: the least distance is from an end of the piece to the box, or from a corner
        # of the box to the piece.
        for t, (qx, qy) in ((0.0, (ax, ay)), (1.0, (bx, by))):
            d = math.hypot(max(xmin - qx, 0.0, qx - xmax), max(ymin - qy, 0.0, qy - ymax))
            if d < best[0]:
                best = (d, k, t)
        dx, dy = bx - ax, by - ay
        length2 = dx * dx + dy * dy
        if length2 > 0:
            for cx, cy in corners:
                t = min(1.0, max(0.0, ((cx - ax) * dx + (cy - ay) * dy) / length2))
                d = math.hypot(ax + t * dx - cx, ay + t * dy - cy)
                if d < best[0]:
                    best = (d, k, t)
    return best


_LSF_CACHE = {}


def _lsf(model, angle_deg, cache=_LSF_CACHE):
    """``(d_arcsec, g, tail)``: the model's line-spread function across the track (pixel
    response included, unit integral, the larger of its two sides) at offsets ``d >= 0`` up
    to :data:`NEAR_PX`, and the fraction of it beyond each ``d`` on one side."""
    from inject.profile import line_spread

    key = (model, round(angle_deg % 90.0, 3))
    if key in cache:
        return cache[key]
    p = model.pixel_scale
    profile = model.profile
    period = 2 * math.pi / profile.stepk
    factor = max(1.0, 4 * NEAR_PX * p / period)  # folded tails ~5% at NEAR_PX
    cs = line_spread(profile, p, pixel_angle_deg=angle_deg, period_factor=factor)
    off, f = np.asarray(cs.offset_arcsec), np.asarray(cs.lsf)
    step = float(off[1] - off[0])
    f = f / (f.sum() * step)
    centre = int(np.argmin(np.abs(off)))
    n = min(centre, len(off) - 1 - centre, int(NEAR_PX * p / step))
    g = np.maximum(f[centre:centre + n + 1], f[centre::-1][:n + 1])
    d = np.arange(n + 1) * step
    far = g[-1] * d[-1] * 3.0 / 5.0  # integral of the d^(-8/3) tail beyond d[-1]
    tail = np.cumsum(g[::-1])[::-1] * step + far
    cache[key] = (d, g, tail)
    return cache[key]


def _lsf_at(lsf, d_arcsec):
    d, g, tail = lsf
    d_arcsec = np.asarray(d_arcsec, float)
    near = np.interp(d_arcsec, d, g)
    ratio = d[-1] / np.maximum(d_arcsec, d[-1])
    far = g[-1] * ratio ** KOLMOGOROV_LSF_POWER
    return np.where(d_arcsec <= d[-1], near, far)


def _tail_at(lsf, d_arcsec):
    d, g, tail = lsf
    if d_arcsec <= d[-1]:
        return float(np.interp(d_arcsec, d, tail))
    return float(_lsf_at(lsf, d_arcsec) * d_arcsec * 3.0 / 5.0)


def dropped_ccds(scene_path, rendered):
    """For every CCD of a focal-plane scene not in ``rendered``: the charge each satellite
    would give it, from the model, against the render tolerance."""
    from dataclasses import replace

    from inject.render import AUTO_MIN_TOLERANCE, Budget, snap_tolerance
    from inject.scene import NOISE_FRACTION, pixel_noise

    fp, margins_px, vertex_model, parse_focal_scene, load_scene_file = _package_api()
    fscene = parse_focal_scene(load_scene_file(scene_path))
    margins = margins_px(fscene)
    noise = {vendor: pixel_noise(replace(fscene.scene, detector=det))
             for vendor, det in fp.SENSORS.items()}
    budget = Budget()
    out = []
    for ccd in fscene.ccds:
        if ccd.name in rendered:
            continue
        ny, nx = ccd.shape
        worst = None
        for i, whole in enumerate(fscene.tracks):
            for part in whole.parts():
                px, py = ccd.focal_to_pixel(np.asarray(part.xs), np.asarray(part.ys))
                px, py = [float(v) for v in px], [float(v) for v in py]
                d_min, k, t = nearest_on_path(px, py, (0.0, nx - 1.0, 0.0, ny - 1.0))
                if d_min > NEAR_PX:
                    t = round(t)  # far: the nearest vertex's model (shared, cached)
                a, b = part.values[k], part.values[k + 1]
                values = {key: a[key] + t * (b[key] - a[key]) for key in a}
                model = vertex_model(fscene, i, values)
                angle = math.degrees(math.atan2(py[k + 1] - py[k], px[k + 1] - px[k]))
                lsf = _lsf(model, angle)
                p = model.pixel_scale
                flux = model.flux_per_px
                peak = flux * p * float(lsf[1].max())
                tol = budget.tolerance
                tightened = max(AUTO_MIN_TOLERANCE, snap_tolerance(
                    NOISE_FRACTION * noise[ccd.vendor] / model.peak_e_per_px))
                tol = min(tol, tightened)
                pixel = flux * p * float(_lsf_at(lsf, d_min * p))
                tail = _tail_at(lsf, d_min * p)
                total = _ccd_charge(px, py, (ny, nx), lsf, flux, p, d_min)
                entry = {"ccd": ccd.name, "vendor": ccd.vendor, "satellite": i,
                         "distance_px": d_min, "margin_px": float(margins[i]),
                         "pixel_e": pixel, "allowed_pixel_e": tol / 2 * peak,
                         "pixel_ratio": pixel / (tol / 2 * peak), "tolerance": tol,
                         "tail_fraction": tail,
                         "tail_ratio": tail / budget.flux_tolerance,
                         "charge_e": total, "peak_check": peak / model.peak_e_per_px}
                if worst is None or entry["pixel_ratio"] > worst["pixel_ratio"]:
                    worst = entry
        if worst is not None:
            out.append(worst)
    return {"ccds": [c.name for c in fscene.ccds], "margins_px": list(margins),
            "noise_e": noise, "flux_tolerance": budget.flux_tolerance,
            "default_tolerance": budget.tolerance, "dropped": out}


def _ccd_charge(px, py, shape, lsf, flux, p, d_min):
    """Charge (e-) a line source along the polyline ``(px, py)`` (CCD pixels) puts on the
    CCD: its line-spread function summed over a grid of pixel blocks."""
    ny, nx = shape
    stride = 8 if d_min < NEAR_PX else 64
    gx, gy = np.meshgrid(np.arange(stride / 2 - 0.5, nx - 0.5, stride),
                         np.arange(stride / 2 - 0.5, ny - 0.5, stride))
    best = np.full(gx.shape, np.inf)
    for k in range(len(px) - 1):
        best = np.minimum(best, segment_distance(gx, gy, px[k], py[k], px[k + 1], py[k + 1]))
    return float(np.sum(flux * p * _lsf_at(lsf, best * p)) * stride * stride)


def helper_main(args):
    import inject

    where = Path(inject.__file__).resolve().parent
    if where != (Path(args.root).resolve() / "inject"):
        raise SystemExit(f"check_truth helper: imported {where}, not {args.root}/inject")
    rendered = set(filter(None, args.rendered.split(",")))
    print(json.dumps(dropped_ccds(args.helper, rendered)))


# -------------------------------------------------------------------------------------------
# The runs

def run_all(checkout, workers=None):
    """Write every output, check it; the records and the focal-plane runs."""
    root, out = checkout.root, checkout.out
    records, focal = [], []
    sim_dir = out / "simulate"
    sim_dir.mkdir(parents=True, exist_ok=True)
    scenes = []
    for path in sorted((root / "sample_fields").glob("*.yaml")):
        raw = load_yaml(path)
        if is_ccd_scene(raw):
            scenes.append((path.stem, path.relative_to(root), raw))
    guide = out / "scenes" / "guide_pass_ccd.yaml"
    guide.parent.mkdir(parents=True, exist_ok=True)
    guide.write_text(GUIDE_PASS_CCD)
    scenes.append(("guide_pass_ccd", guide, load_yaml(guide)))
    print(f"check_truth: {len(scenes)} CCD scenes", file=sys.stderr)
    sim_ok = {}
    for stem, scene, raw in scenes:
        target = sim_dir / f"{stem}.fits"
        ok, message = checkout.inject(["simulate", scene, "-o", target, "--overwrite"],
                                      f"simulate_{stem}", [target])
        sim_ok[stem] = ok
        rec = check_file(target, stem, "simulate", satellite_kinds(raw),
                         str(target.relative_to(out)))
        if not ok:
            rec["error"] = f"simulate failed: {message}"
        records.append(rec)

    for name, scene in FOCAL_RUNS:
        raw = load_yaml(root / scene)
        target = out / "focalplane" / name
        args = ["focalplane", scene, "-o", target, "--streak-ccds-only", "--no-mosaic"]
        if workers:
            args += ["--workers", workers]
        manifest = target / "manifest.csv"
        if not (checkout.reuse and manifest.exists()) and target.exists():
            shutil.rmtree(target)
        target.parent.mkdir(parents=True, exist_ok=True)  # focalplane makes OUTDIR only
        ok, message = checkout.inject(args, f"focalplane_{name}", [manifest])
        plan_ok, plan_text = _plan(checkout, scene, name)
        files = sorted(target.glob("R*_S*.fits")) if target.exists() else []
        for f in files:
            records.append(check_file(f, Path(scene).stem, "focalplane", satellite_kinds(raw),
                                      str(f.relative_to(out))))
        run = {"name": name, "scene": str(scene), "ok": ok, "message": message,
               "rendered": [f.stem for f in files], "planned": plan_text}
        if ok:
            run["dropped"] = checkout.helper([str(scene), "--rendered",
                                              ",".join(run["rendered"])])
        else:  # the CCDs it did not render were not dropped by its plan
            run["dropped"] = {"error": f"focalplane failed: {message}"}
        focal.append(run)

    add_dir = out / "addstreak"
    add_dir.mkdir(parents=True, exist_ok=True)
    plain = add_dir / "plain.fits"
    write_plain(plain)
    base_kinds = {"@plain": []}
    for stem, _, raw in scenes:
        base_kinds[f"@sim:{stem}"] = satellite_kinds(raw)
    for name, source, options in ADD_STREAK_RUNS:
        if source == "@plain":
            src = plain
        elif source.startswith("@sim:"):
            src = sim_dir / f"{source[5:]}.fits"
        else:
            src = add_dir / source[5:]
        kinds = base_kinds.get(source, [])
        base_kinds[f"@add:{name}"] = kinds  # added rows: straight (beyond the scene's)
        target = add_dir / name
        ok, message = checkout.inject(["add-streak", src, "-o", target, "--overwrite",
                                       *options], f"addstreak_{Path(name).stem}", [target])
        rec = check_file(target, f"add-streak {source}", "add-streak", kinds,
                         str(target.relative_to(out)))
        if not ok:
            rec["error"] = f"add-streak failed: {message}"
        records.append(rec)
    return records, focal


def _plan(checkout, scene, name):
    """The plan's CCD count (``focalplane --plan --json``)."""
    done = subprocess.run([checkout.python, "-m", "inject", "focalplane", str(scene), "--plan",
                           "--json"], cwd=checkout.root, env=checkout.env,
                          capture_output=True, text=True)
    checkout.commands.append(f"inject focalplane {scene} --plan --json")
    if done.returncode != 0:
        return False, None
    try:
        return True, [d["name"] for d in json.loads(done.stdout)["detectors"]]
    except (ValueError, KeyError):
        return False, None


# -------------------------------------------------------------------------------------------
# Summary and tables

def _abs_max(values):
    values = [abs(v) for v in values if v is not None and not math.isnan(v)]
    return max(values) if values else None


def summarise(records, focal):
    """Worst values per check, and the verdicts."""
    files = [r for r in records]
    streaks = [(r, s) for r in records for s in r["streaks"]]
    straight = [s for _, s in streaks if s["kind"] == "straight"]
    varying = [s for _, s in streaks if s["kind"] != "straight"]
    rels = [r["model_truth_rel"] for r in files]
    summary = {
        "files": len(files), "rows": sum(r["rows"] or 0 for r in files),
        "file_errors": [(r["file"], r["error"]) for r in files if r["error"]],
        "model_truth_rel": _abs_max(rels),
        "model_truth_failures": [r["file"] for r in files
                                 if r["model_truth_rel"] is None
                                 or abs(r["model_truth_rel"]) > LIMITS["model_truth_rel"]],
        "ridge_straight_px": _abs_max([s["ridge_px"] for s in straight]),
        "ridge_varying_px": _abs_max([s["ridge_px"] for s in varying]),
        "ridge_varying_chord_px": _abs_max([s["ridge_chord_px"] for s in varying]),
        "files_without_vertices": [r["file"] for r in files if r["rows"] and not r["vertices"]],
        "ridge_by_input": ridge_by_input(records),
        "argmax_straight_px": _abs_max([s["argmax_px"] for s in straight]),
        "argmax_varying_px": _abs_max([s["argmax_px"] for s in varying]),
        "ridge_failures": [f"{r['file']}#{s['row']}" for r, s in streaks
                           if s["ridge_px"] is not None and s["ridge_px"] > LIMITS[
                               "ridge_straight_px" if s["kind"] == "straight"
                               else "ridge_varying_px"]],
        "flux_length_straight_rel": _abs_max([s["flux_length_rel"] for s in straight]),
        "flux_length_varying_rel": _abs_max([s["flux_length_rel"] for s in varying]),
        "flux_length_failures": [f"{r['file']}#{s['row']}" for r, s in streaks
                                 if s["kind"] == "straight" and s["flux_length_rel"] is not None
                                 and abs(s["flux_length_rel"])
                                 > LIMITS["flux_length_straight_rel"]],
        "varying_out_of_range": [f"{r['file']}#{s['row']}" for r, s in streaks
                                 if s["kind"] != "straight" and s["in_range"] is False],
        "varying_no_range": sum(1 for s in varying if s["in_range"] is None
                                and s["flux_length_rel"] is not None),
        "unchecked_streaks": [f"{r['file']}#{s['row']}: {s['note']}" for r, s in streaks
                              if s["ridge_px"] is None],
    }
    schemas = {}
    for r in files:
        if r["schema"] is not None:
            schemas.setdefault(r["schema"], []).append(r["file"])
    common = max(schemas, key=lambda k: len(schemas[k])) if schemas else None
    summary["schemas"] = len(schemas)
    summary["schema_odd_files"] = {f: _schema_difference(common, k)
                                   for k, fs in schemas.items() if k != common for f in fs}
    summary["focal"] = []
    for run in focal:
        dropped = run["dropped"].get("dropped", []) if isinstance(run["dropped"], dict) else []
        entry = {"name": run["name"], "ok": run["ok"], "message": run["message"],
                 "rendered": len(run["rendered"]),
                 "planned": None if run["planned"] is None else len(run["planned"]),
                 "dropped": len(dropped), "helper_error": run["dropped"].get("error"),
                 "margin_px": (run["dropped"].get("margins_px") or [None])[0]}
        if dropped:
            nearest = min(dropped, key=lambda d: d["distance_px"])
            entry.update(
                nearest_ccd=nearest["ccd"], nearest_px=nearest["distance_px"],
                worst_pixel_ratio=max(d["pixel_ratio"] for d in dropped),
                worst_pixel_e=max(d["pixel_e"] for d in dropped),
                worst_tail_ratio=max(d["tail_ratio"] for d in dropped),
                most_charge_e=max(d["charge_e"] for d in dropped),
                over=[d["ccd"] for d in dropped if d["pixel_ratio"] > 1 or d["tail_ratio"] > 1])
        summary["focal"].append(entry)
    return summary


def ridge_by_input(records):
    """Per input (the command and scene that wrote the files) with bent tracks (polylines,
    orbits): the streaks, the most vertices of one, and the worst ridge distance from the
    chord and from the path through the vertices."""
    out = {}
    for r in records:
        for s in r["streaks"]:
            if s["kind"] == "straight" or s["ridge_px"] is None:
                continue
            entry = out.setdefault(f"{r['group']} {r['scene']}", {
                "streaks": 0, "vertices": 0, "chord_px": None, "vertices_px": None})
            entry["streaks"] += 1
            entry["vertices"] = max(entry["vertices"], s["vertices"])
            entry["chord_px"] = _abs_max([entry["chord_px"], s["ridge_chord_px"]])
            entry["vertices_px"] = _abs_max([entry["vertices_px"], s["ridge_px"]])
    return out


def _schema_difference(common, other):
    if common is None:
        return "no common schema"
    a, b = dict(common), dict(other)
    missing = [n for n in a if n not in b]
    extra = [n for n in b if n not in a]
    formats = [f"{n} {a[n]}->{b[n]}" for n in a if n in b and a[n] != b[n]]
    order = "" if missing or extra or formats else "same columns, other order"
    parts = [f"missing {', '.join(missing)}" if missing else "",
             f"extra {', '.join(extra)}" if extra else "",
             f"formats {', '.join(formats)}" if formats else "", order]
    return "; ".join(p for p in parts if p)


def _fmt(value, spec=".2e"):
    if value is None:
        return "-"
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return format(value, spec)


def table_rows(records):
    """One row per file and streak (a file without rows or with an error: one row)."""
    rows = []
    for r in records:
        head = [r["scene"], r["file"], "-" if r["rows"] is None else str(r["rows"]),
                _fmt(r["model_truth_rel"])]
        if not r["streaks"]:
            rows.append(head + ["-", "-", "-", "-", "-", r["error"]])
            continue
        for s in r["streaks"]:
            flux = _fmt(s["flux_length_rel"])
            if s["in_range"] is not None and s["kind"] != "straight":
                flux += " (in range)" if s["in_range"] else " (OUT of range)"
            note = "; ".join(dict.fromkeys(x for x in (r["error"], s["note"]) if x))
            rows.append(head + [_fmt(s["ridge_px"], ".3f"), _fmt(s["ridge_chord_px"], ".3f"),
                                _fmt(s["argmax_px"], ".2f"), flux, s["kind"], note])
            head = [r["scene"], r["file"], "", ""]
    return rows


HEADER = ["scene", "file", "rows", "model-vs-TRUTH rel", "ridge max px", "chord max px",
          "peak max px", "flux x length rel", "track kind", "note"]


def markdown(label, checkout, records, focal, summary):
    moved = getattr(checkout, "started", None)
    lines = [f"## check_truth: {label}", "",
             f"Checkout `{checkout.root}` at commit `{checkout.commit()}`"
             + (f" (**moved during the run**, from `{moved}`)" if moved else "") + ".", ""]
    lines += summary_markdown(summary)
    lines += ["", "### Per file and streak", "", "| " + " | ".join(HEADER) + " |",
              "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |"
              for row in table_rows(records)]
    for run in focal:
        dropped = run["dropped"].get("dropped", []) if isinstance(run["dropped"], dict) else []
        lines += ["", f"### Dropped CCDs, focal-plane run `{run['name']}` "
                  f"({len(dropped)} dropped; the 8 nearest the track)", ""]
        if run["dropped"].get("error"):
            lines.append(f"helper failed: {run['dropped']['error']}")
            continue
        lines += ["| CCD | distance px | margin px | max pixel e- | allowed e- | ratio | "
                  "tail / flux_tolerance | charge e- |", "|---|---|---|---|---|---|---|---|"]
        for d in sorted(dropped, key=lambda d: d["distance_px"])[:8]:
            lines.append(f"| {d['ccd']} | {d['distance_px']:.0f} | {d['margin_px']:.0f} | "
                         f"{d['pixel_e']:.2e} | {d['allowed_pixel_e']:.2e} | "
                         f"{d['pixel_ratio']:.2f} | {d['tail_ratio']:.2f} | "
                         f"{d['charge_e']:.3g} |")
    lines += ["", "### Commands", "", "```"] + list(dict.fromkeys(checkout.commands)) + \
        ["```", ""]
    return "\n".join(lines)


def summary_lines(summary):
    """The worst values, one line each."""
    s = summary
    out = [f"files {s['files']}, TRUTH rows {s['rows']}",
           f"(1) model vs TRUTH: worst |rel| {_fmt(s['model_truth_rel'])} (limit "
           f"{LIMITS['model_truth_rel']:g}); failing or not computable: "
           f"{len(s['model_truth_failures'])}",
           f"(2) ridge: straight {_fmt(s['ridge_straight_px'], '.3f')} px (limit "
           f"{LIMITS['ridge_straight_px']:g}), varying {_fmt(s['ridge_varying_px'], '.3f')} px "
           f"(limit {LIMITS['ridge_varying_px']:g}; from TRUTH's chord "
           f"{_fmt(s['ridge_varying_chord_px'], '.3f')} px); peak position: straight "
           f"{_fmt(s['argmax_straight_px'], '.2f')}, varying "
           f"{_fmt(s['argmax_varying_px'], '.2f')} px; failing {len(s['ridge_failures'])}; "
           f"files without TRUTH_VERTICES {len(s['files_without_vertices'])}",
           f"(3) flux x length: straight worst |rel| {_fmt(s['flux_length_straight_rel'])} "
           f"(limit {LIMITS['flux_length_straight_rel']:g}, failing "
           f"{len(s['flux_length_failures'])}); varying worst |rel| "
           f"{_fmt(s['flux_length_varying_rel'])}, outside [min, max] "
           f"{len(s['varying_out_of_range'])}, no range columns {s['varying_no_range']}",
           f"(4) TRUTH schemas: {s['schemas']} distinct"
           + (f" ({len(s['schema_odd_files'])} files differ from the common one)"
              if s["schemas"] > 1 else "")]
    for f in s["focal"]:
        line = (f"(5) focal plane {f['name']}: rendered {f['rendered']} CCDs (plan "
                f"{_fmt(f['planned'], 'd')}), dropped {f['dropped']}")
        if f.get("helper_error"):
            line += f"; dropped-CCD model failed: {f['helper_error']}"
        elif f["dropped"]:
            line += (f"; nearest dropped {f['nearest_ccd']} at {f['nearest_px']:.0f} px "
                     f"(margin {_fmt(f['margin_px'], '.0f')} px); worst pixel "
                     f"{f['worst_pixel_e']:.2e} e- = {f['worst_pixel_ratio']:.2f} x allowed; "
                     f"worst tail {f['worst_tail_ratio']:.2f} x flux_tolerance; most charge on "
                     f"a dropped CCD {f['most_charge_e']:.3g} e-; over tolerance "
                     f"{len(f['over'])}")
        if not f["ok"]:
            line += f"; run failed: {f['message']}"
        out.append(line)
    return out


def ridge_markdown(summary):
    """The bent tracks' ridge per input, from the chord and from the vertices."""
    rows = summary["ridge_by_input"]
    if not rows:
        return []
    lines = ["", "### Ridge of bent tracks (polylines, orbits) per input", "",
             "| input | streaks | most vertices | worst from chord px | worst from vertices px |",
             "|---|---|---|---|---|"]
    lines += [f"| {name} | {e['streaks']} | {e['vertices']} | {_fmt(e['chord_px'], '.3f')} | "
              f"{_fmt(e['vertices_px'], '.3f')} |" for name, e in rows.items()]
    return lines


def summary_markdown(summary):
    lines = ["### Worst values", ""] + [f"* {x}" for x in summary_lines(summary)]
    lines += ridge_markdown(summary)
    details = []
    for key, title in (("model_truth_failures", "model vs TRUTH failing"),
                       ("ridge_failures", "ridge failing"),
                       ("flux_length_failures", "flux x length failing"),
                       ("varying_out_of_range", "varying track outside [min, max]"),
                       ("unchecked_streaks", "streaks without ridge"),
                       ("file_errors", "file errors")):
        if summary[key]:
            items = [x if isinstance(x, str) else f"{x[0]}: {x[1]}" for x in summary[key]]
            details.append(f"* {title}: " + "; ".join(items))
    if summary["schema_odd_files"]:
        details.append("* TRUTH schemas differing: " + "; ".join(
            f"{k}: {v}" for k, v in summary["schema_odd_files"].items()))
    return lines + ([""] + details if details else [])


def print_table(records):
    rows = [HEADER] + table_rows(records)
    widths = [min(60, max(len(r[i]) for r in rows)) for i in range(len(HEADER))]
    for row in rows:
        print("  ".join(c[:60].ljust(w) for c, w in zip(row, widths)).rstrip())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", default=str(ROOT), help="the checkout (default: this one)")
    parser.add_argument("--out", help="output folder (default: out/check_truth/LABEL)")
    parser.add_argument("--label", help="name of this run (default: the checkout's folder)")
    parser.add_argument("--markdown", help="write the tables as Markdown")
    parser.add_argument("--json", help="write every value as JSON")
    parser.add_argument("--workers", help="focalplane --workers")
    parser.add_argument("--reuse", action="store_true",
                        help="keep outputs that exist instead of rewriting them")
    parser.add_argument("--python", default=sys.executable,
                        help="the interpreter that runs inject (default: this one)")
    parser.add_argument("--helper", help=argparse.SUPPRESS)
    parser.add_argument("--rendered", default="", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.helper:
        helper_main(args)
        return 0
    root = Path(args.root).resolve()
    label = args.label or root.name
    out = Path(args.out).resolve() if args.out else ROOT / "out" / "check_truth" / label
    checkout = Checkout(root, out, args.python, args.reuse)
    package = checkout.package_dir()
    if package != root / "inject":
        raise SystemExit(f"check_truth: python -m inject imports {package}, not {root}/inject")
    print(f"check_truth: {label}: inject from {package}, outputs in {out}", file=sys.stderr)
    started = checkout.commit()
    records, focal = run_all(checkout, args.workers)
    if checkout.commit() != started:  # the outputs may mix two versions of the code
        checkout.started = started
        print(f"check_truth: warning: the checkout moved from {started} to "
              f"{checkout.commit()} during the run", file=sys.stderr)
    summary = summarise(records, focal)
    print_table(records)
    print()
    for line in summary_lines(summary):
        print(line)
    if args.markdown:
        Path(args.markdown).write_text(markdown(label, checkout, records, focal, summary))
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"label": label, "root": str(root), "commit": checkout.commit(),
             "records": records, "focal": focal, "summary": summary,
             "commands": checkout.commands}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
