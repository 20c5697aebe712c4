"""Both cores in the main job: our split (``pipeline/run/parallel.py``) against Dagster's own
multiprocess executor (issue 26).

    nice -n 10 python benchmarks/bench_executors.py [--pairs 2] [--flights 100] [--real DIR]

Two ways of running the same main job (``python -m pipeline`` on an empty data root, a fresh
process each time), in turn, A B A B ..., so that a drift of the shared machine's load hits both:

- A, as it runs today: each stage's runs in the job's process, a range of at least 40 flights
  (decoding: 100) split in two halves run at once, the second in a second process;
- B, ``QUADCORE_EXECUTOR=multiprocess``: no split of ours; each run through Dagster's multiprocess
  executor, every step in a process of its own, at most two at once (``max_concurrent: 2``).

On the 19 real flights (read in place) and on ``--flights`` distinct simulated 10 s flights
(bench_scale.py's pool, hard-linked). On the simulated fleet the learning stage is capped at
``QUADCORE_LEARN_ROWS=20000`` rows: it is one step either way, and more rows would only add the
same minutes to both.

Prints, per run: wall seconds, CPU seconds (user + system of the job and every process it
waited for), peak memory of the largest process, seconds per stage, the load average before and
after; then the medians and the ratio B/A pair by pair. A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from _common import REAL_LOGS
from _jobs import JobRun, run_main_job
from bench_scale import fid, pool_logs

CACHE = Path(tempfile.gettempdir()) / "quadcore_bench_executors"
WAYS = {"A parallel.py": {}, "B multiprocess": {"QUADCORE_EXECUTOR": "multiprocess"}}
SIM_LEARN_ROWS = "20000"


def simulated_fleet(n: int, folder: Path) -> Path:
    """A raw folder of ``n`` distinct simulated flights: the pool's logs hard-linked (a symbolic
    link out of the raw folder is refused by the decoder)."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for i, log in enumerate(pool_logs(n)):
        os.link(log, folder / fid(i))
    return folder


def load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def one(way: str, raw: Path, env: dict[str, str]) -> JobRun:
    root = CACHE / "root"
    shutil.rmtree(root, ignore_errors=True)
    before = load()
    run = run_main_job(root, raw, env={**env, **WAYS[way]})
    stages = " ".join(f"{k}:{v:.1f}" for k, v in sorted(run.stage_s.items()))
    print(f"  {way:15s} wall {run.wall_s:7.1f} s  CPU {run.cpu_s:7.1f} s  peak {run.peak_rss_mb:6.0f} MB  "
          f"stages [{stages}]  exit {run.returncode}  load {before} -> {load()}", flush=True)
    if run.returncode != 0:
        print("    " + "\n    ".join(run.output.splitlines()[-8:]))
    return run


def compare(name: str, raw: Path, pairs: int, env: dict[str, str]) -> None:
    print(f"\n{name} ({len(list(raw.iterdir()))} files in {raw})", flush=True)
    runs: dict[str, list[JobRun]] = {way: [] for way in WAYS}
    for _ in range(pairs):
        for way in WAYS:
            runs[way].append(one(way, raw, env))
    a, b = runs.values()
    print(f"  medians over {pairs} pair(s):")
    for way, rs in runs.items():
        print(f"  {way:15s} wall {statistics.median(r.wall_s for r in rs):7.1f} s  "
              f"CPU {statistics.median(r.cpu_s for r in rs):7.1f} s")
    wall = [y.wall_s / x.wall_s for x, y in zip(a, b)]
    cpu = [y.cpu_s / x.cpu_s for x, y in zip(a, b)]
    print(f"  B/A pair by pair: wall {' '.join(f'{r:.2f}' for r in wall)}; CPU {' '.join(f'{r:.2f}' for r in cpu)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--flights", type=int, default=100, help="simulated flights (0: none)")
    parser.add_argument("--real", type=Path, default=REAL_LOGS, help="the real logs (read in place)")
    args = parser.parse_args()
    CACHE.mkdir(parents=True, exist_ok=True)
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} cores, load average {load()}")
    if args.real.is_dir():
        compare("19 real flights", args.real, args.pairs, {})
    else:
        print(f"real logs not found at {args.real}: skipped")
    if args.flights:
        compare(f"{args.flights} simulated flights (QUADCORE_LEARN_ROWS={SIM_LEARN_ROWS})",
                simulated_fleet(args.flights, CACHE / f"raw{args.flights}"), args.pairs,
                {"QUADCORE_LEARN_ROWS": SIM_LEARN_ROWS})


if __name__ == "__main__":
    main()
