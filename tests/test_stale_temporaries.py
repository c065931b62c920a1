"""Temporary files a killed run leaves (``.inject-*``): a rerun removes them, never a live
writer's."""
import fcntl
import os
import time
from concurrent.futures import ThreadPoolExecutor

from inject import make_plan, parse_focal_scene
from inject.camera import layout as fp
from inject.exposure import runner as parallel
from inject.io.atomic import STALE_AFTER_S, atomic_path, remove_stale_temporaries

OLD = time.time() - 10 * STALE_AFTER_S


def plant(directory, name, age=OLD):
    path = directory / name
    path.write_bytes(b"half a FITS file")
    os.utime(path, (age, age))
    return path


def test_only_unlocked_old_temporaries_are_removed(tmp_path):
    stale = plant(tmp_path, ".inject-dead.fits")
    young = plant(tmp_path, ".inject-young.fits", age=time.time())
    output = plant(tmp_path, "R22_S11.fits")
    locked = plant(tmp_path, ".inject-live.fits")
    with open(locked, "rb") as handle:  # a live writer holds the lock
        fcntl.flock(handle, fcntl.LOCK_EX)
        assert remove_stale_temporaries(tmp_path) == [str(stale)]
    assert not stale.exists() and young.exists() and output.exists() and locked.exists()


def test_a_live_atomic_write_is_kept(tmp_path):
    target = tmp_path / "out.fits"
    with atomic_path(target) as tmp:
        with open(tmp, "wb") as stream:
            stream.write(b"x")
        os.utime(tmp, (OLD, OLD))  # even an old-looking one: its lock says it is live
        assert remove_stale_temporaries(tmp_path) == []
        assert os.path.exists(tmp)
    assert target.read_bytes() == b"x"
    assert [n for n in os.listdir(tmp_path) if n.startswith(".inject-")] == []


def test_focal_plane_rerun_removes_a_killed_workers_temporary(tmp_path, caplog):
    fscene = parse_focal_scene({
        "seed": 3, "band": "g", "exptime": 30, "pointing": {"ra": 50.0, "dec": -30.0},
        "stars": False, "cutout": {"nx": 40, "ny": 30}, "detectors": ["R22_S11"],
        "satellites": []})
    stale = plant(tmp_path, ".inject-abc123.fits")
    with ThreadPoolExecutor(1) as pool:
        result = parallel.run(make_plan(fscene), str(tmp_path), pool, ccds=(fp.ccd("R22_S11"),))
    assert len(result.rendered) == 1 and not stale.exists()
    assert any("removed 1 temporary file" in r.getMessage() and r.levelname == "WARNING"
               for r in caplog.records)
    assert sorted(n for n in os.listdir(tmp_path) if n.startswith(".inject-")) == []
