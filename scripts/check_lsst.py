"""Read what inject writes with LSST's own reader, lsst-images (``MaskedImage.read_legacy``).

lsst-images (PyPI ``lsst-images``, pure Python) needs Python >= 3.12; inject's venv may be
older. This script finds such an interpreter (``python3.13``/``python3.12`` on PATH, pyenv's
versions, or the one running it), builds a venv with lsst-images outside the repository (once;
``--venv`` or ``$INJECT_LSST_VENV``, default ``~/.cache/inject/lsst-images-venv``), writes with
inject (this interpreter):

1. ``inject simulate`` of a small CCD with a pointing and a saturating streak;
2. ``inject add-streak`` into an afw-layout Exposure written here from afw's conventions (no
   EXTNAME, xy0 = (100, 200) in LTV1/2 and the "A" WCS, TAN-SIP WCS, uint16 mask stored as
   int16 + BZERO with ``MP_`` planes and no STREAK, archive tables after VARIANCE);
3. ``inject add-streak`` into the output of 1,

and reads them in the lsst-images venv, checking: pixels identical to astropy's; STREAK and
SAT planes by name with the file's pixel counts (no plane map for 1 and 3, a plane map for 2,
as for any afw file); the origin; the WCS equal to astropy's to 1e-8 deg. It prints one line
per check and ``ALL CHECKS PASSED``, exit status 0; 1 if a check fails; 3 if no Python >= 3.12
is found (nothing to check with).

Run: ``.venv/bin/python scripts/check_lsst.py`` (``--workdir DIR`` keeps the files).
"""
import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_VENV = Path(os.environ.get("INJECT_LSST_VENV",
                                   Path.home() / ".cache" / "inject" / "lsst-images-venv"))

#: The afw-layout Exposure of check 2 (and of tests/test_lsst_files.py).
AFW_SHAPE = (120, 150)
AFW_XY0 = (100, 200)
AFW_GAIN = 1.7
#: Planes of an afw visit image (afw's bits), leaving bit 11 as the lowest free one.
AFW_PLANES = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5,
              "DETECTED_NEGATIVE": 6, "SUSPECT": 7, "NO_DATA": 8, "CROSSTALK": 9,
              "UNMASKEDNAN": 10, "ITL_DIP": 12, "SPIKE": 15}


def _version_of(python):
    """``(major, minor)`` of an interpreter, or None if it does not run."""
    try:
        done = subprocess.run([python, "-c", "import sys; print(*sys.version_info[:2])"],
                              capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if done.returncode != 0:
        return None
    major, minor = done.stdout.split()
    return int(major), int(minor)


def find_python():
    """Path of a Python >= 3.12 on this machine, or None."""
    candidates = [shutil.which(name) for name in ("python3.13", "python3.12")]
    pyenv = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv"))
    candidates += sorted(glob.glob(str(pyenv / "versions" / "3.1[2-9]*" / "bin" / "python3")),
                         reverse=True)
    candidates.append(sys.executable)
    for python in candidates:
        if python and (_version_of(python) or (0, 0)) >= (3, 12):
            return python
    return None


def ensure_venv(venv, python):
    """A venv at ``venv`` with lsst-images installed (built with ``python`` if missing);
    returns its interpreter and lsst-images' version."""
    venv = Path(venv)
    exe = venv / "bin" / "python"
    if not exe.exists():
        print(f"building {venv} with {python} (pip install lsst-images) ...", flush=True)
        subprocess.run([python, "-m", "venv", str(venv)], check=True)
    probe = [str(exe), "-c", "from importlib.metadata import version; "
                             "import lsst.images; print(version('lsst-images'))"]
    done = subprocess.run(probe, capture_output=True, text=True)
    if done.returncode != 0:
        subprocess.run([str(exe), "-m", "pip", "install", "-q", "lsst-images"], check=True)
        done = subprocess.run(probe, capture_output=True, text=True, check=True)
    return exe, done.stdout.strip()


def sip_wcs_header():
    """A TAN-SIP WCS of a 150 x 120 array (FITS pixels, as afw writes it): ~2 px of distortion
    at the edge."""
    from astropy.wcs import WCS

    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = [150.0, 2.0]
    wcs.wcs.crpix = [75.5, 60.5]
    wcs.wcs.cd = np.array([[-5.5e-5, 0.0], [0.0, 5.5e-5]])
    header = wcs.to_header()
    header["CTYPE1"], header["CTYPE2"] = "RA---TAN-SIP", "DEC--TAN-SIP"
    header["A_ORDER"], header["B_ORDER"] = 2, 2
    header["A_2_0"], header["A_0_2"], header["B_1_1"] = 8e-4, -5e-4, 6e-4
    return header


def _afw_plane_header(exttype):
    """The cards afw puts on IMAGE, MASK and VARIANCE of an Exposure at xy0 = AFW_XY0."""
    from astropy.io import fits

    header = fits.Header()
    header["INHERIT"] = True
    header["EXTTYPE"] = exttype
    header.extend(sip_wcs_header())
    for key, value in (("CRVAL1A", float(AFW_XY0[0])), ("CRVAL2A", float(AFW_XY0[1])),
                       ("CRPIX1A", 1.0), ("CRPIX2A", 1.0), ("CTYPE1A", "LINEAR"),
                       ("CTYPE2A", "LINEAR"), ("CUNIT1A", "PIXEL"), ("CUNIT2A", "PIXEL")):
        header[key] = value
    header["LTV1"], header["LTV2"] = -float(AFW_XY0[0]), -float(AFW_XY0[1])
    return header


def write_afw_exposure(path):
    """Write an afw-layout Exposure in ADU to ``path`` (see the module's notes)."""
    from astropy.io import fits

    rng = np.random.default_rng(11)
    image = (500 + rng.normal(0, 8, AFW_SHAPE)).astype(np.float32)
    image[3, 4] = -0.0  # a negative zero: must stay negative where the streak does not reach
    mask = np.zeros(AFW_SHAPE, np.uint16)
    for bit in AFW_PLANES.values():
        mask[rng.random(AFW_SHAPE) < 0.02] |= np.uint16(1 << bit)
    variance = (image / AFW_GAIN + 25.0).astype(np.float32)
    primary = fits.PrimaryHDU()
    primary.header["AR_HDU"] = 5
    primary.header["HIERARCH ARCHIVE_ID_PSF"] = 1
    primary.header["EXPTIME"] = 30.0
    primary.header["GAIN"] = AFW_GAIN
    mask_header = _afw_plane_header("MASK")
    for name, bit in AFW_PLANES.items():
        mask_header[f"HIERARCH MP_{name}"] = bit
    image_header = _afw_plane_header("IMAGE")
    image_header["BUNIT"] = "adu"
    archive_index = fits.BinTableHDU.from_columns([
        fits.Column("id", "J", array=[1, 2]),
        fits.Column("name", "20A", array=["PsfA", "ApCorrB"])])
    archive_index.header["EXTTYPE"] = "ARCHIVE_INDEX"
    heap = fits.BinTableHDU.from_columns([fits.Column(
        "coeffs", "PD()", array=np.array([np.arange(3.0), np.arange(7.0)], dtype=object))])
    heap.header["EXTTYPE"] = "ARCHIVE_DATA"
    hdus = fits.HDUList([primary, fits.ImageHDU(image, header=image_header),
                         fits.ImageHDU(mask, header=mask_header),
                         fits.ImageHDU(variance, header=_afw_plane_header("VARIANCE")),
                         archive_index, heap])
    hdus.writeto(path)
    return path


SCENE = {"seed": 5, "band": "i", "exptime": 30.0, "zenith": 50,
         "detector": {"type": "itl", "nx": 300, "ny": 200, "full_well": 30000},
         "sky": True, "stars": True, "noise": True,
         "pointing": {"ra": 53.1, "dec": -27.8, "rotation": 35.0},
         "satellites": [{"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65},
                         "mag": 2.0, "track": {"x0": 20.0, "y0": 40.0, "angle": 25.0}}]}


def write_inputs(workdir):
    """The two files to read (simulate's and add-streak's output), written with inject."""
    import yaml

    from inject.cli.main import main

    workdir = Path(workdir)
    scene = workdir / "scene.yaml"
    scene.write_text(yaml.safe_dump(SCENE))
    simulated = workdir / "simulated.fits"
    if main(["simulate", str(scene), "-o", str(simulated), "--overwrite"]) != 0:
        raise SystemExit("inject simulate failed")
    afw = write_afw_exposure(workdir / "afw_calexp.fits") if not (
        workdir / "afw_calexp.fits").exists() else workdir / "afw_calexp.fits"
    injected = workdir / "afw_injected.fits"
    if main(["add-streak", str(afw), "-o", str(injected), "--height", "550", "--zenith", "60",
             "--mag", "6", "--angle", "20", "--track-length", "80", "--parent", "--x0",
             str(AFW_XY0[0] + 30), "--y0", str(AFW_XY0[1] + 40), "--overwrite"]) != 0:
        raise SystemExit("inject add-streak failed")
    again = workdir / "simulated_injected.fits"
    if main(["add-streak", str(simulated), "-o", str(again), "--height", "350", "--zenith",
             "30", "--mag", "5", "--x0", "10", "--y0", "150", "--angle", "-15",
             "--overwrite"]) != 0:
        raise SystemExit("inject add-streak failed")
    return simulated, injected, again


#: Run in the lsst-images venv: reads each file and prints one JSON object of results.
READER = r'''
import json, sys
import numpy as np
import astropy.units as u
from astropy.io import fits
from astropy.wcs import WCS
from lsst.images import GeneralFrame, MaskedImage, MaskPlane, XY

def check(path, plane_map):
    with fits.open(path) as hdus:
        image, mask, variance = (np.array(hdus[i].data) for i in (1, 2, 3))
        mp = {k[3:]: v for k, v in hdus[2].header.items() if k.startswith("MP_")}
        wcs = WCS(hdus[1].header)
    kwargs = {"fits_wcs_frame": GeneralFrame(unit=u.pix)}
    if plane_map:
        kwargs["plane_map"] = {name: MaskPlane(name, name) for name in mp}
    mi = MaskedImage.read_legacy(path, **kwargs)
    out = {"planes": sorted(mi.mask.schema.names), "x0": mi.bbox.x.start, "y0": mi.bbox.y.start,
           "image_equal": bool(np.array_equal(mi.image.array, image)),
           "variance_equal": bool(np.array_equal(mi.variance.array, variance)),
           "unit": str(mi.unit), "variance_unit": str(mi.variance.unit), "counts": {}}
    for name in mp:
        out["counts"][name] = [int(mi.mask.get(name).sum()),
                               int(np.count_nonzero(mask & (1 << mp[name])))]
    ny, nx = image.shape
    xs, ys = np.meshgrid(np.linspace(0, nx - 1, 7), np.linspace(0, ny - 1, 5))
    ours = wcs.pixel_to_world(xs.ravel(), ys.ravel())
    theirs = mi.sky_projection.pixel_to_sky(x=xs.ravel() + out["x0"], y=ys.ravel() + out["y0"])
    out["wcs_max_sep_deg"] = float(ours.separation(theirs).deg.max())
    return out

print(json.dumps({p: check(p, m == "map") for p, m in zip(sys.argv[1::2], sys.argv[2::2])}))
'''


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--venv", default=str(DEFAULT_VENV),
                        help=f"lsst-images venv, built if missing ({DEFAULT_VENV})")
    parser.add_argument("--workdir", help="where to write the files (default: a temporary one)")
    args = parser.parse_args(argv)
    python = find_python()
    if python is None:
        print("SKIP: no Python >= 3.12 found (python3.12/3.13 on PATH or under pyenv): "
              "lsst-images needs one")
        return 3
    exe, version = ensure_venv(args.venv, python)
    print(f"lsst-images {version} in {args.venv} (Python from {python})")
    with tempfile.TemporaryDirectory() as scratch:
        workdir = Path(args.workdir or scratch)
        workdir.mkdir(parents=True, exist_ok=True)
        simulated, injected, again = write_inputs(workdir)
        done = subprocess.run([str(exe), "-c", READER, str(simulated), "none", str(injected),
                               "map", str(again), "none"], capture_output=True, text=True)
        if done.returncode != 0:
            print(done.stderr)
            print("FAILED: lsst-images could not read the files")
            return 1
        results = json.loads(done.stdout)
    failures = 0

    def report(ok, text):
        nonlocal failures
        failures += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {text}")

    sim, inj = results[str(simulated)], results[str(injected)]
    report(True, f"simulate output: read_legacy with no plane map, planes {sim['planes']}")
    report(sim["image_equal"] and sim["variance_equal"],
           "simulate: IMAGE and VARIANCE identical to astropy's")
    for name in ("STREAK", "SAT"):
        got, want = sim["counts"][name]
        report(got == want and want > 0, f"simulate: {name} plane by name, {got} pixels "
                                         f"(file: {want})")
    report((sim["x0"], sim["y0"]) == (0, 0), f"simulate: origin ({sim['x0']}, {sim['y0']})")
    report(sim["wcs_max_sep_deg"] < 1e-8,
           f"simulate: WCS vs astropy, max {sim['wcs_max_sep_deg']:.2e} deg (< 1e-8)")
    report(sim["unit"] == "electron" and sim["variance_unit"] == "electron2",
           f"simulate: units {sim['unit']}, {sim['variance_unit']}")
    report(inj["image_equal"] and inj["variance_equal"],
           "add-streak on afw Exposure: read_legacy with a plane map; IMAGE, VARIANCE identical")
    got, want = inj["counts"]["STREAK"]
    report(got == want and want > 0, f"add-streak: STREAK plane {got} pixels (file: {want})")
    kept = {name: counts for name, counts in inj["counts"].items() if name != "STREAK"}
    report(all(got == want for got, want in kept.values()),
           f"add-streak: the file's other {len(kept)} planes by name, pixel counts as in the "
           f"file (SAT {kept['SAT'][0]})")
    report((inj["x0"], inj["y0"]) == AFW_XY0, f"add-streak: origin ({inj['x0']}, {inj['y0']})"
                                              f" = xy0 {AFW_XY0}")
    report(inj["wcs_max_sep_deg"] < 1e-8,
           f"add-streak: TAN-SIP WCS vs astropy, max {inj['wcs_max_sep_deg']:.2e} deg (< 1e-8)")
    both = results[str(again)]
    got, want = both["counts"]["STREAK"]
    report(both["image_equal"] and got == want and want > sim["counts"]["STREAK"][1],
           f"add-streak into the simulate output: read_legacy with no plane map, STREAK "
           f"{got} pixels (file: {want}, simulate's {sim['counts']['STREAK'][1]} + the new one)")
    if failures:
        print(f"{failures} CHECK(S) FAILED")
        return 1
    print("ALL CHECKS PASSED")
    return 0


if __name__ == "__main__":
    sys.exit(main())
