"""One CCD scene: streaks (and, as configured, sky, stars and noise), with exact truth.

The engine takes a validated :class:`~inject.config.Scene` and returns arrays and a truth
table; writing files is :mod:`inject.io`'s job.
"""
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from inject.camera.detector import add_cosmic_rays, bleed_saturation, raw_layout
from inject.config import Scene, sky_level
from inject.errors import InputError, SceneError
from inject.instrument import LSST
from inject.maskplanes import (
    FLAG_CLIPPED,
    FLAG_OFF_IMAGE,
    FLAG_SATURATED,
    MASK_PLANES,
    STREAK_MASK_FRACTION,
    STREAK_MASK_SIGMA,
)
from inject.optics import telescope_position_angle
from inject.profile import Seeing, line_spread
from inject.progress import Progress
from inject.render import (
    AUTO_MIN_TOLERANCE,
    PROFILE_CACHE,
    SHORT_TRACK_CHECK_PX,
    Budget,
    render_polyline,
    render_segment,
    snap_tolerance,
    swept_profile,
)
from inject.stars import add_star_field
from inject.streak import StreakModel
from inject.trajectory import (
    Polyline,
    Segment,
    blurred_path,
    clip_path,
    clip_segment,
    path_distance,
)
from inject.truth import vertices

log = logging.getLogger(__name__)

#: Random streams, one per purpose, spawned from the scene seed (numpy SeedSequence). The
#: pixel noise (``noise``: the sky's and dark current's Poisson draws, ``signal_noise``: the
#: streaks' and stars', ``read_noise``) has a stream per fixed block of the whole sensor
#: (:class:`AmplifierNoise`), ``raw`` one per amplifier; ``stars`` and ``cosmic_rays`` are
#: drawn over the whole sensor: so a cut-out draws, pixel for pixel, what the whole CCD does.
STREAMS = {"stars": 0, "noise": 1, "cosmic_rays": 2, "raw": 3, "signal_noise": 4,
           "read_noise": 5}


#: Arrays of at least this many bytes that :func:`sparse_zeros` maps page by page.
SPARSE_MIN_BYTES = 1 << 22


def sparse_zeros(shape, dtype=np.float64):
    """A zero array for a plane most of which may stay zero (a streak's model, the mask).

    numpy asks the kernel for 2 MiB pages for large arrays: each first touch then zeroes
    (and counts in memory) 2 MiB, and where the kernel compacts memory to find them, costs
    system time. A streak's band touches every 2 MiB of the CCD's rows. This array is fresh
    private anonymous memory instead, mapped 4 KiB at a time as it is touched (untouched, it
    reads as zeros from the kernel's zero page); its values are np.zeros' in every way.
    """
    import mmap

    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if nbytes < SPARSE_MIN_BYTES or not hasattr(mmap, "MAP_PRIVATE"):
        return np.zeros(shape, dtype)
    memory = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    return np.frombuffer(memory, dtype).reshape(shape)


def rng(seed, purpose, detector_index=0, *block):
    """Independent generator for one purpose of one detector of a scene seed (and of one
    block of it, such as an amplifier's number, when given)."""
    return np.random.default_rng(
        np.random.SeedSequence(seed, spawn_key=(detector_index, STREAMS[purpose], *block)))


@dataclass
class SceneResult:
    """Arrays of one simulated CCD (electrons) and its truth.

    With noise, ``image`` and ``variance`` are float32 (the types written). Without any
    streak, ``streak_model`` is a read-only zero view of the CCD's shape (no memory).
    """

    image: np.ndarray
    mask: np.ndarray
    variance: np.ndarray
    streak_model: np.ndarray
    truth: list
    sky_level: float
    noise_sigma: float
    raw: np.ndarray | None = None
    raw_sections: list | None = None


def streak_models(scene):
    """The :class:`StreakModel` of every satellite of a scene."""
    telescope = LSST
    field_angle, radius = scene.field or (0.0, 0.0)
    # The image's +x is taken as the focal plane's: a CCD's turn by 90 deg is lost on the vanes.
    vanes = (None if scene.rotator_deg is None
             else telescope_position_angle(scene.rotator_deg, radius))
    return [StreakModel(height_km=s.height, zenith_deg=scene.zenith, phi_deg=s.phi,
                        shape=s.shape, mag=s.mag, band_name=scene.band,
                        seeing=Seeing(scene.seeing), telescope=telescope,
                        ref_range_km=s.ref_range, pupil=scene.pupil,
                        field_angle_deg=field_angle,
                        field_position_angle_deg=radius - s.track.angle,
                        focus_offset_um=scene.focus_offset_um,
                        telescope_position_angle_deg=vanes,
                        sed_temperature_k=s.sed_temperature_k)
            for s in scene.satellites]


def render_streaks(scene, budget=Budget()):
    """Noise-free streak charge of a scene (float64, e-) and one truth row per satellite."""
    return render_tracks(scene.detector.shape, streak_models(scene),
                         [s.track for s in scene.satellites], budget, pixel_noise(scene))


def pixel_noise(scene):
    """Typical per-pixel noise, e-: sky, dark current and the median read noise (0 without
    noise)."""
    if not scene.noise:
        return 0.0
    background = sky_level(scene) + scene.dark_current * scene.exptime
    return float(np.sqrt(background + scene.detector.median("read_noise") ** 2))


#: Streak wings are drawn until they fall below this fraction of the per-pixel noise.
NOISE_FRACTION = 0.05


#: Scenes with at least this many streaks report their progress (:mod:`inject.progress`).
PROGRESS_MIN_STREAKS = 20


def render_tracks(shape, models, tracks, budget=Budget(), noise_sigma=0.0,
                  cache=PROFILE_CACHE, progress=None):
    """Render streak models along tracks into a new image of ``shape``.

    Parameters
    ----------
    shape : tuple
        ``(ny, nx)``.
    models : list of StreakModel
    tracks : list of Track
        ``length=None`` crosses the whole image, with the end caps outside it.
    budget : Budget
    noise_sigma : float
        Per-pixel noise, e-. A bright streak's seeing wings stay above the noise far beyond
        the budget's relative tolerance: the tolerance is tightened (down to
        ``AUTO_MIN_TOLERANCE``, on the grid of :func:`~inject.render.snap_tolerance`) so
        that errors and the wings left out stay below ``NOISE_FRACTION`` of the noise (a cut
        would show as an edge).
    cache : ProfileCache or None
        Streaks with the same profile, angle and budget share one swept profile (its tables
        take most of a short streak's time); None builds each afresh.
    progress : bool, optional
        Report the streaks rendered (:mod:`inject.progress`, on this module's logger); by
        default only for :data:`PROGRESS_MIN_STREAKS` or more.

    Returns
    -------
    image : ndarray
        Streak charge, e-, float64.
    truth : list of dict
        One row per streak.
    """
    model_image = sparse_zeros(shape)
    budgets = [own_budget(budget, model, noise_sigma) for model in models]
    truth = [None] * len(tracks)
    counter = Progress(len(tracks), "rendering streaks", "streak", log,
                       len(tracks) >= PROGRESS_MIN_STREAKS if progress is None else progress)
    # Streaks that share tables are rendered one after the other, so a bounded cache builds
    # each table once (the image changes only by the order of float additions).
    for i in _grouped(models, tracks, budgets):
        model, track, own = models[i], tracks[i], budgets[i]
        if track.vertices is not None:
            truth[i] = _render_polyline_track(model_image, model, track, own, cache)
            counter.update()
            continue
        swept = swept_profile(model, track.angle, own,
                              np.inf if track.length is None else track.length, cache)
        if track.length is None:
            # The profile reaches support_px across and cap_px along: a line that far outside
            # the image still lights it.
            segment = Segment.crossing(shape, track.x0, track.y0, track.angle,
                                       margin=swept.plan.support_px + swept.plan.cap_px)
        else:
            segment = Segment(track.x0, track.y0, track.angle, track.length)
        charge = 0.0
        if segment is not None:
            charge = render_segment(model_image, swept, segment, model.flux_per_px).charge_added
        ends = (track.x0, track.y0, track.x0, track.y0, 0.0) if segment is None else (
            segment.x0, segment.y0, segment.x1, segment.y1, segment.length)
        expected = model.flux_per_px * ends[-1]  # the whole track's: FLAG_CLIPPED
        if track.length is not None:  # TRUTH describes the part the image receives
            reach = swept.plan.support_px + swept.plan.cap_px
            part = clip_segment(*ends[:4], (-0.5 - reach, shape[1] - 0.5 + reach),
                                (-0.5 - reach, shape[0] - 0.5 + reach))
            if part is not None:
                ends = (*part, float(np.hypot(part[2] - part[0], part[3] - part[1])))
        truth[i] = _truth_row(model, track, ends, charge, expected, own)
        counter.update()
    counter.close()
    for i, row in enumerate(truth):
        row["satellite"] = i
    return model_image, truth


def own_budget(budget, model, noise_sigma):
    """The budget tightened for a bright streak in noise (see :func:`render_tracks`)."""
    if noise_sigma > 0:
        tolerance = max(AUTO_MIN_TOLERANCE,
                        snap_tolerance(NOISE_FRACTION * noise_sigma / model.peak_e_per_px))
        if tolerance < budget.tolerance:
            return replace(budget, tolerance=tolerance)
    return budget


def _grouped(models, tracks, budgets):
    """Streak indices, those with the same profile, angle, budget and (short) length
    together, groups in order of first appearance; polylines keep their own place."""
    groups = {}
    for i, (model, track, own) in enumerate(zip(models, tracks, budgets)):
        if track.vertices is not None:
            key = ("polyline", i)
        else:
            length = np.inf if track.length is None else track.length
            key = (model.profile_key, track.angle, own,
                   length if length < SHORT_TRACK_CHECK_PX else np.inf)
        groups.setdefault(key, []).append(i)
    return [i for members in groups.values() for i in members]


_VERTEX_FIELDS = {"height": "height_km", "zenith": "zenith_deg", "phi": "phi_deg", "mag": "mag",
                  "range": "range_km", "angular_speed": "angular_speed_rad_s",
                  "field_angle": "field_angle_deg", "field_pa": "field_position_angle_deg"}


def _render_polyline_track(image, model, track, budget, cache=PROFILE_CACHE):
    """Render a polyline track whose vertices may override the model; return its truth row,
    which describes the part of the track the image receives (:mod:`inject.truth`)."""
    poly = Polyline(tuple(v["x"] for v in track.vertices), tuple(v["y"] for v in track.vertices))
    vertex_models = [replace(model, **_vertex_fields(model, track, poly, k, vertex))
                     for k, vertex in enumerate(track.vertices)]
    rendered = render_polyline(image, poly, vertex_models, budget, cache)
    fluxes = np.array([m.flux_per_px for m in vertex_models])
    steps = np.hypot(np.diff(poly.xs), np.diff(poly.ys))
    expected = float(np.sum(0.5 * (fluxes[:-1] + fluxes[1:]) * steps))
    part = _received_part(poly, steps, image.shape, rendered.reach_px)
    if part is None:  # nowhere near the image: described at its first vertex
        x, y = poly.xs[0], poly.ys[0]
        row = _truth_row(vertex_models[0], track, (x, y, x, y, 0.0), rendered.charge_added,
                         expected, budget)
    else:
        (s0, s1), ends = part
        middle, angle, flux = _along(poly, steps, vertex_models, fluxes, 0.5 * (s0 + s1))
        row = _truth_row(middle, replace(track, angle=angle), (*ends, s1 - s0),
                         rendered.charge_added, expected, budget)
        cum = np.concatenate([[0.0], np.cumsum(steps)])
        inside = [_along(poly, steps, vertex_models, fluxes, s)[2] for s in (s0, s1)]
        inside += list(fluxes[(cum > s0) & (cum < s1)])
        row.update(flux_per_px_e=flux, flux_per_px_min_e=float(min(inside)),
                   flux_per_px_max_e=float(max(inside)),
                   vertices=_part_vertices(poly, cum, (s0, s1), ends, vertex_models))
    row["n_vertices"] = len(poly.xs)
    return row


#: A corner of a polyline whose ridge the blur rounds by more than this (px) is described by
#: points of the rounded ridge (:func:`_corner`) instead of its vertex.
CORNER_TOLERANCE_PX = 0.01
#: Turns below this (deg) are not examined: a profile's mean distance along the track would
#: have to exceed 20 px for the rounding, ``tan(turn / 2)`` times it, to reach the tolerance.
CORNER_MIN_TURN_DEG = 0.05


def _part_vertices(poly, cum, stretch, ends, models):
    """The vertices of the stretch ``(s0, s1)`` (length along the polyline, ``cum`` at each
    vertex) that ends at ``ends = (x0, y0, x1, y1)``: its ends and the polyline's vertices
    between them (repeated ones once), a sharp corner replaced by points of the ridge that the
    profile of ``models`` (one per vertex) rounds it to (:func:`_corner`)."""
    s0, s1 = stretch
    points = [tuple(ends[:2])]
    for k in range(len(poly.xs)):
        if s0 < cum[k] < s1:
            points += _corner(poly, cum, k, models[k], stretch) or [(poly.xs[k], poly.ys[k])]
    points.append(tuple(ends[2:]))
    out = []
    for point in points:
        if not out or point != out[-1]:
            out.append((float(point[0]), float(point[1])))
    return tuple(out) if len(out) > 1 else (out[0], out[0])


def _corner(poly, cum, k, model, stretch):
    """Points of the ridge around vertex ``k`` of a polyline, or None where it turns so little
    that the ridge passes within :data:`CORNER_TOLERANCE_PX` of the vertex.

    The streak is the profile swept along straight pieces, so near a vertex a cut across the
    track collects the light of both pieces: the ridge is the polyline averaged along its
    length by the profile's marginal along the track (:func:`inject.trajectory.blurred_path`),
    which passes inside the vertex by about ``tan(turn / 2)`` times that marginal's mean
    distance. It is sampled every half that distance, out to where it rejoins the pieces
    (within half the tolerance), and no further than halfway to the neighbouring vertices or
    beyond the stretch described.
    """
    before = [j for j in range(k) if cum[j] < cum[k]]
    after = [j for j in range(k + 1, len(cum)) if cum[j] > cum[k]]
    if not before or not after:
        return None
    a, b = before[-1], after[0]
    turn = np.arctan2(poly.ys[b] - poly.ys[k], poly.xs[b] - poly.xs[k]) - np.arctan2(
        poly.ys[k] - poly.ys[a], poly.xs[k] - poly.xs[a])
    turn = abs((turn + np.pi) % (2 * np.pi) - np.pi)
    if np.degrees(turn) < CORNER_MIN_TURN_DEG:
        return None
    offsets, weights, mean = _along_track(model)
    slope = np.tan(turn / 2)
    if slope * mean <= CORNER_TOLERANCE_PX:
        return None
    step = mean / 2
    reach = min(cum[k] - cum[a], cum[b] - cum[k]) / 2
    reach = min(reach, cum[k] - stretch[0], stretch[1] - cum[k])
    j = 1
    while j * step < reach and slope * np.sum(
            weights * np.maximum(np.abs(offsets) - j * step, 0.0)) > CORNER_TOLERANCE_PX / 2:
        j += 1
    s = cum[k] + step * np.arange(-j, j + 1)
    s = s[np.abs(s - cum[k]) < reach]
    x, y = blurred_path(poly.xs, poly.ys, s, offsets, weights)
    return list(zip(x.tolist(), y.tolist()))


@lru_cache(maxsize=64)
def _along_track(model):
    """The marginal of a model's profile along the track (pixel response included): offsets
    (px, about its mean), weights (summing to 1) and its mean distance (px)."""
    import galsim

    spread = line_spread(model.profile.rotate(90 * galsim.degrees), model.pixel_scale,
                         pixel_angle_deg=0.0)
    offsets = np.asarray(spread.offset_arcsec) / model.pixel_scale
    weights = np.clip(np.asarray(spread.lsf), 0.0, None)
    weights = weights / weights.sum()
    offsets = offsets - offsets @ weights
    return offsets, weights, float(np.abs(offsets) @ weights)


def _vertex_fields(model, track, poly, k, vertex):
    """The model fields vertex ``k`` overrides. With the traced pupil, a vertex without its
    own ``field_pa`` keeps the field radius's direction on the image and takes its angle from
    its own piece's direction (the model's is from the first piece's, ``track.angle``)."""
    fields = {_VERTEX_FIELDS[key]: v for key, v in vertex.items() if key in _VERTEX_FIELDS}
    if model.pupil != "annulus" and "field_pa" not in vertex and len(poly.xs) > 1:
        j = min(k, len(poly.xs) - 2)
        heading = np.degrees(np.arctan2(poly.ys[j + 1] - poly.ys[j], poly.xs[j + 1] - poly.xs[j]))
        fields["field_position_angle_deg"] = float(
            model.field_position_angle_deg + track.angle - heading)
    return fields


def _received_part(poly, steps, shape, reach):
    """``((s0, s1), (x0, y0, x1, y1))``: the stretch of a polyline, by length along it, from
    where it first enters the image grown by ``reach`` px to where it last leaves; None if it
    never does."""
    ny, nx = shape
    pieces = clip_path(poly.xs, poly.ys,
                       (-0.5 - reach, nx - 0.5 + reach, -0.5 - reach, ny - 0.5 + reach))
    if not pieces:
        return None
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    (k0, t0, _), (k1, _, t1) = pieces[0], pieces[-1]
    s0, s1 = cum[k0] + t0 * steps[k0], cum[k1] + t1 * steps[k1]
    point = [(poly.xs[k] + t * (poly.xs[k + 1] - poly.xs[k]),
              poly.ys[k] + t * (poly.ys[k + 1] - poly.ys[k])) for k, t in ((k0, t0), (k1, t1))]
    return (float(s0), float(s1)), (*point[0], *point[1])


#: Model fields that vary along a polyline, interpolated between its vertices.
_VARYING = ("height_km", "zenith_deg", "phi_deg", "mag", "range_km", "angular_speed_rad_s",
            "field_angle_deg", "field_position_angle_deg")


def _along(poly, steps, models, fluxes, s):
    """The streak model, track angle and charge per pixel of track (as rendered: linear
    between vertices) at length ``s`` along a polyline."""
    cum = np.cumsum(steps)
    k = min(int(np.searchsorted(cum, s)), len(steps) - 1)
    while steps[k] == 0 and k > 0:  # a repeated vertex: the piece before it
        k -= 1
    f = (s - (cum[k] - steps[k])) / steps[k] if steps[k] > 0 else 0.0
    a, b = models[k], models[k + 1]
    fields = {}
    for name in _VARYING:
        va, vb = getattr(a, name), getattr(b, name)
        if va is not None and vb is not None:
            fields[name] = va + f * (vb - va)
    angle = float(np.degrees(np.arctan2(poly.ys[k + 1] - poly.ys[k], poly.xs[k + 1] - poly.xs[k])))
    flux = float(fluxes[k] + f * (fluxes[k + 1] - fluxes[k]))
    return replace(a, **fields), angle, flux


def _saturates_here(row, saturated):
    """Whether a streak that can reach full well left a saturated pixel on this image: a SAT
    pixel within three FWHM (plus two pixels of bleed) of the part of the track described."""
    if row["flags"] & FLAG_OFF_IMAGE or not len(saturated[0]):
        return False
    distance = path_distance(vertices(row), saturated[1], saturated[0])
    return bool(np.any(distance <= 3 * row["fwhm_arcsec"] / row["pixel_scale_arcsec"] + 2))


def _truth_row(model, track, ends, charge, expected, budget):
    """One TRUTH row: geometry and photometry of the model, where the track went
    (``ends = (x0, y0, x1, y1, length)``) and the charge that landed on the image."""
    g = model.geometry
    flags = 0
    if charge == 0:
        flags |= FLAG_OFF_IMAGE
    elif charge < expected * (1 - 2 * budget.flux_tolerance):
        flags |= FLAG_CLIPPED
    x0, y0, x1, y1, length = ends
    traced = {}
    if model.pupil != "annulus":
        pupil = model.summary_pupil()
        traced = {"field_angle_deg": float(model.field_angle_deg),
                  "field_position_angle_deg": pupil["field_position_angle_deg"],
                  "sed_temperature_k": pupil["sed_temperature_k"]}
    return traced | {
        "x0": x0, "y0": y0, "x1": x1, "y1": y1, "angle_deg": track.angle, "length_px": length,
        "height_km": g.height_km, "zenith_deg": g.zenith_deg, "phi_deg": g.phi_deg,
        "range_km": g.range_km, "nadir_angle_deg": g.nadir_angle_deg,
        "angular_speed_rad_s": g.angular_speed_rad_s, "t_eff_s": g.t_eff_s,
        "apparent_mag": model.apparent_mag, "flux_per_px_e": model.flux_per_px,
        "fwhm_arcsec": model.fwhm_arcsec, "peak_e_per_px": model.peak_e_per_px,
        "flux_per_px_min_e": model.flux_per_px, "flux_per_px_max_e": model.flux_per_px,
        "pixel_scale_arcsec": model.pixel_scale,
        "charge_in_image_e": float(charge), "n_vertices": 2, "flags": flags,
        "vertices": ((float(x0), float(y0)), (float(x1), float(y1))),
    }


#: Threads drawing the noise (None: the CPUs this process may run on); the focal-plane
#: runner's workers set 1, as their parallelism is one CCD per process.
NOISE_THREADS = None


class PoissonTable:
    """Draws of Poisson(``mean``) by inversion of its CDF, sped up by a guide table.

    A draw is the smallest ``k`` with ``CDF(k) > u`` for a uniform ``u`` in [0, 1): that is
    Poisson(mean) to the precision of the float64 CDF (the tail left out beyond ``mean + 40
    sqrt(mean) + 40`` has a probability far below 2**-53). The guide table gives, for each of
    :attr:`GUIDE` equal slices of ``u``, the first ``k`` it can map to; where a slice holds at
    most one CDF step, one comparison finishes the draw, elsewhere (the far tails, a few
    slices) a binary search does. About twice as fast as numpy's ``poisson`` at sky levels.
    """

    GUIDE = 1 << 14
    #: Larger means take numpy's own sampler (the table would be too long).
    MAX_MEAN = 1e6

    def __init__(self, mean):
        # pdtr is what scipy.stats.poisson.cdf evaluates, without importing scipy.stats
        # (about half a second of a process's start).
        from scipy.special import pdtr

        kmax = _kmax(mean)
        self.cdf = pdtr(np.arange(kmax + 1), mean)
        self.cdf[-1] = 1.0  # every u < 1 maps inside the table
        self.guide = np.searchsorted(self.cdf, np.arange(self.GUIDE) / self.GUIDE, side="right")
        # Slice j maps to guide[j] .. guide[j + 1]: more than one step needs the search.
        self.wide = np.diff(self.guide, append=kmax) > 1

    def draw(self, gen, shape):
        """An int64 array of ``shape`` of Poisson draws from generator ``gen``."""
        u = gen.random(shape)
        cell = (u * self.GUIDE).astype(np.intp)  # exact: GUIDE is a power of 2
        k = self.guide[cell]
        k += self.cdf[k] <= u
        # The draws in wide slices, by one lookup (faster than comparing u with the bounds
        # of the tails that hold them).
        rare = np.flatnonzero(self.wide[cell])
        if rare.size:
            np.put(k, rare, np.searchsorted(self.cdf, np.take(u, rare), side="right"))
        return k


def _kmax(mean):
    """Largest count drawn for ``mean``: the CDF is 1 to float64 precision beyond it."""
    return np.floor(mean + 40 * np.sqrt(mean) + 40).astype(np.int64)


@lru_cache(maxsize=8)
def _poisson_table(mean):
    return PoissonTable(mean)


def draw_poisson(gen, mean, shape):
    """Poisson(``mean``) draws of ``shape`` (int64) for one scalar mean >= 0: by
    :class:`PoissonTable` (cached per mean) up to its :attr:`~PoissonTable.MAX_MEAN`."""
    if mean <= PoissonTable.MAX_MEAN:
        return _poisson_table(float(mean)).draw(gen, shape)
    return gen.poisson(mean, size=shape)


#: :func:`poisson_inverse` sums the CDF up from 0 below this mean; from it on, it starts at a
#: normal approximation (on the default CCD's streak and stars, any threshold from 3 to 30
#: takes the same time).
SEARCH_MEAN = 10.0


def poisson_inverse(u, mean):
    """Poisson draws by inversion, one uniform each: the smallest ``k`` with ``CDF(k) > u``
    for Poisson(``mean``), element by element (each its own mean; int64, the shape of ``u``).

    A draw depends only on its own ``u`` and mean, so a pixel's count does not depend on
    which other pixels are drawn (a cut-out's pixels get the whole CCD's counts). Like
    :class:`PoissonTable`, it is Poisson to the precision of the float64 CDF, and stops at
    ``mean + 40 sqrt(mean) + 40``. ``CDF(0) = exp(-mean) >= 1 - mean``, so ``u < 1 - mean``
    is ``k = 0`` at once (most pixels of a wing); below :data:`SEARCH_MEAN` the CDF is summed
    up from 0 (pmf by recurrence), above it the search starts at the Cornish-Fisher normal
    approximation (``scipy.special.pdtr`` there) and steps by the pmf (a step or two).

    Parameters
    ----------
    u : array_like
        Uniforms in [0, 1).
    mean : array_like
        Means >= 0, the shape of ``u``.
    """
    u = np.asarray(u, dtype=np.float64)
    mean = np.asarray(mean, dtype=np.float64)
    k = np.zeros(u.size, np.int64)
    flat_u, flat_m = u.ravel(), mean.ravel()
    todo = np.flatnonzero(flat_u >= 1.0 - flat_m)
    if todo.size:
        m, uu = flat_m[todo], flat_u[todo]
        low = m < SEARCH_MEAN
        k[todo[low]] = _search_up(uu[low], m[low])
        k[todo[~low]] = _search_near(uu[~low], m[~low])
    return k.reshape(u.shape)


def _search_up(u, m):
    """:func:`poisson_inverse` for small means: the CDF summed from 0 until it exceeds ``u``."""
    k = np.zeros(u.size, np.int64)
    p = np.exp(-m)
    cdf = p.copy()
    active = np.flatnonzero(u >= cdf)
    u, m, p, cdf, kmax = u[active], m[active], p[active], cdf[active], _kmax(m[active])
    j = 0
    while active.size:
        j += 1
        p *= m / j
        cdf += p
        going = (u >= cdf) & (j < kmax)
        k[active[~going]] = j
        if not going.all():
            active, u, m, p, cdf, kmax = (a[going] for a in (active, u, m, p, cdf, kmax))
    return k


def _search_near(u, m):
    """:func:`poisson_inverse` for larger means: from the normal approximation with the
    skewness term (``CDF(k)`` by ``scipy.special.pdtr``), up while ``CDF(k) <= u``, down while
    ``CDF(k - 1) > u``, the neighbouring CDF values by adding or taking the pmf (to the
    absolute precision of the float64 CDF, that of ``u``)."""
    from scipy.special import gammaln, ndtri, pdtr, xlogy

    kmax = _kmax(m)
    z = ndtri(np.maximum(u, 1e-300))
    k = np.clip(np.floor(m + np.sqrt(m) * z + (z * z - 1) / 6), 0, kmax).astype(np.int64)
    cdf = pdtr(k, m)
    pmf = np.exp(xlogy(k, m) - m - gammaln(k + 1.0))
    up = (cdf <= u) & (k < kmax)
    # Stepping up ends at the first k with CDF(k) > u; the others may have to step down.
    step = np.flatnonzero(up)
    while step.size:
        k[step] += 1
        pmf[step] *= m[step] / k[step]
        cdf[step] += pmf[step]
        step = step[(cdf[step] <= u[step]) & (k[step] < kmax[step])]
    step = np.flatnonzero(~up & (k > 0))
    step = step[cdf[step] - pmf[step] > u[step]]
    while step.size:
        cdf[step] -= pmf[step]
        pmf[step] *= k[step] / m[step]
        k[step] -= 1
        step = step[k[step] > 0]
        step = step[cdf[step] - pmf[step] > u[step]]
    return k


def _last_lit_row(part, step=8):
    """Index of the last row of ``part`` with a value > 0, or -1 if none: looked for from the
    end, ``step`` rows at a time (the stars light the last rows of most blocks, so this
    reads a few rows instead of the whole block)."""
    for end in range(part.shape[0], 0, -step):
        lit = np.flatnonzero(part[max(end - step, 0):end].max(axis=1) > 0)
        if lit.size:
            return max(end - step, 0) + int(lit[-1])
    return -1


#: Rows of an amplifier per noise block (its last block holds what is left).
BLOCK_ROWS = 256


@dataclass(frozen=True)
class _Block:
    """Pixels of one noise block inside the image: ``region`` (row and column slices) and
    its place on the sensor, ``key = (amplifier row, amplifier column, strip)``."""

    key: tuple
    region: tuple
    read_noise: float


class AmplifierNoise:
    """Poisson and read noise drawn in fixed blocks of the whole sensor, on a thread pool.

    The blocks: each amplifier of the whole sensor (:attr:`Detector.full_shape
    <inject.camera.detector.Detector.full_shape>`), cut into strips of :data:`BLOCK_ROWS`
    rows from its first row. Each block has one random stream per purpose (``noise``: the
    level's Poisson draws; ``signal_noise``: those of the varying charge; ``read_noise``),
    keyed on the seed, the detector, the purpose, the amplifier and the strip, and takes its
    numbers pixel by pixel in rows of the amplifier's whole width. A cut-out (pixels ``[0,
    ny) x [0, nx)`` of the sensor) holds the first rows of its blocks, and the first columns
    of those rows: it draws the same numbers, leaving out those beyond its last column, so
    each pixel gets the numbers the whole CCD gives it. The draws do not depend on the
    threads either (numpy's generators release the GIL: two cores draw twice as fast).

    The expected charge comes in two parts: a level uniform over the CCD (sky and dark
    current) and what varies per pixel (``varying``: streaks and stars). As the sum of
    independent Poisson variables is Poisson with the summed mean, each block draws
    Poisson(level) for all its pixels (one mean: :func:`draw_poisson`) and, from its other
    stream, Poisson(varying) where ``varying > 0``, by inversion of one uniform per pixel at
    the pixel's own mean (:func:`poisson_inverse`; the block's rows up to its last lit one
    each take a uniform per pixel, lit or not, so the numbers stay on their pixels): the
    collected charge is distributed exactly as Poisson of the total per pixel
    (tests/test_noise_split.py checks it).
    """

    def __init__(self, detector, seed, detector_index=0, threads=None):
        self.shape = ny, nx = detector.shape
        self.seed, self.detector_index = seed, detector_index
        self.width = detector.amp_nx
        amp_ny, amp_nx = detector.amp_ny, detector.amp_nx
        self.blocks = []
        for r in range(-(-ny // amp_ny)):
            for c in range(-(-nx // amp_nx)):
                cols = slice(c * amp_nx, min((c + 1) * amp_nx, nx))
                # Each block lies in one amplifier: its read noise is one number.
                sigma = detector.amp_value("read_noise", r * amp_ny, c * amp_nx)
                top = min((r + 1) * amp_ny, ny)
                for s, y in enumerate(range(r * amp_ny, top, BLOCK_ROWS)):
                    rows = slice(y, min(y + BLOCK_ROWS, top))
                    self.blocks.append(_Block((r, c, s), (rows, cols), sigma))
        # The CPUs this process may run on (a batch job's affinity), not the node's.
        usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else \
            os.cpu_count() or 1
        self.threads = threads or NOISE_THREADS or min(len(self.blocks), usable)

    def generator(self, purpose, block):
        """The random stream of one purpose of one block."""
        # SFC64: numpy's fastest bit generator here (float32 normals ~15% faster than PCG64's).
        return np.random.Generator(np.random.SFC64(np.random.SeedSequence(
            self.seed, spawn_key=(self.detector_index, STREAMS[purpose], *block.key))))

    def _each(self, work):
        if self.threads == 1:  # no pool to start and join in a single-threaded worker
            for block in self.blocks:
                work(block)
            return
        with ThreadPoolExecutor(self.threads) as pool:
            list(pool.map(work, self.blocks))

    #: Pixels drawn at a time: the uniforms, guide indices and counts of a chunk (8 bytes a
    #: pixel each) stay in the core's cache instead of streaming through memory (the table's
    #: draw alone: 8 instead of 13 ms per Mpx here); the numbers come in the same order, so
    #: the image is the one a whole-block draw gives.
    CHUNK_PX = 1 << 16

    def _chunks(self, n_rows):
        """``(first row, rows)`` of the chunks of a block's ``n_rows`` rows."""
        rows = max(1, self.CHUNK_PX // max(1, self.width))
        return [(r, min(rows, n_rows - r)) for r in range(0, n_rows, rows)]

    def draw(self, level, varying=None, dtype=np.float32):
        """Collected charge for the expected charge ``level + varying``, and its variance.

        One pass per block: Poisson(level) for every pixel, Poisson(varying) added where
        ``varying > 0``, and the variance ``level + max(varying, 0) + read_noise**2`` (the
        Poisson mean drawn plus the amplifier's read noise squared) from the same pixels.

        Parameters
        ----------
        level : float
            Expected charge of every pixel, e- (>= 0).
        varying : ndarray, optional
            Expected charge on top of it, per pixel, of the image's shape; values <= 0 add
            nothing (the streak model can dip a few 1e-6 of its peak below zero by
            interpolation).
        dtype : numpy dtype
            Of the image: float32 holds every count exactly up to 2**24 e- (100 full wells).

        Returns
        -------
        image : ndarray of ``dtype``
        variance : ndarray of float32
        """
        if varying is not None and varying.shape != self.shape:
            raise InputError("varying", varying.shape, f"must have the image's shape {self.shape}")
        image = np.empty(self.shape, dtype)
        variance = np.empty(self.shape, np.float32)

        def draw(block):
            out, var = image[block.region], variance[block.region]
            width = out.shape[1]
            if level > 0:
                gen = self.generator("noise", block)
                for r, n in self._chunks(out.shape[0]):
                    out[r:r + n] = draw_poisson(gen, level, (n, self.width))[:, :width]
            else:
                out[...] = 0
            var[...] = np.float32(level + block.read_noise ** 2)
            if varying is None:
                return
            part = varying[block.region]
            last = _last_lit_row(part)
            if last < 0:
                return
            gen = self.generator("signal_noise", block)
            chunks = self._chunks(last + 1)
            scratch = np.empty((chunks[0][1], width))
            rows, cols, uniforms = [], [], []
            for r, n in chunks:
                u = gen.random((n, self.width))[:, :width]
                mean = part[r:r + n]
                # CDF(0) = exp(-mean) >= 1 - mean: elsewhere the count is 0 (and where
                # mean <= 0, always).
                bound = np.subtract(1.0, mean, out=scratch[:n])
                y, x = np.nonzero(u >= bound)
                rows.append(y + r)
                cols.append(x)
                uniforms.append(u[y, x])
                np.add(var[r:r + n], np.maximum(mean, 0.0, out=scratch[:n]), out=var[r:r + n],
                       casting="unsafe")
            # One inversion for the block's pixels that may count (its loops run once, not
            # once per chunk); summed in float64 and rounded once: the counts stay exact.
            y, x = np.concatenate(rows), np.concatenate(cols)
            out[y, x] += poisson_inverse(np.concatenate(uniforms), part[y, x])
        self._each(draw)
        return image, variance

    def add_read_noise(self, image):
        """Add Gaussian read noise to ``image`` in place (float32 normals: far finer than
        the noise itself) and return it."""
        def draw(block):
            gen = self.generator("read_noise", block)
            out = image[block.region]
            sigma = np.float32(block.read_noise)
            for r, n in self._chunks(out.shape[0]):
                noise = gen.standard_normal(size=(n, self.width), dtype=np.float32)
                noise *= sigma
                out[r:r + n] += noise[:, :out.shape[1]]
        self._each(draw)
        return image


def simulate(scene, budget=Budget(), detector_index=0, wcs=None, rendered=None,
             add_stars=None):
    """Simulate one CCD of a scene.

    ``rendered`` (the ``(image, truth)`` of :func:`render_tracks`) and ``add_stars`` (a
    function ``add_stars(image)`` adding the stars' expected charge to a float64 image in
    place, as :func:`~inject.stars.draw_stars` does) let a caller that places streaks and
    stars itself, such as the focal plane, reuse the rest.

    The order follows the charge: streaks, sky, stars and dark current are expected charge;
    Poisson noise draws the collected charge; saturation bleeds it along columns; cosmic rays
    add to it; read noise and (for ``units: adu``) the amplifiers' gains come last.

    A cut-out (a detector of ``nx x ny`` pixels: pixels ``[0, ny) x [0, nx)`` of the sensor)
    gets the whole CCD's pixels byte for byte, noise included: every random number is drawn
    for a fixed block of the whole sensor (:class:`AmplifierNoise`, :data:`STREAMS`), the
    random stars and cosmic rays over the whole sensor. Only saturation can differ: charge
    bleeds along a column and stops at the image's edges, the cut-out's top edge (row ``ny
    - 1``) included, so a bleed trail that crosses that row in the whole CCD differs there
    (tests/test_cutout_noise.py).

    Returns
    -------
    SceneResult

    Raises
    ------
    SceneError
        ``scene`` is not a :class:`~inject.config.Scene` (a raw mapping goes through
        :func:`~inject.config.parse_scene` first), or holds a bad sky.
    """
    if not isinstance(scene, Scene):
        raise SceneError(f"scene={type(scene).__name__}: pass a Scene "
                         f"(inject.config.parse_scene of the mapping)")
    det = scene.detector
    if scene.stars and add_stars is None:
        def add_stars(image):
            # Random stars over the whole sensor: a cut-out has the whole CCD's stars.
            return add_star_field(image, scene, rng(scene.seed, "stars", detector_index),
                                  wcs=wcs, field_shape=det.full_shape)
    noise = AmplifierNoise(det, scene.seed, detector_index) if scene.noise else None
    stars = None
    if noise is not None and scene.stars:
        # The stars' expected charge, to join the streaks' (a sum of its own: the model is
        # written as it is), so that each pixel's charge is drawn from its block's stream.
        # With a core to spare, the streaks render meanwhile (each into its own array: the
        # same numbers in either order).
        stars = np.zeros(det.shape)
        if rendered is None and noise.threads > 1:
            with ThreadPoolExecutor(1) as pool:
                pending = pool.submit(render_streaks, scene, budget)
                add_stars(stars)
                rendered = pending.result()
        else:
            add_stars(stars)
    streaks, truth = render_streaks(scene, budget) if rendered is None else rendered
    sky = sky_level(scene)
    # Expected charge = level (uniform: sky, dark current) + streaks + stars.
    level = sky + scene.dark_current * scene.exptime
    if not truth:
        # No streak: no model to add, keep or write (a read-only zero view costs nothing).
        streaks = np.broadcast_to(np.float32(0), det.shape)
    mask = sparse_zeros(det.shape, np.int32)
    if noise is not None:
        varying = streaks if truth else None
        if stars is not None:
            varying = stars
            if truth:
                varying += streaks
        # float32, as written: the counts are integers, exact in float32 to 2**24 e-.
        image, variance = noise.draw(level, varying, np.float32)
        del varying, stars
    else:
        image = np.full(det.shape, level) if not truth else streaks + level
        if scene.stars:
            add_stars(image)
    saturated = bleed_saturation(image, det.full_well, det.midline)
    if scene.cosmic_rays > 0:
        cr_rng = rng(scene.seed, "cosmic_rays", detector_index)
        cosmic = add_cosmic_rays(image, scene.cosmic_rays * scene.exptime, cr_rng,
                                 full_shape=det.full_shape)
        mask[cosmic] |= 1 << MASK_PLANES["CR"]
    raw = sections = None
    if det.layout == "raw":  # the amplifiers read the collected charge, adding their own noise
        raw, sections = raw_layout(image, det,
                                   lambda amp: rng(scene.seed, "raw", detector_index, amp),
                                   det.bias)
    if noise is not None:
        noise.add_read_noise(image)
        noise_sigma = pixel_noise(scene)
    else:
        variance = np.zeros(det.shape)
        noise_sigma = 0.0
    if noise_sigma > 0:
        threshold = STREAK_MASK_SIGMA * noise_sigma
    else:
        threshold = STREAK_MASK_FRACTION * max((row["peak_e_per_px"] for row in truth), default=0)
    if truth:
        mask[streaks > threshold] |= 1 << MASK_PLANES["STREAK"]
    mask[saturated] |= 1 << MASK_PLANES["SAT"]
    for row in truth:
        if row["peak_e_per_px"] + sky >= det.full_well and _saturates_here(row, saturated):
            row["flags"] |= FLAG_SATURATED
    if scene.units == "adu":
        gain = det.per_pixel("gain")
        image, variance = image / gain, variance / gain ** 2
    return SceneResult(image=image, mask=mask, variance=variance, streak_model=streaks,
                       truth=truth, sky_level=sky, noise_sigma=noise_sigma, raw=raw,
                       raw_sections=sections)
