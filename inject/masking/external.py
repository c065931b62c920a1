"""Adapters for external streak maskers, scored by :mod:`.evaluate` side by side with ours.

:func:`findsat_mrt_trails` wraps acstools ``findsat_mrt`` (Stark et al. 2022: median Radon
transform of a binned image, Gaussian fits of the trail profiles, masks 6 sigma wide) and
returns its mask with its own trail catalogue (angles, positions, widths);
:func:`findsat_mrt_mask` returns the mask alone. It is an
optional dependency: ``pip install 'satstreak-inject[mask-external]'`` (acstools, photutils).
"""
import contextlib
import io
import logging
import warnings

import numpy as np

from inject.masking import MaskerOutput, MaskingError

#: Binning before the transform: the acstools documentation recommends binning WFC images
#: (4k x 2k) so the median Radon transform runs in reasonable time; 4 x 4 turns a 7-10 px
#: LSSTCam streak into a ~2 px line.
FINDSAT_BIN = 4


def trail_finder():
    """acstools' ``TrailFinder`` class; :class:`MaskingError` if acstools is not installed."""
    try:
        from acstools.findsat_mrt import TrailFinder
    except ImportError as err:
        raise MaskingError("the findsat_mrt masker needs acstools and photutils: pip install "
                           f"acstools photutils (or the mask-external extra) ({err})") from None
    return TrailFinder


@contextlib.contextmanager
def _quiet():
    """Silence acstools' INFO logging, prints and warnings while it runs (they would drown the
    evaluation's progress lines)."""
    loggers = [logging.getLogger(n) for n in ("findsat_mrt", "utils_findsat_mrt")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # all-NaN slices, "no sources found" (chatter)
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def findsat_mrt_mask(image, bad=None, binning=FINDSAT_BIN, threshold=5.0, processes=1):
    """Boolean streak mask of an image by acstools ``findsat_mrt`` (see
    :func:`findsat_mrt_trails`, which also returns the trails it found).

    Returns
    -------
    ndarray of bool
    """
    return findsat_mrt_trails(image, bad, binning, threshold, processes).mask


def findsat_mrt_trails(image, bad=None, binning=FINDSAT_BIN, threshold=5.0, processes=1,
                       pixel_scale=0.2):
    """Streak mask and trail catalogue of an image by acstools ``findsat_mrt``, run offline.

    The image is median-subtracted (the transform assumes a zero background), bad pixels
    become NaN, it is binned ``binning x binning`` (sum of finite pixels, as in the acstools
    example), and ``TrailFinder.run_all`` finds and masks trails; the binned mask is expanded
    back to full resolution. Nothing is written to disk.

    Parameters
    ----------
    image : array_like
        2-D image.
    bad : array_like of bool, optional
        Pixels not to use.
    binning : int
    threshold : float
        ``TrailFinder`` S/N threshold (its default, 5).
    processes : int
        Worker processes of the transform.
    pixel_scale : float
        Arcsec per pixel (for ``fwhm_arcsec``).

    Returns
    -------
    MaskerOutput
        The mask and one dict per masked trail (:func:`trail_records`): findsat_mrt's own
        lines and widths, so the evaluation scores its angles, offsets and FWHMs, not
        quantities re-derived from its mask.

    Raises
    ------
    MaskingError
        If acstools is not installed.
    """
    TrailFinder = trail_finder()
    from astropy.nddata import block_reduce

    img = np.array(image, dtype=np.float64)
    if bad is not None:
        img[np.asarray(bad, dtype=bool)] = np.nan
    img -= np.nanmedian(img)
    ny, nx = (n // binning * binning for n in img.shape)
    binned = block_reduce(img[:ny, :nx], binning, func=np.nansum)
    finder = TrailFinder(binned, processes=processes, threshold=threshold, plot=False,
                         save_catalog=False, save_diagnostic=False, save_mrt=False,
                         save_mask=False, check_persistence=True)
    with _quiet():
        finder.run_all()
    small = np.zeros(binned.shape, dtype=bool) if finder.mask is None else finder.mask > 0
    mask = np.zeros(img.shape, dtype=bool)
    mask[:ny, :nx] = np.repeat(np.repeat(small, binning, axis=0), binning, axis=1)
    streaks = trail_records(finder.source_list, binning, pixel_scale,
                            getattr(finder, "mask_include_status", (2,)))
    return MaskerOutput(mask, streaks)


def trail_records(source_list, binning, pixel_scale=0.2, include=(2,)):
    """findsat_mrt's masked trails (``status`` in ``include``, its default ``[2]``: robust
    and persistent) as streak dicts in full-resolution pixels.

    ``x0, y0, x1, y1`` are its trail endpoints (where its transform's line meets the edges of
    the binned image; binned pixel ``k`` is centred on image pixel ``binning k + (binning -
    1) / 2``) and ``angle_deg`` their orientation in ``(-90, 90]``. Its ``width`` is 6 sigma
    of a Gaussian fitted to the trail's median profile in the binned image: ``fwhm_px`` is
    that Gaussian's FWHM with the binned pixel (a ``binning``-wide box, variance
    ``binning^2 / 12``) removed in quadrature, as our own FWHM has the pixel response
    removed; ``findsat_width_px`` is its full mask width in image pixels.

    Returns
    -------
    list of dict
    """
    if source_list is None:
        return []
    out = []
    offset = (binning - 1) / 2
    for row in source_list:
        if int(row["status"]) not in set(include):
            continue
        (xa, ya), (xb, yb) = np.asarray(row["endpoints"], dtype=float)
        xa, ya, xb, yb = (float(binning * v + offset) for v in (xa, ya, xb, yb))
        angle = float(np.degrees(np.arctan2(yb - ya, xb - xa)))
        if not -90 < angle <= 90:  # orient like ours: (-90, 90]
            xa, ya, xb, yb = xb, yb, xa, ya
            angle = float(np.degrees(np.arctan2(yb - ya, xb - xa)))
        width = float(row["width"])
        var = (binning * width / 6) ** 2 - binning ** 2 / 12
        fwhm = 2 * np.sqrt(2 * np.log(2)) * np.sqrt(var) if var > 0 else float("nan")
        out.append({"angle_deg": angle, "x0": xa, "y0": ya, "x1": xb, "y1": yb,
                    "fwhm_px": float(fwhm), "fwhm_arcsec": float(fwhm * pixel_scale),
                    "findsat_width_px": binning * width, "snr": float(row["snr"]),
                    "persistence": float(row["persistence"]), "status": int(row["status"])})
    return out
