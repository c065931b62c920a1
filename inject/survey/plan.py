"""The plan of a survey night: each visit's sunlit streaks on the science CCDs, and the pixels
their masks take. No pixel is rendered.

For each visit (:func:`plan_visit`):

1. Candidates: :class:`inject.survey.prefilter.NightPrefilter` (the constellation propagated
   once per 300 s node of the night and interpolated; the satellites whose coarse track comes
   within the field's 2.1 deg and a margin of 0.05-0.1 deg of the boresight).
2. Exact passes of the candidates: :func:`inject.orbits.passes.compute_pass` every
   :data:`~inject.orbits.passes.TRACK_STEP_S` (light time, the stars' aberration, the
   penumbra), all sharing one :class:`~inject.orbits.passes.FieldFrame` of the visit's times
   (:func:`visit_frame`: astropy every 15 s, interpolated between; :func:`plan_visits` asks
   astropy for the nodes of many visits at once).
3. Sunlit runs: :func:`inject.orbits.tracks.sunlit_runs`, the track's sunlit parts as
   focal-plane polylines with the model's values at each vertex (a vertex at least every second
   and wherever the path bends by 0.05 px). A visit of several snaps has no streak during the
   readouts between them.
4. Crossing: a run *crosses* a CCD when its centre line enters the CCD's pixel area (the gaps
   between CCDs are no CCD). A satellite whose sunlit runs cross at least one CCD is a streak
   of the visit: one row of ``streaks.csv``.
5. The streak's model at the middle of its crossing (the vertex values there, the visit's band
   and seeing): FWHM, peak surface brightness, and the mask width by the masker's surface-
   brightness rule (:func:`mask_width_px`) against the visit's sky noise.
6. Pixels lost: the mask, a rectangle of that width along every segment of the run with end
   caps of half the width at the run's ends (as :func:`inject.masking.mask.mask_spans` draws
   it along a measured line), rasterised on each CCD it reaches (pixel centres inside), and
   the streaks of a visit merged on each CCD so that their overlaps count once. With a fixed
   width (``--mask-width``, :mod:`inject.survey.fixed_mask`) a band of that width is counted
   the same way beside it.

Every number is per visit; nothing is kept between visits but the constellation and its
positions at the night's nodes.
"""
import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from inject.camera import layout as fp
from inject.camera.wcs import Pointing
from inject.errors import InputError, InputWarning, OrbitWarning
from inject.instrument import LSST
from inject.masking.geometry import rectangles_spans
from inject.masking.mask import MIN_FWHM
from inject.maskplanes import STREAK_MASK_SIGMA
from inject.optics import FIELD_MAX_DEG, telescope_position_angle
from inject.orbits.passes import (
    RUBIN,
    TRACK_STEP_S,
    Exposure,
    FieldFrame,
    compute_pass,
)
from inject.orbits.tracks import sunlit_runs
from inject.photometry import sky_per_pixel
from inject.profile import Seeing
from inject.streak import StreakModel
from inject.survey.prefilter import NightPrefilter
from inject.survey.visits import ROTATOR_SOURCES
from inject.trajectory import clip_path_boxes

#: Pixels of the 189 science CCDs.
TOTAL_PIXELS = int(sum(c.shape[0] * c.shape[1] for c in fp.CCDS))
#: Seeing of the streak model when a visit has none (the model's default), arcsec.
DEFAULT_SEEING = Seeing().fwhm_arcsec
#: Vertices more than this many seconds apart belong to different snaps (a run's vertices are
#: at most 1 s apart).
SNAP_BREAK_S = 1.5

#: Columns of ``streaks.csv``.
STREAK_FIELDS = ("observationId", "satellite", "n_ccds", "ccds", "length_deg", "mag",
                 "fwhm_arcsec", "peak_e_per_px", "mask_width_px", "pixels_lost", "band",
                 "mjd", "t_mid_s", "alt_deg", "range_km", "height_km",
                 "angular_speed_deg_s", "sun_fraction_min", "sunlit_parts", "rule")
#: Columns of ``visits.csv``.
VISIT_FIELDS = ("observationId", "mjd", "band", "n_streaks", "n_ccds_streaked",
                "streak_length_deg", "pixels_lost", "pixel_fraction_lost", "fieldRA", "fieldDec",
                "rotSkyPos", "exptime_s", "alt_deg", "seeing_arcsec", "sky_e_per_px",
                "n_candidates")
#: Columns ``--mask-width`` adds to ``streaks.csv`` (:mod:`inject.survey.fixed_mask`).
FIXED_STREAK_FIELDS = ("pixels_fixed_mask",)
#: Columns ``--mask-width`` adds to ``visits.csv``.
FIXED_VISIT_FIELDS = ("pixels_fixed_mask", "pixel_fraction_fixed_mask")


@dataclass
class Streak:
    """One satellite's sunlit crossing of a visit's science CCDs.

    Attributes
    ----------
    satellite : str
        The satellite's name.
    ccds : tuple of str
        CCDs its sunlit centre line crosses, in detector-id order.
    length_deg : float
        Length of its sunlit track on those CCDs (the gaps excluded), deg.
    mag : float
        Apparent AB magnitude at the middle of the crossing (penumbra included).
    fwhm_arcsec : float
        The model's FWHM across the track (:attr:`inject.streak.StreakModel.fwhm_arcsec`).
    peak_e_per_px : float
        The model's peak surface brightness, e-/px.
    mask_width_px : float
        The mask's full width (:func:`mask_width_px`), averaged over the CCDs crossed by
        their share of the length (it depends on the sensor's read noise).
    pixels_lost : int
        Pixels its mask takes on all CCDs (those shared with another streak of the visit
        included: the visit's total counts them once).
    pixels_fixed_mask : int or None
        The same for a band of the fixed width ``--mask-width`` (None without it).
    rule : str
        The rule that counted it: ``inject`` (this module) or ``rubin_sim``
        (:mod:`inject.survey.rubin_rule`: no CCDs, the length and a fixed band inside the
        1.75 deg circle).
    """

    satellite: str
    ccds: tuple
    length_deg: float
    mag: float
    fwhm_arcsec: float
    peak_e_per_px: float
    mask_width_px: float
    pixels_lost: int = 0
    t_mid_s: float = math.nan
    alt_deg: float = math.nan
    range_km: float = math.nan
    height_km: float = math.nan
    angular_speed_deg_s: float = math.nan
    sun_fraction_min: float = math.nan
    sunlit_parts: int = 1
    pixels_fixed_mask: int | None = None
    rule: str = "inject"


@dataclass
class VisitPlan:
    """A visit's streaks and the pixels their masks take.

    ``pixels_by_ccd`` maps a CCD's name to the pixels masked on it (every streak of the
    visit merged), ``sky_e_per_px`` and ``seeing_arcsec`` are what the masks were computed
    with (None when the visit has no candidate). With a fixed width (``--mask-width``,
    ``fixed_width_px``), ``fixed_by_ccd`` holds the same for a band of that width.
    """

    visit: object
    streaks: list = field(default_factory=list)
    pixels_by_ccd: dict = field(default_factory=dict)
    n_candidates: int = 0
    alt_deg: float = math.nan
    sky_e_per_px: float | None = None
    seeing_arcsec: float | None = None
    fixed_width_px: float | None = None
    fixed_by_ccd: dict = field(default_factory=dict)

    @property
    def pixels_lost(self):
        return int(sum(self.pixels_by_ccd.values()))

    @property
    def pixels_fixed_mask(self):
        """Pixels the fixed-width band takes (overlaps once); None without a fixed width."""
        if self.fixed_width_px is None:
            return None
        return int(sum(self.fixed_by_ccd.values()))

    @property
    def streak_length_deg(self):
        """The streaks' total length on the science CCDs (each its ``length_deg``), deg."""
        return float(sum(s.length_deg for s in self.streaks))

    @property
    def n_ccds_streaked(self):
        return len({c for s in self.streaks for c in s.ccds})

    def streak_rows(self):
        """The visit's rows of ``streaks.csv`` (:data:`STREAK_FIELDS`)."""
        v = self.visit
        return [{"observationId": v.observation_id, "satellite": s.satellite, "rule": s.rule,
                 "n_ccds": len(s.ccds), "ccds": " ".join(s.ccds),
                 "length_deg": s.length_deg, "mag": s.mag, "fwhm_arcsec": s.fwhm_arcsec,
                 "peak_e_per_px": s.peak_e_per_px, "mask_width_px": s.mask_width_px,
                 "pixels_lost": s.pixels_lost, "band": v.band, "mjd": v.mjd_tai,
                 "t_mid_s": s.t_mid_s, "alt_deg": s.alt_deg, "range_km": s.range_km,
                 "height_km": s.height_km, "angular_speed_deg_s": s.angular_speed_deg_s,
                 "sun_fraction_min": s.sun_fraction_min, "sunlit_parts": s.sunlit_parts,
                 "pixels_fixed_mask": s.pixels_fixed_mask}
                for s in self.streaks]

    def visit_row(self):
        """The visit's row of ``visits.csv`` (:data:`VISIT_FIELDS`, and
        :data:`FIXED_VISIT_FIELDS`, None without a fixed width)."""
        v = self.visit
        fixed = self.pixels_fixed_mask
        return {"observationId": v.observation_id, "mjd": v.mjd_tai, "band": v.band,
                "n_streaks": len(self.streaks), "n_ccds_streaked": self.n_ccds_streaked,
                "streak_length_deg": self.streak_length_deg,
                "pixels_lost": self.pixels_lost,
                "pixels_fixed_mask": fixed,
                "pixel_fraction_fixed_mask": None if fixed is None else fixed / TOTAL_PIXELS,
                "pixel_fraction_lost": self.pixels_lost / TOTAL_PIXELS,
                "fieldRA": v.ra_deg, "fieldDec": v.dec_deg, "rotSkyPos": v.rotation_deg,
                "exptime_s": v.exptime_s, "alt_deg": self.alt_deg,
                "seeing_arcsec": self.seeing_arcsec, "sky_e_per_px": self.sky_e_per_px,
                "n_candidates": self.n_candidates}


# --- the visit's sky -----------------------------------------------------------------------

def sky_sigma(visit, alt_deg, vendor):
    """Per-pixel noise of a visit's image, e-: sky and read noise (one read per snap).

    The sky is the visit's ``skyBrightness`` when given, else the band's dark sky at zenith
    (SMTN-002, :func:`inject.photometry.sky_per_pixel`) brightened by the airmass ``sec z``
    at the boresight's altitude, over the whole open-shutter time.

    Returns
    -------
    sigma : float
        e- per pixel.
    sky : float
        The sky alone, e- per pixel.
    """
    sky = sky_per_pixel(visit.band, visit.exptime_s, LSST.pixel_scale_arcsec,
                        visit.sky_brightness)
    if visit.sky_brightness is None:
        sky /= math.sin(math.radians(max(alt_deg, 1.0)))
    read = fp.SENSORS[vendor].median("read_noise")
    return math.sqrt(sky + visit.n_exposures * read ** 2), float(sky)


def mask_width_px(model, sigma, sb_sigma=STREAK_MASK_SIGMA):
    """Full width (px) of the mask the masker's surface-brightness rule gives this streak.

    The rule of :func:`inject.masking.mask.sb_width`, on the model's cross-section instead of
    a measured profile: out to where the charge per pixel (pixels aligned with the track,
    :attr:`~inject.streak.StreakModel.pixel_lsf`) drops below ``sb_sigma`` times the sky noise
    ``sigma`` (e-) on either side, and never narrower than
    :data:`~inject.masking.mask.MIN_FWHM` times the pixelated FWHM.
    """
    lsf = model.pixel_lsf
    scale = model.pixel_scale
    charge = model.flux_per_px * lsf.lsf * scale
    above = np.flatnonzero(charge >= sb_sigma * sigma)
    reach = float(np.max(np.abs(lsf.offset_arcsec[above]))) / scale if above.size else 0.0
    fwhm = float(lsf.fwhm()) / scale
    return 2.0 * max(reach, 0.5 * MIN_FWHM * fwhm)


def fallbacks(visits):
    """The visits whose seeing or sky the plan takes from a default, for ``summary.json``.

    Returns
    -------
    dict
        ``seeing_default_arcsec`` (:data:`DEFAULT_SEEING`, the streak model's seeing
        without ``seeingFwhmEff``), ``visits_default_seeing`` and ``visits_model_sky`` (those
        without ``skyBrightness``, whose sky is the band's dark sky times the airmass), and
        ``visits_rotator_from``: how many visits took their rotator angle from each source
        (:data:`inject.survey.visits.ROTATOR_SOURCES`; a visit without one is in none).
    """
    return {"seeing_default_arcsec": DEFAULT_SEEING,
            "visits_default_seeing": sum(v.seeing_fwhm_eff is None for v in visits),
            "visits_model_sky": sum(v.sky_brightness is None for v in visits),
            "visits_rotator_from": {source: sum(v.rotator_source == source for v in visits)
                                    for source in ROTATOR_SOURCES}}


def warn_fallbacks(visits):
    """One :class:`~inject.errors.InputWarning` per default the plan takes
    (:func:`fallbacks`), naming the visits (the first five)."""
    for missing, column, instead in (
            ([v for v in visits if v.seeing_fwhm_eff is None], "seeingFwhmEff",
             f"the streak model's default seeing, {DEFAULT_SEEING:g} arcsec"),
            ([v for v in visits if v.sky_brightness is None], "skyBrightness",
             "the band's dark sky at zenith (SMTN-002) times the airmass")):
        if missing:
            ids = " ".join(str(v.observation_id) for v in missing[:5])
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            warnings.warn(f"{len(missing)} of {len(visits)} visits have no {column} "
                          f"(visits {ids}{more}): they take {instead}", InputWarning,
                          stacklevel=2)


# --- pixels ---------------------------------------------------------------------------------

def union_pixels(spans):
    """Pixels covered by a set of row runs, each pixel once.

    Parameters
    ----------
    spans : list of (rows, start, stop)
        Row indices and half-open column ranges (as
        :func:`inject.masking.geometry.rectangle_spans` returns them).

    Returns
    -------
    int
    """
    spans = [s for s in spans if len(s[0])]
    if not spans:
        return 0
    rows, start, stop = (np.concatenate([s[i] for s in spans]).astype(np.int64)
                         for i in range(3))
    new, _ = _new_pixels(rows, start, stop)
    return int(np.sum(new))


def _new_pixels(lines, start, stop, first_lines=()):
    """The pixels each row run adds to those before it on its line (runs in order of their
    start on each line), and where runs on or after each of ``first_lines`` begin in that
    order.

    Parameters
    ----------
    lines, start, stop : ndarray of int64
        Each run's line (a row of an image) and half-open column range.
    first_lines : array_like of int

    Returns
    -------
    new, where : ndarray of int64
    """
    # Lines apart by more than any column: runs of one line never touch another's.
    big = int(stop.max()) + 1
    lo = lines * big
    hi = lo + stop
    lo += start
    order = np.argsort(lo, kind="stable")  # runs come in rising rows: few, long sorted stretches
    lo, hi = lo[order], hi[order]
    where = np.searchsorted(lo, np.asarray(first_lines, np.int64) * big)
    # Each run from the furthest any run before it reached (the first from its start).
    np.maximum(lo[1:], np.maximum.accumulate(hi)[:-1], out=lo[1:])
    hi -= lo
    return np.maximum(hi, 0, out=hi), where


#: Each science CCD's shape (ny, nx) by id.
_SHAPES = np.array([c.shape for c in fp.CCDS], np.int64)
#: Rows of the tallest CCD: CCD ``i``'s row ``r`` is line ``i * _ROWS + r`` of the focal plane.
_ROWS = int(_SHAPES[:, 0].max())


def ccd_pixels(runs):
    """Pixels covered per CCD by row runs of many CCDs, each pixel once.

    Parameters
    ----------
    runs : tuple of ndarray
        ``(ccd, rows, start, stop)``: each run's CCD (id, the index in
        :data:`inject.camera.layout.CCDS`), row and half-open column range (as
        :func:`mask_spans` returns them).

    Returns
    -------
    dict
        ``{CCD name: pixels}`` of the CCDs with any, in id order.
    """
    ccd, rows, start, stop = (np.asarray(v, np.int64) for v in runs)
    if not len(ccd):
        return {}
    # The runs in order of their lines are in order of their CCDs: each CCD's sum is a
    # difference of the running sum.
    new, ends = _new_pixels(ccd * _ROWS + rows, start, stop,
                            np.arange(len(fp.CCDS) + 1) * _ROWS)
    per_ccd = np.diff(np.concatenate([[0], np.cumsum(new)])[ends])
    return {fp.CCDS[i].name: int(per_ccd[i]) for i in np.flatnonzero(per_ccd).tolist()}


def run_spans(xs_mm, ys_mm, width_px, ccd):
    """Row runs of a streak's mask on one CCD: a rectangle ``width_px`` wide along every
    segment of the polyline (focal-plane mm), extended by half the width beyond the first and
    last vertices (the end caps), pixel centres inside, clipped to the CCD.

    Returns
    -------
    list of (rows, start, stop)
        One item: the runs of all segments (a row may hold several, overlapping).
    """
    _, rows, start, stop = _track_runs(xs_mm, ys_mm, [ccd.id], [width_px])
    return [(rows, start, stop)]


def _track_runs(xs_mm, ys_mm, ccd_ids, widths_px):
    """Row runs of the mask along a polyline (mm) on several CCDs (:func:`run_spans` on each,
    every rectangle of every CCD rasterised at once).

    Parameters
    ----------
    xs_mm, ys_mm : array_like
        The polyline's vertices.
    ccd_ids : sequence of int
        The CCDs (ids).
    widths_px : sequence of float
        The mask's full width on each.

    Returns
    -------
    ccd, rows, start, stop : ndarray of int
        Each run's CCD (id), row and half-open column range.
    """
    ids = np.asarray(ccd_ids, np.int64)
    xs, ys = np.asarray(xs_mm, float), np.asarray(ys_mm, float)
    width = np.asarray(widths_px, float)[:, None]
    # Each CCD's pixel coordinates of the vertices: (len(ids), 2, len(xs)).
    pixels = np.array([fp.CCDS[i].focal_to_pixel(xs, ys) for i in ids.tolist()],
                      float).reshape(len(ids), 2, len(xs))
    px, py = pixels[:, 0], pixels[:, 1]
    ny, nx = _SHAPES[ids, 0:1], _SHAPES[ids, 1:2]
    x0, y0, x1, y1 = px[:, :-1], py[:, :-1], px[:, 1:], py[:, 1:]
    length = np.hypot(x1 - x0, y1 - y0)
    # The segments whose box comes within reach of the CCD: its pixel area grown by the width
    # (the rectangle reaches half of it from the segment, a corner of a cap 0.71 of it), so
    # that no segment with a pixel centre in its rectangle is left out. Those beyond it, kept
    # by the box, hold no pixel centre and add no run.
    near = (np.isfinite(length) & (length > 0)
            & (np.minimum(x0, x1) <= nx - 0.5 + width) & (np.maximum(x0, x1) >= -0.5 - width)
            & (np.minimum(y0, y1) <= ny - 0.5 + width) & (np.maximum(y0, y1) >= -0.5 - width))
    c, k = np.nonzero(near)
    half = 0.5 * width[c, 0]
    x0, y0, x1, y1 = x0[c, k], y0[c, k], x1[c, k], y1[c, k]
    last = len(xs) - 2
    # The end caps, extending the first and last segments by half the width.
    for i in np.flatnonzero((k == 0) | (k == last)).tolist():
        dx, dy = x1[i] - x0[i], y1[i] - y0[i]
        step = math.hypot(dx, dy)
        ux, uy = dx / step, dy / step
        if k[i] == 0:
            x0[i], y0[i] = x0[i] - half[i] * ux, y0[i] - half[i] * uy
        if k[i] == last:
            x1[i], y1[i] = x1[i] + half[i] * ux, y1[i] + half[i] * uy
    which, rows, start, stop = rectangles_spans((ny[c, 0], nx[c, 0]), x0, y0, x1, y1, half)
    return ids[c][which], rows, start, stop


_BOUNDS = fp.boxes_mm()


def crossed_ccds(xs_mm, ys_mm):
    """The CCDs a polyline (mm) crosses, with the length (mm) of the polyline on each.

    Returns
    -------
    dict
        ``{CCD: length_mm}`` in detector-id order.
    """
    xs, ys = np.asarray(xs_mm, float), np.asarray(ys_mm, float)
    near = np.flatnonzero((_BOUNDS[:, 0] <= xs.max()) & (_BOUNDS[:, 1] >= xs.min())
                          & (_BOUNDS[:, 2] <= ys.max()) & (_BOUNDS[:, 3] >= ys.min()))
    box, k, t0, t1 = clip_path_boxes(xs, ys, _BOUNDS[near])
    steps = list(map(math.hypot, np.diff(xs).tolist(), np.diff(ys).tolist()))
    mm = [(b - a) * steps[j] for j, a, b in zip(k.tolist(), t0.tolist(), t1.tolist())]
    out = {}
    ends = (np.flatnonzero(np.diff(box)) + 1).tolist()  # where the next CCD's parts begin
    for first, last in zip([0, *ends], [*ends, len(box)]):
        if last > first:  # summed in order along the path, one piece after the other
            out[fp.CCDS[near[box[first]]]] = float(sum(mm[first:last]))
    return out


def _angular_length_deg(xs_mm, ys_mm, pieces_by_ccd):
    """Sky length (deg) of a polyline's parts on CCDs: the clipped pieces' ends through the
    distortion to field angles."""
    xs, ys = np.asarray(xs_mm, float), np.asarray(ys_mm, float)
    _, k, t0, t1 = clip_path_boxes(xs, ys, _BOUNDS[[c.id for c in pieces_by_ccd]])
    ends = np.stack([t0, t1], axis=1)  # (part, 2)
    xa = xs[k, None] + ends * (xs[k + 1] - xs[k])[:, None]
    ya = ys[k, None] + ends * (ys[k + 1] - ys[k])[:, None]
    ax, ay = fp.field_angle(xa, ya)
    # Summed in order (by CCD, then along the path), each from 0.
    total = 0.0
    for dx, dy in zip((ax[:, 1] - ax[:, 0]).tolist(), (ay[:, 1] - ay[:, 0]).tolist()):
        total += math.hypot(dx, dy)
    return math.degrees(total)


# --- one visit ------------------------------------------------------------------------------

def visit_times(visit, step_s=TRACK_STEP_S):
    """Sample times (s from the visit's start) of its snaps, ``step_s`` apart within each."""
    out = []
    for start, duration in visit.snaps():
        n = max(2, int(math.ceil(duration / step_s)) + 1)
        out.append(start + np.linspace(0.0, duration, n))
    return np.concatenate(out)


def _split_snaps(run, t_s):
    """A run's vertex indices cut where consecutive vertices straddle a readout."""
    cuts = np.flatnonzero(np.diff(t_s[run]) > SNAP_BREAK_S) + 1
    return [part for part in np.split(run, cuts) if len(part) >= 2]


#: Largest step (s) between the nodes a visit's dense frame is interpolated from.
FRAME_NODE_STEP_S = 15.0


#: Visits with candidates whose frames are built together (:func:`plan_visits`): enough to
#: spread astropy's cost per call, few enough to keep their candidates and frames small.
FRAME_BATCH_VISITS = 128


def frame_nodes(ts, node_step_s=FRAME_NODE_STEP_S):
    """The times (s, as ``ts``) at which :func:`visit_frame` takes the frame from astropy: at
    least 3, at most ``node_step_s`` apart, from the first sample to the last (``ts`` itself
    when that would be as many)."""
    ts = np.asarray(ts, float)
    span = float(ts[-1] - ts[0])
    n = max(3, int(math.ceil(span / node_step_s)) + 1)
    return ts if n >= len(ts) else np.linspace(ts[0], ts[-1], n)


def visit_frame(start, ts, pointing, site=RUBIN, node_step_s=FRAME_NODE_STEP_S, at_nodes=None):
    """The :class:`~inject.orbits.passes.FieldFrame` of a visit at the times ``ts`` (s from
    ``start``), built by astropy at nodes at most ``node_step_s`` apart (:func:`frame_nodes`)
    and interpolated.

    Every quantity of the frame (the boresight's apparent direction and its East and North,
    the TEME -> ITRS rotation, the Sun, the differential aberration) turns smoothly with the
    Earth (7e-5 rad in 1 s): the polynomial through the nodes (degree = nodes - 1: 3 nodes
    for 30 s) is within 2e-5" of astropy in direction and 12 m in the Sun's position at every
    sample (tests/test_survey.py). It costs the astropy calls of 3 times instead of 301.

    ``at_nodes``, when given, is the frame at ``start + frame_nodes(ts)`` already built (many
    visits' at once by :meth:`~inject.orbits.passes.FieldFrame.build_many`, as
    :func:`plan_visits` does).
    """
    from astropy import units as u

    ts = np.asarray(ts, float)
    nodes = frame_nodes(ts, node_step_s)
    if at_nodes is None:
        at_nodes = FieldFrame.build(start + nodes * u.s, pointing, site)
    elif (at_nodes.times.shape != nodes.shape or at_nodes.pointing != pointing
          or at_nodes.site != site):
        raise InputError("at_nodes", "FieldFrame", "was built for other nodes, pointing or site")
    if len(nodes) == len(ts):  # the nodes are the samples
        return at_nodes
    coarse, n, span = at_nodes, len(nodes), float(ts[-1] - ts[0])
    # Chebyshev basis on [-1, 1]: the interpolating polynomial, well conditioned.
    x_nodes = 2.0 * (nodes - ts[0]) / span - 1.0
    x = 2.0 * (ts - ts[0]) / span - 1.0
    basis = np.polynomial.chebyshev.chebvander(x, n - 1) @ np.linalg.inv(
        np.polynomial.chebyshev.chebvander(x_nodes, n - 1))  # (len(ts), n)

    def interp(values):
        values = np.asarray(values, float)
        flat = values.reshape(n, -1)
        return (basis @ flat).reshape((len(ts),) + values.shape[1:])

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    az = np.degrees(np.unwrap(np.radians(coarse.az_deg)))
    return FieldFrame(start + ts * u.s, site, pointing, unit(interp(coarse.centre)),
                      unit(interp(coarse.east)), unit(interp(coarse.north)),
                      interp(coarse.alt_deg), interp(az) % 360.0, interp(coarse.teme_to_itrs),
                      coarse.itrs_to_altaz, interp(coarse.sun_itrs), interp(coarse.to_icrs))


def _visit_setup(visit):
    """A visit's pointing, sample times (s, :func:`visit_times`) and exposure."""
    ts = visit_times(visit)
    return (Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg), ts,
            Exposure(visit.start, float(ts[-1])))


def plan_visit(visit, constellation, site=RUBIN, prefilter=None, fixed_width_px=None,
               candidates=None, at_nodes=None):
    """The :class:`VisitPlan` of one visit.

    Parameters
    ----------
    visit : inject.survey.visits.Visit
    constellation : inject.survey.constellation.Constellation
    site : inject.orbits.passes.Site
    prefilter : inject.survey.prefilter.NightPrefilter, optional
        The night's prefilter (built for this visit alone if not given).
    fixed_width_px : float, optional
        Also count a band of this full width (px) along every crossing, as the mask is
        counted (``--mask-width``, :mod:`inject.survey.fixed_mask`).
    candidates : ndarray, optional
        The prefilter's sunlit candidates of the visit, when already asked for.
    at_nodes : inject.orbits.passes.FieldFrame, optional
        The visit's frame at its :func:`frame_nodes`, when already built (:func:`visit_frame`).

    Returns
    -------
    VisitPlan
    """
    plan = VisitPlan(visit, fixed_width_px=fixed_width_px)
    orbits = constellation.orbits
    if candidates is None:
        if prefilter is None:
            prefilter = NightPrefilter(orbits, [visit], site)
        candidates = prefilter.candidates(visit, sunlit=True)
    idx = candidates
    plan.n_candidates = int(len(idx))
    if not len(idx):
        return plan
    pointing, ts, exposure = _visit_setup(visit)
    frame = visit_frame(exposure.start, ts, pointing, site, at_nodes=at_nodes)
    i_mid = int(np.argmin(np.abs(ts - 0.5 * ts[-1])))
    plan.alt_deg = float(frame.alt_deg[i_mid])
    sigmas = {}
    for vendor in fp.SENSORS:
        sigmas[vendor], plan.sky_e_per_px = sky_sigma(visit, plan.alt_deg, vendor)
    seeing = visit.seeing_arcsec if visit.seeing_arcsec is not None else DEFAULT_SEEING
    plan.seeing_arcsec = seeing
    spec = constellation.satellite
    masks, bands, mask_counts, band_counts = [], [], [], []
    for i in idx:
        orbit = orbits[i]
        p = compute_pass(orbit, exposure, pointing, site, t_s=ts, frame=frame,
                         check_epoch=False)
        if not p.in_field:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OrbitWarning)  # no streak: said by its absence
            runs, _ = sunlit_runs("satellite.orbit", p, spec.mag, constellation.lumos,
                                  spec.ref_range)
        xd, yd = p.focal_mm()
        crossings = []
        for run, values in runs:
            for piece in _split_snaps(run, p.t_s):
                hit = crossed_ccds(xd[piece], yd[piece])
                if hit:
                    first = int(np.flatnonzero(run == piece[0])[0])
                    crossings.append((piece, values[first:first + len(piece)], hit))
        if not crossings:
            continue
        streak, widths = _streak(orbit.name, p, crossings, spec, visit, seeing, sigmas,
                                 constellation.pupil, constellation.focus_offset_um)
        pieces = [piece for piece, _, _ in crossings]
        masks.append(mask_spans(xd, yd, pieces, widths))
        mask_counts.append(ccd_pixels(masks[-1]))
        streak.pixels_lost = sum(mask_counts[-1].values())
        if fixed_width_px is not None:
            bands.append(mask_spans(xd, yd, pieces, dict.fromkeys(widths, fixed_width_px)))
            band_counts.append(ccd_pixels(bands[-1]))
            streak.pixels_fixed_mask = sum(band_counts[-1].values())
        plan.streaks.append(streak)
    plan.pixels_by_ccd = _merged(masks, mask_counts)
    plan.fixed_by_ccd = _merged(bands, band_counts)
    return plan


def mask_spans(xd, yd, pieces, widths):
    """Row runs of a streak's mask on every CCD it reaches.

    Parameters
    ----------
    xd, yd : ndarray
        The track's samples, focal-plane mm.
    pieces : list of ndarray
        Indices of the samples of each part of the track to mask (its crossings).
    widths : dict
        The mask's full width (px) by sensor vendor (``e2v``, ``ITL``).

    Returns
    -------
    ccd, rows, start, stop : ndarray of int
        Each run's CCD (id) and its row and half-open column range: a rectangle of the CCD's
        width along each part with its end caps (:func:`run_spans`), on every CCD it reaches
        (:func:`ccd_pixels` counts them).
    """
    width = np.array([widths[c.vendor] for c in fp.CCDS], float)
    # Each CCD's pixel area grown by its width, mm (and a pixel more, for rounding): the
    # CCDs beyond it from a piece's box hold none of its mask (_track_runs keeps the segments).
    reach = (width + 1.0) * fp.PIXEL_MM
    runs = []
    for piece in pieces:
        xs, ys = xd[piece], yd[piece]
        near = np.flatnonzero((_BOUNDS[:, 0] - reach <= xs.max())
                              & (_BOUNDS[:, 1] + reach >= xs.min())
                              & (_BOUNDS[:, 2] - reach <= ys.max())
                              & (_BOUNDS[:, 3] + reach >= ys.min()))
        runs.append(_track_runs(xs, ys, near, width[near]))
    if len(runs) == 1:
        return runs[0]
    if not runs:
        return tuple(np.zeros(0, np.intp) for _ in range(4))
    return tuple(np.concatenate(column) for column in zip(*runs))


def _merged(runs, counts):
    """Pixels per CCD of the union of several :func:`mask_spans`' runs (CCDs with none left
    out), given each one's :func:`ccd_pixels`.

    A CCD that only one of them reaches keeps that one's count; the runs of the CCDs that
    several reach are merged, so that their overlaps count once.
    """
    total, seen = {}, {}
    for mine in counts:
        for name, n in mine.items():
            total[name] = total.get(name, 0) + n
            seen[name] = seen.get(name, 0) + 1
    shared = [fp.ccd(name).id for name, k in seen.items() if k > 1]
    if shared:
        parts = []
        for ccd, rows, start, stop in runs:
            on = np.isin(ccd, shared)
            parts.append((ccd[on], rows[on], start[on], stop[on]))
        total.update(ccd_pixels([np.concatenate(column) for column in zip(*parts)]))
    return {name: total[name] for name in sorted(total, key=lambda name: fp.ccd(name).id)}


def _field(xd, yd, piece, n, rotator_deg=None):
    """The traced pupil's field angle and radius direction (from the direction of motion) at
    sample ``n`` of a crossing's ``piece`` of focal-plane samples (mm), and with the visit's
    ``rotator_deg`` (rotTelPos) the radius's direction in the telescope's frame."""
    j = piece[n]
    a, b = piece[max(n - 1, 0)], piece[min(n + 1, len(piece) - 1)]
    heading = math.atan2(yd[b] - yd[a], xd[b] - xd[a])
    angle = math.degrees(math.hypot(*fp.field_angle(xd[j], yd[j])))
    radius = math.atan2(yd[j], xd[j])
    field = {"field_angle_deg": min(angle, FIELD_MAX_DEG),
             "field_position_angle_deg": math.degrees(radius - heading)}
    if rotator_deg is not None:
        field["telescope_position_angle_deg"] = telescope_position_angle(
            rotator_deg, math.degrees(radius))
    return field


def _streak(name, p, crossings, spec, visit, seeing, sigmas, pupil="annulus",
            focus_offset_um=0.0):
    """A :class:`Streak` from its crossing parts (the model at the middle of the samples on
    the CCDs crossed, with the constellation's ``pupil`` and ``focus_offset_um``) and its mask
    width (px) on each sensor type."""
    inside = []
    lengths = {}
    xd, yd = p.focal_mm()
    total_deg = 0.0
    for piece, values, hit in crossings:
        xs, ys = xd[piece], yd[piece]
        total_deg += _angular_length_deg(xs, ys, hit)
        for ccd, mm in hit.items():
            lengths[ccd] = lengths.get(ccd, 0.0) + mm
        for n in np.flatnonzero(_inside(hit, xs, ys)).tolist():
            inside.append((piece, values, n))
    if not inside:  # crosses only between vertices: take the vertex before the first crossing
        piece, values, _ = crossings[0]
        inside = [(piece, values, 0)]
    piece, values, n = inside[len(inside) // 2]
    v = values[n]
    j = piece[n]
    model = StreakModel(height_km=v["height"], zenith_deg=v["zenith"], phi_deg=v["phi"],
                        shape=spec.shape, mag=v["mag"], band_name=visit.band,
                        seeing=Seeing(seeing), telescope=LSST, ref_range_km=spec.ref_range,
                        range_km=v["range"], angular_speed_rad_s=v["angular_speed"],
                        pupil=pupil, focus_offset_um=focus_offset_um,
                        sed_temperature_k=spec.sed_temperature_k,
                        **(_field(xd, yd, piece, n, visit.rotator_deg)
                           if pupil != "annulus" else {}))
    widths = {vendor: mask_width_px(model, sigma) for vendor, sigma in sigmas.items()}
    total_mm = sum(lengths.values())
    mean_width = sum(widths[c.vendor] * mm for c, mm in lengths.items()) / total_mm \
        if total_mm > 0 else widths["e2v"]
    lit = np.concatenate([piece for piece, _, _ in crossings])
    streak = Streak(
        satellite=name, ccds=tuple(c.name for c in sorted(lengths, key=lambda c: c.id)),
        length_deg=total_deg, mag=float(model.apparent_mag), fwhm_arcsec=model.fwhm_arcsec,
        peak_e_per_px=model.peak_e_per_px, mask_width_px=float(mean_width),
        t_mid_s=float(p.t_s[j]), alt_deg=float(p.alt_deg[j]), range_km=float(p.range_km[j]),
        height_km=float(p.height_km[j]),
        angular_speed_deg_s=float(np.degrees(p.angular_speed_rad_s[j])),
        sun_fraction_min=float(p.sun_fraction[lit].min()), sunlit_parts=len(crossings))
    return streak, widths


def _inside(ccds, xs, ys):
    """Whether each point (mm) lies on one of the CCDs' pixel areas (edges included)."""
    b = _BOUNDS[[c.id for c in ccds]][:, :, None]
    return np.any((b[:, 0] <= xs) & (xs <= b[:, 1]) & (b[:, 2] <= ys) & (ys <= b[:, 3]),
                  axis=0)


# --- many visits ----------------------------------------------------------------------------

def plan_visits(visits, constellation, site=RUBIN, progress=None, fixed_width_px=None):
    """:func:`plan_visit` for each visit, in order (``progress()`` called after each), with
    one :class:`~inject.survey.prefilter.NightPrefilter` for them all (and
    ``fixed_width_px`` as :func:`plan_visit` takes it).

    The visits go in batches: the prefilter's candidates of each visit until
    :data:`FRAME_BATCH_VISITS` of them have some, those visits' frames at their nodes in one
    :meth:`~inject.orbits.passes.FieldFrame.build_many` (the same numbers as one visit's at
    a time, for a fraction of astropy's cost), then each visit's passes.
    """
    out = []
    prefilter = NightPrefilter(constellation.orbits, visits, site) if len(visits) else None

    def plan_batch(batch):
        frames = iter(_frames_at_nodes([visit for visit, idx in batch if len(idx)], site))
        for visit, idx in batch:
            out.append(plan_visit(visit, constellation, site, prefilter, fixed_width_px,
                                  candidates=idx, at_nodes=next(frames) if len(idx) else None))
            if progress is not None:
                progress()

    batch, n_framed = [], 0
    for visit in visits:
        idx = prefilter.candidates(visit, sunlit=True)
        batch.append((visit, idx))
        n_framed += bool(len(idx))
        if n_framed == FRAME_BATCH_VISITS:
            plan_batch(batch)
            batch, n_framed = [], 0
    plan_batch(batch)
    return out


def _frames_at_nodes(visits, site):
    """The visits' frames at their :func:`frame_nodes`, from astropy in one go."""
    from astropy import units as u

    times, pointings = [], []
    for visit in visits:
        pointing, ts, exposure = _visit_setup(visit)
        times.append(exposure.start + frame_nodes(ts) * u.s)
        pointings.append(pointing)
    return FieldFrame.build_many(times, pointings, site)
