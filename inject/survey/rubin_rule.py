"""The literature's rule: ``inject survey --rule rubin_sim``.

The studies of constellations against LSST (Hu et al. 2022; Yoachim 2023, SMTN-018; Kandula
et al. 2025) counted streaks with rubin_sim's ``Constellation.check_pointings``. This module
counts them the same way, per visit, so that inject's numbers can be put beside theirs:

* Time. The visit starts at ``observationStartMJD`` *read as UT1*, as rubin_sim reads it,
  although opsim writes TAI: the satellites are placed as they are ~37 s (TAI - UT1) after
  the visit's real start, 280 km along a 550 km orbit. This is only to reproduce the
  literature; inject's own rule (``--rule inject``) reads TAI.
* Span. The visit lasts ``visitTime`` when the visits file has that column (opsim's: the
  snaps, their readouts and shutter motions), else the exposure time plus the readouts between
  snaps (:func:`visit_span`); the rule has no readout gap: the track is one line.
* Samples. ``round(span / 2 s)`` times evenly from the start to the end, both included
  (rubin_sim's ``np.linspace(mjd, mjd + span, round(span / dt))``).
* Positions. Geometric: the SGP4 position minus the site's, in the GCRS, no light time and
  no aberration (skyfield's ``(satellite - site).at(t)``), compared with the boresight's ICRS
  RA and Dec as given.
* A satellite counts when it is sunlit at the start or at the end (:func:`sunlit`: the line
  from it to the Sun's centre clears a sphere of skyfield's Earth radius; the Sun geometric),
  above 20 deg (geodetic altitude, no refraction) at the start or at the end (either may hold
  at either end), its start and end are within 10 deg of the boresight's arc (rubin_sim's
  coarse test, :func:`arc_distance`), and its sampled track, a polyline in the gnomonic plane
  about the boresight, has a length > 0 inside the circle of radius 1.75 deg in that plane
  (:func:`length_in_circle`; rubin_sim draws the circle as a 64-sided polygon, whose edges
  come 0.002 deg inside the circle).
* Its length is the polyline's inside the circle (deg of the gnomonic plane); there are no
  CCDs, no gaps and no corners beyond 1.75 deg.
* Pixels lost: the circle's pixels (0.2" squares of the gnomonic plane, centres inside the
  circle) whose centres lie within half a fixed width of the track: a rectangle along every
  segment of the sampled track and half a width beyond its first and last samples, as
  :func:`inject.survey.plan.run_spans` draws a mask, merged over the visit's streaks
  (:func:`band_spans`). The width is ``--mask-width``, 300 px (60") by default
  (:data:`DEFAULT_WIDTH_PX`), the width the studies masked.

The positions come from inject's SGP4 and astropy's frames; rubin_sim's come from skyfield.
Two differences remain. skyfield's UT1 (its own tables) is 0.028 s off astropy's on the
sample night of 2026, in which a satellite near the zenith moves 0.02 deg; and rubin_sim's
skyfield has no polar motion (the site 10 m off, 3" at 600 km), which astropy includes. A
crossing that grazes the polygon, or a satellite at the shadow's or the altitude's edge at
the start or end, can fall on different sides in the two codes (docs/guides/survey.md,
"Against rubin_sim").
"""
import math
import warnings
from dataclasses import replace

import numpy as np

from inject.masking.geometry import Line, rectangle_spans
from inject.orbits.passes import RUBIN, altaz_basis, propagate_teme
from inject.survey.visits import READOUT_S
from inject.trajectory import clip_path

#: The rule's names (``--rule``).
RULES = ("inject", "rubin_sim")
#: rubin_sim's circle: radius in the gnomonic plane (deg as radians of that plane).
RADIUS_DEG = 1.75
#: rubin_sim's altitude limit, deg.
ALT_LIMIT_DEG = 20.0
#: rubin_sim's time step, s.
STEP_S = 2.0
#: rubin_sim's coarse test: the start-to-end arc within this of the boresight, deg.
TEST_RADIUS_DEG = 10.0
#: skyfield's Earth radius (``skyfield.constants.ERAD``), km: the sphere of its shadow test.
SKYFIELD_EARTH_RADIUS_KM = 6378.1366
#: The fixed mask's width when ``--mask-width`` is not given, px (60" at 0.2"/px).
DEFAULT_WIDTH_PX = 300.0
#: The plane's pixel, arcsec (LSSTCam's nominal plate scale).
PIXEL_ARCSEC = 0.2


def visit_span(visit):
    """The rule's span of a visit (s) and where it came from.

    Returns
    -------
    seconds : float
        ``visitTime`` if the visit has it, else ``visitExposureTime + (numExposures - 1) *``
        :data:`~inject.survey.visits.READOUT_S`.
    source : str
        ``"visitTime"`` or ``"exposure+readouts"``.
    """
    if visit.visit_time_s is not None:
        return float(visit.visit_time_s), "visitTime"
    return float(visit.exptime_s + READOUT_S * (visit.n_exposures - 1)), "exposure+readouts"


def sample_times(span_s, step_s=STEP_S):
    """rubin_sim's samples of a span: ``round(span / step)`` times from 0 to ``span`` (the
    ratio taken in days, as rubin_sim takes it, so that a half rounds the same way)."""
    n = int(np.round((span_s / 3600.0 / 24.0) / (step_s / 3600.0 / 24.0)))
    return np.linspace(0.0, span_s, max(n, 2))


def ut1_start(mjd):
    """The instant ``observationStartMJD`` names when read as UT1 (an astropy Time, TAI)."""
    from astropy.time import Time

    return Time(mjd, format="mjd", scale="ut1").tai


def sunlit(r_sat_km, r_sun_km, radius_km=SKYFIELD_EARTH_RADIUS_KM):
    """skyfield's shadow test: the half-line from the satellite towards the Sun's centre
    misses the sphere of ``radius_km`` about the Earth's centre, or meets it only behind the
    satellite.

    Parameters
    ----------
    r_sat_km, r_sun_km : array_like, shape (..., 3)
        Geocentric positions, km, in the same frame.

    Returns
    -------
    ndarray of bool
    """
    r = np.asarray(r_sat_km, float)
    to_sun = np.asarray(r_sun_km, float) - r
    u = to_sun / np.linalg.norm(to_sun, axis=-1, keepdims=True)
    # |r + s u|^2 = R^2: s^2 + 2 (r.u) s + |r|^2 - R^2 = 0; the far root's sign decides.
    b = np.sum(r * u, axis=-1)
    disc = b * b - (np.sum(r * r, axis=-1) - radius_km ** 2)
    far = -b + np.sqrt(np.where(disc >= 0, disc, 0.0))
    return (disc < 0) | (far <= 0)


def gnomonic(d, ra_deg, dec_deg):
    """Gnomonic coordinates (radians of the plane) of directions ``d`` (..., 3) about the
    boresight, as rubin_sim's ``gnomonic_project_toxy``: x towards increasing RA, y towards
    the North; NaN where a direction is not in front."""
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    b = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    e = np.array([-math.sin(ra), math.cos(ra), 0.0])
    n = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    d = np.asarray(d, float)
    z = d @ b
    z = np.where(z > 0, z, np.nan)
    return (d @ e) / z, (d @ n) / z


def length_in_circle(x, y, radius):
    """Length of the polyline ``(x, y)`` inside the circle of ``radius`` about the origin
    (segments with a NaN end left out)."""
    x0, y0, x1, y1 = x[:-1], y[:-1], x[1:], y[1:]
    dx, dy = x1 - x0, y1 - y0
    a = dx * dx + dy * dy
    b = x0 * dx + y0 * dy
    c = x0 * x0 + y0 * y0 - radius * radius
    disc = b * b - a * c
    ok = np.isfinite(disc) & (disc > 0) & (a > 0)
    root = np.sqrt(np.where(ok, disc, 0.0))
    safe = np.where(ok, a, 1.0)
    t0 = np.clip((-b - root) / safe, 0.0, 1.0)
    t1 = np.clip((-b + root) / safe, 0.0, 1.0)
    return float(np.sum(np.where(ok, (t1 - t0) * np.sqrt(a), 0.0)))


#: Sides of the polygon rubin_sim takes for its circle (shapely's ``Point.buffer``, 16
#: segments a quarter circle, a vertex at angle 0).
POLYGON_SIDES = 64


def length_in_polygon(x, y, radius, sides=POLYGON_SIDES):
    """Length of the polyline ``(x, y)`` inside the regular polygon of ``sides`` vertices on
    the circle of ``radius``, one at angle 0: rubin_sim's circle (``Point(0, 0).buffer(r)``
    and ``intersection(LineString).length``). Its edges are ``radius cos(pi / sides)`` from
    the centre (0.0021 deg inside the 1.75 deg circle at their middles)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    x0, y0, dx, dy = x[:-1], y[:-1], np.diff(x), np.diff(y)
    angle = (np.arange(sides) + 0.5) * 2.0 * math.pi / sides
    nx, ny = np.cos(angle)[None], np.sin(angle)[None]
    c = radius * math.cos(math.pi / sides)
    num = c - (x0[:, None] * nx + y0[:, None] * ny)  # >= 0 where the start is inside edge j
    den = dx[:, None] * nx + dy[:, None] * ny
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    lo = np.max(np.where(den < 0, t, 0.0), axis=1, initial=0.0)
    hi = np.min(np.where(den > 0, t, 1.0), axis=1, initial=1.0)
    parallel_out = np.any((den == 0) & (num < 0), axis=1)
    ok = np.isfinite(x0) & np.isfinite(y0) & np.isfinite(dx) & np.isfinite(dy) & ~parallel_out
    seg = np.where(ok, np.clip(hi - lo, 0.0, None), 0.0) * np.hypot(dx, dy)
    return float(np.nansum(seg))


def arc_distance(a, b, p):
    """Angle (rad) from the unit vector ``p`` to the great-circle arc from ``a`` to ``b``."""
    n = np.cross(a, b)
    norm = np.linalg.norm(n)
    ends = min(math.acos(np.clip(p @ a, -1, 1)), math.acos(np.clip(p @ b, -1, 1)))
    if norm == 0:
        return ends
    n = n / norm
    q = p - (p @ n) * n  # p's foot on the great circle
    if np.linalg.norm(q) == 0:
        return ends
    q = q / np.linalg.norm(q)
    if np.cross(a, q) @ n >= 0 and np.cross(q, b) @ n >= 0:  # the foot lies on the arc
        return math.asin(min(abs(p @ n), 1.0))
    return ends


class Disc:
    """The circle's pixels: a square grid of :data:`PIXEL_ARCSEC` pixels of the gnomonic
    plane about the boresight, with :func:`inject.survey.plan.run_spans`'s ``shape`` and
    ``focal_to_pixel`` (here from the plane's radians)."""

    def __init__(self, radius=math.radians(RADIUS_DEG), pixel_arcsec=PIXEL_ARCSEC):
        self.pixel_rad = math.radians(pixel_arcsec / 3600.0)
        self.r_px = radius / self.pixel_rad
        self.half = int(math.ceil(self.r_px))
        self.shape = (2 * self.half + 1, 2 * self.half + 1)
        self.name = "circle"

    def focal_to_pixel(self, x, y):
        return x / self.pixel_rad + self.half, y / self.pixel_rad + self.half

    def clip(self, spans):
        """Row runs clipped to the pixels whose centres are inside the circle."""
        out = []
        for rows, start, stop in spans:
            dy = rows - self.half
            w = np.sqrt(np.maximum(self.r_px ** 2 - dy.astype(float) ** 2, 0.0))
            lo = np.ceil(self.half - w).astype(np.int64)
            hi = np.floor(self.half + w).astype(np.int64) + 1
            inside = np.abs(dy) <= self.r_px
            s, e = np.maximum(start, lo), np.minimum(stop, hi)
            keep = inside & (e > s)
            out.append((rows[keep], s[keep], e[keep]))
        return out

    def area(self):
        """Pixels of the circle (centres inside)."""
        dy = np.arange(-self.half, self.half + 1, dtype=float)
        w = np.sqrt(np.maximum(self.r_px ** 2 - dy ** 2, 0.0))
        ok = np.abs(dy) <= self.r_px
        return int(np.sum((np.floor(w) - np.ceil(-w) + 1)[ok]))


def band_spans(x, y, width_px, disc):
    """Row runs of a band ``width_px`` wide along the polyline ``(x, y)`` (the plane's
    radians) on the :class:`Disc`: a rectangle along each segment near the circle, half a
    width beyond the first and last samples, clipped to the circle."""
    px, py = disc.focal_to_pixel(np.asarray(x, float), np.asarray(y, float))
    good = np.isfinite(px) & np.isfinite(py)
    half = 0.5 * width_px
    ny, nx = disc.shape
    out = []
    n = len(px)
    for k in sorted({p[0] for p in clip_path(np.where(good, px, 1e12), np.where(good, py, 1e12),
                                             (-width_px, nx + width_px,
                                              -width_px, ny + width_px))}):
        if not (good[k] and good[k + 1]):
            continue
        x0, y0, x1, y1 = px[k], py[k], px[k + 1], py[k + 1]
        length = math.hypot(x1 - x0, y1 - y0)
        if length == 0:
            continue
        ux, uy = (x1 - x0) / length, (y1 - y0) / length
        if k == 0:
            x0, y0 = x0 - half * ux, y0 - half * uy
        if k == n - 2:
            x1, y1 = x1 + half * ux, y1 + half * uy
        out.append(rectangle_spans(disc.shape, Line(x0, y0, x1, y1), half))
    return disc.clip(out)


def _rotations(frame, times):
    """Matrices (n, 3, 3) taking vectors of ``frame`` (TEME or ITRS) at ``times`` to the
    GCRS (geocentric: astropy's chain of rotations, no aberration)."""
    from astropy import units as u
    from astropy.coordinates import GCRS, CartesianRepresentation, SkyCoord

    n = len(times)
    eye = np.repeat(np.eye(3)[:, :, None], n, axis=2)  # (component, basis vector, time)
    rep = CartesianRepresentation(eye * u.km)
    out = SkyCoord(rep, frame=frame(obstime=times)).transform_to(GCRS(obstime=times))
    m = out.cartesian.xyz.to_value(u.km)  # (component, basis vector, time)
    return np.moveaxis(m, 2, 0)


def _sun_gcrs(times):
    """The Sun's geometric geocentric position (km, (n, 3)), ICRS axes."""
    from astropy import units as u
    from astropy.coordinates import get_body_barycentric

    sun = get_body_barycentric("sun", times) - get_body_barycentric("earth", times)
    return sun.xyz.to_value(u.km).T


def rule_visits(visits):
    """Stand-ins of ``visits`` for :class:`~inject.survey.prefilter.NightPrefilter`: one snap
    over the rule's span, starting at the rule's (UT1-read) instant."""
    from astropy.time import Time

    if not visits:
        return ()
    starts = Time([v.mjd_tai for v in visits], format="mjd", scale="ut1").tai.mjd
    return tuple(replace(v, mjd_tai=float(s), exptime_s=visit_span(v)[0], n_exposures=1)
                 for v, s in zip(visits, np.atleast_1d(starts)))


def tracks(visit, orbits, site=RUBIN):
    """The rule's samples of ``orbits`` over ``visit``.

    Returns
    -------
    dict
        ``t_s`` (s from the rule's start, (t,)); per orbit and sample: ``d`` (unit
        directions from the site, GCRS, (n, t, 3)), ``alt_deg``, ``range_km``; at the start
        and end: ``r_km`` (geocentric GCRS, (n, 2, 3)), ``sun_km`` ((2, 3)) and ``sunlit``
        ((n, 2)).
    """
    from astropy import units as u
    from astropy.coordinates import ITRS, TEME

    span, _ = visit_span(visit)
    ts = sample_times(span)
    times = ut1_start(visit.mjd_tai) + ts * u.s
    r_teme, _ = propagate_teme(list(orbits), times)  # (n, t, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # beyond the IERS table: said once by the plan
        to_gcrs = _rotations(TEME, times)
        itrs_gcrs = _rotations(ITRS, times)
        sun = _sun_gcrs(times[[0, -1]])
    r = np.einsum("tij,ntj->nti", to_gcrs, r_teme)
    _, _, up = altaz_basis(site)
    topo = r - (itrs_gcrs @ site.itrs_km)[None]
    dist = np.linalg.norm(topo, axis=-1)
    d = topo / dist[..., None]
    alt = np.degrees(np.arcsin(np.clip(np.einsum("nti,ti->nt", d, itrs_gcrs @ up), -1, 1)))
    ends = [0, len(ts) - 1]
    return {"t_s": ts, "d": d, "alt_deg": alt, "range_km": dist, "r_km": r[:, ends],
            "sun_km": sun, "sunlit": sunlit(r[:, ends], sun[None])}


def count_visit(visit, orbits, candidates, site=RUBIN):
    """The satellites of ``orbits`` (indices ``candidates``) the rule counts in ``visit``.

    Returns
    -------
    list of dict
        Per satellite counted: ``index``, ``length_deg``, the track's plane coordinates
        ``x``, ``y`` (radians), ``t_s`` (from the rule's start), ``alt_deg`` and
        ``range_km`` (at each sample), ``sunlit`` (start, end), ``closest_deg`` (the sampled
        track's closest to the boresight).
    """
    if not len(candidates):
        return []
    got = tracks(visit, [orbits[i] for i in candidates], site)
    ts, d, alt, lit = got["t_s"], got["d"], got["alt_deg"], got["sunlit"]
    ra, dec = math.radians(visit.ra_deg), math.radians(visit.dec_deg)
    p = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    radius = math.radians(RADIUS_DEG)
    out = []
    for k, i in enumerate(candidates):
        if not ((alt[k, [0, -1]] > ALT_LIMIT_DEG).any() and lit[k].any()):
            continue
        if arc_distance(d[k, 0], d[k, -1], p) >= math.radians(TEST_RADIUS_DEG):
            continue
        x, y = gnomonic(d[k], visit.ra_deg, visit.dec_deg)
        length = length_in_polygon(x, y, radius)
        if length > 0:
            out.append({"index": int(i), "length_deg": math.degrees(length), "x": x, "y": y,
                        "t_s": ts, "alt_deg": alt[k], "sunlit": lit[k],
                        "range_km": got["range_km"][k], "closest_deg": math.degrees(
                            float(np.nanmin(np.hypot(x, y))))})
    return out


def plan_visit(visit, constellation, prefilter, width_px=DEFAULT_WIDTH_PX, site=RUBIN,
               disc=None):
    """The :class:`~inject.survey.plan.VisitPlan` of one visit by the rule.

    Parameters
    ----------
    visit : inject.survey.visits.Visit
    constellation : inject.survey.constellation.Constellation
    prefilter : inject.survey.prefilter.NightPrefilter
        Built on :func:`rule_visits` of the night with ``field_radius_deg`` =
        :data:`RADIUS_DEG`.
    width_px : float
        The fixed mask's full width, px.

    Returns
    -------
    VisitPlan
        One :class:`~inject.survey.plan.Streak` (``rule="rubin_sim"``, no CCDs, no model:
        magnitude, FWHM and peak NaN) per satellite counted, its ``length_deg`` inside the
        circle and ``pixels_lost`` its band's; the visit's ``pixels_by_ccd`` is
        ``{"circle": pixels}`` of the bands merged.
    """
    from inject.survey.plan import Streak, VisitPlan, union_pixels

    disc = disc or Disc()
    plan = VisitPlan(visit)
    stand_in = prefilter_visit(prefilter, visit)
    idx = prefilter.candidates(stand_in, sunlit=True)
    plan.n_candidates = int(len(idx))
    spans = []
    for hit in count_visit(visit, constellation.orbits, idx, site):
        x, y, ts = hit["x"], hit["y"], hit["t_s"]
        inside = np.flatnonzero(np.hypot(x, y) <= math.radians(RADIUS_DEG))
        j = int(inside[len(inside) // 2]) if len(inside) else int(np.nanargmin(np.hypot(x, y)))
        a, b = max(j - 1, 0), min(j + 1, len(ts) - 1)
        speed = math.degrees(math.hypot(x[b] - x[a], y[b] - y[a]) / (ts[b] - ts[a]))
        mine = band_spans(x, y, width_px, disc)
        spans.extend(mine)
        plan.streaks.append(Streak(
            satellite=constellation.orbits[hit["index"]].name, ccds=(),
            length_deg=hit["length_deg"], mag=math.nan, fwhm_arcsec=math.nan,
            peak_e_per_px=math.nan, mask_width_px=float(width_px),
            pixels_lost=union_pixels(mine), t_mid_s=float(ts[j]),
            alt_deg=float(hit["alt_deg"][j]), range_km=float(hit["range_km"][j]),
            angular_speed_deg_s=speed, rule="rubin_sim"))
    n = union_pixels(spans)
    plan.pixels_by_ccd = {"circle": n} if n else {}
    return plan


def prefilter_visit(prefilter, visit):
    """The stand-in of ``visit`` that ``prefilter`` was built on (:func:`rule_visits`)."""
    return prefilter.stand_ins[visit.observation_id]


def night_prefilter(orbits, visits, site=RUBIN):
    """A :class:`~inject.survey.prefilter.NightPrefilter` of the rule's stand-ins of
    ``visits`` (the circle's radius and the prefilter's margin), with ``stand_ins`` by
    observationId."""
    from inject.survey.prefilter import NightPrefilter

    stand_ins = rule_visits(visits)
    prefilter = NightPrefilter(orbits, stand_ins, site, field_radius_deg=RADIUS_DEG)
    prefilter.stand_ins = {v.observation_id: v for v in stand_ins}
    return prefilter


def plan_visits(visits, constellation, site=RUBIN, progress=None,
                width_px=DEFAULT_WIDTH_PX):
    """:func:`plan_visit` for each visit, in order, one prefilter for them all."""
    out = []
    if not len(visits):
        return out
    prefilter = night_prefilter(constellation.orbits, visits, site)
    disc = Disc()
    for visit in visits:
        out.append(plan_visit(visit, constellation, prefilter, width_px, site, disc))
        if progress is not None:
            progress()
    return out
