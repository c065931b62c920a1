"""One CCD of a focal-plane exposure: its scene, its stars and its simulation.

Random streams are keyed on (scene seed, detector id, purpose) (:func:`inject.scene.rng`);
stars on (scene seed, sky tile) (:mod:`inject.skytiles`): each CCD draws the sky tiles its
pixels and stamps reach, so a star is where the sky puts it whichever CCDs are rendered, and
at any pointing or rotation.
"""
from dataclasses import replace

from inject.camera.wcs import ccd_wcs
from inject.config import with_detector
from inject.exposure.plan import ccd_shape, vertex_model
from inject.render import Budget
from inject.scene import pixel_noise, render_tracks, simulate
from inject.stars import add_star_field


def ccd_scene(fscene, ccd, streaks=()):
    """The CCD scene of one detector: its sensor (cut-out), the satellites that reach it with
    their tracks in its pixels."""
    ny, nx = ccd_shape(fscene, ccd)
    det = ccd.detector if (ny, nx) == ccd.shape else ccd.detector.cutout(nx, ny)
    sats = [replace(fscene.scene.satellites[s.satellite], track=s.track) for s in streaks]
    return with_detector(fscene.scene, det, sats)


def add_focal_stars(image, fscene, ccd, wcs=None, noise=None, variance=None):
    """Add the scene's stars that light a CCD (in place): the sky's stars
    (:mod:`inject.skytiles`) within the bright-star stamp of its pixels, placed through the
    CCD's WCS, so every CCD, pointing and rotation sees the same sky; a catalog in ra, dec goes
    through the CCD's WCS too. The same code as a CCD scene's with a pointing
    (:func:`inject.stars.add_star_field`). ``noise`` and ``variance``: see
    :func:`inject.stars.draw_stars`."""
    wcs = ccd_wcs(ccd, fscene.pointing) if wcs is None else wcs
    return add_star_field(image, fscene.scene, None, wcs=wcs, noise=noise, variance=variance)


def ccd_cards(ccd, digest, what="focal-plane scene digest (sha256)"):
    """The primary-header cards naming a focal-plane CCD and the scene it belongs to
    (``DETNAME``, ``DETECTOR``, ``VENDOR``, ``FPSCENE``: the first 16 hex digits of
    ``digest``)."""
    return {"DETNAME": (ccd.name, "detector name"),
            "DETECTOR": (ccd.id, "detector id (obs_lsst, 0-188)"),
            "VENDOR": (ccd.vendor.upper(), "sensor vendor"),
            "FPSCENE": (digest[:16], what)}


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
    return scene, simulate_streaks(fscene, ccd, scene, wcs, streaks, budget), streaks, wcs


def simulate_streaks(fscene, ccd, scene, wcs, streaks, budget=Budget()):
    """Simulate a CCD's ``scene`` (the CCD or a box of it, ``wcs`` in its pixels) with its
    ``streaks`` in those pixels: each streak's model and plate scale are the whole CCD's
    (:class:`~inject.exposure.plan.CCDStreak`), the stars the sky's through ``wcs``.

    Returns
    -------
    inject.scene.SceneResult
    """
    models = [vertex_model(fscene, s.satellite, s.values[0], s.pixel_scale) for s in streaks]
    rendered = render_tracks(scene.detector.shape, models, [s.track for s in streaks], budget,
                             pixel_noise(scene))
    for row, s in zip(rendered[1], streaks):
        row["satellite"] = s.satellite
        row["pixel_scale_arcsec"] = s.pixel_scale
    return simulate(scene, budget, detector_index=ccd.id, wcs=wcs, rendered=rendered,
                    add_stars=lambda image, **noise: add_focal_stars(image, fscene, ccd, wcs,
                                                                     **noise))
