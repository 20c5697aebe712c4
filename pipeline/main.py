"""The main job, headless: every flight in the raw folder through every stage.

    python -m pipeline            (what ``make run`` calls)

Where the raw folder holds no logs, it first simulates a small set of flights with one
hidden effect (``DEMO_EFFECT``), so that a new user sees the whole loop: decode ->
residuals -> fitted model -> diagnosis naming the hidden effect -> error history.

It uses the persistent Dagster instance under ``$DAGSTER_HOME`` (default
``<data root>/.dagster``), so ``dagster dev`` shows these runs afterwards.
"""

import os
import sys
import time
from pathlib import Path

import dagster as dg
from dagster._core.storage.tags import (
    ASSET_PARTITION_RANGE_END_TAG,
    ASSET_PARTITION_RANGE_START_TAG,
)

from pipeline.definitions import FLEET, LEARNING, PER_FLIGHT
from pipeline.partitions import failed_flights, flights
from pipeline.resources import (
    DataRoot,
    ModelConfig,
    data_root_from_env,
    model_config_from_env,
)
from quadcore import flight, history, store

DAGSTER_YAML = """\
# Written by `python -m pipeline`. SQLite storage: keep concurrent runs low.
concurrency:
  runs:
    max_concurrent_runs: 2
telemetry:
  enabled: false
"""

# The effect hidden in the demo flights, and its true parameters (SI).
DEMO_EFFECT = {"rotor_drag": {"k_x_s_per_m": 0.12, "k_y_s_per_m": 0.12}}

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


def simulate_demo_flights(raw: Path, log=print) -> list[Path]:
    """The embedded default: six simulated flights with ``DEMO_EFFECT`` hidden in them."""
    from quadcore import simulation

    log(f"No logs in {raw}: simulating 6 demo flights with a hidden effect (see {raw}/*.truth.json) ...")
    written = simulation.simulate_set(raw, simulation.default_flights(seed=0), DEMO_EFFECT)
    return [log_path for log_path, _ in written]


def _failure_reason(result) -> str:
    """The failures' own messages, once each (without Dagster's exception class prefix)."""
    reasons = [
        e.step_failure_data.error.message.strip().splitlines()[0].split("Failure: ", 1)[-1]
        for e in result.all_events
        if e.is_step_failure and e.step_failure_data and e.step_failure_data.error
    ]
    return "; ".join(dict.fromkeys(reasons)) or "failed"


def materialize(assets, resources, instance, partition_key=None, tags=None):
    return dg.materialize(assets, partition_key=partition_key, instance=instance, resources=resources,
                          run_config=QUIET, raise_on_error=False, tags=tags)


def flight_ranges(registered: list[str], wanted: list[str]) -> list[list[str]]:
    """``wanted`` flights as runs of consecutive partitions (in the instance's order): a run
    covers one range of partitions, so a flight not wanted splits the range."""
    want, ranges, current = set(wanted), [], []
    for fid in registered:
        if fid in want:
            current.append(fid)
        elif current:
            ranges.append(current)
            current = []
    return ranges + ([current] if current else [])


def range_tags(keys: list[str]) -> dict[str, str]:
    return {ASSET_PARTITION_RANGE_START_TAG: keys[0], ASSET_PARTITION_RANGE_END_TAG: keys[-1]}


def run_flights(instance, resources: dict, flight_ids: list[str], assets, label: str, log=print) -> dict[str, str]:
    """Materialise per-flight ``assets`` for the flights, in as few runs as possible: one run per
    range of consecutive flight partitions (one run in all for a fresh data root). A flight
    that fails is retried alone, so that it fails in a run of its own and the others' runs
    succeed. Returns flight -> failure reason."""
    new = [f for f in flight_ids if not instance.has_dynamic_partition(flights.name, f)]
    if new:
        instance.add_dynamic_partitions(flights.name, new)
    registered = instance.get_dynamic_partitions(flights.name)
    failures: dict[str, str] = {}
    pending = flight_ranges(registered, flight_ids)
    while pending:
        keys = pending.pop(0)
        t0 = time.perf_counter()
        result = materialize(assets, resources, instance, tags=range_tags(keys))
        if result.success:
            log(f"  {label} {keys[0]}..{keys[-1]}: {len(keys)} flight(s) in one run ({time.perf_counter() - t0:.1f} s)"
                if len(keys) > 1 else f"  {label} {keys[0]}: ok ({time.perf_counter() - t0:.1f} s)")
            continue
        failed = failed_flights(result) if len(keys) > 1 else {keys[0]: _failure_reason(result)}
        if not failed:  # a failure not tied to a flight: retry each flight alone to find it
            pending = [[k] for k in keys] + pending
            continue
        for fid, why in failed.items():
            if len(keys) > 1:
                pending.insert(0, [fid])  # its own failed run, with its reason, in the UI
            else:
                failures[fid] = why
                log(f"  {label} {fid}: FAILED: {why}")
        pending = flight_ranges(registered, [k for k in keys if k not in failed]) + pending
    return failures


def run_fleet(instance, resources: dict, log) -> dict | None:
    """Fit, diagnose, record; returns the diagnosis (None if the run failed)."""
    t0 = time.perf_counter()
    result = materialize(FLEET, resources, instance)
    if not result.success:
        log(f"  FAILED: {_failure_reason(result)}")
        return None
    diag = store.read_json(resources["data_root"].root_path / "reports" / "diagnosis.json")
    log(f"  {diag['verdict']}\n  (one run, {time.perf_counter() - t0:.1f} s)")
    return diag


def _suggestion(diag: dict) -> str | None:
    """The top candidate if the diagnosis found one that explains something, significantly."""
    useful = [r for r in diag["candidates"] if r["useful"]]
    return useful[0]["effect"] if useful else None


def _print_history(root: Path, log) -> None:
    hist = history.read(root)
    if hist.height == 0:
        return
    log("\nError history (held-out residual RMSE, force N / torque mN m). Compare rows scored on the "
        "same flights only:")
    for row in hist.tail(8).iter_rows(named=True):
        f = " ".join(f"{row[f'force_rmse_{a}_N']:.4f}" for a in "xyz")
        t = " ".join(f"{row[f'torque_rmse_{a}_Nm'] * 1e3:.4f}" for a in "xyz")
        n = len([x for x in row["eval_flights"].split(",") if x])
        scored = f"{row['eval_mode']} on {n} flight{'s' if n != 1 else ''}"
        log(f"  {row['source']:<9} {row['model_label']:<40} {scored:<28} force {f}   torque {t}")


def run_all(data_root: DataRoot, model: ModelConfig, instance, log=print) -> int:
    raw = data_root.raw_path
    logs = flight.discover_logs(raw) if raw.is_dir() else []
    demo = not logs
    if demo:
        raw.mkdir(parents=True, exist_ok=True)
        logs = simulate_demo_flights(raw, log)
    ids = [flight.flight_id_of(p) for p in logs]
    resources = {"data_root": data_root, "model": model}
    root = data_root.root_path

    log(f"1/4 decode ({len(ids)} flights)")
    failures = run_flights(instance, resources, ids, PER_FLIGHT[:1], "decode", log)
    good = [f for f in ids if f not in failures]
    if len(good) < 2:
        log("fewer than two flights decoded: stopping before the fleet-wide stages")
        return 1
    log("2/4 fit the model, diagnose, record the error history")
    diag = run_fleet(instance, resources, log)
    if diag is None:
        return 1
    suggested = _suggestion(diag)
    if demo and suggested:
        # The demo shows the loop's next turn: add the suggested effect, refit, diagnose again.
        names = [*model.spec().effects, suggested]
        log(f"2b  demo: adding {suggested!r} to the model (as a user would in model.toml) and diagnosing again")
        model = ModelConfig(model_file=model.model_file, vehicle=model.vehicle, thrust_map=model.thrust_map,
                            effects=",".join(names), holdout=model.holdout)
        resources["model"] = model
        if run_fleet(instance, resources, log) is None:
            return 1
    log("3/4 residuals, rollouts and MCAP against the fitted model")
    failures.update(run_flights(instance, resources, good, PER_FLIGHT[1:], "flights", log))
    log("4/4 learned residual models on top of the physics (XGBoost, MLP), with baselines")
    t0 = time.perf_counter()
    result = materialize(LEARNING, resources, instance)
    if not result.success:
        log(f"  FAILED: {_failure_reason(result)}")
        return 1
    log(f"  (one run, {time.perf_counter() - t0:.1f} s)")

    log("\nOutputs:")
    log(f"  decoded Parquet    {root / 'decoded'}/<event>/flight=<id>/data.parquet")
    log(f"  residual tables    {root / 'residuals'}/flight=<id>/data.parquet")
    log(f"  rollout errors     {root / 'rollouts'}/flight=<id>/data.parquet")
    log(f"  fitted model       {root / 'models' / 'physics_model.json'}")
    log(f"  diagnosis report   {root / 'reports' / 'diagnosis.html'} (and .md, .json)")
    log(f"  learned models     {root / 'learned'}/<run>/ (model, scaler, features, manifest)")
    log(f"  learning report    {root / 'reports' / 'learning.html'} (and .md, .json)")
    log(f"  flights as MCAP    {root / 'mcap'}/<flight>.mcap (open in Foxglove)")
    log(f"  error history      {root / 'history'}/*.parquet")
    _print_history(root, log)
    if suggested and not demo:
        log(f"\nNext step: add {suggested!r} to `effects` in {model.model_file or 'model.toml'} and run again.")
    if failures:
        log(f"\n{len(failures)} flight(s) failed or were quarantined (see {root / 'quarantine'}):")
        for fid, why in failures.items():
            log(f"  {fid}: {why}")
    log("\nSee it in the UI:  make ui   (dagster dev on http://127.0.0.1:3000)")
    return 0


def main() -> int:
    data_root = data_root_from_env()
    home = ensure_dagster_home(data_root.root_path)
    print(f"Data root: {data_root.root_path}\nRaw logs:  {data_root.raw_path}\nDagster:   {home}\n")
    try:
        model = model_config_from_env()
        model.spec()  # a bad model file is a user error: say so before any work
    except (ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return run_all(data_root, model, dg.DagsterInstance.get())


if __name__ == "__main__":
    sys.exit(main())
