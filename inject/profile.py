"""The stationary profile of a satellite and its streak cross-section.

Stationary profile = projected shape (x) defocus annulus (x) atmospheric PSF, all GalSim
profiles in arcsec in the track frame (motion along +x). The streak's cross-section is the
profile's marginal along the track, the line-spread function (LSF), computed exactly from the
profile's Fourier transform on the ky axis (Fourier slice theorem: the 1-D transform of a
projection is the slice of the 2-D transform), with the pixel response as a product in k-space.
"""
from dataclasses import dataclass

import galsim
import numpy as np

from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD, LSST
from inject.validate import finite, positive

#: GalSim accuracy for every profile here. The LSF is exact up to aliasing from the period
#: 2 pi / stepk (folding 1e-4 leaves ~1e-6 of the peak for Kolmogorov tails) and truncation
#: at maxk (the transform below 1e-7).
GSPARAMS = galsim.GSParams(folding_threshold=1e-4, maxk_threshold=1e-7,
                           kvalue_accuracy=1e-8, xvalue_accuracy=1e-8,
                           maximum_fft_size=16384)

#: Reference wavelength of the seeing FWHM, nm (Kolmogorov 0.67" <-> r0 = 0.150 m at 500 nm).
SEEING_WAVELENGTH_NM = 500.0


@dataclass(frozen=True)
class Seeing:
    """Atmospheric PSF.

    Parameters
    ----------
    fwhm_arcsec : float
        FWHM of the Kolmogorov profile; for von Karman, the FWHM of the Kolmogorov profile with
        the same Fried parameter (so ``L0`` alone makes it narrower, as in GalSim).
        0 means no atmosphere (a space telescope, or the defocus alone).
    model : str
        ``"kolmogorov"`` or ``"vonkarman"``.
    outer_scale_m : float
        Von Karman outer scale L0, m.
    """

    fwhm_arcsec: float = 0.67
    model: str = "kolmogorov"
    outer_scale_m: float = 25.0

    def __post_init__(self):
        # A single finite number: a string or an array would fail later in GalSim.
        if finite("seeing", self.fwhm_arcsec, scalar=True) < 0:
            raise InputError("seeing", self.fwhm_arcsec, "must be >= 0 and finite")
        if not isinstance(self.model, str) or self.model not in ("kolmogorov", "vonkarman"):
            raise InputError("seeing.model", self.model, "choose kolmogorov or vonkarman")
        positive("outer_scale_m", self.outer_scale_m, scalar=True)

    def profile(self, gsparams=GSPARAMS):
        """The PSF as a unit-flux GalSim profile, or None for no atmosphere."""
        if self.fwhm_arcsec == 0:
            return None
        if self.model == "kolmogorov":
            return galsim.Kolmogorov(fwhm=self.fwhm_arcsec, gsparams=gsparams)
        lam_over_r0 = galsim.Kolmogorov(fwhm=self.fwhm_arcsec).lam_over_r0
        r0_m = SEEING_WAVELENGTH_NM * 1e-9 / (lam_over_r0 / ARCSEC_PER_RAD)
        return galsim.VonKarman(lam=SEEING_WAVELENGTH_NM, r0=r0_m, L0=self.outer_scale_m,
                                gsparams=gsparams)


def defocus_kernel(range_km, telescope=LSST, gsparams=GSPARAMS):
    """The telescope pupil seen from the satellite: a unit-flux annulus of radii R/r (arcsec).

    A point at range r, imaged by a telescope focused at infinity, spreads into the pupil's
    shape scaled by 1/r (Bektesevic et al. 2018). leosim's ``TopHat(a_o) - TopHat(a_i,
    flux=(a_i/a_o)^2)`` has flux 1 - eps^2; here it is renormalised to 1.
    """
    r_m = float(positive("range_km", range_km)) * 1e3
    a_o = telescope.outer_radius_m / r_m * ARCSEC_PER_RAD
    eps2 = telescope.obscuration ** 2
    outer = galsim.TopHat(a_o, flux=1.0 / (1.0 - eps2), gsparams=gsparams)
    if eps2 == 0:
        return outer
    inner = galsim.TopHat(a_o * telescope.obscuration, flux=eps2 / (1.0 - eps2),
                          gsparams=gsparams)
    return galsim.Sum([outer, -inner], gsparams=gsparams)


def stationary_profile(shape_profile, range_km, seeing=Seeing(), telescope=LSST,
                       gsparams=GSPARAMS, drop=(), defocus=None):
    """Convolve the projected shape, the defocus kernel and the seeing (unit flux).

    ``drop`` may name ``"shape"`` and/or ``"defocus"`` to leave them out (a point source, a
    telescope in focus), for components too small to matter (see
    :meth:`inject.streak.StreakModel.render_profile`). ``defocus``, a unit-flux GalSim
    profile, takes the place of the annulus (the kernel traced through the real optics).
    """
    parts = []
    if "shape" not in drop:
        parts.append(shape_profile.withGSParams(gsparams))
    if "defocus" not in drop:
        parts.append(defocus_kernel(range_km, telescope, gsparams) if defocus is None
                     else defocus.withGSParams(gsparams))
    atmosphere = seeing.profile(gsparams)
    if atmosphere is not None:
        parts.append(atmosphere)
    if not parts:
        raise InputError("drop", drop, "nothing left to draw (no seeing either)")
    if len(parts) == 1:
        return parts[0]
    return galsim.Convolve(parts, gsparams=gsparams)


@dataclass(frozen=True)
class CrossSection:
    """A profile's line-spread function across the track.

    Attributes
    ----------
    offset_arcsec : ndarray
        Offsets across the track (track-frame y), uniformly spaced, increasing.
    lsf : ndarray
        Line-spread function per arcsec, unit integral (pixel response included when asked).
    """

    offset_arcsec: np.ndarray
    lsf: np.ndarray

    @property
    def step(self):
        return self.offset_arcsec[1] - self.offset_arcsec[0]

    def peak(self):
        """Maximum of the LSF over offsets (refined between samples by a parabola)."""
        i = int(np.argmax(self.lsf))
        if 0 < i < len(self.lsf) - 1:
            a, b, c = self.lsf[i - 1:i + 2]
            denom = a - 2 * b + c
            if denom < 0:
                return b - 0.125 * (a - c) ** 2 / denom
        return self.lsf[i]

    def fwhm(self):
        """Distance between the outermost half-maximum crossings (linear interpolation).

        A defocused profile can have two horns, so the crossings are searched from the outside
        in, not from the maximum out.
        """
        half = 0.5 * self.peak()
        above = np.flatnonzero(self.lsf >= half)
        lo, hi = above[0], above[-1]
        if lo == 0 or hi == len(self.lsf) - 1:
            raise ValueError("cross-section sampled too narrowly to reach half maximum")
        y, f = self.offset_arcsec, self.lsf

        def crossing(i, j):
            return y[i] + (half - f[i]) * (y[j] - y[i]) / (f[j] - f[i])

        return crossing(hi, hi + 1) - crossing(lo - 1, lo)


def line_spread(profile, pixel_scale_arcsec=None, step_arcsec=None, pixel_angle_deg=0.0,
                period_factor=1.0):
    """Line-spread function of ``profile`` across the track (its marginal along track-frame x).

    Parameters
    ----------
    profile : galsim.GSObject
        Stationary profile in the track frame, arcsec.
    pixel_scale_arcsec : float, optional
        Include the response of square pixels of this size. ``pixel_angle_deg`` is the angle of
        the track to the pixel rows: the pixel's projection across the track is then a trapezoid,
        the convolution of boxes ``p |cos a|`` and ``p |sin a|``.
    step_arcsec : float, optional
        Output sampling; by default fine enough for every feature GalSim keeps (``maxk``).
    period_factor : float
        The transform's period in units of GalSim's ``2 pi / stepk``: the tails folded back
        into the output fall as ``period^(-8/3)`` for Kolmogorov seeing.

    Returns
    -------
    CrossSection
    """
    step = _lsf_step(profile, pixel_scale_arcsec, step_arcsec)
    slice_k, ky, dk = _k_slice(profile, step, period_factor)
    return _cross_section(slice_k, ky, dk, step, pixel_scale_arcsec, pixel_angle_deg)


def line_spreads(profile, pixel_scale_arcsec, step_arcsec=None, period_factor=1.0):
    """The line-spread functions without and with pixel response from one drawn transform.

    The same as :func:`line_spread` of ``profile`` without pixels and with pixels of
    ``pixel_scale_arcsec`` aligned with the track, both sampled at the step the pixelated one
    takes (``step_arcsec`` capped at ``pixel_scale_arcsec / 16``): the profile's transform,
    the expensive part, is drawn once for both.

    Returns
    -------
    bare, pixelated : CrossSection
    """
    step = _lsf_step(profile, pixel_scale_arcsec, step_arcsec)
    slice_k, ky, dk = _k_slice(profile, step, period_factor)
    return (_cross_section(slice_k, ky, dk, step),
            _cross_section(slice_k, ky, dk, step, pixel_scale_arcsec))


def _lsf_step(profile, pixel_scale_arcsec, step_arcsec):
    """The sampling of :func:`line_spread`, arcsec."""
    step = np.pi / profile.maxk / 2 if step_arcsec is None else step_arcsec
    if pixel_scale_arcsec is not None:
        step = min(step, pixel_scale_arcsec / 16)
    return step


def _k_slice(profile, step, period_factor):
    """The profile's transform on the ky axis (kx = 0) for samples ``step`` apart over the
    period ``period_factor`` times ``2 pi / stepk``: the values, their ky and spacing dk."""
    period = period_factor * 2 * np.pi / profile.stepk
    n = int(2 ** np.ceil(np.log2(max(period / step, 64))))
    dk = 2 * np.pi / (n * step)
    slice_k = _k_column(profile, n, dk)  # rows run ky = -n/2 .. n/2-1
    ky = (np.arange(n) - n // 2) * dk
    return slice_k, ky, dk


#: GalSim profiles that fill a centred k-image from ky = 0 outward by symmetry when drawn
#: without a Jacobian, so that the kx = 0 column drawn alone holds the values it has in a wider
#: image (tests/test_profile.py checks each, bit for bit).
_COLUMN_ALONE = (galsim.Kolmogorov, galsim.VonKarman, galsim.TopHat, galsim.Gaussian)


def _k_column(profile, n, dk):
    """The kx = 0 column of ``profile.drawKImage(nx=2, ny=n, scale=dk)``, bit for bit.

    The column of the two-column image is the one of the profile drawn alone where that gives
    the same values (:func:`_draws_column_alone`); a sum or convolution of parts is the sum or
    product, in GalSim's order, of its parts' columns (GalSim combines their images element by
    element); anything else is drawn in two columns as the plain call would. An axisymmetric
    part drawn alone costs a fifth to a seventh of its two columns (the kx = -dk column
    has no symmetry to fill it from).
    """
    if _draws_column_alone(profile):
        image = galsim.ImageCD(galsim.BoundsI(0, 0, -(n // 2), n // 2 - 1), scale=dk)
        return profile.drawKImage(image=image).array[:, 0]
    if type(profile) in (galsim.Convolution, galsim.Sum):
        columns = [_k_column(part, n, dk) for part in profile.obj_list]
        combined = np.ascontiguousarray(columns[0])
        for column in columns[1:]:
            if type(profile) is galsim.Convolution:
                combined *= column
            else:
                combined += column
        return combined
    return profile.drawKImage(nx=2, ny=n, scale=dk).array[:, 1]


def _draws_column_alone(profile):
    """Whether ``profile`` drawn in the kx = 0 column alone gives that column's values in any
    wider centred image: an axisymmetric profile of :data:`_COLUMN_ALONE`, one scaled in flux
    alone (a transformation whose GalSim ``_jac`` is None and with no offset: with a Jacobian,
    even the identity, GalSim steps through k from the image's corner, so the column's values
    depend on where the image starts), or sums and convolutions of these."""
    if type(profile) in _COLUMN_ALONE:
        return True
    if type(profile) is galsim.Transformation:
        unshifted = profile.offset.x == 0 and profile.offset.y == 0
        return (getattr(profile, "_jac", False) is None and unshifted
                and _draws_column_alone(profile.original))
    if type(profile) in (galsim.Convolution, galsim.Sum):
        return all(_draws_column_alone(part) for part in profile.obj_list)
    return False


def _cross_section(slice_k, ky, dk, step, pixel_scale_arcsec=None, pixel_angle_deg=0.0):
    """The :class:`CrossSection` of a transform on the ky axis (:func:`_k_slice`), times the
    pixel response if ``pixel_scale_arcsec`` is given."""
    n = len(slice_k)
    if pixel_scale_arcsec is not None:
        a = np.radians(pixel_angle_deg)
        for width in (pixel_scale_arcsec * abs(np.cos(a)), pixel_scale_arcsec * abs(np.sin(a))):
            # No width (a track along a pixel axis) is sinc(0) at every ky: one number.
            slice_k = slice_k * (np.sinc(ky * width / (2 * np.pi)) if width else np.sinc(0.0))
    lsf = np.fft.fftshift(np.fft.ifft(np.fft.ifftshift(slice_k))).real * n * dk / (2 * np.pi)
    offsets = (np.arange(n) - n // 2) * step
    return CrossSection(offsets, lsf)
