"""Lab scale: the main job on N simulated flights, time per flight and peak memory, and the
refresh after one more flight.

    nice -n 10 python benchmarks/bench_scale.py [N ...]      (default: 10 50 100)

For each N: N simulated flights (random go-to flights, 10 s each, simulated once and cached
under $TMPDIR/quadcore_bench_scale), then ``python -m pipeline`` on an empty data root (a fresh
process: wall time, peak resident memory, seconds per stage), then one more flight and the job
again: the refit + diagnosis + history refresh. Prints a table (N, wall, per-flight seconds of the
per-flight stages, fleet seconds, learning seconds, peak MB, refresh seconds) and, with two N or
more, a plot of time per flight and memory against N (scale.png beside the cache).

Targets (issue 13): per-flight time flat from 10 to 1,000 flights (ratio of the largest N's
per-flight time to the smallest's, target <= 1.5), peak memory < 4 GB, the refresh after one more
flight <= 15 s. 1,000 flights take about an hour on the 2-core machine (simulation alone ~13 min).
A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from _jobs import REPO, report, run_main_job

sys.path.insert(0, str(REPO))

from quadcore import simulation  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "quadcore_bench_scale"


def simulated(n: int) -> Path:
    """A folder with links to the first ``n`` cached simulated flights (simulating what is missing)."""
    pool = CACHE / "pool"
    pool.mkdir(parents=True, exist_ok=True)
    have = len([p for p in pool.iterdir() if not p.suffix])
    if have < n + 1:
        configs = [simulation.SimConfig(kind="random", duration_s=10.0, seed=1000 + i) for i in range(have, n + 1)]
        tmp = Path(tempfile.mkdtemp(dir=CACHE))
        for (log, truth), i in zip(simulation.simulate_set(tmp, configs), range(have, n + 1)):
            log.rename(pool / f"sim{i:04d}")
            truth.rename(pool / f"sim{i:04d}{simulation.TRUTH_SUFFIX}")
        shutil.rmtree(tmp)
    raw = CACHE / f"raw{n}"
    shutil.rmtree(raw, ignore_errors=True)
    raw.mkdir()
    for i in range(n):
        (raw / f"sim{i:04d}").symlink_to(pool / f"sim{i:04d}")
    return raw


def main() -> None:
    sizes = [int(a) for a in sys.argv[1:]] or [10, 50, 100]
    rows = []
    for n in sizes:
        raw = simulated(n)
        root = CACHE / f"root{n}"
        shutil.rmtree(root, ignore_errors=True)
        run = run_main_job(root, raw)
        per_flight = (run.stage_s.get("1", 0.0) + run.stage_s.get("3", 0.0)) / n
        (raw / f"sim{n:04d}").symlink_to(CACHE / "pool" / f"sim{n:04d}")
        more = run_main_job(root, raw)
        refresh = sum(more.stage_s.get(k, 0.0) for k in ("1", "2", "3"))
        rows.append((n, run.wall_s, per_flight, run.stage_s.get("2", 0.0), run.stage_s.get("4", 0.0),
                     run.peak_rss_mb, refresh, more.wall_s, run.returncode))
        print(f"N={n}: job {run.wall_s:.1f} s (exit {run.returncode}), per flight {per_flight:.3f} s, "
              f"peak {run.peak_rss_mb:.0f} MB; one more flight: stages {refresh:.1f} s, job {more.wall_s:.1f} s",
              flush=True)
    print(f"\n{'flights':>8} {'job s':>8} {'s/flight':>9} {'fleet s':>8} {'learn s':>8} {'peak MB':>8} "
          f"{'+1 refresh s':>13} {'+1 job s':>9}")
    for n, wall, pf, fleet, learn, mb, refresh, more_wall, _ in rows:
        print(f"{n:>8} {wall:>8.1f} {pf:>9.3f} {fleet:>8.1f} {learn:>8.1f} {mb:>8.0f} "
              f"{refresh:>13.1f} {more_wall:>9.1f}")
    largest = rows[-1]
    report(f"per-flight time, {rows[-1][0]} vs {rows[0][0]} flights (ratio)", largest[2] / rows[0][2], 1.5, "x")
    report(f"peak memory, {largest[0]} flights", largest[5], 4096.0, "MB")
    report(f"refit + diagnosis + history after one more flight ({largest[0]}+1)", largest[6], 15.0)
    if len(rows) > 1:
        _plot(rows, CACHE / "scale.png")
        print(f"plot: {CACHE / 'scale.png'}")


def _plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r[0] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5), layout="constrained")
    a.plot(n, [r[2] for r in rows], "o-")
    a.set(xscale="log", xlabel="flights", ylabel="per-flight stages [s / flight]", ylim=(0, None))
    b.plot(n, [r[5] for r in rows], "o-")
    b.set(xscale="log", xlabel="flights", ylabel="peak memory [MB]", ylim=(0, None))
    fig.savefig(path, dpi=80)


if __name__ == "__main__":
    main()
