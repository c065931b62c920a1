"""Sweep a stationary profile along a track onto the pixel grid, at a cost set by the streak's
footprint.

The streak is the profile ``f`` swept along a straight track, so a pixel centred at track-frame
coordinates ``(t, d)`` (``t`` along the track from its start, ``d`` across) collects

    V(t, d) = F p [C(t, d) - C(t - L, d)],   C(t, d) = integral_{-inf}^{t} h(t', d) dt'

where ``F`` is the charge per pixel of track length, ``L`` the track length, ``p`` the pixel scale
and ``h`` the profile convolved with the (rotated) square pixel. Far from the ends ``C`` is the
line-spread function ``LSF(d)``: one 1-D function for the whole interior. Near the ends ``C`` is
tabulated once per profile and angle on a fine grid by an exact spectral antiderivative of ``h``
(computed from the profile's 2-D Fourier transform) and interpolated by cubic splines. Nothing is
drawn on pixels the streak cannot reach: the support across and along the track follows from an
accuracy budget.
"""
from dataclasses import dataclass, field

import galsim
import numpy as np
from scipy import fft, ndimage

from .profile import line_spread
from .errors import InputError
from .validate import positive


#: Finest pixel tolerance the renderer can honour: the LSF's own aliasing at GSPARAMS
#: (folding_threshold 1e-4) is ~1e-6 of the peak.
MIN_TOLERANCE = 2e-6

#: Largest end-cap table (samples on a side) before the renderer stops widening it and
#: reports the mismatch it reached as its predicted error instead.
MAX_TABLE_SIZE = 4096


@dataclass(frozen=True)
class Budget:
    """Accuracy budget of the fast renderer (the analogue of GalSim's ``GSParams``).

    Parameters
    ----------
    tolerance : float
        Target for the largest pixel error, as a fraction of the streak's peak pixel value.
        Sets the support (pixels whose value is below ``tolerance / 2`` of the peak are not
        touched), the end-cap table's sampling and the LSF sampling.
    flux_tolerance : float
        Largest fraction of the streak's charge that may fall outside the footprint. Seeing
        profiles have power-law tails (Kolmogorov's LSF falls as ``d^(-8/3)``), so this, not
        ``tolerance``, usually sets the support.
    """

    tolerance: float = 5e-5
    flux_tolerance: float = 5e-5

    def __post_init__(self):
        positive("tolerance", self.tolerance)
        positive("flux_tolerance", self.flux_tolerance)
        if self.tolerance < MIN_TOLERANCE:
            raise InputError("tolerance", self.tolerance,
                             f"must be >= {MIN_TOLERANCE:g}, the accuracy of the line-spread "
                             f"function at inject.profile.GSPARAMS")


@dataclass(frozen=True)
class RenderPlan:
    """What the budget decided for one profile and angle, and the error it predicts.

    Attributes
    ----------
    support_px : float
        Half-width of the footprint across the track.
    cap_px : float
        Reach of each end cap along the track beyond the segment's end points.
    table_step_px : float
        Sampling of the end-cap table.
    lsf_step_px : float
        Sampling of the interior line-spread function.
    predicted_error : dict
        Predicted largest pixel error of each approximation, relative to the peak.
    """

    support_px: float
    cap_px: float
    table_step_px: float
    lsf_step_px: float
    predicted_error: dict = field(default_factory=dict)

    @property
    def total_predicted_error(self):
        return float(sum(self.predicted_error.values()))


def _extent(cross_section, threshold, flux_fraction):
    """Half-width outside which a cross-section is below ``threshold`` times its peak and
    holds less than ``flux_fraction`` of its integral."""
    y, f = cross_section.offset_arcsec, cross_section.lsf
    above = np.flatnonzero(f > threshold * f.max())
    by_value = np.max(np.abs(y[above[[0, -1]]]))
    # Flux outside +-k steps: the sum left of centre - k plus the sum right of centre + k.
    left, right = np.cumsum(f), np.cumsum(f[::-1])[::-1]
    centre = len(f) // 2  # offset 0
    k = np.arange(centre - 1)
    outside = (left[centre - k - 1] + right[centre + k + 1]) * cross_section.step
    enough = np.flatnonzero(outside <= flux_fraction)
    by_flux = (enough[0] if len(enough) else centre) * cross_section.step
    return float(max(by_value, by_flux))


class SweptProfile:
    """The interior LSF and the end-cap table of one profile at one track angle.

    Build once, render any number of segments at that angle (e.g. all CCDs a track crosses).

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux stationary profile in the track frame (arcsec, motion along +x).
    pixel_scale : float
        Arcsec per pixel.
    angle_deg : float
        Track angle on the pixel grid (the pixel's orientation relative to the track matters).
    budget : Budget
    """

    def __init__(self, profile, pixel_scale, angle_deg, budget=Budget()):
        self.profile, self.pixel_scale, self.budget = profile, float(pixel_scale), budget
        self.angle_deg = float(angle_deg)
        tol, p = budget.tolerance, self.pixel_scale
        # Interior: the LSF with the pixel's projection across the track; sampled so linear
        # interpolation errs by < tol/8 of the peak (error ~ step^2 |f''| / 8).
        coarse = line_spread(profile, p, pixel_angle_deg=self.angle_deg)
        curvature = np.abs(np.diff(coarse.lsf, 2)).max() / coarse.step ** 2
        lsf_step = min(p / 8, np.sqrt(tol * coarse.lsf.max() / curvature))
        self.lsf = line_spread(profile, p, step_arcsec=lsf_step, pixel_angle_deg=self.angle_deg)
        self._peak = self.lsf.lsf.max()
        # Along the track: the marginal across it, and its cumulative, for the far tails.
        along = line_spread(profile.rotate(90 * galsim.degrees), p,
                            pixel_angle_deg=self.angle_deg + 90)
        self._along_t = along.offset_arcsec
        self._along_cdf = np.cumsum(along.lsf) * along.step
        # Across, the footprint must hold all but flux_tolerance of the charge (seeing tails
        # are power laws); the end-cap table only where values exceed tol/2 of the peak.
        # Either way flux is conserved: C rises from 0 to LSF(d) whatever the cap model.
        support = _extent(self.lsf, tol / 2, budget.flux_tolerance) + p
        self._cap = _extent(along, tol / 2, 1.0) + p
        self._table_d = _extent(self.lsf, tol / 2, 1.0) + p
        # The marginal along the track bounds the cap only roughly (it is not the tail of
        # h(t, d) at fixed d): trim the table where its ends match 0 and LSF(d) within tol/2,
        # and widen it if that was not far enough.
        while True:
            step, mismatch, size = self._build_cap_table(tol / 2)
            if mismatch <= tol / 2 or size * 1.5 > MAX_TABLE_SIZE:
                break
            self._cap *= 1.5
        self.plan = RenderPlan(
            support_px=support / p, cap_px=self._cap / p, table_step_px=step / p,
            lsf_step_px=lsf_step / p,
            predicted_error={"support": tol / 2, "lsf_interpolation": tol / 8,
                             "cap_tails": tol / 2, "cap_table": mismatch})

    def _build_cap_table(self, trim):
        """Tabulate ``C(t, d)`` for ``|t| <= cap``, ``|d| <= table_d`` (arcsec), then trim the
        cap to where ``C`` is within ``trim`` (relative to the peak) of 0 before it and of
        ``LSF(d)`` after it.

        Returns the table step, the table's largest mismatch with 0 at its start and with
        the interior LSF at its far end (relative to the peak: a direct measure of its
        error), and the transform size used.
        """
        p = self.pixel_scale
        # Cubic-spline interpolation errs by ~ step^4 |f""""| / 384: sample on the scale of the
        # finest feature GalSim keeps (pi / maxk), never coarser than p / 4.
        step = min(p / 4, max(np.pi / self.profile.maxk, p / 16))
        # A period three times the table (GalSim samples k on a square grid), so the table
        # stays clear of the tails wrapped around from the other end.
        n = fft.next_fast_len(int(3 * max(self._cap, self._table_d) / step) + 16)
        n_t = n_d = n
        dk_t = dk_d = 2 * np.pi / (n * step)
        # The profile is real, so the half plane kt >= 0 holds its whole transform.
        kimage = galsim.ImageCD(galsim.BoundsI(0, n // 2, -(n // 2), n - n // 2 - 1))
        spectrum = self.profile.drawKImage(image=kimage, scale=dk_t, recenter=False).array
        kt = np.arange(n_t // 2 + 1)[None, :] * dk_t
        kd = (np.arange(n_d) - n_d // 2)[:, None] * dk_d
        a = np.radians(self.angle_deg)
        # Unit square pixel in the track frame: its x axis is (cos a, -sin a), its y axis
        # (sin a, cos a); its transform is a product of sincs along those axes.
        spectrum *= np.sinc((kt * np.cos(a) - kd * np.sin(a)) * p / (2 * np.pi))
        spectrum *= np.sinc((kt * np.sin(a) + kd * np.cos(a)) * p / (2 * np.pi))
        # Back to real space across the track: coeffs[d, m] are the transforms along t.
        coeffs = fft.fftshift(fft.ifft(fft.ifftshift(spectrum, axes=0), axis=0), axes=0)
        coeffs *= n_d * dk_d / (2 * np.pi)
        del spectrum
        lsf = coeffs[:, 0].real.copy()  # the kt = 0 term is the integral along t
        # Exact antiderivative of the trigonometric series along t, from t = -period/2.
        km = kt[0]
        coeffs[:, 1:] /= 1j * km[1:]
        coeffs[:, 0] = 0.0
        if n_t % 2 == 0:
            coeffs[:, -1] = 0.0  # the Nyquist term has no antiderivative on the grid
        periodic = fft.fftshift(fft.irfft(coeffs, n=n_t, axis=1), axes=1) * n_t * dk_t / (2 * np.pi)
        t = (np.arange(n_t) - n_t // 2) * step
        d = (np.arange(n_d) - n_d // 2) * step
        table = periodic - periodic[:, :1] + np.outer(lsf, (t + n_t * step / 2) / (n_t * step))
        keep_d = np.abs(d) <= self._table_d + 3 * step
        table = table[keep_d]
        far = np.interp(d[keep_d], self.lsf.offset_arcsec, self.lsf.lsf)
        # Largest |t| where C still differs from its limit by more than ``trim``.
        off = np.where(t < 0, np.abs(table).max(axis=0),
                       np.abs(table - far[:, None]).max(axis=0)) > trim * self._peak
        inside = np.abs(t) <= self._cap
        if off[inside].any():
            self._cap = min(self._cap, float(np.abs(t[inside & off]).max()) + step)
        keep_t = np.abs(t) <= self._cap + 3 * step
        table = table[:, keep_t]
        self._table = ndimage.spline_filter(table, order=3)
        self._t0, self._d0, self._table_step = t[keep_t][0], d[keep_d][0], step
        ends = max(np.abs(table[:, -1] - far).max(), np.abs(table[:, 0]).max())
        return step, float(ends / self._peak), n

    def _cap_cumulative(self, t, d, inner):
        """``C(t, d)`` for ``|t| <= cap`` (arcsec), given ``inner = LSF(d)``."""
        out = np.empty_like(t)
        in_table = np.abs(d) <= self._table_d
        if in_table.any():
            coords = np.vstack(((d[in_table] - self._d0) / self._table_step,
                                (t[in_table] - self._t0) / self._table_step))
            out[in_table] = ndimage.map_coordinates(self._table, coords, order=3,
                                                    prefilter=False, mode="nearest")
        # Far from the track the cap is below tol/2 of the peak: a separable model is enough.
        tails = ~in_table
        out[tails] = inner[tails] * np.interp(t[tails], self._along_t, self._along_cdf)
        return out

    def _cumulative(self, t, d, inner):
        """``C(t, d)`` anywhere: 0 before the cap, ``LSF(d)`` after it."""
        out = np.where(t > self._cap, inner, 0.0)
        near = np.abs(t) <= self._cap
        if near.any():
            out[near] = self._cap_cumulative(t[near], d[near], inner[near])
        return out

    def pixel_values(self, t_px, d_px, length_px):
        """Charge fraction ``V / F`` at track-frame pixel coordinates, for a track of length
        ``length_px`` starting at ``t = 0``."""
        p = self.pixel_scale
        t, d = t_px * p, d_px * p
        inner = np.interp(d, self.lsf.offset_arcsec, self.lsf.lsf)
        # Most pixels see the whole profile pass: C(t) = LSF(d) and C(t - L) = 0.
        ends = (t <= self._cap) | (t >= length_px * p - self._cap)
        values = inner.copy()
        if ends.any():
            te, de, ie = t[ends], d[ends], inner[ends]
            values[ends] = (self._cumulative(te, de, ie)
                            - self._cumulative(te - length_px * p, de, ie))
        values *= p
        return values


def footprint(shape, segment, support_px, cap_px):
    """Pixels within ``support_px`` of a segment and ``cap_px`` beyond its ends.

    Returns ``(y, x, t, d)``: integer pixel indices and their track-frame coordinates.
    """
    ny, nx = shape
    c, s = segment.direction
    horizontal = abs(c) >= abs(s)
    # Walk along the major axis; on each line, the pixels within the band across it.
    (major_n, minor_n) = (nx, ny) if horizontal else (ny, nx)
    (m0, n0, dm, dn) = ((segment.x0, segment.y0, c, s) if horizontal
                        else (segment.y0, segment.x0, s, c))
    ends = [m0 - cap_px * dm, m0 + (segment.length + cap_px) * dm]
    reach = support_px * abs(dn)  # the band's extent along the major axis, from its slant
    lo = max(0, int(np.floor(min(ends) - reach)))
    hi = min(major_n - 1, int(np.ceil(max(ends) + reach)))
    if hi < lo:
        return (np.empty(0, int),) * 2 + (np.empty(0),) * 2
    major = np.arange(lo, hi + 1)
    centre = n0 + (major - m0) * dn / dm
    half = support_px / abs(dm)
    start = np.clip(np.floor(centre - half).astype(int), 0, minor_n)
    stop = np.clip(np.ceil(centre + half).astype(int) + 1, 0, minor_n)
    counts = np.maximum(stop - start, 0)
    major = np.repeat(major, counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    minor = np.repeat(start, counts) + offsets
    x, y = (major, minor) if horizontal else (minor, major)
    t = (x - segment.x0) * c + (y - segment.y0) * s
    d = -(x - segment.x0) * s + (y - segment.y0) * c
    keep = (np.abs(d) <= support_px) & (t >= -cap_px) & (t <= segment.length + cap_px)
    return y[keep], x[keep], t[keep], d[keep]


@dataclass(frozen=True)
class RenderResult:
    """What one rendered segment touched: the pixels, the charge added, the plan used."""

    n_pixels: int
    charge_added: float
    plan: RenderPlan


def render_segment(image, swept, segment, flux_per_px):
    """Add one segment's streak charge into ``image`` (in place).

    Parameters
    ----------
    image : ndarray
        2-D float array, indexed ``[y, x]``; accumulated in float64 and added once.
    swept : SweptProfile
        Profile and angle; ``segment.angle_deg`` must equal ``swept.angle_deg``.
    segment : Segment
    flux_per_px : float
        Charge per pixel of track length, e-.

    Returns
    -------
    RenderResult
    """
    if not np.isclose(segment.angle_deg, swept.angle_deg, rtol=0, atol=1e-9):
        raise ValueError("segment angle differs from the SweptProfile's angle")
    plan = swept.plan
    y, x, t, d = footprint(image.shape, segment, plan.support_px, plan.cap_px)
    values = flux_per_px * swept.pixel_values(t, d, segment.length)
    # Footprint pixels are unique, so a plain fancy-indexed add is safe (no np.add.at).
    image.reshape(-1)[y * image.shape[1] + x] += values
    return RenderResult(len(values), float(values.sum()), plan)


def render_streak(image, model, segment, budget=Budget()):
    """Render a :class:`~inject.streak.StreakModel` along a segment into ``image``."""
    swept = SweptProfile(model.profile, model.pixel_scale, segment.angle_deg, budget)
    return render_segment(image, swept, segment, model.flux_per_px)
