"""One satellite pass seen by one telescope: geometry + photometry + profile -> streak model.

:class:`StreakModel` gathers everything a renderer, the truth table and ``inject profile``
need: the stationary profile in the track frame, the charge per pixel of track length, the
cross-section across the track, its FWHM and peak.
"""
from dataclasses import dataclass
from functools import cached_property, lru_cache

import galsim
import numpy as np

from inject import optics
from inject.errors import InputError
from inject.geometry import Geometry
from inject.instrument import LSST, Telescope
from inject.photometry import apparent_magnitude, band, electron_rate
from inject.profile import Seeing, line_spread, line_spreads, stationary_profile
from inject.satellite import Box, Shape
from inject.validate import finite, positive

#: Defocus kernels: the paper's ideal annulus, or traced through Rubin's optics.
PUPILS = ("annulus", "rubin")


@dataclass(frozen=True)
class StreakModel:
    """A satellite of given shape and brightness on a circular orbit, seen at one zenith angle.

    Parameters
    ----------
    height_km, zenith_deg, phi_deg : float
        Orbit height, zenith angle of the line of sight, rotation angle of the velocity (paper
        eq. 8; 90 = along constant azimuth).
    shape : Shape
        Satellite shape (body frame, metres).
    mag : float
        Stationary AB magnitude at ``ref_range_km``, viewed face-on.
    band_name : str
        LSST filter.
    seeing : Seeing
        Atmospheric PSF.
    telescope : Telescope
        Pupil and plate scale.
    ref_range_km : float
        Range at which ``mag`` is given.
    range_km, angular_speed_rad_s : float, optional
        A real pass's exact range and angular speed across the tracked star field
        (:func:`inject.orbits.passes.compute_pass`), in place of the paper's spherical-Earth values
        from (height, zenith, phi): ``t_eff``, the charge per pixel, the defocus and the
        shape's angular size then follow the pass. None (the default): the paper's.
    pupil : str
        The defocus kernel: ``"annulus"`` (the paper's ideal annulus, the default) or
        ``"rubin"`` (a point at the range traced through Rubin's optics for the band,
        :func:`inject.optics.kernel`).
    field_angle_deg : float
        With ``pupil="rubin"``: the streak's angle from the optical axis, deg (0 to 2.05).
    field_position_angle_deg : float
        With ``pupil="rubin"``: direction of the outward field radius in the track frame, deg
        counter-clockwise from the direction of motion (0: the satellite moves outward along
        the radius; 90: across it). Kept to whole degrees (the FWHM moves by < 0.05% a
        degree at 1.5 deg).
    focus_offset_um : float
        With ``pupil="rubin"``: the detector's shift from the design's position along the
        optical axis, micron (0: focused at infinity; negative: towards the light arriving
        from the camera's last lens, :func:`inject.optics.traced_kernel`).
    telescope_position_angle_deg : float, optional
        With ``pupil="rubin"``: the field radius's direction in the telescope's frame, where
        the spider vanes are fixed, deg (:func:`inject.optics.telescope_position_angle` of the
        camera rotator and the radius's direction on the focal plane). None (the default, no
        rotator given): the radius 22.5 deg from a vane (:data:`inject.optics.VANE_OFFSET_DEG`).
    sed_temperature_k : float
        With ``pupil="rubin"``: the satellite's spectrum, a blackbody of this temperature, K,
        over which the kernel is traced (default: the Sun's, sunlight reflected without
        colour; :func:`inject.optics.colour_temperature` gives one from a colour).

    Raises
    ------
    InputError
        If a parameter has the wrong type (an array or a string for a number, a number for
        ``seeing``) or is out of its domain.
    """

    height_km: float
    zenith_deg: float = 0.0
    phi_deg: float = 90.0
    shape: object = Box(7.25, 2.65)
    mag: float = 5.0
    band_name: str = "g"
    seeing: Seeing = Seeing()
    telescope: object = LSST
    ref_range_km: float = 550.0
    range_km: float | None = None
    angular_speed_rad_s: float | None = None
    pupil: str = "annulus"
    field_angle_deg: float = 0.0
    field_position_angle_deg: float = 0.0
    focus_offset_um: float = 0.0
    telescope_position_angle_deg: float | None = None
    sed_temperature_k: float = optics.SUN_TEMPERATURE_K

    def __post_init__(self):
        # Wrong types would otherwise fail much later, as an AttributeError or TypeError.
        expected = {"shape": (Shape, "a Box, Disk or Composite"),
                    "seeing": (Seeing, "a Seeing, e.g. Seeing(0.7)"),
                    "telescope": (Telescope, "a Telescope")}
        for name, (cls, what) in expected.items():
            if not isinstance(getattr(self, name), cls):
                raise InputError(name, getattr(self, name), f"must be {what}")
        for name in ("height_km", "zenith_deg", "phi_deg", "mag", "ref_range_km"):
            finite(name, getattr(self, name), scalar=True)  # not an array, a string or None
        for name in ("range_km", "angular_speed_rad_s"):
            if getattr(self, name) is not None:
                positive(name, getattr(self, name), scalar=True)
        positive("ref_range_km", self.ref_range_km)
        if not isinstance(self.band_name, str):
            raise InputError("band", self.band_name, "must be a band name such as 'g'")
        band(self.band_name)
        if not isinstance(self.pupil, str) or self.pupil not in PUPILS:
            raise InputError("pupil", self.pupil, "choose " + " or ".join(PUPILS))
        optics.check_field_angle(self.field_angle_deg)
        finite("field_position_angle_deg", self.field_position_angle_deg, scalar=True)
        optics.check_focus_offset(self.focus_offset_um)
        if self.pupil == "annulus" and self.focus_offset_um != 0:
            raise InputError("focus_offset_um", self.focus_offset_um,
                             "only applies to pupil rubin (the annulus is the design's focus)")
        if self.telescope_position_angle_deg is not None:
            finite("telescope_position_angle_deg", self.telescope_position_angle_deg,
                   scalar=True)
            if self.pupil == "annulus":
                raise InputError("telescope_position_angle_deg",
                                 self.telescope_position_angle_deg,
                                 "only applies to pupil rubin (the annulus has no spider vanes)")
        optics.check_sed_temperature(self.sed_temperature_k)
        if self.pupil == "annulus" and self.sed_temperature_k != optics.SUN_TEMPERATURE_K:
            raise InputError("sed_temperature_k", self.sed_temperature_k,
                             "only applies to pupil rubin (the annulus is achromatic)")
        # Touch the cached geometry: validates height and zenith now rather than on first use.
        _ = self.geometry

    @cached_property
    def geometry(self):
        """The :class:`~inject.geometry.Geometry` of this pass."""
        return Geometry.from_orbit(self.height_km, self.zenith_deg, self.phi_deg,
                                   self.telescope.pixel_scale_arcsec, self.range_km,
                                   self.angular_speed_rad_s)

    @property
    def profile_key(self):
        """What the stationary profile (and so every table built from it) depends on: the
        geometry, shape, seeing and telescope; not the magnitude or band, which only scale
        the charge; the range override (the defocus) but not the angular speed's. Models
        with equal keys share swept profiles (:mod:`inject.render`). With the traced pupil,
        also the band (its optics), the field angle, the radius's direction, the focus, the
        radius's direction in the telescope's frame and the satellite's spectrum."""
        key = (self.height_km, self.zenith_deg, self.phi_deg, self.shape, self.seeing,
               self.telescope, self.range_km)
        if self.pupil == "annulus":
            return key
        return key + (self.pupil, self.band_name, float(self.field_angle_deg),
                      self._radius_direction, float(self.focus_offset_um),
                      self._vane_node, float(self.sed_temperature_k))

    @property
    def _vane_node(self):
        """The telescope-frame angle as traced (:func:`inject.optics.vane_node`), or None."""
        angle = self.telescope_position_angle_deg
        return None if angle is None else optics.vane_node(angle)

    @property
    def _radius_direction(self):
        """The field position angle as used: whole degrees in [0, 360)."""
        return float(round(self.field_position_angle_deg) % 360)

    @property
    def pixel_scale(self):
        return self.telescope.pixel_scale_arcsec

    @cached_property
    def apparent_mag(self):
        """Magnitude at this range and nadir angle (``cos theta_N / r^2`` scaling)."""
        g = self.geometry
        return float(apparent_magnitude(self.mag, g.range_km, g.nadir_angle_deg,
                                        self.ref_range_km))

    @property
    def zeropoint(self):
        return band(self.band_name).zeropoint

    @cached_property
    def flux_per_px(self):
        """Charge deposited per pixel of track length, e-: count rate times ``t_eff``, times
        :attr:`pupil_transmission`."""
        return (float(electron_rate(self.apparent_mag, self.band_name)) * self.geometry.t_eff_s
                * self.pupil_transmission)

    @cached_property
    def traced_kernel(self):
        """The :class:`inject.optics.TracedKernel` of ``pupil="rubin"`` (None for the annulus)."""
        if self.pupil == "annulus":
            return None
        return optics.kernel(self.band_name, self.geometry.range_km, self.field_angle_deg,
                             self.focus_offset_um, self.telescope_position_angle_deg,
                             self.sed_temperature_k)

    @property
    def pupil_transmission(self):
        """Light the traced optics deliver from the satellite relative to a star at the same
        field position (what the flat field leaves); 1 for the annulus."""
        kernel = self.traced_kernel
        return 1.0 if kernel is None else kernel.transmitted

    @cached_property
    def defocus_profile(self):
        """The unit-flux defocus kernel in the track frame for ``pupil="rubin"``, else None
        (the annulus of :func:`inject.profile.stationary_profile`); one object for the
        model's full and reduced profiles (:meth:`render_profile`)."""
        kernel = self.traced_kernel
        if kernel is None:
            return None
        # The kernel's frame has the field radius at its field_position_angle_deg from +x;
        # the track frame has it at ours from the direction of motion (+x).
        turn = self._radius_direction - kernel.field_position_angle_deg
        return kernel.profile().withFlux(1.0).rotate(turn * galsim.degrees)

    @cached_property
    def profile(self):
        """Unit-flux stationary profile in the track frame (arcsec, motion along +x); one
        object for all models of equal :attr:`profile_key`."""
        return _shared_profile(_ByProfile(self))

    def _profile_without(self, drop):
        g = self.geometry
        shape = self.shape.profile(g.range_km, g.nadir_angle_deg, g.phi_deg)
        return stationary_profile(shape, g.range_km, self.seeing, self.telescope, drop=drop,
                                  defocus=self.defocus_profile)

    def render_profile(self, tolerance):
        """The simplest profile that draws this streak to within ``tolerance`` of its peak.

        A component (the satellite's shape, the defocus annulus) much smaller than the seeing
        (e.g. any satellite at GEO) cannot change the streak: it is dropped when the
        line-spread functions across and along the track, with pixel response, change by at
        most ``tolerance / 2`` of their peaks without it. That change is the predicted error.

        Returns
        -------
        profile : galsim.GSObject
        dropped : tuple of str
        predicted_error : float
            Relative to the peak.
        """
        if self.seeing.fwhm_arcsec == 0:
            return self.profile, (), 0.0
        p = self.pixel_scale
        reference = [line_spread(self.profile.rotate(a * galsim.degrees), p)
                     for a in (0.0, 90.0)]
        best = (self.profile, (), 0.0)
        for drop in (("defocus",), ("shape",), ("shape", "defocus")):
            candidate = self._profile_without(drop)
            error = 0.0
            for angle, ref in zip((0.0, 90.0), reference):
                lsf = line_spread(candidate.rotate(angle * galsim.degrees), p,
                                  step_arcsec=ref.step)
                values = np.interp(ref.offset_arcsec, lsf.offset_arcsec, lsf.lsf)
                error = max(error, np.abs(values - ref.lsf).max() / ref.lsf.max())
            if error <= tolerance / 2 and len(drop) >= len(best[1]):
                best = (candidate, drop, float(error))
        return best

    @cached_property
    def lsf(self):
        """Line-spread function across the track, without pixel response."""
        return _shared_line_spreads(_ByProfile(self))[0]

    @cached_property
    def pixel_lsf(self):
        """Line-spread function with the response of pixels aligned with the track."""
        return _shared_line_spreads(_ByProfile(self))[1]

    @property
    def _fine_step(self):
        # Fine enough that linear interpolation of the half-maximum crossings is good to 1e-4.
        return min(np.pi / self.profile.maxk / 2, self.pixel_scale / 40)

    @property
    def fwhm_arcsec(self):
        """FWHM of the line-spread function (outermost half-maximum crossings)."""
        return float(self.lsf.fwhm())

    @property
    def peak_e_per_px(self):
        """Most charge one pixel can collect, over all sub-pixel offsets of the streak."""
        return float(self.flux_per_px * self.pixel_lsf.peak() * self.pixel_scale)

    def cross_section(self, half_width_arcsec=None):
        """Offsets (arcsec) and the charge a pixel centred there collects (e-/px).

        Restricted to ``|offset| <= half_width_arcsec`` (default: where the signal is above
        1e-4 of its peak; Kolmogorov wings reach far below that).
        """
        cs = self.pixel_lsf
        e_per_px = self.flux_per_px * cs.lsf * self.pixel_scale
        if half_width_arcsec is None:
            significant = np.flatnonzero(e_per_px > 1e-4 * e_per_px.max())
            half_width_arcsec = max(abs(cs.offset_arcsec[significant[[0, -1]]]))
        keep = np.abs(cs.offset_arcsec) <= half_width_arcsec
        return cs.offset_arcsec[keep], e_per_px[keep]

    def summary(self):
        """The scalar quantities of ``inject profile --json`` as a dict of plain floats."""
        g = self.geometry
        return {
            "height_km": g.height_km, "zenith_deg": g.zenith_deg, "phi_deg": g.phi_deg,
            "range_km": g.range_km, "nadir_angle_deg": g.nadir_angle_deg,
            "orbital_speed_m_s": g.orbital_speed_m_s,
            "tangential_speed_m_s": g.tangential_speed_m_s,
            "angular_speed_rad_s": g.angular_speed_rad_s,
            "angular_speed_deg_s": float(np.degrees(g.angular_speed_rad_s)),
            "t_eff_s": g.t_eff_s, "band": self.band_name, "zeropoint_mag": self.zeropoint,
            "apparent_mag": self.apparent_mag, "flux_per_px_e": self.flux_per_px,
            "fwhm_arcsec": self.fwhm_arcsec,
            "fwhm_pixelated_arcsec": float(self.pixel_lsf.fwhm()),
            "peak_e_per_px": self.peak_e_per_px,
            "pixel_scale_arcsec": self.pixel_scale,
            **self.summary_pupil(),
        }

    def summary_pupil(self):
        """The defocus kernel's part of :meth:`summary`."""
        return {"pupil": self.pupil, "field_angle_deg": float(self.field_angle_deg),
                "field_position_angle_deg": self._radius_direction,
                "focus_offset_um": float(self.focus_offset_um),
                "sed_temperature_k": float(self.sed_temperature_k),
                "pupil_transmission": self.pupil_transmission}


class _ByProfile:
    """A model that hashes and compares by its :attr:`StreakModel.profile_key`, so that
    ``lru_cache`` shares what depends on the profile alone between models of any brightness."""

    __slots__ = ("model", "key")

    def __init__(self, model):
        self.model, self.key = model, model.profile_key

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return self.key == other.key


@lru_cache(maxsize=256)
def _shared_profile(ref):
    model = ref.model
    g = model.geometry
    shape = model.shape.profile(g.range_km, g.nadir_angle_deg, g.phi_deg)
    return stationary_profile(shape, g.range_km, model.seeing, model.telescope,
                              defocus=model.defocus_profile)


@lru_cache(maxsize=256)  # two arrays of a few thousand samples each
def _shared_line_spreads(ref):
    model = ref.model
    # The fine step is below the pixel's cap of line_spreads: both at the same step.
    return line_spreads(model.profile, model.pixel_scale, step_arcsec=model._fine_step)
