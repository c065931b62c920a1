"""FITS output in LSST afw's MaskedImage layout: IMAGE, MASK, VARIANCE, then STREAK_MODEL and
TRUTH (and RAW).

HDUs 1-3 follow what afw writes (``MaskedImage::writeFits``, ``ExposureInfo::_startWriteFits``,
``Fits::writeImage``) so that afw and LSST's pure-Python ``lsst-images`` read the file as a
MaskedImage: ``EXTTYPE`` and ``INHERIT = T`` on each of them, the image origin xy0 as the
``LTV1/2`` cards and afw's linear "A" WCS (``CTYPE1A = 'LINEAR'``, ...), the celestial WCS on all
three, and the mask planes of :mod:`inject.maskplanes` (afw's ``MP_`` cards and lsst-images'
``MSKN/MSKM/MSKD`` cards). The primary header has the cards afw's VisitInfo uses (``EXPTIME``,
``DATE-AVG`` + ``TIMESYS``, ``BORE-RA/DEC``, ``BORE-ROTANG`` + ``ROTTYPE``) and ``FILTER``.
"""
import hashlib
import os

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .. import __version__
from ..maskplanes import FLAG_CLIPPED, FLAG_OFF_IMAGE, FLAG_SATURATED, mask_header
from .atomic import atomic_path

#: Extension types of afw's MaskedImage HDUs 1-3, in that order.
MASKED_IMAGE_TYPES = ("IMAGE", "MASK", "VARIANCE")


def primary_header(scene, primary_cards=None):
    """Scene summary cards for HDU 0, with the keys LSST readers take from it.

    Parameters
    ----------
    scene : inject.config.Scene
    primary_cards : mapping or iterable of (key, value), optional
        Extra cards (e.g. ``DETNAME``, ``DETECTOR`` of a focal-plane CCD): a value or a
        ``(value, comment)`` pair per key; they replace cards of the same key.
    """
    hdr = fits.Header()
    hdr["ORIGIN"] = ("inject", "satellite streak simulator")
    hdr["INJVER"] = (__version__, "inject version")
    hdr["BAND"] = (scene.band, "LSST filter")
    hdr["FILTER"] = (scene.band, "band (afw FilterLabel band)")
    hdr["EXPTIME"] = (scene.exptime, "[s] exposure time")
    from ..config import time_cards

    for key, card in time_cards(scene).items():  # a scene with an exposure start (time:)
        hdr[key] = card
    pointing = scene.pointing
    if pointing is not None:
        rotation = float(pointing.get("rotation", 0.0))
        hdr["BORE-RA"] = (float(pointing["ra"]), "[deg] ICRS RA of the pointing")
        hdr["BORE-DEC"] = (float(pointing["dec"]), "[deg] ICRS Dec of the pointing")
        hdr["HIERARCH BORE-ROTANG"] = (rotation, "[deg] sky rotation angle (rotSkyPos)")
        hdr["ROTTYPE"] = ("SKY", "type of BORE-ROTANG (afw RotType)")
        hdr["ROTPA"] = (rotation, "[deg] sky position angle of the camera")
        hdr["ROTCOORD"] = ("sky", "frame of ROTPA")
    hdr["SEEING"] = (scene.seeing, "[arcsec] atmospheric FWHM (Kolmogorov)")
    hdr["ZENITH"] = (scene.zenith, "[deg] zenith angle of the line of sight")
    hdr["SEED"] = (scene.seed, "scene random seed")
    hdr["DETTYPE"] = (scene.detector.kind.upper(), "sensor type")
    hdr["NSTREAK"] = (len(scene.satellites), "number of injected streaks")
    if primary_cards is not None:
        cards = primary_cards.items() if hasattr(primary_cards, "items") else primary_cards
        for key, value in cards:
            hdr[key] = value
    return hdr


def plane_header(exttype, xy0=(0, 0), wcs_header=None):
    """The cards afw writes on each of IMAGE, MASK and VARIANCE.

    Parameters
    ----------
    exttype : str
        ``IMAGE``, ``MASK`` or ``VARIANCE``.
    xy0 : tuple of int
        LSST parent pixel of array pixel (0, 0).
    wcs_header : astropy.io.fits.Header, optional
        Celestial WCS of the array (FITS pixels, as afw writes it).
    """
    x0, y0 = (int(v) for v in xy0)
    hdr = fits.Header()
    hdr["INHERIT"] = (True, "take missing cards from the primary HDU")
    hdr["EXTTYPE"] = (exttype, "afw MaskedImage plane")
    if wcs_header is not None:
        hdr.extend(wcs_header)
    # afw's origin, twice: the "A" WCS (what LSST reads) and LTV (the STScI convention ds9 uses).
    hdr["CTYPE1A"] = ("LINEAR", "Type of projection")
    hdr["CTYPE2A"] = ("LINEAR", "Type of projection")
    hdr["CRPIX1A"] = (1.0, "Column Pixel Coordinate of Reference")
    hdr["CRPIX2A"] = (1.0, "Row Pixel Coordinate of Reference")
    hdr["CRVAL1A"] = (float(x0), "Column pixel of Reference Pixel")
    hdr["CRVAL2A"] = (float(y0), "Row pixel of Reference Pixel")
    hdr["CUNIT1A"] = ("PIXEL", "Column unit")
    hdr["CUNIT2A"] = ("PIXEL", "Row unit")
    hdr["LTV1"] = (float(-x0), "-x0: array x minus LSST parent x")
    hdr["LTV2"] = (float(-y0), "-y0: array y minus LSST parent y")
    return hdr


def truth_table(rows):
    """The TRUTH binary-table HDU (one row per streak, with a ``flags`` column)."""
    table = Table(rows=rows) if rows else Table(names=["x0", "y0", "x1", "y1", "flags"])
    hdu = fits.BinTableHDU(table, name="TRUTH")
    hdu.header["FLAG_OFF"] = (FLAG_OFF_IMAGE, "flag bit: track misses the image")
    hdu.header["FLAG_CLP"] = (FLAG_CLIPPED, "flag bit: part of the streak is off the image")
    hdu.header["FLAG_SAT"] = (FLAG_SATURATED, "flag bit: streak saturates")
    return hdu


def raw_hdu(raw, sections, bias):
    """The amplifiers' readout (ADU, bias, prescan and overscan) with each amplifier's data
    section, image section, gain and read noise as header cards."""
    hdu = fits.ImageHDU(raw, name="RAW")
    hdu.header["BUNIT"] = "adu"
    hdu.header["BIAS"] = (bias, "[adu] bias level added to every pixel")
    for sec in sections:
        key = f"A{sec['amp']:02d}"
        hdu.header[f"HIERARCH {key} DATASEC"] = sec["datasec"]
        hdu.header[f"HIERARCH {key} IMAGESEC"] = sec["imagesec"]
        hdu.header[f"HIERARCH {key} GAIN"] = sec["gain"]
        hdu.header[f"HIERARCH {key} RDNOISE"] = sec["read_noise"]
    return hdu


def write_truth_csv(path, rows, overwrite=False):
    """The truth table as CSV (one row per streak), written atomically."""
    table = Table(truth_table(rows).data)
    with atomic_path(path, overwrite) as tmp:
        table.write(tmp, format="ascii.csv", overwrite=True)


class _DigestStream:
    """A write-only stream to a binary file that hashes (SHA-256) what goes through it, so a
    file's digest needs no second read.

    Runs of zero bytes of at least :attr:`HOLE` (a zero STREAK_MODEL, most of a MASK) are
    skipped over with a seek instead of written: the file system leaves a hole that reads
    back as zeros (the file's bytes, and its digest, are those of a dense write; nothing is
    copied to the disk). The file must be truncated at its final size when done.
    """

    #: Chunk checked for zeros, bytes (a multiple of the file system's 4 KiB blocks).
    HOLE = 1 << 20

    def __init__(self, out):
        self._out, self.digest = out, hashlib.sha256()

    def write(self, data):
        view = memoryview(data).cast("B")
        self.digest.update(view)
        if view.nbytes < self.HOLE:
            self._out.write(view)
            return view.nbytes
        words = np.frombuffer(view, np.uint8)
        for start in range(0, view.nbytes, self.HOLE):
            chunk = words[start:start + self.HOLE]
            if chunk.size == self.HOLE and not chunk.view(np.uint64).any():
                self._out.seek(self.HOLE, os.SEEK_CUR)
            else:
                self._out.write(chunk)
        return view.nbytes

    def tell(self):  # no seek method: astropy writes to it as a stream (mode "ostream")
        return self._out.tell()

    def flush(self):
        self._out.flush()


def _is_zero(array):
    """True when every value is zero (a zero-stride view is checked at one element)."""
    array = np.asarray(array)
    if array.size and all(s == 0 for s in array.strides):
        return not array.flat[0]
    return not array.any()


def _big_endian(array, dtype):
    """``array`` ready for astropy to write as ``dtype``: as it is when it already has that
    type (astropy byte-swaps a writeable array in place and back, two cheap passes over memory
    already mapped), else converted to big-endian ``dtype`` in one pass (not converted to the
    native type first and then swapped)."""
    array = np.asarray(array)
    if array.dtype == np.dtype(dtype) and array.flags.writeable:
        return array
    return np.asarray(array, dtype=np.dtype(dtype).newbyteorder(">"))


def write_exposure(path, scene, result, gain, wcs_header=None, overwrite=False,
                   primary_cards=None, xy0=(0, 0)):
    """Write a simulated CCD to ``path`` atomically (afw's MaskedImage layout, see above).

    A STREAK_MODEL of zeros (a CCD no streak reaches) is not computed: it is a fresh
    ``np.zeros`` that the writer leaves as a hole in the file (as it does for any MiB of
    zeros, most of a MASK), which reads back as the same zero bytes: the file's bytes, and
    so its digest, are those of a dense write.

    Parameters
    ----------
    path : str or os.PathLike
    scene : inject.config.Scene
    result : inject.scene.SceneResult
    gain : float
        e-/ADU, written as ``GAIN``.
    wcs_header : astropy.io.fits.Header, optional
        Celestial WCS of the CCD (on IMAGE, MASK and VARIANCE).
    overwrite : bool
    primary_cards : mapping, optional
        Extra primary-header cards (see :func:`primary_header`).
    xy0 : tuple of int
        LSST parent pixel of the array's first pixel (``LTV1/2`` and the "A" WCS).

    Returns
    -------
    str
        SHA-256 of the file's bytes (hex), computed as they were written.
    """
    image_hdr = plane_header("IMAGE", xy0, wcs_header)
    image_hdr["BUNIT"] = (scene.units, "pixel values")
    image_hdr["GAIN"] = (gain, "[e-/ADU] detector gain")
    mask_hdr = mask_header(plane_header("MASK", xy0, wcs_header))
    variance_hdr = plane_header("VARIANCE", xy0, wcs_header)
    variance_hdr["BUNIT"] = (f"{scene.units}**2", "variance of the pixel values")
    planes = [
        fits.PrimaryHDU(header=primary_header(scene, primary_cards)),
        fits.ImageHDU(_big_endian(result.image, np.float32), header=image_hdr, name="IMAGE"),
        fits.ImageHDU(_big_endian(result.mask, np.int32), header=mask_hdr, name="MASK"),
        fits.ImageHDU(_big_endian(result.variance, np.float32), header=variance_hdr,
                      name="VARIANCE"),
    ]
    zero_model = _is_zero(result.streak_model)
    # A zero model is a fresh np.zeros (pages the system maps only when touched).
    model = fits.ImageHDU(np.zeros(np.shape(result.streak_model), ">f4") if zero_model else
                          _big_endian(result.streak_model, np.float32), name="STREAK_MODEL")
    model.header["BUNIT"] = "electron"
    hdus = fits.HDUList([*planes, model, truth_table(result.truth)])
    if result.raw is not None:
        hdus.append(raw_hdu(result.raw, result.raw_sections, scene.detector.bias))
    with atomic_path(path, overwrite) as tmp:
        with open(tmp, "wb") as raw:
            stream = _DigestStream(raw)
            hdus.writeto(stream)
            raw.truncate()  # a hole at the very end still counts in the file's size
    return stream.digest.hexdigest()
