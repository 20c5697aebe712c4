"""Residual tables and the diagnosis on the real flights: prints figures against the targets.

    python benchmarks/bench_physics.py [LOGS_FOLDER]

Targets (2-core machine): residual tables for all 19 flights (175k rows) < 0.5 s;
`quadcore diagnose` on the 19 flights, decoding included, < 20 s.
"""

import time

from _common import best_of, logs_folder

from quadcore.identify import diagnosis
from quadcore.logs import flight
from quadcore.physics import residuals, vehicle
from quadcore.spec.model import spec_from


def main() -> None:
    folder = logs_folder()
    veh = vehicle.load()
    tables = {f.flight_id: f.tables["fixedFrequency"] for f in map(flight.decode_flight, flight.discover_logs(folder))}
    rows = sum(t.height for t in tables.values())

    t_res, _ = best_of(lambda: [residuals.residual_table(t, veh) for t in tables.values()])
    print(f"flights: {len(tables)}, rows: {rows:,}")
    print(f"residual tables (nominal model):   {t_res:7.3f} s  ({rows / t_res / 1e6:.2f} M rows/s)   "
          f"target < 0.5 s: {'MET' if t_res < 0.5 else 'NOT MET'}")

    t0 = time.perf_counter()
    decoded = {f.flight_id: f.tables["fixedFrequency"] for f in map(flight.decode_flight, flight.discover_logs(folder))}
    result = diagnosis.diagnose(decoded, spec_from(veh, []))
    t_diag = time.perf_counter() - t0
    print(f"diagnosis incl. decoding (5-fold): {t_diag:7.3f} s   target < 20 s: {'MET' if t_diag < 20 else 'NOT MET'}")
    print(f"  top candidate: {result.candidates[0].effect}")


if __name__ == "__main__":
    main()
