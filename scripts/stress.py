#!/usr/bin/env python
"""Numerical stress grid of the streak engine: finite results, flux conservation, agreement
with the brute-force reference, continuity across branch points, clipping at image edges,
saturating and sub-noise magnitudes, float32 images.

Usage::

    python scripts/stress.py [--out out/stress] [--quick] [--workers 2]

The grid varies one or two axes at a time around the paper's case (Snyder & Tyson: a 7.25 x
2.65 m box at 550 km, zenith 70 deg, phi 90 deg, Kolmogorov 0.67", g = 5 at 550 km, a track
at 33 deg), not the Cartesian product. Every cell runs a few checks; each check has a value, a
limit and passes when ``value <= limit``:

``finite``
    Every output (image, cross-section, the ``inject profile`` scalars, the render plan) is
    finite: the value is the number of non-finite entries, the limit 0.
``flux``
    On an image large enough to hold the whole footprint, ``|sum / (flux_per_px * length) - 1|``
    <= 1e-4 (the budget drops at most ``flux_tolerance`` = 5e-5 of the charge in the seeing
    wings).
``reference``
    Largest pixel difference from :func:`inject.reference.render_brute_force`, relative to the
    streak's peak surface brightness ``peak_e_per_px`` (by definition: the most charge a pixel can
    get), <= 1e-4. Tracks are short (<= 3 px) to keep the brute force affordable; the
    reference is Richardson-extrapolated from ``n`` and ``2n`` sub-steps, which removes the
    midpoint rule's ``O(step^2)`` error. The error relative to the short streak's own
    (lower) peak is recorded as ``reference_own_peak`` for information: see the report.
``exact``
    A Gaussian profile swept along a row or column has a closed form (error functions): the
    largest difference relative to the long-streak peak, <= 1e-4.
``continuity``
    Two renders just either side of a branch point (zenith 0, the footprint's major-axis
    switch at 45 deg, angles 1e-9 from 0 and 90 deg, a pixel edge, the thresholds at which the
    renderer drops the satellite's shape or the defocus, the noise-driven tightening of the
    tolerance) differ by at most the budget's tolerance (5e-5) of the peak: each side is
    within its own budget of a truth that barely moves.
``clip``
    A streak rendered on a small image equals the same streak rendered on a padded image and
    cropped (to 1e-9 of the peak); a line crossing the image (``Track`` without a length, as
    scenes draw it) agrees with a long explicit segment along the same line to the tolerance.
``float32``
    Rendering into a float32 image differs from the float64 render by at most one float32
    rounding of the pixel value (the value is the difference in units of that rounding).
``saturation`` / ``sub-noise`` / ``io``
    Scene cells (``simulate`` on a 256 x 200 cut-out with sky, stars and noise): saturation
    flags and SAT mask pixels exactly when ``peak + sky >= full well``; no pixel above full
    well plus read noise; a mag-25 streak peaks below the noise; FITS and EXR written and read
    back bit for bit.

Outputs in ``--out``: ``stress.json`` (every cell), ``stress.md`` (the table printed at the
end), ``stress.png`` (worst value/limit per axis value). Exit status 1 if any cell fails.
"""
import argparse
import json
import math
import os
import sys
import tempfile
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

FLUX_LIMIT = 1e-4
REF_LIMIT = 1e-4
EXACT_LIMIT = 1e-4
CLIP_LIMIT = 1e-9
#: An ITL CCD's diagonal, corner to corner, pixels.
ITL_DIAGONAL = math.hypot(4072, 4000)
ITL_DIAGONAL_ANGLE = math.degrees(math.atan2(4000, 4072))

PAPER = {"height": 550.0, "zenith": 70.0, "phi": 90.0, "shape": ("box", 7.25, 2.65),
         "mag": 5.0, "band": "g", "seeing": 0.67, "seeing_model": "kolmogorov",
         "telescope": None}
TRACK = {"angle": 33.0, "fx": 0.3, "fy": 0.7, "length": 60.0}


# ---------------------------------------------------------------------------------------------
# Building blocks


def make_model(spec):
    from inject.instrument import LSST, Telescope
    from inject.profile import Seeing
    from inject.satellite import Box, Disk
    from inject.streak import StreakModel

    kind, *dims = spec["shape"]
    shape = Box(*dims) if kind == "box" else Disk(*dims)
    telescope = LSST if spec["telescope"] is None else Telescope(*spec["telescope"])
    return StreakModel(height_km=spec["height"], zenith_deg=spec["zenith"],
                       phi_deg=spec["phi"], shape=shape, mag=spec["mag"],
                       band_name=spec["band"],
                       seeing=Seeing(spec["seeing"], spec["seeing_model"]),
                       telescope=telescope)


def paper_box(size):
    """The paper's box scaled so that its long side is ``size`` metres."""
    return ("box", size, size * 2.65 / 7.25)


def count_nonfinite(*arrays):
    return int(sum(np.size(a) - np.count_nonzero(np.isfinite(a)) for a in arrays))


def model_nonfinite(model):
    """Non-finite entries among the summary scalars and the cross-section."""
    summary = model.summary()
    scalars = [v for v in summary.values() if isinstance(v, float)]
    offsets, e_per_px = model.cross_section()
    return count_nonfinite(np.array(scalars), offsets, e_per_px)


def check(name, value, limit, **info):
    value = float(value)
    return {"check": name, "value": value, "limit": float(limit),
            "ok": bool(np.isfinite(value) and value <= limit), **info}


def placed_segment(swept, angle, fx, fy, length):
    """A padded image shape and a segment whose whole footprint lies inside it."""
    from inject.trajectory import Segment

    c, s = abs(math.cos(math.radians(angle))), abs(math.sin(math.radians(angle)))
    sup, cap = swept.plan.support_px, swept.plan.cap_px
    hx = (length / 2 + cap) * c + sup * s + 4
    hy = (length / 2 + cap) * s + sup * c + 4
    nx, ny = 2 * math.ceil(hx) + 1, 2 * math.ceil(hy) + 1
    cx, cy = nx // 2, ny // 2
    a = math.radians(angle)
    # round, not floor: a track 1e-9 deg off an axis must start in the same pixel.
    x0 = round(cx - length / 2 * math.cos(a)) + fx
    y0 = round(cy - length / 2 * math.sin(a)) + fy
    return (ny, nx), Segment(x0, y0, angle, length)


def brute_reference(model, segment, shape):
    """Richardson-extrapolated brute-force streak (midpoint rule with n and 2n sub-steps)."""
    from inject.reference import render_brute_force

    fwhm_px = model.fwhm_arcsec / model.pixel_scale
    step = 0.25 if fwhm_px >= 4 else 0.1 if fwhm_px >= 2.5 else 0.05
    n = max(1, math.ceil(segment.length / step - 1e-9))
    images = []
    for k in (n, 2 * n):
        # The step that gives exactly k sub-steps (render_brute_force takes ceil(L / step)).
        step_k = segment.length / k * (1 + 1e-12) if segment.length > 0 else 1.0
        images.append(render_brute_force(shape, model.profile, model.pixel_scale, segment,
                                         model.flux_per_px, step_px=step_k))
    return (4 * images[1] - images[0]) / 3, (n, 2 * n)


# ---------------------------------------------------------------------------------------------
# Cell kinds


def render_cell(p):
    """One model and track: finite outputs, flux on a padded image, float32, brute force.

    The image is drawn as the product draws it (:func:`inject.render.render_streak`, whose
    budget follows the track's length); the brute-force check exercises the footprint
    renderer itself on a short track.
    """
    from inject.render import Budget, render_streak, swept_profile
    from inject.trajectory import Segment

    model = make_model(p["model"])
    t = p["track"]
    budget = Budget()
    # The plan render_streak will use: a short track's budget is tighter (its own peak).
    swept = swept_profile(model, t["angle"], budget, t["length"])
    peak = model.peak_e_per_px
    checks = []
    plan = swept.plan
    plan_values = np.array([plan.support_px, plan.cap_px, plan.table_step_px, plan.lsf_step_px,
                            *plan.predicted_error.values()], dtype=float)
    shape, seg = placed_segment(swept, t["angle"], t["fx"], t["fy"], t["length"])
    dtype = np.dtype(p.get("dtype", "float64"))
    pedestal = p.get("pedestal", 0.0)
    image = np.full(shape, pedestal, dtype=dtype)
    result = render_streak(image, model, seg, budget)
    nonfinite = model_nonfinite(model) + count_nonfinite(plan_values, image) + (
        0 if math.isfinite(result.charge_added) else 1)
    checks.append(check("finite", nonfinite, 0))
    total = float(image.sum(dtype=np.float64)) - pedestal * image.size
    expected = model.flux_per_px * seg.length
    if seg.length > 0:
        checks.append(check("flux", abs(total / expected - 1), FLUX_LIMIT,
                            signed=total / expected - 1, pixels=int(result.n_pixels)))
    else:
        checks.append(check("flux", abs(total) / model.flux_per_px, 1e-12, signed=total))
    if dtype != np.float64:
        ref = np.zeros(shape)
        render_streak(ref, model, seg, budget)
        diff = np.abs(image.astype(np.float64) - pedestal - ref).max()
        ulp = np.finfo(dtype).eps * (pedestal + np.abs(ref).max())
        checks.append(check("float32", diff / ulp, 1.0, rel_to_peak=diff / peak))
    del image
    if p.get("brute"):
        length = min(t["length"], 3.0)
        fwhm_px = model.fwhm_arcsec / model.pixel_scale
        n = 2 * math.ceil(4 * fwhm_px + length / 2) + 31
        a = math.radians(t["angle"])
        c0 = n // 2
        short = Segment(c0 - length / 2 * math.cos(a) + t["fx"] - 0.5,
                        c0 - length / 2 * math.sin(a) + t["fy"] - 0.5, t["angle"], length)
        fast = np.zeros((n, n))
        render_streak(fast, model, short, budget)  # budgeted against its own peak
        ref, steps = brute_reference(model, short, (n, n))
        err = np.abs(fast - ref).max()
        # Relative to the short track's own peak (below peak_e_per_px when the track is
        # shorter than the profile): the stricter of the two.
        own_peak = ref.max() if ref.max() > 0 else peak
        checks.append(check("reference", err / own_peak, REF_LIMIT,
                            relative_to_long_peak=err / peak, track_px=length,
                            substeps=steps, image_px=n))
    return checks


def exact_gaussian(shape, sigma, seg, flux):
    """Closed form of a unit-flux Gaussian (sigma in px) swept along +x and pixel-integrated."""
    from inject.reference import swept_gaussian

    return swept_gaussian(shape, sigma, seg, flux)


def gaussian_cell(p):
    """A Gaussian of FWHM ``fwhm_px`` swept along rows and columns against its closed form."""
    import galsim

    from inject.profile import GSPARAMS
    from inject.render import SweptProfile, render_segment
    from inject.trajectory import Segment

    sigma = p["fwhm_px"] / (2 * math.sqrt(2 * math.log(2)))
    scale = 0.2
    profile = galsim.Gaussian(sigma=sigma * scale, gsparams=GSPARAMS)
    worst, worst_at, nonfinite = 0.0, None, 0
    for angle in (0.0, 90.0):
        swept = SweptProfile(profile, scale, angle)
        long_peak = swept.lsf.lsf.max() * scale
        for length in (0.1, 3.0, 40.0):
            seg = Segment(30.3, 40.6, 0.0, length)
            ref = exact_gaussian((90, 100), sigma, seg, 1.0)
            image = np.zeros((90, 100))
            if angle == 0.0:
                render_segment(image, swept, seg, 1.0)
            else:  # the transposed track: x <-> y
                image_t = np.zeros((100, 90))
                render_segment(image_t, swept, Segment(40.6, 30.3, 90.0, length), 1.0)
                image = image_t.T
            nonfinite += count_nonfinite(image)
            err = np.abs(image - ref).max() / long_peak
            if err > worst:
                worst, worst_at = err, {"angle": angle, "length": length,
                                        "table_step_px": swept.plan.table_step_px}
    return [check("finite", nonfinite, 0),
            check("exact", worst, EXACT_LIMIT, at=worst_at,
                  budget_tolerance=5e-5, over_budget=worst > 5e-5)]


def _render_on(shape, model, segment, swept):
    from inject.render import render_segment

    image = np.zeros(shape)
    render_segment(image, swept, segment, model.flux_per_px)
    return image


def edge_cell(p):
    """A track touching the edges or corners of a small image (64 x 48)."""
    from inject.render import swept_profile
    from inject.scene import render_tracks
    from inject.trajectory import Segment, Track

    model = make_model(p["model"])
    ny, nx = shape = (48, 64)
    angle = p["angle"]
    swept = swept_profile(model, angle)
    peak = model.peak_e_per_px
    pad = math.ceil(swept.plan.support_px + swept.plan.cap_px) + 2
    big_shape = (ny + 2 * pad, nx + 2 * pad)
    checks = []
    if p["mode"] == "segment":
        seg = Segment(p["x0"], p["y0"], angle, p["length"])
        small = _render_on(shape, model, seg, swept)
        big = _render_on(big_shape, model, Segment(seg.x0 + pad, seg.y0 + pad, angle,
                                                   seg.length), swept)
        crop = big[pad:pad + ny, pad:pad + nx]
        checks.append(check("finite", count_nonfinite(small, big), 0))
        checks.append(check("clip", np.abs(small - crop).max() / peak, CLIP_LIMIT,
                            charge_on_image=float(small.sum())))
        if p.get("expect_zero"):
            checks.append(check("off-image", float(small.any()), 0))
        else:
            checks.append(check("flux", abs(big.sum() / (model.flux_per_px * seg.length) - 1),
                                FLUX_LIMIT))
    else:  # a line crossing the image, drawn as a scene draws it
        image, truth = render_tracks(shape, [model], [Track(p["x0"], p["y0"], angle, None)])
        # The same line as a long explicit segment, well beyond the footprint on both sides.
        reach = swept.plan.support_px + swept.plan.cap_px + math.hypot(nx, ny) + 10
        a = math.radians(angle)
        line = Segment(p["x0"] - reach * math.cos(a) + pad, p["y0"] - reach * math.sin(a) + pad,
                       angle, 2 * reach)
        crop = _render_on(big_shape, model, line, swept)[pad:pad + ny, pad:pad + nx]
        checks.append(check("finite", count_nonfinite(image), 0))
        checks.append(check("clip", np.abs(image - crop).max() / peak, swept.budget.tolerance,
                            charge_on_image=float(image.sum()), flags=int(truth[0]["flags"]),
                            line_charge_on_image=float(crop.sum())))
    return checks


def _pair_images(model_a, model_b, track_a, track_b, budget_a=None, budget_b=None, shape=None):
    from inject.render import Budget, render_segment, swept_profile
    from inject.trajectory import Segment

    budget_a, budget_b = budget_a or Budget(), budget_b or Budget()
    sa = swept_profile(model_a, track_a["angle"], budget_a)
    sb = swept_profile(model_b, track_b["angle"], budget_b)
    if shape is None:
        shape, _ = placed_segment(sa, track_a["angle"], 0, 0, track_a["length"])
        shape = tuple(s + 6 for s in shape)
    images = []
    for swept, model, t in ((sa, model_a, track_a), (sb, model_b, track_b)):
        image = np.zeros(shape)
        cx, cy = shape[1] // 2, shape[0] // 2
        a = math.radians(t["angle"])
        seg = Segment(round(cx - t["length"] / 2 * math.cos(a)) + t["fx"],
                      round(cy - t["length"] / 2 * math.sin(a)) + t["fy"],
                      t["angle"], t["length"])
        render_segment(image, swept, seg, model.flux_per_px)
        images.append(image)
    return images, (sa.plan, sb.plan)


def _bisect(flag, lo, hi, rel=1e-7, log=True):
    """Narrow ``[lo, hi]`` (``flag(lo) != flag(hi)``) until ``hi / lo - 1 < rel``."""
    f_lo = flag(lo)
    if f_lo == flag(hi):
        raise RuntimeError(f"no threshold between {lo} and {hi}")
    while hi / lo - 1 > rel:
        mid = math.sqrt(lo * hi) if log else 0.5 * (lo + hi)
        if flag(mid) == f_lo:
            lo = mid
        else:
            hi = mid
    return lo, hi


def continuity_cell(p):
    """Two renders either side of a branch point."""
    from inject.render import Budget
    from inject.scene import NOISE_FRACTION, render_tracks
    from inject.trajectory import Track
    kind = p["kind"]
    base = dict(PAPER)
    track = dict(TRACK)
    budget = Budget()
    info = {}
    checks = []
    if kind == "zenith0":
        a, b = make_model(base | {"zenith": 0.0}), make_model(base | {"zenith": 1e-9})
        sa, sb = a.summary(), b.summary()
        worst = 0.0
        for key, va in sa.items():
            if isinstance(va, float) and key != "zenith_deg":
                vb = sb[key]
                worst = max(worst, abs(va - vb) / (max(abs(va), abs(vb)) + 1e-300)
                            if key != "nadir_angle_deg" else abs(va - vb))
        checks.append(check("scalars", worst, 1e-8))
        images, plans = _pair_images(a, b, track, track)
        info["sides"] = "zenith 0 vs 1e-9 deg"
    elif kind in ("angle", "offset", "length"):
        a = b = make_model(base)
        ta, tb = track | p["a"], track | p["b"]
        images, plans = _pair_images(a, b, ta, tb)
        info["sides"] = f"{p['a']} vs {p['b']}"
    elif kind == "shape_drop":
        key = p["axis"]

        def model_at(v):
            spec = base | p.get("base", {})
            spec = spec | ({"shape": paper_box(v)} if key == "size" else {key: v})
            return make_model(spec)

        def dropped(v):
            return "shape" in model_at(v).render_profile(budget.tolerance)[1]

        lo, hi = _bisect(dropped, *p["bracket"])
        a, b = model_at(lo), model_at(hi)
        images, plans = _pair_images(a, b, track, track)
        info["sides"] = f"{key} {lo:.7g} vs {hi:.7g}"
    elif kind == "defocus_drop":
        def model_at(radius):
            return make_model(base | {"telescope": (radius, 0.612 * radius)})

        def dropped(radius):
            return "defocus" in model_at(radius).render_profile(budget.tolerance)[1]

        lo, hi = _bisect(dropped, 0.01, 4.18)
        a, b = model_at(lo), model_at(hi)
        images, plans = _pair_images(a, b, track, track)
        info["sides"] = f"pupil radius {lo:.7g} vs {hi:.7g} m"
    elif kind == "noise_tightening":
        model = make_model(base)
        sigma = budget.tolerance * model.peak_e_per_px / NOISE_FRACTION
        shape = (460, 480)
        tr = Track(200.3, 220.7, track["angle"], track["length"])
        images = [render_tracks(shape, [model], [tr], budget, s)[0]
                  for s in (sigma * (1 - 1e-6), sigma * (1 + 1e-6))]
        a = b = model
        plans = (None, None)
        info["sides"] = f"noise {sigma * (1 - 1e-6):.6g} vs {sigma * (1 + 1e-6):.6g} e-"
    else:
        raise ValueError(kind)
    peak = max(a.peak_e_per_px, b.peak_e_per_px)
    diff = np.abs(images[0] - images[1]).max() / peak
    if plans[0] is not None:
        info["dropped"] = [list(plans[0].dropped), list(plans[1].dropped)]
    checks.insert(0, check("finite", count_nonfinite(*images), 0))
    checks.append(check("continuity", diff, budget.tolerance, **info))
    return checks


def scene_cell(p):
    """``simulate`` on a noisy cut-out: finite outputs, saturation, sub-noise, FITS/EXR."""
    from astropy.io import fits

    from inject.config import parse_scene
    from inject.io.exr import read_exr, write_exr
    from inject.io.fits import write_exposure
    from inject.maskplanes import FLAG_SATURATED, MASK_PLANES
    from inject.scene import simulate
    raw = {"seed": 3, "band": "g", "exptime": 30, "seeing": 0.67, "zenith": 70,
           "detector": {"type": p["detector"], "nx": 256, "ny": 200}, "sky": True,
           "stars": {"mag_bright": 18.0, "mag_limit": 24.0}, "noise": True,
           "satellites": [{"height": 550, "shape": {"type": "box", "length": 7.25,
                                                    "width": 2.65},
                           "mag": p["mag"], "track": {"x0": 20.3, "y0": 30.7, "angle": 25.0}}]}
    scene = parse_scene(raw)
    res = simulate(scene)
    det = scene.detector
    row = res.truth[0]
    checks = []
    numbers = np.array([v for v in row.values() if isinstance(v, (int, float))], dtype=float)
    checks.append(check("finite", count_nonfinite(res.image, res.variance, res.streak_model,
                                                  numbers), 0))
    expect_sat = row["peak_e_per_px"] + res.sky_level >= det.full_well
    flagged = bool(row["flags"] & FLAG_SATURATED)
    sat_pixels = int(np.count_nonzero(res.mask & (1 << MASK_PLANES["SAT"])))
    checks.append(check("saturation", float(flagged != expect_sat)
                        + float((sat_pixels > 0) != expect_sat), 0,
                        expected=bool(expect_sat), sat_pixels=sat_pixels,
                        peak_e=row["peak_e_per_px"]))
    # Bled charge stops at full well; only read noise (sigma = read_noise) lies on top.
    checks.append(check("full-well sigma", (res.image.max() - det.full_well) / det.read_noise,
                        10.0))
    charge = float(res.streak_model.sum())
    checks.append(check("truth-charge", abs(charge - row["charge_in_image_e"])
                        / max(charge, 1e-300), 1e-9))
    if p["mag"] >= 25:
        checks.append(check("sub-noise", row["peak_e_per_px"] / res.noise_sigma, 1.0))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "cell.fits")
        write_exposure(path, scene, res, det.gain)
        with fits.open(path) as hdus:
            back = hdus["IMAGE"].data.astype(np.float32)
            model_back = hdus["STREAK_MODEL"].data.astype(np.float32)
        exr = os.path.join(tmp, "cell.exr")
        write_exr(exr, scene, res)
        exr_back = read_exr(exr)
        mismatches = int(np.count_nonzero(back != res.image.astype(np.float32))
                         + np.count_nonzero(model_back != res.streak_model.astype(np.float32))
                         + np.count_nonzero(exr_back["image"] != res.image.astype(np.float32))
                         + np.count_nonzero(exr_back["mask"] != res.mask))
        checks.append(check("io", mismatches, 0))
    return checks


KINDS = {"render": render_cell, "gauss": gaussian_cell, "edge": edge_cell,
         "continuity": continuity_cell, "scene": scene_cell}


def run_cell(cell):
    start = time.perf_counter()
    try:
        checks = KINDS[cell["kind"]](cell["params"])
        error = None
    except Exception as err:  # a crash is a failed cell, reported with its traceback
        checks = []
        error = "".join(traceback.format_exception_only(type(err), err)).strip()
        error += "\n" + traceback.format_exc()
    ok = error is None and all(c["ok"] for c in checks)
    return cell | {"checks": checks, "ok": ok, "error": error,
                   "seconds": time.perf_counter() - start}


# ---------------------------------------------------------------------------------------------
# The grid


def render(axis, label, model=None, track=None, brute=False, cost=1.0, **extra):
    return {"axis": axis, "label": label, "kind": "render", "cost": cost + (8 if brute else 0),
            "params": {"model": PAPER | (model or {}), "track": TRACK | (track or {}),
                       "brute": brute, **extra}}


def near(value, bases=(0.0, 0.5, 45.0, 90.0, 360.0)):
    """A label that keeps a 1e-9 perturbation visible: ``45+1e-9`` rather than ``45``."""
    for base in bases:
        d = value - base
        if d != 0 and abs(d) < 1e-6:
            return f"{base:g}{'+' if d > 0 else '-'}{abs(d):.0e}".replace("e-09", "e-9")
    return f"{value:g}"


def grid(quick=False):
    cells = []

    def pick(values, keep):
        return [v for v in values if not quick or v in keep]

    # Zenith, exactly 0 and 1e-9 from it.
    for z in pick([0.0, 1e-9, 10.0, 30.0, 45.0, 60.0, 70.0, 80.0, 85.0, 89.0, 89.9],
                  {0.0, 70.0, 89.9}):
        cells.append(render("zenith", f"{z:g}", {"zenith": z},
                            brute=not quick or z in (0.0, 89.9)))
    # Heights, 160 km to GEO.
    for h in pick([160.0, 200.0, 350.0, 550.0, 1000.0, 2000.0, 5000.0, 20200.0, 36000.0],
                  {160.0, 36000.0}):
        cells.append(render("height", f"{h:g}", {"height": h},
                            brute=not quick or h == 36000.0, cost=2))
    # Sizes, 1 cm to 100 m (the paper box scaled; disks at the extremes).
    for size in pick([0.01, 0.1, 1.0, 7.25, 30.0, 100.0], {0.01, 100.0}):
        cells.append(render("size (m)", f"box {size:g}", {"shape": paper_box(size)},
                            brute=True, cost=3))
    for radius in pick([0.005, 50.0], set()):
        cells.append(render("size (m)", f"disk r={radius:g}", {"shape": ("disk", radius)},
                            brute=True))
    # Seeing, 0.3" to 3" (and von Karman).
    for fwhm in pick([0.3, 0.5, 0.67, 1.0, 1.5, 2.0, 3.0], {0.3, 3.0}):
        cells.append(render("seeing (\")", f"{fwhm:g}", {"seeing": fwhm},
                            brute=not quick or fwhm == 0.3, cost=8 if fwhm >= 2 else 1))
    if not quick:
        cells.append(render("seeing (\")", "0.67 vonkarman", {"seeing_model": "vonkarman"},
                            brute=True))
    # Track angles: 0/45/90 and 1e-9 away from them.
    e = 1e-9
    for angle in pick([0.0, e, -e, 33.0, 45 - e, 45.0, 45 + e, 90 - e, 90.0, 90 + e, 135.0,
                       180.0, 270.0, 360 - e], {0.0, e, 45.0, 90 - e}):
        cells.append(render("angle (deg)", near(angle), track={"angle": angle},
                            brute=not quick or angle == 45.0))
    # Sub-pixel offsets of the start point (pixel centres at integers, edges at .5).
    for fx, fy in pick([(0.0, 0.0), (0.5, 0.5), (0.25, 0.75), (0.5 - e, 0.5 + e), (e, -e),
                        (0.999, 0.001)], {(0.5, 0.5)}):
        cells.append(render("sub-pixel offset", f"({near(fx)}, {near(fy)})",
                            track={"fx": fx, "fy": fy}, brute=True))
    # Lengths, 0.1 px to a full ITL diagonal (and 0).
    for length in pick([0.0, 0.1, 0.5, 1.0, 3.0, 10.0, 100.0, 1000.0, ITL_DIAGONAL],
                       {0.1, ITL_DIAGONAL}):
        label = "ITL diagonal" if length == ITL_DIAGONAL else f"{length:g}"
        track = {"length": length}
        if length == ITL_DIAGONAL:
            track["angle"] = ITL_DIAGONAL_ANGLE
        cells.append(render("length (px)", label, track=track, brute=0 < length <= 3,
                            cost=20 if length == ITL_DIAGONAL else 1))
    # Short tracks along the pixel axes and the diagonal.
    for angle in (0.0, 45.0):
        for length in pick([0.1, 0.3, 0.5, 1.0], {0.3}):
            cells.append(render("length (px)", f"{length:g} at {angle:g} deg",
                                track={"length": length, "angle": angle}, brute=True))
    # float32 vs float64 images, bright, faint, on a pedestal.
    for dtype in ("float32", "float64"):
        for label, model, pedestal in (("paper", {}, 0.0), ("mag -5", {"mag": -5.0}, 0.0),
                                       ("mag 25", {"mag": 25.0}, 0.0),
                                       ("on 1e4 e- sky", {}, 1e4)):
            if quick and label not in ("paper",):
                continue
            cells.append(render("image dtype", f"{dtype} {label}", model, dtype=dtype,
                                pedestal=pedestal))
    # Two axes at a time, at their extremes.
    combos = [("160 km, 100 m, z 0", {"height": 160.0, "zenith": 0.0,
                                      "shape": paper_box(100.0)}, 25, False),
              ("GEO, 1 cm", {"height": 36000.0, "shape": paper_box(0.01)}, 1, True),
              ("160 km, z 0", {"height": 160.0, "zenith": 0.0}, 1, True),
              ("GEO, z 0", {"height": 36000.0, "zenith": 0.0}, 1, True),
              ("160 km, z 89.9", {"height": 160.0, "zenith": 89.9}, 1, True),
              ("GEO, z 89.9", {"height": 36000.0, "zenith": 89.9}, 1, True),
              ("GEO, seeing 0.3, z 0", {"height": 36000.0, "zenith": 0.0, "seeing": 0.3},
               1, True),
              ("160 km, seeing 3", {"height": 160.0, "seeing": 3.0}, 8, True),
              ("100 m, z 89.9", {"zenith": 89.9, "shape": paper_box(100.0)}, 2, True),
              ("disk 1 m, 350 km, z 0", {"height": 350.0, "zenith": 0.0,
                                          "shape": ("disk", 1.0)}, 1, True)]
    for label, model, cost, brute in combos:
        if quick and label not in ("GEO, seeing 0.3, z 0", "160 km, z 0"):
            continue
        cells.append(render("two axes", label, model, brute=brute, cost=cost))
    # Exact reference: Gaussians (the narrowest physical streak is ~1.6 px: GEO, 0.3").
    for fwhm in pick([1.5, 2.0, 3.0, 5.0], {1.5}):
        cells.append({"axis": "exact Gaussian (FWHM px)", "label": f"{fwhm:g}", "kind": "gauss",
                      "cost": 2, "params": {"fwhm_px": fwhm}})
    # Edges and corners of a 64 x 48 image.
    wide = PAPER | {"zenith": 0.0, "shape": ("box", 1.0, 100.0)}  # 100 m across the motion
    edges = [
        ("start at corner", {"mode": "segment", "x0": -0.5, "y0": -0.5, "angle": 30.0,
                             "length": 40.0}),
        ("end at corner", {"mode": "segment", "x0": 63.5 - 40 * math.cos(math.radians(30)),
                           "y0": 47.5 - 40 * math.sin(math.radians(30)), "angle": 30.0,
                           "length": 40.0}),
        ("on bottom edge", {"mode": "segment", "x0": 5.0, "y0": -0.5, "angle": 0.0,
                            "length": 50.0}),
        ("on top edge", {"mode": "segment", "x0": 5.0, "y0": 47.5, "angle": 0.0,
                         "length": 50.0}),
        ("on left edge", {"mode": "segment", "x0": -0.5, "y0": 3.0, "angle": 90.0,
                          "length": 40.0}),
        ("outside, wings in", {"mode": "segment", "x0": 5.0, "y0": -8.5, "angle": 0.0,
                               "length": 50.0}),
        ("outside, beyond support", {"mode": "segment", "x0": 5.0, "y0": -600.0,
                                     "angle": 0.0, "length": 50.0, "expect_zero": True}),
        ("corner pixel, leaving", {"mode": "segment", "x0": 0.0, "y0": 0.0, "angle": 225.0,
                                   "length": 10.0}),
        ("line corner to corner", {"mode": "line", "x0": -0.5, "y0": -0.5,
                                   "angle": math.degrees(math.atan2(48, 64))}),
        ("line touching a corner", {"mode": "line", "x0": -0.5, "y0": -0.5, "angle": 135.0}),
        ("line on bottom edge", {"mode": "line", "x0": 0.0, "y0": -0.5, "angle": 0.0}),
        ("line on right edge", {"mode": "line", "x0": 63.5, "y0": 0.0, "angle": 90.0}),
        ("line 1e-9 off a row", {"mode": "line", "x0": 0.0, "y0": 20.0, "angle": 1e-9}),
        ("line outside by 40 px", {"mode": "line", "x0": 0.0, "y0": -40.5, "angle": 0.0}),
        ("wide box, line outside by 40 px", {"mode": "line", "x0": 0.0, "y0": -40.5,
                                             "angle": 0.0, "model": wide}),
        ("wide box, line outside by cap+5 px", {"mode": "line", "x0": 0.0, "y0": None,
                                                "angle": 0.0, "model": wide}),
    ]
    for label, params in edges:
        if quick and label not in ("start at corner", "line corner to corner",
                                   "wide box, line outside by cap+5 px"):
            continue
        params = {"model": PAPER} | params
        cells.append({"axis": "edges and corners", "label": label, "kind": "edge", "cost": 1,
                      "params": params})
    # Branch points.
    continuity = [
        ("zenith 0 vs 1e-9", {"kind": "zenith0"}),
        ("angle 45 -/+ 1e-9", {"kind": "angle", "a": {"angle": 45 - e},
                               "b": {"angle": 45 + e}}),
        ("angle 0 vs 1e-9", {"kind": "angle", "a": {"angle": 0.0}, "b": {"angle": e}}),
        ("angle -1e-9 vs 0", {"kind": "angle", "a": {"angle": -e}, "b": {"angle": 0.0}}),
        ("angle 90 vs 90+1e-9", {"kind": "angle", "a": {"angle": 90.0},
                                "b": {"angle": 90 + e}}),
        ("pixel edge y0 0.5 -/+ 1e-9", {"kind": "offset", "a": {"fy": 0.5 - e},
                                        "b": {"fy": 0.5 + e}}),
        ("length 0 vs 1e-9", {"kind": "length", "a": {"length": 0.0}, "b": {"length": e}}),
        ("shape skip (size)", {"kind": "shape_drop", "axis": "size", "bracket": (0.01, 1.0)}),
        ("shape skip (height, 1 m box)", {"kind": "shape_drop", "axis": "height",
                                          "bracket": (1000.0, 36000.0),
                                          "base": {"shape": paper_box(1.0), "zenith": 0.0}}),
        ("defocus skip (pupil radius)", {"kind": "defocus_drop"}),
        ("noise tightening", {"kind": "noise_tightening"}),
    ]
    for label, params in continuity:
        if quick and label not in ("zenith 0 vs 1e-9", "angle 45 -/+ 1e-9",
                                   "shape skip (size)", "defocus skip (pupil radius)"):
            continue
        cells.append({"axis": "continuity", "label": label, "kind": "continuity", "cost": 2,
                      "params": params})
    # Magnitudes on a noisy scene cut-out.
    for mag in pick([-5.0, 0.0, 5.0, 10.0, 15.0, 20.0, 25.0], {-5.0, 25.0}):
        cells.append({"axis": "magnitude (scene)", "label": f"{mag:g} itl", "kind": "scene",
                      "cost": 2, "params": {"mag": mag, "detector": "itl"}})
    if not quick:
        for mag in (-5.0, 25.0):
            cells.append({"axis": "magnitude (scene)", "label": f"{mag:g} e2v", "kind": "scene",
                          "cost": 2, "params": {"mag": mag, "detector": "e2v"}})
    return cells


def resolve(cells):
    """Fill values that need a render plan (the cap of the wide box) before running."""
    from inject.render import swept_profile

    for cell in cells:
        p = cell["params"]
        if cell["kind"] == "edge" and p.get("y0") is None:
            cap = swept_profile(make_model(p["model"]), p["angle"]).plan.cap_px
            p["y0"] = -0.5 - cap - 5.0
            cell["label"] = f"wide box, line outside by cap+5 = {cap + 5:.1f} px"
    return cells


# ---------------------------------------------------------------------------------------------
# Report


def worst(results, name, field="value"):
    values = [c[field] for r in results for c in r["checks"] if c["check"] == name
              and field in c]
    return max(values) if values else None


def table(results):
    axes = []
    for r in results:
        if r["axis"] not in axes:
            axes.append(r["axis"])
    lines = ["| axis | values tried | cells | pass | worst flux \\|ΔF\\|/F | worst vs reference "
             "(/ track's peak) | worst other check (value / limit) |",
             "|---|---|---:|---|---:|---:|---|"]
    for axis in axes:
        rows = [r for r in results if r["axis"] == axis]
        labels = "; ".join(r["label"] for r in rows)
        passed = sum(r["ok"] for r in rows)
        flux = worst(rows, "flux")
        ref = max([v for v in (worst(rows, "reference"), worst(rows, "exact")) if v is not None],
                  default=None)
        other, other_name = None, ""
        for r in rows:
            for c in r["checks"]:
                if c["check"] in ("flux", "reference", "exact", "finite") or c["limit"] == 0:
                    continue
                ratio = c["value"] / c["limit"]
                if other is None or ratio > other[0]:
                    other = (ratio, c)
        if other is not None:
            c = other[1]
            other_name = f"{c['check']} {c['value']:.2g} / {c['limit']:.0e}"
        zero_limit = [c for r in rows for c in r["checks"] if c["limit"] == 0 and not c["ok"]]
        if zero_limit:
            other_name += "; " + ", ".join(sorted({c["check"] for c in zero_limit})) + " FAILED"
        errors = [r for r in rows if r["error"]]
        if errors:
            other_name += f"; {len(errors)} crashed"
        status = "PASS" if passed == len(rows) else f"FAIL ({len(rows) - passed})"
        lines.append(f"| {axis} | {labels} | {len(rows)} | {status} | "
                     f"{'' if flux is None else f'{flux:.2e}'} | "
                     f"{'' if ref is None else f'{ref:.2e}'} | {other_name} |")
    return "\n".join(lines)


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = []
    for r in results:
        if r["axis"] not in axes:
            axes.append(r["axis"])
    ncol = 3
    nrow = math.ceil(len(axes) / ncol)
    fig, grid_axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, 3.4 * nrow), squeeze=False)
    for ax, axis in zip(grid_axes.ravel(), axes):
        rows = [r for r in results if r["axis"] == axis]
        for i, r in enumerate(rows):
            for c in r["checks"]:
                if c["limit"] == 0:
                    ratio = 1e-12 if c["ok"] else 10.0
                else:
                    ratio = max(c["value"] / c["limit"], 1e-12)
                ratio = min(ratio, 30.0)  # off-scale failures are drawn at the top
                ax.scatter(i, ratio, s=14, color="C3" if not c["ok"] else "C0",
                           marker={"flux": "o", "reference": "s", "exact": "s",
                                   "continuity": "^", "clip": "D"}.get(c["check"], "."))
            if r["error"]:
                ax.scatter(i, 10.0, s=40, color="C3", marker="x")
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_ylim(1e-12, 1e2)
        ax.set_xticks(range(len(rows)))
        ax.set_xticklabels([r["label"] for r in rows], rotation=60, ha="right", fontsize=6)
        ax.set_title(axis, fontsize=9)
        ax.set_ylabel("value / limit", fontsize=7)
    for ax in grid_axes.ravel()[len(axes):]:
        ax.axis("off")
    fig.suptitle("inject stress grid: every check's value over its limit (red: failed; "
                 "o flux, s reference, ^ continuity, D clipping)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="out/stress", help="output directory (out/stress)")
    parser.add_argument("--quick", action="store_true", help="a small grid (~1 min)")
    parser.add_argument("--workers", type=int, default=2, help="processes (2)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    cells = resolve(grid(args.quick))
    order = sorted(range(len(cells)), key=lambda i: -cells[i]["cost"])
    results = [None] * len(cells)
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as pool:
            futures = {pool.submit(run_cell, cells[i]): i for i in order}
            for done, future in enumerate(as_completed(futures), 1):
                i = futures[future]
                results[i] = future.result()
                _progress(done, len(cells), results[i])
    else:
        for done, i in enumerate(order, 1):
            results[i] = run_cell(cells[i])
            _progress(done, len(cells), results[i])
    elapsed = time.perf_counter() - start
    md = table(results)
    failed = [r for r in results if not r["ok"]]
    command = "python scripts/stress.py" + (" --quick" if args.quick else "")
    header = (f"Stress grid: {len(results)} cells, {len(results) - len(failed)} passed, "
              f"{len(failed)} failed; {elapsed:.0f} s with {args.workers} worker(s). "
              f"Made by `{command}`.")
    with open(os.path.join(args.out, "stress.md"), "w") as f:
        f.write(header + "\n\n" + md + "\n")
    with open(os.path.join(args.out, "stress.json"), "w") as f:
        json.dump({"cells": results, "seconds": elapsed, "quick": args.quick,
                   "workers": args.workers, "limits": {"flux": FLUX_LIMIT,
                                                       "reference": REF_LIMIT,
                                                       "exact": EXACT_LIMIT}},
                  f, indent=1, default=_json_default)
    plot(results, os.path.join(args.out, "stress.png"))
    print()
    print(header)
    print()
    print(md)
    for r in failed:
        bad = [c for c in r["checks"] if not c["ok"]]
        print(f"\nFAILED {r['axis']} / {r['label']}: "
              + "; ".join(f"{c['check']} = {c['value']:.3g} > {c['limit']:.3g}" for c in bad)
              + (f" {r['error'].splitlines()[0]}" if r["error"] else ""))
    print(f"\nwrote {args.out}/stress.md, stress.json, stress.png")
    return 1 if failed else 0


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple):
        return list(value)
    raise TypeError(type(value).__name__)


def _progress(done, total, result):
    status = "ok" if result["ok"] else "FAIL"
    print(f"[{done:3d}/{total}] {status:4s} {result['seconds']:6.1f} s  {result['axis']} / "
          f"{result['label']}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
