"""Lab scale: the main job on N simulated flights, time per flight and peak memory, and the
refresh after one more flight.

    nice -n 10 python benchmarks/bench_scale.py [N ...]                 (default: 10 50 100)
    nice -n 10 python benchmarks/bench_scale.py --per-flight [N ...]    (default: 10 100 300)

N flights: a pool of 20 simulated flights (random go-to flights, 10 s each, simulated once and
cached under $TMPDIR/quadcore_bench_scale), linked under N flight ids (flight ``sim0042`` is pool
flight 42 mod 20: same bytes, its own partition and outputs). For each N, ``python -m pipeline``
on an empty data root (a fresh process: wall time, peak resident memory, seconds per stage), then
one more flight and the job again: the refit + diagnosis + history refresh. ``--per-flight`` runs
only the per-flight stages (decode, then residuals, rollouts and MCAP, each over all flights in
one run, as the main job does) in a fresh process: the time per flight and the memory of the part
that grows with the fleet one flight at a time. Prints a table (N, wall, per-flight seconds of the
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

from quadcore.sim import simulation  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "quadcore_bench_scale"


POOL = 20


def pool_log(i: int) -> Path:
    """Pool flight ``i mod POOL`` (simulating the pool once)."""
    pool = CACHE / "pool"
    pool.mkdir(parents=True, exist_ok=True)
    have = len([p for p in pool.iterdir() if not p.suffix])
    if have < POOL:
        configs = [simulation.SimConfig(kind="random", duration_s=10.0, seed=1000 + k) for k in range(have, POOL)]
        tmp = Path(tempfile.mkdtemp(dir=CACHE))
        for (log, truth), k in zip(simulation.simulate_set(tmp, configs), range(have, POOL)):
            log.rename(pool / f"sim{k:04d}")
            truth.rename(pool / f"sim{k:04d}{simulation.TRUTH_SUFFIX}")
        shutil.rmtree(tmp)
    return pool / f"sim{i % POOL:04d}"


def simulated(n: int) -> Path:
    """A raw folder with ``n`` flights (links into the pool)."""
    raw = CACHE / f"raw{n}"
    shutil.rmtree(raw, ignore_errors=True)
    raw.mkdir()
    for i in range(n):
        (raw / f"sim{i:04d}").symlink_to(pool_log(i))
    return raw


def per_flight_child(n: int) -> None:
    """In a fresh process: the per-flight stages on n flights, one run per stage; prints seconds."""
    import time

    import dagster as dg

    from pipeline import main as job
    from pipeline.definitions import PER_FLIGHT
    from pipeline.resources import DataRoot, ModelConfig

    raw, root = simulated(n), CACHE / f"root{n}"
    shutil.rmtree(root, ignore_errors=True)
    resources = {"data_root": DataRoot(root=str(root), raw=str(raw)), "model": ModelConfig()}
    ids = [f"sim{i:04d}" for i in range(n)]
    with dg.instance_for_test() as instance:
        t0 = time.perf_counter()
        failed = job.run_flights(instance, resources, ids, PER_FLIGHT[:1], "decode", log=lambda *_: None)
        t1 = time.perf_counter()
        failed.update(job.run_flights(instance, resources, ids, PER_FLIGHT[1:], "flights", log=lambda *_: None))
        t2 = time.perf_counter()
    print(f"{t1 - t0:.3f} {t2 - t1:.3f} {len(failed)}")


def per_flight_main(sizes: list[int]) -> None:
    import os
    import subprocess

    rows = []
    for n in sizes:
        simulated(n)  # outside the timed process
        proc = subprocess.Popen([sys.executable, __file__, "--child", str(n)], stdout=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONPATH": str(REPO)})
        out = proc.stdout.read() if proc.stdout else ""
        _, _, usage = os.wait4(proc.pid, 0)
        decode_s, tables_s, failed = out.split()[-3:]
        rows.append((n, float(decode_s), float(tables_s), usage.ru_maxrss / 1024, int(failed)))
        print(f"N={n}: decode {float(decode_s):.1f} s, residuals+rollouts+MCAP {float(tables_s):.1f} s, "
              f"{(float(decode_s) + float(tables_s)) / n:.3f} s/flight, peak {usage.ru_maxrss / 1024:.0f} MB, "
              f"{failed} failed", flush=True)
    per = [(d + t) / n for n, d, t, _, _ in rows]
    report(f"per-flight stages: s/flight at {rows[-1][0]} vs {rows[0][0]} flights (ratio)", per[-1] / per[0], 1.5, "x")
    report(f"per-flight stages: peak memory at {rows[-1][0]} flights", rows[-1][3], 4096.0, "MB")


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        per_flight_child(int(sys.argv[2]))
        return
    if sys.argv[1:2] == ["--per-flight"]:
        per_flight_main([int(a) for a in sys.argv[2:]] or [10, 100, 300])
        return
    sizes = [int(a) for a in sys.argv[1:]] or [10, 50, 100]
    rows = []
    for n in sizes:
        raw = simulated(n)
        root = CACHE / f"root{n}"
        shutil.rmtree(root, ignore_errors=True)
        run = run_main_job(root, raw)
        per_flight = (run.stage_s.get("1", 0.0) + run.stage_s.get("3", 0.0)) / n
        (raw / f"sim{n:04d}").symlink_to(pool_log(n))
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
