"""A survey planned on a real Dask cluster against the process pool, side by side.

Starts a ``dask scheduler`` and ``--workers`` ``dask worker`` processes (one thread each, no
nanny) on 127.0.0.1, as a cluster's are started: their own processes and working folder,
inject imported from this checkout by PYTHONPATH. Then runs ``inject survey VISITS
--scheduler ADDRESS`` and ``inject survey VISITS --workers N`` alternately (``--pairs``
times), each into a fresh OUTDIR, and prints each run's wall time and the peak resident
memory of every process of it (sampled every half second: the workers, or the command and
its pool), and checks that the two give the same tables: the nights' Parquet files, the
manifest's digests, ``visits.csv`` and ``streaks.csv``, byte for byte.

Usage::

    python scripts/make_synthetic_survey.py -o out/month.db --nights 30 --start 2026-06-01 --seed 1
    python scripts/bench_survey_cluster.py out/month.db \
        --constellation sample_fields/constellation_starlink_gen2.yaml [--pairs 1] [-- EXTRA]

Anything after ``--`` is passed to both commands (e.g. ``--job 0 --njobs 10``).
"""
import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import psutil

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class Sampler(threading.Thread):
    """Peak resident memory (MiB) of each process of a tree, sampled every half second."""

    def __init__(self, pids):
        super().__init__(daemon=True)
        self.pids, self.peaks, self._done = list(pids), {}, threading.Event()

    def run(self):
        while not self._done.wait(0.5):
            procs = []
            for pid in self.pids:
                with contextlib.suppress(psutil.Error):
                    top = psutil.Process(pid)
                    procs += [top] + top.children(recursive=True)
            for proc in procs:
                with contextlib.suppress(psutil.Error):
                    mib = proc.memory_info().rss / 2 ** 20
                    self.peaks[proc.pid] = max(self.peaks.get(proc.pid, 0.0), mib)

    def stop(self):
        self._done.set()
        self.join()
        return self.peaks


def start_cluster(folder, workers, env):
    """The scheduler and workers' processes and the scheduler's address."""
    info = os.path.join(folder, "scheduler.json")
    elsewhere = os.path.join(folder, "elsewhere")
    os.makedirs(elsewhere)

    def start(name, *command):
        with open(os.path.join(folder, f"{name}.log"), "wb") as log:
            return subprocess.Popen([sys.executable, "-m", "dask", *command], cwd=elsewhere,
                                    env=env, stdout=log, stderr=subprocess.STDOUT,
                                    start_new_session=True)

    procs = [start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", "0",
                   "--no-dashboard", "--scheduler-file", info)]
    deadline = time.monotonic() + 120
    while not (os.path.exists(info) and os.path.getsize(info)):
        if time.monotonic() > deadline:
            raise SystemExit("the scheduler did not start (see its log in " + folder + ")")
        time.sleep(0.1)
    for k in range(1, workers + 1):
        procs.append(start(f"w{k}", "worker", "--scheduler-file", info, "--name", f"w{k}",
                           "--nworkers", "1", "--nthreads", "1", "--no-nanny", "--host",
                           "127.0.0.1", "--no-dashboard"))
    with open(info) as f:
        return procs, json.load(f)["address"]


def stop(procs):
    for proc in reversed(procs):
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)


def run(command, env, watch=()):
    """Wall seconds, the command's peak memory (MiB) and that of each other process (its
    pool's, or the processes ``watch``), largest first."""
    start = time.perf_counter()
    proc = subprocess.Popen(command, env=env, cwd=ROOT)
    sampler = Sampler([proc.pid, *watch])
    sampler.start()
    code = proc.wait()
    seconds = time.perf_counter() - start
    peaks = sampler.stop()
    if code:
        raise SystemExit(f"{' '.join(command)}: exit {code}")
    own = peaks.pop(proc.pid, 0.0)
    return seconds, own, sorted(peaks.values(), reverse=True)


def tables(outdir):
    """``{path: bytes}`` of the run's tables (the nights' files, the CSVs) and the manifests'
    per-night entries without the run's times."""
    out = {}
    for folder, _, names in os.walk(outdir):
        for name in names:
            path = os.path.join(folder, name)
            rel = os.path.relpath(path, outdir)
            if name.endswith((".parquet", ".csv")):
                with open(path, "rb") as f:
                    out[rel] = f.read()
            elif name.startswith("manifest") and name.endswith(".json"):
                with open(path) as f:
                    nights = json.load(f).get("nights", {})
                out[rel] = json.dumps(nights, sort_keys=True).encode()
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("visits")
    parser.add_argument("--constellation", required=True)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--pairs", type=int, default=1)
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    args = parser.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (ROOT, os.environ.get("PYTHONPATH")) if p))
    folder = tempfile.mkdtemp(prefix="bench-cluster-")
    procs, address = start_cluster(folder, args.workers, env)
    base = [sys.executable, "-m", "inject", "survey", os.path.abspath(args.visits),
            "--constellation", os.path.abspath(args.constellation), "--no-plots", "-q", *extra]
    try:
        from dask.distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(args.workers, timeout=120)
        worker_pids = [p.pid for p in procs[1:]]
        results = {"dask": [], "pool": []}
        for pair in range(args.pairs):
            for kind in ("dask", "pool"):
                out = os.path.join(folder, f"{kind}-{pair}")
                how = (["--scheduler", address] if kind == "dask"
                       else ["--workers", str(args.workers)])
                seconds, own, others = run(base + ["-o", out, *how], env,
                                           worker_pids if kind == "dask" else ())
                results[kind].append((seconds, own, tables(out)))
                print(f"{kind} (pair {pair + 1}): {seconds:.1f} s; peak memory: the command "
                      f"{own:.0f} MiB, its workers "
                      + ", ".join(f"{p:.0f}" for p in others[:args.workers]) + " MiB",
                      flush=True)
        same = all(d[2] == p[2] for d, p in zip(results["dask"], results["pool"]))
        print(f"tables byte-identical (dask vs pool): {same} "
              f"({len(results['dask'][0][2])} files)")
        for kind, rows in results.items():
            walls = sorted(r[0] for r in rows)
            print(f"{kind}: median {walls[len(walls) // 2]:.1f} s over {len(walls)} runs")
        return 0 if same else 1
    finally:
        stop(procs)
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
