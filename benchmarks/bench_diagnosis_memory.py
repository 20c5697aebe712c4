"""Peak memory of the fleet diagnosis against the number of flights (issue 13: peak < 4 GB).

    nice -n 10 python benchmarks/bench_diagnosis_memory.py [N ...]     (default: 40 100 300)

For each N, in a fresh process: the diagnosis as ``model_diagnosis`` runs it
(:func:`quadcore.workflows.identify.diagnose` on every usable decoded flight under the data root,
the default held-out flight left out, 5-fold cross-validation over the others, the nominal model,
every offered candidate, the flights' stored sufficient statistics) on N flights: bench_scale's
pool of 20 simulated 10 s flights decoded once and linked under N ids. The statistics are
computed first, in that process too, untimed. Prints seconds and peak resident memory per N, and
the growth in MB a flight between consecutive N. A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import bench_scale
from _jobs import REPO

sys.path.insert(0, str(REPO))

from quadcore import workflows  # noqa: E402
from quadcore.identify import sufficient  # noqa: E402
from quadcore.store import store  # noqa: E402
from quadcore.workflows import fleet, identify  # noqa: E402


def measure(n: int) -> None:
    """In the child: the statistics, then the diagnosis; prints one JSON line."""
    root, _ = bench_scale.fleet_root(n)
    spec = workflows.resolve_model(None)
    for i in range(n):
        f = bench_scale.fid(i)
        decoded = store.read_decoded(root, store.MAIN_EVENT, f)
        sufficient.save(sufficient.compute_current(spec, f, decoded, sufficient.decoded_source(root, f) or ""), root)
    del decoded
    t0 = time.perf_counter()
    result = identify.diagnose(fleet.fleet_from_store(root, spec.vehicle), spec, [],
                               stats=sufficient.stored(root, spec))
    print(json.dumps({"flights": n, "evaluated": len(result.evaluation.eval_flights),
                      "seconds": round(time.perf_counter() - t0, 1), "peak_mb": round(bench_scale.peak_mb())}))


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        measure(int(sys.argv[2]))
        return
    sizes = [int(a) for a in sys.argv[1:]] or [40, 100, 300]
    rows = []
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--child", str(n)], stdout=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": str(REPO)}, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| flights | evaluated | diagnosis s | peak MB | growth MB/flight |")
    print("|---|---|---|---|---|")
    for prev, r in zip([None, *rows], rows):
        growth = f"{(r['peak_mb'] - prev['peak_mb']) / (r['flights'] - prev['flights']):.1f}" if prev else ""
        print(f"| {r['flights']} | {r['evaluated']} | {r['seconds']} | {r['peak_mb']} | {growth} |")


if __name__ == "__main__":
    main()
