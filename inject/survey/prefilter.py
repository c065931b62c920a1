"""The survey's prefilter: which satellites may cross a visit's field, for a night of visits.

:func:`inject.orbits.passes.crossing_candidates` propagates every satellite at seven times of
each exposure and builds an astropy frame for it. Over a night of visits most of that work is
shared: :class:`NightPrefilter` interpolates the constellation between *nodes* of a time grid
(:data:`NODE_STEP_S` apart, SGP4 positions and velocities, cubic Hermite between, kept while
visits need them; only the satellites that may come near a visit are propagated there: see
below), and computes the site's direction in TEME for all the visits in one astropy call,
every boresight's and the Sun's at a few times of the night (below). A visit then costs an
interpolation and dot products:

1. At the visit's middle, a satellite is kept only if it lies within the distance it can
   travel during half the visit (its speed plus the site's) of the cone of half-angle
   ``field_radius_deg + margin`` about the boresight (a test on the line of sight only), and
   no farther than that behind the observer along the line of sight (a candidate has a
   sample in front of the observer, and the satellite and the site move by less than that
   reach between it and the middle).
2. The survivors at :data:`COARSE_STEP_S` steps through the visit: their gnomonic offsets
   from the boresight, and a candidate is one whose chord between two samples (both in front
   of the observer) comes within ``field_radius_deg + margin`` of it, as
   :func:`~inject.orbits.passes.crossing_candidates` tests, or one sample does.

The margin (:func:`prefilter_margin_deg`) covers what this leaves out of the exact pass, each
bounded by the lowest perigee of the constellation (the nearest a satellite can be seen from):

* the Hermite interpolation between nodes, whose position error is at most
  ``step^4 / 384 max|r''''|``, with ``|r''''| = n^4 a`` on a circular orbit (mean motion n;
  5% more for the Earth's flattening): 0.26 km at 350 km with 300 s nodes, 0.04 deg seen
  from 350 km;
* the chord between coarse samples: gnomonic projection keeps straight 3-D lines straight, so
  the track only leaves the chord by the bending of the relative motion, the satellite's
  gravity, ``g dt^2 / 8`` = 0.03 km for 5 s (0.005 deg);
* the light time (the track moves by v / c = 5", whatever the range), the stars' aberration
  (20.5" annual, 0.3" diurnal) and the polar motion (the site is 10 m off): 0.008 deg;
* the boresights' directions, astropy's at times at most :data:`DIRECTION_STEP_S` (12 h)
  apart and linear between (normalised): the direction of a fixed star in TEME bends only
  with the nutation and the annual aberration, ``sum A w^2`` below 0.1"/day^2, so the
  chord is within ``(0.5 day)^2 / 8 * 0.1"`` = 0.003" of it (measured 0.001"); 0.01"
  (:data:`DIRECTION_ERROR_DEG`) is added. The Sun's direction is interpolated the same way
  (within 0.011": the Earth's lunar wobble; 0.5 m at 10,000 km, inside the umbra's slack).

These add to 0.05 deg at 350 km; the margin is twice the sum, floored at 0.05 deg. A test
checks on hundreds of satellites that no satellite whose exact pass enters the field is left
out.

With ``sunlit=True`` a candidate must also leave the Earth's umbra at some time of the visit:
a satellite that stays, at every coarse sample, inside the umbra of the sphere of the
Earth's polar radius (inside the ellipsoid's umbra: no part of the Sun is seen past it),
shrunk by :data:`UMBRA_SLACK_KM`, stays in the umbra between them too (the umbra is a convex
cone and the track leaves its chord by 0.03 km), so no sunlit part of its track is lost.

**Which satellites are propagated at the nodes.** Test 2 works on test 1's survivors, and
test 1 on a shortlist that provably holds every satellite test 1 keeps, so the candidates are
those of all satellites at every node. Every satellite is propagated only on a *coarse* grid,
every :data:`COARSE_NODES` nodes (and at the first and last node the visits need); the cubic
Hermite between two coarse nodes ``h_c`` apart is within ``E_c = h_c^4 / 384 max|r''''|`` of
SGP4. Per satellite, ``max|r''''|`` is taken as ``2 * 1.05 (1 + e) w^4 r_p``, with ``w =
sqrt(mu (1 + e) / r_p^3)`` the angular rate at perigee of the osculating orbits at the two
coarse nodes (the lower perigee ``r_p`` less :data:`PERIGEE_DROP_KM`, the larger
eccentricity ``e`` plus :data:`ECCENTRICITY_RISE`, for their change between the nodes): a
Kepler orbit's ``max|r''''|`` is at most ``(1 + e) w^4 r_p`` (measured, over ``w^4 r_p``:
1.0097 at e = 0.01, 1.074 at 0.1, 1.125 at 0.3, 1.07 at 0.7), 1.05 for the Earth's
flattening as above, and twice that. ``E_c`` is 680 km at 350 km with 1800 s coarse steps
(it grows as ``h_c^4``: 42 km at 900 s); the same formula with the node step bounds the
nodes' interpolation, ``E_f`` = 0.5 km. The satellite's speed is at most ``v_max = 1.01
sqrt(mu (1 + e) / r_p)`` (vis-viva at perigee, 1% for the flattening) and the nodes'
interpolated velocity is within ``sqrt(3) / 216 h^3 max|r''''|`` (0.005 km/s) of SGP4's.
The shortlists take the largest of these bounds over the satellites; one without them (no
ellipse for its osculating orbit) is on every shortlist.

Test 1 keeps a satellite when ``g(r) = d - z tan(a) <= (reach + 0.1) / cos(a)``, ``d`` and
``z`` the distances of its interpolated position ``r`` from the line of sight and along it,
``a`` the cone's half-angle. ``g``'s gradient is a unit vector square to the line of sight
less ``tan(a)`` times one along it, so ``g`` changes by at most ``|dr| / cos(a)`` when ``r``
moves by ``|dr|``: at any point within ``D`` of ``r``, a satellite test 1 keeps has ``g <=
(reach + 0.1 + D) / cos(a)``, and its reach is at most ``(1.02 (v_max + 0.005) + 0.47)
T / 2`` for a visit ``T`` long. Test 1 also keeps only ``z >= -(reach + 0.1)``, so ``z >=
-(reach + 0.1 + D)`` there. The shortlist is three tests with these bounds:

0. Once per node interval, for all its visits together (visits are assigned to the interval
   of their middle ``t``), a half-space ``r . n >= level`` holding every point with ``d <=
   z tan(a) + far`` and ``z >= -back`` about each visit's line of sight, ``back = reach +
   0.1 + D`` and ``far = back / cos(a)`` with test a's ``D``: such a point is ``apex + z b +
   w``, ``|w| <= z tan(a) + far``, so with ``c = b . n`` and ``s = sqrt(1 - c^2)`` (``c >=
   s tan(a)``, the aim within ``90 deg - a`` of ``n``) ``(r - apex) . n >= -back (c - s
   tan(a)) - far s``; ``level`` is the least of these over the visits, for the best of three
   normals (the mean aim, the zenith, their bisector; none if none fits: every satellite).
   One product of every satellite's coarse states with a vector; it keeps about a fifth of
   Starlink on a June night (14% to 21% an interval).
a. For those, their coarse interpolation at ``t_c``, halfway between the first and last
   middles of the interval's visits, and per visit the cone test on these positions (two
   products with vectors), ``D = E_c + E_f + v_max |t - t_c|``: SGP4 at ``t_c`` is within
   ``E_c`` of the coarse interpolation and within ``v_max |t - t_c|`` of SGP4 at ``t``, which
   is within ``E_f`` of test 1's position.
b. For those, the coarse interpolation at ``t``, ``D = E_c + E_f``.

All three add :data:`ROUNDING_KM`. A satellite is propagated at a node when a visit that
needs the node shortlists it (about 220 a visit of Starlink's 29,988 on a June night), once a
night; the visits of a node interval are done together: their shortlists propagated at the
nodes about their middles in one SGP4 call a node, tests 1 and 2 interpolated in one call
each. An SGP4 error at a coarse node stops the prefilter, as one at a node did when every
satellite was propagated at every node.
"""
import math

import numpy as np

from inject.errors import OrbitError
from inject.orbits.passes import (
    EARTH_ROTATION_RAD_S,
    FIELD_RADIUS_DEG,
    RUBIN,
    segment_distances,
)

#: Seconds between two nodes of the night's grid.
NODE_STEP_S = 300.0
#: Largest step (s) between the coarse samples of a visit.
COARSE_STEP_S = 5.0
#: Earth's gravitational parameter (WGS72, SGP4's), km^3/s^2, and its equatorial radius, km.
MU_KM3_S2 = 398600.8
R_EQ_KM = 6378.135
#: The largest speed of a site on the Earth's surface in an inertial frame, km/s.
SITE_SPEED_KM_S = 0.47
#: Longest step (s) between the times of the night where astropy gives the Sun's and the
#: boresights' directions in TEME (linear between: module notes).
DIRECTION_STEP_S = 12 * 3600.0
#: Bound on that interpolation's error, deg (module notes).
DIRECTION_ERROR_DEG = 0.01 / 3600.0
#: Angles the prefilter leaves out (light time 5.3", aberration 20.8", polar motion 0.3" at the
#: ground seen from the satellite) and the boresights' interpolation, deg.
FIXED_ERRORS_DEG = (5.3 + 20.8 + 2.0) / 3600.0 + DIRECTION_ERROR_DEG
#: The circular orbit's bound raised for the Earth's flattening and SGP4's short-period terms
#: (measured 1.008 at 350 km).
INTERP_SLACK = 1.05
#: The Earth's polar radius (WGS84), km: the sphere inside the ellipsoid, whose umbra lies
#: inside the ellipsoid's.
R_POLAR_KM = 6356.752
#: The umbra's narrowing per km behind the Earth, (R_sun - R_polar) / (Sun's distance) at
#: perihelion (0.00454 at aphelion).
UMBRA_TAPER = 0.0047
#: Slack of the umbra test, km: the interpolation (0.26), the Sun's aberration and parallax
#: as seen from the satellite (1), the chord between samples (0.03).
UMBRA_SLACK_KM = 5.0
#: Nodes kept in memory (a visit needs two; the next visits usually the same).
CACHED_NODES = 4
#: Nodes per step of the coarse grid, where every satellite is propagated (module notes).
COARSE_NODES = 6
#: The factor on the Kepler orbit's bound of the coarse interpolation (module notes).
COARSE_SLACK = 2.0
#: Changes of the osculating perigee (km) and eccentricity between two coarse nodes that the
#: bounds allow for (the Earth's flattening's short-period terms: about 7 km and 0.001).
PERIGEE_DROP_KM = 20.0
ECCENTRICITY_RISE = 0.002
#: Added to the distance bounds of the shortlists, km (the arithmetic's rounding).
ROUNDING_KM = 0.5


def prefilter_margin_deg(perigee_height_km, node_step_s=NODE_STEP_S, step_s=COARSE_STEP_S):
    """The prefilter's margin (deg) for satellites no lower than ``perigee_height_km``.

    Twice the sum of the bounds of the module notes: the Hermite interpolation's error and
    the chord's sagitta, seen from the perigee height, and :data:`FIXED_ERRORS_DEG`; at
    least 0.05 deg.
    """
    r = R_EQ_KM + perigee_height_km
    n = math.sqrt(MU_KM3_S2 / r ** 3)
    interp_km = INTERP_SLACK * node_step_s ** 4 / 384.0 * n ** 4 * r
    sagitta_km = MU_KM3_S2 / r ** 2 * step_s ** 2 / 8.0
    angle = math.degrees((interp_km + sagitta_km) / perigee_height_km) + FIXED_ERRORS_DEG
    return max(2.0 * angle, 0.05)


def _basis(b):
    """Two unit vectors completing ``b`` (n, 3) into orthonormal triads."""
    helper = np.where(np.abs(b[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(helper, b)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(b, e1)


def _eccentricity_perigee(r, v):
    """Osculating eccentricity and perigee radius (km) of TEME states (km, km/s; (n, 3)):
    ``e^2 = 1 - |r x v|^2 / (mu a)``, ``|r x v|^2 = r^2 v^2 - (r . v)^2``."""
    r2 = np.einsum("ij,ij->i", r, r)
    v2 = np.einsum("ij,ij->i", v, v)
    rv = np.einsum("ij,ij->i", r, v)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = 1.0 / (2.0 / np.sqrt(r2) - v2 / MU_KM3_S2)
        e = np.sqrt(np.maximum(1.0 - (r2 * v2 - rv * rv) / (MU_KM3_S2 * a), 0.0))
    return e, np.where(a > 0.0, a * (1.0 - e), np.nan)


def _direction_grid(times_s):
    """Times (s) spanning ``times_s``, at most :data:`DIRECTION_STEP_S` apart (two at least)."""
    lo = float(np.min(times_s, initial=0.0))
    hi = max(float(np.max(times_s, initial=0.0)), lo + 1.0)
    return np.linspace(lo, hi, int(math.ceil((hi - lo) / DIRECTION_STEP_S)) + 1)


def _interpolated_directions(grid_s, values, times_s):
    """Unit vectors (m, 3) at ``times_s`` (m,): linear in time between the vectors
    ``values`` ((len(grid_s), m or 1, 3)) at the times ``grid_s``, normalised."""
    i = np.clip(np.searchsorted(grid_s, times_s, side="right") - 1, 0, len(grid_s) - 2)
    f = ((times_s - grid_s[i]) / (grid_s[i + 1] - grid_s[i]))[:, None]
    cols = np.arange(len(times_s)) if values.shape[1] > 1 else np.zeros(len(times_s), int)
    out = (1.0 - f) * values[i, cols] + f * values[i + 1, cols]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _half_space(apexes, aims, backs, fars, tan_a):
    """A half-space ``r . n >= level`` holding, for every visit ``j``, the points ``r`` with
    ``d <= z tan_a + fars[j]`` and ``z >= -backs[j]`` (``z`` and ``d`` the distances along
    and from the line of sight from ``apexes[j]`` along the unit vector ``aims[j]``): ``n``
    and ``level`` (km), or None if no normal tried is within ``90 deg - a`` of every aim.

    A point there is ``apex + z b + w`` with ``w`` square to ``b`` and ``|w| <= z tan_a +
    far``; with ``c = b . n`` and ``s = sqrt(1 - c^2)``, ``w . n >= -|w| s``, so ``(r - apex)
    . n >= z (c - s tan_a) - far s >= -back (c - s tan_a) - far s`` when ``c >= s tan_a``.
    The normals tried: the mean aim, the zenith at the mean apex, and their bisector; the
    one with the highest level is kept (the fewest satellites above it).
    """
    mean_aim = aims.sum(axis=0)
    up = apexes.sum(axis=0)
    best = None
    for n in (mean_aim, up, mean_aim / np.linalg.norm(mean_aim) + up / np.linalg.norm(up)):
        n = n / np.linalg.norm(n)
        c = aims @ n
        s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
        if np.any(c < s * tan_a):
            continue
        level = float(np.min(apexes @ n - backs * (c - s * tan_a) - fars * s))
        if best is None or level > best[1]:
            best = (n, level)
    return best


def _evict(cache, key, size, position=lambda k: k):
    """Make room in ``cache`` for ``key``: drop the entries farthest from it (by
    ``position`` of the keys)."""
    while len(cache) >= size:
        del cache[max(cache, key=lambda j: abs(position(j) - position(key)))]


class NightPrefilter:
    """Crossing candidates of a night's visits (module notes).

    Parameters
    ----------
    orbits : sequence of inject.orbits.passes.Orbit
    visits : sequence of inject.survey.visits.Visit
        The visits :meth:`candidates` will be asked about (any order).
    site : inject.orbits.passes.Site
    field_radius_deg : float
        Radius of the field disc (gnomonic, as :attr:`inject.orbits.passes.Pass.in_field`).
    margin_deg : float, optional
        Added to the radius; :func:`prefilter_margin_deg` of the lowest perigee by default.
    node_step_s, step_s : float
        :data:`NODE_STEP_S`, :data:`COARSE_STEP_S`.
    coarse_nodes : int
        :data:`COARSE_NODES`.
    """

    def __init__(self, orbits, visits, site=RUBIN, field_radius_deg=FIELD_RADIUS_DEG,
                 margin_deg=None, node_step_s=NODE_STEP_S, step_s=COARSE_STEP_S,
                 coarse_nodes=COARSE_NODES):
        from astropy import units as u
        from astropy.coordinates import ITRS, TEME, CartesianRepresentation, SkyCoord
        from astropy.time import Time
        from sgp4.api import SatrecArray

        self.orbits = tuple(orbits)
        self.node_step_s = float(node_step_s)
        self._satrecs = [o.satrec for o in self.orbits]
        self._array = SatrecArray(self._satrecs)
        perigee = min(o.satrec.altp for o in self.orbits) * R_EQ_KM  # earth radii -> km
        self.margin_deg = (prefilter_margin_deg(max(perigee, 100.0), node_step_s, step_s)
                           if margin_deg is None else float(margin_deg))
        self.radius = field_radius_deg + self.margin_deg
        self._tan = math.tan(math.radians(self.radius))
        self._cos = math.cos(math.radians(self.radius))
        self._coarse_n = int(coarse_nodes)
        self._all = np.arange(len(self.orbits))
        self._nodes, self._coarse_nodes, self._intervals, self._middles = {}, {}, {}, {}
        self._index = {v.observation_id: k for k, v in enumerate(visits)}
        starts = Time([v.mjd_tai for v in visits], format="mjd", scale="tai").utc
        self._jd1 = float(starts.jd1[0]) if len(visits) else 0.0
        self._jd2 = float(starts.jd2[0]) if len(visits) else 0.0
        # Seconds of each visit's start from the first's, on UTC Julian dates (SGP4's clock).
        offsets = ((starts.jd1 - self._jd1) + (starts.jd2 - self._jd2)) * 86400.0
        self._samples = []
        for v, t0 in zip(visits, offsets):
            start, duration = v.snaps()[-1]
            end = start + duration  # the last snap's end
            n = max(2, int(math.ceil(end / step_s)) + 1)
            self._samples.append(t0 + np.linspace(0.0, end, n))
        middles_s = np.array([0.5 * (s[0] + s[-1]) for s in self._samples])
        # The nodes the visits' samples need: the coarse grid's first and last.
        ends = [f(s) for s in self._samples for f in (np.min, np.max)] or [0.0]
        self._k_first = int(math.floor(min(ends) / self.node_step_s))
        self._k_last = int(math.floor(max(ends) / self.node_step_s)) + 1
        middles = Time(np.full(len(visits), self._jd1), self._jd2 + middles_s / 86400.0,
                       format="jd", scale="utc")
        # The site in TEME at each visit's middle: one astropy call for the night. Within a
        # visit the site turns about TEME's z at the Earth's rate (the pole's 0.3" tilt from z
        # moves it by 1e-5 km in 20 s).
        rep = CartesianRepresentation(np.repeat(site.itrs_km[:, None], len(visits), axis=1),
                                      unit=u.km)
        site_mid = (SkyCoord(rep, frame=ITRS(obstime=middles)).transform_to(
            TEME(obstime=middles)).cartesian.xyz.to_value(u.km).T)
        self._site = []
        for s, mid, r in zip(self._samples, middles_s, site_mid):
            angle = EARTH_ROTATION_RAD_S * (s - mid)
            c, sn = np.cos(angle), np.sin(angle)
            self._site.append(np.stack([c * r[0] - sn * r[1], sn * r[0] + c * r[1],
                                        np.full(len(s), r[2])], axis=-1))
        # The Sun's and every boresight's direction in TEME (with the annual aberration) at
        # a few times of the night (astropy), linear between them (module notes).
        from astropy.coordinates import get_sun

        grid_s = _direction_grid(middles_s)
        grid = Time(np.full(len(grid_s), self._jd1), self._jd2 + grid_s / 86400.0,
                    format="jd", scale="utc")
        sun = get_sun(grid).transform_to(TEME(obstime=grid)).cartesian.xyz.value.T
        self._sun = _interpolated_directions(grid_s, sun[:, None], middles_s)
        sky = SkyCoord([v.ra_deg for v in visits] * u.deg, [v.dec_deg for v in visits] * u.deg,
                       frame="icrs")
        aims = np.stack([sky.transform_to(TEME(obstime=g)).cartesian.xyz.value.T
                         for g in grid]) if len(visits) else np.zeros((2, 0, 3))
        self._b = _interpolated_directions(grid_s, aims, middles_s)
        self._e1, self._e2 = _basis(self._b)
        # Each visit's middle, half-length, apex (the site's mean: within 0.01 km of its
        # middle) and node interval; the visits of each node interval.
        self._mid = middles_s
        self._half = np.array([0.5 * (s[-1] - s[0]) for s in self._samples])
        self._apex = (np.array([np.mean(site, axis=0) for site in self._site])
                      if len(visits) else np.zeros((0, 3)))
        self._kt = np.array([self._interval_of(m) for m in middles_s], int)
        self._groups, self._group_lists = {}, (None, {})
        for k, kt in enumerate(self._kt.tolist()):
            self._groups.setdefault(kt, []).append(k)

    def _interval_of(self, mid):
        """The node interval (index of its first node) test a uses for a visit's middle."""
        k = int(math.floor(mid / self.node_step_s))
        return min(max(k, self._k_first), self._k_last - 1)

    def _propagate(self, k, which=None):
        """SGP4 TEME positions and velocities (km, km/s) of the orbits ``which`` (indices;
        all by default) at node ``k``."""
        from sgp4.api import SGP4_ERRORS, SatrecArray

        jd2 = np.array([self._jd2 + k * self.node_step_s / 86400.0])
        array = (self._array if which is None
                 else SatrecArray(list(map(self._satrecs.__getitem__, which.tolist()))))
        err, r, v = array.sgp4(np.array([self._jd1]), jd2)
        if np.any(err):
            j = int(np.argwhere(err)[0][0])
            i = j if which is None else int(which[j])
            raise OrbitError(f"orbit {self.orbits[i].name!r}: SGP4 error {err[j, 0]} "
                             f"({SGP4_ERRORS.get(int(err[j, 0]), 'unknown')})")
        return r[:, 0], v[:, 0]

    def _node(self, k, which=slice(None)):
        """TEME positions and velocities (km, km/s; (n, 3) each) of the orbits ``which`` at
        node ``k``: SGP4 for those not yet propagated there."""
        if k not in self._nodes:
            _evict(self._nodes, k, CACHED_NODES)
            n = len(self.orbits)
            if k in self._coarse_nodes:  # the same SGP4 call on every satellite
                r, v = self._coarse_nodes[k][:2]
                self._nodes[k] = (r, v, np.ones(n, bool))
            else:
                self._nodes[k] = (np.empty((n, 3)), np.empty((n, 3)), np.zeros(n, bool))
        r, v, done = self._nodes[k]
        rows = self._all[which]
        missing = rows[~done[rows]]
        if len(missing):
            r[missing], v[missing] = self._propagate(k, missing)
            done[missing] = True
        return np.take(r, rows, axis=0), np.take(v, rows, axis=0)

    def _coarse_node(self, k):
        """Every orbit's SGP4 state at node ``k`` of the coarse grid, with its osculating
        orbit's eccentricity and perigee radius (km)."""
        if k not in self._coarse_nodes:
            _evict(self._coarse_nodes, k, CACHED_NODES)
            r, v = self._propagate(k)
            self._coarse_nodes[k] = (r, v, *_eccentricity_perigee(r, v))
        return self._coarse_nodes[k]

    def _coarse(self, kt):
        """The coarse interval holding node interval ``kt``: its nodes ``k0``, ``k1``, their
        states, and the bounds of the module notes over the satellites that have one
        (``speed``, km/s, the largest; ``reach_speed`` the largest speed test 1's reach
        uses; ``slack``, km, ``E_c + E_f`` and the rounding), ``always`` the others."""
        n = self._coarse_n
        k0 = max(self._k_first, n * (kt // n))
        k1 = min(self._k_last, n * (kt // n + 1))
        if (k0, k1) not in self._intervals:
            _evict(self._intervals, (k0, k1), 2, position=lambda pair: pair[0])
            r0, v0, e0, p0 = self._coarse_node(k0)
            r1, v1, e1, p1 = self._coarse_node(k1)
            e = np.maximum(e0, e1) + ECCENTRICITY_RISE
            perigee = np.minimum(p0, p1) - PERIGEE_DROP_KM
            # An orbit SGP4 gives no ellipse for has no bound: on every shortlist.
            bounded = (e < 1.0) & (perigee > 0.0)  # False for NaN
            e, perigee = e[bounded], perigee[bounded]
            # w^2 = mu (1 + e) / r_p^3: (1 + e) w^4 r_p = mu^2 (1 + e)^3 / r_p^5 and
            # w r_p = sqrt(mu (1 + e) / r_p).
            rise, inverse = 1.0 + e, 1.0 / perigee
            inverse2 = inverse * inverse
            fourth = COARSE_SLACK * INTERP_SLACK * MU_KM3_S2 ** 2 * np.max(
                rise * rise * rise * inverse2 * inverse2 * inverse, initial=0.0)
            speed = 1.01 * math.sqrt(MU_KM3_S2 * np.max(rise * inverse, initial=0.0))
            h, h_c = self.node_step_s, (k1 - k0) * self.node_step_s
            self._intervals[(k0, k1)] = {
                "k0": k0, "k1": k1, "states": np.concatenate([r0, v0, r1, v1], axis=1),
                "speed": speed,
                "reach_speed": (1.02 * (speed + math.sqrt(3.0) / 216.0 * h ** 3 * fourth)
                                + SITE_SPEED_KM_S),
                "slack": (h_c ** 4 + h ** 4) / 384.0 * fourth + ROUNDING_KM,
                "always": np.flatnonzero(~bounded)}
        return self._intervals[(k0, k1)]

    def _hermite_weights(self, coarse, t_s):
        """The (12, 3) matrix taking a row of the coarse interval's ``states`` (``r0, v0,
        r1, v1``) to the coarse interpolation at ``t_s``."""
        h = (coarse["k1"] - coarse["k0"]) * self.node_step_s
        s = (t_s - coarse["k0"] * self.node_step_s) / h
        s2, s3 = s * s, s * s * s
        weights = np.array([2 * s3 - 3 * s2 + 1, h * (s3 - 2 * s2 + s), -2 * s3 + 3 * s2,
                            h * (s3 - s2)])
        return (weights[:, None, None] * np.eye(3)).reshape(12, 3)

    def _coarse_positions(self, coarse, t_s, which=slice(None)):
        """The coarse interpolation (km, (n, 3)) of the orbits ``which`` at ``t_s``."""
        states = coarse["states"]
        rows = states[which] if isinstance(which, slice) else np.take(states, which, axis=0)
        return rows @ self._hermite_weights(coarse, t_s)

    def _interval(self, kt):
        """The satellites that may pass test a for a visit of node interval ``kt`` (indices,
        ascending: those above the half-space of test 0, module notes), their coarse
        interpolation at test a's time ``t_c``, its squared norms, and ``t_c``."""
        if kt not in self._middles:
            _evict(self._middles, kt, 2)
            coarse = self._coarse(kt)
            group = self._groups.get(kt, [])
            # Halfway between the interval's first and last visit middles (all in the
            # interval: the coarse interpolation holds there).
            t_c = (0.5 * (self._mid[group].min() + self._mid[group].max()) if group
                   else (kt + 0.5) * self.node_step_s)
            backs = (coarse["slack"] + coarse["reach_speed"] * self._half[group] + 0.1
                     + coarse["speed"] * np.abs(self._mid[group] - t_c))
            plane = _half_space(self._apex[group], self._b[group], backs, backs / self._cos,
                                self._tan) if group else None
            weights = self._hermite_weights(coarse, t_c)
            if plane is None:
                which = self._all
            else:
                n, level = plane
                which = np.flatnonzero(coarse["states"] @ (weights @ n)
                                       >= level - ROUNDING_KM)
            r = np.take(coarse["states"], which, axis=0) @ weights
            self._middles[kt] = (which, r, np.einsum("ij,ij->i", r, r), t_c)
        return self._middles[kt]

    def _shortlist(self, k):
        """Indices (ascending) of the satellites that may pass test 1 at visit ``k``'s middle:
        tests 0, a and b of the module notes."""
        mid, half, apex, b = self._mid[k], self._half[k], self._apex[k], self._b[k]
        kt = self._kt[k]
        coarse = self._coarse(kt)
        which, r, norm2, t_c = self._interval(kt)
        reach = coarse["slack"] + coarse["reach_speed"] * half + 0.1
        # a: at t_c (|r - apex|^2 = d^2 + z^2).
        far = (reach + coarse["speed"] * abs(mid - t_c)) / self._cos
        zw = r @ np.stack([b, apex], axis=1)
        z = zw[:, 0] - apex @ b
        bound = z * self._tan + far
        d2 = (norm2 - 2.0 * zw[:, 1] + apex @ apex) - z * z
        which = which[(bound >= 0.0) & (d2 <= bound * bound)]
        if len(which):
            # b: the visit's middle, on those.
            los = self._coarse_positions(coarse, mid, which) - apex
            z = los @ b
            d = np.linalg.norm(los - z[:, None] * b, axis=1)
            which = which[d <= z * self._tan + reach / self._cos]
        return np.union1d(which, coarse["always"]) if len(coarse["always"]) else which

    def _near(self, k):
        """Test 1's survivors at visit ``k`` (indices, ascending) and their interpolated
        positions at its samples ((n, len(samples), 3) km). The visits of a node interval are
        done together: their shortlists (the satellites on them propagated at the nodes
        about their middles in one SGP4 call a node), interpolated at all their middles at
        once, and test 1's survivors at all their samples at once."""
        kt = self._kt[k]
        if self._group_lists[0] != kt:
            group = self._groups[kt]
            lists = [self._shortlist(j) for j in group]
            union = np.unique(np.concatenate(lists))
            r, v = self.positions(self._mid[group], union)
            nears = []
            for col, (j, which) in enumerate(zip(group, lists)):
                rows = np.searchsorted(union, which)
                nears.append(which[self._test_1(j, np.take(r[:, col], rows, axis=0),
                                                np.take(v[:, col], rows, axis=0))])
            union = np.unique(np.concatenate(nears))
            r, _ = self.positions(np.concatenate([self._samples[j] for j in group]), union)
            ends = np.cumsum([0] + [len(self._samples[j]) for j in group])
            self._group_lists = (kt, {j: (near, np.take(r[:, ends[col]:ends[col + 1]],
                                                         np.searchsorted(union, near), axis=0))
                                      for col, (j, near) in enumerate(zip(group, nears))})
        return self._group_lists[1][k]

    def _test_1(self, k, r, v):
        """Test 1 at visit ``k`` on interpolated positions and velocities at its middle ((n,
        3) each): a mask."""
        ts, b, apex = self._samples[k], self._b[k], self._apex[k]
        los = r - apex
        z = los @ b
        d = np.linalg.norm(los - z[:, None] * b, axis=1)
        # 2% on the speed for its change along an eccentric orbit within the visit.
        speed = 1.02 * np.linalg.norm(v, axis=1) + SITE_SPEED_KM_S
        reach = speed * 0.5 * (ts[-1] - ts[0]) + 0.1
        return (d <= z * self._tan + reach / self._cos) & (z >= -reach)

    def positions(self, t_s, which=slice(None)):
        """TEME positions (km, (n, len(t_s), 3)) of the orbits ``which`` at ``t_s`` (s from
        the first visit's start), and their velocities: cubic Hermite between nodes."""
        t_s = np.atleast_1d(np.asarray(t_s, float))
        h = self.node_step_s
        k = np.floor(t_s / h).astype(int)
        u = t_s / h - k
        n = len(self._all[which])
        r_out, v_out = np.empty((n, t_s.size, 3)), np.empty((n, t_s.size, 3))
        for kk in np.unique(k).tolist():
            cols = np.flatnonzero(k == kk)
            r0, v0 = self._node(kk, which)
            r1, v1 = self._node(kk + 1, which)
            # The cubic Hermite basis (and its derivative) at each time, on the node states.
            s = u[cols][:, None]
            s2, s3 = s * s, s * s * s
            weights = np.concatenate([2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2,
                                      s3 - s2], axis=1)
            slopes = np.concatenate([6 * s2 - 6 * s, 3 * s2 - 4 * s + 1, -6 * s2 + 6 * s,
                                     3 * s2 - 2 * s], axis=1) / h
            states = np.stack([r0, h * v0, r1, h * v1], axis=1)
            r_out[:, cols] = weights @ states
            v_out[:, cols] = slopes @ states
        return r_out, v_out

    def candidates(self, visit, sunlit=False):
        """Indices (into ``orbits``) of the satellites that may cross ``visit``'s field (and,
        with ``sunlit``, leave the Earth's umbra during it: module notes)."""
        k = self._index[visit.observation_id]
        near, r = self._near(k)
        if not len(near):
            return near
        keep = self._closest(k, r) <= self.radius
        if sunlit:
            keep &= ~self._dark(k, r)
        return near[keep]

    def _dark(self, k, r):
        """Per satellite (positions ``r``, (n, len(samples), 3) km): inside the shrunk umbra
        at every sample of visit ``k``."""
        s = self._sun[k]
        behind = -(r @ s)
        off = np.linalg.norm(r + behind[..., None] * s, axis=-1)
        umbra = R_POLAR_KM - UMBRA_TAPER * behind - UMBRA_SLACK_KM
        return ((behind > 0) & (off < umbra)).all(axis=1)

    def closest_deg(self, visit, which=None):
        """The closest approach (deg, gnomonic) to ``visit``'s boresight of the coarse tracks
        of the orbits ``which`` (indices; all by default): of a sample, or of a chord between
        two samples both in front of the observer; inf if none is."""
        k = self._index[visit.observation_id]
        which = np.arange(len(self.orbits)) if which is None else np.asarray(which)
        r, _ = self.positions(self._samples[k], which)
        return self._closest(k, r)

    def _closest(self, k, r):
        """:meth:`closest_deg` of the positions ``r`` ((n, len(samples), 3) km) at visit
        ``k``'s samples."""
        los = r - self._site[k][None]
        cz = los @ self._b[k]
        front = cz > 0.05 * np.linalg.norm(los, axis=-1)
        safe = np.where(front, cz, 1.0)
        xi = np.degrees(los @ self._e1[k] / safe)
        eta = np.degrees(los @ self._e2[k] / safe)
        point = np.where(front, np.hypot(xi, eta), np.inf).min(axis=1)
        seg = np.where(front[:, :-1] & front[:, 1:], segment_distances(xi, eta), np.inf)
        return np.minimum(point, seg.min(axis=1))
