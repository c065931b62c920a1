"""The survey's prefilter: which satellites may cross a visit's field, for a night of visits.

:func:`inject.orbits.passes.crossing_candidates` propagates every satellite at seven times of
each exposure and builds an astropy frame for it. Over a night of visits most of that work is
shared: :class:`NightPrefilter` propagates the constellation once per *node* of a coarse time
grid (:data:`NODE_STEP_S` apart, SGP4 positions and velocities, kept while visits need them),
and computes the site's and every boresight's direction in TEME for all the visits in two
astropy calls. A visit then costs a cubic Hermite interpolation and dot products:

1. At the visit's middle, a satellite is kept only if it lies within the distance it can
   travel during half the visit (its speed plus the site's) of the cone of half-angle
   ``field_radius_deg + margin`` about the boresight (a test on the line of sight only).
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
  (20.5" annual, 0.3" diurnal) and the polar motion (the site is 10 m off): 0.008 deg.

These add to 0.05 deg at 350 km; the margin is twice the sum, floored at 0.05 deg. A test
checks on hundreds of satellites that no satellite whose exact pass enters the field is left
out.

With ``sunlit=True`` a candidate must also leave the Earth's umbra at some time of the visit:
a satellite that stays, at every coarse sample, inside the umbra of the sphere of the
Earth's polar radius (inside the ellipsoid's umbra: no part of the Sun is seen past it),
shrunk by :data:`UMBRA_SLACK_KM`, stays in the umbra between them too (the umbra is a convex
cone and the track leaves its chord by 0.03 km), so no sunlit part of its track is lost.
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
#: Angles the prefilter leaves out (light time 5.3", aberration 20.8", polar motion 0.3" at the
#: ground seen from the satellite), deg.
FIXED_ERRORS_DEG = (5.3 + 20.8 + 2.0) / 3600.0
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
    """

    def __init__(self, orbits, visits, site=RUBIN, field_radius_deg=FIELD_RADIUS_DEG,
                 margin_deg=None, node_step_s=NODE_STEP_S, step_s=COARSE_STEP_S):
        from astropy import units as u
        from astropy.coordinates import ITRS, TEME, CartesianRepresentation, SkyCoord
        from astropy.time import Time
        from sgp4.api import SatrecArray

        self.orbits = tuple(orbits)
        self.node_step_s = float(node_step_s)
        self._array = SatrecArray([o.satrec for o in self.orbits])
        perigee = min(o.satrec.altp for o in self.orbits) * R_EQ_KM  # earth radii -> km
        self.margin_deg = (prefilter_margin_deg(max(perigee, 100.0), node_step_s, step_s)
                           if margin_deg is None else float(margin_deg))
        self.radius = field_radius_deg + self.margin_deg
        self._tan = math.tan(math.radians(self.radius))
        self._cos = math.cos(math.radians(self.radius))
        self._nodes = {}
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
        middles = Time(np.full(len(visits), self._jd1), self._jd2 + middles_s / 86400.0,
                       format="jd", scale="utc")
        # The site in TEME at each visit's middle and each boresight's direction (with the
        # annual aberration) there: one astropy call each for the night. Within a visit the
        # site turns about TEME's z at the Earth's rate (the pole's 0.3" tilt from z moves it
        # by 1e-5 km in 20 s).
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
        from astropy.coordinates import get_sun

        sun = get_sun(middles).transform_to(TEME(obstime=middles)).cartesian.xyz.value.T
        self._sun = sun / np.linalg.norm(sun, axis=1, keepdims=True)
        aim = SkyCoord([v.ra_deg for v in visits] * u.deg, [v.dec_deg for v in visits] * u.deg,
                       frame="icrs").transform_to(TEME(obstime=middles))
        b = aim.cartesian.xyz.value.T
        self._b = b / np.linalg.norm(b, axis=1, keepdims=True)
        self._e1, self._e2 = _basis(self._b)

    def _node(self, k):
        """TEME positions and velocities (km, km/s; (n_orbits, 3) each) at node ``k``."""
        if k not in self._nodes:
            if len(self._nodes) >= CACHED_NODES:
                del self._nodes[max(self._nodes, key=lambda j: abs(j - k))]
            jd2 = np.array([self._jd2 + k * self.node_step_s / 86400.0])
            from sgp4.api import SGP4_ERRORS

            err, r, v = self._array.sgp4(np.array([self._jd1]), jd2)
            if np.any(err):
                i = int(np.argwhere(err)[0][0])
                raise OrbitError(f"orbit {self.orbits[i].name!r}: SGP4 error {err[i, 0]} "
                                 f"({SGP4_ERRORS.get(int(err[i, 0]), 'unknown')})")
            self._nodes[k] = (r[:, 0], v[:, 0])
        return self._nodes[k]

    def positions(self, t_s, which=slice(None)):
        """TEME positions (km, (n, len(t_s), 3)) of the orbits ``which`` at ``t_s`` (s from
        the first visit's start), and their velocities: cubic Hermite between nodes."""
        t_s = np.atleast_1d(np.asarray(t_s, float))
        h = self.node_step_s
        k = np.floor(t_s / h).astype(int)
        u = t_s / h - k
        n = len(np.arange(len(self.orbits))[which])
        r_out, v_out = np.empty((n, t_s.size, 3)), np.empty((n, t_s.size, 3))
        for kk in np.unique(k):
            cols = np.flatnonzero(k == kk)
            r0, v0 = (a[which] for a in self._node(kk))
            r1, v1 = (a[which] for a in self._node(kk + 1))
            s = u[cols][None, :, None]
            s2, s3 = s * s, s * s * s
            h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
            a, b_, c, d = r0[:, None], h * v0[:, None], r1[:, None], h * v1[:, None]
            r_out[:, cols] = h00 * a + h10 * b_ + h01 * c + h11 * d
            dh00, dh10 = 6 * s2 - 6 * s, 3 * s2 - 4 * s + 1
            dh01, dh11 = -6 * s2 + 6 * s, 3 * s2 - 2 * s
            v_out[:, cols] = (dh00 * a + dh10 * b_ + dh01 * c + dh11 * d) / h
        return r_out, v_out

    def candidates(self, visit, sunlit=False):
        """Indices (into ``orbits``) of the satellites that may cross ``visit``'s field (and,
        with ``sunlit``, leave the Earth's umbra during it: module notes)."""
        k = self._index[visit.observation_id]
        ts, site, b = self._samples[k], self._site[k], self._b[k]
        mid = 0.5 * (ts[0] + ts[-1])
        r, v = self.positions([mid])
        los = r[:, 0] - np.mean(site, axis=0)  # the site's mean: within 0.01 km of its middle
        z = los @ b
        d = np.linalg.norm(los - z[:, None] * b, axis=1)
        # 2% on the speed for its change along an eccentric orbit within the visit.
        speed = 1.02 * np.linalg.norm(v[:, 0], axis=1) + SITE_SPEED_KM_S
        reach = speed * 0.5 * (ts[-1] - ts[0])
        near = np.flatnonzero(d <= z * self._tan + (reach + 0.1) / self._cos)
        if not len(near):
            return near
        r, _ = self.positions(ts, near)
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
