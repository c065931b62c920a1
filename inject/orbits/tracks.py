"""A satellite's pass turned into tracks: the sunlit, apparent parts of its path during the
exposure, as a polyline in focal-plane mm (focal-plane scenes) or in a CCD's pixels (CCD
scenes), each vertex with the pass's height, zenith, phi, range, angular speed and brightness.
"""
import warnings

import numpy as np

from inject.camera.detector import detector_from_spec
from inject.camera.wcs import Pointing
from inject.errors import InjectError, OrbitWarning, SceneError
from inject.instrument import LSST
from inject.orbits.passes import (
    SHADOW_ATMOSPHERE_KM,
    TRACK_STEP_S,
    Exposure,
    compute_pass,
    orbit_from_spec,
    site_from_spec,
    track_runs,
)
from inject.schema import check_keys, number, ranged
from inject.trajectory import FocalTrack
from inject.validate import check_pointing, parse_time


def orbit_focal_track(where, spec, sat, scene, lumos=None):
    """A satellite's track from its orbit during the exposure: the apparent, sunlit parts of
    the pass inside the field (all of them, in time order) as a polyline in mm
    (:func:`inject.orbits.passes.track_runs` on a pass sampled every 0.1 s: a vertex at least
    every second and wherever the path bends by more than 0.05 px), each vertex with the
    orbit's height, zenith (90 - alt), phi and the satellite's ``mag`` dimmed by the penumbra
    (the streak model scales it with range and nadir angle itself, as
    :meth:`inject.orbits.passes.Pass.magnitude` does), and the pass's exact ``range`` and
    ``angular_speed`` (so t_eff, the charge per pixel and the defocus are the pass's, not those
    of the paper's spherical Earth at that height and zenith). A pass that never enters the
    field or is in shadow there has no vertices, and says why (OrbitWarning).

    ``scene`` is the parsed common part of the scene (:class:`inject.config.Scene`): its
    exposure start, exposure time, pointing, site and grazing atmosphere are used as parsed."""
    if scene.time is None:
        raise SceneError(f"time: required with {where} (exposure start, ISO 8601 UTC)")
    dense = orbit_pass(where, spec, time=scene.time, exptime=scene.exptime,
                       pointing=scene.pointing, site=scene.site,
                       atmosphere_km=scene.shadow_atmosphere_km)
    runs, message = sunlit_runs(where, dense, sat.mag, lumos, sat.ref_range)
    about = {"name": dense.orbit.name or "", "in_field": bool(dense.in_field),
             "sunlit": bool(dense.visible)}
    if not runs:
        return FocalTrack("polyline", (), (), (), 0.0, message, **about)
    xd, yd = dense.focal_mm()
    xs, ys, values = [], [], []
    for run, vals in runs:
        if xs:  # a break between sunlit parts
            xs.append(np.nan), ys.append(np.nan), values.append(None)
        xs += [float(v) for v in xd[run]]
        ys += [float(v) for v in yd[run]]
        values += vals
    angle = float(np.degrees(np.arctan2(ys[1] - ys[0], xs[1] - xs[0])))
    return FocalTrack("polyline", tuple(xs), tuple(ys), tuple(values), angle, message, **about)


def orbit_pass(where, spec, *, time, exptime, pointing, site=None, atmosphere_km=None):
    """The pass (every 0.1 s) of a satellite's ``orbit:`` during an exposure starting at
    ``time`` (UTC) seen from ``site`` (a scene's ``site:`` value, None for Rubin), errors as
    SceneError. ``atmosphere_km`` None: :data:`inject.orbits.passes.SHADOW_ATMOSPHERE_KM`."""
    try:
        time = parse_time(time, "time")
        orbit = orbit_from_spec(spec, time, where)
        site = site_from_spec(site)
        return compute_pass(orbit, Exposure(time, exptime), pointing, site, step_s=TRACK_STEP_S,
                            atmosphere_km=SHADOW_ATMOSPHERE_KM if atmosphere_km is None
                            else atmosphere_km)
    except SceneError:
        raise
    except InjectError as err:
        text = str(err)
        raise SceneError(text if text.startswith(("site", where)) else f"{where}: {text}") \
            from None


def _no_streak(where, dense):
    """Why a pass renders no streak (the message, also warned as an OrbitWarning)."""
    if not dense.in_field:
        why = dense.message
    elif dense.visible:
        why = "crosses the field only outside the camera's reach"
    else:
        why = "crosses the field in Earth's shadow"
    message = f"{where}: no streak: {why}"
    warnings.warn(message, OrbitWarning, stacklevel=3)
    return message


def sunlit_runs(where, dense, mag, lumos=None, ref_range=550.0):
    """The sunlit runs of a pass's track, in time order: a list of (sample indices, vertex
    values), and a message; no runs when there is no streak (the message says why).

    ``lumos`` (a satellite's ``lumos:`` mapping): each vertex's brightness from lumos-sat
    (:mod:`inject.orbits.lumos`) instead of ``mag`` scaled by the paper's law."""
    xd, yd, runs = track_runs(dense, lit_only=True)
    if not runs:
        return [], _no_streak(where, dense)
    lit = np.concatenate(runs)
    message = "crosses the field, sunlit" if dense.sun_fraction[lit].min() >= 1 else \
        "crosses the field, partly in Earth's shadow (the streak ends or fades there)"
    if len(runs) > 1:
        message += f"; {len(runs)} sunlit parts (out of and back into the shadow), all rendered"
    out = []
    for run in runs:
        dim = -2.5 * np.log10(dense.sun_fraction[run])
        base = np.full(len(run), float(mag))
        if lumos is not None:
            from inject.geometry import nadir_angle
            from inject.orbits.lumos import magnitudes
            from inject.photometry import apparent_magnitude

            # The mag at ref_range, face-on, that the streak model's cos/r^2 scaling turns
            # into lumos's apparent magnitude here.
            zenith = 90.0 - dense.alt_deg[run]
            base = magnitudes(where.replace(".orbit", ".lumos"), lumos, dense, run) - \
                apparent_magnitude(0.0, dense.range_km[run],
                                   nadir_angle(dense.height_km[run], zenith), ref_range)
        phi = np.where(np.isfinite(dense.phi_deg[run]), dense.phi_deg[run], 90.0)  # at zenith
        values = [{"height": float(h), "zenith": float(90.0 - a), "phi": float(f),
                   "mag": float(m + d), "range": float(r), "angular_speed": float(w)}
                  for h, a, f, m, d, r, w in zip(dense.height_km[run], dense.alt_deg[run], phi,
                                                 base, dim, dense.range_km[run],
                                                 dense.angular_speed_rad_s[run])]
        out.append((run, values))
    return out, message


def resolve_ccd_orbits(raw):
    """A CCD scene mapping with each satellite's ``orbit:`` replaced by its track in the CCD's
    pixels (a polyline whose vertices carry the pass's values); other satellites as they are.

    The CCD scene's WCS (:func:`inject.camera.wcs.pointing_wcs`: TAN about the pointing at the
    image centre, LSST's plate scale, no distortion) maps the pass's field angles (ICRS
    gnomonic offsets, rotated as the WCS's CD matrix) linearly to pixels. A pass with no streak
    gets a track far off the image (its TRUTH row is flagged off-image) and a warning saying
    why; a pass sunlit in several parts gives one satellite (and TRUTH row) per part.
    """
    satellites = raw.get("satellites") if isinstance(raw, dict) else None
    if not isinstance(satellites, list) or not any(
            isinstance(sat, dict) and "orbit" in sat for sat in satellites):
        return raw
    try:
        shape = detector_from_spec(raw.get("detector", {"type": "itl"})).shape
    except SceneError:
        raise
    except InjectError as err:
        raise SceneError(str(err)) from None
    if raw.get("pointing") is None:
        raise SceneError("pointing: required with an orbit ({ra, dec, rotation})")
    check_keys("pointing", raw["pointing"], {"ra", "dec", "rotation"}, {"ra", "dec"})
    try:
        pointing = Pointing(*check_pointing(raw["pointing"]))
    except InjectError as err:
        raise SceneError(str(err)) from None
    exptime = number("exptime", raw.get("exptime", 30.0))
    time = raw.get("time")
    atmosphere = raw.get("shadow_atmosphere_km")
    if atmosphere is not None:
        atmosphere = ranged("shadow_atmosphere_km", "shadow_atmosphere_km", atmosphere)
    ny, nx = shape
    scale_deg = LSST.pixel_scale_arcsec / 3600.0
    out = []
    for i, sat in enumerate(satellites):
        if not (isinstance(sat, dict) and "orbit" in sat):
            out.append(sat)
            continue
        where = f"satellites[{i}].orbit"
        for key in ("track", "height", "phi"):
            if key in sat:
                raise SceneError(f"satellites[{i}].{key}: comes from the orbit (remove it)")
        if time is None:
            raise SceneError(f"time: required with {where} (exposure start, ISO 8601 UTC)")
        dense = orbit_pass(where, sat["orbit"], time=time, exptime=exptime, pointing=pointing,
                           site=raw.get("site"), atmosphere_km=atmosphere)
        runs, _ = sunlit_runs(where, dense, number(f"satellites[{i}].mag", sat.get("mag")),
                                  sat.get("lumos"), number(f"satellites[{i}].ref_range",
                                                            sat.get("ref_range", 550.0)))
        rest = {k: v for k, v in sat.items() if k not in ("orbit", "lumos")}
        if not runs:
            far = -9e5  # 50 deg off: nothing of it on the image
            vertices = [{"x": far, "y": far}, {"x": far + 1.0, "y": far}]
            out.append({**rest, "height": float(np.nanmean(dense.height_km)),
                        "track": {"vertices": vertices}})
            continue
        for run, values in runs:  # one streak (and TRUTH row) per sunlit part
            x = (nx - 1) / 2 + dense.field_x_deg[run] / scale_deg
            y = (ny - 1) / 2 + dense.field_y_deg[run] / scale_deg
            vertices = [{"x": float(a), "y": float(b), **v} for a, b, v in zip(x, y, values)]
            out.append({**rest, "height": values[0]["height"], "track": {"vertices": vertices}})
    return {**raw, "satellites": out}
