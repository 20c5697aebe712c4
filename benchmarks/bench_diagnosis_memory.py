"""Peak memory of the fleet diagnosis against the number of flights (issue 13: peak < 4 GB).

    nice -n 10 python benchmarks/bench_diagnosis_memory.py [--without-timing] [N ...]     (default: 40 100 300)
    nice -n 10 python benchmarks/bench_diagnosis_memory.py [--without-timing] --real FOLDER

For each N, in a fresh process: the diagnosis as ``model_diagnosis`` runs it
(:func:`quadcore.workflows.identify.diagnose` on every usable decoded flight under the data root,
the default held-out flight left out, 5-fold cross-validation over the others, the nominal model,
every offered candidate, or with ``--without-timing`` those that do not re-time the rotors'
thrust (no ``motor_lag``, ``thrust_delay``: no rate level, docs/timing.md), the flights' stored
sufficient statistics) on N distinct flights: bench_scale's pool of simulated 10 s flights
(each its own seed), decoded once and linked. The statistics are computed first, in that
process too, untimed. Prints seconds and peak resident memory per N
(the process's resident peak, and the diagnosis's own: the peak of what it allocates, numpy's
arrays included, traced by tracemalloc, which the allocator's keeping of freed memory does not
blur), and the growth of the diagnosis's own peak in MB a flight between consecutive N. A
report, not a test: exits 0 either way.

``--real FOLDER``: the same on the logs in FOLDER (the 19 real flights:
/work/shared/crazyflie/logs), decoded into a temporary data root of their own. The simulated
pool's flights have white gyro noise, so the rate level keeps no unwhitened copy of their
per-block sums (``RateSums.unwhitened_blocks``, rates.bin format 3); the real flights' noise is
coloured and the copy is kept: they measure what it costs.
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import bench_scale
from _jobs import REPO

sys.path.insert(0, str(REPO))

from quadcore import effects, workflows  # noqa: E402
from quadcore.identify import diagnosis
from quadcore.identify.stats import sufficient
from quadcore.store import store  # noqa: E402
from quadcore.workflows import fleet, identify  # noqa: E402


def measure(n: int, timing: bool, real: str | None = None) -> None:
    """In the child: the statistics, then the diagnosis (without the timing candidates unless
    ``timing``) on ``n`` pool flights, or on the logs in the folder ``real`` decoded into a
    temporary data root, removed however the run ends; prints one JSON line."""
    if real is None:
        root, _ = bench_scale.fleet_root(n)
        _measure(root, [bench_scale.fid(i) for i in range(n)], timing)
        return
    with tempfile.TemporaryDirectory(prefix="bench_diagnosis_memory_") as tmp:
        root = Path(tmp)
        _measure(root, [f.flight_id for f in fleet.decode_logs([real], root)[0]], timing)


def _measure(root: Path, ids: list[str], timing: bool) -> None:
    """:func:`measure` on the flights ``ids`` of the data root ``root``."""
    spec = workflows.resolve_model(None)
    n = len(ids)
    for f in ids:
        decoded = store.read_decoded(root, store.MAIN_EVENT, f)
        sufficient.save(sufficient.compute_current(spec, f, decoded, sufficient.decoded_source(root, f) or ""), root)
    del decoded
    gc.collect()
    tracemalloc.start()
    t0 = time.perf_counter()
    seen, holdout = identify.diagnosis_flights(fleet.fleet_from_store(root, spec.vehicle), [], "the data root")
    candidates = None if timing else [n for n in effects.builtin_names() if n not in spec.effects
                                      and effects.get(n).offered and not effects.get(n).retimes_thrust]
    result = diagnosis.diagnose(seen.tables, spec, holdout, candidates, sessions=fleet.sessions_of(spec, seen.ids),
                                stats=sufficient.stored(root, spec))
    print(json.dumps({"flights": n, "evaluated": len(result.evaluation.eval_flights),
                      "seconds": round(time.perf_counter() - t0, 1), "peak_mb": round(bench_scale.peak_mb()),
                      "diagnosis_mb": round(tracemalloc.get_traced_memory()[1] / 2**20, 1)}))


def main() -> None:
    args = sys.argv[1:]
    real = args[args.index("--real") + 1] if "--real" in args else None
    if real is not None:
        args.remove("--real")
        args.remove(real)
    if args[:1] == ["--child"]:
        measure(int(args[1]), "--without-timing" not in args, real)
        return
    flags = [a for a in args if a == "--without-timing"]
    sizes = [0] if real is not None else [int(a) for a in args if a not in flags] or [40, 100, 300]
    rows = []
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--child", str(n), *flags, *(["--real", real] if real else [])],
                             stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)}, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| flights | evaluated | diagnosis s | peak MB | the diagnosis's own peak MB | its growth MB/flight |")
    print("|---|---|---|---|---|---|")
    for prev, r in zip([None, *rows], rows):
        growth = (f"{(r['diagnosis_mb'] - prev['diagnosis_mb']) / (r['flights'] - prev['flights']):.2f}"
                  if prev else "")
        print(f"| {r['flights']} | {r['evaluated']} | {r['seconds']} | {r['peak_mb']} | {r['diagnosis_mb']} "
              f"| {growth} |")


if __name__ == "__main__":
    main()
