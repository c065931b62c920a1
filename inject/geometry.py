"""Observing geometry of a satellite in a circular orbit (Snyder & Tyson, section 2).

All functions are vectorised over numpy arrays of heights, zenith angles and rotation angles.
Heights and ranges are in km, angles in degrees at the interface; the satellite frame follows the
paper: z along the satellite's nadir, the telescope in the yz-plane at the nadir angle, the
velocity in the xy-plane at rotation angle ``phi`` from x (``phi = 90`` is motion along constant
azimuth).
"""
from dataclasses import dataclass

import numpy as np
from astropy import constants

from inject.instrument import ARCSEC_PER_RAD
from inject.validate import in_range, positive

#: Equatorial Earth radius, km (astropy's IAU 2015 nominal value).
R_EARTH_KM = constants.R_earth.to_value("km")
#: Geocentric gravitational constant, m^3 s^-2.
GM_EARTH = constants.GM_earth.to_value("m3 / s2")
#: Sidereal rate, rad/s (the telescope's tracking rate, ignored by default as in the paper).
SIDEREAL_RATE_RAD_S = 7.292115e-5


def _inputs(height_km, zenith_deg):
    h = positive("height_km", height_km)
    z = np.radians(in_range("zenith_deg", zenith_deg, 0.0, 90.0))
    return h, z


def nadir_angle(height_km, zenith_deg):
    """Angle at the satellite between its nadir and the line to the telescope, in degrees.

    ``theta_N = arcsin(R / (R + h) * sin z)`` (paper eq. 1).
    """
    h, z = _inputs(height_km, zenith_deg)
    return np.degrees(np.arcsin(R_EARTH_KM / (R_EARTH_KM + h) * np.sin(z)))


def slant_range(height_km, zenith_deg):
    """Distance from the telescope to the satellite, km.

    Uses ``sqrt((R + h)^2 - R^2 sin^2 z) - R cos z``, the law of cosines solved for the range. It
    has no branch at zenith (where the paper's ``R sin(z - theta_N) / sin(theta_N)`` is 0/0) and is
    written as ``h (2R + h) / (sqrt(...) + R cos z)`` so it does not lose digits to cancellation
    when ``h << R`` near zenith.
    """
    h, z = _inputs(height_km, zenith_deg)
    root = np.sqrt((R_EARTH_KM + h) ** 2 - (R_EARTH_KM * np.sin(z)) ** 2)
    return h * (2 * R_EARTH_KM + h) / (root + R_EARTH_KM * np.cos(z))


def orbital_speed(height_km):
    """Circular orbital speed ``sqrt(GM / (R + h))``, m/s."""
    h = positive("height_km", height_km)
    return np.sqrt(GM_EARTH / ((R_EARTH_KM + h) * 1e3))


def tangential_velocity(height_km, zenith_deg, phi_deg=90.0):
    """Velocity component perpendicular to the line of sight, in the satellite frame, m/s.

    Paper eq. 8: ``(v cos phi, v sin phi cos^2 theta_N, -v sin phi sin theta_N cos theta_N)``.
    Returns an array whose last axis holds the three components.
    """
    v = orbital_speed(height_km)
    tn = np.radians(nadir_angle(height_km, zenith_deg))
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    return np.stack(np.broadcast_arrays(
        v * np.cos(phi),
        v * np.sin(phi) * np.cos(tn) ** 2,
        -v * np.sin(phi) * np.sin(tn) * np.cos(tn)), axis=-1)


def tangential_speed(height_km, zenith_deg, phi_deg=90.0):
    """``|v_T| = v sqrt(cos^2 phi + sin^2 phi cos^2 theta_N)``, m/s."""
    v = orbital_speed(height_km)
    tn = np.radians(nadir_angle(height_km, zenith_deg))
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    return v * np.hypot(np.cos(phi), np.sin(phi) * np.cos(tn))


def angular_speed(height_km, zenith_deg, phi_deg=90.0):
    """Apparent angular speed ``omega = |v_T| / r`` in the alt-az frame, rad/s."""
    return tangential_speed(height_km, zenith_deg, phi_deg) / (
        slant_range(height_km, zenith_deg) * 1e3)


def effective_exposure(height_km, zenith_deg, phi_deg=90.0, pixel_scale_arcsec=0.2):
    """Time the satellite takes to cross one pixel, ``t_eff = p / omega``, s."""
    p = positive("pixel_scale_arcsec", pixel_scale_arcsec)
    return p / ARCSEC_PER_RAD / angular_speed(height_km, zenith_deg, phi_deg)


def track_direction(height_km, zenith_deg, phi_deg=90.0):
    """Direction of the apparent motion on the sky, in degrees from the azimuth axis.

    Projecting the satellite-frame velocity onto the sky plane leaves ``(cos phi, sin phi cos
    theta_N)`` in the (azimuth, altitude) basis.
    """
    tn = np.radians(nadir_angle(height_km, zenith_deg))
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    return np.degrees(np.arctan2(np.sin(phi) * np.cos(tn), np.cos(phi)))


@dataclass(frozen=True)
class Geometry:
    """Everything the streak depends on for one orbit height and line of sight (scalars).

    Build it with :meth:`from_orbit`. ``range_km`` and ``angular_speed_rad_s`` are the
    paper's spherical-Earth values unless given explicitly (a real pass's exact ones, from
    :func:`inject.orbits.passes.compute_pass`); then ``t_eff = p / omega`` and the tangential speed
    ``omega r`` follow them.
    """

    height_km: float
    zenith_deg: float
    phi_deg: float
    pixel_scale_arcsec: float
    nadir_angle_deg: float
    range_km: float
    orbital_speed_m_s: float
    tangential_speed_m_s: float
    angular_speed_rad_s: float
    t_eff_s: float

    @classmethod
    def from_orbit(cls, height_km, zenith_deg=0.0, phi_deg=90.0, pixel_scale_arcsec=0.2,
                   range_km=None, angular_speed_rad_s=None):
        """Compute the geometry of a circular orbit seen at one zenith angle.

        ``range_km`` and ``angular_speed_rad_s`` (optional) replace the spherical-Earth range
        and the angular speed across the star field (see the class docstring).
        """
        r = float(slant_range(height_km, zenith_deg) if range_km is None
                  else positive("range_km", range_km))
        if angular_speed_rad_s is None:
            omega = float(angular_speed(height_km, zenith_deg, phi_deg))
            v_t = float(tangential_speed(height_km, zenith_deg, phi_deg))
            t_eff = float(effective_exposure(height_km, zenith_deg, phi_deg, pixel_scale_arcsec))
        else:
            omega = float(positive("angular_speed_rad_s", angular_speed_rad_s))
            v_t = omega * r * 1e3
            t_eff = float(positive("pixel_scale_arcsec", pixel_scale_arcsec)) / ARCSEC_PER_RAD \
                / omega
        return cls(
            height_km=float(height_km), zenith_deg=float(zenith_deg), phi_deg=float(phi_deg),
            pixel_scale_arcsec=float(pixel_scale_arcsec),
            nadir_angle_deg=float(nadir_angle(height_km, zenith_deg)),
            range_km=r, orbital_speed_m_s=float(orbital_speed(height_km)),
            tangential_speed_m_s=v_t, angular_speed_rad_s=omega, t_eff_s=t_eff,
        )
