"""Compressed outputs with no time of writing in them: the same data give the same bytes."""
import functools
import gzip


def reproducible_gzip_tiles():
    """Make astropy's GZIP tile codecs stamp every tile with the time 0 rather than the time
    of writing, so that the same data written twice give the same bytes (and digests).

    The gzip header's modification time is the only part of a GZIP_1/GZIP_2 tile that
    depends on when it was written; readers (astropy, cfitsio) ignore it. astropy's codecs
    call ``gzip.compress`` without its ``mtime``; if a version no longer does so, nothing is
    changed. The writers (:mod:`inject.io.fits`, :mod:`inject.io.reader`) call it when
    imported; calling it again does nothing.
    """
    try:
        from astropy.io.fits.hdu.compressed import _codecs
    except ImportError:  # another layout of astropy's compression: left as it is
        return
    if getattr(_codecs, "gzip_compress", None) is gzip.compress:
        _codecs.gzip_compress = functools.partial(gzip.compress, mtime=0)

