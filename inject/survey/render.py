"""``inject survey --render``: the streaked CCDs of a night rendered, masked and measured.

For every visit with streaks (its :class:`~inject.survey.plan.VisitPlan`):

1. **The visit's focal-plane scene** (:func:`visit_scene`, on a worker): the visit's band,
   seeing (the plan's ``FWHMgeom``), sky (the plan's e-/px, so that the masker meets the
   noise the plan's mask widths were computed against), pointing (fieldRA, fieldDec,
   rotSkyPos), start and open-shutter time, and the satellites the plan found, each with its
   exact pass over the visit's snaps (the plan's own passes: one shared frame, the readouts
   between snaps left out) as an orbit track (:class:`~inject.trajectory.FocalTrack`). Its
   plan (:func:`inject.exposure.plan.make_plan`) gives each CCD the parts of the tracks that
   reach it.
2. **Each streaked CCD** (the CCDs the plan's centre lines cross; :func:`render_ccd`, on a
   worker): simulated as the focal-plane runner simulates it (:mod:`inject.exposure.ccd`:
   stars of the sky, noise per amplifier, the streak model at the CCD's plate scale), whole,
   or only a square cut-out centred on its streaks (``cutout``: its pixels' coordinates,
   WCS and ``LTV``/xy0 are those of the whole CCD); written tile-compressed
   (:data:`inject.io.fits.COMPRESSIONS`) to ``OUTDIR/visits/<observationId>/<CCD>.fits``;
   searched by the masker (:func:`inject.masking.run.analyse`, its defaults: the ``sb``
   rule at 1 sigma), and each streak it finds matched to the planned track it lies on
   (:func:`match_streaks`). What it measured goes to ``<CCD>.mask.json`` beside the file.
3. **streaks.csv** gains, per planned crossing, the measured values next to the planned ones
   (:data:`MEASURED_FIELDS`, :func:`measured_columns`).

The CCDs run on any ``concurrent.futures`` executor (a process pool, Dask's), one task per
visit scene and one per CCD. Each visit's folder has the focal-plane runner's
``manifest.csv`` (:mod:`inject.exposure.runner`): a CCD's file and its row are committed
together, so a run stopped partway and started again renders only the CCDs not done. The
rows carry the visit's key (:func:`visit_key`: the visit, its satellites' element sets, the
model and the options), so that a run with other inputs is refused without ``overwrite``.
"""
import contextlib
import hashlib
import json
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from inject import __version__
from inject.errors import InjectError, OrbitWarning, OutputError
from inject.trajectory import clip_segment

#: Columns :func:`measured_columns` adds to ``streaks.csv``.
MEASURED_FIELDS = ("rendered_ccds", "found_ccds", "measured_fwhm_arcsec",
                   "measured_mask_width_px", "measured_pixels_lost", "planned_pixels_rendered")
#: Side of a cut-out (px) by default.
DEFAULT_CUTOUT_PX = 1024
#: Folder of the visits' CCD files in OUTDIR.
VISITS_DIR = "visits"
#: A found streak lies on a planned track when their directions differ by at most this
#: (deg) and its middle is within :data:`MATCH_DISTANCE_PX` (or the planned mask's width) of
#: the track's line.
MATCH_ANGLE_DEG = 3.0
MATCH_DISTANCE_PX = 15.0


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


def _file_sha256(path):
    with open(path, "rb") as stream:
        return hashlib.sha256(stream.read()).hexdigest()


def visit_key(plan, constellation, model, options):
    """SHA-256 of what a visit's CCD files depend on: the visit, the plan's seeing and sky,
    its streak satellites' element sets, the satellites' model and the render options."""
    by_name = constellation.by_name
    v = plan.visit
    text = json.dumps({
        "visit": [v.observation_id, v.mjd_tai, v.ra_deg, v.dec_deg, v.rotation_deg, v.band,
                  v.exptime_s, v.n_exposures, plan.seeing_arcsec, plan.sky_e_per_px,
                  plan.alt_deg],
        "satellites": [[s.satellite, *by_name[s.satellite].tle_lines()] for s in plan.streaks],
        "model": model, "options": [options.cutout, options.compression, options.stars],
        "version": __version__}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def model_keys(path):
    """The satellites' model keys of a constellation file (``shape``, ``mag``,
    ``ref_range``, ``lumos``: a scene satellite's) and its ``pupil`` (the scene's)."""
    from inject.schema import load_scene_file

    raw = load_scene_file(path)
    return {k: raw[k] for k in ("shape", "mag", "ref_range", "lumos", "pupil") if k in raw}


# --- the visit's scene (a worker) -----------------------------------------------------------

@dataclass(frozen=True)
class VisitJob:
    """A streaked visit to render: what the parent knows from the plan."""

    visit: object
    names: tuple
    ccds: tuple
    seeing: float
    sky: float
    alt_deg: float
    key: str
    outdir: str
    #: ``{satellite: planned mask width, px}``.
    widths: dict


@dataclass(frozen=True)
class VisitWork:
    """A visit's scene, its plan and each CCD's rendered box: what the CCD tasks need."""

    fscene: object
    plan: object
    boxes: dict


def visit_scene(constellation_path, epoch, model, job, options):
    """The visit's :class:`~inject.exposure.scene.FocalScene` (its satellites' passes as
    orbit tracks), its plan, and each CCD's box (``(x0, y0, nx, ny)``, or None for the
    whole CCD). Runs on a worker; reads the constellation once per process."""
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
           "pointing": {"ra": visit.ra_deg, "dec": visit.dec_deg,
                        "rotation": visit.rotation_deg},
           "detectors": list(job.ccds),
           "satellites": [{**{k: v for k, v in model.items() if k != "pupil"},
                           "orbit": {"tle": list(by_name[n].tle_lines())}}
                          for n in job.names]}

    def orbit_track(where, *_):
        return tracks[int(where[len("satellites["):].split("]")[0])]

    scene, ftracks, ccds, _ = parse_focal_parts(raw, orbit_track)
    fscene = FocalScene(scene=scene, tracks=ftracks, ccds=ccds, cutout=None, digest=job.key,
                        raw=raw)
    plan = make_plan(fscene)
    boxes = {}
    for ccd in ccds:
        boxes[ccd.name] = None if options.cutout is None else \
            cutout_box(ccd, plan.streaks(ccd), options.cutout)
    return VisitWork(fscene, plan, boxes)


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


def cutout_box(ccd, streaks, side):
    """``(x0, y0, nx, ny)``: a ``side`` x ``side`` box of the CCD (clipped to it) centred on
    the middle of its streaks' parts on the CCD (the mean of their middles)."""
    ny_all, nx_all = ccd.shape
    middles = []
    for s in streaks:
        x0, y0, x1, y1 = s.ends
        a = clip_segment(x0, y0, x1, y1, (-0.5, nx_all - 0.5), (-0.5, ny_all - 0.5))
        if a is not None:
            middles.append(((a[0] + a[2]) / 2, (a[1] + a[3]) / 2))
    cx, cy = np.mean(middles, axis=0) if middles else (nx_all / 2, ny_all / 2)
    nx, ny = min(side, nx_all), min(side, ny_all)
    bx = int(min(max(round(cx - nx / 2), 0), nx_all - nx))
    by = int(min(max(round(cy - ny / 2), 0), ny_all - ny))
    return (bx, by, nx, ny)


# --- one CCD (a worker) ---------------------------------------------------------------------

@dataclass(frozen=True)
class CCDTask:
    """One CCD of a visit to render and mask."""

    fscene: object
    detector: str
    streaks: tuple
    box: tuple | None
    outdir: str
    compression: str | None
    #: ``{satellite index: (name, planned mask width px)}`` of the visit's streaks.
    planned: dict


def _shifted(track, dx, dy):
    from inject.trajectory import Track

    vertices = None if track.vertices is None else tuple(
        {**v, "x": v["x"] - dx, "y": v["y"] - dy} for v in track.vertices)
    return Track(track.x0 - dx, track.y0 - dy, track.angle, track.length, vertices)


def simulate_box(fscene, ccd, streaks, box):
    """Simulate a CCD of a focal-plane scene, whole (``box`` None) or only the pixels
    ``[y0, y0 + ny) x [x0, x0 + nx)`` of ``box = (x0, y0, nx, ny)``, with its streaks from the
    plan (:meth:`inject.exposure.plan.Plan.streaks`), as
    :func:`inject.exposure.ccd.simulate_ccd` does for a whole CCD: the streaks' models are the
    whole CCD's, the tracks and the WCS moved to the box, the sky's stars placed through that
    WCS. A box's noise is drawn as for a cut-out at the CCD's corner (statistically the same).

    Returns
    -------
    scene, result, wcs, streaks
        The CCD's scene, its :class:`~inject.scene.SceneResult`, WCS and the streaks in the
        box's pixels.
    """
    from astropy.wcs import Sip

    from inject.camera.wcs import ccd_wcs
    from inject.config import with_detector
    from inject.exposure.ccd import simulate_streaks

    wcs = ccd_wcs(ccd, fscene.pointing)
    det = ccd.detector
    if box is not None:
        x0, y0, nx, ny = box
        det = det.cutout(nx, ny)
        streaks = [replace(s, track=_shifted(s.track, x0, y0),
                           ends=(s.ends[0] - x0, s.ends[1] - y0, s.ends[2] - x0,
                                 s.ends[3] - y0)) for s in streaks]
        wcs = wcs.deepcopy()
        wcs.wcs.crpix = wcs.wcs.crpix - np.array([x0, y0], float)
        if wcs.sip is not None:
            sip = wcs.sip
            wcs.sip = Sip(sip.a, sip.b, sip.ap, sip.bp, wcs.wcs.crpix)
        wcs.wcs.set()
    sats = [replace(fscene.scene.satellites[s.satellite], track=s.track) for s in streaks]
    scene = with_detector(fscene.scene, det, sats)
    return scene, simulate_streaks(fscene, ccd, scene, wcs, streaks), wcs, streaks


def match_streaks(found, streaks, widths):
    """Match the masker's streaks to the planned tracks they lie on.

    Parameters
    ----------
    found : list of dict
        The masker's streaks (:func:`inject.masking.run.streak_record`), most significant
        first.
    streaks : list of CCDStreak
        The planned tracks on the image (pixels of the image).
    widths : list of float
        The planned mask width of each (px).

    Returns
    -------
    dict
        ``{index into streaks: found streak}``: each found streak goes to the nearest
        planned track within :data:`MATCH_ANGLE_DEG` and :data:`MATCH_DISTANCE_PX` (or the
        planned width); a track keeps the first (most significant) streak found on it.
    """
    out = {}
    for rec in found:
        mx, my = (rec["x0"] + rec["x1"]) / 2, (rec["y0"] + rec["y1"]) / 2
        best = None
        for k, s in enumerate(streaks):
            if k in out:
                continue
            x0, y0, x1, y1 = s.ends
            length = math.hypot(x1 - x0, y1 - y0)
            if length == 0:
                continue
            angle = math.degrees(math.atan2(y1 - y0, x1 - x0))
            turn = abs((rec["angle_deg"] - angle + 90.0) % 180.0 - 90.0)
            distance = abs((x1 - x0) * (y0 - my) - (x0 - mx) * (y1 - y0)) / length
            if turn <= MATCH_ANGLE_DEG and distance <= max(MATCH_DISTANCE_PX, widths[k]):
                if best is None or distance < best[0]:
                    best = (distance, k)
        if best is not None:
            out[best[1]] = rec
    return out


def planned_pixels(track, width, ccd, box):
    """Pixels the plan's mask of a track (a FocalTrack, mm) takes on a CCD, inside ``box``
    (None: the whole CCD), each once (:func:`inject.survey.plan.run_spans`)."""
    from inject.survey.plan import run_spans, union_pixels

    spans = []
    for part in track.parts():
        spans += run_spans(part.xs, part.ys, width, ccd)
    if box is not None:
        x0, y0, nx, ny = box
        clipped = []
        for rows, start, stop in spans:
            rows, start, stop = (np.asarray(a) for a in (rows, start, stop))
            keep = (rows >= y0) & (rows < y0 + ny)
            lo, hi = np.maximum(start[keep], x0), np.minimum(stop[keep], x0 + nx)
            clipped.append((rows[keep], lo, np.maximum(hi, lo)))
        spans = clipped
    return union_pixels(spans)


def render_ccd(task):
    """Render one CCD of a visit, write it, mask it, and commit its file with its manifest
    row (:func:`inject.exposure.runner.commit`) after its ``<CCD>.mask.json``.

    Returns
    -------
    dict
        The manifest row, with ``measured`` (the JSON's content).
    """
    import multiprocessing

    from inject.camera import layout as fp
    from inject.exposure.ccd import ccd_cards
    from inject.exposure.runner import FIELDS, commit, limit_threads
    from inject.instrument import LSST
    from inject.io.atomic import temporary_prefix
    from inject.io.fits import write_exposure
    from inject.masking.detect import BAD_PLANES
    from inject.masking.run import analyse
    from inject.maskplanes import MASK_PLANES

    if multiprocessing.parent_process() is not None:
        limit_threads()
    start = time.perf_counter()
    ccd = fp.ccd(task.detector)
    scene, result, wcs, streaks = simulate_box(task.fscene, ccd, task.streaks, task.box)
    simulated = time.perf_counter()
    path = os.path.join(task.outdir, f"{ccd.name}.fits")
    part = os.path.join(task.outdir, f"{temporary_prefix()}part-{ccd.name}.fits")
    x0, y0 = (0, 0) if task.box is None else task.box[:2]
    cards = ccd_cards(ccd, task.fscene.digest, "survey visit key (sha256)")
    try:
        digest = write_exposure(part, scene, result, scene.detector.gain,
                                wcs_header=wcs.to_header(relax=True), overwrite=True,
                                primary_cards=cards, xy0=(x0, y0),
                                compression=task.compression)
        written = time.perf_counter()
        image = result.image
        if task.compression == "lossy":  # the masker sees what was kept
            from astropy.io import fits

            with fits.open(part) as hdus:
                image = np.asarray(hdus["IMAGE"].data)
        planes = sum(1 << MASK_PLANES[p] for p in BAD_PLANES if p in MASK_PLANES)
        bad = (np.asarray(result.mask) & planes) != 0
        masked = analyse(image, bad=bad if bad.any() else None,
                         pixel_scale=LSST.pixel_scale_arcsec)
        widths = [task.planned[s.satellite][1] for s in streaks]
        matched = match_streaks(masked.streaks, streaks, widths)
        measured = {}
        for k, s in enumerate(streaks):
            name, width = task.planned[s.satellite]
            entry = measured.setdefault(name, {"planned_pixels": 0})
            entry["planned_pixels"] += planned_pixels(task.fscene.tracks[s.satellite], width,
                                                      ccd, task.box)
            rec = matched.get(k)
            if rec is not None and "fwhm_px" not in entry:
                entry.update({
                    "fwhm_px": _number(rec["fwhm_px"]),
                    "fwhm_arcsec": _number(rec["fwhm_px"] * s.pixel_scale),
                    "mask_width_px": _number(rec["mask_width_px"]),
                    "masked_pixels": int(rec["masked_pixels"]),
                    "length_px": _number(rec["length_px"]),
                    "significance": _number(rec["significance"]),
                    "pixel_scale_arcsec": s.pixel_scale})
        masked_s = time.perf_counter()
        ny, nx = result.image.shape
        record = {"key": task.fscene.digest, "ccd": ccd.name, "box": [x0, y0, nx, ny],
                  "found": len(masked.streaks), "matched": len(matched),
                  "masked_pixels": masked.masked_pixels, "sky_sigma": _number(masked.sky_sigma),
                  "streaks": measured, "compression": task.compression,
                  "file_bytes": os.path.getsize(part),
                  # IMAGE, MASK, VARIANCE and STREAK_MODEL of 4 bytes a pixel, uncompressed.
                  "plain_bytes": 16 * nx * ny,
                  "seconds": {"simulate": simulated - start, "write": written - simulated,
                              "mask": masked_s - written}}
        _write_json(os.path.join(task.outdir, f"{ccd.name}.mask.json"), record)
        end = time.perf_counter()
        row = {"detector": ccd.name, "id": ccd.id, "vendor": ccd.vendor,
               "file": os.path.basename(path), "sha256": digest, "streaks": len(streaks),
               "seconds": round(end - start, 3), "status": "done",
               "scene_sha256": task.fscene.digest, "inject_version": __version__, "error": ""}
        claimed = commit(task.outdir, row, part)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(part)
    if claimed is not None:
        raise OutputError(claimed)
    return {**{k: row[k] for k in FIELDS}, "measured": record}


def _number(value):
    value = float(value)
    return value if math.isfinite(value) else None


def _write_json(path, mapping):
    from inject.io.atomic import atomic_path

    with atomic_path(path, overwrite=True) as tmp:
        with open(tmp, "w", encoding="utf-8") as stream:
            json.dump(mapping, stream, indent=1)


def _attempt(function, *args):
    """``function(*args)`` on a worker, a failure on the input returned as a ``failed``
    result instead of raised (:func:`inject.exposure.runner.deterministic`: a retry would
    fail the same way)."""
    from inject.exposure.runner import deterministic, error_text

    try:
        return function(*args)
    except InjectError as err:
        if not deterministic(err):
            raise
        return {"status": "failed", "error": error_text(err)}


# --- the run --------------------------------------------------------------------------------

@dataclass
class RenderResult:
    """What a render did: per visit ``{CCD: measured}``, the CCDs rendered now, skipped
    (done before) and failed (manifest-like rows), and its seconds."""

    measured: dict
    rendered: list
    skipped: list
    failed: list
    seconds: float = 0.0


def prepare(plans, constellation, model, outdir, options, overwrite=False):
    """The :class:`VisitJob` of every streaked visit, with its CCDs to render and those done.

    Each visit's folder is checked as the focal-plane runner checks its output
    (:func:`inject.exposure.runner.triage`: another key's run refused without ``overwrite``,
    replaced with it), before any work; a CCD done is one whose file matches its manifest row
    and whose ``<CCD>.mask.json`` has the visit's key.

    Returns
    -------
    list of (VisitJob, todo names, {done name: measured})
    """
    from inject.camera import layout as fp
    from inject.exposure.runner import make_outdir, triage
    from inject.io.atomic import remove_stale_temporaries

    out = []
    streaked = [p for p in plans if p.streaks]
    if streaked:
        make_outdir(os.path.join(outdir, VISITS_DIR))
    for plan in streaked:
        names = tuple(s.satellite for s in plan.streaks)
        ccds = tuple(sorted({c for s in plan.streaks for c in s.ccds},
                            key=lambda n: fp.ccd(n).id))
        folder = visit_dir(outdir, plan.visit)
        key = visit_key(plan, constellation, model, options)
        job = VisitJob(plan.visit, names, ccds, plan.seeing_arcsec, plan.sky_e_per_px,
                       plan.alt_deg, key, folder,
                       {s.satellite: s.mask_width_px for s in plan.streaks})
        make_outdir(folder)
        remove_stale_temporaries(folder)
        todo, done = triage(SimpleNamespace(digest=key), [fp.ccd(n) for n in ccds], folder,
                            overwrite)
        measured = {}
        for ccd in done:
            record = _read_json(os.path.join(folder, f"{ccd.name}.mask.json"))
            if record is None or record.get("key") != key:
                todo.append(ccd)
            else:
                measured[ccd.name] = record
        out.append((job, tuple(c.name for c in sorted(todo, key=lambda c: c.id)), measured))
    return out


def _read_json(path):
    try:
        with open(path, encoding="utf-8") as stream:
            return json.load(stream)
    except (OSError, ValueError):
        return None


def render_visits(jobs, constellation_path, epoch, model, options, executor, retries=2,
                  progress=None):
    """Render and mask the CCDs of ``jobs`` (:func:`prepare`) on ``executor``.

    A visit's scene is one task, then each of its CCDs one task; a CCD that fails does not
    stop the others (its row says why; a failure that is not on the input is retried
    ``retries`` times). A stop (or an error) cancels the tasks not started and stops a process
    pool's workers (:func:`inject.exposure.runner.stop_workers`); the CCDs committed so far
    stay done.

    Returns
    -------
    RenderResult
    """
    from concurrent.futures import FIRST_COMPLETED, wait

    from inject.exposure.runner import cancel, error_text, stop_workers, update_manifest

    started = time.perf_counter()
    result = RenderResult({}, [], [], [])
    for job, _, done in jobs:
        result.measured[job.visit.observation_id] = dict(done)
        result.skipped += [{"visit": job.visit.observation_id, "detector": n} for n in done]
    pending, attempts, works = {}, {}, {}
    planned = {}
    for job, todo, _ in jobs:
        planned[job.visit.observation_id] = todo

    def fail(job, name, text):
        from inject.camera import layout as fp

        ccd = fp.ccd(name)
        row = {"detector": name, "id": ccd.id, "vendor": ccd.vendor, "file": f"{name}.fits",
               "status": "failed", "scene_sha256": job.key, "inject_version": __version__,
               "error": text}
        with contextlib.suppress(OutputError):
            update_manifest(job.outdir, [row], job.key)
        result.failed.append({"visit": job.visit.observation_id, **row})
        if progress is not None:
            progress(result)

    def submit_ccd(job, name):
        work = works[job.visit.observation_id]
        from inject.camera import layout as fp

        ccd = fp.ccd(name)
        widths = {i: (n, job.widths[n]) for i, n in enumerate(job.names)}
        task = CCDTask(work.fscene, name, tuple(work.plan.streaks(ccd)), work.boxes[name],
                       job.outdir, options.compression, widths)
        pending[executor.submit(_attempt, render_ccd, task)] = ("ccd", job, name)

    def submit_visit(job):
        pending[executor.submit(_attempt, visit_scene, constellation_path, epoch, model, job,
                                options)] = ("visit", job, None)

    try:
        for job, todo, _ in jobs:
            if todo:
                submit_visit(job)
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                kind, job, name = pending.pop(future)
                tag = (job.visit.observation_id, name)
                try:
                    value = future.result()
                except Exception as err:  # a worker's failure must not lose the others
                    attempts[tag] = attempts.get(tag, 0) + 1
                    if attempts[tag] <= retries:
                        (submit_visit(job) if kind == "visit" else submit_ccd(job, name))
                    elif kind == "visit":
                        for n in planned[job.visit.observation_id]:
                            fail(job, n, error_text(err))
                    else:
                        fail(job, name, error_text(err))
                    continue
                if kind == "visit":
                    if isinstance(value, dict):  # failed on its input
                        for n in planned[job.visit.observation_id]:
                            fail(job, n, value["error"])
                        continue
                    works[job.visit.observation_id] = value
                    for n in planned[job.visit.observation_id]:
                        submit_ccd(job, n)
                    continue
                if value.get("status") == "failed":
                    fail(job, name, value["error"])
                    continue
                result.measured[job.visit.observation_id][name] = value["measured"]
                result.rendered.append({"visit": job.visit.observation_id,
                                        **{k: v for k, v in value.items() if k != "measured"}})
                if progress is not None:
                    progress(result)
    except BaseException:
        cancel(executor, pending)
        stop_workers(executor)
        raise
    result.seconds = time.perf_counter() - started
    return result


# --- streaks.csv's measured columns ---------------------------------------------------------

def measured_columns(plans, measured):
    """``{(observationId, satellite): {column: value}}`` of :data:`MEASURED_FIELDS` for every
    streak of ``plans``, from the CCDs' measurements (``measured``: per visit, ``{CCD:
    the CCD's mask.json}``).

    ``rendered_ccds`` and ``found_ccds``: the streak's CCDs rendered, and those on which the
    masker found it; ``measured_fwhm_arcsec`` and ``measured_mask_width_px``: the means over
    those CCDs weighted by the length found on each; ``measured_pixels_lost``: the pixels its
    masks take on them (within the cut-outs); ``planned_pixels_rendered``: the plan's mask's
    pixels on the same rendered pixels (the measured pixels' counterpart: on cut-outs, a part
    of ``pixels_lost``).
    """
    out = {}
    for plan in plans:
        ccds = measured.get(plan.visit.observation_id, {})
        for s in plan.streaks:
            rendered, found = 0, []
            planned = 0
            for name in s.ccds:
                record = ccds.get(name)
                if record is None:
                    continue
                rendered += 1
                entry = record["streaks"].get(s.satellite, {})
                planned += entry.get("planned_pixels", 0)
                if entry.get("fwhm_px") is not None or entry.get("mask_width_px") is not None:
                    found.append(entry)
            row = {"rendered_ccds": rendered, "found_ccds": len(found),
                   "measured_fwhm_arcsec": _weighted(found, "fwhm_arcsec"),
                   "measured_mask_width_px": _weighted(found, "mask_width_px"),
                   "measured_pixels_lost": sum(e.get("masked_pixels", 0) for e in found)
                   if found else None,
                   "planned_pixels_rendered": planned if rendered else None}
            out[plan.visit.observation_id, s.satellite] = row
    return out


def _weighted(entries, key):
    pairs = [(e[key], e.get("length_px") or 0.0) for e in entries if e.get(key) is not None]
    if not pairs:
        return None
    weights = np.array([w for _, w in pairs], float)
    values = np.array([v for v, _ in pairs], float)
    if weights.sum() <= 0:
        return float(values.mean())
    return float(np.sum(values * weights) / weights.sum())


def render_summary(plans, columns, result, options):
    """The ``render`` block of ``summary.json``: the CCDs, the time, the files' sizes, and
    the measured against the planned (medians of the ratios over the streaks found)."""
    records = [r for visit in result.measured.values() for r in visit.values()]
    ratios = {}
    for plan in plans:
        for s in plan.streaks:
            row = columns.get((plan.visit.observation_id, s.satellite))
            if not row or not row["found_ccds"]:
                continue
            for key, planned, measured in (
                    ("fwhm", s.fwhm_arcsec, row["measured_fwhm_arcsec"]),
                    ("mask_width", s.mask_width_px, row["measured_mask_width_px"]),
                    ("pixels", row["planned_pixels_rendered"], row["measured_pixels_lost"])):
                if planned and measured is not None:
                    ratios.setdefault(key, []).append(measured / planned)
    n = len(result.rendered)
    file_bytes = sum(r.get("file_bytes", 0) for r in records)
    plain = sum(r.get("plain_bytes", 0) for r in records)
    return {
        "ccds": len(records), "ccds_rendered": n, "ccds_skipped": len(result.skipped),
        "ccds_failed": len(result.failed), "seconds": round(result.seconds, 3),
        "ccds_per_second": round(n / result.seconds, 4) if n and result.seconds else None,
        "cutout_px": options.cutout, "compression": options.compression,
        "file_bytes": file_bytes, "plain_bytes": plain,
        "size_ratio": round(file_bytes / plain, 4) if plain else None,
        "streaks_found": sum(1 for r in columns.values() if r["found_ccds"]),
        "streaks_rendered": sum(1 for r in columns.values() if r["rendered_ccds"]),
        "measured_over_planned_median": {k: float(np.median(v)) for k, v in ratios.items()},
    }


class Progress:
    """A line per tenth of the CCDs on stderr (``progress(result)`` after each)."""

    def __init__(self, total):
        self.total, self.next = total, 0

    def __call__(self, result):
        done = len(result.rendered) + len(result.failed)
        if done >= self.next or done == self.total:
            print(f"inject survey --render: CCD {done}/{self.total}", file=sys.stderr,
                  flush=True)
            self.next = done + max(1, self.total // 10)
