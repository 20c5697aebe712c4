"""The per-flight summaries behind the diagnosis's regime, flight, segment and frequency tables
(:mod:`quadcore.identify.describe.summaries`): their size and compute time on the real logs, and the
diagnosis that reads them.

    python benchmarks/bench_summaries.py [LOGS_FOLDER]
    python benchmarks/bench_summaries.py --diagnose DATA_ROOT

The first: per real flight, the sufficient statistics (:func:`quadcore.identify.stats.sufficient.flight_stats`)
and the summary computed from its rows (the nominal model's layout, as ``flight_statistics``
stores them), their times (median and largest) and the summary's size. The second: the
diagnosis as ``model_diagnosis`` runs it on a data root the main job made (nominal model, every
offered candidate, the default held-out flight left out, stored statistics); its seconds and
peak memory (run it under ``farm-bench`` against another checkout for a ratio). A report, not a
test: exits 0 either way.
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np
from _common import logs_folder

from quadcore import workflows
from quadcore.identify import flightdata
from quadcore.identify.describe import summaries
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from
from quadcore.workflows import fleet, identify


def per_flight() -> None:
    logs = sorted(p for p in logs_folder().iterdir() if p.is_file() and "." not in p.name)
    veh = vehicle.load()
    layout = sufficient.spec_layout(spec_from(veh, []))
    columns = sufficient.Layout(layout.effects, layout.sizes)  # what a summary holds: no profiles' extras
    stats_s, summary_s, sizes, seconds = [], [], [], []
    for log in logs:
        fd = flightdata.flight_data(log.name, flight.decode_flight(log).tables["fixedFrequency"], veh)
        t0 = time.perf_counter()
        sufficient.flight_stats(fd, veh, layout)
        t1 = time.perf_counter()
        s = summaries.summarize(fd, veh, sufficient.design_rows(fd, veh, columns))
        summary_s.append(time.perf_counter() - t1)
        stats_s.append(t1 - t0)
        sizes.append(sum(a.nbytes for a in s.arrays().values()) / 1e3)
        seconds.append(fd.state.t_s[-1] - fd.state.t_s[0])
    print(f"{len(logs)} flights of {min(seconds):.1f}-{max(seconds):.1f} s")
    print(f"  statistics: {np.median(stats_s) * 1e3:.0f} ms median, {max(stats_s) * 1e3:.0f} ms largest")
    print(f"  summary:    {np.median(summary_s) * 1e3:.0f} ms median, {max(summary_s) * 1e3:.0f} ms largest; "
          f"{min(sizes):.0f}-{max(sizes):.0f} kB")


def diagnose(root: str) -> None:
    spec = workflows.resolve_model(None)
    t0 = time.perf_counter()
    result = identify.diagnose(fleet.fleet_from_store(root, spec.vehicle), spec, [],
                               stats=sufficient.stored(root, spec))
    print(f"diagnosis of {len(result.evaluation.eval_flights)} evaluated flights: "
          f"{time.perf_counter() - t0:.2f} s, peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--diagnose"]:
        diagnose(sys.argv[2])
    else:
        per_flight()
