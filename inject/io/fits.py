"""FITS output in LSST afw's MaskedImage layout: IMAGE, MASK, VARIANCE, then STREAK_MODEL,
TRUTH and TRUTH_VERTICES (and RAW).

HDUs 1-3 follow what afw writes (``MaskedImage::writeFits``, ``ExposureInfo::_startWriteFits``,
``Fits::writeImage``) so that afw and LSST's pure-Python ``lsst-images`` read the file as a
MaskedImage: ``EXTTYPE`` and ``INHERIT = T`` on each of them, the image origin xy0 as the
``LTV1/2`` cards and afw's linear "A" WCS (``CTYPE1A = 'LINEAR'``, ...), the celestial WCS on all
three, and the mask planes of :mod:`inject.maskplanes` (afw's ``MP_`` cards and lsst-images'
``MSKN/MSKM/MSKD`` cards). The primary header has the cards afw's VisitInfo uses (``EXPTIME``,
``DATE-AVG`` + ``TIMESYS``, ``BORE-RA/DEC``, ``BORE-ROTANG`` + ``ROTTYPE``) and ``FILTER``.
"""
import hashlib
import io
import os
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.time import Time, TimeDelta

import inject
from inject.errors import OutputError
from inject.io.atomic import atomic_path
from inject.io.gzip_tiles import reproducible_gzip_tiles
from inject.maskplanes import FLAG_CLIPPED, FLAG_OFF_IMAGE, FLAG_SATURATED, mask_header
from inject.truth import TRUTH_COLUMNS, VERTEX_COLUMNS, complete, vertex_records

reproducible_gzip_tiles()

#: Extension types of afw's MaskedImage HDUs 1-3, in that order.
MASKED_IMAGE_TYPES = ("IMAGE", "MASK", "VARIANCE")

#: The longest string value that fits on one 80-column FITS card (FITS 4.0, 4.2.1.1).
CARD_STRING_MAX = 68

#: How a FITS output may be named (lower case).
FITS_EXTENSIONS = (".fits", ".fit", ".fts")


def check_fits_name(path, compressed=False):
    """Raise :class:`~inject.errors.OutputError` unless ``path`` is named as a FITS file:
    :data:`FITS_EXTENSIONS`, and with ``compressed`` also those followed by ``.gz`` (the file
    is gzipped) or ``.fz`` (tile-compressed HDUs), so that a picture name (``.png``) never
    holds FITS bytes."""
    name = os.path.basename(os.fspath(path)).lower()
    allowed = FITS_EXTENSIONS
    if compressed:
        allowed += tuple(ext + ".gz" for ext in FITS_EXTENSIONS) + (".fz",)
    if not name.endswith(allowed):
        names = ", ".join(FITS_EXTENSIONS) + (" (.gz after them to gzip it) or .fz"
                                              if compressed else "")
        raise OutputError(f"{path}: the output is a FITS file: name it {names}")


def version_card():
    """The ``INJVER`` card, ``(value, comment)``: inject's version, on one 80-column card.

    Returns
    -------
    tuple of str
        :data:`inject.__version__`, cut at :data:`CARD_STRING_MAX` characters (longer than
        any version inject makes itself), and the comment, left out when the card has no
        room for it.
    """
    value = inject.__version__[:CARD_STRING_MAX]
    comment = "inject version"
    # KEYWORD= (10 columns), the quoted value (at least 8 wide), " / " and the comment.
    if 10 + max(len(value), 8) + 2 + 3 + len(comment) > 80:
        comment = ""  # astropy would cut it with a warning
    return value, comment


def time_cards(scene):
    """FITS cards of the exposure's time, when the scene has one (``{}`` otherwise).

    As LSSTCam's headers and afw's VisitInfo have them: ``TIMESYS = 'TAI'`` and the dates in
    TAI (the FITS standard reads DATE-* and MJD-* in TIMESYS's scale; TAI - UTC is 37 s in
    2026): ``DATE-OBS``/``MJD-OBS`` the exposure start (the UTC start in the comment),
    ``DATE-AVG``/``MJD-AVG`` its middle (what afw takes as the VisitInfo date), ``DATE-END``
    /``MJD-END`` its end.
    """
    if scene.time is None:
        return {}

    start = Time(scene.time, scale="utc")
    cards = {"TIMESYS": ("TAI", "time scale of DATE-* and MJD-*")}
    for key, t, what in (("OBS", start, "exposure start"),
                         ("AVG", start + TimeDelta(scene.exptime / 2, format="sec"),
                          "middle of the exposure"),
                         ("END", start + TimeDelta(scene.exptime, format="sec"),
                          "exposure end")):
        tai = t.tai
        cards[f"DATE-{key}"] = (tai.isot, f"{what} (TAI)")
        cards[f"MJD-{key}"] = (float(tai.mjd), f"[d] {what}, MJD (TAI)")
    return cards


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
    hdr["INJVER"] = version_card()
    hdr["BAND"] = (scene.band, "LSST filter")
    hdr["FILTER"] = (scene.band, "band (afw FilterLabel band)")
    hdr["EXPTIME"] = (scene.exptime, "[s] exposure time")
    for key, card in time_cards(scene).items():  # a scene with an exposure start (time:)
        hdr[key] = card
    pointing = scene.pointing
    if pointing is not None:
        rotation = float(pointing.rotation_deg)
        hdr["BORE-RA"] = (float(pointing.ra_deg), "[deg] ICRS RA of the pointing")
        hdr["BORE-DEC"] = (float(pointing.dec_deg), "[deg] ICRS Dec of the pointing")
        hdr["HIERARCH BORE-ROTANG"] = (rotation, "[deg] sky rotation angle (rotSkyPos)")
        hdr["ROTTYPE"] = ("SKY", "type of BORE-ROTANG (afw RotType)")
        hdr["ROTPA"] = (rotation, "[deg] sky position angle of the camera")
        hdr["ROTCOORD"] = ("sky", "frame of ROTPA")
    hdr["SEEING"] = (scene.seeing, "[arcsec] atmospheric FWHM (Kolmogorov)")
    hdr["PUPIL"] = (scene.pupil, "defocus kernel: annulus or rubin (traced)")
    hdr["FOCUSDZ"] = (float(scene.focus_offset_um), "[um] detector from design focus (rubin)")
    if scene.rotator_deg is not None:  # only when given: files without it keep their bytes
        hdr["HIERARCH ROTTELPOS"] = (float(scene.rotator_deg), "[deg] camera rotator angle")
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


def _table(records, spec, name):
    """A binary-table HDU of ``records`` with the columns of ``spec`` (name -> (dtype, unit,
    description)), in their order and types, with their units, whether there are records or
    not."""
    # TUNITn for the units FITS knows; "electron" is none of them (readers would warn), so
    # the charge columns say it in their names (``_e``).
    columns = [fits.Column(name=column, format={"i4": "J", "f8": "D"}[dtype],
                           unit=unit if unit and unit != "electron" else None,
                           array=np.array([r[column] for r in records], dtype=dtype))
               for column, (dtype, unit, _) in spec.items()]
    return fits.BinTableHDU.from_columns(columns, name=name)


def truth_table(rows):
    """The TRUTH binary-table HDU: the columns of :data:`inject.truth.TRUTH_COLUMNS`, in their
    order and types, with their units, whether there are rows or not."""
    hdu = _table(complete(rows), TRUTH_COLUMNS, "TRUTH")
    hdu.header["INJVER"] = version_card()  # also in the files add-streak writes into
    hdu.header["FLAG_OFF"] = (FLAG_OFF_IMAGE, "flag bit: track misses the image")
    hdu.header["FLAG_CLP"] = (FLAG_CLIPPED, "flag bit: part of the streak is off the image")
    hdu.header["FLAG_SAT"] = (FLAG_SATURATED, "flag bit: streak saturates")
    return hdu


def vertices_table(rows):
    """The TRUTH_VERTICES binary-table HDU of TRUTH rows: the columns of
    :data:`inject.truth.VERTEX_COLUMNS`, one record per vertex of each row's part of its track
    (:func:`inject.truth.vertex_records`), whether there are rows or not."""
    hdu = _table(vertex_records(rows), VERTEX_COLUMNS, "TRUTH_VERTICES")
    hdu.header["INJVER"] = version_card()
    return hdu


def read_truth(source):
    """The TRUTH rows of a FITS file, each with its ``vertices`` from TRUTH_VERTICES.

    Parameters
    ----------
    source : str, os.PathLike or astropy.io.fits.HDUList
        The file, or its HDUs.

    Returns
    -------
    list of dict
        One per TRUTH row, its columns as Python numbers, and ``vertices``: ``((x, y), ...)``
        in order along the part, or the row's ends ``(x0, y0), (x1, y1)`` when the file has
        no TRUTH_VERTICES (written before it existed); empty without a TRUTH table.
    """
    if not isinstance(source, fits.HDUList):
        with fits.open(source) as hdus:
            return read_truth(hdus)
    names = [hdu.name for hdu in source]
    if "TRUTH" not in names:
        return []
    table = Table(source["TRUTH"].data)
    rows = [{k: row[k].item() if hasattr(row[k], "item") else row[k] for k in table.colnames}
            for row in table]
    if "TRUTH_VERTICES" in names:
        points = Table(source["TRUTH_VERTICES"].data)
        for i, row in enumerate(rows):
            mine = points[points["row"] == i]
            mine = mine[np.argsort(mine["vertex"], kind="stable")]
            if len(mine):
                row["vertices"] = tuple(zip(mine["x"].tolist(), mine["y"].tolist()))
    return rows


def raw_header(sections, bias):
    """Cards of the RAW HDU (the amplifiers' readout in ADU, with bias, prescan and
    overscan): each amplifier's data section, image section, gain and read noise."""
    hdr = fits.Header()
    hdr["BUNIT"] = "adu"
    hdr["BIAS"] = (bias, "[adu] bias level added to every pixel")
    for sec in sections:
        key = f"A{sec['amp']:02d}"
        hdr[f"HIERARCH {key} DATASEC"] = sec["datasec"]
        hdr[f"HIERARCH {key} IMAGESEC"] = sec["imagesec"]
        hdr[f"HIERARCH {key} GAIN"] = sec["gain"]
        hdr[f"HIERARCH {key} RDNOISE"] = sec["read_noise"]
    return hdr


def vertices_csv_path(path):
    """Where :func:`write_truth_csv` writes the vertices beside the truth CSV ``path``:
    ``_vertices`` before its extension (``truth.csv`` -> ``truth_vertices.csv``)."""
    stem, ext = os.path.splitext(os.fspath(path))
    return f"{stem}_vertices{ext}"


def write_truth_csv(path, rows, overwrite=False):
    """The truth table as CSV (one row per streak) at ``path``, and its TRUTH_VERTICES as CSV
    at :func:`vertices_csv_path`, each written atomically."""
    for target, hdu in ((path, truth_table(rows)), (vertices_csv_path(path),
                                                    vertices_table(rows))):
        with atomic_path(target, overwrite) as tmp:
            Table(hdu.data).write(tmp, format="ascii.csv", overwrite=True)


class _Hasher:
    """SHA-256 of a file's bytes computed on a thread of its own while they are written, so
    the hash runs beside the writing and the flush to disk that follows (hashlib releases
    the GIL); as a context manager, the thread is joined on the way out.

    Pieces are hashed in the order given. A piece must not change until it is hashed:
    :meth:`update` copies a small one; a large one is a buffer of :meth:`ring`, which hands
    a buffer out again only once its last piece is hashed. ``enabled=False``: nothing is
    hashed and :meth:`hexdigest` is None.
    """

    #: Buffers in a :meth:`ring`: how far the writer may run ahead of the hash.
    RING = 8

    def __init__(self, enabled=True):
        self._digest = hashlib.sha256() if enabled else None
        self._pool = ThreadPoolExecutor(1) if enabled else None
        # id of a ring buffer -> the future of its last piece (an id reused by a later
        # ring's buffer at most waits for an earlier piece: the thread hashes in order).
        self._done = {}
        self._last = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=exc[0] is not None)
        return False

    def update(self, view, buffer=None):
        """Queue the bytes ``view`` (a piece of ring ``buffer``, or anything: copied)."""
        if self._digest is None:
            return
        if buffer is None:
            view = bytes(view)
        self._last = self._pool.submit(self._digest.update, view)
        if buffer is not None:
            self._done[id(buffer)] = self._last

    def ring(self, dtype, size):
        """An endless cycle of :attr:`RING` arrays of ``size`` items of ``dtype``, each
        handed out once the hash is done with what was last written from it."""
        buffers = [np.empty(size, dtype)
                   for _ in range(1 if self._digest is None else self.RING)]
        while True:
            for buffer in buffers:
                pending = self._done.pop(id(buffer), None)
                if pending is not None:
                    pending.result()
                yield buffer

    def hexdigest(self):
        """The digest of every piece (waits for them), hex; None when not enabled."""
        if self._digest is None:
            return None
        if self._last is not None:
            self._last.result()  # one thread, in order: the last piece is hashed last
        return self._digest.hexdigest()


class _DigestStream:
    """A write-only stream to a binary file that hands what goes through it to a
    :class:`_Hasher`, so a file's digest needs no second read.

    Runs of zero bytes of at least :attr:`HOLE` (a zero STREAK_MODEL, most of a MASK) are
    skipped over with a seek instead of written: the file system leaves a hole that reads
    back as zeros (the file's bytes, and its digest, are those of a dense write; nothing is
    copied to the disk). The file must be truncated at its final size when done.
    """

    #: Chunk checked for zeros, bytes (a multiple of the file system's 4 KiB blocks).
    HOLE = 1 << 20

    def __init__(self, out, hasher):
        self._out, self.hasher = out, hasher

    def write(self, data, buffer=None):
        """Write ``data`` (from ring ``buffer`` of the hasher, if so: not copied)."""
        view = memoryview(data).cast("B")
        self.hasher.update(view, buffer)
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


#: FITS blocks: every header and data unit is padded to a multiple of this many bytes.
BLOCK = 2880


def _stand_in(array, dtype):
    """An array of ``array``'s shape and the written ``dtype`` for astropy to build an image
    header from (BITPIX, NAXISn): zero-strided, so it costs no memory; the data themselves go
    through :func:`_write_image_data`."""
    return np.broadcast_to(np.zeros((), dtype), np.shape(array))


def _write_image_data(stream, array, dtype):
    """Write ``array`` as FITS image data of ``dtype`` (big-endian), padded to a block.

    A MiB at a time: each piece is converted (byte-swapped) into a buffer that stays in the
    core's cache and written from there, instead of astropy's in-place byte swap of the
    whole array and back (two passes over memory); the hasher's thread hashes it meanwhile.
    """
    written = np.dtype(dtype).newbyteorder(">")
    array = np.asarray(array)
    step = _DigestStream.HOLE // written.itemsize
    size = min(step, array.size)
    if array.size and all(s == 0 for s in array.strides):  # one value (a zero model)
        constant = np.full(size, array.flat[0], written)  # never refilled: no ring
        for start in range(0, array.size, step):
            stream.write(constant[:min(step, array.size - start)], constant)
    else:
        flat = np.ascontiguousarray(array).reshape(-1)
        ring = stream.hasher.ring(written, size)
        for start in range(0, array.size, step):
            buffer = next(ring)
            piece = buffer[:min(step, array.size - start)]
            piece[...] = flat[start:start + piece.size]
            stream.write(piece, buffer)
    nbytes = array.size * written.itemsize
    if nbytes % BLOCK:
        stream.write(bytes(BLOCK - nbytes % BLOCK))


def _write_hdus(stream, hdus, planes):
    """Write ``hdus`` to ``stream`` with the bytes astropy's ``HDUList.writeto`` gives.

    Headers are astropy's (verified, ``EXTEND`` set, BITPIX and NAXISn from the data);
    ``planes`` maps the index of an image HDU to the array whose data it holds (the HDU
    itself holds a :func:`_stand_in`), streamed by :func:`_write_image_data`. Other HDUs
    with data (the TRUTH tables) are small: :func:`_extension_bytes`.
    """
    hdus.update_extend()
    hdus.verify("exception")
    for index, hdu in enumerate(hdus):
        if index in planes:
            hdu.update_header()
            stream.write(hdu.header.tostring().encode("ascii"))
            _write_image_data(stream, planes[index], hdu.data.dtype)
        elif index == 0 and hdu.data is None:
            stream.write(hdu.header.tostring().encode("ascii"))
        else:
            stream.write(_extension_bytes(hdu))


def _extension_bytes(hdu):
    """The bytes of an extension HDU with data, as astropy writes it after an empty primary
    HDU (whose block is dropped)."""
    buffer = io.BytesIO()
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(buffer)
    return buffer.getvalue()[len(fits.PrimaryHDU().header.tostring()):]


@lru_cache(maxsize=4)
def _empty_truth_tables(version):
    """The TRUTH and TRUTH_VERTICES HDUs of no rows as written, for the ``version`` card they
    carry: the same bytes for every CCD no streak reaches, so built once per process."""
    return b"".join(_extension_bytes(hdu) for hdu in (truth_table([]), vertices_table([])))


#: Tile compression of a CCD file's image planes (:func:`write_exposure`'s ``compression``).
#: ``lossless``: GZIP with byte shuffling (``GZIP_2``) on every plane, as the ``lossless`` FITS
#: recipe of LSST's butler writes them; floats are not quantised. ``lossy``: IMAGE and
#: VARIANCE quantised as LSST's lossy recipe does (``RICE_1``, a step of a tenth of each
#: tile's noise, ``quantize_level`` 10) with subtractive dithering that keeps zeros exact
#: (``SUBTRACTIVE_DITHER_2``, seeded from the tile's checksum, so the bytes are reproducible):
#: a uniform error of that step adds ``1 / (10 sqrt(12)) = 0.029`` of the noise in
#: quadrature. MASK, STREAK_MODEL and RAW stay lossless in both.
COMPRESSIONS = ("lossless", "lossy")
#: Quantisation step of ``lossy``, as a fraction of a tile's noise: ``1 / LOSSY_LEVEL``.
LOSSY_LEVEL = 10.0
#: The rms a ``lossy`` write adds, in units of the noise: a uniform error over a step.
LOSSY_NOISE = 1.0 / (LOSSY_LEVEL * 12 ** 0.5)


def _compressed_hdu(array, dtype, header, name, compression):
    """A tile-compressed image HDU (one row of the image per tile, as cfitsio's default)."""
    lossy = compression == "lossy" and name in ("IMAGE", "VARIANCE")
    if lossy:
        options = {"compression_type": "RICE_1", "quantize_level": LOSSY_LEVEL,
                   "quantize_method": 2, "dither_seed": -1}
    else:
        options = {"compression_type": "GZIP_2", "quantize_level": 0.0}
    data = np.ascontiguousarray(array, dtype=dtype)
    return fits.CompImageHDU(data, header=header, name=name, **options)


def check_compression(compression):
    """``compression`` checked: None (no compression) or one of :data:`COMPRESSIONS`."""
    if compression is not None and compression not in COMPRESSIONS:
        from inject.errors import InputError

        raise InputError("--compression", compression, f"choose {' or '.join(COMPRESSIONS)}")
    return compression


def write_exposure(path, scene, result, gain, wcs_header=None, overwrite=False,
                   primary_cards=None, xy0=(0, 0), compression=None, digest=True):
    """Write a simulated CCD to ``path`` atomically (afw's MaskedImage layout, see above).

    The planes' data are streamed (see :func:`_write_image_data`); the bytes are those of
    astropy's ``writeto``. A STREAK_MODEL of zeros (a CCD no streak reaches) is a zero view
    that the writer leaves as a hole in the file (as it does for any MiB of zeros, most of a
    MASK), which reads back as the same zero bytes: the file's bytes, and so its digest, are
    those of a dense write.

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
    compression : str, optional
        ``lossless`` or ``lossy`` (:data:`COMPRESSIONS`): the image planes tile-compressed
        (``.fits`` still: readers see through the compression); None writes them plain.
    digest : bool
        Hash the bytes written; False spares a plain write that pass over its 260 MB (about
        0.15 s for a full CCD) when the caller has no use for the digest.

    Returns
    -------
    str or None
        SHA-256 of the file's bytes (hex), computed as they were written; None for a plain
        write with ``digest=False``.
    """
    check_compression(compression)
    image_hdr = plane_header("IMAGE", xy0, wcs_header)
    image_hdr["BUNIT"] = (scene.units, "pixel values")
    image_hdr["GAIN"] = (gain, "[e-/ADU] detector gain")
    mask_hdr = mask_header(plane_header("MASK", xy0, wcs_header))
    variance_hdr = plane_header("VARIANCE", xy0, wcs_header)
    variance_hdr["BUNIT"] = (f"{scene.units}**2", "variance of the pixel values")
    planes = [(result.image, np.float32, image_hdr, "IMAGE"),
              (result.mask, np.int32, mask_hdr, "MASK"),
              (result.variance, np.float32, variance_hdr, "VARIANCE"),
              (result.streak_model, np.float32, None, "STREAK_MODEL")]
    hdus = fits.HDUList([fits.PrimaryHDU(header=primary_header(scene, primary_cards))])
    hdus.extend(fits.ImageHDU(_stand_in(a, dtype), header=h, name=n) for a, dtype, h, n in planes)
    hdus["STREAK_MODEL"].header["BUNIT"] = "electron"
    # A CCD no streak reaches, with no HDU after the tables: the same tables as every such
    # CCD, written last from their bytes.
    empty_tables = not result.truth and result.raw is None and compression is None
    if not empty_tables:
        hdus.append(truth_table(result.truth))
        hdus.append(vertices_table(result.truth))
    data = {k + 1: plane[0] for k, plane in enumerate(planes)}
    if result.raw is not None:
        data[len(hdus)] = result.raw
        hdus.append(fits.ImageHDU(_stand_in(result.raw, np.float32), name="RAW"))
        hdus["RAW"].header.extend(raw_header(result.raw_sections, scene.detector.bias))
    if compression is not None:
        return _write_compressed(path, hdus, data, overwrite, compression)
    # The hash goes on while the file is flushed to disk and moved into place.
    with _Hasher(digest) as hasher, atomic_path(path, overwrite) as tmp:
        with open(tmp, "wb") as out:
            stream = _DigestStream(out, hasher)
            _write_hdus(stream, hdus, data)
            if empty_tables:
                stream.write(_empty_truth_tables(version_card()))
            out.truncate()  # a hole at the very end still counts in the file's size
    return hasher.hexdigest()


def _write_compressed(path, hdus, data, overwrite, compression):
    """Write ``hdus`` with the image planes in ``data`` tile-compressed; the file's SHA-256."""
    out = fits.HDUList([hdus[0]])
    for index, hdu in enumerate(hdus):
        if index in data:
            header = hdu.header.copy()
            for key in ("XTENSION", "BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "PCOUNT", "GCOUNT",
                        "EXTNAME"):
                header.remove(key, ignore_missing=True)
            out.append(_compressed_hdu(data[index], hdu.data.dtype, header, hdu.name,
                                       compression))
        elif index:
            out.append(hdu)
    buffer = io.BytesIO()
    out.writeto(buffer)
    with atomic_path(path, overwrite) as tmp:
        with open(tmp, "wb") as stream:
            stream.write(buffer.getbuffer())
    return hashlib.sha256(buffer.getbuffer()).hexdigest()
