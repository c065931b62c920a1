"""One CCD of a focal-plane exposure: its scene, its stars and its simulation.

Random streams are keyed on (scene seed, detector id, purpose) (:func:`inject.scene.rng`);
stars on (scene seed, sky tile) (:mod:`inject.skytiles`): each CCD draws the sky tiles its
pixels and stamps reach, so a star is where the sky puts it whichever CCDs are rendered, and
at any pointing or rotation.
"""
from dataclasses import replace

import numpy as np

from inject.camera.wcs import ccd_wcs
from inject.config import with_detector
from inject.exposure.plan import ccd_shape, vertex_model
from inject.render import Budget
from inject.scene import pixel_noise, render_tracks, simulate
from inject.stars import add_star_field
from inject.trajectory import Track, clip_segment


def ccd_scene(fscene, ccd, streaks=(), shape=None):
    """The CCD scene of one detector: its sensor (the scene's cut-out, or ``shape = (ny,
    nx)``), the satellites that reach it with their tracks in its pixels."""
    ny, nx = ccd_shape(fscene, ccd) if shape is None else shape
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


def simulate_ccd(fscene, ccd, streaks, budget=Budget(), box=None):
    """Simulate one CCD of a focal-plane scene, with its streaks from the plan
    (:meth:`inject.exposure.plan.Plan.streaks`): the scene's cut-out (or the whole CCD), or
    only the pixels ``[y0, y0 + ny) x [x0, x0 + nx)`` of ``box = (x0, y0, nx, ny)``.

    A box renders what the whole CCD renders on its pixels: the streaks' models are the whole
    CCD's, the tracks and the WCS moved to the box, the sky's stars placed through that WCS;
    its noise is drawn as for a cut-out at the CCD's corner (statistically the same).

    Returns
    -------
    scene : inject.config.Scene
        The CCD's scene (for the file's headers).
    result : inject.scene.SceneResult
    streaks : list of CCDStreak
        In the simulated pixels.
    wcs : astropy.wcs.WCS
        Of the simulated pixels.
    """
    wcs = ccd_wcs(ccd, fscene.pointing)
    shape = None
    if box is not None:
        x0, y0, nx, ny = box
        streaks = [replace(s, track=_shifted(s.track, x0, y0),
                           ends=(s.ends[0] - x0, s.ends[1] - y0, s.ends[2] - x0,
                                 s.ends[3] - y0)) for s in streaks]
        wcs, shape = _shifted_wcs(wcs, x0, y0), (ny, nx)
    scene = ccd_scene(fscene, ccd, streaks, shape)
    return scene, simulate_streaks(fscene, ccd, scene, wcs, streaks, budget), streaks, wcs


def cutout_box(ccd, streaks, side):
    """``(x0, y0, nx, ny)``: a ``side`` x ``side`` box of the CCD (clipped to it) centred on
    the middle of its streaks' parts on the CCD (the mean of their middles; the CCD's centre
    without one)."""
    ny_all, nx_all = ccd.shape
    middles = []
    for s in streaks:
        a = clip_segment(*s.ends, (-0.5, nx_all - 0.5), (-0.5, ny_all - 0.5))
        if a is not None:
            middles.append(((a[0] + a[2]) / 2, (a[1] + a[3]) / 2))
    cx, cy = np.mean(middles, axis=0) if middles else (nx_all / 2, ny_all / 2)
    nx, ny = min(side, nx_all), min(side, ny_all)
    bx = int(min(max(round(cx - nx / 2), 0), nx_all - nx))
    by = int(min(max(round(cy - ny / 2), 0), ny_all - ny))
    return (bx, by, nx, ny)


def _shifted(track, dx, dy):
    vertices = None if track.vertices is None else tuple(
        {**v, "x": v["x"] - dx, "y": v["y"] - dy} for v in track.vertices)
    return Track(track.x0 - dx, track.y0 - dy, track.angle, track.length, vertices)


def _shifted_wcs(wcs, dx, dy):
    """``wcs`` of the pixels from ``(dx, dy)`` on (its SIP polynomials about the new
    reference pixel)."""
    from astropy.wcs import Sip

    wcs = wcs.deepcopy()
    wcs.wcs.crpix = wcs.wcs.crpix - np.array([dx, dy], float)
    if wcs.sip is not None:
        sip = wcs.sip
        wcs.sip = Sip(sip.a, sip.b, sip.ap, sip.bp, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


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
