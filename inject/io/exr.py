"""OpenEXR output: the arrays of one simulated CCD in a two-part EXR, via OpenImageIO.

Layout
------
Part ``"image"``
    float32 channels ``IMAGE``, ``VARIANCE``, ``STREAK_MODEL`` (electrons, electrons^2,
    electrons), zip compressed, plus the metadata attributes below.
Part ``"mask"``
    One uint32 channel ``MASK`` holding the FITS MASK bits unchanged. It has its own part
    because OpenImageIO normalises int<->float conversions: sharing a part with float
    channels would turn bit patterns into fractions.

Attributes (strings; ``inject:`` prefix)
    ``inject:fits_header``
        The FITS primary header (:func:`inject.io.fits.primary_header`) as text, cards
        joined by newlines. A string because OpenImageIO stores double attributes as float32
        (or drops them) and drops attributes named ``fits:*``/``oiio:*``.
    ``inject:truth``
        The truth table, JSON (a list of objects, as ``SceneResult.truth``).
    ``inject:mask_planes``
        JSON ``{"PLANE": bit, ...}`` (:data:`inject.maskplanes.MASK_PLANES`).
    ``inject:units``
        JSON ``{"CHANNEL": unit, ...}``.
    ``inject:row_order``
        :data:`ROW_ORDER`. EXR row 0 is the top of a picture, FITS row 0 the bottom; rows are
        written flipped so that EXR viewers show the CCD the same way up as ds9 shows the
        FITS file. :func:`read_exr` flips them back.

Compression is zip (lossless) and pixels are 32-bit: DWA/pxr24 are lossy and half floats
overflow above 65504 e-, both unacceptable for science arrays.
"""
import json

import numpy as np
from astropy.io import fits

from inject.errors import FileFormatError, OutputError
from inject.io.atomic import atomic_path
from inject.io.fits import primary_header
from inject.maskplanes import MASK_PLANES

#: Float channels of the ``image`` part, in the order written (EXR files store channels
#: sorted by name, so readers must look them up by name, not position).
FLOAT_CHANNELS = ("IMAGE", "VARIANCE", "STREAK_MODEL")
#: Units of every channel.
UNITS = {"IMAGE": "electron", "VARIANCE": "electron2", "STREAK_MODEL": "electron", "MASK": ""}
#: Part (subimage) names.
IMAGE_PART, MASK_PART = "image", "mask"
#: Value of the ``inject:row_order`` attribute.
ROW_ORDER = ("flipped: EXR row r holds FITS row ny-1-r (EXR row 0 is the top of the image, "
             "FITS row 0 its bottom), so the EXR displays the same way up as ds9 shows the FITS")
#: Header text separator (newlines keep ``exrheader``/``oiiotool --info`` output readable).
HEADER_SEP = "\n"


def _json_default(value):
    # numpy scalars (int64, bool_) are not JSON types; everything else is a bug to surface.
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def header_text(header):
    """The text stored in ``inject:fits_header``: the cards of ``header``, one a line."""
    return header.tostring(sep=HEADER_SEP, endcard=True, padding=False)


def _spec(oiio, width, height, channels, fmt, part, attributes):
    spec = oiio.ImageSpec(width, height, len(channels), fmt)
    spec.channelnames = tuple(channels)
    spec.attribute("name", part)
    spec.attribute("compression", "zip")
    # An empty DateTime stops OpenImageIO stamping the write time, so identical scenes give
    # byte-identical files.
    spec.attribute("DateTime", "")
    for key, value in attributes.items():
        spec.attribute(key, value)
    return spec


def write_exr(path, scene, result, overwrite=False):
    """Write a simulated CCD to a multi-part OpenEXR file, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (any extension; the format is always OpenEXR).
    scene : inject.config.Scene
        The scene, for the FITS primary header cards.
    result : inject.scene.SceneResult
        Arrays (electrons) and truth.
    overwrite : bool
        Replace an existing ``path``.

    Raises
    ------
    OutputError
        ``path`` exists without ``overwrite``, cannot be written, or OpenImageIO fails.
    """
    import OpenImageIO as oiio  # heavy import, only needed here

    path = str(path)
    height, width = result.image.shape
    # [::-1]: FITS row 0 (bottom) becomes the last EXR row (see ROW_ORDER). The arrays must be
    # (h, w, nchannels) and contiguous: a 2-D array is accepted and written as garbage.
    pixels = np.ascontiguousarray(np.stack(
        [np.asarray(getattr(result, name.lower()), dtype=np.float32) for name in FLOAT_CHANNELS],
        axis=-1)[::-1])
    # int32 -> uint32 keeps every bit (bit 31 included); the FITS MASK is int32.
    mask = np.ascontiguousarray(
        np.asarray(result.mask).astype(np.int32).view(np.uint32)[::-1, :, np.newaxis])
    shared = {"inject:row_order": ROW_ORDER, "inject:units": json.dumps(UNITS)}
    image_spec = _spec(oiio, width, height, FLOAT_CHANNELS, oiio.FLOAT, IMAGE_PART, {
        "inject:fits_header": header_text(primary_header(scene)),
        "inject:truth": json.dumps(result.truth, default=_json_default),
        **shared})
    mask_spec = _spec(oiio, width, height, ("MASK",), oiio.UINT, MASK_PART, {
        "inject:mask_planes": json.dumps(MASK_PLANES), **shared})

    with atomic_path(path, overwrite) as tmp:
        out = oiio.ImageOutput.create("openexr")
        if out is None:
            raise OutputError(f"{path}: OpenImageIO has no OpenEXR writer ({oiio.geterror()})")
        ok, error = False, ""
        try:
            ok = (out.open(tmp, [image_spec, mask_spec])
                  and out.write_image(pixels)
                  and out.open(tmp, mask_spec, "AppendSubimage")
                  and out.write_image(mask))
            error = out.geterror()
        finally:
            # Closed whatever stopped the write (an error, Ctrl-C, SIGTERM), so the file is
            # released before atomic_path removes it; ``ok`` is set before the try, as the
            # stop may come before the write's result is assigned.
            closed = out.close()
        if not (ok and closed):
            raise OutputError(f"{path}: cannot write EXR ({error or oiio.geterror()})")


def read_exr(path):
    """Read a file written by :func:`write_exr`.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    dict
        ``image``, ``variance``, ``streak_model`` (float32), ``mask`` (int32, the FITS type,
        bit for bit), all indexed ``[y, x]`` with FITS row order; ``header``
        (:class:`astropy.io.fits.Header`), ``mask_planes`` (dict), ``truth`` (list of dict).

    Raises
    ------
    FileFormatError
        The file cannot be opened or lacks the parts, channels or attributes written by
        :func:`write_exr`.
    """
    import OpenImageIO as oiio

    path = str(path)
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise FileFormatError(f"{path}: cannot read as OpenEXR ({oiio.geterror()})")
    parts = {}
    try:
        index = 0
        while inp.seek_subimage(index, 0):
            spec = inp.spec()
            name = spec.getattribute("name") or spec.getattribute("oiio:subimagename")
            # UINT for the mask: an integer read with no conversion (reading it as FLOAT would
            # normalise it to [0, 1]).
            fmt = oiio.UINT if name == MASK_PART else oiio.FLOAT
            data = inp.read_image(fmt)
            if data is None:
                raise FileFormatError(f"{path}: cannot read part {name!r} ({inp.geterror()})")
            parts[name] = (spec, data)
            index += 1
    finally:
        inp.close()

    missing = {IMAGE_PART, MASK_PART} - parts.keys()
    if missing:
        raise FileFormatError(f"{path}: not an inject EXR (no part {sorted(missing)[0]!r})")
    image_spec, pixels = parts[IMAGE_PART]
    mask_spec, mask = parts[MASK_PART]

    def attribute(spec, key):
        value = spec.getattribute(key)
        if not isinstance(value, str):
            raise FileFormatError(f"{path}: not an inject EXR (no attribute {key!r})")
        return value

    def rows(array):
        # Undo the flip of write_exr; copy so callers get ordinary C-ordered arrays.
        if attribute(image_spec, "inject:row_order").startswith("flipped"):
            array = array[::-1]
        return np.ascontiguousarray(array)

    names = list(image_spec.channelnames)  # stored sorted by name, not in write order
    out = {}
    for channel in FLOAT_CHANNELS:
        if channel not in names:
            raise FileFormatError(f"{path}: not an inject EXR (no channel {channel!r})")
        out[channel.lower()] = rows(pixels[:, :, names.index(channel)].astype(np.float32))
    out["mask"] = rows(mask[:, :, 0].astype(np.uint32).view(np.int32))
    out["header"] = fits.Header.fromstring(attribute(image_spec, "inject:fits_header"),
                                           sep=HEADER_SEP)
    out["mask_planes"] = json.loads(attribute(mask_spec, "inject:mask_planes"))
    out["truth"] = json.loads(attribute(image_spec, "inject:truth"))
    return out
