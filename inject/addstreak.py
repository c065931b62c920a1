"""Inject streaks into an existing image (the user's own FITS).

Only the injected charge gets Poisson noise (the image already has its own); VARIANCE grows by
the injected charge's Poisson variance (noise or not, unless asked to stay), MASK gets the
STREAK plane (on the first free bit if the file has none), and SAT where an integer image
reaches its ADC limit. The pixels go back in the file's own storage (see
:mod:`inject.io.reader`): pixels the streak does not reach are unchanged bit for bit, and
undefined ones (NaN, infinite, ``BLANK``) take no charge: neither the image, nor TRUTH's
``charge_in_image_e``, nor STREAK_MODEL counts any there. IMAGE, MASK and VARIANCE of an afw
file written without ``EXTNAME`` get ``EXTNAME = EXTTYPE`` (as afw writes today; lsst-images
needs it); their other cards stay. The input file is never modified.
"""
import numpy as np
from astropy.io import fits

from inject.errors import FileFormatError, InputError
from inject.io.fits import read_truth, truth_table, vertices_table
from inject.maskplanes import FLAG_CLIPPED, FLAG_OFF_IMAGE, FLAG_SATURATED, STREAK_MASK_SIGMA
from inject.render import Budget
from inject.scene import render_tracks
from inject.trajectory import path_distance
from inject.truth import vertices
from inject.validate import positive


def robust_sigma(image):
    """Noise estimate from the median absolute deviation of finite pixels."""
    values = image[np.isfinite(image)]
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def sky_to_array(wcs, ra, dec, shape, name="ra, dec"):
    """Array pixel ``(x, y)`` of sky position ``(ra, dec)`` (deg, the WCS's frame) in an image
    of ``shape`` with celestial WCS ``wcs``, SIP or other distortion included.

    The position must lie where the WCS's projection has a pixel: within 90 deg of the
    reference point (CRVAL) for TAN, where the projection of the position and back gives it
    again. It may lie far off the image: a distortion polynomial is fitted over the image
    only, so off it the distortion is held at its value on the image's nearest edge (on and
    near the image this is the full WCS's exact inverse, as ``all_world2pix`` gives it).

    Raises
    ------
    InputError
        (named ``name``) The projection has no pixel for the position, or the distortion
        cannot be inverted there.
    """
    ra, dec = float(ra), float(dec)
    reference = wcs.wcs.crval
    distance = _separation_deg(ra, dec, reference[0], reference[1])
    where = (f"{distance:.4g} deg from the WCS's reference point ({reference[0]:.6g}, "
             f"{reference[1]:.6g})")
    projection = wcs.wcs.ctype[0][5:8] or "linear"
    if projection == "TAN" and distance >= 90.0:
        raise InputError(name, (ra, dec), f"is {where}: the TAN projection has no pixel 90 "
                                          f"deg or more from it")
    with np.errstate(invalid="ignore"):
        u = np.array(wcs.wcs_world2pix([[ra, dec]], 0)[0], dtype=np.float64)
        back = wcs.wcs_pix2world([u], 0)[0] if np.all(np.isfinite(u)) else (np.nan, np.nan)
    if not (np.all(np.isfinite(u)) and _separation_deg(ra, dec, *back) < 1e-6):
        raise InputError(name, (ra, dec), f"is {where}: the WCS's {projection} projection has "
                                          f"no pixel there")
    if not wcs.has_distortion:
        return float(u[0]), float(u[1])
    ny, nx = shape
    low, high = np.array([-0.5, -0.5]), np.array([nx - 0.5, ny - 0.5])
    x = u.copy()
    for _ in range(100):  # fixed point x = u - d(x), d = the distortion (small: contracting)
        edge = np.clip(x, low, high)
        new = u - (wcs.pix2foc([edge], 0)[0] - edge)
        if not np.all(np.isfinite(new)):
            break
        step, x = np.max(np.abs(new - x)), new
        if step < 1e-10 * max(1.0, float(np.max(np.abs(x)))):
            return float(x[0]), float(x[1])
    raise InputError(name, (ra, dec), f"is {where}: the WCS's distortion cannot be inverted "
                                      f"there")


def _separation_deg(ra1, dec1, ra2, dec2):
    """Angle between two sky positions, deg (Vincenty's formula: exact at every angle)."""
    ra1, dec1, ra2, dec2 = np.radians([ra1, dec1, ra2, dec2])
    dra = ra2 - ra1
    num = np.hypot(np.cos(dec2) * np.sin(dra),
                   np.cos(dec1) * np.sin(dec2) - np.sin(dec1) * np.cos(dec2) * np.cos(dra))
    den = np.sin(dec1) * np.sin(dec2) + np.cos(dec1) * np.cos(dec2) * np.cos(dra)
    return float(np.degrees(np.arctan2(num, den)))


def add_streaks(exposure, models, tracks, gain, rng, noise=True, budget=Budget(),
                variance=True):
    """Add streaks into an :class:`~inject.io.reader.InputExposure` (in memory).

    Parameters
    ----------
    exposure : InputExposure
        From :func:`inject.io.reader.read_exposure`; write it with its ``write`` method.
    models : list of StreakModel
    tracks : list of Track
        One per model, in array pixels (0-based: pixel (0, 0) is the centre of the first
        pixel; subtract ``exposure.xy0`` from LSST parent pixels).
    gain : float
        e- per image unit (1 for images in electrons).
    rng : numpy.random.Generator or int
        Draws the Poisson noise of the injected charge; anything
        :func:`numpy.random.default_rng` takes (an int seeds a new generator).
    noise : bool
        Add Poisson noise to the injected charge; else the exact model.
    budget : Budget
    variance : bool
        Add the injected charge's Poisson variance, ``model / gain**2`` (the file's units), to
        VARIANCE, with or without ``noise`` (as LSST's source_injection, whose
        ``inject_variance`` and ``add_noise`` are separate switches: the variance then
        describes the noise real light of that brightness would have); else leave VARIANCE
        as it is.

    Returns
    -------
    model_e : ndarray
        The injected charge, e- (noise-free), 0 on undefined pixels (NaN, infinite,
        ``BLANK``).
    truth : list of dict
        Rows with ``FLAG_SATURATED`` set where an integer image reached its ADC limit (or
        its ``SATURATE`` level) under the streak.

    Raises
    ------
    InputError
        An argument is of the wrong kind, ``models`` and ``tracks`` differ in length, or
        ``gain`` is not a number > 0.
    FileFormatError
        The image has no usable pixel (every one NaN, infinite or ``BLANK``), or the mask has
        no free bit for a new plane.
    """
    rng = _check_arguments(exposure, models, tracks, rng)
    positive("gain", gain)
    image = exposure.image
    usable = exposure.defined()
    if not usable.any():
        raise FileFormatError(f"{exposure.path or 'the exposure'}: the image (HDU "
                              f"{exposure.image_index}) has no usable pixel (every one NaN, "
                              f"infinite or BLANK): nothing can take a streak")
    model_e, truth = _render(image.shape, models, tracks, budget, usable)
    # The model can dip a few 1e-6 of its peak below zero (interpolation): not a charge.
    model_e = np.clip(model_e, 0, None)
    injected = rng.poisson(model_e).astype(np.float64) if noise else model_e
    exposure.add_extnames()
    saturation = exposure.header_value("SATURATE")
    saturation = float(saturation) if isinstance(saturation, (int, float)) else None
    saturated = exposure.add(exposure.image_index, injected / gain, saturation)
    if exposure.variance_index is not None:
        before = np.asarray(exposure.hdus[exposure.variance_index].data, dtype=np.float64)
        finite = before[np.isfinite(before)]
        sigma = float(np.sqrt(np.median(finite))) if finite.size else 0.0
        if variance:
            exposure.add(exposure.variance_index, model_e / gain ** 2)
    else:
        sigma = robust_sigma(image)
    threshold = STREAK_MASK_SIGMA * sigma * gain if sigma > 0 else 1e-3 * model_e.max()
    if exposure.mask_index is not None:
        index = exposure.mask_index
        exposure.set_bits(index, exposure.name_plane(index, "STREAK"), model_e > threshold)
        if saturated.any():
            exposure.set_bits(index, exposure.name_plane(index, "SAT"), saturated)
    if saturated.any():
        _flag_saturated(truth, models, saturated)
    _append_truth(exposure, truth)
    _add_to_streak_model(exposure, model_e)
    return model_e, truth


def _add_to_streak_model(exposure, model_e):
    """STREAK_MODEL holds every streak's charge (e-): the input's (an inject file, or an
    earlier injection) plus this one's, so that it sums to TRUTH's ``charge_in_image_e``."""
    names = [h.name for h in exposure.hdus]
    if "STREAK_MODEL" not in names and "INJECTED_MODEL" in names:  # older inject output
        exposure.hdus["INJECTED_MODEL"].name = "STREAK_MODEL"
        names = [h.name for h in exposure.hdus]
    if "STREAK_MODEL" in names:
        previous = exposure.hdus["STREAK_MODEL"]
        previous.data = (np.asarray(previous.data, np.float64) + model_e).astype(np.float32)
        exposure.mark_changed(names.index("STREAK_MODEL"))
    else:
        hdu = fits.ImageHDU(model_e.astype(np.float32), name="STREAK_MODEL")
        hdu.header["BUNIT"] = ("electron", "noise-free injected streak charge")
        exposure.hdus.append(hdu)


def _render(shape, models, tracks, budget, usable):
    """:func:`~inject.scene.render_tracks`, with the charge only on ``usable`` pixels: each
    TRUTH row counts what its streak puts there (flag 2 if that is short of the whole streak's,
    flag 1 if nothing)."""
    if usable.all():
        return render_tracks(shape, models, tracks, budget)
    model_e, truth = np.zeros(shape), []
    for model, track in zip(models, tracks):
        one, (row,) = render_tracks(shape, [model], [track], budget)
        one[~usable] = 0.0
        model_e += one
        row["charge_in_image_e"] = charge = float(one.sum())
        expected = row["flux_per_px_e"] * row["length_px"]
        if charge <= 0:
            row["flags"] = (row["flags"] | FLAG_OFF_IMAGE) & ~FLAG_CLIPPED
        elif charge < expected * (1 - 2 * budget.flux_tolerance):
            row["flags"] |= FLAG_CLIPPED
        truth.append(row)
    return model_e, truth


def _flag_saturated(truth, models, saturated):
    """Set ``FLAG_SATURATED`` on the rows whose track passes within a few FWHM of a pixel that
    saturated."""
    ys, xs = np.nonzero(saturated)
    for row, model in zip(truth, models):
        distance = path_distance(vertices(row), xs, ys)
        if np.any(distance <= 3 * row["fwhm_arcsec"] / model.pixel_scale + 2):
            row["flags"] |= FLAG_SATURATED


def _check_arguments(exposure, models, tracks, rng):
    """Raise :class:`InputError` for arguments of the wrong kind (which would otherwise fail
    deep inside the renderer); return ``rng`` as a generator."""
    from inject.io.reader import InputExposure
    from inject.streak import StreakModel
    from inject.trajectory import Track

    if not isinstance(exposure, InputExposure):
        raise InputError("exposure", type(exposure).__name__,
                         "must be an InputExposure (inject.io.reader.read_exposure)")
    models, tracks = list(models), list(tracks)
    if len(models) != len(tracks):
        raise InputError("tracks", len(tracks), f"need one per model ({len(models)})")
    for i, (model, track) in enumerate(zip(models, tracks)):
        if not isinstance(model, StreakModel):
            raise InputError(f"models[{i}]", type(model).__name__, "must be a StreakModel")
        if not isinstance(track, Track):
            raise InputError(f"tracks[{i}]", type(track).__name__,
                             "must be an inject.config.Track")
    try:
        return np.random.default_rng(rng)  # a Generator is returned as it is
    except (TypeError, ValueError):
        raise InputError("rng", rng, "must be a numpy Generator or an integer seed") from None


def _append_truth(exposure, rows):
    """TRUTH and TRUTH_VERTICES with ``rows`` after the input's (its own TRUTH's rows completed
    to today's columns, with their vertices, or their ends from a file written before
    TRUTH_VERTICES; the new streaks numbered after them), each replacing the input's table in
    its place or appended (so that the HDUs after it are still copied byte for byte)."""
    hdus = exposure.hdus
    earlier = read_truth(hdus)
    if earlier:
        for k, row in enumerate(rows):
            row["satellite"] = len(earlier) + k
    rows = earlier + list(rows)
    x0, y0 = exposure.xy0
    for table in (truth_table(rows), vertices_table(rows)):
        table.header["PARENTX0"] = (x0, "LSST parent x of array x 0 (x0.. are array px)")
        table.header["PARENTY0"] = (y0, "LSST parent y of array y 0")
        names = [hdu.name for hdu in hdus]
        if table.name in names:
            hdus[names.index(table.name)] = table
        else:
            hdus.append(table)
