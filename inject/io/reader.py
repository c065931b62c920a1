"""Reading a user's FITS image for injection, and writing it back changed only where asked.

Any 2-D image HDU is accepted; LSST MaskedImage/Exposure files are recognised as afw's
``MaskedImageFitsReader`` does: IMAGE, MASK and VARIANCE by their ``EXTTYPE`` (else their
``EXTNAME``), whatever their names, with the file's own mask pixel type and plane bits.

Writing (:meth:`InputExposure.write`) copies every HDU that was not changed byte for byte from
the input (archive tables and their heap, checksums and all), and rewrites the pixels it was
asked to change in the file's own storage: integers stay integers of the same BITPIX, BZERO
and BSCALE (rounded, clipped at the type's range), floats stay floats, so that every pixel the
change does not reach comes back bit-identical; undefined integer pixels (``BLANK``) are never
changed. A tile-compressed image is compressed again losslessly: integers with their own
algorithm (RICE_1 for a lossy HCOMPRESS; the same integers, scaling and ``BLANK`` when astropy
shows them as floats), floats that were
quantised (lossy) with GZIP_2 and no quantisation (``quantize_level=0``), which keeps exactly
the values the input decompresses to (the file grows).
"""
import gzip
import io
import os
import warnings
from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning
from astropy.wcs import WCS, FITSFixedWarning

from inject.errors import FileFormatError
from inject.io.atomic import atomic_path
from inject.io.gzip_tiles import reproducible_gzip_tiles

reproducible_gzip_tiles()

#: numpy type of each FITS BITPIX (big-endian, as stored).
_BITPIX = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
_BLOCK = 2880


@dataclass
class InputExposure:
    """A FITS file's HDUs (copied into memory) and where the science image is.

    ``mask_index`` and ``variance_index`` are set for LSST MaskedImage files (HDUs typed or
    named MASK and VARIANCE of the image's shape). The file's bytes are kept so that
    :meth:`write` can copy the HDUs nobody changed as they were.
    """

    hdus: fits.HDUList
    image_index: int
    mask_index: int | None
    variance_index: int | None
    source: bytes | None = field(default=None, repr=False)
    path: str | None = None  # the file read, for messages
    spans: list = field(default_factory=list, repr=False)  # (header, data, end) per HDU
    _originals: list = field(default_factory=list, repr=False)
    _stored: dict = field(default_factory=dict, repr=False)  # index -> new stored array
    _headers: dict = field(default_factory=dict, repr=False)  # index -> the file's header
    _changed: set = field(default_factory=set, repr=False)

    @property
    def image_hdu(self):
        return self.hdus[self.image_index]

    @property
    def image(self):
        """The science image as native-endian float64 (astropy arrays are big-endian)."""
        return np.asarray(self.image_hdu.data, dtype=np.float64)

    def header_value(self, *keys):
        """First of ``keys`` found in the image header, then the primary header, or None."""
        for header in (self.image_hdu.header, self.hdus[0].header):
            for key in keys:
                if key in header:
                    return header[key]
        return None

    @property
    def wcs(self):
        """Celestial WCS of the image (SIP distortion included), or None if it has none."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            try:
                wcs = WCS(self.image_hdu.header)
            except Exception:  # astropy raises many kinds for broken WCS headers
                return None
        return wcs.celestial if wcs.has_celestial else None

    @property
    def xy0(self):
        """LSST parent pixel ``(x0, y0)`` of array pixel (0, 0): from ``LTV1/2`` (afw and
        lsst-images prefer it), else afw's linear "A" WCS, else (0, 0)."""
        header = self.image_hdu.header
        if "LTV1" in header and "LTV2" in header:
            return (-int(round(header["LTV1"])), -int(round(header["LTV2"])))
        if header.get("CTYPE1A") == "LINEAR" and "CRVAL1A" in header and "CRVAL2A" in header:
            return tuple(int(round(header[f"CRVAL{i}A"] - (header.get(f"CRPIX{i}A", 1.0) - 1)))
                         for i in (1, 2))
        return (0, 0)

    # -- changing pixels in the file's storage -------------------------------------------

    def _is_plain(self, index):
        """Whether HDU ``index`` is an uncompressed image whose stored pixels are known."""
        hdu = self.hdus[index]
        return (self.source is not None and index < len(self._originals)
                and hdu is self._originals[index] and not isinstance(hdu, fits.CompImageHDU))

    def file_header(self, index):
        """The header of HDU ``index`` as the file has it (BZERO and BSCALE included); edit
        it, not ``hdus[index].header``, to change the cards :meth:`write` writes."""
        if not self._is_plain(index):
            return self.hdus[index].header
        if index not in self._headers:
            start, data, _ = self.spans[index]
            self._headers[index] = fits.Header.fromstring(
                self.source[start:data].decode("ascii"))
        return self._headers[index]

    def _stored_array(self, index):
        """``(stored, bscale, bzero, blank)`` of a plain image HDU: its pixels as in the file."""
        if index in self._stored:
            stored = self._stored[index]
        else:
            header = self.file_header(index)
            start, data, _ = self.spans[index]
            shape = tuple(header[f"NAXIS{i}"] for i in range(header["NAXIS"], 0, -1))
            stored = np.frombuffer(self.source, dtype=_BITPIX[header["BITPIX"]],
                                   count=int(np.prod(shape)), offset=data).reshape(shape)
            stored = stored.astype(stored.dtype.newbyteorder("="))
        header = self.file_header(index)
        blank = header.get("BLANK") if stored.dtype.kind in "iu" else None
        return stored, float(header.get("BSCALE", 1.0)), float(header.get("BZERO", 0.0)), blank

    def defined(self, index=None):
        """Pixels of HDU ``index`` (default: the image) that hold a value: finite, and not an
        integer image's undefined value (``BLANK``; astropy shows it as NaN when the HDU is
        scaled or compressed).

        Returns
        -------
        ndarray of bool
        """
        index = self.image_index if index is None else index
        hdu = self.hdus[index]
        data = np.asarray(hdu.data)
        defined = np.isfinite(data) if data.dtype.kind == "f" else np.ones(data.shape, bool)
        if self._is_plain(index):
            stored, _, _, blank = self._stored_array(index)
            if blank is not None:
                defined &= stored != blank
        elif data.dtype.kind in "iu" and hdu.header.get("BLANK") is not None:
            defined &= data != hdu.header["BLANK"]  # made in memory, unscaled
        return defined

    def _compressed_storage(self, index):
        """``(dtype, bscale, bzero, blank)`` of a tile-compressed HDU of the input that stores
        integers astropy shows as floats (scaled, or with ``BLANK``: NaN), else None."""
        hdu = self.hdus[index]
        if not (isinstance(hdu, fits.CompImageHDU) and self.source is not None
                and index < len(self._originals) and hdu is self._originals[index]
                and np.asarray(hdu.data).dtype.kind == "f"):
            return None
        start, data, _ = self.spans[index]
        table = fits.Header.fromstring(self.source[start:data].decode("ascii"))
        zbitpix = table.get("ZBITPIX")
        if zbitpix not in (8, 16, 32, 64):
            return None
        blank = table.get("BLANK", table.get("ZBLANK"))
        return (np.dtype(_BITPIX[zbitpix]).newbyteorder("="), float(table.get("BSCALE", 1.0)),
                float(table.get("BZERO", 0.0)), None if blank is None else int(blank))

    def add(self, index, delta, saturation=None):
        """Add ``delta`` (physical units) to the pixels of HDU ``index`` where it is not 0.

        Integer pixels are rounded and clipped at their type's range (one step inside it if
        ``BLANK`` is at that end: a clipped pixel stays defined); undefined (``BLANK``) pixels
        stay undefined; nothing else changes.

        Parameters
        ----------
        index : int
        delta : ndarray
            Of the HDU's shape.
        saturation : float, optional
            Physical value at and above which a changed integer pixel counts as saturated
            (default: the type's largest value, the ADC limit).

        Returns
        -------
        saturated : ndarray of bool
            Changed integer pixels at or above the saturation level (all False for floats).
        """
        sel = np.isfinite(delta) & (delta != 0) & self.defined(index)
        saturated = np.zeros(delta.shape, dtype=bool)
        hdu = self.hdus[index]
        if self._is_plain(index):
            stored, bscale, bzero, blank = self._stored_array(index)
            new = stored.copy()
            physical = stored[sel].astype(np.float64) * bscale + bzero + delta[sel]
            if stored.dtype.kind == "f":
                new[sel] = ((physical - bzero) / bscale).astype(stored.dtype)
            else:
                values, saturated[sel] = _to_integers(physical, stored.dtype, bscale, bzero,
                                                      blank, saturation)
                new[sel] = values.astype(stored.dtype)
            self._stored[index] = new
            values = new[sel].astype(np.float64) * bscale + bzero
        else:  # compressed (or made in memory): astropy's physical values
            data = np.asarray(hdu.data)
            physical = data[sel].astype(np.float64) + delta[sel]
            storage = self._compressed_storage(index)
            if storage is not None:  # integers shown as floats: rounded as they will be stored
                dtype, bscale, bzero, blank = storage
                values, saturated[sel] = _to_integers(physical, dtype, bscale, bzero, blank,
                                                      saturation)
                values = values * bscale + bzero
            elif data.dtype.kind == "f":
                values = physical
            else:
                blank = hdu.header.get("BLANK")
                values, saturated[sel] = _to_integers(physical, data.dtype, 1.0, 0.0, blank,
                                                      saturation)
            self._changed.add(index)
        memory = np.array(hdu.data)  # native copy, what readers of ``hdus`` see
        memory[sel] = values.astype(memory.dtype)
        hdu.data = memory
        return saturated

    def set_bits(self, index, bit, where, replace=False):
        """Set mask bit ``bit`` of HDU ``index`` (an integer image) where ``where`` is True;
        with ``replace``, clear it everywhere else (the plane becomes ``where``)."""
        hdu = self.hdus[index]
        one = np.int64(1) << bit

        def changed(values):
            if replace:
                values &= ~one
            values[where] |= one
            return values
        if self._is_plain(index):
            stored, bscale, bzero, _ = self._stored_array(index)
            if bscale != 1.0:
                raise FileFormatError(f"HDU {index}: a mask with BSCALE = {bscale} is not bits")
            offset = int(bzero)  # uint16 masks are int16 + BZERO 32768
            values = changed(stored.astype(np.int64) + offset)
            # Back to the stored type; bit 31 of an int32 mask wraps to the sign, as in afw.
            self._stored[index] = (values - offset).astype(stored.dtype)
        else:
            self._changed.add(index)
        memory = np.array(hdu.data)
        hdu.data = changed(memory.astype(np.int64)).astype(memory.dtype)

    def set_card(self, index, key, value, after=None):
        """Set card ``key`` of HDU ``index`` (in the file's header and in memory)."""
        for header in {id(h): h for h in (self.file_header(index),
                                          self.hdus[index].header)}.values():
            if key in header:
                header[key] = value
            else:
                header.set(key, value,
                           after=after if after is not None and after in header else None)
        if not self._is_plain(index):
            self._changed.add(index)

    def add_extnames(self):
        """Give IMAGE, MASK and VARIANCE typed by ``EXTTYPE`` but unnamed ``EXTNAME = EXTTYPE``,
        as afw writes them today: lsst-images' ``read_legacy`` needs the name."""
        for index in (self.image_index, self.mask_index, self.variance_index):
            if index is None or index == 0:
                continue
            header = self.file_header(index)
            exttype = str(header.get("EXTTYPE", "")).strip()
            if exttype and "EXTNAME" not in header:
                self.set_card(index, "EXTNAME", exttype, after="EXTTYPE")

    def mark_changed(self, index):
        """Have :meth:`write` write HDU ``index`` from memory (it was changed in place)."""
        self._changed.add(index)

    def name_plane(self, index, name):
        """The bit of mask plane ``name`` in MASK HDU ``index``, naming it on the first free
        bit (:func:`inject.maskplanes.plane_bit`) if it has none.

        Raises
        ------
        FileFormatError
            Every bit of the mask's pixel type is taken.
        """
        from inject.maskplanes import plane_bit

        header = self.file_header(index)
        before = set(header.keys())
        dtype = np.asarray(self.hdus[index].data).dtype
        bit = plane_bit(header, name, 8 * dtype.itemsize)
        if bit is None:
            raise FileFormatError(f"MASK (HDU {index}): no free bit for a {name} plane")
        memory = self.hdus[index].header
        if memory is not header:  # keep the in-memory header in step
            for key in header:
                if key not in before:
                    card = f"HIERARCH {key}" if len(key) > 8 else key
                    memory[card] = (header[key], header.comments[key])
        return bit

    def _plain_bytes(self, index, primary):
        """The bytes of plain HDU ``index``: the input's, with its new header and stored
        pixels where they changed."""
        start, data, end = self.spans[index]
        original = self.source[start:data]
        if index not in self._headers and index not in self._stored:
            return self.source[start:end]  # untouched: the input's bytes
        header = self.file_header(index)
        text = header.tostring().encode("ascii")
        if index not in self._stored and text == original:
            return self.source[start:end]
        if index in self._stored:
            stored = self._stored[index]
            raw = stored.astype(stored.dtype.newbyteorder(">")).tobytes()
            raw += b"\0" * (-len(raw) % _BLOCK)
        else:
            raw = self.source[data:end]
        content = (original if text == original else text) + raw
        if "CHECKSUM" in header or "DATASUM" in header:
            return _with_checksum(content, primary)
        return content

    # -- writing ---------------------------------------------------------------------------

    def write(self, path, overwrite=False):
        """Write the exposure to ``path`` atomically (see the module's notes).

        Raises
        ------
        OutputError
            ``path`` cannot be written.
        """
        with atomic_path(path, overwrite) as tmp:  # an OSError anywhere: OutputError
            content = self._content()
            with open(tmp, "wb") as out:
                if os.fspath(path).endswith(".gz"):
                    # No name or time in the gzip header: the same content, the same bytes.
                    with gzip.GzipFile(filename="", mode="wb", fileobj=out, mtime=0) as packed:
                        packed.write(content)
                else:
                    out.write(content)

    def _content(self):
        """The bytes of the whole file."""
        parts = []
        for index, hdu in enumerate(self.hdus):
            primary = index == 0
            original = (self.source is not None and index < len(self._originals)
                        and hdu is self._originals[index] and index not in self._changed)
            if original:  # plain, or compressed and untouched
                parts.append(self._plain_bytes(index, primary))
            else:
                storage = self._compressed_storage(index)
                parts.append(_serialise(_lossless(hdu, storage), primary,
                                        checksum="CHECKSUM" in hdu.header))
        return b"".join(parts)


def _to_integers(physical, dtype, bscale, bzero, blank, saturation):
    """Physical values as the stored integers of ``dtype`` (rounded, clipped at the type's
    range, kept off ``blank``), and whether each reaches ``saturation`` (default: the top)."""
    info = np.iinfo(dtype)
    low = info.min + 1 if blank == info.min else info.min
    high = info.max - 1 if blank == info.max else info.max
    values = np.clip(np.rint((physical - bzero) / bscale), low, high)
    top = high * bscale + bzero
    limit = top if saturation is None else min(saturation, top)
    return values, values * bscale + bzero >= limit


def _with_checksum(content, primary):
    """The bytes of one HDU with its CHECKSUM and DATASUM computed again (by astropy, on the
    stored values: no scaling on the way)."""
    prefix = b"" if primary else _serialise(fits.PrimaryHDU(), True)
    buffer = io.BytesIO()
    with fits.open(io.BytesIO(prefix + content), do_not_scale_image_data=True) as hdus:
        hdus.writeto(buffer, checksum=True)
    return buffer.getvalue()[len(prefix):]


def _lossless(hdu, storage=None):
    """``hdu``, or a copy of a tile-compressed one set to compress its pixels losslessly
    (``storage``: :meth:`InputExposure._compressed_storage`, for integers shown as floats)."""
    if not isinstance(hdu, fits.CompImageHDU):
        return hdu
    data = np.asarray(hdu.data)
    kind = hdu.compression_type
    if storage is not None:
        return _integers_compressed(hdu, data, storage)
    if data.dtype.kind == "f":
        if kind.startswith("GZIP") and not hdu.quantize_level:
            return hdu
        kind, level = "GZIP_2", 0  # no quantisation: the values as they are, bit for bit
    else:
        if kind == "HCOMPRESS_1" and hdu.hcomp_scale:
            kind = "RICE_1"  # HCOMPRESS with a scale is lossy for integers too
        level = hdu.quantize_level
    header = hdu.header.copy()
    for key in ("BZERO", "BSCALE"):  # astropy sets them again from the data's type
        header.remove(key, ignore_missing=True)
    return fits.CompImageHDU(data, header=header, name=hdu.name, compression_type=kind,
                             tile_shape=tuple(int(n) for n in hdu.tile_shape),
                             quantize_level=level)


def _integers_compressed(hdu, data, storage):
    """A tile-compressed copy of ``hdu`` storing ``data`` (physical floats, NaN undefined) as
    the integers, ``BSCALE``, ``BZERO`` and ``BLANK`` of ``storage``, losslessly."""
    dtype, bscale, bzero, blank = storage
    undefined = np.isnan(data)
    info = np.iinfo(dtype)
    stored = np.clip(np.rint((np.where(undefined, bzero, data) - bzero) / bscale),
                     info.min, info.max).astype(dtype)
    if blank is not None:
        stored[undefined] = blank
    kind = hdu.compression_type
    if kind == "HCOMPRESS_1" and hdu.hcomp_scale:
        kind = "RICE_1"
    header = hdu.header.copy()
    for key in ("BZERO", "BSCALE", "BLANK", "BITPIX"):
        header.remove(key, ignore_missing=True)
    new = fits.CompImageHDU(stored, header=header, name=hdu.name, compression_type=kind,
                            tile_shape=tuple(int(n) for n in hdu.tile_shape))
    # Set after the pixels, so that astropy writes them as they are and records the scaling.
    if bscale != 1.0 or bzero != 0.0:
        new.header["BSCALE"], new.header["BZERO"] = bscale, bzero
    if blank is not None:
        new.header["BLANK"] = blank
    return new


def _serialise(hdu, primary, checksum=False):
    """The bytes of one HDU as astropy writes it (as the primary HDU, or an extension)."""
    buffer = io.BytesIO()
    if primary:
        fits.HDUList([hdu]).writeto(buffer, checksum=checksum)
        return buffer.getvalue()
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(buffer, checksum=checksum)
    return buffer.getvalue()[_BLOCK:]  # an empty primary HDU is one block


def read_exposure(path):
    """Read ``path`` fully into memory (the file is closed and never modified).

    Raises
    ------
    FileFormatError
        If the file cannot be read or holds no 2-D image, or its MASK or VARIANCE does not
        match its IMAGE.
    """
    try:
        with open(path, "rb") as stream:
            source = stream.read()
        if source[:2] == b"\x1f\x8b":  # a gzipped file: offsets refer to its content
            source = gzip.decompress(source)
        with warnings.catch_warnings():
            # A truncated or corrupt file is an error here, not a warning to scroll past.
            warnings.simplefilter("error", fits.verify.VerifyWarning)
            warnings.simplefilter("error", AstropyUserWarning)  # e.g. "may have been truncated"
            # Opened on the bytes in memory and left open (no file handle): tables with a
            # heap read from it (astropy cannot copy those), and nothing refers to the file.
            hdus = fits.open(io.BytesIO(source), memmap=False)
            hdus.verify("exception")
            for hdu in hdus:
                hdu.data  # noqa: B018 -- read every HDU now, so a truncated one fails here
            spans = []
            for i in range(len(hdus)):
                info = hdus.fileinfo(i)
                spans.append((info["hdrLoc"], info["datLoc"], info["datLoc"] + info["datSpan"]))
    except FileNotFoundError:
        raise FileFormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise FileFormatError(f"{path}: not a readable FITS file (a directory)") from None
    except (OSError, EOFError, ValueError, fits.VerifyError, TypeError,
            fits.verify.VerifyWarning, AstropyUserWarning) as err:
        raise FileFormatError(f"{path}: not a readable FITS file ({err})") from None
    roles = {}
    for i, hdu in enumerate(hdus):
        role = str(hdu.header.get("EXTTYPE", "")).strip().upper() or hdu.name
        if role in ("IMAGE", "MASK", "VARIANCE") and role not in roles and _is_image(hdu):
            roles[role] = i
    if "IMAGE" in roles:
        image_index = roles["IMAGE"]
    else:
        candidates = [i for i, hdu in enumerate(hdus) if _is_image(hdu)]
        if not candidates:
            raise FileFormatError(f"{path}: no 2-D image HDU found")
        image_index = candidates[0]
    shape = hdus[image_index].data.shape
    for role in ("MASK", "VARIANCE"):
        index = roles.get(role)
        if index is not None and hdus[index].data.shape != shape:
            got = hdus[index].data.shape
            raise FileFormatError(f"{path}: {role} (HDU {index}) is {got[1]} x {got[0]}, "
                                  f"the image {shape[1]} x {shape[0]}")
    if "MASK" in roles and hdus[roles["MASK"]].data.dtype.kind not in "iu":
        raise FileFormatError(f"{path}: MASK (HDU {roles['MASK']}) holds "
                              f"{hdus[roles['MASK']].data.dtype} values, not integer bits")
    return InputExposure(hdus, image_index, roles.get("MASK"), roles.get("VARIANCE"),
                         source=source, path=os.fspath(path), spans=spans,
                         _originals=list(hdus))


def _is_image(hdu):
    return (isinstance(hdu, (fits.PrimaryHDU, fits.ImageHDU, fits.CompImageHDU))
            and hdu.data is not None and hdu.data.ndim == 2)
