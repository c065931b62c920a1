"""``inject survey --render``: the streaked CCDs of a night rendered, masked and measured.

For every visit with streaks (its :class:`~inject.survey.plan.VisitPlan`), the survey's part:

1. **The visit's focal-plane scene** (:func:`visit_plan`, on a worker): the visit's band,
   seeing (the plan's ``FWHMgeom``), sky (the plan's e-/px, so that the masker meets the
   noise the plan's mask widths were computed against), pointing (fieldRA, fieldDec,
   rotSkyPos), start and open-shutter time, and the satellites the plan found, each with its
   exact pass over the visit's snaps (the plan's own passes: one shared frame, the readouts
   between snaps left out) as an orbit track (:class:`~inject.trajectory.FocalTrack`). Its
   plan (:func:`inject.exposure.plan.make_plan`) gives each CCD the parts of the tracks that
   reach it.
2. **Its key** (:func:`visit_key`: the visit, its satellites' element sets, the model, the
   options and the inject version), the digest of its scene: the claim of its folder
   ``OUTDIR/visits/<observationId>``, so that a run with other inputs is refused without
   ``overwrite``.
3. **Its CCDs** (:func:`visit_batches`): the CCDs the survey's plan crosses, one
   :class:`~inject.exposure.runner.Batch` per visit.

The rest is the focal plane's: :func:`inject.exposure.runner.run_batches` claims every
visit's folder before any work, makes each visit's plan and renders each CCD on any
``concurrent.futures`` executor (a process pool, Dask's), whole or as a square cut-out centred
on its streaks (:func:`inject.exposure.ccd.cutout_box`), tile-compressed, with the manifest,
the retries, the failures and the stop of ``inject focalplane``; the masker measures each CCD
(:func:`inject.survey.compare.measure_ccd`) before its file is committed.
"""
import hashlib
import json
import math
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np

from inject import __version__
from inject.errors import OrbitWarning

#: A constellation file's keys that are its visits' scene keys, not its satellites'.
SCENE_MODEL_KEYS = ("pupil", "focus_offset_um")
#: Side of a cut-out (px) by default.
DEFAULT_CUTOUT_PX = 1024
#: Folder of the visits' CCD files in OUTDIR.
VISITS_DIR = "visits"


@dataclass(frozen=True)
class RenderOptions:
    """How the streaked CCDs are rendered.

    Attributes
    ----------
    cutout : int or None
        Side (px) of the square cut-out around each CCD's streaks; None renders whole CCDs.
    compression : str or None
        ``lossless``, ``lossy`` (:data:`inject.io.fits.COMPRESSIONS`) or None.
    stars : bool
        The sky's stars (a scene's ``stars: true``).
    """

    cutout: int | None = None
    compression: str | None = "lossless"
    stars: bool = True


# --- the visit's key and folder -------------------------------------------------------------

def visit_dir(outdir, visit):
    """``OUTDIR/visits/<observationId>``."""
    return os.path.join(outdir, VISITS_DIR, str(visit.observation_id))


def visit_key(plan, constellation, model, options):
    """SHA-256 of what a visit's CCD files depend on: the visit, the plan's seeing and sky,
    its streak satellites' element sets, the satellites' model and the render options."""
    by_name = constellation.by_name
    v = plan.visit
    text = json.dumps({
        "visit": [v.observation_id, v.mjd_tai, v.ra_deg, v.dec_deg, v.rotation_deg, v.band,
                  v.exptime_s, v.n_exposures, plan.seeing_arcsec, plan.sky_e_per_px,
                  plan.alt_deg] + ([] if v.rotator_deg is None else [v.rotator_deg]),
        "satellites": [[s.satellite, *by_name[s.satellite].tle_lines()] for s in plan.streaks],
        "model": model, "options": [options.cutout, options.compression, options.stars],
        "version": __version__}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def model_keys(path):
    """The satellites' model keys of a constellation file (``shape``, ``mag``,
    ``ref_range``, ``sed``, ``lumos``: a scene satellite's) and its ``pupil`` and
    ``focus_offset_um`` (the scene's: :data:`SCENE_MODEL_KEYS`)."""
    from inject.schema import load_scene_file

    raw = load_scene_file(path)
    return {k: raw[k] for k in ("shape", "mag", "ref_range", "sed", "lumos", *SCENE_MODEL_KEYS)
            if k in raw}


# --- the visit's scene (a worker) -----------------------------------------------------------

@dataclass(frozen=True)
class VisitJob:
    """A streaked visit to render: what its scene takes from the plan (its satellites' names,
    the CCDs they cross, the seeing, sky and altitude) and its key."""

    visit: object
    names: tuple
    ccds: tuple
    seeing: float
    sky: float
    alt_deg: float
    key: str


def visit_plan(constellation_path, epoch, model, job, options):
    """The :class:`~inject.exposure.plan.Plan` of the visit's
    :class:`~inject.exposure.scene.FocalScene` (its satellites' passes as orbit tracks, its
    digest the visit's key). Runs on a worker; reads the constellation once per process."""
    from astropy import units as u

    from inject.camera.wcs import Pointing
    from inject.config import parse_focal_parts
    from inject.exposure.plan import make_plan
    from inject.exposure.scene import FocalScene
    from inject.orbits.passes import RUBIN, Exposure, FieldFrame, compute_pass
    from inject.orbits.tracks import sunlit_runs
    from inject.survey.constellation import read_constellation_once
    from inject.survey.plan import SNAP_BREAK_S, visit_times
    from inject.trajectory import FocalTrack

    constellation = read_constellation_once(constellation_path, epoch)
    by_name = constellation.by_name
    visit = job.visit
    pointing = Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg)
    ts = visit_times(visit)
    exposure = Exposure(visit.start, float(ts[-1]))
    frame = FieldFrame.build(exposure.start + ts * u.s, pointing, RUBIN)
    spec = constellation.satellite
    tracks = []
    for name in job.names:
        p = compute_pass(by_name[name], exposure, pointing, RUBIN, t_s=ts, frame=frame,
                         check_epoch=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OrbitWarning)
            runs, message = sunlit_runs("satellite.orbit", p, spec.mag, constellation.lumos,
                                        spec.ref_range)
        xd, yd = p.focal_mm()
        xs, ys, values = [], [], []
        for run, vals in runs:
            # The plan's parts: no light during the readouts between snaps.
            cuts = np.flatnonzero(np.diff(p.t_s[run]) > SNAP_BREAK_S) + 1
            start = 0
            for stop in (*cuts, len(run)):
                if stop - start >= 2:
                    if xs:
                        xs.append(math.nan), ys.append(math.nan), values.append(None)
                    xs += [float(v) for v in xd[run[start:stop]]]
                    ys += [float(v) for v in yd[run[start:stop]]]
                    values += vals[start:stop]
                start = stop
        angle = float(np.degrees(np.arctan2(ys[1] - ys[0], xs[1] - xs[0]))) if xs else 0.0
        tracks.append(FocalTrack("polyline", tuple(xs), tuple(ys), tuple(values), angle,
                                 message, name=name, in_field=bool(p.in_field),
                                 sunlit=bool(p.visible)))
    raw = {"seed": int(visit.observation_id) % 2**31, "band": visit.band,
           "exptime": visit.exptime_s, "seeing": job.seeing,
           "zenith": 90.0 - job.alt_deg, "sky": {"level": job.sky},
           "stars": _stars(visit) if options.stars else False,
           "noise": True, "time": visit.start.utc.isot,
           "pupil": model.get("pupil", "annulus"),
           "focus_offset_um": model.get("focus_offset_um", 0.0),
           "pointing": {"ra": visit.ra_deg, "dec": visit.dec_deg,
                        "rotation": visit.rotation_deg},
           "detectors": list(job.ccds),
           "satellites": [{**{k: v for k, v in model.items() if k not in SCENE_MODEL_KEYS},
                           "orbit": {"tle": list(by_name[n].tle_lines())}}
                          for n in job.names]}
    if raw["pupil"] == "rubin" and visit.rotator_deg is not None:
        raw["rotator_deg"] = visit.rotator_deg  # opsim's rotTelPos turns the CCDs on the vanes

    def orbit_track(where, *_):
        return tracks[int(where[len("satellites["):].split("]")[0])]

    scene, ftracks, ccds, _ = parse_focal_parts(raw, orbit_track)
    fscene = FocalScene(scene=scene, tracks=ftracks, ccds=ccds, cutout=None, digest=job.key,
                        raw=raw)
    return make_plan(fscene)


#: The star counts' fit (Bahcall & Soneira) holds from this galactic latitude, deg.
MIN_STAR_LATITUDE_DEG = 20.0


def _stars(visit):
    """A visit's ``stars:``: the sky's stars at its galactic position; within
    :data:`MIN_STAR_LATITUDE_DEG` of the plane, where the star counts' fit does not reach,
    those at that latitude (fewer stars than the plane has)."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    gal = SkyCoord(ra=visit.ra_deg * u.deg, dec=visit.dec_deg * u.deg).galactic
    b = float(gal.b.deg)
    if abs(b) >= MIN_STAR_LATITUDE_DEG:
        return True
    return {"galactic_l": float(gal.l.deg),
            "galactic_b": math.copysign(MIN_STAR_LATITUDE_DEG, b)}


# --- the run --------------------------------------------------------------------------------

@dataclass
class RenderResult:
    """What a render did: per visit ``{CCD: measured}``, the CCDs rendered now, skipped
    (done before) and failed (manifest rows with their ``visit``), and its seconds."""

    measured: dict
    rendered: list
    skipped: list
    failed: list
    seconds: float = 0.0


def visit_batches(plans, constellation, model, outdir, options, constellation_path, epoch):
    """One :class:`~inject.exposure.runner.Batch` per streaked visit: its folder, its key,
    the CCDs its streaks cross, the work that makes its plan (:func:`visit_plan`), the CCDs'
    cut-out, compression and measure (:func:`inject.survey.compare.measure_ccd`). A CCD is
    done when its file matches its manifest row and its ``<CCD>.mask.json`` has the key.

    Returns
    -------
    dict
        ``{observationId: Batch}``.
    """
    from inject.camera import layout as fp
    from inject.exposure.runner import Batch
    from inject.survey.compare import measure_ccd, read_measured

    out = {}
    for plan in plans:
        if not plan.streaks:
            continue
        names = tuple(s.satellite for s in plan.streaks)
        ccds = tuple(sorted({fp.ccd(c) for s in plan.streaks for c in s.ccds},
                            key=lambda c: c.id))
        folder = visit_dir(outdir, plan.visit)
        key = visit_key(plan, constellation, model, options)
        job = VisitJob(plan.visit, names, tuple(c.name for c in ccds), plan.seeing_arcsec,
                       plan.sky_e_per_px, plan.alt_deg, key)

        def done(ccd, folder=folder, key=key):
            return (read_measured(folder, ccd.name) or {}).get("key") == key

        out[plan.visit.observation_id] = Batch(
            folder, key, ccds, prepare=(visit_plan, constellation_path, epoch, model, job,
                                        options),
            task={"compression": options.compression, "measure": measure_ccd,
                  "planned": {i: (s.satellite, s.mask_width_px)
                              for i, s in enumerate(plan.streaks)}},
            cutout=options.cutout, done=done)
    return out


def render_visits(batches, executor, overwrite=False, retries=2, progress=None, verify=False):
    """Render and mask the CCDs of ``batches`` (:func:`visit_batches`) on ``executor``: the
    focal plane's :func:`inject.exposure.runner.run_batches`, whose claims, retries, failures
    and stop are those of ``inject focalplane`` (``verify``: as there).

    Returns
    -------
    RenderResult

    Raises
    ------
    OutputError, Stopped
        As :func:`~inject.exposure.runner.run_batches`.
    """
    from inject.exposure.runner import make_outdir, run_batches
    from inject.survey.compare import read_measured

    started = time.perf_counter()
    if batches:  # OUTDIR/visits, the visits' folders' parent
        make_outdir(os.path.dirname(next(iter(batches.values())).outdir))
    run = run_batches(list(batches.values()), executor, overwrite, retries, progress, verify)
    visit = {b.outdir: v for v, b in batches.items()}
    result = RenderResult({v: {} for v in batches}, [], [], [],
                          time.perf_counter() - started)
    for row in run.skipped:
        record = read_measured(row["outdir"], row["detector"])
        result.measured[visit[row["outdir"]]][row["detector"]] = record
        result.skipped.append({"visit": visit[row["outdir"]], **row})
    for row in run.rendered:
        result.measured[visit[row["outdir"]]][row["detector"]] = row["measured"]
        result.rendered.append({"visit": visit[row["outdir"]],
                                **{k: v for k, v in row.items() if k != "measured"}})
    result.failed = [{"visit": visit[row["outdir"]], **row} for row in run.failed]
    return result
