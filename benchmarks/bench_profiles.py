"""One-parameter nonlinear candidates from per-flight profiles (:mod:`quadcore.identify.stats.profiles`)
against the row search they replace: where each lands, its error, what each costs, and how big
the profiles are on disk.

    python benchmarks/bench_profiles.py [LOGS]     (default: the 19 real logs)

Per effect (``motor_lag``, ``thrust_delay``), fitted alone to the nominal residual of all the
flights: the row search (:func:`quadcore.identify.fit.fit_rows`, the one-parameter search on every
flight's rows: grid, Brent, profile interval) and the same search from the flights' statistics. The
difference is given in units of the search's own tolerance ``xatol`` (5e-4 of the span) and in
sample periods. Then the same on simulated flights with a hidden ``motor_lag`` of 30 ms.
"Profile" is the time to compute every flight's statistics with the profiles (once per flight,
in the ``flight_statistics`` asset), "search" the fit from them; sizes are bytes per flight in
the statistics file, and per 10 s of flight.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from _common import logs_folder

from quadcore import effects
from quadcore.identify import fit as fitlib, flightdata
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import gate, vehicle
from quadcore.sim import simulation

VEHICLE = vehicle.load()
NAMES = ("motor_lag", "thrust_delay")


def flights(folder: Path) -> dict[str, flightdata.FlightData]:
    tables = {p.name: flight.decode_flight(p).tables.get("fixedFrequency") for p in flight.discover_logs(folder)}
    good, _ = gate.usable_flights({f: t for f, t in tables.items() if t is not None}, VEHICLE)
    return {f: flightdata.flight_data(f, tables[f], VEHICLE) for f in good}


def compare(label: str, fds: dict[str, flightdata.FlightData]) -> None:
    ids = sorted(fds)
    t0 = time.perf_counter()
    stats = {f: sufficient.flight_stats(fds[f], VEHICLE, sufficient.library_layout()) for f in ids}
    t_profile = time.perf_counter() - t0
    sizes = {}
    with tempfile.TemporaryDirectory(prefix="bench_profiles_") as root:
        for f in ids:
            sufficient.save(stats[f], root)
            sizes[f] = sufficient.stats_path(root, f).stat().st_size
    seconds = sum(fds[f].state.t_s[-1] - fds[f].state.t_s[0] for f in ids)
    dt_s = float(np.median(np.diff(fds[ids[0]].state.t_s)))
    print(f"\n{label}: {len(ids)} flights, {seconds:.0f} s, {1 / dt_s:.0f} Hz; statistics with profiles computed in "
          f"{t_profile:.2f} s; file {np.mean(list(sizes.values())) / 1e3:.0f} kB per flight, "
          f"{sum(sizes.values()) / seconds * 10 / 1e3:.0f} kB per 10 s of flight")
    print(f"{'effect':>13} {'rows':>10} {'profiles':>10} {'diff/xatol':>10} {'diff/dt':>8} {'std rows':>9} "
          f"{'std prof':>9} {'t rows':>8} {'t prof':>8}")
    for name in NAMES:
        e = effects.get(name)
        (p,) = e.parameters
        t0 = time.perf_counter()
        rows = fitlib.fit_rows([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
        t_rows = time.perf_counter() - t0
        t0 = time.perf_counter()
        prof = fitlib.fit_effects([e], [stats[f] for f in ids], [stats[f].layout.target() for f in ids], VEHICLE)
        t_prof = time.perf_counter() - t0
        a, b = rows.params[name][p.name], prof.params[name][p.name]
        print(f"{name:>13} {a:10.6f} {b:10.6f} {(b - a) / (5e-4 * (p.upper - p.lower)):10.2f} {(b - a) / dt_s:8.3f} "
              f"{rows.std[name][p.name]:9.3g} {prof.std[name][p.name]:9.3g} {t_rows:7.2f}s {t_prof:7.3f}s")


def main() -> None:
    compare("real logs", flights(logs_folder()))
    with tempfile.TemporaryDirectory(prefix="bench_profiles_sim_") as folder:
        configs = [simulation.SimConfig(kind="random", duration_s=10.0, seed=s, speed_min_mps=0.8) for s in range(6)]
        simulation.simulate_set(Path(folder), configs, {"motor_lag": {"tau_s": 0.03}}, VEHICLE)
        compare("simulated, motor_lag tau_s = 0.03 hidden", flights(Path(folder)))


if __name__ == "__main__":
    main()
