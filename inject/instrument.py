"""Telescope and camera parameters: the one place the LSST numbers live.

Sources: the clear M1 annulus from batoid's ``LSST_r.yaml`` and leosim;
plate scale and focal length from the LSST overview paper (Ivezic et al. 2019) and ts_wep.
"""
from dataclasses import dataclass, replace

ARCSEC_PER_RAD = 206264.80624709636


@dataclass(frozen=True)
class Telescope:
    """An annular telescope pupil and its camera's plate scale.

    Parameters
    ----------
    outer_radius_m : float
        Outer radius of the clear primary-mirror annulus, m.
    inner_radius_m : float
        Inner (obscuration) radius, m; 0 for a filled pupil.
    pixel_scale_arcsec : float
        Plate scale, arcsec per pixel.
    focal_length_m : float
        Effective focal length, m (informational; the plate scale is what is used).
    """

    outer_radius_m: float = 4.18
    inner_radius_m: float = 2.558
    pixel_scale_arcsec: float = 0.2
    focal_length_m: float = 10.312

    def __post_init__(self):
        from inject.errors import InputError

        if not self.outer_radius_m > 0:
            raise InputError("outer_radius_m", self.outer_radius_m, "must be > 0")
        if not 0 <= self.inner_radius_m < self.outer_radius_m:
            raise InputError("inner_radius_m", self.inner_radius_m,
                             "must satisfy 0 <= inner < outer radius")
        if not self.pixel_scale_arcsec > 0:
            raise InputError("pixel_scale_arcsec", self.pixel_scale_arcsec, "must be > 0")

    @property
    def obscuration(self):
        """Linear obscuration ratio ``inner/outer``."""
        return self.inner_radius_m / self.outer_radius_m

    def with_pixel_scale(self, pixel_scale_arcsec):
        """Return a copy with another plate scale."""
        return replace(self, pixel_scale_arcsec=pixel_scale_arcsec)


#: Rubin Observatory's Simonyi telescope with LSSTCam.
LSST = Telescope()
