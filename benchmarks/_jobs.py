"""Shared by the pipeline benchmarks: run ``python -m pipeline`` as a user would (a fresh process),
with its wall time, its peak memory and the seconds its stage lines report."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass
class JobRun:
    wall_s: float
    peak_rss_mb: float
    returncode: int
    output: str
    stage_s: dict[str, float] = field(default_factory=dict)  # stage number ("1".."4") -> seconds of its runs
    cpu_s: float = 0.0  # user + system seconds of the job and every process it waited for (its second process, steps)


def run_main_job(data_root: Path, raw: Path | None, cwd: Path | None = None, env: dict | None = None) -> JobRun:
    """``python -m pipeline`` on ``data_root`` (raw logs from ``raw``; None: the demo)."""
    environ = {**os.environ, "QUADCORE_DATA_ROOT": str(data_root), "PYTHONPATH": str(REPO), **(env or {})}
    environ.pop("DAGSTER_HOME", None)
    if raw is not None:
        environ["QUADCORE_RAW_DIR"] = str(raw)
    t0 = time.perf_counter()
    demo = ["--demo"] if raw is None else []  # the demo runs when asked, in the root it is given
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *demo], cwd=cwd or REPO, env=environ,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    return JobRun(wall, usage.ru_maxrss / 1024, os.waitstatus_to_exitcode(status), out, stage_seconds(out),
                  usage.ru_utime + usage.ru_stime)


def stage_seconds(output: str) -> dict[str, float]:
    """Seconds per stage from the job's lines: each ``(... 1.2 s)`` counted for the stage above it."""
    stages: dict[str, float] = {}
    stage = None
    for line in output.splitlines():
        head = re.match(r"(\d)(?:/4|b)\s", line)
        if head:
            stage = head.group(1)
            stages.setdefault(stage, 0.0)
        for seconds in re.findall(r"\(([\d.]+) s\)|one run, ([\d.]+) s", line):
            stages[stage or "?"] = stages.get(stage or "?", 0.0) + float(seconds[0] or seconds[1])
    return stages


def report(name: str, figure: float, target: float, unit: str = "s", lower_is_better: bool = True) -> None:
    ratio = target / figure if lower_is_better and figure else figure / target if target else float("nan")
    met = "meets" if (figure <= target if lower_is_better else figure >= target) else "MISSES"
    print(f"{name:<58} {figure:10.2f} {unit:<4} target {'<=' if lower_is_better else '>='} {target:g} {unit:<4}"
          f" ratio {ratio:5.2f}  {met}")
