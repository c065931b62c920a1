"""Stop latency of ``inject focalplane`` and the state it leaves, measured.

Runs ``inject focalplane`` on 4 full-size CCDs with 2 workers (a process pool) in its own
process group, sends SIGTERM to the command's process alone (as ``kill PID`` or a batch
system's first signal does; ``--signal INT --group``: Ctrl-C at a terminal, to every process of
the group) once ``--after`` CCDs are done (or ``--at`` seconds after the start), and measures:

* the stop latency: from the signal to the command's exit, and to the last process of its
  group (the workers) gone;
* the exit status (128 + the signal: 143 for SIGTERM, 130 for SIGINT, 129 for SIGHUP);
* the manifest against the files: every ``done`` row's SHA-256 equals its file's; no CCD file
  without a ``done`` row; no ``pending`` row with a file; no temporary file (``.inject-*``) and
  no ``.manifest.lock`` left.

Usage::

    python scripts/bench_stop.py [--tries 5] [--after 1 | --at 3.0] [--workers 2]
        [--signal TERM|INT|HUP] [--group] [--out out/bench_stop] [--python PYTHON]
        [--pythonpath DIR]

``--pythonpath`` runs another checkout of the package (e.g. the code before a change).
"""
import argparse
import csv
import hashlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time

SCENE = {"seed": 11, "band": "g", "zenith": 70, "exptime": 30,
         "pointing": {"ra": 50.0, "dec": -30.0, "rotation": 10.0},
         "stars": {"galactic_b": 30, "mag_limit": 23}, "cosmic_rays": 0.2,
         "detectors": ["R22_S11", "R22_S12", "R01_S00", "R43_S22"],
         "satellites": [{"height": 550, "mag": 5.0,
                         "shape": {"type": "box", "length": 7.25, "width": 2.65},
                         "track": {"x0_mm": -21.0, "y0_mm": -19.7, "angle": 0.4}}]}


def sha256(path):
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while block := stream.read(1 << 22):
            digest.update(block)
    return digest.hexdigest()


def rows(outdir):
    path = os.path.join(outdir, "manifest.csv")
    if not os.path.exists(path):
        return {}
    with open(path, newline="") as stream:
        return {row["detector"]: row for row in csv.DictReader(stream)}


def consistency(outdir):
    """What is wrong between the manifest and the files (an empty list: nothing)."""
    problems = []
    if not os.path.isdir(outdir):
        return problems  # stopped before it was made
    manifest = rows(outdir)
    names = os.listdir(outdir)
    for name, row in manifest.items():
        path = os.path.join(outdir, f"{name}.fits")
        if row["status"] == "done":
            if not os.path.exists(path):
                problems.append(f"{name}: done, no file")
            elif sha256(path) != row["sha256"]:
                problems.append(f"{name}: done, file's SHA-256 differs")
        elif os.path.exists(path):
            problems.append(f"{name}: file present, row {row['status']}")
    for name in names:
        if name.endswith(".fits") and not name.startswith(".") and name[:-5] not in manifest:
            problems.append(f"{name}: no row")
        if name.startswith(".inject-"):
            problems.append(f"{name}: temporary file left")
        if name == ".manifest.lock":
            problems.append("lock file left")
    return problems


def group_alive(pgid):
    """Whether a process of the group still runs (a zombie, dead and waiting for init to reap
    it, does not count); ``os.killpg(pgid, 0)`` where there is no /proc."""
    if not os.path.isdir("/proc"):
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        return True
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as stream:
                fields = stream.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            return True
    return False


def one(args, k):
    outdir = os.path.abspath(os.path.join(args.out, f"try{k}"))
    shutil.rmtree(outdir, ignore_errors=True)
    scene = os.path.abspath(os.path.join(args.out, "scene.json"))
    env = dict(os.environ)
    if args.pythonpath:
        env["PYTHONPATH"] = args.pythonpath
    proc = subprocess.Popen([args.python, "-m", "inject", "focalplane", scene, "-o", outdir,
                             "--workers", str(args.workers), "--no-mosaic"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            cwd=args.pythonpath or None,  # -m puts the folder first
                            start_new_session=True)
    start = time.perf_counter()
    while proc.poll() is None:
        done = sum(r["status"] == "done" for r in rows(outdir).values()) \
            if os.path.isdir(outdir) else 0
        if (args.at is not None and time.perf_counter() - start >= args.at) or \
                (args.at is None and done >= args.after):
            break
        time.sleep(0.01)
    if proc.poll() is not None:
        raise SystemExit(f"try {k}: the run ended before the signal; use a smaller --at")
    signum = getattr(signal, f"SIG{args.signal}")
    sent = time.perf_counter()
    if args.group:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    proc.wait()
    exited = time.perf_counter() - sent
    while group_alive(proc.pid) and time.perf_counter() - sent < 60:
        time.sleep(0.005)
    gone = time.perf_counter() - sent
    stderr = proc.stderr.read().decode(errors="replace").strip().splitlines()
    manifest = rows(outdir)
    result = {"exit_s": exited, "group_gone_s": gone, "status": proc.returncode,
              "signal_at_s": sent - start,
              "done": sorted(n for n, r in manifest.items() if r["status"] == "done"),
              "pending": sorted(n for n, r in manifest.items() if r["status"] == "pending"),
              "files": sorted(n for n in (os.listdir(outdir) if os.path.isdir(outdir) else ())
                              if n.endswith(".fits") and not n.startswith(".")),
              "problems": consistency(outdir), "last_line": stderr[-1] if stderr else "",
              "traceback": any("Traceback" in line for line in stderr)}
    if result["traceback"]:
        result["problems"].append("a traceback on stderr")
    print(f"try {k}: signal at {sent - start:.1f} s, exit {exited:.3f} s, all processes gone "
          f"{gone:.3f} s, status {proc.returncode}, done {result['done']}, pending "
          f"{result['pending']}, problems {result['problems'] or 'none'}", flush=True)
    return result


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tries", type=int, default=5)
    parser.add_argument("--after", type=int, default=1, help="signal once N CCDs are done")
    parser.add_argument("--at", type=float, help="signal N s after the start instead")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--signal", default="TERM", choices=("TERM", "INT", "HUP"))
    parser.add_argument("--group", action="store_true",
                        help="to every process of the group, as Ctrl-C at a terminal")
    parser.add_argument("--out", default="out/bench_stop")
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--pythonpath", help="PYTHONPATH of the command (another checkout)")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "scene.json"), "w") as stream:
        json.dump(SCENE, stream)
    results = [one(args, k) for k in range(args.tries)]
    summary = {"tries": args.tries, "workers": args.workers, "ccds": 4,
               "signal": f"SIG{args.signal}", "group": args.group,
               "exit_s_median": statistics.median(r["exit_s"] for r in results),
               "exit_s_max": max(r["exit_s"] for r in results),
               "group_gone_s_median": statistics.median(r["group_gone_s"] for r in results),
               "consistent": all(not r["problems"] for r in results), "results": results}
    sent_to = " (to the group)" if args.group else ""
    print(f"stop latency after SIG{args.signal}{sent_to}: median "
          f"{summary['exit_s_median']:.3f} s (max {summary['exit_s_max']:.3f} s) to exit, "
          f"{summary['group_gone_s_median']:.3f} s to the last process; manifest consistent "
          f"with the files: {summary['consistent']}")
    with open(os.path.join(args.out, "bench_stop.json"), "w") as stream:
        json.dump(summary, stream, indent=1)


if __name__ == "__main__":
    main()
