"""A run's workers and memory from what its job may use: the CPU affinity, a control group's
CPU quota and memory limit (fake /sys/fs/cgroup trees with hand-written limits, v1 and v2),
RLIMIT_AS (set in a subprocess), and a SLURM array's --job/--njobs."""
import argparse
import os
import resource
import shutil
import subprocess
import sys

import pytest

from inject.errors import InputError, ResourceError
from inject.exposure import sizing

GIB = 2**30
HOST = 64 * GIB  # the fake host's MemAvailable


def write(root, relative, text):
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def proc(tmp_path, groups, available=HOST):
    """A fake /proc: this process's groups and the host's MemAvailable."""
    root = tmp_path / "proc"
    write(root, "self/cgroup", groups)
    write(root, "meminfo", f"MemTotal: {2 * available // 1024} kB\n"
                           f"MemAvailable: {available // 1024} kB\n")
    return root


def affinity():
    """The CPUs this test process may use, as the OS says."""
    return len(os.sched_getaffinity(0))


def unlimited_address_space():
    return resource.getrlimit(resource.RLIMIT_AS)[0] == resource.RLIM_INFINITY


@pytest.fixture(autouse=True)
def _no_address_limit():
    if not unlimited_address_space():
        pytest.skip("the test process itself runs under an RLIMIT_AS")


def v2_tree(tmp_path):
    """A cgroup v2 tree: the job's group /job_1 (4 GiB, 3.5 GiB in use of which 0.25 GiB is
    page cache the kernel can drop; 2.5 CPUs) and its step /job_1/step_0 (8 GiB, 1 GiB in use;
    no CPU quota)."""
    root = tmp_path / "cgroup"
    write(root, "cgroup.controllers", "cpu memory pids\n")
    write(root, "cpu.max", "max 100000\n")  # the root: no limit
    write(root, "job_1/cpu.max", "250000 100000\n")
    write(root, "job_1/memory.max", f"{4 * GIB}\n")
    write(root, "job_1/memory.current", f"{int(3.5 * GIB)}\n")
    write(root, "job_1/memory.stat", f"anon 1000\ninactive_file {GIB // 4}\nactive_file 7\n")
    write(root, "job_1/step_0/cpu.max", "max 100000\n")
    write(root, "job_1/step_0/memory.max", f"{8 * GIB}\n")
    write(root, "job_1/step_0/memory.current", f"{GIB}\n")
    return root


def test_cgroup_v2_limits_bind_from_the_tightest_level(tmp_path):
    root = v2_tree(tmp_path)
    got = sizing.job_resources(str(root), str(proc(tmp_path, "0::/job_1/step_0\n")))
    # 4 GiB less (3.5 - 0.25) GiB in use: 0.75 GiB, tighter than the step's 8 - 1 = 7 GiB.
    assert got.memory == int(0.75 * GIB)
    assert got.memory_why == "cgroup v2 memory.max 4 GiB, 3.25 GiB in use"
    # 2.5 CPUs of quota: 2 workers keep them busy (unless the affinity gives fewer).
    assert got.cpus == min(2, affinity())
    if affinity() > 2:  # else the affinity binds first
        assert got.cpus_why == "cgroup v2 cpu.max 250000 100000: 2.5 CPUs"


def test_cgroup_v2_without_limits_leaves_the_host_and_affinity(tmp_path):
    root = tmp_path / "cgroup"
    write(root, "cgroup.controllers", "cpu memory\n")
    write(root, "free/cpu.max", "max 100000\n")
    write(root, "free/memory.max", "max\n")
    write(root, "free/memory.current", "12345\n")
    got = sizing.job_resources(str(root), str(proc(tmp_path, "0::/free\n", 5 * GIB)))
    assert (got.memory, got.memory_why) == (5 * GIB, "the host's MemAvailable 5 GiB")
    assert got.cpus == affinity()


def test_a_quota_under_one_cpu_still_gives_one_worker(tmp_path):
    root = tmp_path / "cgroup"
    write(root, "cgroup.controllers", "cpu\n")
    write(root, "small/cpu.max", "50000 100000\n")
    got = sizing.job_resources(str(root), str(proc(tmp_path, "0::/small\n")))
    assert got.cpus == 1
    assert got.cpus_why == "cgroup v2 cpu.max 50000 100000: 0.5 CPUs"


def v1_tree(tmp_path):
    """A cgroup v1 tree as SLURM makes it: memory and cpu,cpuacct mounted apart, the job's
    group /slurm/uid_1/job_7 (6 GiB, 2 GiB in use of which 1 GiB is page cache; 3 CPUs), the
    mount's root unlimited (v1 writes that as 2**63 less a page)."""
    root = tmp_path / "cgroup"
    job = "slurm/uid_1/job_7"
    write(root, "memory/memory.limit_in_bytes", "9223372036854771712\n")
    write(root, "memory/memory.usage_in_bytes", f"{40 * GIB}\n")
    write(root, f"memory/{job}/memory.limit_in_bytes", f"{6 * GIB}\n")
    write(root, f"memory/{job}/memory.usage_in_bytes", f"{2 * GIB}\n")
    write(root, f"memory/{job}/memory.stat", f"cache 9\ninactive_file 5\n"
                                             f"total_inactive_file {GIB}\n")
    write(root, "cpu,cpuacct/cpu.cfs_quota_us", "-1\n")
    write(root, "cpu,cpuacct/cpu.cfs_period_us", "100000\n")
    write(root, f"cpu,cpuacct/{job}/cpu.cfs_quota_us", "300000\n")
    write(root, f"cpu,cpuacct/{job}/cpu.cfs_period_us", "100000\n")
    groups = f"5:pids:/{job}\n4:memory:/{job}\n3:cpu,cpuacct:/{job}\n1:name=systemd:/x\n0::/\n"
    return root, groups


def test_cgroup_v1_limits(tmp_path):
    root, groups = v1_tree(tmp_path)
    got = sizing.job_resources(str(root), str(proc(tmp_path, groups)))
    assert got.memory == 5 * GIB  # 6 GiB less (2 - 1) GiB in use
    assert got.memory_why == "cgroup v1 memory.limit_in_bytes 6 GiB, 1 GiB in use"
    assert got.cpus == min(3, affinity())
    if affinity() > 3:
        assert got.cpus_why == ("cgroup v1 cpu.cfs_quota_us 300000 / cpu.cfs_period_us 100000:"
                                " 3 CPUs")


def test_cgroup_v1_in_a_container_reads_the_mount_point(tmp_path):
    """A container sees its own group at the mount point: the path /proc names is not there."""
    root = tmp_path / "cgroup"
    write(root, "memory/memory.limit_in_bytes", f"{3 * GIB}\n")
    write(root, "memory/memory.usage_in_bytes", f"{GIB}\n")
    got = sizing.job_resources(str(root), str(proc(tmp_path, "4:memory:/docker/abc\n")))
    assert (got.memory, got.memory_why) == (2 * GIB, "cgroup v1 memory.limit_in_bytes 3 GiB, "
                                                     "1 GiB in use")


def test_the_host_binds_when_it_has_less_than_the_group(tmp_path):
    root = v2_tree(tmp_path)
    got = sizing.job_resources(str(root), str(proc(tmp_path, "0::/job_1/step_0\n", GIB // 2)))
    assert (got.memory, got.memory_why) == (GIB // 2, "the host's MemAvailable 0.5 GiB")


def test_nothing_readable_gives_no_memory_figure(tmp_path):
    got = sizing.job_resources(str(tmp_path / "none"), str(tmp_path / "none"))
    assert got.memory is None and got.cpus == affinity()
    assert got.describe().endswith("memory unknown (no memory figure could be read)")


def test_a_garbled_limit_file_is_not_read(tmp_path):
    root = tmp_path / "cgroup"
    write(root, "cgroup.controllers", "cpu memory\n")
    write(root, "g/cpu.max", "lots 100000\n")
    write(root, "g/memory.max", "a lot\n")
    got = sizing.job_resources(str(root), str(proc(tmp_path, "0::/g\n", 7 * GIB)))
    assert (got.cpus, got.memory) == (affinity(), 7 * GIB)


@pytest.mark.parametrize("cpus, memory_gib, asked, tasks, count, bound", [
    (8, 64.0, None, 6, 6, "6 tasks"),
    (4, 64.0, None, 189, 4, "the CPUs"),
    (128, 8.0, None, 189, 9, "the memory, about 0.81 GiB a worker"),  # 8 // 0.81 GiB
    (128, None, None, 189, 128, "the CPUs"),
    (2, 64.0, 5, 189, 5, "--workers"),
    (2, 64.0, 5, 3, 3, "3 tasks"),
])
def test_worker_count(cpus, memory_gib, asked, tasks, count, bound):
    need = 0.81 * GIB
    job = sizing.Resources(cpus, "w", None if memory_gib is None else int(memory_gib * GIB), "m")
    got, why = sizing.worker_count(job, need, tasks, asked)
    assert got == count
    assert why.startswith(f"bound by {bound}; the job has {cpus} CPUs (w), ")


def test_worker_count_refuses_what_does_not_fit():
    job = sizing.Resources(4, "w", 2 * GIB, "cgroup v2 memory.max 2 GiB, 0 GiB in use")
    with pytest.raises(ResourceError, match=r"--workers 3: 3 workers need about 2\.43 GiB of "
                                            r"memory \(about 0\.81 GiB a worker\), 2 GiB "
                                            r"available: cgroup v2 memory\.max 2 GiB, 0 GiB in "
                                            r"use; use --workers 2 or fewer"):
        sizing.worker_count(job, 0.81 * GIB, 10, 3)
    with pytest.raises(ResourceError, match=r"not enough memory for one worker"):
        sizing.worker_count(sizing.Resources(4, "w", GIB // 2, "m"), 0.81 * GIB, 10)


# -------------------------------------------------------------------------------------------
# The real process, limited by the OS

PROBE = ("from inject.exposure.sizing import job_resources; r = job_resources(); "
         "print(r.cpus, r.memory); print(r.cpus_why); print(r.memory_why)")


def probe(prefix=(), preexec_fn=None):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [os.path.dirname(os.path.dirname(os.path.abspath(__file__)))] +
        [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    out = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True,
                         text=True, check=True, env=env, preexec_fn=preexec_fn).stdout
    amounts, cpus_why, memory_why = out.splitlines()
    cpus, memory = amounts.split()
    return int(cpus), None if memory == "None" else int(memory), cpus_why, memory_why


@pytest.mark.skipif(shutil.which("taskset") is None, reason="needs taskset (util-linux)")
def test_taskset_to_one_cpu_gives_one_worker():
    cpus, _, why, _ = probe(["taskset", "-c", "0"])
    assert cpus == 1
    if (os.cpu_count() or 1) > 1:
        assert why == f"CPU affinity: 1 of {os.cpu_count()} CPUs"


@pytest.mark.skipif(shutil.which("taskset") is None, reason="needs taskset (util-linux)")
def test_taskset_to_one_cpu_gives_one_noise_thread():
    """A single CCD's noise draws (inject simulate) use the CPUs the process may run on."""
    code = ("from inject.camera.detector import ITL; from inject.scene import AmplifierNoise; "
            "print(AmplifierNoise(ITL, 1).threads)")
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(
        __file__))))
    out = subprocess.run(["taskset", "-c", "0", sys.executable, "-c", code],
                         capture_output=True, text=True, check=True, env=env).stdout
    assert out.split() == ["1"]


def test_rlimit_as_bounds_the_memory():
    limit = 3 * GIB
    free = sizing.job_resources().memory
    if free is None or free < limit + GIB:
        pytest.skip("this machine's job has less memory than the limit to test")

    def limited():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    _, memory, _, why = probe(preexec_fn=limited)
    assert memory == limit
    assert why == "RLIMIT_AS (ulimit -v) 3 GiB"


# -------------------------------------------------------------------------------------------
# A SLURM array's slice

def options(job=None, njobs=None):
    return argparse.Namespace(job=job, njobs=njobs)


ARRAY = {"SLURM_ARRAY_TASK_ID": "7", "SLURM_ARRAY_TASK_MIN": "5",
         "SLURM_ARRAY_TASK_COUNT": "4"}


def test_a_slurm_array_gives_job_and_njobs():
    from inject.cli.options import slurm_slice

    args = options()
    said = slurm_slice(args, ARRAY)
    assert (args.job, args.njobs) == (2, 4)  # tasks 5, 6, 7, 8: 7 is the third
    assert said == ("--job 2 --njobs 4 from the SLURM job array (SLURM_ARRAY_TASK_ID=7, "
                    "SLURM_ARRAY_TASK_MIN=5, SLURM_ARRAY_TASK_COUNT=4)")
    stepped = dict(ARRAY, SLURM_ARRAY_TASK_ID="9", SLURM_ARRAY_TASK_STEP="2")
    args = options()
    slurm_slice(args, stepped)  # tasks 5, 7, 9, 11
    assert (args.job, args.njobs) == (2, 4)


def test_options_given_win_over_the_array_and_no_array_changes_nothing():
    from inject.cli.options import slurm_slice

    for given in (options(0, 1), options(job=1), options(njobs=3)):
        before = vars(given).copy()
        assert slurm_slice(given, ARRAY) is None and vars(given) == before
    args = options()
    assert slurm_slice(args, {"SLURM_JOB_ID": "12"}) is None
    assert (args.job, args.njobs) == (None, None)


def test_an_uneven_array_asks_for_the_options():
    from inject.cli.options import slurm_slice

    with pytest.raises(InputError, match="give --job and --njobs"):
        slurm_slice(options(), dict(ARRAY, SLURM_ARRAY_TASK_ID="12"))  # beyond 4 tasks


def test_focalplane_in_a_slurm_array_renders_its_slice(tmp_path, monkeypatch, capsys):
    """The fourth task of an array of 2 from 3 (--array=3-4) renders the second of two
    interleaved slices of the scene's CCDs: ids 1 (R01_S00), 49 (R22_S11), 50 (R22_S12) and
    187 (R43_S22), so R22_S11 and R43_S22."""
    import yaml

    from inject.cli.main import main
    from inject.exposure import runner

    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump({
        "seed": 3, "band": "g", "exptime": 30, "pointing": {"ra": 50.0, "dec": -30.0},
        "stars": False, "cutout": {"nx": 40, "ny": 30},
        "detectors": ["R22_S12", "R01_S00", "R43_S22", "R22_S11"], "satellites": []}))
    for name, value in {"SLURM_ARRAY_TASK_ID": "4", "SLURM_ARRAY_TASK_MIN": "3",
                        "SLURM_ARRAY_TASK_COUNT": "2"}.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "out"
    assert main(["focalplane", str(scene), "-o", str(out), "--workers", "1",
                 "--no-mosaic"]) == 0
    assert sorted(runner.read_manifest(str(out))) == ["R22_S11", "R43_S22"]
    assert ("inject focalplane: --job 1 --njobs 2 from the SLURM job array (SLURM_ARRAY_TASK_ID"
            "=4, SLURM_ARRAY_TASK_MIN=3, SLURM_ARRAY_TASK_COUNT=2)") \
        in capsys.readouterr().err.splitlines()
    other = tmp_path / "other"
    assert main(["focalplane", str(scene), "-o", str(other), "--workers", "1", "--no-mosaic",
                 "--job", "0", "--njobs", "1"]) == 0  # given: the whole scene
    assert len(runner.read_manifest(str(other))) == 4
