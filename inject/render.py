"""Sweep a stationary profile along a track onto the pixel grid, at a cost set by the streak's
footprint.

The streak is the profile ``f`` swept along a straight track, so a pixel centred at track-frame
coordinates ``(t, d)`` (``t`` along the track from its start, ``d`` across) collects

    V(t, d) = F p [C(t, d) - C(t - L, d)],   C(t, d) = integral_{-inf}^{t} h(t', d) dt'

where ``F`` is the charge per pixel of track length, ``L`` the track length, ``p`` the pixel scale
and ``h`` the profile convolved with the (rotated) square pixel. Far from the ends ``C`` is the
line-spread function ``LSF(d)``: one 1-D function for the whole interior. Near the ends ``C`` is
tabulated once per profile and angle on a fine grid by an exact spectral antiderivative of ``h``
(computed from the profile's 2-D Fourier transform) and interpolated by cubic splines; what the
table misses of 0 and ``LSF(d)`` at its ends (tails beyond it) is taken off over smooth ramps,
so ``C`` meets its limits exactly and every track, however short, keeps its flux. Nothing is
drawn on pixels the streak cannot reach: the support across and along the track follows from an
accuracy budget.

The profile is given in the track frame, so the track angle enters the tables only through the
orientation of the square pixel there, which repeats every 90 deg; and as the square's second
moments are isotropic, tables change with that orientation only at fourth order (~cos 4a).
:func:`swept_profile` therefore builds tables on a grid of orientations whose step is measured
per profile and budget (:func:`orientation_slope`, :func:`orientation_step`) so that snapping
adds at most :data:`ORIENTATION_FRACTION` of the tolerance: streaks at all-different angles
share a few tables. The pixel coordinates along and across the track always use the track's
own angle.
"""
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import galsim
import numpy as np
from scipy import ndimage

from inject.errors import InputError
from inject.profile import line_spread
from inject.validate import positive

#: Finest pixel tolerance the renderer accepts (at 5e-7 it agrees with GalSim's Box FFT of a
#: whole CCD to 1.5e-7 of the peak; such budgets cost seconds per profile).
MIN_TOLERANCE = 2e-7

#: Tightest tolerance chosen automatically (a bright streak in noise, a short track's own
#: peak): it keeps a profile's tables to about a second; tighter ones must be asked for.
AUTO_MIN_TOLERANCE = 2e-6

#: Tail of the LSF folded back by a transform of GalSim's period (folding_threshold 1e-4 in
#: inject.profile.GSPARAMS), relative to its peak.
FOLDED_LSF = 1e-6

#: Tracks shorter than this (px) have their tolerance checked against their own peak
#: (:func:`short_track_budget`); no seeing profile is wide enough for longer ones to matter.
SHORT_TRACK_CHECK_PX = 1000.0

#: Largest end-cap table (samples on a side) before the renderer stops widening it and
#: reports the mismatch it reached as its predicted error instead.
MAX_TABLE_SIZE = 4096

#: Tightened tolerances (noise, short tracks) are rounded down to this grid of powers of two,
#: so streaks of different brightness or length share tables: a scene of magnitudes 1-9
#: builds 5 tables between AUTO_MIN_TOLERANCE and the default (19 at quarter octaves, whose
#: tightest few cost as much as all of these), each at most twice as tight as needed.
TOLERANCE_STEPS_PER_OCTAVE = 1

#: Largest error that snapping a track's pixel orientation to a grid may add, as a fraction of
#: the budget's tolerance (see :func:`orientation_step`).
ORIENTATION_FRACTION = 0.25

#: Margin on the measured orientation slope (:func:`orientation_slope`): for the secant
#: slopes between its samples against the steepest tangent, and its coarse periodic grid.
ORIENTATION_SAFETY = 2.0

#: Pixel orientations (over 90 deg) at which :func:`orientation_slope` measures the tables.
ORIENTATION_SAMPLES = 24

#: Most orientation steps over 90 deg; a profile that needs finer ones uses exact angles.
MAX_ORIENTATION_STEPS = 3600


def snap_tolerance(tolerance):
    """Round a tolerance down to the grid of :data:`TOLERANCE_STEPS_PER_OCTAVE` steps per
    factor of two: never looser than asked, and a discrete key for shared tables."""
    if not tolerance > 0:  # a zero-length (or invalid) track: the callers clamp it
        return float(tolerance)
    n = TOLERANCE_STEPS_PER_OCTAVE
    snapped = 2.0 ** (np.floor(np.log2(tolerance) * n + 1e-9) / n)
    return float(min(tolerance, snapped))


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
                             f"must be >= {MIN_TOLERANCE:g} (inject.render.MIN_TOLERANCE)")


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
    dropped : tuple of str
        Profile components left out because they cannot change the streak beyond the
        budget (see :meth:`inject.streak.StreakModel.render_profile`).
    """

    support_px: float
    cap_px: float
    table_step_px: float
    lsf_step_px: float
    predicted_error: dict = field(default_factory=dict)
    dropped: tuple = ()

    @property
    def total_predicted_error(self):
        return float(sum(self.predicted_error.values()))


class _UniformInterp:
    """``np.interp`` on a uniform grid by index arithmetic: no binary search, ~5x faster on
    the millions of footprint pixels that each need ``LSF(d)``. Clamps outside like
    ``np.interp``."""

    def __init__(self, grid, values):
        self.start, self.step = float(grid[0]), float(grid[1] - grid[0])
        self.values = np.asarray(values, dtype=float)
        self.slopes = np.append(np.diff(self.values), 0.0)

    def __call__(self, x):
        q = x - self.start
        q *= 1.0 / self.step
        np.clip(q, 0.0, len(self.values) - 1, out=q)
        i = q.astype(np.intp)
        q -= i
        q *= self.slopes.take(i)
        q += self.values.take(i)
        return q


class UniformSpline:
    """The cubic B-spline interpolating ``values`` sampled ``step`` apart from ``start``
    (ndimage's, mirrored about the end samples: flat there, as a cumulative whose tails have
    run out is), and its exact antiderivative from the first sample.

    The antiderivative of ``sum_j c_j B3(u - j)`` is ``sum_j C_j B4(u - j - 1/2)`` with
    ``C_j`` the running sum of the ``c_j`` (``B4' (x) = B3(x + 1/2) - B3(x - 1/2)``): a
    quartic B-spline, which ndimage evaluates as it does the cubic.
    """

    PAD = 3  # coefficients beyond each end that the quartic's support reaches

    def __init__(self, start, step, values):
        self.start, self.step = float(start), float(step)
        self.coeffs = ndimage.spline_filter1d(np.asarray(values, float), order=3, mode="mirror")
        c, pad = self.coeffs, self.PAD
        mirrored = np.concatenate((c[pad:0:-1], c, c[-2:-2 - pad:-1]))
        self._running = np.cumsum(mirrored)
        self._origin = self._quartic(np.zeros(1))[0]

    def _grid(self, x):
        return (np.atleast_1d(np.asarray(x, float)) - self.start) / self.step

    def _quartic(self, u):
        return ndimage.map_coordinates(self._running, [u + self.PAD - 0.5], order=4,
                                       prefilter=False, mode="nearest")

    def __call__(self, x):
        u = self._grid(x)
        values = ndimage.map_coordinates(self.coeffs, [u], order=3, prefilter=False,
                                         mode="mirror")
        return values if np.ndim(x) else values[0]

    def antiderivative(self, x):
        """The integral of the spline from ``start`` to ``x``."""
        values = self.step * (self._quartic(self._grid(x)) - self._origin)
        return values if np.ndim(x) else values[0]


def next_fast_length(n):
    """The smallest length ``>= n`` whose only prime factors are 2, 3, 5, 7 and 11: the
    lengths pocketfft transforms fastest (what ``scipy.fft.next_fast_len`` gives)."""
    n = max(int(n), 1)
    best = 1 << (n - 1).bit_length()  # a power of two always qualifies
    odd = [1]  # the products of 3, 5, 7 and 11 below best
    for prime in (3, 5, 7, 11):
        odd = [m * prime ** e for m in odd for e in range(best.bit_length())
               if m * prime ** e < best]
    for m in odd:
        while m < n:
            m *= 2
        best = min(best, m)
    return best


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
    """The interior LSF and the end-cap table of one profile at one pixel orientation.

    Build once, render any number of segments at that angle (e.g. all CCDs a track crosses),
    or within ``angle_tolerance_deg`` of it (modulo 90 deg).

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux stationary profile in the track frame (arcsec, motion along +x).
    pixel_scale : float
        Arcsec per pixel.
    angle_deg : float
        Track angle on the pixel grid. Only the square pixel's orientation in the track frame
        depends on it, and the square is the same every 90 deg: the tables are built at
        ``angle_deg % 90`` (kept as :attr:`angle_deg`), so angles 90 deg apart give identical
        tables.
    budget : Budget
    angle_tolerance_deg : float
        Segments whose angle is this close to ``angle_deg`` (modulo 90 deg) may be rendered
        with these tables (see :func:`orientation_step`); 0 (the default) asks for the same
        orientation.
    angle_error : float
        Largest pixel error that rendering such a segment may add, relative to the peak;
        goes into the plan's ``predicted_error`` as ``"orientation"``.
    """

    def __init__(self, profile, pixel_scale, angle_deg, budget=Budget(), angle_tolerance_deg=0.0,
                 angle_error=0.0):
        self.profile, self.pixel_scale, self.budget = profile, float(pixel_scale), budget
        self.angle_deg = float(angle_deg) % 90.0  # the pixel orientation: period 90 deg
        self.angle_tolerance_deg = float(angle_tolerance_deg)
        tol, p = budget.tolerance, self.pixel_scale
        # Interior: the LSF with the pixel's projection across the track; sampled so linear
        # interpolation errs by < tol/8 of the peak (error ~ step^2 |f''| / 8).
        coarse = line_spread(profile, p, pixel_angle_deg=self.angle_deg)
        curvature = np.abs(np.diff(coarse.lsf, 2)).max() / coarse.step ** 2
        lsf_step = min(p / 8, np.sqrt(tol * coarse.lsf.max() / curvature))
        # GalSim's period (folding_threshold 1e-4) folds ~FOLDED_LSF of the peak back into
        # the LSF: budgets tighter than twice that take a longer one (folding falls as
        # period^(-8/3) for Kolmogorov tails).
        fold = max(1.0, (2 * FOLDED_LSF / tol) ** (3 / 8))
        self.lsf = line_spread(profile, p, step_arcsec=lsf_step, pixel_angle_deg=self.angle_deg,
                               period_factor=fold)
        self._lsf_at = _UniformInterp(self.lsf.offset_arcsec, self.lsf.lsf)
        self._peak = self.lsf.lsf.max()
        # Along the track: the marginal across it, whose cumulative makes the separable model.
        along = line_spread(profile.rotate(90 * galsim.degrees), p,
                            pixel_angle_deg=self.angle_deg + 90, period_factor=fold)
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
            step, mismatch, size = self._build_cap_table(tol / 2, along)
            if mismatch <= tol / 2 or size * 1.5 > MAX_TABLE_SIZE:
                break
            self._cap *= 1.5
        self.plan = RenderPlan(
            support_px=support / p, cap_px=self._cap / p, table_step_px=step / p,
            lsf_step_px=lsf_step / p,
            predicted_error={"support": tol / 2, "lsf_interpolation": tol / 8,
                             "cap_tails": tol / 2, "cap_table": mismatch})
        if self.angle_tolerance_deg > 0:
            self.plan.predicted_error["orientation"] = float(angle_error)

    def _separable_model(self, along):
        """The separable end-cap model ``LSF(d) Phi(t)``, ``Phi`` the along-track marginal's
        cumulative: the whole cap far from the track (``|d| > table_d``), and the base the
        tables' residuals are added to near it.

        ``Phi`` is rescaled to rise from 0 to 1 exactly across ``[-cap, cap]``, so C and its
        antiderivative K join their limits (0 before, ``LSF`` and ``t LSF - m1`` after)
        continuously: flux then stays exact for constant and linearly varying tracks alike.
        """
        t, f = along.offset_arcsec, along.lsf
        inside = np.abs(t) <= self._cap
        t, f = t[inside], f[inside]
        cdf = np.concatenate(([0.0], np.cumsum(np.diff(t) * (f[1:] + f[:-1]) / 2.0)))
        # A cubic spline, not linear interpolation: the tables hold C - LSF(d) Phi(t), and
        # Phi's kinks would show through their splines at ~step^2 Phi'' (2e-5 of the peak).
        self._phi = UniformSpline(t[0], t[1] - t[0], cdf / cdf[-1])
        self._psi = self._phi.antiderivative  # 0 at the first sample
        # K(cap) = cap - m1 per unit LSF: the first moment that keeps K continuous at +cap.
        self._along_moment = float(self._cap - self._psi(self._cap))

    def _along_integral(self, t, power):
        """``Phi(t)`` (``power`` 0) or its integral from ``-cap`` (``power`` 1), continued by
        their limits beyond ``+-cap``."""
        inside = np.clip(t, -self._cap, self._cap)
        if power == 0:
            return np.where(np.abs(t) <= self._cap, self._phi(inside), (t > 0).astype(float))
        return np.where(t > self._cap, t - self._along_moment,
                        np.where(t < -self._cap, 0.0, self._psi(inside)))

    def _build_cap_table(self, trim, along):
        """Tabulate ``C(t, d)`` for ``|t| <= cap``, ``|d| <= table_d`` (arcsec), then trim the
        cap to where ``C`` is within ``trim`` (relative to the peak) of 0 before it and of
        ``LSF(d)`` after it.

        Returns the table step, the table's largest mismatch with 0 at its start and with
        the interior LSF at its far end (relative to the peak: a direct measure of its
        error), and the transform size used.
        """
        p = self.pixel_scale
        # Cubic-spline interpolation errs by ~ step^4 |f""""| / 384: sample the finest feature
        # GalSim keeps (pi / maxk, down to p / 16), never coarser than p / 4, and at least 24
        # samples per FWHM of the pixel-convolved LSF (a 0.3" seeing profile needs ~p / 16).
        step = min(p / 4, max(np.pi / self.profile.maxk, p / 16), self.lsf.fwhm() / 24)
        # Periods three times the table's extents, so the table stays clear of the tails
        # wrapped around from the other end.
        n_t = next_fast_length(int(3 * self._cap / step) + 16)
        n_d = next_fast_length(int(3 * self._table_d / step) + 16)
        dk_t, dk_d = 2 * np.pi / (n_t * step), 2 * np.pi / (n_d * step)
        # GalSim draws k-images on square grids: the profile stretched along t by
        # dk_t / dk_d, sampled every dk_d, is the profile sampled every dk_t along t.
        # The unit square pixel, in the track frame: rotated by -angle. GalSim multiplies the
        # components' transforms in C++ (faster than sincs over the grid in numpy).
        pixel = galsim.Pixel(p, gsparams=self.profile.gsparams).rotate(
            -self.angle_deg * galsim.degrees)
        stretched = galsim.Convolve(self.profile, pixel).transform(dk_t / dk_d, 0.0, 0.0, 1.0)
        # The profile is real, so the half plane kt >= 0 holds its whole transform.
        kimage = galsim.ImageCD(galsim.BoundsI(0, n_t // 2, -(n_d // 2), n_d - n_d // 2 - 1))
        spectrum = stretched.drawKImage(image=kimage, scale=dk_d, recenter=False).array
        spectrum *= self.profile.flux / stretched.flux
        # Back to real space across the track: coeffs[d, m] are the transforms along t.
        coeffs = np.fft.fftshift(np.fft.ifft(np.fft.ifftshift(spectrum, axes=0), axis=0), axes=0)
        coeffs *= n_d * dk_d / (2 * np.pi)
        t = (np.arange(n_t) - n_t // 2) * step
        d = (np.arange(n_d) - n_d // 2) * step
        keep_d = np.abs(d) <= self._table_d + 3 * step
        coeffs = coeffs[keep_d]
        far = np.interp(d[keep_d], self.lsf.offset_arcsec, self.lsf.lsf)
        table = self._antiderivative(coeffs, 1, t)
        # Largest |t| where C still differs from its limit by more than ``trim``.
        off = np.where(t < 0, np.abs(table).max(axis=0),
                       np.abs(table - far[:, None]).max(axis=0)) > trim * self._peak
        inside = np.abs(t) <= self._cap
        if off[inside].any():
            self._cap = min(self._cap, float(np.abs(t[inside & off]).max()) + step)
        # On the grid (t is symmetric about 0), with three samples beyond it for the spline.
        self._cap = step * np.ceil(self._cap / step - 1e-9)
        keep_t = np.abs(t) <= self._cap + 3.5 * step
        grid, table, t = t, table[:, keep_t], t[keep_t]
        edge = np.argmin(np.abs(t + self._cap)), np.argmin(np.abs(t - self._cap))
        misses = (table[:, edge[0]].copy(), table[:, edge[1]] - far)
        ends = max(np.abs(misses[0]).max(), np.abs(misses[1]).max())
        # What the ends miss of 0 and LSF(d) (tails beyond the cap, folding) is taken off
        # over a ramp of width w at each end, so C meets its limits exactly: no step, flux
        # kept. A track of length L then sees L / w of the miss, within the tolerance of its
        # own peak (~ L / FWHM) when w >= (miss / tol) FWHM.
        width = float(np.clip(ends / self._peak / (2 * trim) * along.fwhm(), 4 * p, self._cap))
        self._ramp = (width, misses)
        table -= self._ramp_correction(t, 0)
        # The table holds C - LSF(d) Phi(t): the separable model carries the LSF's sharp
        # profile across the track at every t, and what is left is smooth in d away from the
        # end point: a spline at the table's step interpolates it far better than C itself
        # (at tol 5e-7 the render agrees with GalSim's Box FFT of a whole CCD to 2e-7).
        self._separable_model(along)
        table -= far[:, None] * self._along_integral(t, 0)
        self._table = ndimage.spline_filter(table, order=3)
        self._t0, self._d0, self._table_step = t[0], d[keep_d][0], step
        self._second = None
        # K = int C is needed only for tracks whose brightness varies: built on first use.
        self._second_inputs = (coeffs, grid, keep_t, d[keep_d], far)
        return step, float(ends / self._peak), max(n_t, n_d)

    def _ramp_correction(self, t, power):
        """The correction taken off the table (``power`` 0) or its integral from ``-cap``
        (``power`` 1), per table row: smoothsteps ``S(u) = 3u^2 - 2u^3`` over the first and
        the last ``width`` of the table."""
        width, (start, end) = self._ramp
        u0, u1 = (t + self._cap) / width, (t - self._cap + width) / width
        c0, c1 = np.clip(u0, 0.0, 1.0), np.clip(u1, 0.0, 1.0)
        if power == 0:
            fade_out, fade_in = 1 - c0 * c0 * (3 - 2 * c0), c1 * c1 * (3 - 2 * c1)
        else:  # integrals of 1 - S and S, continued linearly beyond the ramps (the margins)
            fade_out = width * np.where(u0 < 0, u0, c0 - c0 ** 3 + c0 ** 4 / 2)
            fade_in = width * (c1 ** 3 - c1 ** 4 / 2 + np.maximum(u1 - 1, 0.0))
        return start[:, None] * fade_out + end[:, None] * fade_in

    @staticmethod
    def _antiderivative(coeffs, power, t):
        """First (C) or second (K = int C) antiderivative along t, from ``t[0]``, of the
        series whose coefficients along the track are ``coeffs[d, m]`` (m >= 0), exactly."""
        n_t = len(t)
        step = t[1] - t[0]
        period = n_t * step
        km = 2 * np.pi * np.arange(1, coeffs.shape[1]) / period
        scale = 1.0 / step  # irfft's 1/n times the continuous transform's n dk / (2 pi)
        series = []
        for p in range(1, power + 1):
            c = np.zeros_like(coeffs)
            c[:, 1:] = coeffs[:, 1:] / (1j * km) ** p
            if n_t % 2 == 0:
                c[:, -1] = 0.0  # the Nyquist term has no antiderivative on the grid
            series.append(np.fft.fftshift(np.fft.irfft(c, n=n_t, axis=1), axes=1) * scale)
        lsf = coeffs[:, :1].real  # the kt = 0 term is the integral along t
        tau = t - t[0]  # from the first sample (-period / 2 only when n_t is even)
        g1 = series[0]
        if power == 1:
            return g1 - g1[:, :1] + lsf * (tau / period)
        g2 = series[1]
        return g2 - g2[:, :1] - g1[:, :1] * tau + lsf * (tau ** 2 / (2 * period))

    def _table_at(self, table, d, t):
        """Cubic-spline value of an end-cap table (C or K) at track-frame ``(t, d)``."""
        coords = np.vstack(((d - self._d0) / self._table_step, (t - self._t0) / self._table_step))
        return ndimage.map_coordinates(table, coords, order=3, prefilter=False, mode="nearest")

    def _second_table(self):
        """Spline coefficients of K, built once, started at 0 at -cap and continued after
        +cap as ``t LSF(d) - m1(d)``: the antiderivative of the C the renderer uses (0 before
        -cap, the corrected table, LSF(d) after +cap), or linearly varying tracks would not
        conserve flux."""
        if self._second is None:
            coeffs, grid, keep_t, d, far = self._second_inputs
            t = grid[keep_t]
            second = (self._antiderivative(coeffs, 2, grid)[:, keep_t]
                      - self._ramp_correction(t, 1) - far[:, None] * self._along_integral(t, 1))
            second = ndimage.spline_filter(second, order=3)
            ones = np.ones_like(d)
            # Spline coefficients shift with a constant: start each row at 0 at -cap.
            second -= self._table_at(second, d, -self._cap * ones)[:, None]
            self._moment_d = d
            # K(cap) = LSF (cap - m1_separable) + residual(cap) = cap LSF - m1.
            self._moment = far * self._along_moment - self._table_at(second, d, self._cap * ones)
            self._second = second
        return self._second

    def _cumulatives(self, t, d, inner, want_second):
        """``C(t, d)`` and, if asked, ``K(t, d)`` (arcsec), given ``inner = LSF(d)``.

        Before the cap both vanish; after it ``C = LSF(d)`` and ``K = t LSF(d) - m1(d)``.
        """
        first = np.where(t > self._cap, inner, 0.0)
        second = None
        if want_second:
            moment = self._first_moment(d, inner)
            second = np.where(t > self._cap, t * inner - moment, 0.0)
        near = np.abs(t) <= self._cap
        if not near.any():
            return first, second
        tn, dn, inn = t[near], d[near], inner[near]
        # The separable model LSF(d) Phi(t), plus the table's residual near the track (far
        # from it the cap is below tol/2 of the peak and the model is enough).
        in_table = np.abs(dn) <= self._table_d
        values = inn * self._along_integral(tn, 0)
        values[in_table] += self._table_at(self._table, dn[in_table], tn[in_table])
        first[near] = values
        if want_second:
            values = inn * self._along_integral(tn, 1)
            values[in_table] += self._table_at(self._second_table(), dn[in_table],
                                               tn[in_table])
            second[near] = values
        return first, second

    def _first_moment(self, d, inner):
        """``m1(d) = integral of t h(t, d) dt``: from the table near the track, separable
        (LSF times the along-track marginal's mean) in the far wings."""
        table = np.abs(d) <= self._table_d
        self._second_table()
        return np.where(table, np.interp(d, self._moment_d, self._moment),
                        inner * self._along_moment)

    def pixel_values(self, t_px, d_px, length_px, flux0=1.0, flux1=None):
        """Charge at track-frame pixel coordinates for a track of ``length_px`` starting at
        ``t = 0`` whose charge per pixel of track goes linearly from ``flux0`` to ``flux1``
        (constant by default).

        With ``F(s) = F0 + g s``, ``V = p {F0 [C(t) - C(t - L)] + g [K(t) - K(t - L)
        - L C(t - L)]}`` where ``K`` is the antiderivative of ``C`` along the track.
        """
        p = self.pixel_scale
        t, d, length = t_px * p, d_px * p, length_px * p
        flux1 = flux0 if flux1 is None else flux1
        slope = (flux1 - flux0) / length if length > 0 else 0.0
        inner = self._lsf_at(d)
        # Most pixels see the whole profile pass: C(t) = LSF(d), C(t - L) = 0.
        values = flux0 * inner
        if slope:
            values += slope * (t * inner - self._first_moment(d, inner))
        ends = (t <= self._cap) | (t >= length - self._cap)
        if ends.any():
            te, de, ie = t[ends], d[ends], inner[ends]
            c_now, k_now = self._cumulatives(te, de, ie, bool(slope))
            c_then, k_then = self._cumulatives(te - length, de, ie, bool(slope))
            v = flux0 * (c_now - c_then)
            if slope:
                v += slope * (k_now - k_then - length * c_then)
            values[ends] = v
        values *= p
        return values


def orientation_slope(profile, pixel_scale, samples=ORIENTATION_SAMPLES):
    """How fast a swept profile changes with the pixel's orientation: the largest change of a
    pixel value per degree, relative to the streak's peak.

    The square pixel convolved with the profile is drawn in the track frame at ``samples``
    orientations over 90 deg (its period) on a grid around the core (4 FWHM of the LSF and
    2 px on each side; the change is a fourth derivative of the profile and lives there), and
    its exact spectral antiderivative along the track, ``C(t, d)``, taken as for the end-cap
    tables. A track of any length, at any ``t``, sees ``C(t) - C(t - L)``: the change between
    neighbouring orientations is bounded by the range of ``Delta C`` along the track at each
    ``d`` (and a track whose brightness varies linearly by the same at its larger end, by the
    second mean-value theorem). The largest such range over neighbours, per degree of their
    separation, is returned (a secant slope: :data:`ORIENTATION_SAFETY` covers the tangent).

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux stationary profile in the track frame.
    pixel_scale : float
        Arcsec per pixel.
    samples : int
        Orientations sampled over 90 deg.

    Returns
    -------
    float
        Per degree, relative to the peak of the LSF.
    """
    p = float(pixel_scale)
    lsf = line_spread(profile, p)
    step = min(p / 4, max(np.pi / profile.maxk, p / 16), lsf.fwhm() / 24)  # as the tables
    n = next_fast_length(int(2 * (4 * lsf.fwhm() + 2 * p) / step) + 16)
    dk = 2 * np.pi / (n * step)
    bounds = galsim.BoundsI(0, n // 2, -(n // 2), n - n // 2 - 1)  # kt >= 0: h is real
    spectrum = profile.drawKImage(image=galsim.ImageCD(bounds), scale=dk, recenter=False).array
    pixel = galsim.Pixel(p, gsparams=profile.gsparams)
    t = (np.arange(n) - n // 2) * step
    tables = []
    for angle in np.arange(samples) * (90.0 / samples):
        # The unit square pixel in the track frame, as in SweptProfile._build_cap_table.
        square = pixel.rotate(-angle * galsim.degrees).drawKImage(
            image=galsim.ImageCD(bounds), scale=dk, recenter=False).array
        coeffs = np.fft.fftshift(
            np.fft.ifft(np.fft.ifftshift(spectrum * square, axes=0), axis=0), axes=0)
        coeffs *= n * dk / (2 * np.pi)
        tables.append(SweptProfile._antiderivative(coeffs, 1, t))
    peak = lsf.lsf.max()  # the renderer's reference (the grid's own is folded, higher)
    change = 0.0
    for a, b in zip(tables, tables[1:] + tables[:1]):  # the last neighbours the first (+90)
        delta = b - a
        change = max(change, float((delta.max(axis=1) - delta.min(axis=1)).max()))
    return change / peak / (90.0 / samples)


def orientation_step(slope, tolerance):
    """The grid of pixel orientations for a profile of measured ``slope`` (per degree, from
    :func:`orientation_slope`) at ``tolerance``.

    The step is ``90 / N`` deg, ``N`` the fewest steps for which snapping an angle to the
    nearest grid orientation (at most half a step away) errs by at most
    :data:`ORIENTATION_FRACTION` of the tolerance, with :data:`ORIENTATION_SAFETY` on the
    slope. A narrow profile (FWHM ~2 px) or a tight budget gets a fine grid; beyond
    :data:`MAX_ORIENTATION_STEPS` the angles stay exact.

    Returns
    -------
    step_deg : float
        0 for exact angles.
    error : float
        Largest pixel error the snapping adds, relative to the peak.
    """
    per_degree = ORIENTATION_SAFETY * float(slope)
    if not per_degree > 0:
        return 90.0, 0.0
    steps = int(np.ceil(45.0 * per_degree / (ORIENTATION_FRACTION * tolerance)))
    if steps > MAX_ORIENTATION_STEPS:
        return 0.0, 0.0
    steps = max(steps, 1)
    return 90.0 / steps, per_degree * 45.0 / steps


def snap_orientation(angle_deg, step_deg):
    """The grid orientation in ``[0, 90)`` nearest to ``angle_deg`` modulo 90 (the angle
    itself, reduced, if ``step_deg`` is 0)."""
    angle = float(angle_deg) % 90.0
    if step_deg <= 0:
        return angle
    steps = int(round(90.0 / step_deg))
    return float((int(np.floor(angle / step_deg + 0.5)) % steps) * step_deg)


def footprint(shape, segment, support_px, cap_px):
    """Pixels within ``support_px`` of a segment and ``cap_px`` beyond its ends.

    Returns ``(y, x, t, d)``: integer pixel indices (each pixel once) and their track-frame
    coordinates.
    """
    ny, nx = shape
    c, s = segment.direction
    horizontal = abs(c) >= abs(s)
    # Walk along the major axis. On each line both |d| <= support and -cap <= t <= L + cap
    # are linear in the minor coordinate, so the pixels kept form one interval per line.
    if horizontal:
        major_n, minor_n, m0, n0 = nx, ny, segment.x0, segment.y0
        (t_major, t_minor), (d_major, d_minor) = (c, s), (-s, c)
    else:
        major_n, minor_n, m0, n0 = ny, nx, segment.y0, segment.x0
        (t_major, t_minor), (d_major, d_minor) = (s, c), (c, -s)
    ends = [m0 - cap_px * t_major, m0 + (segment.length + cap_px) * t_major]
    reach = support_px * abs(t_minor) + 1  # the band's slant adds to its major extent
    lo = max(0, int(np.floor(min(ends) - reach)))
    hi = min(major_n - 1, int(np.ceil(max(ends) + reach)))
    major = np.arange(lo, hi + 1)
    offset = major - m0

    def interval(a_major, a_minor, low, high):
        """Minor coordinates n with low <= a_major * offset + a_minor * (n - n0) <= high."""
        if abs(a_minor) < 1e-12:
            inside = (a_major * offset >= low) & (a_major * offset <= high)
            return np.where(inside, -np.inf, np.inf), np.where(inside, np.inf, -np.inf)
        bounds = ((low - a_major * offset) / a_minor, (high - a_major * offset) / a_minor)
        return n0 + np.minimum(*bounds), n0 + np.maximum(*bounds)

    d_lo, d_hi = interval(d_major, d_minor, -support_px, support_px)
    t_lo, t_hi = interval(t_major, t_minor, -cap_px, segment.length + cap_px)
    start = np.clip(np.ceil(np.maximum(d_lo, t_lo)), 0, minor_n).astype(int)
    stop = np.clip(np.floor(np.minimum(d_hi, t_hi)) + 1, 0, minor_n).astype(int)
    counts = np.maximum(stop - start, 0)
    major = np.repeat(major, counts)
    minor = np.arange(counts.sum()) + np.repeat(start - (np.cumsum(counts) - counts), counts)
    x, y = (major, minor) if horizontal else (minor, major)
    dx, dy = x - segment.x0, y - segment.y0
    return y, x, dx * c + dy * s, dy * c - dx * s


@dataclass(frozen=True)
class RenderResult:
    """What one rendered segment touched: the pixels, the charge added, the plan used."""

    n_pixels: int
    charge_added: float
    plan: RenderPlan


@dataclass(frozen=True)
class PolylineResult:
    """What a rendered polyline added: its charge, and how far its widest swept profile
    reaches from the track (support across plus end cap along, px)."""

    charge_added: float
    reach_px: float


def render_segment(image, swept, segment, flux_per_px, flux_end=None):
    """Add one segment's streak charge into ``image`` (in place).

    Parameters
    ----------
    image : ndarray
        2-D float array, indexed ``[y, x]``; accumulated in float64 and added once.
    swept : SweptProfile
        Profile and pixel orientation; ``segment.angle_deg`` must equal ``swept.angle_deg``
        modulo 90 deg, within ``swept.angle_tolerance_deg``. The footprint and the pixels'
        track-frame coordinates follow the segment's own angle.
    segment : Segment
    flux_per_px : float
        Charge per pixel of track length at the start, e-.
    flux_end : float, optional
        Charge per pixel of track length at the end (linear in between); constant by default.

    Returns
    -------
    RenderResult
    """
    offset = (segment.angle_deg - swept.angle_deg + 45.0) % 90.0 - 45.0
    if abs(offset) > swept.angle_tolerance_deg + 1e-9:
        raise InputError("segment.angle_deg", segment.angle_deg,
                         f"differs from the SweptProfile's angle ({swept.angle_deg:g} deg "
                         f"modulo 90, within {swept.angle_tolerance_deg:g} deg)")
    plan = swept.plan
    y, x, t, d = footprint(image.shape, segment, plan.support_px, plan.cap_px)
    values = swept.pixel_values(t, d, segment.length, flux_per_px, flux_end)
    # Footprint pixels are unique, so a plain fancy-indexed add is safe (no np.add.at); on a
    # contiguous image a flat index is faster, and views or Fortran arrays take the 2-D one.
    if image.flags.c_contiguous:
        image.reshape(-1)[y * image.shape[1] + x] += values
    else:
        image[y, x] += values
    return RenderResult(len(values), float(values.sum()), plan)


def short_track_budget(budget, profile, pixel_scale, angle_deg, length_px):
    """The budget for a track of ``length_px``, its tolerance relative to its own peak.

    A track shorter than the profile along it peaks below an infinite streak's ``F p
    max LSF``, which the tables are budgeted against: the tolerance is scaled by the ratio of
    the two peaks, ``min(1, L max phi)`` (``phi`` the pixel-convolved marginal along the
    track, exact for separable profiles as ``L -> 0``), rounded down to the grid of
    :func:`snap_tolerance`, down to :data:`AUTO_MIN_TOLERANCE`.
    """
    if not np.isfinite(length_px):
        return budget
    along = line_spread(profile.rotate(90 * galsim.degrees), pixel_scale,
                        pixel_angle_deg=angle_deg + 90)
    ratio = min(1.0, length_px * pixel_scale * along.lsf.max())
    if ratio >= 1.0:
        return budget
    return replace(budget, tolerance=max(min(AUTO_MIN_TOLERANCE, budget.tolerance),
                                         snap_tolerance(budget.tolerance * ratio)))


def along_peak_floor(profile, pixel_scale, samples=6):
    """A lower bound, over all pixel orientations, of the peak of the pixel-convolved marginal
    along the track (``max phi`` of :func:`short_track_budget`), per arcsec.

    The pixel's projection along the track is the same at ``a``, ``-a`` and ``90 - a``: the
    peak is sampled over 0-45 deg, and its smallest value lowered by 1% or ten times its
    spread over the samples (it changes only at fourth order, ~1e-3 for a 2 px FWHM). A track
    at least ``1 / (p floor)`` long therefore keeps the budget at any angle, without a
    line-spread function per angle.
    """
    peaks = np.array([line_spread(profile.rotate(90 * galsim.degrees), pixel_scale,
                                  pixel_angle_deg=a + 90).lsf.max()
                      for a in np.linspace(0.0, 45.0, samples)])
    spread = (peaks.max() - peaks.min()) / peaks.max()
    return float(peaks.min() * (1 - max(0.01, 10 * spread)))


class ProfileCache:
    """What streaks share, built once: swept profiles (LSF and end-cap tables), the profile
    chosen for a budget, short-track budgets. A bounded LRU, thread-safe.

    Every key holds exactly what determines the value: the model's
    :attr:`~inject.streak.StreakModel.profile_key` (geometry, shape, seeing, telescope; not
    the magnitude or band, which only scale the charge), the pixel orientation the tables are
    built at (the track angle snapped by :func:`swept_profile`; short-track budgets keep the
    exact angle), the budget and, for short-track budgets, the length. A hit therefore
    returns what a fresh build would.

    Parameters
    ----------
    max_bytes : int
        Memory the cached tables may hold; the least recently used are dropped beyond it.
    max_entries : int
    """

    def __init__(self, max_bytes=256 * 2 ** 20, max_entries=256):
        self.max_bytes, self.max_entries = int(max_bytes), int(max_entries)
        self._items = OrderedDict()  # key -> (value, nbytes)
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @property
    def nbytes(self):
        return sum(size for _, size in self._items.values())

    def __len__(self):
        return len(self._items)

    def clear(self):
        with self._lock:
            self._items.clear()
            self.hits = self.misses = 0

    def get(self, key, build):
        """The value for ``key``, from ``build()`` on a miss."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                self.hits += 1
                return self._items[key][0]
        value = build()  # outside the lock: tables take seconds at tight budgets
        size = _nbytes(value)
        with self._lock:
            self.misses += 1
            self._items[key] = (value, size)
            self._items.move_to_end(key)
            while self._items and (len(self._items) > self.max_entries
                                   or self.nbytes > self.max_bytes):
                self._items.popitem(last=False)
        return value


def _nbytes(value):
    """Memory held by a cached value (a SweptProfile's tables, including K's inputs and
    table, built on first use; small objects count as 0)."""
    if not isinstance(value, SweptProfile):
        return 0
    coeffs = value._second_inputs[0]
    return int(2 * value._table.nbytes + coeffs.nbytes + value.lsf.lsf.nbytes)


#: The cache :func:`swept_profile` uses unless told otherwise.
PROFILE_CACHE = ProfileCache()


def swept_profile(model, angle_deg, budget=Budget(), length_px=np.inf, cache=PROFILE_CACHE,
                  snap=True):
    """A :class:`SweptProfile` of a :class:`~inject.streak.StreakModel`, with components
    that cannot matter at this budget dropped, and that decision in its plan.

    ``length_px``, if given, tightens the tolerance of a track too short to reach the
    long streak's peak (:func:`short_track_budget`). The tables are built at the pixel
    orientation nearest to ``angle_deg`` on the profile's grid (:func:`orientation_step`),
    whose snapping error is in the plan as ``"orientation"``; render the segment at its own
    angle. ``cache`` (a :class:`ProfileCache`, or None to build afresh) shares the result
    between streaks with the same profile, grid orientation and budget. ``snap=False`` builds
    the tables at the exact angle, without measuring the grid (for a profile no other streak
    will share).
    """
    if cache is None:
        cache = ProfileCache()  # a throwaway one: nothing shared with other calls
    key = model.profile_key
    angle_deg = float(angle_deg)
    if length_px < SHORT_TRACK_CHECK_PX:
        # Most short tracks are still longer than the profile at any pixel orientation: one
        # bound per profile, not a line-spread function per angle.
        floor = cache.get(("along_peak", key),
                          lambda: along_peak_floor(model.profile, model.pixel_scale))
        if length_px * model.pixel_scale * floor < 1.0:
            budget = cache.get(("budget", key, angle_deg, float(length_px), budget),
                               lambda: short_track_budget(budget, model.profile,
                                                          model.pixel_scale, angle_deg,
                                                          length_px))
    profile, dropped, error = cache.get(("profile", key, budget.tolerance),
                                        lambda: model.render_profile(budget.tolerance))
    step, snap_error = 0.0, 0.0
    if snap:
        slope = cache.get(("orientation", key, dropped),
                          lambda: orientation_slope(profile, model.pixel_scale))
        step, snap_error = orientation_step(slope, budget.tolerance)
    angle_deg = snap_orientation(angle_deg, step)

    def build():
        swept = SweptProfile(profile, model.pixel_scale, angle_deg, budget,
                             angle_tolerance_deg=step / 2, angle_error=snap_error)
        if dropped:
            swept.plan = replace(swept.plan, dropped=dropped,
                                 predicted_error=swept.plan.predicted_error | {"dropped": error})
        return swept
    return cache.get(("swept", key, angle_deg, budget), build)


def render_streak(image, model, segment, budget=Budget(), cache=PROFILE_CACHE):
    """Render a :class:`~inject.streak.StreakModel` along a segment into ``image``."""
    swept = swept_profile(model, segment.angle_deg, budget, segment.length, cache)
    return render_segment(image, swept, segment, model.flux_per_px)


def render_polyline(image, polyline, models, budget=Budget(), cache=PROFILE_CACHE):
    """Render a track through vertices whose streak models differ (width, speed, brightness).

    Each piece between two vertices is split at its middle: the first half is swept with the
    first vertex's profile, the second half with the second's, while the charge per pixel of
    track varies linearly from one vertex's value to the next (exactly, see
    :meth:`SweptProfile.pixel_values`). Profiles are built once per model and angle, at the
    exact angle unless several vertices share a profile (then on the orientation grid of
    :func:`swept_profile`, so that pieces at other angles share its tables).

    Parameters
    ----------
    image : ndarray
    polyline : Polyline
    models : list of StreakModel
        One per vertex.
    budget : Budget
    cache : ProfileCache or None
        Shared swept profiles (see :func:`swept_profile`); within the polyline each model and
        angle is built once even without it.

    Returns
    -------
    PolylineResult
        The charge added and the reach of the widest profile used.
    """
    if len(models) != len(polyline.xs):
        raise InputError("models", len(models), f"need one per vertex ({len(polyline.xs)})")
    local = ProfileCache() if cache is None else cache
    # Tables are shared through snapped orientations only where a vertex profile recurs: one
    # of its own (an orbit's vertex, a focal-plane CCD's interpolated ends) is built at its
    # exact angle, without measuring how fast it changes with the orientation.
    keys = [model.profile_key for model in models]
    recurring = {key for key in keys if keys.count(key) > 1}

    def profile_for(model, angle):
        return swept_profile(model, angle, budget, cache=local,
                             snap=model.profile_key in recurring)

    total, vertex, reach = 0.0, 0, 0.0
    for seg in polyline.segments():
        while (polyline.xs[vertex], polyline.ys[vertex]) != (seg.x0, seg.y0):
            vertex += 1  # skip repeated vertices (zero-length pieces)
        first, second = models[vertex], models[vertex + 1]
        f0, f1 = first.flux_per_px, second.flux_per_px
        mid = 0.5 * (f0 + f1)
        half = seg.length / 2
        c, s = seg.direction
        halves = ((first, seg.x0, seg.y0, f0, mid),
                  (second, seg.x0 + half * c, seg.y0 + half * s, mid, f1))
        for model, x, y, fa, fb in halves:
            piece = type(seg)(x, y, seg.angle_deg, half)
            swept = profile_for(model, seg.angle_deg)
            reach = max(reach, swept.plan.support_px + swept.plan.cap_px)
            total += render_segment(image, swept, piece, fa, fb).charge_added
        vertex += 1
    return PolylineResult(total, reach)
