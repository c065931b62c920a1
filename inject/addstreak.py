"""Inject streaks into an existing image (the user's own FITS).

Only the injected charge gets Poisson noise (the image already has its own); VARIANCE grows by
the injected charge and MASK gets the STREAK plane. The input file is never modified.
"""
import numpy as np
from astropy.io import fits
from astropy.table import Table, vstack

from .errors import InputError
from .io.fits import truth_table
from .render import Budget
from .scene import MASK_PLANES, STREAK_MASK_SIGMA, render_tracks
from .validate import positive


def _mask_bit(header):
    """The STREAK bit of a MASK header, adding an ``MP_STREAK`` card on a free bit if needed."""
    planes = {key[3:]: header[key] for key in header if key.startswith("MP_")}
    if "STREAK" in planes:
        return int(planes["STREAK"])
    used = set(planes.values())
    bit = MASK_PLANES["STREAK"] if MASK_PLANES["STREAK"] not in used else min(
        b for b in range(31) if b not in used)
    header["HIERARCH MP_STREAK"] = bit
    return bit


def robust_sigma(image):
    """Noise estimate from the median absolute deviation of finite pixels."""
    values = image[np.isfinite(image)]
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def add_streaks(exposure, models, tracks, gain, rng, noise=True, budget=Budget()):
    """Add streaks into an :class:`~inject.io.reader.InputExposure` (in memory).

    Parameters
    ----------
    exposure : InputExposure
        From :func:`inject.io.reader.read_exposure`.
    models : list of StreakModel
    tracks : list of Track
        One per model.
    gain : float
        e- per image unit (1 for images in electrons).
    rng : numpy.random.Generator or int
        Draws the Poisson noise of the injected charge; anything
        :func:`numpy.random.default_rng` takes (an int seeds a new generator).
    noise : bool
        Add Poisson noise to the injected charge (else the exact model).

    Returns
    -------
    model_e : ndarray
        The injected charge, e- (noise-free).
    truth : list of dict

    Raises
    ------
    InputError
        An argument is of the wrong kind, ``models`` and ``tracks`` differ in length, or
        ``gain`` is not a number > 0.
    """
    rng = _check_arguments(exposure, models, tracks, rng)
    positive("gain", gain)
    image = exposure.image
    model_e, truth = render_tracks(image.shape, models, tracks, budget)
    # The model can dip a few 1e-6 of its peak below zero (interpolation): not a charge.
    injected = rng.poisson(np.clip(model_e, 0, None)).astype(np.float64) if noise else model_e
    hdu = exposure.image_hdu
    dtype = hdu.data.dtype.newbyteorder("=")
    hdu.data = (image + injected / gain).astype(dtype if dtype.kind == "f" else np.float32)
    if exposure.variance_index is not None:
        var_hdu = exposure.hdus[exposure.variance_index]
        variance = np.asarray(var_hdu.data, dtype=np.float64)
        var_hdu.data = (variance + model_e / gain ** 2).astype(np.float32)
        sigma = float(np.sqrt(np.median(variance[np.isfinite(variance)])))
    else:
        sigma = robust_sigma(image)
    threshold = STREAK_MASK_SIGMA * sigma * gain if sigma > 0 else 1e-3 * model_e.max()
    if exposure.mask_index is not None:
        mask_hdu = exposure.hdus[exposure.mask_index]
        bit = _mask_bit(mask_hdu.header)
        mask = np.asarray(mask_hdu.data).astype(np.int32)
        mask[model_e > threshold] |= np.int32(1 << bit)
        mask_hdu.data = mask
    _append_truth(exposure.hdus, truth)
    if "INJECTED_MODEL" in [h.name for h in exposure.hdus]:  # injecting into our own output
        previous = exposure.hdus["INJECTED_MODEL"]
        previous.data = (np.asarray(previous.data, np.float64) + model_e).astype(np.float32)
    else:
        exposure.hdus.append(fits.ImageHDU(model_e.astype(np.float32), name="INJECTED_MODEL"))
    return model_e, truth


def _check_arguments(exposure, models, tracks, rng):
    """Raise :class:`InputError` for arguments of the wrong kind (which would otherwise fail
    deep inside the renderer); return ``rng`` as a generator."""
    from .config import Track
    from .io.reader import InputExposure
    from .streak import StreakModel

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


def _append_truth(hdus, rows):
    names = [hdu.name for hdu in hdus]
    new = truth_table(rows)
    if "TRUTH" in names:
        old = Table(hdus["TRUTH"].data)
        combined = vstack([old, Table(new.data)], metadata_conflicts="silent")
        hdus[names.index("TRUTH")] = fits.BinTableHDU(combined, header=new.header, name="TRUTH")
    else:
        hdus.append(new)
