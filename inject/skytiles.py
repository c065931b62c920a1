"""Random stars fixed to the sky: a fixed grid of tiles in (RA, Dec), each with its own random
stream, so the same sky shows the same stars whatever the pointing, rotation or CCD.

Declination is cut into bands :data:`TILE_DEG` high; band ``j`` is cut into ``n_j`` equal RA
tiles, ``n_j`` the nearest count that keeps them about :data:`TILE_DEG` wide on the sky. A
tile's stars come from the stream keyed on (scene seed, tile); their number and magnitudes
from the star-count model over the tile's exact solid angle, their positions uniform on the
sphere within it. An image draws the tiles its pixels (grown by a margin) reach and places
their stars through its WCS, each on its own (:func:`world_to_pixel`), so that a star lands
on the same pixel whichever image (a CCD, its cut-out) draws it. Focal-plane CCDs and CCD
scenes with a pointing draw their random stars here (:func:`inject.stars.add_star_field`).
"""
import math

import numpy as np

#: Height of a declination band and width of an RA tile on the sky, deg (0.1 deg: a full
#: LSSTCam CCD spans about three).
TILE_DEG = 0.1
_N_BANDS = int(round(180.0 / TILE_DEG))
#: First key of the tiles' random streams (after every detector's and purpose's).
SKY_TILE_KEY = 1 << 20


def _band_count(j):
    """RA tiles in declination band ``j``."""
    lo, hi = -90.0 + j * TILE_DEG, -90.0 + (j + 1) * TILE_DEG
    width = 360.0 * math.cos(math.radians(0.5 * (lo + hi)))
    return max(1, int(round(width / TILE_DEG)))


def tile_bounds(tile):
    """``(ra_lo, ra_hi, dec_lo, dec_hi)`` of tile ``(j, i)``, deg."""
    j, i = tile
    n = _band_count(j)
    return 360.0 * i / n, 360.0 * (i + 1) / n, -90.0 + j * TILE_DEG, -90.0 + (j + 1) * TILE_DEG


def tile_area_deg2(tile):
    """Exact solid angle of a tile, deg^2."""
    ra_lo, ra_hi, dec_lo, dec_hi = tile_bounds(tile)
    steradians = math.radians(ra_hi - ra_lo) * (math.sin(math.radians(dec_hi))
                                                 - math.sin(math.radians(dec_lo)))
    return steradians * (180.0 / math.pi) ** 2


def tile_generator(seed, tile):
    """The random stream of one tile of one scene seed."""
    j, i = tile
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(SKY_TILE_KEY, j, i)))


def tile_positions(gen, tile, n):
    """``n`` (ra, dec) deg uniform on the sphere within a tile."""
    ra_lo, ra_hi, dec_lo, dec_hi = tile_bounds(tile)
    ra = gen.uniform(ra_lo, ra_hi, n)
    z = gen.uniform(math.sin(math.radians(dec_lo)), math.sin(math.radians(dec_hi)), n)
    return ra, np.degrees(np.arcsin(z))


def tiles_reached(wcs, shape, margin_px):
    """The tiles an image's pixels, grown by ``margin_px``, reach: from the sky positions of
    points along its grown edges (every ~TILE_DEG / 4), with a tile's width of slack."""
    ny, nx = shape
    x0, x1, y0, y1 = -0.5 - margin_px, nx - 0.5 + margin_px, -0.5 - margin_px, ny - 0.5 + margin_px
    scale = float(np.mean(np.abs(np.linalg.svd(wcs.pixel_scale_matrix, compute_uv=False))))
    step = max(1.0, TILE_DEG / 4 / scale)
    xs = np.arange(x0, x1 + step, step).clip(x0, x1)
    ys = np.arange(y0, y1 + step, step).clip(y0, y1)
    px = np.concatenate([xs, xs, np.full(ys.size, x0), np.full(ys.size, x1), [0.5 * (x0 + x1)]])
    py = np.concatenate([np.full(xs.size, y0), np.full(xs.size, y1), ys, ys, [0.5 * (y0 + y1)]])
    ra, dec = (np.asarray(v, float) for v in wcs.pixel_to_world_values(px, py))
    centre_ra = ra[-1]
    unwrapped = centre_ra + (ra - centre_ra + 180.0) % 360.0 - 180.0
    dec_lo, dec_hi = dec.min() - TILE_DEG, dec.max() + TILE_DEG
    # A pole within the grown image's half-diagonal of its centre: every RA near it.
    half_diagonal = scale * 0.5 * math.hypot(x1 - x0, y1 - y0)
    pole = 90.0 - abs(dec[-1]) <= half_diagonal + TILE_DEG
    if pole:
        dec_lo, dec_hi = (min(dec_lo, -90.0), dec_hi) if dec.mean() < 0 else (dec_lo, 90.0)
    out = []
    for j in range(max(0, int((dec_lo + 90.0) // TILE_DEG)),
                   min(_N_BANDS, int((dec_hi + 90.0) // TILE_DEG) + 1)):
        n = _band_count(j)
        width = 360.0 / n
        if pole or n * TILE_DEG < 3 * (unwrapped.max() - unwrapped.min()) + 2 * width:
            out.extend((j, i) for i in range(n))
            continue
        # RA slack: a tile's width, and the image's RA spread grows toward the poles.
        lo = unwrapped.min() - width
        hi = unwrapped.max() + width
        out.extend((j, i % n) for i in range(int(math.floor(lo / width)),
                                             int(math.floor(hi / width)) + 1))
    return sorted(set(out))


def sky_stars(spec, wcs, shape, margin_px, band, seed, sample_stars):
    """The random stars an image receives: those of every tile it reaches, through its WCS.

    Parameters
    ----------
    spec : inject.stars.StarFieldSpec
    wcs : astropy.wcs.WCS
    shape : tuple
        ``(ny, nx)`` of the image.
    margin_px : float
        Stars this far beyond the edges are kept (their stamps reach the image).
    band : str
    seed : int
    sample_stars : callable
        ``sample_stars(spec, area_deg2, band, gen)``: magnitudes over an area
        (:func:`inject.stars.sample_stars`).

    Returns
    -------
    dict
        ``x``, ``y`` (pixels, 0-based) and ``mag`` of the stars within the grown image.
    """
    ras, decs, mags = [], [], []
    for tile in tiles_reached(wcs, shape, margin_px):
        gen = tile_generator(seed, tile)
        mag = sample_stars(spec, tile_area_deg2(tile), band, gen)
        ra, dec = tile_positions(gen, tile, mag.size)
        ras.append(ra), decs.append(dec), mags.append(mag)
    if not mags:
        return {"x": np.zeros(0), "y": np.zeros(0), "mag": np.zeros(0)}
    ra, dec, mag = (np.concatenate(v) for v in (ras, decs, mags))
    ny, nx = shape
    # Only stars near the image go through the projection (a TAN WCS has no pixel for the far
    # side of the sky, and SIP's inverse iterates): within the grown image's half-diagonal.
    centre = np.radians(wcs.pixel_to_world_values((nx - 1) / 2, (ny - 1) / 2))
    scale = float(np.mean(np.abs(np.linalg.svd(wcs.pixel_scale_matrix, compute_uv=False))))
    reach = math.radians(scale * (0.5 * math.hypot(nx, ny) + margin_px) * 1.5 + TILE_DEG)
    r, d = np.radians(ra), np.radians(dec)
    cos_sep = (np.sin(d) * math.sin(centre[1])
               + np.cos(d) * math.cos(centre[1]) * np.cos(r - centre[0]))
    near = cos_sep > math.cos(reach)
    ra, dec, mag = ra[near], dec[near], mag[near]
    x, y = world_to_pixel(wcs, ra, dec)
    keep = (np.isfinite(x) & np.isfinite(y) & (x >= -0.5 - margin_px)
            & (x < nx - 0.5 + margin_px) & (y >= -0.5 - margin_px) & (y < ny - 0.5 + margin_px))
    return {"x": x[keep], "y": y[keep], "mag": mag[keep]}


#: Largest correction (px) at which the inverse of a distorted WCS stops iterating a point.
INVERSE_TOLERANCE_PX = 1e-6


def world_to_pixel(wcs, ra, dec):
    """Pixel ``x, y`` (0-based) of sky positions through a celestial WCS, each star on its own.

    A distorted (SIP) WCS has no closed-form inverse: astropy iterates, and by default until
    the worst of the points it is given has converged, so a star's position (to ~1e-10 px)
    would depend on which others are projected with it, and a cut-out would place its stars a
    hair off the full CCD's. Here each point iterates until its own correction is below
    :data:`INVERSE_TOLERANCE_PX` (astropy's adaptive mode): its position depends only on its
    sky position and the WCS. A point that does not converge keeps its best solution, as
    astropy's ``world_to_pixel_values`` does.
    """
    if not np.size(ra):
        return np.zeros(0), np.zeros(0)
    x, y = wcs.all_world2pix(ra, dec, 0, adaptive=True, tolerance=INVERSE_TOLERANCE_PX,
                             quiet=True)
    return np.asarray(x, float), np.asarray(y, float)
