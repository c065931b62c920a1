"""Adapters for external streak maskers, scored by :mod:`.evaluate` side by side with ours.

:func:`findsat_mrt_mask` wraps acstools ``findsat_mrt`` (Stark et al. 2022: median Radon
transform of a binned image, Gaussian fits of the trail profiles, masks 6 sigma wide). It is an
optional dependency: ``pip install 'satstreak-inject[mask-external]'`` (acstools, photutils).
"""
import contextlib
import io
import logging
import warnings

import numpy as np

from . import MaskingError

#: Binning before the transform: the acstools documentation recommends binning WFC images
#: (4k x 2k) so the median Radon transform runs in reasonable time; 4 x 4 turns a 7-10 px
#: LSSTCam streak into a ~2 px line.
FINDSAT_BIN = 4


def _trail_finder():
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
    """Boolean streak mask of an image by acstools ``findsat_mrt``, run offline.

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

    Returns
    -------
    ndarray of bool

    Raises
    ------
    MaskingError
        If acstools is not installed.
    """
    TrailFinder = _trail_finder()
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
    return mask
