"""`quadcore discover` on the real flights: prints figures against the target.

    python benchmarks/bench_discover.py [LOGS_FOLDER]

Target (2-core machine): discovery on the 19 flights, decoding included, < 30 s, with the
nominal model and with the README's model (four fitted effects, one of them nonlinear).
"""

import time

from _common import logs_folder

from quadcore.identify import discovery
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from

EFFECTS = ["thrust_scale", "com_offset", "rotor_drag", "motor_lag"]


def main() -> None:
    folder = logs_folder()
    veh = vehicle.load()
    for effects in ([], EFFECTS):
        t0 = time.perf_counter()
        decoded = {f.flight_id: f.tables["fixedFrequency"]
                   for f in map(flight.decode_flight, flight.discover_logs(folder))}
        holdout = ["jana02"] if "jana02" in decoded else []
        result = discovery.discover(decoded, spec_from(veh, effects), holdout)
        dt = time.perf_counter() - t0
        rows = sum(t.height for t in decoded.values())
        label = "+".join(["nominal", *effects])
        print(f"discover on {len(decoded)} flights ({rows:,} rows), model {label}, incl. decoding: {dt:6.2f} s   "
              f"target < 30 s: {'MET' if dt < 30 else 'NOT MET'}   ({len(result.terms)} terms kept, library "
              f"{result.library_size['force']} force / {result.library_size['torque']} torque terms)")


if __name__ == "__main__":
    main()
