"""Term discovery from per-flight statistics (`quadcore.identify.discovery.library_stats`): prints the
statistics' size and compute time per real flight, and discovery's combine time and peak memory
at 19 / 100 / 1,000 flights against discovery from rows.

    TMPDIR=/tmp/x nice -n 10 python benchmarks/bench_discover_stats.py [LOGS_FOLDER] [--flights 19,100,1000]
    python benchmarks/bench_discover_stats.py --root DATA_ROOT [--rows]

The second form is what ``term_discovery`` does on a data root the main job filled (the usable
flights, then discovery from their stored statistics, or with ``--rows`` from their rows), once,
for ``farm-bench``: prints its seconds in process.

The fleets past the real flights repeat the real flights' statistics under new ids (the combine's
cost depends on the number of flights and columns, not on what the matrices hold). Target (issue
#13): a refreshed discovery at 1,000 flights well inside the 15 s of a refreshed diagnosis.
"""

import argparse
import resource
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

import polars as pl
from _common import REAL_LOGS

from quadcore.identify import discovery
from quadcore.identify.discovery import library_stats
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from


class _NoRows(Mapping[str, pl.DataFrame]):
    """The flights' ids without their rows: discovery from stored statistics reads none."""

    def __init__(self, ids: list[str]):
        self._ids = ids

    def __getitem__(self, flight: str) -> pl.DataFrame:
        raise AssertionError(f"{flight}'s rows were read")

    def __contains__(self, flight: object) -> bool:
        return flight in self._ids

    def __iter__(self) -> Iterator[str]:
        return iter(self._ids)

    def __len__(self) -> int:
        return len(self._ids)


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def once(root: str, rows: bool) -> None:
    """term_discovery's work on a data root: the usable flights, then discovery (nominal model,
    cross-validated without the default held-out flight, as the asset does)."""
    from quadcore.workflows import fleet, identify

    spec = spec_from(vehicle.load(), [])
    t0 = time.perf_counter()
    result = identify.discover(fleet.fleet_from_store(root, spec.vehicle), spec, [], root=None if rows else root)
    print(f"{'rows' if rows else 'stored statistics'}: {time.perf_counter() - t0:.2f} s, {len(result.terms)} terms")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("logs", nargs="?", default=str(REAL_LOGS))
    parser.add_argument("--flights", default="19,100,1000")
    parser.add_argument("--root", help="a data root the main job filled: time term_discovery's work there, once")
    parser.add_argument("--rows", action="store_true", help="with --root: discovery from the rows")
    args = parser.parse_args()
    if args.root:
        once(args.root, args.rows)
        return
    if not Path(args.logs).is_dir():
        print(f"real Crazyflie logs not found at {args.logs}: pass a folder of logs as the first argument")
        sys.exit(0)
    spec = spec_from(vehicle.load(), [])
    decoded = {f.flight_id: f.tables["fixedFrequency"]
               for f in map(flight.decode_flight, flight.discover_logs(args.logs))}
    real = sorted(decoded)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        libs = {f: library_stats.compute(spec, f, decoded[f]) for f in real}
        per_flight = (time.perf_counter() - t0) / len(real)
        sizes = [library_stats.save(lib, root).stat().st_size for lib in libs.values()]
        width = len(next(iter(libs.values())).labels)
        print(f"per real flight: {width} columns, {sum(sizes) / len(sizes) / 1e6:.2f} MB on disk (float64 "
              f"upper triangles), computed in {per_flight:.3f} s")
        holdout = ["jana02"] if "jana02" in decoded else []
        t0 = time.perf_counter()
        rows = discovery.discover(decoded, spec, holdout)
        from_rows = time.perf_counter() - t0
        raw = {f: (root / "stats" / f"flight={f}" / "library.bin").read_bytes() for f in real}
        for n in (int(x) for x in args.flights.split(",")):
            ids = [f"{real[i % len(real)]}_{i:04d}" if n > len(real) else real[i] for i in range(n)]
            for i, f in enumerate(ids):
                path = library_stats.library_path(root, f)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(raw[real[i % len(real)]])
            held = [f for f in ids if f.startswith("jana02")][:1]
            t0 = time.perf_counter()
            result = discovery.discover(_NoRows(ids), spec, held,
                                        stored=lambda f: library_stats.load(root, f))
            dt = time.perf_counter() - t0
            line = (f"{n:5d} flights: discovery from stored statistics {dt:6.2f} s, peak RSS {_peak_mb():,.0f} MB, "
                    f"{len(result.terms)} terms")
            if n == len(real):
                same = [t.to_dict() for t in result.terms] == [t.to_dict() for t in rows.terms]
                line += f"; from rows {from_rows:.2f} s ({from_rows / dt:.0f}x), the same terms: {same}"
            print(line)


if __name__ == "__main__":
    main()
