"""FITS output in an LSST-like layout (CONTRACT.md): IMAGE, MASK, VARIANCE, STREAK_MODEL,
TRUTH."""
import numpy as np
from astropy.io import fits
from astropy.table import Table

from .. import __version__
from ..scene import FLAG_CLIPPED, FLAG_OFF_IMAGE, FLAG_SATURATED, MASK_PLANES
from .atomic import atomic_path


def primary_header(scene):
    """Scene summary cards for HDU 0."""
    hdr = fits.Header()
    hdr["ORIGIN"] = ("inject", "satellite streak simulator")
    hdr["INJVER"] = (__version__, "inject version")
    hdr["BAND"] = (scene.band, "LSST filter")
    hdr["EXPTIME"] = (scene.exptime, "[s] exposure time")
    hdr["SEEING"] = (scene.seeing, "[arcsec] atmospheric FWHM (Kolmogorov)")
    hdr["ZENITH"] = (scene.zenith, "[deg] zenith angle of the line of sight")
    hdr["SEED"] = (scene.seed, "scene random seed")
    hdr["DETTYPE"] = (scene.detector.kind.upper(), "sensor type")
    hdr["NSTREAK"] = (len(scene.satellites), "number of injected streaks")
    return hdr


def _mask_header(hdr):
    for name, bit in MASK_PLANES.items():
        hdr[f"HIERARCH MP_{name}"] = bit  # LSST writes these as HIERARCH cards too
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


def _with_cards(header, cards):
    for key, value in (cards or {}).items():
        header[key] = value
    return header


def write_truth_csv(path, rows, overwrite=False):
    """The truth table as CSV (one row per streak), written atomically."""
    table = Table(truth_table(rows).data)
    with atomic_path(path, overwrite) as tmp:
        table.write(tmp, format="ascii.csv", overwrite=True)


def write_exposure(path, scene, result, gain, wcs_header=None, overwrite=False,
                   primary_cards=None):
    """Write a simulated CCD to ``path`` atomically; ``primary_cards`` (a mapping of keyword
    to value or ``(value, comment)``) are appended to the primary header."""
    image_hdr = fits.Header()
    image_hdr["BUNIT"] = (scene.units, "pixel values")
    image_hdr["GAIN"] = (gain, "[e-/ADU] detector gain")
    if wcs_header is not None:
        image_hdr.extend(wcs_header)
    hdus = fits.HDUList([
        fits.PrimaryHDU(header=_with_cards(primary_header(scene), primary_cards)),
        fits.ImageHDU(result.image.astype(np.float32), header=image_hdr, name="IMAGE"),
        fits.ImageHDU(result.mask.astype(np.int32), header=_mask_header(fits.Header()),
                      name="MASK"),
        fits.ImageHDU(result.variance.astype(np.float32), name="VARIANCE"),
        fits.ImageHDU(result.streak_model.astype(np.float32), name="STREAK_MODEL"),
        truth_table(result.truth),
    ])
    hdus["VARIANCE"].header["BUNIT"] = f"{scene.units}2"
    if result.raw is not None:
        hdus.append(raw_hdu(result.raw, result.raw_sections, scene.detector.bias))
    hdus["STREAK_MODEL"].header["BUNIT"] = "electron"
    with atomic_path(path, overwrite) as tmp:
        hdus.writeto(tmp, overwrite=True)
