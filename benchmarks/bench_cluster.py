"""The simulated fleet through the local cluster with 1, 2 and 4 Celery workers, and the main job
without the cluster beside it, in one run (issue 26): wall time and CPU seconds summed over
every process.

    nice -n 10 python benchmarks/bench_cluster.py [--flights 100] [--workers 1 2 4]

In this order, so that the ratios are of one sitting on the shared machine: the main job without
the cluster in one process (``QUADCORE_EXECUTOR=in_process``) and as it runs on one machine (our
split over two processes from 40 flights, ``pipeline/run/parallel.py``; ``--local 'one process'``
leaves it out); then for each number of workers, in the order given, a cluster
of its own (``python -m pipeline.cluster up --workers N`` in a fresh folder: PostgreSQL, Redis,
moto's S3 server, the Celery workers, the daemon, the webserver), the main job through it
(``python -m pipeline.cluster run``: runs through the daemon's queue, steps on the workers,
outputs in the S3 store), then ``down --purge``; last the one-process job again, to show how far
the machine's load drifted meanwhile. The fleet is N distinct simulated 10 s flights from
bench_scale.py's pool, hard-linked, the learning stage capped at ``QUADCORE_LEARN_ROWS=20000``
rows as in bench_executors.py. Ends with a table: each way's wall and CPU seconds and their ratios to
the first one-process job.

CPU seconds: this script makes itself the subreaper of everything it starts (``prctl
PR_SET_CHILD_SUBREAPER``), so every service, daemonised or not, stays its descendant. The CPU
of the descendants at a moment is what the ones that ended have left in this process's
``RUSAGE_CHILDREN`` plus, for each one alive, its own and its ended children's user + system
time (``/proc/PID/stat``); the job's CPU is the difference across the job. Also printed: the
steps each worker executed, and the load average before and after. A report, not a test.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from _jobs import REPO, run_main_job, stage_seconds
from bench_executors import SIM_LEARN_ROWS, load, simulated_fleet

PR_SET_CHILD_SUBREAPER = 36
TICK = os.sysconf("SC_CLK_TCK")


def descendants() -> list[int]:
    """The live processes below this one (from every process's parent in /proc)."""
    parent: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parent[int(stat.parent.name)] = int(fields[1])
    found, frontier = [], [os.getpid()]
    while frontier:
        kids = [pid for pid, ppid in parent.items() if ppid in frontier]
        found += kids
        frontier = kids
    return found


def cpu_now() -> float:
    """User + system seconds of every process this one started, ended or alive."""
    ended = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = ended.ru_utime + ended.ru_stime
    for pid in descendants():
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += sum(int(f) for f in fields[11:15]) / TICK  # utime stime cutime cstime
    return total


def reap(keep: int | None = None) -> None:
    """Wait for the ended orphans the subreaper inherited (their CPU then counts in
    RUSAGE_CHILDREN), each by its pid, all but ``keep`` (a child that subprocess waits for)."""
    for pid in descendants():
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if pid != keep and state[0] == "Z" and int(state[1]) == os.getpid():
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, os.WNOHANG)


def down(env: dict[str, str]) -> None:
    """``down --purge``, reaping the services as they end: ``down`` waits for each to be gone,
    and an unreaped child of this subreaper would look alive to it."""
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cluster", "down", "--purge"], env=env, cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while proc.poll() is None:
        reap(keep=proc.pid)
        time.sleep(0.2)
    reap()


def cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cluster", *args], env=env, cwd=REPO, text=True,
                          capture_output=True)


@dataclass
class Figure:
    """One way's main job: wall and CPU seconds (all processes), and the load average around it."""

    way: str
    wall_s: float
    cpu_s: float
    load: str
    ok: bool


def own_environment() -> dict[str, str]:
    """This process's environment without settings of the project, Dagster or AWS: each way
    gets only its own."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("QUADCORE_", "DAGSTER_", "AWS_"))}


def measure_cluster(workers: int, raw: Path, base: Path) -> Figure | None:
    home = base / f"cluster{workers}"
    shutil.rmtree(home, ignore_errors=True)
    env = own_environment()
    env.update(QUADCORE_CLUSTER_DIR=str(home), QUADCORE_AUTOMATION="off", QUADCORE_LEARN_ROWS=SIM_LEARN_ROWS)
    t0, c0 = time.perf_counter(), cpu_now()
    up = cli(env, "up", "--workers", str(workers), "--raw", str(raw))
    up_s, up_cpu = time.perf_counter() - t0, cpu_now() - c0
    if up.returncode != 0:
        print(f"  cluster, {workers} worker(s): up failed: {up.stderr.strip()[-500:]}", flush=True)
        down(env)
        return None
    before = load()
    t1, c1 = time.perf_counter(), cpu_now()
    run = cli(env, "run")
    run_s, run_cpu = time.perf_counter() - t1, cpu_now() - c1
    after = load()
    tasks = {log.stem: log.read_text(errors="replace").count("succeeded in")
             for log in sorted((home / "logs").glob("worker*.log"))}
    down(env)
    stages = " ".join(f"{k}:{v:.1f}" for k, v in sorted(stage_seconds(run.stdout).items()))
    print(f"  cluster, {workers} worker(s): up {up_s:5.1f} s ({up_cpu:5.1f} s CPU); job wall {run_s:7.1f} s, "
          f"CPU {run_cpu:7.1f} s (all processes); stages [{stages}]; steps per worker {tasks}; exit {run.returncode}; "
          f"load {before} -> {after}", flush=True)
    if run.returncode != 0:
        print("    " + "\n    ".join((run.stdout + run.stderr).splitlines()[-8:]))
    return Figure(f"cluster, {workers} worker(s)", run_s, run_cpu, f"{before} -> {after}", run.returncode == 0)


def measure_local(way: str, extra: dict[str, str], raw: Path, base: Path) -> Figure:
    """The main job on this machine without the cluster (``python -m pipeline``, no service)."""
    root = base / "local"
    shutil.rmtree(root, ignore_errors=True)
    env = own_environment()
    before = load()
    run = run_main_job(root, raw, env={**env, "QUADCORE_LEARN_ROWS": SIM_LEARN_ROWS, **extra})
    shutil.rmtree(root, ignore_errors=True)
    after = load()
    stages = " ".join(f"{k}:{v:.1f}" for k, v in sorted(run.stage_s.items()))
    print(f"  {way}: job wall {run.wall_s:7.1f} s, CPU {run.cpu_s:7.1f} s; stages [{stages}]; exit {run.returncode}; "
          f"load {before} -> {after}", flush=True)
    if run.returncode != 0:
        print("    " + "\n    ".join(run.output.splitlines()[-8:]))
    return Figure(way, run.wall_s, run.cpu_s, f"{before} -> {after}", run.returncode == 0)


# The main job without the cluster: as it runs on one machine (our split over two processes from
# 40 flights, pipeline/run/parallel.py) and in one process only.
LOCAL = {"one machine (parallel.py)": {}, "one process": {"QUADCORE_EXECUTOR": "in_process"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--flights", type=int, default=100)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4], help="clusters, in this order")
    parser.add_argument("--local", nargs="+", choices=list(LOCAL), default=list(LOCAL),
                        help="the ways without the cluster to run first ('one process' always runs)")
    args = parser.parse_args()
    if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        print("prctl(PR_SET_CHILD_SUBREAPER) failed: the CPU of daemonised services would be lost")
        return
    # a folder the postgres user can enter (PostgreSQL runs as that user when this runs as root)
    base = Path(tempfile.mkdtemp(prefix="quadcore-bench-cluster-", dir="/tmp"))
    base.chmod(0o755)
    raw = simulated_fleet(args.flights, base / "raw")
    print(f"{args.flights} simulated flights, workers {args.workers}, {os.cpu_count()} cores, "
          f"load average {load()}", flush=True)
    figures: list[Figure] = []
    try:
        ways = ["one process", *(way for way in args.local if way != "one process")]
        figures += [measure_local(way, LOCAL[way], raw, base) for way in ways]
        figures += [f for n in args.workers if (f := measure_cluster(n, raw, base)) is not None]
        # the one-process job again: how far the shared machine's load drifted over the run
        figures.append(measure_local("one process, again", LOCAL["one process"], raw, base))
    finally:
        shutil.rmtree(base, ignore_errors=True)
    summary(figures)


def summary(figures: list[Figure]) -> None:
    """Each way's figures and its ratios to the first one-process job."""
    ref = next(f for f in figures if f.way == "one process")
    print(f"\n  {'way':28s} {'wall s':>8s} {'CPU s':>8s} {'wall/one':>9s} {'CPU/one':>8s}  load average (1/5/15 min)")
    for f in figures:
        print(f"  {f.way:28s} {f.wall_s:8.1f} {f.cpu_s:8.1f} {f.wall_s / ref.wall_s:9.2f} {f.cpu_s / ref.cpu_s:8.2f}"
              f"  {f.load}{'' if f.ok else '  (FAILED)'}")


if __name__ == "__main__":
    main()
