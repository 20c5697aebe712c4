"""The main job, headless: every flight in the raw folder through every stage.

    python -m pipeline            (what ``make run`` calls)

It uses the persistent Dagster instance under ``$DAGSTER_HOME`` (default
``<data root>/.dagster``), so ``dagster dev`` shows these runs afterwards.
"""

import os
import sys
import time
from pathlib import Path

import dagster as dg

from pipeline.definitions import PER_FLIGHT
from pipeline.partitions import flights
from pipeline.resources import DataRoot, PhysicsModel, data_root_from_env, physics_model_from_env
from quadcore import flight

DAGSTER_YAML = """\
# Written by `python -m pipeline`. SQLite storage: keep concurrent runs low.
concurrency:
  runs:
    max_concurrent_runs: 2
telemetry:
  enabled: false
"""


# Keep the console to our progress lines; Dagster's own events stay in the instance (and the UI).
QUIET = {"loggers": {"console": {"config": {"log_level": "ERROR"}}}}


def ensure_dagster_home(root: Path) -> Path:
    """Use ``$DAGSTER_HOME`` or ``<root>/.dagster``; create it with a dagster.yaml."""
    home = Path(os.environ.get("DAGSTER_HOME") or root / ".dagster").resolve()
    home.mkdir(parents=True, exist_ok=True)
    if not (home / "dagster.yaml").exists():
        (home / "dagster.yaml").write_text(DAGSTER_YAML)
    os.environ["DAGSTER_HOME"] = str(home)
    return home


def run_flights(
    instance: dg.DagsterInstance, data_root: DataRoot, physics: PhysicsModel, flight_ids: list[str], log=print
) -> dict[str, str]:
    """Materialise the per-flight assets for each flight. Returns flight -> failure reason."""
    new = [f for f in flight_ids if not instance.has_dynamic_partition(flights.name, f)]
    if new:
        instance.add_dynamic_partitions(flights.name, new)
    failures = {}
    for i, fid in enumerate(flight_ids, 1):
        t0 = time.perf_counter()
        result = dg.materialize(
            PER_FLIGHT,
            partition_key=fid,
            instance=instance,
            resources={"data_root": data_root, "physics": physics},
            run_config=QUIET,
            raise_on_error=False,
        )
        if result.success:
            log(f"[{i}/{len(flight_ids)}] {fid}: ok ({time.perf_counter() - t0:.1f} s)")
        else:
            reasons = [
                e.step_failure_data.error.message.strip().splitlines()[0]
                for e in result.all_events
                if e.is_step_failure and e.step_failure_data and e.step_failure_data.error
            ]
            failures[fid] = "; ".join(reasons) or "failed"
            log(f"[{i}/{len(flight_ids)}] {fid}: FAILED: {failures[fid]}")
    return failures


def main() -> int:
    data_root = data_root_from_env()
    home = ensure_dagster_home(data_root.root_path)
    logs = flight.discover_logs(data_root.raw_path) if data_root.raw_path.is_dir() else []
    if not logs:
        print(f"No logs in {data_root.raw_path}. Put uSD logs there or set QUADCORE_RAW_DIR.", file=sys.stderr)
        return 2
    print(f"Data root: {data_root.root_path}\nRaw logs:  {data_root.raw_path} ({len(logs)} files)\nDagster:   {home}\n")
    instance = dg.DagsterInstance.get()
    failures = run_flights(instance, data_root, physics_model_from_env(), [flight.flight_id_of(p) for p in logs])
    root = data_root.root_path
    print(f"\nDecoded Parquet: {root / 'decoded'}/<event>/flight=<id>/data.parquet")
    if failures:
        print(f"{len(failures)} flight(s) failed or were quarantined (see {root / 'quarantine'}):")
        for fid, why in failures.items():
            print(f"  {fid}: {why}")
    print("\nSee it in the UI:  make ui   (dagster dev on http://127.0.0.1:3000)")
    return 0 if len(failures) < len(logs) else 1


if __name__ == "__main__":
    sys.exit(main())
