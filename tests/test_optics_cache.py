"""The traced kernels' disk cache (inject.optics): one file per everything a kernel depends
on, damaged files traced again, an unwritable folder said once.

The point here is the cache, not the physics: a stand-in tracer returns a small kernel whose
image counts the traces, so a kernel read back is told from one traced again.
"""
import functools
import os
import shutil
import struct
import warnings
import zipfile

import numpy as np
import pytest

from inject import optics
from inject.errors import InputWarning
from inject.optics import TracedKernel, _grid_kernel

batoid = pytest.importorskip("batoid")

NODE = ("g", 500, 0)  # 1.02**500 = 19957 km, on the axis


@pytest.fixture
def traces(tmp_path, monkeypatch):
    """The stand-in tracer's calls (keyword arguments), the cache in ``tmp_path``."""
    monkeypatch.setenv("INJECT_CACHE_DIR", str(tmp_path))
    calls = []

    def trace(band, range_km, field_angle_deg=0.0, field_position_angle_deg=0.0,
              n_rays=optics.N_RAYS, pixel_scale=optics.KERNEL_SCALE_ARCSEC,
              focus_offset_um=0.0, **spectrum):
        calls.append(dict(band=band, range_km=range_km, field_angle_deg=field_angle_deg))
        image = np.full((5, 5), float(len(calls)))
        return TracedKernel(image=image, scale=pixel_scale, centroid=(0.0, 0.0),
                            inner_radius=np.nan, outer_radius=0.02,
                            transmitted=float(image.sum() * pixel_scale ** 2),
                            star_throughput=1.0, band=band, range_km=range_km,
                            field_angle_deg=field_angle_deg,
                            field_position_angle_deg=field_position_angle_deg, n_traced=n_rays,
                            focus_offset_um=focus_offset_um)

    monkeypatch.setattr(optics, "traced_kernel", trace)
    _grid_kernel.cache_clear()
    yield calls
    _grid_kernel.cache_clear()


def _files(folder):
    return sorted(os.path.join(d, f) for d, _, names in os.walk(folder) for f in names)


def _new_run():
    _grid_kernel.cache_clear()  # what a new process starts with


def test_a_kernel_cached_for_one_band_is_not_used_for_another(traces, tmp_path):
    g = _grid_kernel(*NODE)
    _new_run()
    u = _grid_kernel("u", *NODE[1:])
    assert [c["band"] for c in traces] == ["g", "u"]
    assert u.band == "u" and u.image[0, 0] == 2 and g.image[0, 0] == 1
    _new_run()
    assert _grid_kernel(*NODE).image[0, 0] == 1  # both read back, each its own
    assert _grid_kernel("u", *NODE[1:]).image[0, 0] == 2
    assert len(traces) == 2 and len(_files(tmp_path)) == 2


def _another_model(monkeypatch, name, value):
    """batoid's ``name`` set to ``value``, the model's identity worked out again."""
    monkeypatch.setattr(batoid, name, value)
    monkeypatch.setattr(optics, "_model_identity",
                        functools.lru_cache(optics._model_identity.__wrapped__))


def _modified_model(monkeypatch, tmp_path):
    """batoid's model files with a comment added to the g camera's."""
    folder = tmp_path / "batoid-data"
    shutil.copytree(os.path.join(batoid.datadir, "LSST"), folder / "LSST")
    with open(folder / "LSST" / "LSST_g.yaml", "a") as stream:
        stream.write("\n# edited\n")
    _another_model(monkeypatch, "datadir", str(folder))


def _another_throughput(monkeypatch, tmp_path):
    """GalSim's g throughput file with a comment added."""
    tmp_path.mkdir()
    path = tmp_path / "LSST_g.dat"
    path.write_text(open(optics._throughput_path("g")).read() + "\n# edited\n")
    monkeypatch.setattr(optics, "_throughput_path", lambda band: str(path))
    monkeypatch.setattr(optics, "_throughput_identity",
                        functools.lru_cache(optics._throughput_identity.__wrapped__))


#: How to change each thing a kernel depends on, for the node NODE: a new node, or a change
#: to the module (what a later version of inject or batoid would change).
CHANGES = {
    "band": lambda mp, tmp: ("u", 500, 0),
    "range bin": lambda mp, tmp: ("g", 501, 0),
    "focus offset": lambda mp, tmp: ("g", 500, 0, 20.0),
    "field node": lambda mp, tmp: ("g", 500, 1),
    "vane offset": lambda mp, tmp: mp.setattr(optics, "VANE_OFFSET_DEG", 30.0),
    "rays": lambda mp, tmp: mp.setattr(optics, "GRID_RAYS", 100_000),
    "sampling": lambda mp, tmp: mp.setattr(optics, "KERNEL_SCALE_ARCSEC", 0.005),
    "wavelengths": lambda mp, tmp: mp.setattr(optics, "N_WAVELENGTHS", 5),
    "spectrum": lambda mp, tmp: ("g", 500, 0, 0.0, None, 6000.0),
    "throughput file": _another_throughput,
    "pupil seed": lambda mp, tmp: mp.setattr(optics, "_PUPIL_SEED", 1),
    "pupil margin": lambda mp, tmp: mp.setattr(optics, "_PUPIL_MARGIN_M", 0.2),
    "jacobian step": lambda mp, tmp: mp.setattr(optics, "_JACOBIAN_STEP_RAD", 1e-4),
    "jacobian grid": lambda mp, tmp: mp.setattr(optics, "_JACOBIAN_GRID", 64),
    "model files": _modified_model,
    "batoid version": lambda mp, tmp: _another_model(mp, "__version__", "99.0"),
    "format version": lambda mp, tmp: mp.setattr(optics, "CACHE_VERSION", 99),
}


@pytest.mark.parametrize("change", CHANGES)
def test_a_change_to_what_the_kernel_depends_on_is_another_file(change, traces, tmp_path,
                                                                 monkeypatch):
    _grid_kernel(*NODE)
    _new_run()
    node = CHANGES[change](monkeypatch, tmp_path / "elsewhere") or NODE
    kernel = _grid_kernel(*node)
    assert len(traces) == 2 and kernel.image[0, 0] == 2  # traced, not the first one read back
    assert len(_files(tmp_path / "kernels")) == 2


def _flip_a_byte_of_the_image(path):
    """Change one byte of the image's data inside the npz (stored uncompressed): its CRC-32
    no longer matches."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("image.npy")
    data = bytearray(open(path, "rb").read())
    name_length, extra_length = struct.unpack("<HH", data[info.header_offset + 26:
                                                            info.header_offset + 30])
    start = info.header_offset + 30 + name_length + extra_length
    data[start + info.compress_size - 4] ^= 0xFF  # the last pixel, past the .npy header
    open(path, "wb").write(bytes(data))


def _truncate(path):
    data = open(path, "rb").read()
    open(path, "wb").write(data[:len(data) // 2])


def _resave(path, **arrays):
    with np.load(path) as data:
        members = {name: data[name] for name in data.files} | arrays
    np.savez(path, **members)


DAMAGE = {
    "truncated": _truncate,
    "bad CRC": _flip_a_byte_of_the_image,
    "empty": lambda path: open(path, "wb").close(),
    "not an npz": lambda path: open(path, "wb").write(b"not a kernel"),
    "wrong shape": lambda path: _resave(path, image=np.ones((4, 6), np.float32)),
    "light lost": lambda path: _resave(path, image=np.zeros((5, 5), np.float32)),
    "NaN": lambda path: _resave(path, image=np.full((5, 5), np.nan, np.float32)),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_file_is_traced_again_and_rewritten(damage, traces, tmp_path):
    _grid_kernel(*NODE)
    [path] = _files(tmp_path)
    DAMAGE[damage](path)
    if damage == "bad CRC":
        with np.load(path) as data, pytest.raises(zipfile.BadZipFile, match="CRC"):
            data["image"]
    _new_run()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kernel = _grid_kernel(*NODE)
    assert len(traces) == 2 and kernel.image[0, 0] == 2
    assert _files(tmp_path) == [path]  # rewritten in place, no temporary left
    _new_run()
    assert _grid_kernel(*NODE).image[0, 0] == 2 and len(traces) == 2


def test_an_unwritable_cache_warns_once_and_the_run_goes_on(traces, tmp_path, monkeypatch):
    (tmp_path / "a-file").write_text("")
    root = tmp_path / "a-file" / "cache"  # no folder can be made under a file
    monkeypatch.setenv("INJECT_CACHE_DIR", str(root))
    monkeypatch.setattr(optics, "_unwritable_said", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = _grid_kernel(*NODE)
        _grid_kernel("g", 500, 1)
        _new_run()
        again = _grid_kernel(*NODE)
    assert first.image[0, 0] == 1 and again.image[0, 0] == 3 and len(traces) == 3
    assert len(caught) == 1 and caught[0].category is InputWarning
    text = str(caught[0].message)
    assert str(root) in text and "INJECT_CACHE_DIR" in text and "\n" not in text


def test_the_command_says_it_in_one_line_and_goes_on(traces, tmp_path, monkeypatch, cli):
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("INJECT_CACHE_DIR", str(tmp_path / "a-file" / "cache"))
    monkeypatch.setattr(optics, "_unwritable_said", False)
    status, out, err = cli("profile", "--height", "550", "--pupil", "rubin", "--field-angle",
                           "1.0", "--field-position-angle", "30")
    assert status == 0 and "FWHM" in out and len(traces) == 1
    [line] = err.splitlines()
    assert line.startswith("inject profile: warning: kernel cache folder ")


def test_field_nodes_0_002_deg_apart_are_two_files(traces, tmp_path):
    """Beyond 1.9 deg the field nodes are 0.002 deg apart (1.902, 1.904): each is traced and
    kept in its own file, neither read back for the other."""
    nodes = optics.FIELD_NODES_DEG
    a = int(np.flatnonzero(np.isclose(nodes, 1.902))[0])
    assert nodes[a + 1] == pytest.approx(1.904, abs=1e-9)
    first = _grid_kernel("g", 500, a)
    _new_run()
    second = _grid_kernel("g", 500, a + 1)
    assert [c["field_angle_deg"] for c in traces] == pytest.approx([1.902, 1.904], abs=1e-9)
    assert first.image[0, 0] == 1 and second.image[0, 0] == 2
    assert len(_files(tmp_path)) == 2
    _new_run()
    assert _grid_kernel("g", 500, a).image[0, 0] == 1  # each read back as its own
    assert _grid_kernel("g", 500, a + 1).image[0, 0] == 2 and len(traces) == 2
