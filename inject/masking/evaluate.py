"""Scoring masking functions against a simulation's truth.

:func:`match_streaks` matches detected lines to TRUTH rows. :func:`evaluate` runs any masking
function (:class:`Masker`: ``f(image) -> bool mask``; the built-in one is :func:`inject_masker`)
on simulated images and scores it per streak and per image (:func:`score_image`): completeness
against peak surface brightness and integrated S/N, false positives, angle, offset and FWHM
errors, mask recall, over-masking and IoU against the true region ``{streak_model > t x sky
sigma}``, and the streak charge left outside the mask; :func:`summarise` aggregates.
"""
import importlib
import inspect
import time
from dataclasses import dataclass

import numpy as np

from inject.errors import InjectError, InputError
from inject.masking import MaskerOutput, MaskingError, external
from inject.masking.geometry import Line, angle_difference, band_pixels
from inject.masking.run import analyse
from inject.trajectory import clip_segment, path_distance
from inject.truth import vertices


def truth_path(row, shape):
    """The pieces of a TRUTH row's path (:func:`inject.truth.vertices`) inside an image of
    ``shape``, in order along the track.

    Returns
    -------
    list of Line
        Each piece between two vertices clipped to the image's pixel area; empty when the path
        misses the image.
    """
    ny, nx = shape
    pieces = []
    points = vertices(row)
    for (ax, ay), (bx, by) in zip(points[:-1], points[1:]):
        part = clip_segment(ax, ay, bx, by, (-0.5, nx - 0.5), (-0.5, ny - 0.5))
        if part is not None and part[:2] != part[2:]:
            pieces.append(Line(*part))
    return pieces


def truth_line(row, shape):
    """The straight line from where a TRUTH row's path enters an image of ``shape`` to where
    it last leaves it (for a bent track, its chord: :func:`truth_path` has its pieces), or
    None if it misses."""
    pieces = truth_path(row, shape)
    if not pieces:
        return None
    return Line(pieces[0].x0, pieces[0].y0, pieces[-1].x1, pieces[-1].y1)


def _middle(pieces):
    """The point halfway along a path's pieces (by length)."""
    lengths = np.array([piece.length for piece in pieces])
    k = min(int(np.searchsorted(np.cumsum(lengths), 0.5 * lengths.sum())), len(pieces) - 1)
    rest = 0.5 * lengths.sum() - lengths[:k].sum()
    (ux, uy), piece = pieces[k].direction, pieces[k]
    return piece.x0 + rest * ux, piece.y0 + rest * uy


def path_offset(line, pieces, at):
    """A straight line's offset from a path, and the path's piece it is measured against.

    The point of ``line`` nearest ``at`` is taken to the nearest point of the path: the
    distance between them, signed as the side of that piece it lies on (positive on its left,
    as :meth:`Line.coordinates`). At a vertex, of the two pieces as near, the one closer to
    ``line``'s direction.

    Returns
    -------
    offset : float
        Pixels.
    piece : Line
        The nearest piece.
    """
    t, _ = line.coordinates(*at)
    cx, cy = line.centre
    ux, uy = line.direction
    x, y = cx + t * ux, cy + t * uy
    distance = [float(path_distance(((p.x0, p.y0), (p.x1, p.y1)), x, y)) for p in pieces]
    k = min(range(len(pieces)), key=lambda i: (
        round(distance[i], 9), angle_difference(line.angle_deg, pieces[i].angle_deg)))
    side = pieces[k].coordinates(x, y)[1]
    return float(np.copysign(distance[k], side)), pieces[k]


@dataclass
class Match:
    """A truth streak and the detection matched to it (None if missed).

    ``angle_error_deg`` and ``offset_px`` (:func:`path_offset`: the distance of the detected
    line from the true path, taken from the middle of the path's part in the image, and the
    angle to the path's piece there) are NaN when missed.
    """

    truth_index: int
    found_index: int | None
    angle_error_deg: float = float("nan")
    offset_px: float = float("nan")


def match_streaks(found, truth, shape, max_angle_deg=0.5, max_offset_px=5.0):
    """Match detected streaks (dicts with ``x0, y0, x1, y1``) to TRUTH rows, one to one.

    Each truth streak, in order, takes the closest unused detection within the tolerances: the
    angle to the truth's path and the offset from it (:func:`path_offset`), both where the
    detection passes the middle of the path's part in the image.

    Returns
    -------
    matches : list of Match
        One per truth row that crosses the image.
    false_positives : list of int
        Indices of detections matched to no truth streak.
    """
    lines = [Line(s["x0"], s["y0"], s["x1"], s["y1"]) for s in found]
    used, matches = set(), []
    for i, row in enumerate(truth):
        pieces = truth_path(row, shape)
        if not pieces:
            continue
        middle = _middle(pieces)
        best = None
        for j, line in enumerate(lines):
            if j in used:
                continue
            off, piece = path_offset(line, pieces, middle)
            da = angle_difference(line.angle_deg, piece.angle_deg)
            if da <= max_angle_deg and abs(off) <= max_offset_px:
                if best is None or abs(off) < abs(best[2]):
                    best = (j, da, off)
        if best is None:
            matches.append(Match(i, None))
        else:
            used.add(best[0])
            matches.append(Match(i, *best))
    return matches, [j for j in range(len(found)) if j not in used]


# ---------------------------------------------------------------------------------------------
# Scoring any masking function against injected truth

#: ``t`` of the true region ``{streak_model > t x sky sigma}`` that masks are scored against
#: (the simulator's STREAK plane uses the same level, :data:`inject.maskplanes.STREAK_MASK_SIGMA`).
TRUTH_SIGMA = 1.0

#: A streak counts as found by a mask when the mask covers at least this fraction of its core
#: (pixel centres within half a true FWHM of its line). Unlike the true region, the core exists
#: however faint the streak, and every masker is judged on the same footing.
CORE_COVER = 0.5

#: Names accepted by :func:`load_masker` besides ``module:function``.
BUILTIN_MASKERS = ("inject", "findsat_mrt")


class Masker:
    """A masking function, called as ``func(image)`` or ``func(image, bad=bad)``.

    The function gets the image array and returns a boolean mask (or a :class:`MaskerOutput`).
    It is given the bad-pixel mask only if it takes a ``bad`` keyword, so plain ``f(image)``
    functions work unchanged.

    Parameters
    ----------
    func : callable
    name : str, optional
        Label in tables and plots (default: the function's name).
    """

    def __init__(self, func, name=None):
        self.func = func
        self.name = name or getattr(func, "__name__", repr(func))
        try:
            self._takes_bad = "bad" in inspect.signature(func).parameters
        except (TypeError, ValueError):  # some builtins have no signature
            self._takes_bad = False

    def __call__(self, image, bad=None):
        """Run the function on ``image``: ``(MaskerOutput, wall seconds)``."""
        start = time.perf_counter()
        out = self.func(image, bad=bad) if self._takes_bad else self.func(image)
        seconds = time.perf_counter() - start
        if not isinstance(out, MaskerOutput):
            out = MaskerOutput(np.asarray(out))
        mask = np.asarray(out.mask, dtype=bool)
        if mask.shape != np.shape(image):
            raise MaskingError(f"masker {self.name} returned a mask of shape {mask.shape} for "
                               f"an image of shape {np.shape(image)}")
        return MaskerOutput(mask, out.streaks), seconds

    def __repr__(self):
        return f"Masker({self.name!r})"


def inject_masker(image, bad=None, pixel_scale=0.2, n_boot=0):
    """The built-in masker (:func:`~inject.masking.run.analyse`) as a masking function.

    ``n_boot`` is 0 by default: the bootstrap only gives the FWHM's error bar, which scoring
    against truth does not need.
    """
    from inject.masking.mask import mask_spans, paint  # SciPy, astropy: when first used

    res = analyse(image, bad=bad, pixel_scale=pixel_scale, n_boot=n_boot)
    mask = np.zeros(np.shape(image), dtype=bool)
    for s in res.streaks:
        paint(mask, mask_spans(mask.shape, Line(s["x0"], s["y0"], s["x1"], s["y1"]),
                               s["mask_width_px"]))
    return MaskerOutput(mask, res.streaks)


def load_masker(spec):
    """A :class:`Masker` from a callable, a built-in name or ``"module:function"``.

    Built-in names: ``inject`` (ours) and ``findsat_mrt`` (acstools, optional dependency; its
    own trail catalogue gives the lines and FWHMs scored).
    A module is imported only when a ``module:function`` spec names it.

    Raises
    ------
    InputError
        For a spec that is neither, or a function that cannot be imported.
    """
    if isinstance(spec, Masker):
        return spec
    if callable(spec):
        return Masker(spec)
    if spec == "inject":
        return Masker(inject_masker, "inject")
    if spec == "findsat_mrt":
        # acstools is optional: say it is missing now, not after the first image.
        external.trail_finder()
        return Masker(external.findsat_mrt_trails, "findsat_mrt")
    module, sep, name = str(spec).partition(":")
    if not sep or not module or not name:
        raise InputError("--masker", spec, "give module:function or one of "
                         + ", ".join(BUILTIN_MASKERS))
    try:
        func = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as err:
        raise InputError("--masker", spec, f"cannot be loaded ({err})") from None
    if not callable(func):
        raise InputError("--masker", spec, "is not callable")
    return Masker(func, spec)


def streak_regions(streak_model, truth, shape, pixel_scale=0.2):
    """Which truth streak each pixel of a streak-model image belongs to, and each one's core.

    Pixels with charge go to the nearest truth path (:func:`inject.truth.vertices`; exact for
    one streak; for crossing streaks the charge near the crossing is shared out by distance).

    Returns
    -------
    owner : ndarray of int
        Index of the truth row owning each pixel, -1 for none (no charge, or a row whose track
        misses the image).
    cores : dict
        ``{row index: (yy, xx)}`` pixels within half the true FWHM of the path's pieces in the
        image, each once.
    """
    owner = np.full(shape, -1, dtype=np.int32)
    paths = {i: truth_path(row, shape) for i, row in enumerate(truth)}
    yy, xx = np.nonzero(streak_model > 0)
    best = np.full(yy.size, np.inf)
    cores = {}
    for i, pieces in paths.items():
        if not pieces:
            continue
        d = path_distance(vertices(truth[i]), xx, yy)
        closer = d < best
        owner[yy[closer], xx[closer]] = i
        best[closer] = d[closer]
        half = max(0.5, 0.5 * truth[i]["fwhm_arcsec"] / pixel_scale)
        flat = np.unique(np.concatenate([np.ravel_multi_index(band_pixels(shape, piece, half),
                                                              shape) for piece in pieces]))
        cores[i] = np.unravel_index(flat, shape)
    return owner, cores


def _sum(values):
    return float(np.sum(values, dtype=np.float64))


def score_image(sim, output, seconds=float("nan"), truth_sigma=TRUTH_SIGMA, pixel_scale=0.2,
                max_angle_deg=0.5, max_offset_px=5.0):
    """Score one masker's output on one simulated image.

    Parameters
    ----------
    sim : inject.scene.SceneResult
        Simulated image with ``streak_model``, ``truth`` and ``noise_sigma``.
    output : MaskerOutput
    seconds : float
        Wall time the masker took (reported).
    truth_sigma : float
        ``t`` of the true region ``{streak_model > t x noise_sigma}``.
    pixel_scale : float
        Arcsec per pixel (true FWHM to pixels).
    max_angle_deg, max_offset_px : float
        Tolerances of :func:`match_streaks` for maskers that report lines.

    Returns
    -------
    image : dict
        Image-level numbers: ``masked_px``, ``false_positives`` (mask components touching no
        streak core, or unmatched lines for maskers that report them), ``recall``,
        ``overmask`` (masked pixels outside the true region over its size), ``iou``,
        ``flux_left`` (fraction of the injected streak charge outside the mask), ``time_s``.
    streaks : list of dict
        One per truth streak crossing the image: ``peak_sb`` (peak charge per pixel over the
        sky sigma), ``int_snr`` (matched-filter S/N, ``sqrt(sum model^2) / sigma``),
        ``core_cover``, ``found`` (core covered >= :data:`CORE_COVER`), ``line_found`` (None
        for mask-only maskers), ``angle_err_deg``, ``offset_px``, ``fwhm_true``,
        ``fwhm_meas`` (arcsec), ``recall`` (of that streak's true region).
    """
    from scipy import ndimage

    mask, model, sigma = output.mask, sim.streak_model, sim.noise_sigma
    shape = mask.shape
    truth = list(sim.truth)
    owner, cores = streak_regions(model, truth, shape, pixel_scale)
    region = model > truth_sigma * sigma
    n_region, n_mask = int(region.sum()), int(mask.sum())
    inter = int((mask & region).sum())
    union = n_region + n_mask - inter
    total = _sum(model)
    image = {
        "masked_px": n_mask, "region_px": n_region,
        "recall": inter / n_region if n_region else float("nan"),
        "overmask": (n_mask - inter) / n_region if n_region else float("nan"),
        "iou": inter / union if union else float("nan"),
        "flux_left": _sum(model[~mask]) / total if total > 0 else float("nan"),
        "time_s": seconds,
    }
    matches = None
    if output.streaks is not None:
        matches, false = match_streaks(output.streaks, truth, shape, max_angle_deg,
                                       max_offset_px)
        image["false_positives"] = len(false)
        matches = {m.truth_index: m for m in matches}
    else:
        # A mask component is a false positive if it touches no streak's core.
        labels, n = ndimage.label(mask, structure=np.ones((3, 3)))
        hit = np.zeros(n + 1, dtype=bool)
        for yy, xx in cores.values():
            hit[labels[yy, xx]] = True
        image["false_positives"] = int(n - hit[1:].sum())
    rows = []
    for i, (yy, xx) in cores.items():
        own = owner == i
        cover = float(mask[yy, xx].mean()) if yy.size else float("nan")
        own_region = region & own
        n_own = int(own_region.sum())
        row = {"truth_index": i, "peak_sb": truth[i]["peak_e_per_px"] / sigma,
               "int_snr": float(np.sqrt(_sum(model[own] ** 2))) / sigma,
               "core_cover": cover, "found": bool(cover >= CORE_COVER),
               "recall": int((mask & own_region).sum()) / n_own if n_own else float("nan"),
               "fwhm_true": float(truth[i]["fwhm_arcsec"]), "fwhm_meas": float("nan"),
               "line_found": None, "angle_err_deg": float("nan"), "offset_px": float("nan")}
        if matches is not None:
            m = matches[i]
            row["line_found"] = m.found_index is not None
            if m.found_index is not None:
                row["angle_err_deg"], row["offset_px"] = m.angle_error_deg, m.offset_px
                row["fwhm_meas"] = float(output.streaks[m.found_index].get("fwhm_arcsec",
                                                                           float("nan")))
        rows.append(row)
    return image, rows


def evaluate(images, maskers, truth_sigma=TRUTH_SIGMA, pixel_scale=0.2, bad=None):
    """Score maskers on simulated images: one record per (image, masker, truth streak).

    Parameters
    ----------
    images : iterable of SceneResult or (SceneResult, dict)
        Simulated images, optionally with labels copied into their records (e.g. height, mag,
        seed).
    maskers : list
        Anything :func:`load_masker` accepts.
    truth_sigma, pixel_scale : float
        See :func:`score_image`.
    bad : callable, optional
        ``bad(sim)`` -> bool array of unusable pixels, given to maskers that take ``bad``.

    Returns
    -------
    list of dict
        Image-level numbers (see :func:`score_image`) merged with each streak's; a streak-free
        image gives one record with ``found`` None, so its false positives still count.
    """
    maskers = [load_masker(m) for m in maskers]
    records = []
    for index, item in enumerate(images, 1):
        sim, labels = item if isinstance(item, tuple) else (item, {})
        flags = bad(sim) if bad is not None else None
        for masker in maskers:
            try:
                out, seconds = masker(sim.image, flags)
            except Exception as err:  # a user's function may raise anything: say whose, where
                what = err if isinstance(err, InjectError) else f"{type(err).__name__}: {err}"
                raise MaskingError(f"masker {masker.name} failed on {_describe(index, labels)}: "
                                   f"{what}") from err
            image, rows = score_image(sim, out, seconds, truth_sigma, pixel_scale)
            base = {"masker": masker.name, **labels, **image}
            for row in rows or [{"found": None}]:
                records.append(base | row)
    return records


def _describe(index, labels):
    """``image 3 (550 km, mag 11.00, seed 2)``: which image of a campaign."""
    if labels.get("streak_free"):
        return f"image {index} (streak-free, seed {labels.get('seed')})"
    parts = [f"{labels['height_km']:g} km" if labels.get("height_km") is not None else None,
             f"mag {labels['mag']:.2f}" if labels.get("mag") is not None else None,
             f"seed {labels['seed']}" if labels.get("seed") is not None else None]
    parts = [p for p in parts if p]
    return f"image {index}" + (f" ({', '.join(parts)})" if parts else "")


def summarise(records, by=("masker", "height_km", "mag")):
    """Aggregate records per group: completeness, errors, mask quality, time.

    Returns
    -------
    list of dict
        One per group (sorted), with the group keys and ``n``, ``peak_sb`` and ``int_snr``
        (medians), ``completeness`` (fraction with the core covered), ``line_completeness``
        (maskers reporting lines), ``fp_per_ccd``, ``angle_err_deg`` (median |error|),
        ``offset_px`` (median |offset|), ``fwhm_bias_pct`` and ``fwhm_scatter_pct`` (mean and
        standard deviation of measured / true - 1), ``recall``, ``overmask``, ``iou``,
        ``flux_left`` (means), ``masked_px`` and ``time_s`` (means).
    """
    groups = {}
    for r in records:
        groups.setdefault(tuple(r.get(k) for k in by), []).append(r)
    out = []
    for key in sorted(groups, key=lambda k: tuple((v is None, v) for v in k)):
        rs = groups[key]
        streaky = [r for r in rs if r.get("found") is not None]

        def col(name, rows=streaky):
            return np.array([np.nan if r.get(name) is None else r[name] for r in rows], float)

        def stat(func, values):
            values = values[np.isfinite(values)]
            return float(func(values)) if values.size else float("nan")

        lines = [r["line_found"] for r in streaky if r.get("line_found") is not None]
        ratio = 100 * (col("fwhm_meas") / col("fwhm_true") - 1)
        out.append({
            **dict(zip(by, key)), "n": len(streaky),
            "peak_sb": stat(np.median, col("peak_sb")), "int_snr": stat(np.median, col("int_snr")),
            "completeness": stat(np.mean, col("found")),
            "line_completeness": float(np.mean(lines)) if lines else float("nan"),
            "fp_per_ccd": stat(np.mean, col("false_positives", rs)),
            "angle_err_deg": stat(np.median, np.abs(col("angle_err_deg"))),
            "offset_px": stat(np.median, np.abs(col("offset_px"))),
            "fwhm_bias_pct": stat(np.mean, ratio), "fwhm_scatter_pct": stat(np.std, ratio),
            "recall": stat(np.mean, col("recall")), "overmask": stat(np.mean, col("overmask")),
            "iou": stat(np.mean, col("iou")), "flux_left": stat(np.mean, col("flux_left")),
            "masked_px": stat(np.mean, col("masked_px", rs)),
            "time_s": stat(np.mean, col("time_s", rs)),
        })
    return out


def completeness_point(peak_sb, completeness, level=0.5):
    """Peak surface brightness (sky sigma) where completeness first reaches ``level``, by
    linear interpolation in log brightness between neighbouring points; NaN if never reached
    (the faintest value if already reached there)."""
    x, c = np.asarray(peak_sb, float), np.asarray(completeness, float)
    keep = np.isfinite(x) & np.isfinite(c) & (x > 0)
    x, c = x[keep], c[keep]
    order = np.argsort(x)
    x, c = x[order], c[order]
    if x.size == 0 or not (c >= level).any():
        return float("nan")
    k = int(np.argmax(c >= level))
    if k == 0:
        return float(x[0])
    lx = np.log(x[k - 1:k + 1])
    f = (level - c[k - 1]) / (c[k] - c[k - 1])
    return float(np.exp(lx[0] + f * (lx[1] - lx[0])))
