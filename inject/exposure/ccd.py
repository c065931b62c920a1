"""One CCD of a focal-plane exposure: its scene, its stars and its simulation.

Random streams are keyed on (scene seed, detector id, purpose) (:func:`inject.scene.rng`);
stars on (scene seed, star tile, ``"stars"``): stars are drawn per fixed 10 mm tile of the
focal plane, and each CCD draws the tiles its pixels and stamps reach, so a star is where the
scene puts it whichever CCDs are rendered.
"""
from dataclasses import replace

import numpy as np

from inject.camera import layout as fp
from inject.camera.wcs import ccd_wcs
from inject.config import with_detector
from inject.errors import SceneError
from inject.exposure.plan import ccd_shape, vertex_model
from inject.instrument import LSST
from inject.photometry import electron_rate
from inject.profile import Seeing
from inject.render import Budget
from inject.scene import pixel_noise, render_tracks, rng, simulate
from inject.stars import add_star_field, draw_stars, psf_stamps, sample_stars

#: Star tiles: squares of this side (mm) on a fixed grid over the focal plane.
STAR_TILE_MM = 10.0
_TILE_GRID = 80  # tiles per side, centred on the boresight (covers +-400 mm)
#: Star tiles' random streams start here (detector ids are 0-188).
STAR_TILE_KEY = 1000



def ccd_scene(fscene, ccd, streaks=()):
    """The CCD scene of one detector: its sensor (cut-out), the satellites that reach it with
    their tracks in its pixels."""
    ny, nx = ccd_shape(fscene, ccd)
    det = ccd.detector if (ny, nx) == ccd.shape else ccd.detector.cutout(nx, ny)
    sats = [replace(fscene.scene.satellites[s.satellite], track=s.track) for s in streaks]
    return with_detector(fscene.scene, det, sats)


def _star_tiles(box):
    """Indices of the star tiles overlapping a box (mm)."""
    lo = -_TILE_GRID / 2 * STAR_TILE_MM
    ix = range(max(0, int(np.floor((box[0] - lo) / STAR_TILE_MM))),
               min(_TILE_GRID, int(np.floor((box[1] - lo) / STAR_TILE_MM)) + 1))
    iy = range(max(0, int(np.floor((box[2] - lo) / STAR_TILE_MM))),
               min(_TILE_GRID, int(np.floor((box[3] - lo) / STAR_TILE_MM)) + 1))
    return [(i, j) for j in iy for i in ix]


def tile_stars(scene, spec, tile):
    """The stars of one focal-plane tile: ``x_mm, y_mm, mag`` (its own random stream)."""
    i, j = tile
    lo = -_TILE_GRID / 2 * STAR_TILE_MM
    gen = rng(scene.seed, "stars", STAR_TILE_KEY + j * _TILE_GRID + i)
    side_deg = STAR_TILE_MM * fp.PLATE_SCALE_ARCSEC_PER_MM / 3600.0
    mag = sample_stars(spec, side_deg ** 2, scene.band, gen)
    x = lo + STAR_TILE_MM * (i + gen.uniform(0.0, 1.0, mag.size))
    y = lo + STAR_TILE_MM * (j + gen.uniform(0.0, 1.0, mag.size))
    return x, y, mag


def add_focal_stars(image, fscene, ccd, wcs=None, noise=None, variance=None):
    """Add the scene's stars that light a CCD (in place): those of every tile its pixels, grown
    by the bright-star stamp, overlap. A catalog in ra, dec goes through the CCD's WCS.
    ``noise`` and ``variance``: see :func:`inject.stars.draw_stars`."""
    scene = fscene.scene
    spec = scene.stars
    if spec.catalog is not None:
        return add_star_field(image, scene, None, wcs=wcs, noise=noise, variance=variance)
    if scene.seeing <= 0:
        raise SceneError("stars: need seeing > 0 (stars share the atmospheric PSF)")
    pixel_scale = LSST.pixel_scale_arcsec
    stamps = psf_stamps(Seeing(scene.seeing).profile(), pixel_scale)
    box = ccd.bounds_mm(stamps.bright_half + 1, image.shape)
    parts = [tile_stars(scene, spec, tile) for tile in _star_tiles(box)]
    if not parts:
        return None
    x_mm, y_mm, mag = (np.concatenate(v) for v in zip(*parts))
    x, y = ccd.focal_to_pixel(x_mm, y_mm)
    flux = electron_rate(mag, scene.band) * scene.exptime
    return draw_stars(image, x, y, flux, stamps, pixel_scale, noise=noise, variance=variance)


def simulate_ccd(fscene, ccd, streaks, budget=Budget()):
    """Simulate one CCD of a focal-plane scene, with its streaks from the plan
    (:meth:`inject.exposure.plan.Plan.streaks`).

    Returns
    -------
    scene : inject.config.Scene
        The CCD's scene (for the file's headers).
    result : inject.scene.SceneResult
    streaks : list of CCDStreak
    wcs : astropy.wcs.WCS
    """
    scene = ccd_scene(fscene, ccd, streaks)
    wcs = ccd_wcs(ccd, fscene.pointing)
    models = [vertex_model(fscene, s.satellite, s.values[0], s.pixel_scale) for s in streaks]
    rendered = render_tracks(scene.detector.shape, models, [s.track for s in streaks], budget,
                             pixel_noise(scene))
    for row, s in zip(rendered[1], streaks):
        row["satellite"] = s.satellite
        row["pixel_scale_arcsec"] = s.pixel_scale
    result = simulate(scene, budget, detector_index=ccd.id, wcs=wcs, rendered=rendered,
                      add_stars=lambda image, **noise: add_focal_stars(image, fscene, ccd, wcs,
                                                                       **noise))
    return scene, result, streaks, wcs
