"""Mask planes and TRUTH flags: their one definition, and how FITS headers name the planes.

The planes sit on LSST afw's default bits (``Mask::addMaskPlane`` order: BAD 0 ... VIGNETTED
9) with STREAK on the next one, 10, and keep afw's names. A MASK header names each plane twice:

- ``MP_<PLANE> = bit``: afw's cards (``lsst.afw.image.Mask``), which every afw reader uses;
- ``MSKNnnnn = name``, ``MSKMnnnn = 1 << n`` and ``MSKDnnnn = description`` (``n`` the bit):
  the self-describing cards of LSST's pure-Python ``lsst-images``, with which
  ``MaskedImage.read_legacy`` takes the planes as they are, with no plane map (without them it
  guesses a visit-image map that has no STREAK plane and refuses a file that sets it).
"""

#: Truth mask threshold: STREAK is set where the noise-free streak exceeds this many sigma of
#: the per-pixel noise (or this fraction of its peak in a noise-free image). The masker's
#: default surface-brightness rule masks to the same level.
STREAK_MASK_SIGMA = 1.0
STREAK_MASK_FRACTION = 1e-3

#: Mask planes and their bits (afw's default bits and names; STREAK on bit 10).
MASK_PLANES = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5,
               "DETECTED_NEGATIVE": 6, "SUSPECT": 7, "NO_DATA": 8, "VIGNETTED": 9,
               "STREAK": 10}

#: One line per plane (the ``MSKD`` cards).
PLANE_DESCRIPTIONS = {
    "BAD": "Bad pixel of the detector.",
    "SAT": "Pixel reached full well (or the ADC limit), or was filled by its bleed trail.",
    "INTRP": "Pixel value was interpolated.",
    "CR": "A cosmic ray hit this pixel.",
    "EDGE": "Pixel too close to the image edge for detection.",
    "DETECTED": "Pixel is part of a detected source.",
    "DETECTED_NEGATIVE": "Pixel is part of a detected source of negative flux.",
    "SUSPECT": "Pixel is close to saturation.",
    "NO_DATA": "No data for this pixel.",
    "VIGNETTED": "Pixel is vignetted by the optics.",
    "STREAK": "A satellite streak injected by inject reaches this pixel.",
}

#: TRUTH flag bits (the ``flags`` column).
FLAG_OFF_IMAGE = 1    # the track misses the image: no charge on it
FLAG_CLIPPED = 2      # part of the track (or its end caps) lies outside the image
FLAG_SATURATED = 4    # some streak pixel reached full well (or the ADC limit)


def _bit_key(key):
    """``"MSKN0010"`` -> 10 (None for other keys)."""
    digits = key[4:]
    return int(digits) if key[:4] in ("MSKN", "MSKM", "MSKD") and digits.isdigit() else None


def header_planes(header):
    """``{plane: bit}`` of a MASK header: its ``MSKN`` cards, then its ``MP_`` cards (afw's
    win where both name a plane).

    Parameters
    ----------
    header : astropy.io.fits.Header

    Returns
    -------
    dict
        Empty if the header names no plane.
    """
    planes = {str(value): _bit_key(key) for key, value in header.items()
              if key.startswith("MSKN") and _bit_key(key) is not None}
    for key, value in header.items():
        name = key.split()[-1]  # "HIERARCH MP_X" reads back as "MP_X"
        if name.startswith("MP_") and isinstance(value, int) and not isinstance(value, bool):
            planes[name[3:]] = value
    return planes


def set_plane_cards(header, name, bit):
    """Name plane ``name`` on ``bit`` in ``header`` (``MP_`` and ``MSKN/MSKM/MSKD`` cards)."""
    header[f"HIERARCH MP_{name}"] = bit  # afw writes these as HIERARCH cards too
    header[f"MSKN{bit:04d}"] = (name, f"Name for mask plane {bit}.")
    header[f"MSKM{bit:04d}"] = (1 << bit, f"Bitmask for plane n={bit}; always 1<<n.")
    # No comment on the description: a long value would continue and lose it anyway.
    header[f"MSKD{bit:04d}"] = PLANE_DESCRIPTIONS.get(name, name)


def mask_header(header, planes=MASK_PLANES):
    """``header`` with every plane of ``planes`` named (see :func:`set_plane_cards`)."""
    for name, bit in planes.items():
        set_plane_cards(header, name, bit)
    return header


def plane_bit(header, name, nbits=32):
    """The bit of plane ``name`` in a MASK header, naming it on a free bit if it has none.

    The new plane goes where afw's ``addMaskPlane`` would put it: on the lowest free bit
    (``MaskDict::getUnusedPlane``). The ``MSKN`` cards are written too when the header already
    uses them, so that lsst-images sees the new plane.

    Parameters
    ----------
    header : astropy.io.fits.Header
        Changed in place when the plane is added.
    name : str
    nbits : int
        Bits of the mask's pixel type (16 for a uint16 mask).

    Returns
    -------
    int or None
        None if every bit is taken.
    """
    planes = header_planes(header)
    if name in planes:
        return int(planes[name])
    used = set(planes.values()) | {_bit_key(k) for k in header if _bit_key(k) is not None}
    free = [b for b in range(nbits) if b not in used]
    if not free:
        return None
    bit = free[0]
    uses_mskn = any(_bit_key(k) is not None for k in header)
    header[f"HIERARCH MP_{name}"] = bit
    if uses_mskn:
        set_plane_cards(header, name, bit)
    return bit
