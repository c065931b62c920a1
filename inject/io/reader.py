"""Reading a user's FITS image for injection: any 2-D image HDU, or an LSST-style
IMAGE/MASK/VARIANCE file."""
from dataclasses import dataclass

import warnings

import numpy as np
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning
from astropy.wcs import WCS, FITSFixedWarning

from ..errors import FileFormatError


@dataclass
class InputExposure:
    """A FITS file's HDUs (copied into memory) and where the science image is."""

    hdus: fits.HDUList
    image_index: int
    mask_index: int | None
    variance_index: int | None

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
        """Celestial WCS of the image, or None if its header has none."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            try:
                wcs = WCS(self.image_hdu.header)
            except Exception:  # astropy raises many kinds for broken WCS headers
                return None
        return wcs.celestial if wcs.has_celestial else None


def read_exposure(path):
    """Read ``path`` fully into memory (the file is closed and never modified).

    Raises
    ------
    FileFormatError
        If the file cannot be read or holds no 2-D image.
    """
    try:
        with warnings.catch_warnings():
            # A truncated or corrupt file is an error here, not a warning to scroll past.
            warnings.simplefilter("error", fits.verify.VerifyWarning)
            warnings.simplefilter("error", AstropyUserWarning)  # e.g. "may have been truncated"
            with fits.open(path, memmap=False) as opened:
                opened.verify("exception")
                hdus = fits.HDUList([hdu.copy() for hdu in opened])
    except FileNotFoundError:
        raise FileFormatError(f"{path}: no such file") from None
    except (OSError, ValueError, fits.VerifyError, TypeError, fits.verify.VerifyWarning,
            AstropyUserWarning) as err:
        raise FileFormatError(f"{path}: not a readable FITS file ({err})") from None
    names = [hdu.name for hdu in hdus]
    if "IMAGE" in names and _is_image(hdus[names.index("IMAGE")]):
        image_index = names.index("IMAGE")
    else:
        candidates = [i for i, hdu in enumerate(hdus) if _is_image(hdu)]
        if not candidates:
            raise FileFormatError(f"{path}: no 2-D image HDU found")
        image_index = candidates[0]

    def index_of(name):
        return names.index(name) if name in names and _is_image(hdus[names.index(name)]) else None

    return InputExposure(hdus, image_index, index_of("MASK"), index_of("VARIANCE"))


def _is_image(hdu):
    return (isinstance(hdu, (fits.PrimaryHDU, fits.ImageHDU, fits.CompImageHDU))
            and hdu.data is not None and hdu.data.ndim == 2)
