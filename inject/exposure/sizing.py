"""What this job may use of the machine: its CPUs and its memory, and which limit binds each.

A batch job on a large node gets a share of it: a CPU affinity mask (``taskset``, SLURM's
``--cpus-per-task`` with task binding), a control group's CPU quota and memory limit (SLURM,
Kubernetes, systemd), or an address-space limit (``ulimit -v``). The machine's core count and
free memory say nothing of these, and a run sized from them starts more workers than the job
may hold and is killed. :func:`job_resources` reads each limit and keeps the smallest:

- CPUs: the affinity mask (``os.process_cpu_count`` on Python 3.13+, else
  ``os.sched_getaffinity``), further cut by the control group's CPU quota (cgroup v2
  ``cpu.max``, v1 ``cpu.cfs_quota_us / cpu.cfs_period_us``), rounded down, at least 1;
- memory: the host's ``MemAvailable``; the control group's limit less what the group uses
  (v2 ``memory.max - memory.current``, v1 ``memory.limit_in_bytes - memory.usage_in_bytes``;
  the page cache the kernel can drop, ``inactive_file``, is not counted as used); and
  ``RLIMIT_AS`` where set. ``RLIMIT_AS`` bounds each process's address space; it is taken as
  the whole job's memory, the cautious reading of a batch system that sets it for the job.

A control group's limits are those of its own folder and of every folder above it (the
smallest binds), so each is read from the group that ``/proc/self/cgroup`` names up to the
mount point.
"""
import math
import os
import resource
from dataclasses import dataclass

from inject.errors import ResourceError

#: Where the control-group file system is mounted.
CGROUP_ROOT = "/sys/fs/cgroup"
#: Where the process file system is mounted.
PROC_ROOT = "/proc"
#: cgroup v1 writes "no limit" as a huge page-aligned number (2**63 less a page); any limit at
#: or above this is none.
V1_UNLIMITED = 2**60


@dataclass(frozen=True)
class Resources:
    """The CPUs and memory this job may use, each with the limit that bounds it.

    Attributes
    ----------
    cpus : int
        CPUs the job may keep busy (at least 1).
    cpus_why : str
        What bounds ``cpus``, e.g. ``"CPU affinity: 4 of 128 CPUs"``.
    memory : int or None
        Bytes of memory the job may still take; None where nothing could be read.
    memory_why : str
        What bounds ``memory``, e.g. ``"cgroup v2 memory.max 8 GiB, 0.4 GiB in use"``.
    """

    cpus: int
    cpus_why: str
    memory: int | None
    memory_why: str

    def describe(self):
        """One line for the run's log: both amounts and why."""
        memory = "memory unknown" if self.memory is None else \
            f"{gib(self.memory)} GiB of memory"
        return f"{self.cpus} CPU{'s' if self.cpus != 1 else ''} ({self.cpus_why}), " \
               f"{memory} ({self.memory_why})"

    def record(self):
        """The amounts and their reasons as a JSON-ready dict (a run's summary)."""
        return {"cpus": self.cpus, "cpus_why": self.cpus_why, "memory_bytes": self.memory,
                "memory_why": self.memory_why}


def gib(nbytes):
    """``nbytes`` in GiB, three significant figures, as text."""
    return f"{nbytes / 2**30:.3g}"


def job_resources(cgroup_root=CGROUP_ROOT, proc_root=PROC_ROOT):
    """The CPUs and memory this process's job may use (see the module's text).

    Parameters
    ----------
    cgroup_root : str
        The control-group mount point (a folder laid out as ``/sys/fs/cgroup``: cgroup v2's
        unified tree, or v1's one folder per controller).
    proc_root : str
        The process file system: ``self/cgroup`` names this process's groups, ``meminfo``
        holds ``MemAvailable``.

    Returns
    -------
    Resources
    """
    groups = _own_groups(os.path.join(proc_root, "self", "cgroup"))
    cpus, cpus_why = affinity_cpus()
    quota = _cpu_quota(cgroup_root, groups)
    if quota is not None and max(1, math.floor(quota[0])) < cpus:
        cpus, cpus_why = max(1, math.floor(quota[0])), quota[1]
    bounds = [b for b in (_host_memory(proc_root), _cgroup_memory(cgroup_root, groups),
                          _address_space()) if b is not None]
    if not bounds:
        return Resources(cpus, cpus_why, None, "no memory figure could be read")
    memory, memory_why = min(bounds, key=lambda b: b[0])
    return Resources(cpus, cpus_why, max(0, memory), memory_why)


def worker_count(resources, need, tasks, asked=None, each="about {need} GiB a worker"):
    """How many worker processes to start, and why that many.

    Parameters
    ----------
    resources : Resources
        What the job may use (:func:`job_resources`).
    need : float
        Estimated peak bytes of one worker.
    tasks : int
        Tasks to run: more workers than tasks would idle.
    asked : int or None
        ``--workers``: taken as given if the memory holds it, refused if not. None: as many
        as the CPUs, the tasks and the memory allow.
    each : str
        How a worker's need is stated in messages (``{need}``: its GiB).

    Returns
    -------
    count : int
    why : str
        What bounds ``count``, with the job's CPUs and memory, for the run's log.

    Raises
    ------
    ResourceError
        Not even one worker fits in the memory, or ``asked`` workers do not.
    """
    each = each.format(need=f"{need / 2**30:.2g}")
    free = resources.memory
    fit = None if free is None else int(free // need)
    room = "" if free is None else f"{gib(free)} GiB available: {resources.memory_why}"
    if fit is not None and fit < 1:
        raise ResourceError(f"not enough memory for one worker ({each}, {room})")
    if asked is not None:
        count = max(1, min(asked, tasks))
        if fit is not None and count > fit:
            raise ResourceError(f"--workers {asked}: {count} workers need about "
                                f"{count * need / 2**30:.3g} GiB of memory ({each}), {room}; "
                                f"use --workers {fit} or fewer")
        why = "--workers" if count == asked else f"{tasks} task{'s' if tasks != 1 else ''}"
    else:
        bounds = [(resources.cpus, "the CPUs"),
                  (max(1, tasks), f"{tasks} task{'s' if tasks != 1 else ''}")]
        if fit is not None:
            bounds.append((fit, f"the memory, {each}"))
        count, why = min(bounds, key=lambda b: b[0])
    return count, f"bound by {why}; the job has {resources.describe()}"


def affinity_cpus():
    """``(n, why)``: the CPUs this process may run on (its affinity mask where the system has
    one, else the machine's)."""
    machine = os.cpu_count() or 1
    counter = getattr(os, "process_cpu_count", None)  # Python 3.13+
    try:
        n = counter() if counter is not None else len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = None
    if not n:
        return machine, f"the machine's {machine} CPUs"
    if n < machine:
        return n, f"CPU affinity: {n} of {machine} CPUs"
    return n, f"the machine's {n} CPUs"


def _read(path):
    """A small file's text, stripped; None if it cannot be read."""
    try:
        with open(path, encoding="ascii") as stream:
            return stream.read().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _own_groups(path):
    """``{controller: group path}`` from ``/proc/self/cgroup``: cgroup v2's unified group
    under ``""``, each v1 controller (``cpu``, ``memory``...) under its name, and each v1
    mount's folder name (``cpu,cpuacct``) under itself."""
    text = _read(path)
    groups = {}
    for line in (text or "").splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, group = parts
        if not controllers:
            groups[""] = group
            continue
        groups[controllers] = group
        for name in controllers.split(","):
            groups.setdefault(name, group)
    return groups


def _levels(cgroup_root, mount, group):
    """The folders of ``group`` under ``cgroup_root/mount`` and every one above it, up to
    the mount point, that exist (a container sees its own group as the mount point)."""
    base = os.path.join(cgroup_root, mount) if mount else cgroup_root
    parts = [p for p in (group or "/").split("/") if p]
    out = []
    for k in range(len(parts), -1, -1):
        folder = os.path.join(base, *parts[:k])
        if os.path.isdir(folder):
            out.append(folder)
    return out


def _v1_mount(cgroup_root, groups, controller):
    """``(mount folder name, group)`` of a v1 controller, or None."""
    for name, group in groups.items():
        if name and controller in name.split(",") \
                and os.path.isdir(os.path.join(cgroup_root, name)):
            return name, group
    return None


def _cpu_quota(cgroup_root, groups):
    """``(cpus, why)`` of the tightest control-group CPU quota, or None where there is none."""
    found = []
    if "" in groups and os.path.exists(os.path.join(cgroup_root, "cgroup.controllers")):
        for folder in _levels(cgroup_root, "", groups[""]):
            fields = (_read(os.path.join(folder, "cpu.max")) or "").split()
            if len(fields) == 2 and fields[0] != "max":
                with _ignoring_bad_numbers():
                    quota, period = int(fields[0]), int(fields[1])
                    found.append((quota / period, f"cgroup v2 cpu.max {quota} {period}: "
                                                  f"{quota / period:.3g} CPUs"))
    mount = _v1_mount(cgroup_root, groups, "cpu")
    if mount is not None:
        for folder in _levels(cgroup_root, *mount):
            with _ignoring_bad_numbers():
                quota = int(_read(os.path.join(folder, "cpu.cfs_quota_us")) or "-1")
                period = int(_read(os.path.join(folder, "cpu.cfs_period_us")) or "0")
                if quota > 0 and period > 0:
                    found.append((quota / period,
                                  f"cgroup v1 cpu.cfs_quota_us {quota} / cpu.cfs_period_us "
                                  f"{period}: {quota / period:.3g} CPUs"))
    return min(found, key=lambda f: f[0]) if found else None


def _host_memory(proc_root):
    """``(bytes, why)``: the host's ``MemAvailable``, or None."""
    for line in (_read(os.path.join(proc_root, "meminfo")) or "").splitlines():
        if line.startswith("MemAvailable:"):
            with _ignoring_bad_numbers():
                free = int(line.split()[1]) * 1024
                return free, f"the host's MemAvailable {gib(free)} GiB"
    return None


def _stat_field(folder, names):
    """The first of ``names`` found in ``folder/memory.stat``, bytes (0 if none)."""
    fields = {}
    for line in (_read(os.path.join(folder, "memory.stat")) or "").splitlines():
        key, _, value = line.partition(" ")
        fields[key] = value
    for name in names:
        with _ignoring_bad_numbers():
            return int(fields[name])
    return 0


def _cgroup_memory(cgroup_root, groups):
    """``(bytes, why)``: the least memory left under a control group's limit, or None."""
    found = []
    if "" in groups and os.path.exists(os.path.join(cgroup_root, "cgroup.controllers")):
        for folder in _levels(cgroup_root, "", groups[""]):
            limit = _read(os.path.join(folder, "memory.max"))
            if limit in (None, "max"):
                continue
            with _ignoring_bad_numbers():
                limit = int(limit)
                used = int(_read(os.path.join(folder, "memory.current")) or "0")
                used = max(0, used - _stat_field(folder, ("inactive_file",)))
                found.append((limit - used, f"cgroup v2 memory.max {gib(limit)} GiB, "
                                            f"{gib(used)} GiB in use"))
    mount = _v1_mount(cgroup_root, groups, "memory")
    if mount is not None:
        for folder in _levels(cgroup_root, *mount):
            with _ignoring_bad_numbers():
                limit = int(_read(os.path.join(folder, "memory.limit_in_bytes")) or "-1")
                if 0 < limit < V1_UNLIMITED:
                    used = int(_read(os.path.join(folder, "memory.usage_in_bytes")) or "0")
                    used = max(0, used - _stat_field(folder, ("total_inactive_file",
                                                              "inactive_file")))
                    found.append((limit - used, f"cgroup v1 memory.limit_in_bytes "
                                                f"{gib(limit)} GiB, {gib(used)} GiB in use"))
    return min(found, key=lambda f: f[0]) if found else None


def _address_space():
    """``(bytes, why)``: this process's ``RLIMIT_AS`` (soft), or None where unlimited."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (AttributeError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    return soft, f"RLIMIT_AS (ulimit -v) {gib(soft)} GiB"


class _ignoring_bad_numbers:
    """Skip a block whose file holds no number where one was expected (a file system in
    the middle of a change, a layout not foreseen): that limit is then not read."""

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        return kind is not None and issubclass(kind, (ValueError, KeyError, IndexError,
                                                      ZeroDivisionError))
