"""Mutation check: would the default tests notice a small deliberate bug in a numerical core?

Each mutation is one textual change (a factor of a few percent, a flipped sign, a dropped
term) to one function that sets a number users rely on. For each, the repository (without
its venv and git data) is copied to a temporary directory, the change applied to the copy,
and the default tests that cover that core run there (``-x``: the first failure is enough)
with the copy first on ``PYTHONPATH``; the working tree is never modified. A mutation is
*caught* if those tests fail. The unmutated copy is run first on the union of the test files
(they must pass, or "caught" would mean nothing).

Usage::

    python scripts/mutation_check.py [--only NAME ...] [--list] [--markdown]

Exit status 1 if a mutation is missed or a patch no longer applies (the code moved: update
the list), so it can run in CI.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
IGNORE = shutil.ignore_patterns(".venv", ".git", "out", "__pycache__", "*.egg-info",
                                ".hypothesis", ".pytest_cache")


@dataclass(frozen=True)
class Mutation:
    name: str
    path: str     # relative to the repository
    old: str      # must occur exactly once
    new: str
    tests: tuple  # default test files (or node ids) that must catch it


PHOT = ("tests/test_absolute_photometry.py", "tests/test_photometry.py")
GEOM = ("tests/test_geometry.py", "tests/test_absolute_photometry.py")
RENDER = ("tests/test_end_caps.py", "tests/test_render.py", "tests/test_properties.py")
PROFILE = ("tests/test_profile.py", "tests/test_cli.py", "tests/test_render.py")
MASK = ("tests/test_masking.py",)

MUTATIONS = [
    Mutation("tangential speed 2% high", "inject/geometry.py",
             "return v * np.hypot(np.cos(phi), np.sin(phi) * np.cos(tn))",
             "return 1.02 * v * np.hypot(np.cos(phi), np.sin(phi) * np.cos(tn))", GEOM),
    Mutation("tangential speed: cos^2 of the nadir angle", "inject/geometry.py",
             "return v * np.hypot(np.cos(phi), np.sin(phi) * np.cos(tn))",
             "return v * np.hypot(np.cos(phi), np.sin(phi) * np.cos(tn) ** 2)", GEOM),
    Mutation("range 1% long", "inject/geometry.py",
             "return h * (2 * R_EARTH_KM + h) / (root + R_EARTH_KM * np.cos(z))",
             "return 1.01 * h * (2 * R_EARTH_KM + h) / (root + R_EARTH_KM * np.cos(z))", GEOM),
    Mutation("t_eff 2% long", "inject/geometry.py",
             "return p / ARCSEC_PER_RAD / angular_speed(",
             "return 1.02 * p / ARCSEC_PER_RAD / angular_speed(", GEOM),
    Mutation("zero-point sign flipped", "inject/photometry.py",
             "return 10.0 ** (0.4 * (band(band_name).zeropoint - m))",
             "return 10.0 ** (0.4 * (m - band(band_name).zeropoint))", PHOT),
    Mutation("magnitude offset in the streak flux (5% high)", "inject/streak.py",
             "return float(electron_rate(self.apparent_mag, self.band_name))",
             "return float(electron_rate(self.apparent_mag - 0.053, self.band_name))", PHOT),
    Mutation("extinction applied to the streak", "inject/streak.py",
             "return float(electron_rate(self.apparent_mag, self.band_name))",
             "return float(electron_rate(self.apparent_mag + band(self.band_name).extinction"
             " / np.cos(np.radians(self.zenith_deg)), self.band_name))", PHOT),
    Mutation("hardware zero point for the streak", "inject/streak.py",
             "return float(electron_rate(self.apparent_mag, self.band_name))",
             "return float(electron_rate(self.apparent_mag - band(self.band_name).extinction,"
             " self.band_name))", PHOT),
    Mutation("range scaling of the magnitude 2% off", "inject/photometry.py",
             "return m + 5.0 * np.log10(r / r_ref) - 2.5 * np.log10(cos_tn)",
             "return m + 5.1 * np.log10(r / r_ref) - 2.5 * np.log10(cos_tn)", PHOT),
    Mutation("cos(nadir) scaling of the magnitude dropped", "inject/photometry.py",
             "return m + 5.0 * np.log10(r / r_ref) - 2.5 * np.log10(cos_tn)",
             "return m + 5.0 * np.log10(r / r_ref)", PHOT),
    Mutation("sky with the airmass-1 zero point", "inject/photometry.py",
             "10.0 ** (0.4 * (b.zeropoint + b.extinction - mu))",
             "10.0 ** (0.4 * (b.zeropoint - mu))", PHOT),
    Mutation("annulus not renormalised (outer disk)", "inject/profile.py",
             "outer = galsim.TopHat(a_o, flux=1.0 / (1.0 - eps2), gsparams=gsparams)",
             "outer = galsim.TopHat(a_o, flux=1.0, gsparams=gsparams)", PROFILE + RENDER[:2]),
    Mutation("annulus not renormalised (inner disk)", "inject/profile.py",
             "inner = galsim.TopHat(a_o * telescope.obscuration, flux=eps2 / (1.0 - eps2),",
             "inner = galsim.TopHat(a_o * telescope.obscuration, flux=eps2,",
             PROFILE + RENDER[:2]),
    Mutation("LSF pixel response 5% wide", "inject/profile.py",
             "slice_k = slice_k * np.sinc(ky * width / (2 * np.pi))",
             "slice_k = slice_k * np.sinc(1.05 * ky * width / (2 * np.pi))", PROFILE),
    Mutation("end-cap table scale 0.1% high", "inject/render.py",
             "coeffs *= n_d * dk_d / (2 * np.pi)",
             "coeffs *= 1.001 * n_d * dk_d / (2 * np.pi)", RENDER),
    Mutation("end-cap pixel rotation sign flipped", "inject/render.py",
             "            -self.angle_deg * galsim.degrees)",
             "            self.angle_deg * galsim.degrees)", RENDER),
    Mutation("interior LSF pixel at the wrong angle", "inject/render.py",
             "step_arcsec=lsf_step, pixel_angle_deg=self.angle_deg,",
             "step_arcsec=lsf_step, pixel_angle_deg=self.angle_deg + 20,", RENDER),
    Mutation("end caps' cumulative integrated half a sample off", "inject/render.py",
             "[u + self.PAD - 0.5], order=4", "[u + self.PAD + 0.5], order=4", RENDER),
    Mutation("end caps' cumulative not flat at its ends", "inject/render.py",
             'spline_filter1d(np.asarray(values, float), order=3, mode="mirror")',
             'spline_filter1d(np.asarray(values, float), order=3, mode="nearest")', RENDER),
    Mutation("transform lengths one past a fast length", "inject/render.py",
             "        while m < n:\n            m *= 2",
             "        while m <= n:\n            m *= 2", RENDER),
    Mutation("short tracks not budgeted against their own peak", "inject/render.py",
             "    if ratio >= 1.0:\n        return budget\n    return replace(",
             "    if ratio >= 0.0:\n        return budget\n    return replace(", RENDER),
    Mutation("tolerance snapped up (looser than asked)", "inject/render.py",
             "snapped = 2.0 ** (np.floor(np.log2(tolerance) * n + 1e-9) / n)",
             "snapped = 2.0 ** (np.ceil(np.log2(tolerance) * n + 1e-9) / n)",
             ("tests/test_many_streaks.py",)),
    Mutation("swept-profile cache key without the angle", "inject/render.py",
             'return cache.get(("swept", key, angle_deg, budget), build)',
             'return cache.get(("swept", key, budget), build)', ("tests/test_many_streaks.py",)),
    Mutation("profile key without the seeing", "inject/streak.py",
             "return (self.height_km, self.zenith_deg, self.phi_deg, self.shape, self.seeing,",
             "return (self.height_km, self.zenith_deg, self.phi_deg, self.shape, None,",
             ("tests/test_many_streaks.py",)),
    Mutation("FWHM pixel response not removed", "inject/masking/measure.py",
             'return 2 * values - np.convolve(values, '
             'pixel_response(step, angle_deg), mode="same")',
             "return values", MASK),
    Mutation("smoothing that widens (moving average)", "inject/masking/measure.py",
             'return savgol_filter(f, n, 2, mode="interp") if n < f.size else f',
             'return savgol_filter(f, n, 0, mode="interp") if n < f.size else f', MASK),
    Mutation("half-maximum level at 52%", "inject/masking/measure.py",
             "half = 0.5 * peak", "half = 0.52 * peak", MASK),
]


def copy_tree(dest):
    shutil.copytree(ROOT, dest, ignore=IGNORE, dirs_exist_ok=True)


def run_tests(copy, tests, timeout, every=False):
    """Run ``tests`` in ``copy``; return (status, seconds, first failing test or ''), or with
    ``every`` (no ``-x``) the failing test files, comma-separated, in place of the test."""
    env = dict(os.environ, PYTHONPATH=copy + os.pathsep + os.environ.get("PYTHONPATH", ""),
               PYTHONDONTWRITEBYTECODE="1")
    check = subprocess.run([sys.executable, "-c", "import inject; print(inject.__file__)"],
                           cwd=copy, env=env, capture_output=True, text=True)
    if not check.stdout.startswith(copy):
        raise SystemExit(f"the copy's package is not the one imported: {check.stdout.strip()}")
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-m", "pytest", *([] if every else ["-x"]),
                               "-q", "-p", "no:cacheprovider", *tests], cwd=copy, env=env,
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - start, ""
    failed = [line.split()[1] for line in proc.stdout.splitlines()
              if line.startswith(("FAILED", "ERROR")) and len(line.split()) > 1]
    if every:
        text = ", ".join(dict.fromkeys(os.path.basename(f.split("::")[0]) for f in failed))
    else:
        text = failed[0] if failed else ""
    return proc.returncode, time.perf_counter() - start, text


def baseline_passes(base, tests, timeout):
    """Run ``tests`` on the unmutated copy ``base`` and say how it went; remove the copy when
    they pass (a mutant that fails tests already failing would prove nothing)."""
    status, seconds, failed = run_tests(base, tests, timeout)
    print(f"baseline (unmutated) on {len(tests)} test files: "
          f"{'pass' if status == 0 else 'FAIL ' + failed} in {seconds:.0f} s", flush=True)
    if status == 0:
        shutil.rmtree(base)
    return status == 0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", nargs="*", help="substrings of mutation names to run")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--timeout", type=float, default=1200)
    parser.add_argument("--no-baseline", action="store_true")
    args = parser.parse_args(argv)
    chosen = [m for m in MUTATIONS
              if not args.only or any(s in m.name for s in args.only)]
    if args.list:
        for m in chosen:
            print(f"{m.name}: {m.path} -> {' '.join(m.tests)}")
        return 0
    rows, bad = [], 0
    with tempfile.TemporaryDirectory(prefix="inject-mutants-") as tmp:
        if not args.no_baseline:
            base = os.path.join(tmp, "baseline")
            copy_tree(base)
            if not baseline_passes(base, sorted({t for m in chosen for t in m.tests}),
                                   args.timeout):
                return 1
        for i, m in enumerate(chosen):
            copy = os.path.join(tmp, f"mutant{i}")
            copy_tree(copy)
            target = os.path.join(copy, m.path)
            with open(target) as f:
                text = f.read()
            if text.count(m.old) != 1:
                rows.append((m, "PATCH DOES NOT APPLY", 0.0, ""))
                bad += 1
                shutil.rmtree(copy)
                continue
            with open(target, "w") as f:
                f.write(text.replace(m.old, m.new))
            status, seconds, failed = run_tests(copy, m.tests, args.timeout)
            result = "caught" if status not in (0, "timeout") else (
                "MISSED" if status == 0 else "timeout")
            bad += result != "caught"
            rows.append((m, result, seconds, failed))
            print(f"{result:>7s}  {seconds:6.0f} s  {m.name}  ({failed or '-'})", flush=True)
            shutil.rmtree(copy)
    print()
    print("| mutation | file | result | first failing test | time (s) |")
    print("|---|---|---|---|---:|")
    for m, result, seconds, failed in rows:
        print(f"| {m.name} | {m.path} | {result} | {failed.replace('|', '/') or '-'} | "
              f"{seconds:.0f} |")
    caught = sum(r[1] == "caught" for r in rows)
    print(f"\n{caught} of {len(rows)} mutations caught by the default tests.")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
