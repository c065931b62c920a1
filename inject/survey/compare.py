"""``inject survey --render``: what the masker measures on a rendered CCD, set against the plan.

On each rendered CCD (:func:`measure_ccd`, the runner's measure hook, on a worker) the masker
(:func:`inject.masking.run.analyse`, its defaults: the ``sb`` rule at 1 sigma; no bootstrap of
the FWHM's error bar, which is not recorded) searches the
image, each streak it finds is matched to the planned track it lies on (:func:`match_streaks`)
and the plan's mask is counted on the same pixels (:func:`planned_pixels`); the results go to
``<CCD>.mask.json`` beside the file. ``streaks.csv`` then gains, per planned crossing, the
measured values next to the planned ones (:data:`MEASURED_FIELDS`, :func:`measured_columns`),
and ``summary.json`` a ``render`` block (:func:`render_summary`).
"""
import json
import math
import os
import time

import numpy as np

#: Columns :func:`measured_columns` adds to ``streaks.csv``.
MEASURED_FIELDS = ("rendered_ccds", "found_ccds", "measured_fwhm_arcsec",
                   "measured_mask_width_px", "measured_pixels_lost", "planned_pixels_rendered")
#: A found streak lies on a planned track when their directions differ by at most this
#: (deg) and its middle is within :data:`MATCH_DISTANCE_PX` (or the planned mask's width) of
#: the track's line.
MATCH_ANGLE_DEG = 3.0
MATCH_DISTANCE_PX = 15.0
#: The masker's results of a CCD, beside its file: ``<CCD>`` + this.
MEASURED_SUFFIX = ".mask.json"


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
    """Pixels the plan's mask of a track (a FocalTrack, mm) takes on a CCD, inside ``box =
    (x0, y0, nx, ny)`` (None: the whole CCD), each once
    (:func:`inject.survey.plan.run_spans`)."""
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


def measure_ccd(task, ccd, scene, result, streaks, part):
    """Mask a rendered CCD (the runner's measure hook: :class:`inject.exposure.runner.Task`)
    and write what was measured to ``<CCD>.mask.json``, before the file is committed.

    ``task.planned`` is ``{satellite index: (name, planned mask width px)}``; ``part`` the
    written file (a lossy file is masked as it was kept).

    Returns
    -------
    dict
        The JSON's content.
    """
    from inject.instrument import LSST
    from inject.masking.detect import BAD_PLANES
    from inject.masking.run import analyse
    from inject.maskplanes import MASK_PLANES

    start = time.perf_counter()
    image = result.image
    if task.compression == "lossy":  # the masker sees what was kept
        from astropy.io import fits

        with fits.open(part) as hdus:
            image = np.asarray(hdus["IMAGE"].data)
    planes = sum(1 << MASK_PLANES[p] for p in BAD_PLANES if p in MASK_PLANES)
    bad = (np.asarray(result.mask) & planes) != 0
    # No bootstrap of the FWHM's error bar: it is not recorded.
    masked = analyse(image, bad=bad if bad.any() else None, pixel_scale=LSST.pixel_scale_arcsec,
                     n_boot=0)
    widths = [task.planned[s.satellite][1] for s in streaks]
    matched = match_streaks(masked.streaks, streaks, widths)
    measured = {}
    for k, s in enumerate(streaks):
        name, width = task.planned[s.satellite]
        entry = measured.setdefault(name, {"planned_pixels": 0})
        entry["planned_pixels"] += planned_pixels(task.fscene.tracks[s.satellite], width, ccd,
                                                  task.box)
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
    ny, nx = result.image.shape
    x0, y0 = (0, 0) if task.box is None else task.box[:2]
    record = {"key": task.fscene.digest, "ccd": ccd.name, "box": [x0, y0, nx, ny],
              "found": len(masked.streaks), "matched": len(matched),
              "masked_pixels": masked.masked_pixels, "sky_sigma": _number(masked.sky_sigma),
              "streaks": measured, "compression": task.compression,
              "file_bytes": os.path.getsize(part),
              # IMAGE, MASK, VARIANCE and STREAK_MODEL of 4 bytes a pixel, uncompressed.
              "plain_bytes": 16 * nx * ny,
              "seconds": {"mask": time.perf_counter() - start}}
    _write_json(os.path.join(task.outdir, ccd.name + MEASURED_SUFFIX), record)
    return record


def read_measured(outdir, name):
    """The ``<CCD>.mask.json`` of CCD ``name`` in ``outdir`` (None if missing or unreadable)."""
    try:
        with open(os.path.join(outdir, name + MEASURED_SUFFIX), encoding="utf-8") as stream:
            return json.load(stream)
    except (OSError, ValueError):
        return None


def _number(value):
    value = float(value)
    return value if math.isfinite(value) else None


def _write_json(path, mapping):
    from inject.io.atomic import atomic_path

    with atomic_path(path, overwrite=True) as tmp:
        with open(tmp, "w", encoding="utf-8") as stream:
            json.dump(mapping, stream, indent=1)


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
