r"""Mutation check of the newer code: the focal plane, the passes, the noise, the runner, the
readers, the survey and the optics. Would the default tests notice a realistic single bug?

Each mutation is one textual change (a constant of the wrong vendor, a random stream keyed on
too little, a dropped term, an inverted guard) in one function that sets something users rely
on. For each, the repository is copied (without its venv and git data) to a temporary
directory, the change applied to the copy, and the default tests of that part run there
(``-x``: the first failure is enough) with the copy first on ``PYTHONPATH``; the working tree
is never modified. A mutation is *caught* if those tests fail. The unmutated copy is run first
on the union of the test files (they must pass, or "caught" would mean nothing).

The same bugs can be made in the code before the package moved into folders (the flat
modules: ``focalplane``, ``focalscene``, ``orbits``, ``parallel``, ``wcs``): each mutation
carries its text for both layouts, and ``--root`` points at another checkout, e.g. a git
worktree of an older commit, to measure what its own tests caught. Test files that a
checkout does not have are left out (the run says which); with ``--new`` the test files
added by issue 19 run for every mutation too (``tests/test_independent_checks.py``,
``tests/test_reliability*.py``, ``tests/test_runner_reliability*.py``).

The areas ``survey`` (``inject/survey/``, ``inject/cli/survey.py``) and ``optics``
(``inject/optics.py``) exist only in the package in folders. Their tests are globs
(``tests/test_survey*.py``; ``tests/test_optics*.py``, ``tests/test_pupil*.py``), so the test
files written for them later are run without changing this list.

Usage::

    python scripts/mutation_check_pipeline.py [--root DIR] [--area AREA ...] [--only NAME ...]
        [--list] [--check] [--new] [--every] [--tests FILE ...] [--add-tests GLOB ...]
        [--jobs N] [--markdown FILE] [--label TEXT]

The tables of docs/explanation/testing.md come from::

    AREAS=("focal plane" passes noise runner readers)
    git worktree add /tmp/before 1cf9c16   # the code before issue 19's session
    git worktree add /tmp/after c86fddb    # the code with issue 19's tests
    python scripts/mutation_check_pipeline.py --root /tmp/before --area "${AREAS[@]}" \
        --markdown before.md
    python scripts/mutation_check_pipeline.py --root /tmp/after --area "${AREAS[@]}" --new \
        --markdown after.md

and, for the survey and the optics (a checkout of f730894 before their audit's tests, and one
after)::

    python scripts/mutation_check_pipeline.py --root /tmp/before --area survey optics \
        --label "commit f730894" --markdown before.md
    python scripts/mutation_check_pipeline.py --root /tmp/after --area survey optics \
        --markdown after.md

``--every`` drops ``-x`` and lists every test file that fails (several times slower).

``--check`` only verifies that every patch applies (exactly once) to the checkout. Exit status
1 if a mutation is missed or a patch no longer applies (the code moved: update the list).
"""
import argparse
import glob
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from mutation_check import (  # this folder's: the same pytest run in a copy
    baseline_passes,
    run_tests,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
IGNORE = shutil.ignore_patterns(".venv", ".git", "out", "__pycache__", "*.egg-info",
                                ".hypothesis", ".pytest_cache", "site")


@dataclass(frozen=True)
class Patch:
    path: str  # relative to the repository
    old: str   # must occur exactly once
    new: str


@dataclass(frozen=True)
class Mutation:
    name: str
    area: str
    folders: Patch        # the package in folders (camera/, orbits/, exposure/, io/)
    flat: Patch | None    # the flat package before it, None if the code was not there
    tests: tuple          # groups of test files (TESTS) that must catch it
    audit: bool = False   # one of the bugs issue 19's audit (the survey's and the optics':
    #                       the earlier audit of those wings) found the tests missed


TESTS = {
    "layout": ("tests/test_focalplane.py", "tests/test_focalplane_scene.py",
               "tests/test_mosaic_scale.py"),
    "focal": ("tests/test_focalplane_scene.py", "tests/test_focalplane.py",
              "tests/test_satellites_record.py", "tests/test_pass_truth.py"),
    "stars": ("tests/test_stars.py", "tests/test_focalplane_scene.py", "tests/test_sky_stars.py"),
    "noise": ("tests/test_noise_split.py", "tests/test_stars.py", "tests/test_scene.py",
              "tests/test_simulate.py", "tests/test_cutout_noise.py"),
    "passes": ("tests/test_orbits.py", "tests/test_pass_truth.py", "tests/test_pass_cli.py"),
    "runner": ("tests/test_focalplane_run.py", "tests/test_stale_temporaries.py",
               "tests/test_satellites_record.py"),
    "reader": ("tests/test_add_streak.py", "tests/test_lsst_files.py"),
    # Globs: the test files added for these wings later are run too. The quick files of
    # independent numbers first (a bug they catch costs seconds, not the skyfield night's).
    "survey": ("tests/test_survey_independent*.py", "tests/test_survey_trust*.py",
               "tests/test_survey.py", "tests/test_survey*.py"),
    "optics": ("tests/test_optics*.py", "tests/test_pupil*.py", "tests/test_rotator*.py",
               "tests/test_sed*.py"),
}
#: Test files issue 19 added (``--new``): run for every mutation.
NEW_TESTS = ("tests/test_independent_checks*.py", "tests/test_reliability*.py",
             "tests/test_runner_reliability*.py")

_TILE = 'gen = rng(scene.seed, "stars", STAR_TILE_KEY + j * _TILE_GRID + i)'
_PENDING = "        for c in todo:\n            rows[c.name] = {"
_BLANK_FLAT = "            if blank is not None:\n                sel &= stored != blank"

MUTATIONS = [
    # --- the focal plane: layout, WCS, plan, CCDs, star tiles --------------------------
    Mutation("ITL reference pixel replaced by e2v's", "focal plane",
             Patch("inject/camera/layout.py", '"itl": (2036.5, 2000.5)}',
                   '"itl": (2047.5, 2001.5)}'),
             Patch("inject/focalplane.py", '"itl": (2036.5, 2000.5)}',
                   '"itl": (2047.5, 2001.5)}'), ("layout",), audit=True),
    Mutation("raft rows and columns swapped", "focal plane",
             Patch("inject/camera/layout.py", "centre = (RAFT_PITCH_MM * (rj - 2)",
                   "centre = (RAFT_PITCH_MM * (ri - 2)"),
             Patch("inject/focalplane.py", "centre = (RAFT_PITCH_MM * (rj - 2)",
                   "centre = (RAFT_PITCH_MM * (ri - 2)"), ("layout",)),
    Mutation("distortion with the wrong sign", "focal plane",
             Patch("inject/camera/layout.py", "factor = (1.0 - DISTORTION_R3 * r2",
                   "factor = (1.0 + DISTORTION_R3 * r2"),
             Patch("inject/focalplane.py", "factor = (1.0 - DISTORTION_R3 * r2",
                   "factor = (1.0 + DISTORTION_R3 * r2"), ("layout",)),
    Mutation("radial plate scale is the tangential one", "focal plane",
             Patch("inject/camera/layout.py",
                   "return (s * (1 - 3 * DISTORTION_R3 * r2 - 5 * DISTORTION_R5 * r2 * r2),",
                   "return (s * (1 - DISTORTION_R3 * r2 - DISTORTION_R5 * r2 * r2),"),
             Patch("inject/focalplane.py",
                   "return (s * (1 - 3 * DISTORTION_R3 * r2 - 5 * DISTORTION_R5 * r2 * r2),",
                   "return (s * (1 - DISTORTION_R3 * r2 - DISTORTION_R5 * r2 * r2),"),
             ("layout", "focal")),
    Mutation("rotator turns the sky the other way", "focal plane",
             Patch("inject/camera/wcs.py", "return np.array([[-c, s], [s, c]])",
                   "return np.array([[-c, -s], [-s, c]])"),
             Patch("inject/focalplane.py", "return np.array([[-c, s], [s, c]])",
                   "return np.array([[-c, -s], [-s, c]])"), ("layout", "passes")),
    Mutation("SIP forward terms with the wrong sign", "focal plane",
             Patch("inject/camera/wcs.py", "((a, (-DISTORTION_R3, -DISTORTION_R5)),",
                   "((a, (DISTORTION_R3, DISTORTION_R5)),"),
             Patch("inject/focalplane.py", "((a, (-DISTORTION_R3, -DISTORTION_R5)),",
                   "((a, (DISTORTION_R3, DISTORTION_R5)),"), ("layout",)),
    Mutation("cut-out sides swapped", "focal plane",
             Patch("inject/exposure/plan.py",
                   "return (min(ny, fscene.cutout[0]), min(nx, fscene.cutout[1]))",
                   "return (min(ny, fscene.cutout[1]), min(nx, fscene.cutout[0]))"),
             Patch("inject/focalscene.py",
                   "return (min(ny, fscene.cutout[0]), min(nx, fscene.cutout[1]))",
                   "return (min(ny, fscene.cutout[1]), min(nx, fscene.cutout[0]))"),
             ("focal", "runner")),
    Mutation("every star tile draws from one stream", "focal plane",
             Patch("inject/skytiles.py", "spawn_key=(SKY_TILE_KEY, j, i)",
                   "spawn_key=(SKY_TILE_KEY,)"),
             Patch("inject/focalscene.py", _TILE,
                   'gen = rng(scene.seed, "stars", STAR_TILE_KEY)'), ("stars",), audit=True),
    Mutation("halo tiles chosen by the core stamp", "focal plane",
             Patch("inject/stars.py", "sky, image.shape, stamps.bright_half + 1,",
                   "sky, image.shape, stamps.core_half + 1,"),
             Patch("inject/focalscene.py", "box = ccd.bounds_mm(stamps.bright_half + 1,",
                   "box = ccd.bounds_mm(stamps.core_half + 1,"), ("stars",), audit=True),
    Mutation("every CCD draws the noise of detector 0", "focal plane",
             Patch("inject/exposure/ccd.py", "detector_index=ccd.id, wcs=wcs",
                   "detector_index=0, wcs=wcs"),
             Patch("inject/focalscene.py", "detector_index=ccd.id, wcs=wcs",
                   "detector_index=0, wcs=wcs"), ("focal", "noise", "runner")),
    # --- the passes -------------------------------------------------------------------------
    Mutation("Earth's rotation over the light time left out", "passes",
             Patch("inject/orbits/passes.py", "_rot_z(EARTH_ROTATION_RAD_S * tau) @ m, r_ret_teme",
                   "m, r_ret_teme"),
             Patch("inject/orbits.py", "_rot_z(EARTH_ROTATION_RAD_S * tau) @ m, r_ret_teme",
                   "m, r_ret_teme"), ("passes",), audit=True),
    Mutation("light time added instead of taken", "passes",
             Patch("inject/orbits/passes.py", "jd2 - tau / 86400.0", "jd2 + tau / 86400.0"),
             Patch("inject/orbits.py", "jd2 - tau / 86400.0", "jd2 + tau / 86400.0"),
             ("passes",)),
    Mutation("differential aberration left out", "passes",
             Patch("inject/orbits/passes.py", "if self.to_icrs is not None:", "if False:"),
             Patch("inject/orbits.py", "if self.to_icrs is not None:", "if False:"),
             ("passes",)),
    Mutation("tracking term left out of the angular speed", "passes",
             Patch("inject/orbits/passes.py", "v_rel = v_in - np.cross(omega, obs)",
                   "v_rel = v_in"),
             Patch("inject/orbits.py", "v_rel = v_in - np.cross(omega, obs)", "v_rel = v_in"),
             ("passes",)),
    Mutation("focal-plane track rotated the other way", "passes",
             Patch("inject/orbits/passes.py",
                   "x, y = tangent_to_focal(xi, eta, self.pointing.rotation_deg)",
                   "x, y = tangent_to_focal(xi, eta, -self.pointing.rotation_deg)"),
             Patch("inject/orbits.py",
                   "x, y = sky_to_focal(xi, eta, self.pointing.rotation_deg)",
                   "x, y = sky_to_focal(xi, eta, -self.pointing.rotation_deg)"),
             ("passes",)),
    Mutation("penumbra brightens the streak", "passes",
             Patch("inject/orbits/tracks.py", '"mag": float(m + d)', '"mag": float(m - d)'),
             Patch("inject/focalscene.py", '"mag": float(m + d)', '"mag": float(m - d)'),
             ("passes", "focal")),
    Mutation("CCD-scene orbit vertices half a pixel off", "passes",
             Patch("inject/orbits/tracks.py", "x = (nx - 1) / 2 + dense.field_x_deg[run]",
                   "x = nx / 2 + dense.field_x_deg[run]"),
             Patch("inject/focalscene.py", "x = (nx - 1) / 2 + dense.field_x_deg[run]",
                   "x = nx / 2 + dense.field_x_deg[run]"), ("passes",), audit=True),
    # --- the noise ----------------------------------------------------------------------------
    Mutation("star photons not keyed on the detector", "noise",
             Patch("inject/scene.py",
                   "spawn_key=(self.detector_index, STREAMS[purpose], *block.key)",
                   'spawn_key=(self.detector_index * (purpose != "signal_noise"), '
                   "STREAMS[purpose], *block.key)"),
             Patch("inject/scene.py", 'noise=rng(scene.seed, "star_noise", detector_index)',
                   'noise=rng(scene.seed, "star_noise")'), ("noise",), audit=True),
    Mutation("ADU variance over the gain, not its square", "noise",
             Patch("inject/scene.py", "variance / gain ** 2", "variance / gain"),
             Patch("inject/scene.py", "variance / gain ** 2", "variance / gain"),
             ("noise",), audit=True),
    Mutation("variance without the read noise", "noise",
             Patch("inject/scene.py", "var[...] = np.float32(level + block.read_noise ** 2)",
                   "var[...] = np.float32(level)"),
             Patch("inject/scene.py", "var[...] = np.float32(level + sigma ** 2)",
                   "var[...] = np.float32(level)"), ("noise",)),
    Mutation("streak charge left out of the variance", "noise",
             Patch("inject/scene.py", "np.add(var[r:r + n], np.maximum(mean, 0.0, "
                   "out=scratch[:n]), out=var[r:r + n],",
                   "np.add(var[r:r + n], 0.0, out=var[r:r + n],"),
             Patch("inject/scene.py", "var[chunk][where] += mean.astype(np.float32)", "pass"),
             ("noise",)),
    Mutation("every amplifier (noise block) draws the same noise", "noise",
             Patch("inject/scene.py",
                   "spawn_key=(self.detector_index, STREAMS[purpose], *block.key)",
                   "spawn_key=(self.detector_index, STREAMS[purpose])"),
             Patch("inject/scene.py", "for s in root.spawn(len(self.blocks))]",
                   "for s in [root] * len(self.blocks)]"), ("noise",)),
    Mutation("Poisson table cut at 2 sigma", "noise",
             Patch("inject/scene.py", "np.floor(mean + 40 * np.sqrt(mean) + 40)",
                   "np.floor(mean + 2 * np.sqrt(mean) + 2)"),
             Patch("inject/scene.py", "kmax = int(mean + 40 * np.sqrt(mean) + 40)",
                   "kmax = int(mean + 2 * np.sqrt(mean) + 2)"), ("noise",)),
    Mutation("stars' charge left out of the variance", "noise",
             Patch("inject/stars.py", "variance[region] += expected",
                   "variance[region] += 0.0"),
             Patch("inject/stars.py", "variance[region] += expected",
                   "variance[region] += 0.0"), ("noise",)),
    # --- the runner and its manifest ---------------------------------------------------------
    Mutation("manifest digest without the resolved tracks", "runner",
             Patch("inject/exposure/scene.py", '"tracks": [\n', '"tracks": [] and [\n'),
             Patch("inject/focalscene.py", '"tracks": [\n', '"tracks": [] and [\n'),
             ("runner", "focal"), audit=True),
    Mutation("no pending rows: a run killed before its first row", "runner",
             Patch("inject/exposure/runner.py", _PENDING,
                   _PENDING.replace("in todo", "in ()")),
             Patch("inject/parallel.py", _PENDING, _PENDING.replace("in todo", "in ()")),
             ("runner",), audit=True),
    Mutation("stray file replaced without --overwrite", "runner",
             Patch("inject/exposure/runner.py", "        elif overwrite:\n            todo.append",
                   "        elif True:\n            todo.append"),
             Patch("inject/parallel.py", "if row is None and ours:", "if row is None:"),
             ("runner",), audit=True),
    Mutation("done without checking the file's digest", "runner",
             Patch("inject/exposure/runner.py",
                   'if row.get("status") == "done" and row.get("sha256") == sha256_file(path):',
                   'if row.get("status") == "done":'),
             Patch("inject/parallel.py",
                   'if row.get("status") == "done" and row.get("sha256") == sha256_file(path):',
                   'if row.get("status") == "done":'), ("runner",)),
    Mutation("another scene's files replaced without --overwrite", "runner",
             Patch("inject/exposure/runner.py", "if others and not overwrite:", "if False:"),
             Patch("inject/parallel.py",
                   'if row is not None and row.get("scene_sha256") == fscene.digest:',
                   "if row is not None:"), ("runner",)),
    Mutation("stale temporaries left in place", "runner",
             Patch("inject/exposure/runner.py", "stale = remove_stale_temporaries(outdir)",
                   "stale = []"),
             Patch("inject/parallel.py", "stale = remove_stale_temporaries(outdir)",
                   "stale = []"), ("runner",)),
    Mutation("job slices contiguous, not interleaved", "runner",
             Patch("inject/exposure/runner.py", "return tuple(ccds)[job::njobs]",
                   "return tuple(ccds)[job * len(ccds) // njobs:"
                   "(job + 1) * len(ccds) // njobs]"),
             Patch("inject/parallel.py", "return tuple(ccds)[job::njobs]",
                   "return tuple(ccds)[job * len(ccds) // njobs:"
                   "(job + 1) * len(ccds) // njobs]"), ("runner",)),
    # --- the readers ----------------------------------------------------------------------------
    Mutation("BLANK pixels overwritten by add-streak", "readers",
             Patch("inject/io/reader.py",
                   "sel = np.isfinite(delta) & (delta != 0) & self.defined(index)",
                   "sel = np.isfinite(delta) & (delta != 0)"),
             Patch("inject/io/reader.py", _BLANK_FLAT,
                   "            if blank is not None:\n                pass"),
             ("reader",), audit=True),
    Mutation("integer pixels truncated, not rounded", "readers",
             Patch("inject/io/reader.py", "values = np.clip(np.rint((physical - bzero) / bscale),",
                   "values = np.clip(np.trunc((physical - bzero) / bscale),"),
             Patch("inject/io/reader.py", "values = np.clip(np.rint((physical - bzero) / bscale),",
                   "values = np.clip(np.trunc((physical - bzero) / bscale),"), ("reader",)),
    Mutation("BZERO left out when adding", "readers",
             Patch("inject/io/reader.py",
                   "physical = stored[sel].astype(np.float64) * bscale + bzero + delta[sel]",
                   "physical = stored[sel].astype(np.float64) * bscale + delta[sel]"),
             Patch("inject/io/reader.py",
                   "physical = stored[sel].astype(np.float64) * bscale + bzero + delta[sel]",
                   "physical = stored[sel].astype(np.float64) * bscale + delta[sel]"),
             ("reader",)),
    Mutation("LTV origin with the wrong sign", "readers",
             Patch("inject/io/reader.py",
                   'return (-int(round(header["LTV1"])), -int(round(header["LTV2"])))',
                   'return (int(round(header["LTV1"])), int(round(header["LTV2"])))'),
             Patch("inject/io/reader.py",
                   'return (-int(round(header["LTV1"])), -int(round(header["LTV2"])))',
                   'return (int(round(header["LTV1"])), int(round(header["LTV2"])))'),
             ("reader",)),
    Mutation("add-streak variance over the gain, not its square", "readers",
             Patch("inject/addstreak.py", "model_e / gain ** 2)", "model_e / gain)"),
             Patch("inject/addstreak.py", "model_e / gain ** 2)", "model_e / gain)"),
             ("reader",)),
]


# --- the survey and the optics -------------------------------------------------------------
# These bugs exist only in the package in folders (``flat`` is None). Their tests are picked
# by globs (TESTS["survey"], TESTS["optics"]), so test files added later are run too. The
# anchors are formulas and constants (``--check`` says when one no longer applies).

def _survey(name, area, path, old, new, audit=False):
    """A mutation of the survey or the optics: one patch, the area's own test group."""
    return Mutation(name, area, Patch(path, old, new), None, (area,), audit)


_PLAN = "inject/survey/plan.py"
_VISITS = "inject/survey/visits.py"
_PRE = "inject/survey/prefilter.py"
_CONST = "inject/survey/constellation.py"
_RENDER = "inject/survey/render.py"
_COMPARE = "inject/survey/compare.py"
_CLI = "inject/cli/survey.py"
_OPTICS = "inject/optics.py"
_NIGHTS = "inject/survey/nights.py"
_STREAM = "inject/survey/stream.py"
_RULE = "inject/survey/rubin_rule.py"
_FIXED = "inject/survey/fixed_mask.py"

SURVEY_MUTATIONS = [
    # --- what the earlier audit found missed --------------------------------------------------
    _survey("summary's total pixel fraction over one visit's pixels", "survey", _STREAM,
            '"pixel_fraction_lost_total": float(lost.sum() / (n * total_pixels)) if n else None,',
            '"pixel_fraction_lost_total": float(lost.sum() / total_pixels) if n else None,',
            audit=True),
    _survey("sky dimmed instead of brightened with airmass", "survey", _PLAN,
            "sky /= math.sin(math.radians(max(alt_deg, 1.0)))",
            "sky *= math.sin(math.radians(max(alt_deg, 1.0)))", audit=True),
    _survey("read noise counted once per visit, not per snap", "survey", _PLAN,
            "return math.sqrt(sky + visit.n_exposures * read ** 2), float(sky)",
            "return math.sqrt(sky + read ** 2), float(sky)", audit=True),
    _survey("rendered CCDs' time from TAI read as UTC (37 s late)", "survey", _RENDER,
            '"noise": True, "time": visit.start.utc.isot,',
            '"noise": True, "time": visit.start.tai.isot,', audit=True),
    _survey("plots' local-hour axis with the longitude's sign flipped", "survey", _CLI,
            'plot_data = {"hours": local_hours(visits["mjd"], RUBIN.lon_deg),',
            'plot_data = {"hours": local_hours(visits["mjd"], -RUBIN.lon_deg),',
            audit=True),
    _survey("cut-out box's row clipping off by one", "survey", _COMPARE,
            "keep = (rows >= y0) & (rows < y0 + ny)",
            "keep = (rows >= y0) & (rows <= y0 + ny)", audit=True),
    # --- visits ---------------------------------------------------------------------------------
    _survey("snaps' readout gap ignored", "survey", _VISITS,
            "return tuple(((each + READOUT_S) * k, each) for k in range(n))",
            "return tuple((each * k, each) for k in range(n))"),
    _survey("visitExposureTime taken as each snap's", "survey", _VISITS,
            "each = self.exptime_s / n", "each = self.exptime_s"),
    _survey("physical filter name (r_57) not read as its band", "survey", _VISITS,
            "        band = band[0]\n", "        band = band\n"),
    _survey("rotSkyPos read with the opposite sign", "survey", _VISITS,
            'rotation = get("rotSkyPos") % 360.0',
            'rotation = -get("rotSkyPos") % 360.0'),
    _survey("local solar time with the longitude's sign flipped", "survey", _VISITS,
            "local = (np.asarray(mjd, float) + site_lon_deg / 360.0) % 1.0 * 24.0",
            "local = (np.asarray(mjd, float) - site_lon_deg / 360.0) % 1.0 * 24.0"),
    # --- the plan: sky, seeing, masks, pixels ------------------------------------------------
    _survey("sky over one snap's time, not the visit's", "survey", _PLAN,
            "sky = sky_per_pixel(visit.band, visit.exptime_s, LSST.pixel_scale_arcsec,",
            "sky = sky_per_pixel(visit.band, visit.exptime_s / visit.n_exposures, "
            "LSST.pixel_scale_arcsec,"),
    _survey("streak seeing is FWHMeff, not FWHMgeom", "survey", _PLAN,
            "seeing = visit.seeing_arcsec if visit.seeing_arcsec is not None else DEFAULT_SEEING",
            "seeing = visit.seeing_fwhm_eff if visit.seeing_arcsec is not None "
            "else DEFAULT_SEEING"),
    _survey("mask width with e2v's read noise on ITL CCDs", "survey", _PLAN,
            "sigmas[vendor], plan.sky_e_per_px = sky_sigma(visit, plan.alt_deg, vendor)",
            'sigmas[vendor], plan.sky_e_per_px = sky_sigma(visit, plan.alt_deg, "e2v")'),
    _survey("mask reach left in arcsec, not px", "survey", _PLAN,
            "reach = float(np.max(np.abs(lsf.offset_arcsec[above]))) / scale if above.size",
            "reach = float(np.max(np.abs(lsf.offset_arcsec[above]))) if above.size"),
    _survey("streak model at the start of its crossing, not the middle", "survey", _PLAN,
            "piece, values, n = inside[len(inside) // 2]",
            "piece, values, n = inside[0]"),
    _survey("snap break at 2.5 s: a streak drawn across the readout", "survey", _PLAN,
            "SNAP_BREAK_S = 1.5", "SNAP_BREAK_S = 2.5"),
    _survey("total pixels counted as 189 e2v CCDs", "survey", _PLAN,
            "TOTAL_PIXELS = int(sum(c.shape[0] * c.shape[1] for c in fp.CCDS))",
            "TOTAL_PIXELS = int(len(fp.CCDS) * 4096 * 4004)"),
    _survey("union of row runs counts overlaps twice", "survey", _PLAN,
            "np.maximum(lo[1:], np.maximum.accumulate(hi)[:-1], out=lo[1:])",
            "np.maximum(lo[1:], lo[1:], out=lo[1:])"),
    _survey("visit's pixels summed over its streaks, overlaps twice", "survey", _PLAN,
            "    if shared:\n", "    if False:\n"),
    _survey("CCD gaps (65 px each side) counted as sensitive", "survey", _PLAN,
            "box, k, t0, t1 = clip_path_boxes(xs, ys, _BOUNDS[near])",
            "box, k, t0, t1 = clip_path_boxes(xs, ys, fp.boxes_mm(fp.CCDS, 65.0)[near])"),
    # --- the prefilter ---------------------------------------------------------------------------
    _survey("umbra test with the Sun's side flipped", "survey", _PRE,
            "behind = -(r @ s)", "behind = r @ s"),
    _survey("umbra widening behind the Earth, not narrowing", "survey", _PRE,
            "umbra = R_POLAR_KM - UMBRA_TAPER * behind - UMBRA_SLACK_KM",
            "umbra = R_POLAR_KM + UMBRA_TAPER * behind - UMBRA_SLACK_KM"),
    _survey("prefilter margin halved", "survey", _PRE,
            "return max(2.0 * angle, 0.05)", "return max(angle, 0.05)"),
    _survey("prefilter samples only the first snap", "survey", _PRE,
            "start, duration = v.snaps()[-1]", "start, duration = v.snaps()[0]"),
    _survey("Hermite end-velocity term with the wrong sign", "survey", _PRE,
            "-2 * s3 + 3 * s2, s3 - s2\n", "-2 * s3 + 3 * s2, s2 - s3\n"),
    # --- the constellation and the command ----------------------------------------------------
    _survey("Walker shell with planes and satellites per plane swapped", "survey", _CONST,
            "walker_shell(planes * per_plane, planes, phasing, height,",
            "walker_shell(planes * per_plane, per_plane, phasing, height,"),
    _survey("shell's raan0 ignored", "survey", _CONST,
            'raan0 = number(f"{where}.raan0", spec.get("raan0", 0.0))', "raan0 = 0.0"),
    _survey("OUTDIR claim's key without the visits' content (an edited VISITS is one run)",
            "survey", _CLI, "json.dumps(inputs, sort_keys=True)",
            'json.dumps({k: v for k, v in inputs.items() if k != "visits_sha256"}, '
            'sort_keys=True)'),
    _survey("a night's parts on the workers drop each part's last visit", "survey", _CLI,
            "pieces = [visits[k:k + size] for k in",
            "pieces = [visits[k:k + size - 1] for k in"),
    # --- the survey night by night, the rubin_sim rule and the fixed mask ---------------------
    _survey("night boundary at local midnight, not noon", "survey", _NIGHTS,
            "return math.floor(mjd + lon_deg / 360.0 - 0.5)",
            "return math.floor(mjd + lon_deg / 360.0)"),
    _survey("night's local date with the longitude's sign flipped", "survey", _NIGHTS,
            "return math.floor(mjd + lon_deg / 360.0 - 0.5)",
            "return math.floor(mjd - lon_deg / 360.0 - 0.5)"),
    _survey("Sun-altitude bins: the -18 deg edge at -12", "survey", _NIGHTS,
            "+ (alt < SUN_ALT_BINS[2][2])", "+ (alt < SUN_ALT_BINS[1][2])"),
    _survey("a resumed night trusted with its streaks file changed (first file checked only)",
            "survey", _STREAM, 'for f in entry["files"].values())',
            'for f in list(entry["files"].values())[:1])'),
    _survey("summary read from the last night's files only", "survey", _STREAM,
            "for n in nights]\n    return pa.concat_tables",
            "for n in nights[-1:]]\n    return pa.concat_tables"),
    _survey("by_year keyed on the UTC year of the visit's start, not its night's", "survey",
            _STREAM, 'years = np.asarray(visits["year"], int)',
            'years = np.array([int(t[:4]) for t in __import__("astropy.time").time.Time('
            'visits["mjd"], format="mjd", scale="tai").utc.isot], int)'),
    _survey("sky map's HEALPix pixels in NESTED order, drawn as RING", "survey", _STREAM,
            "lonlat=True)\n    npix", "lonlat=True, nest=True)\n    npix"),
    _survey("fixed mask's median over every visit, not the streaked", "survey", _STREAM,
            "float(np.median(band[streaked]) / TOTAL_PIXELS)",
            "float(np.median(band) / TOTAL_PIXELS)"),
    _survey("a visit's streak length the longest streak's, not their sum", "survey", _PLAN,
            "return float(sum(s.length_deg for s in self.streaks))",
            "return float(max((s.length_deg for s in self.streaks), default=0.0))"),
    _survey("--mask-width in arcsec at DECam's 0.263 arcsec a pixel", "survey", _FIXED,
            'width = value if unit == "px" else value / LSST.pixel_scale_arcsec',
            'width = value if unit == "px" else value / 0.263'),
    _survey("rubin_sim rule: the altitude limit at the start only", "survey", _RULE,
            "(alt[k, [0, -1]] > ALT_LIMIT_DEG).any()", "(alt[k, 0] > ALT_LIMIT_DEG)"),
    _survey("rubin_sim rule: sunlit at the start only", "survey", _RULE,
            "and lit[k].any()):", "and lit[k, 0]):"),
    _survey("rubin_sim rule's prefilter on half the circle (the radius taken as a diameter)",
            "survey", _RULE, "field_radius_deg=RADIUS_DEG)", "field_radius_deg=RADIUS_DEG / 2)"),
    _survey("rubin_sim rule's prefilter reads observationStartMJD as TAI, not UT1", "survey",
            _RULE, 'format="mjd", scale="ut1").tai.mjd', 'format="mjd", scale="tai").tai.mjd'),
    # --- the optics: the traced kernel, its grid and its cache ---------------------------------
    _survey("traced kernel turned the wrong way across the track", "optics", _OPTICS,
            "parts = [self.profile(gsparams).rotate(-float(track_angle_deg) * galsim.degrees)]",
            "parts = [self.profile(gsparams).rotate(float(track_angle_deg) * galsim.degrees)]",
            audit=True),
    _survey("kernel cache file named without its key's digest (band, range, field only)",
            "optics", _OPTICS, 'f"f{key[\'field_angle_deg\']:.3f}{focus}_{digest}.npz")',
            'f"f{key[\'field_angle_deg\']:.3f}{focus}.npz")', audit=True),
    _survey("kernel cache key without the ray count", "optics", _OPTICS,
            "return dict(trace, wavelengths_nm=list(waves),",
            'return dict({k: v for k, v in trace.items() if k != "n_rays"}, '
            "wavelengths_nm=list(waves),"),
    _survey("kernel cache key's field to 0.01 deg (nodes 0.002 apart)", "optics", _OPTICS,
            "return dict(trace, wavelengths_nm=list(waves),",
            'return dict(trace, field_angle_deg=round(trace["field_angle_deg"], 2), '
            "wavelengths_nm=list(waves),"),
    _survey("kernel's range scaling inverted", "optics", _OPTICS,
            "zoom = RANGE_BIN_FACTOR ** range_index / range_km",
            "zoom = range_km / RANGE_BIN_FACTOR ** range_index"),
    _survey("field-node interpolation weight flipped", "optics", _OPTICS,
            "weight = (field - FIELD_NODES_DEG[low]) / (",
            "weight = (FIELD_NODES_DEG[low + 1] - field) / ("),
    _survey("light kept relative to the clear annulus, not the star", "optics", _OPTICS,
            "transmitted = pw.sum() / sw.sum()", "transmitted = pw.sum() / np.sum(weights)"),
    _survey("plate-scale Jacobian over one step, not two", "optics", _OPTICS,
            "columns.append((ends[1] - ends[0]) / (2 * _JACOBIAN_STEP_RAD))",
            "columns.append((ends[1] - ends[0]) / _JACOBIAN_STEP_RAD)"),
    _survey("field position angle measured from y, not x", "optics", _OPTICS,
            "np.array([np.cos(np.radians(pa)), np.sin(np.radians(pa))])",
            "np.array([np.sin(np.radians(pa)), np.cos(np.radians(pa))])"),
    _survey("the vanes turned by the rotator the other way", "optics", _OPTICS,
            "return float((radius - rotator) % 90.0)", "return float((radius + rotator) % 90.0)"),
    _survey("a visit's rotTelPos from paraAngle with rotSkyPos's sign flipped", "optics",
            _VISITS, "return float((parallactic_deg - rot_sky_pos_deg - 90.0 + 180.0) % 360.0",
            "return float((parallactic_deg + rot_sky_pos_deg - 90.0 + 180.0) % 360.0"),
    _survey("the parallactic angle measured to the zenith's opposite", "optics",
            "inject/orbits/passes.py", "alt=horizontal.alt + 10 * u.arcsec",
            "alt=horizontal.alt - 10 * u.arcsec"),
    _survey("the satellite's spectrum not passed to the kernel", "optics", "inject/streak.py",
            "                             self.sed_temperature_k)",
            "                             )"),
    _survey("a colour's temperature from the red band's magnitude twice", "optics", _OPTICS,
            "return float(magnitude(blue) - magnitude(red))",
            "return float(magnitude(red) - magnitude(red))"),
    _survey("the band's photons weighted by the blackbody's energy, not its photons",
            "optics", _OPTICS,
            "photons = throughput(wave) * wave ** -4.0 / np.expm1(",
            "photons = throughput(wave) * wave ** -5.0 / np.expm1("),
]
MUTATIONS += SURVEY_MUTATIONS


def layout_of(root):
    """``"folders"`` for the package in folders, ``"flat"`` for the one before it."""
    return "folders" if os.path.isdir(os.path.join(root, "inject", "camera")) else "flat"


def patch_of(mutation, layout):
    return mutation.folders if layout == "folders" else mutation.flat


def test_files(root, mutation, new=False, only=None, add=()):
    """The mutation's test files present in ``root`` and those it does not have (``only``:
    these files instead of the mutation's own; ``add``: files or globs run as well)."""
    wanted = list(dict.fromkeys(only or [f for group in mutation.tests for f in TESTS[group]]))
    have, missing = [], []
    for f in wanted:
        if glob.has_magic(f):  # a pattern: the files matching it in ``root``, in order
            found = sorted(os.path.relpath(p, root) for p in glob.glob(os.path.join(root, f)))
            have += [p for p in found if p not in have]
            missing += [] if found else [f]
        elif os.path.exists(os.path.join(root, f)):
            have += [f] if f not in have else []
        else:
            missing.append(f)
    for pattern in (NEW_TESTS if new else ()) + tuple(add):
        have += sorted(os.path.relpath(p, root) for p in glob.glob(os.path.join(root, pattern))
                       if os.path.relpath(p, root) not in have)
    return have, missing


def applies(root, patch):
    """How many times the patch's text occurs in its file (1 is right)."""
    path = os.path.join(root, patch.path)
    if not os.path.exists(path):
        return 0
    with open(path) as stream:
        return stream.read().count(patch.old)


def describe(root):
    """The checkout's commit (short), marked when its tracked files differ from it."""
    def git(*args):
        return subprocess.run(["git", "-C", root, *args], capture_output=True, text=True)

    head = git("rev-parse", "--short", "HEAD")
    if head.returncode:
        return root
    dirty = git("status", "--porcelain", "--untracked-files=no").stdout.strip()
    return f"commit {head.stdout.strip()}" + (" with local changes" if dirty else "")


def run_one(root, tmp, i, mutation, layout, new, timeout, only=None, every=False, add=()):
    patch = patch_of(mutation, layout)
    tests, _ = test_files(root, mutation, new, only, add)
    if patch is None:
        return mutation, "not in this code", 0.0, "", tests
    copy = os.path.join(tmp, f"mutant{i}")
    shutil.copytree(root, copy, ignore=IGNORE, dirs_exist_ok=True)
    try:
        target = os.path.join(copy, patch.path)
        with open(target) as f:
            text = f.read()
        if text.count(patch.old) != 1:
            return mutation, "PATCH DOES NOT APPLY", 0.0, "", tests
        with open(target, "w") as f:
            f.write(text.replace(patch.old, patch.new))
        status, seconds, failed = run_tests(copy, tests, timeout, every)
        result = "caught" if status not in (0, "timeout", 5) else (
            "MISSED" if status in (0, 5) else "timeout")
        return mutation, result, seconds, failed, tests
    finally:
        shutil.rmtree(copy, ignore_errors=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--root", default=ROOT, help="checkout to mutate (default: this one)")
    parser.add_argument("--only", nargs="*", help="substrings of mutation names to run")
    parser.add_argument("--area", nargs="*", help="only these areas (focal plane, passes, "
                        "noise, runner, readers, survey, optics)")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--check", action="store_true", help="only check that patches apply")
    parser.add_argument("--new", action="store_true",
                        help="also run issue 19's new test files for every mutation")
    parser.add_argument("--tests", nargs="*", help="run these test files for every mutation "
                        "instead of its own")
    parser.add_argument("--add-tests", nargs="*", default=[], metavar="GLOB",
                        help="also run these test files (globs allowed) for every mutation")
    parser.add_argument("--every", action="store_true",
                        help="run every test (no -x) and list all the files that fail")
    parser.add_argument("--jobs", type=int, default=1, help="mutants tested at once")
    parser.add_argument("--timeout", type=float, default=1200)
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--markdown", metavar="FILE", help="also write the table to FILE")
    parser.add_argument("--label", help="how the table's last line names the checkout "
                        "(default: its git commit, or its path)")
    args = parser.parse_args(argv)
    root = os.path.abspath(args.root)
    layout = layout_of(root)
    chosen = [m for m in MUTATIONS if (not args.only or any(s in m.name for s in args.only))
              and (not args.area or m.area in args.area)]
    if args.list or args.check:
        bad = 0
        for m in chosen:
            patch = patch_of(m, layout)
            tests, missing = test_files(root, m, args.new, args.tests, args.add_tests)
            count = None if patch is None else applies(root, patch)
            bad += count not in (None, 1)
            state = "n/a" if count is None else ("ok" if count == 1 else f"{count} matches")
            print(f"{state:>10s}  {m.area:12s} {m.name}: "
                  f"{patch.path if patch else '-'} -> {' '.join(tests)}"
                  + (f" (missing: {' '.join(missing)})" if missing else ""))
        return 1 if bad else 0
    print(f"checkout {root} ({layout} layout), {len(chosen)} mutations", flush=True)
    rows, bad = [], 0
    with tempfile.TemporaryDirectory(prefix="inject-mutants-") as tmp:
        if not args.no_baseline:
            base = os.path.join(tmp, "baseline")
            shutil.copytree(root, base, ignore=IGNORE, dirs_exist_ok=True)
            tests = sorted({t for m in chosen
                            for t in test_files(root, m, args.new, args.tests,
                                                args.add_tests)[0]})
            if not baseline_passes(base, tests, args.timeout):
                return 1
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            futures = [pool.submit(run_one, root, tmp, i, m, layout, args.new, args.timeout,
                                   args.tests, args.every, args.add_tests)
                       for i, m in enumerate(chosen)]
            for future in futures:
                m, result, seconds, failed, _ = future.result()
                bad += result not in ("caught", "not in this code")
                rows.append((m, result, seconds, failed))
                print(f"{result:>7s}  {seconds:6.0f} s  {m.name}  ({failed or '-'})",
                      flush=True)
    failing = "test files that fail" if args.every else "first failing test"
    lines = [f"| mutation | area | audit | file | result | {failing} | time (s) |",
             "|---|---|:-:|---|---|---|---:|"]
    for m, result, seconds, failed in rows:
        patch = patch_of(m, layout)
        lines.append(f"| {m.name} | {m.area} | {'yes' if m.audit else ''} | "
                     f"{patch.path if patch else '-'} | {result} | "
                     f"{failed.replace('|', '/') or '-'} | {seconds:.0f} |")
    caught = sum(r[1] == "caught" for r in rows)
    lines.append("")
    lines.append(f"{caught} of {len(rows)} mutations caught ({layout} layout, "
                 f"{args.label or describe(root)}).")
    print("\n" + "\n".join(lines))
    if args.markdown:
        with open(args.markdown, "w") as stream:
            stream.write("\n".join(lines) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
