"""Shared by the benchmark scripts: where the real logs are, and a best-of timer."""

import sys
import time
from pathlib import Path

REAL_LOGS = Path(__file__).resolve().parents[1].parent / "shared" / "crazyflie" / "logs"


def logs_folder() -> Path:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else REAL_LOGS
    if not folder.is_dir():
        print(f"real Crazyflie logs not found at {folder}: pass a folder of logs as the first argument")
        sys.exit(0)
    return folder


def best_of(fn, repeats: int = 3):
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out
