"""Lab scale: time per flight and peak memory against the number of flights, and the refresh
after one more flight.

    nice -n 10 python benchmarks/bench_scale.py [N ...]                 the main job (default: 10 50 100)
    nice -n 10 python benchmarks/bench_scale.py --per-flight [N ...]    per-flight stages (default: 10 100 300)
    nice -n 10 python benchmarks/bench_scale.py --fleet [N ...]         fleet stages (default: 10 100 1000)
    nice -n 10 python benchmarks/bench_scale.py --learning [N ...]      learning stage (default: 10 100)

N flights: N distinct simulated flights, each a random go-to flight of 10 s with its own seed
(flight ``sim0042``: seed 1042), so each has its own log bytes and the fleet stages and the
learning use every one (the workflows use a log whose bytes repeat another's once:
``quadcore.workflows.fleet.duplicates``). Each is simulated once and cached under
$TMPDIR/quadcore_bench_scale/pool (its own $TMPDIR for a benchmark of your own: the cache is
shared), in runs of 20 that print the seconds a simulated flight took; raw folders hard-link it.

- Main job: for each N, ``python -m pipeline`` on an empty data root (a fresh process: wall time,
  peak resident memory, seconds per stage), then one more flight and the job again: the refit +
  diagnosis + history refresh.
- ``--per-flight``: only the per-flight stages (decode, then residuals, rollouts and MCAP, each
  over all flights in one run, as the main job does) in a fresh process: the part that grows
  with the fleet one flight at a time.
- ``--fleet``: only the fleet stages (fit, discovery, diagnosis, history: the main job's stage 2)
  in a fresh process on N decoded flights (the pool's decoded tables linked under N ids), then
  one more flight decoded and the fleet stages again (the refresh a new flight costs).
- ``--learning``: only the learning stage and the C export (the main job's stage 4) in a fresh
  process, on the residual tables ``--per-flight N`` left. Above the row budget
  (``QUADCORE_LEARN_ROWS``, 250,000 rows: 50 of these flights) every training run holds the same
  number of rows.

Each prints a table and, with two N or more, writes a plot of time per flight and peak memory
against N (``quadcore.report.plots.scaling``) beside the cache: scale_main.png, scale_per_flight.png,
scale_fleet.png.

Targets (issue 13): time per flight flat from 10 to 1,000 flights (ratio of the largest N's
per-flight time to the smallest's, target <= 1.5), peak memory < 4 GB, the refresh after one
more flight <= 15 s. A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from _jobs import REPO, report, run_main_job

sys.path.insert(0, str(REPO))

from quadcore.physics import decoded_store, gate  # noqa: E402
from quadcore.report import plots  # noqa: E402
from quadcore.sim import simulation  # noqa: E402
from quadcore.store import store  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "quadcore_bench_scale"
CHUNK = 20  # flights simulated per run
EVENTS = ("fixedFrequency", "estPose")


def pool_logs(n: int) -> list[Path]:
    """The logs of simulated flights 0 .. n-1 (flight ``k``: seed 1000 + k), each simulated once
    and cached: the missing ones in runs of ``CHUNK``, each run's flights moved into the pool once
    written (truth first, its log last: a log in the pool is a whole flight), so a killed run keeps
    the runs it finished."""
    pool = CACHE / "pool"
    pool.mkdir(parents=True, exist_ok=True)
    missing = [k for k in range(n) if not (pool / fid(k)).is_file()]
    for start in range(0, len(missing), CHUNK):
        ks = missing[start:start + CHUNK]
        configs = [simulation.SimConfig(kind="random", duration_s=10.0, seed=1000 + k) for k in ks]
        tmp = Path(tempfile.mkdtemp(dir=CACHE))
        t0 = time.perf_counter()
        for (log, truth), k in zip(simulation.simulate_set(tmp, configs), ks):
            truth.rename(pool / f"{fid(k)}{simulation.TRUTH_SUFFIX}")
            log.rename(pool / fid(k))
        shutil.rmtree(tmp)
        print(f"simulated {len(ks)} flights ({fid(ks[0])}..{fid(ks[-1])}): "
              f"{(time.perf_counter() - t0) / len(ks):.2f} s a flight", flush=True)
    return [pool / fid(k) for k in range(n)]


def pool_log(i: int) -> Path:
    """Simulated flight ``i`` (simulated once, cached)."""
    return pool_logs(i + 1)[i]


def simulated(n: int) -> Path:
    """A raw folder with ``n`` distinct flights: the pool's logs hard-linked (the decoder refuses
    a symbolic link out of the raw folder)."""
    raw = CACHE / f"raw{n}"
    shutil.rmtree(raw, ignore_errors=True)
    raw.mkdir()
    for i, log in enumerate(pool_logs(n)):
        os.link(log, raw / fid(i))
    return raw


def fid(i: int) -> str:
    return f"sim{i:04d}"


def child(args: list[str]) -> subprocess.CompletedProcess:
    """This script in a fresh process (its own peak memory), stdout captured."""
    return subprocess.run([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, check=False)


def peak_mb() -> float:
    """This process's peak resident memory plus its largest child's (the main job's second
    process, pipeline.run.parallel): an upper bound of the two at once."""
    return sum(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)) / 1024


class PerFlightRow(NamedTuple):
    flights: int
    decode_s: float
    tables_s: float
    s_per_flight: float
    peak_mb: float
    failed: int


class FleetRow(NamedTuple):
    flights: int
    fleet_s: float
    s_per_flight: float
    peak_mb: float
    refresh_s: float
    refresh_peak_mb: float
    ok: str


class LearningRow(NamedTuple):
    flights: int
    wall_s: float
    s_per_flight: float
    peak_mb: float
    ok: str


class MainJobRow(NamedTuple):
    flights: int
    wall_s: float
    s_per_flight: float
    per_flight_stages_s: float
    fleet_s: float
    learning_s: float
    peak_mb: float
    refresh_s: float
    refresh_wall_s: float
    exit: int


def table(header: list[str], rows: Sequence[tuple]) -> None:
    print("\n" + " ".join(f"{h:>12}" for h in header))
    for r in rows:
        print(" ".join(f"{v:>12.3f}" if isinstance(v, float) else f"{v:>12}" for v in r))


def plot(name: str, flights: list[int], series: dict[str, list[float]], mem: list[float], title: str) -> None:
    if len(flights) > 1:
        path = store.write_bytes(plots.scaling(flights, series, mem, title), CACHE / name)
        print(f"plot: {path}")


# -- per-flight stages ---------------------------------------------------------------------------

def per_flight_child(n: int) -> None:
    """In a fresh process: the per-flight stages on n flights, one run per stage (decode and the
    sufficient statistics, then the tables against the model); prints seconds."""
    import dagster as dg

    from pipeline.assets import AGAINST_MODEL, DECODE, STATISTICS
    from pipeline.resources import DataRoot, ModelConfig
    from pipeline.run import main as job, parallel

    raw, root = simulated(n), CACHE / f"root{n}"
    shutil.rmtree(root, ignore_errors=True)
    resources = {"data_root": DataRoot(root=str(root), raw=str(raw)), "model": ModelConfig()}
    ids = [fid(i) for i in range(n)]
    with dg.instance_for_test() as instance:
        t0 = time.perf_counter()
        failed = job.run_flights(instance, resources, ids, DECODE, "decode", lambda *_: None, parallel.DECODE_SPLIT_AT)
        failed.update(job.run_flights(instance, resources, ids, STATISTICS, "statistics", log=lambda *_: None))
        t1 = time.perf_counter()
        failed.update(job.run_flights(instance, resources, ids, AGAINST_MODEL, "flights", log=lambda *_: None))
        t2 = time.perf_counter()
        parallel.shutdown()  # before the peak memory: the second process's is counted once it has ended
    print(f"{t1 - t0:.3f} {t2 - t1:.3f} {len(failed)} {peak_mb():.0f}")


def per_flight_main(sizes: list[int]) -> None:
    rows: list[PerFlightRow] = []
    for n in sizes:
        simulated(n)  # outside the timed process
        decode_s, tables_s, failed, mb = child(["--per-flight-child", str(n)]).stdout.split()[-4:]
        d, t = float(decode_s), float(tables_s)
        rows.append(PerFlightRow(n, d, t, (d + t) / n, float(mb), int(failed)))
        print(f"N={n}: decode + statistics {d:.1f} s, residuals+rollouts+MCAP {t:.1f} s, {(d + t) / n:.3f} s/flight, "
              f"peak {float(mb):.0f} MB, {failed} failed", flush=True)
    table(["flights", "decode+st s", "tables s", "s/flight", "peak MB", "failed"], rows)
    first, last = rows[0], rows[-1]
    report(f"per-flight stages: s/flight at {last.flights} vs {first.flights} flights (ratio)",
           last.s_per_flight / first.s_per_flight, 1.5, "x")
    report(f"per-flight stages: peak memory at {last.flights} flights", last.peak_mb, 4096.0, "MB")
    plot("scale_per_flight.png", [r.flights for r in rows],
         {"decode + statistics": [r.decode_s / r.flights for r in rows],
          "residuals + rollouts + MCAP": [r.tables_s / r.flights for r in rows]}, [r.peak_mb for r in rows],
         "per-flight stages (bench_scale.py --per-flight)")


# -- fleet stages --------------------------------------------------------------------------------

def decoded_pool(n: int) -> Path:
    """The pool's flights 0 .. n-1 decoded once (their tables are linked under the data roots that
    use them); again when decoded by another decoder (:func:`quadcore.physics.decoded_store.decoded_from`)
    or by older code (no physics facts in the main table's footer, or facts found by another gate:
    the fleet stages would then read every table to judge it)."""
    from quadcore.logs import flight

    root = CACHE / "decoded_pool"
    for i, log in enumerate(pool_logs(n)):
        main = store.decoded_path(root, store.MAIN_EVENT, fid(i))
        if (not decoded_store.decoded_from(root, store.MAIN_EVENT, fid(i), log)
                or gate.PhysicsFacts.from_dict(decoded_store.recorded_physics_facts(main)) is None):
            decoded_store.write_decoded(root, flight.decode_flight(log))
    return root


def fleet_root(n: int) -> tuple[Path, Path]:
    """(data root with n distinct decoded flights linked from the pool, raw folder of n + 1 flights)."""
    pool, raw, root = decoded_pool(n), simulated(n + 1), CACHE / f"fleet{n}"
    shutil.rmtree(root, ignore_errors=True)
    for i in range(n):
        for event in EVENTS:
            src = store.decoded_path(pool, event, fid(i))
            if src.is_file():
                dest = store.decoded_path(root, event, fid(i))
                dest.parent.mkdir(parents=True)
                dest.symlink_to(src)
    return root, raw


def fleet_child(n: int) -> None:
    """In a fresh process: the flights' sufficient statistics (untimed: a per-flight stage), the
    fleet stages on n decoded flights, then one more flight decoded with its statistics and the
    fleet stages again. Prints each asset's seconds of the first run, then fleet seconds, peak
    MB, refresh seconds, peak MB."""
    import dagster as dg

    from pipeline.assets import DECODE, FLEET, STATISTICS
    from pipeline.resources import DataRoot, ModelConfig
    from pipeline.run import main as job

    root, raw = CACHE / f"fleet{n}", CACHE / f"raw{n + 1}"
    resources = {"data_root": DataRoot(root=str(root), raw=str(raw)), "model": ModelConfig()}
    with dg.instance_for_test() as instance:
        job.run_flights(instance, resources, [fid(i) for i in range(n)], STATISTICS, "statistics", log=lambda *_: None)
        t0 = time.perf_counter()
        first = job.materialize(FLEET, resources, instance)
        fleet_s, fleet_mb = time.perf_counter() - t0, peak_mb()
        t0 = time.perf_counter()
        job.run_flights(instance, resources, [fid(n)], [*DECODE, *STATISTICS], "decode", log=lambda *_: None)
        decode_s = time.perf_counter() - t0
        again = job.materialize(FLEET, resources, instance)
        refresh_s = time.perf_counter() - t0
        steps = _steps(instance, first.run_id), _steps(instance, again.run_id)
    ok = first.success and again.success
    print(f"one more flight: decode + statistics={decode_s:.2f} {steps[1]}")
    print(steps[0])
    print(f"{fleet_s:.3f} {fleet_mb:.0f} {refresh_s:.3f} {peak_mb():.0f} {int(ok)}")


def _steps(instance, run_id: str) -> str:
    """Each asset's seconds in a run (its step's start to end)."""
    return " ".join(f"{s.step_key}={s.end_time - s.start_time:.2f}" for s in instance.get_run_step_stats(run_id)
                    if s.end_time and s.start_time)


def fleet_main(sizes: list[int]) -> None:
    rows: list[FleetRow] = []
    for n in sizes:
        fleet_root(n)  # outside the timed process
        out = child(["--fleet-child", str(n)]).stdout.strip().splitlines()
        fleet_s, fleet_mb, refresh_s, mb, ok = (float(x) for x in out[-1].split())
        rows.append(FleetRow(n, fleet_s, fleet_s / n, fleet_mb, refresh_s, mb, "yes" if ok else "FAILED"))
        print(f"N={n}: fleet stages {fleet_s:.1f} s ({out[-2] if len(out) > 1 else ''}), peak {fleet_mb:.0f} MB; "
              f"one more flight (decode + fleet stages) {refresh_s:.1f} s ({out[-3] if len(out) > 2 else ''}), "
              f"peak {mb:.0f} MB", flush=True)
    table(["flights", "fleet s", "s/flight", "peak MB", "+1 refresh s", "+1 peak MB", "ok"], rows)
    first, last = rows[0], rows[-1]
    report(f"fleet stages: s/flight at {last.flights} vs {first.flights} flights (ratio)",
           last.s_per_flight / first.s_per_flight, 1.5, "x")
    report(f"fleet stages: peak memory at {last.flights} flights", max(last.peak_mb, last.refresh_peak_mb), 4096.0,
           "MB")
    report(f"refit + diagnosis + history after one more flight ({last.flights}+1)", last.refresh_s, 15.0)
    plot("scale_fleet.png", [r.flights for r in rows], {"fleet stages": [r.s_per_flight for r in rows]},
         [r.peak_mb for r in rows],
         "fleet stages: fit, discovery, diagnosis, history (bench_scale.py --fleet)")


# -- learning ------------------------------------------------------------------------------------

def learning_child(n: int) -> None:
    """In a fresh process: the learning stage and the C export (the main job's stage 4) on the
    residual tables ``--per-flight n`` left; prints seconds per asset, peak MB."""
    import dagster as dg

    from pipeline.assets import EXPORT, LEARNING
    from pipeline.resources import DataRoot, ModelConfig
    from pipeline.run import main as job

    resources = {"data_root": DataRoot(root=str(CACHE / f"root{n}"), raw=str(CACHE / f"raw{n}")),
                 "model": ModelConfig()}
    with dg.instance_for_test() as instance:
        t0 = time.perf_counter()
        result = job.materialize([*LEARNING, *EXPORT], resources, instance)
        wall = time.perf_counter() - t0
        steps = {s.step_key: s.end_time - s.start_time for s in instance.get_run_step_stats(result.run_id)
                 if s.end_time and s.start_time}
    print(" ".join(f"{k}={v:.1f}" for k, v in steps.items()))
    print(f"{wall:.3f} {peak_mb():.0f} {int(result.success)}")


def learning_main(sizes: list[int]) -> None:
    rows: list[LearningRow] = []
    for n in sizes:
        if not (CACHE / f"root{n}" / "residuals").is_dir():
            print(f"N={n}: no residual tables in {CACHE / f'root{n}'}: run --per-flight {n} first")
            continue
        out = child(["--learning-child", str(n)]).stdout.strip().splitlines()
        wall, mb, ok = (float(x) for x in out[-1].split())
        rows.append(LearningRow(n, wall, wall / n, mb, "yes" if ok else "FAILED"))
        print(f"N={n}: learning + C export {wall:.1f} s ({out[-2] if len(out) > 1 else ''}), peak {mb:.0f} MB",
              flush=True)
    if rows:
        table(["flights", "learning s", "s/flight", "peak MB", "ok"], rows)
        first, last = rows[0], rows[-1]
        report(f"learning: s/flight at {last.flights} vs {first.flights} flights (ratio)",
               last.s_per_flight / first.s_per_flight, 1.5, "x")
        report(f"learning: peak memory at {last.flights} flights", max(r.peak_mb for r in rows), 4096.0, "MB")
        plot("scale_learning.png", [r.flights for r in rows], {"learning + C export": [r.s_per_flight for r in rows]},
             [r.peak_mb for r in rows], "learning stage (bench_scale.py --learning)")


# -- the main job --------------------------------------------------------------------------------

def main_job(sizes: list[int]) -> None:
    rows: list[MainJobRow] = []
    for n in sizes:
        raw = simulated(n)
        root = CACHE / f"root{n}"
        shutil.rmtree(root, ignore_errors=True)
        run = run_main_job(root, raw)
        per_flight = (run.stage_s.get("1", 0.0) + run.stage_s.get("3", 0.0)) / n
        os.link(pool_log(n), raw / fid(n))
        more = run_main_job(root, raw)
        refresh = sum(more.stage_s.get(k, 0.0) for k in ("1", "2", "3"))
        rows.append(MainJobRow(n, run.wall_s, run.wall_s / n, per_flight, run.stage_s.get("2", 0.0),
                               run.stage_s.get("4", 0.0), run.peak_rss_mb, refresh, more.wall_s, run.returncode))
        print(f"N={n}: job {run.wall_s:.1f} s (exit {run.returncode}), per flight {per_flight:.3f} s, "
              f"peak {run.peak_rss_mb:.0f} MB; one more flight: stages {refresh:.1f} s, job {more.wall_s:.1f} s",
              flush=True)
    table(["flights", "job s", "job s/flight", "stages 1+3 s/fl", "fleet s", "learn s", "peak MB", "+1 refresh s",
           "+1 job s", "exit"], rows)
    first, last = rows[0], rows[-1]
    report(f"main job: s/flight at {last.flights} vs {first.flights} flights (ratio)",
           last.s_per_flight / first.s_per_flight, 1.5, "x")
    report(f"main job: peak memory at {last.flights} flights", last.peak_mb, 4096.0, "MB")
    report(f"refit + diagnosis + history after one more flight ({last.flights}+1)", last.refresh_s, 15.0)
    plot("scale_main.png", [r.flights for r in rows], {"main job": [r.s_per_flight for r in rows],
         "per-flight stages (1 + 3)": [r.per_flight_stages_s for r in rows]}, [r.peak_mb for r in rows],
         "the main job (bench_scale.py)")


def main() -> None:
    mode, sizes = (sys.argv[1], sys.argv[2:]) if sys.argv[1:2] and sys.argv[1].startswith("--") else ("", sys.argv[1:])
    n = [int(a) for a in sizes]
    if mode == "--per-flight-child":
        per_flight_child(n[0])
    elif mode == "--fleet-child":
        fleet_child(n[0])
    elif mode == "--learning-child":
        learning_child(n[0])
    elif mode == "--learning":
        learning_main(n or [10, 100])
    elif mode == "--per-flight":
        per_flight_main(n or [10, 100, 300])
    elif mode == "--fleet":
        fleet_main(n or [10, 100, 1000])
    else:
        main_job(n or [10, 50, 100])


if __name__ == "__main__":
    main()
