"""The main job, headless: every flight in the raw folder through every stage.

    python -m pipeline            (what ``make run`` calls)
    python -m pipeline --demo     (``make demo``)

The demo simulates a small set of flights with one hidden effect (``DEMO_EFFECT``) into a data
root of its own (``data/demo``), so that a new user sees the whole loop: decode -> residuals ->
fitted model -> diagnosis naming the hidden effect -> error history. It runs when asked, or on
the default data root while ``data/raw`` holds no logs (``pipeline.resources.choose_demo``).
Anywhere else a missing or empty raw folder is an error, never a reason to simulate; and a data
root never holds simulated and real flights together unless ``QUADCORE_ALLOW_SIMULATED=1``.

It uses the persistent Dagster instance under ``$DAGSTER_HOME`` (default
``<data root>/.dagster``), so ``make ui`` shows these runs afterwards.
"""

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import dagster as dg

from pipeline.assets import AGAINST_MODEL, DECODE, EXPORT, FLEET, LEARNING, STATISTICS
from pipeline.assets.decode import MAIN_EVENT
from pipeline.assets.model import current_model
from pipeline.cluster import launch
from pipeline.freshness import model_version
from pipeline.partitions import flights
from pipeline.resources import (
    DEFAULT_ROOT,
    DataRoot,
    ModelConfig,
    SettingError,
    allow_simulated,
    choose_demo,
    data_root_from_env,
    executor_from_env,
    learn_row_budget,
    make_command,
    model_config_from_env,
    model_file_from_env,
    retrain_cron,
)
from pipeline.run import parallel
from pipeline.run.instance import ensure_dagster_home, unsynced_event_log
from pipeline.run.parallel import failure_reason, halves, log_sizes, materialize, materialize_ranges
from quadcore.identify.discovery import library_stats
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import decoded_store
from quadcore.store import ownership, safewrite, store
from quadcore.workflows import identify, learn, summary
from quadcore.workflows.demo import (
    MixedFlightsError,
    check_flight_kinds,
    simulate_demo_flights,
    write_demo_model_file,
)

# QUADCORE_RECOMPUTE=1: every stage for every flight, even where its outputs are up to date.
RECOMPUTE = os.environ.get("QUADCORE_RECOMPUTE", "").lower() in ("1", "true", "yes", "on")

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


def run_flights(instance, resources: dict, flight_ids: list[str], assets, label: str, log=print,
                split_at: int | None = None) -> dict[str, str]:
    """Materialise per-flight ``assets`` for the flights, in as few runs as possible: one run per
    range of consecutive flight partitions (one run in all for a fresh data root), a long range
    as two runs at once, one per core (:func:`pipeline.run.parallel.halves`, from ``split_at``
    flights). A flight that fails
    is retried alone, so that it fails in a run of its own and the others' runs succeed.
    Returns flight -> failure reason."""
    new = [f for f in flight_ids if not instance.has_dynamic_partition(flights.name, f)]
    if new:
        instance.add_dynamic_partitions(flights.name, new)
    registered = instance.get_dynamic_partitions(flights.name)
    failures: dict[str, str] = {}
    pending = flight_ranges(registered, flight_ids)
    while pending:
        keys = pending.pop(0)
        batch = halves(keys, log_sizes(resources["data_root"], keys), split_at)
        for keys, outcome in zip(batch, materialize_ranges(assets, resources, instance, batch)):
            if outcome.success:
                log(f"  {label} {keys[0]}..{keys[-1]}: {len(keys)} flight(s) in one run ({outcome.seconds:.1f} s)"
                    if len(keys) > 1 else f"  {label} {keys[0]}: ok ({outcome.seconds:.1f} s)")
                continue
            failed = outcome.failed if len(keys) > 1 else {keys[0]: outcome.reason}
            if not failed:  # a failure not tied to a flight: retry each flight alone to find it
                pending = [[k] for k in keys] + pending
                continue
            for fid, why in failed.items():
                if len(keys) > 1:
                    pending.insert(0, [fid])  # its own failed run, with its reason, in the UI
                else:
                    failures[fid] = reason_of(fid, why)
                    log(f"  {label} {fid}: skipped: {failures[fid]}")
            pending = flight_ranges(registered, [k for k in keys if k not in failed]) + pending
    return failures


def reason_of(fid: str, why: str) -> str:
    """A failure's reason without the flight's name in front (the line names it once)."""
    while why.startswith(f"{fid}: "):
        why = why[len(fid) + 2:]
    return why


def run_fleet(instance, resources: dict, log) -> dict | None:
    """Fit, diagnose, record; returns the diagnosis (None if the run failed)."""
    t0 = time.perf_counter()
    result = materialize(FLEET, resources, instance)
    if not result.success:
        log(f"  FAILED: {failure_reason(result)}")
        return None
    root = resources["data_root"].root_path
    diag = store.read_json(store.diagnosis_path(root))
    log(f"  {diag['verdict']}")
    if store.discovery_path(root).is_file():  # term_discovery: what no library effect has
        terms = store.read_json(store.discovery_path(root))["terms"]
        log("  Discovered terms: " + ("; ".join(t["formula"] for t in terms[:3]) if terms else "none kept"))
    log(f"  (one run, {time.perf_counter() - t0:.1f} s)")
    return diag


def _materialized(instance, asset: str) -> set[str]:
    return instance.get_materialized_partitions(dg.AssetKey(asset))


def to_decode(instance, data_root: DataRoot, ids: list[str]) -> list[str]:
    """Flights whose decoded tables are missing, or older than their log (another SHA-256)."""
    done = _materialized(instance, "decoded_flight")
    return [fid for fid in ids if fid not in done or not _decoded_from_current_log(data_root, fid)]


def _decoded_from_current_log(data_root: DataRoot, fid: str) -> bool:
    try:
        log_path = data_root.raw_log(fid)
    except (OSError, ValueError):
        return False  # unreadable or unsafe: decode it, and let decoding say why it fails
    return decoded_store.decoded_from(data_root.root_path, MAIN_EVENT, fid, log_path)


def to_recompute(
    instance, data_root: DataRoot, model: ModelConfig, ids: list[str], decoded_now: list[str]
) -> list[str]:
    """Flights whose residual table, rollouts or MCAP are missing, or were computed from an
    older decode or against another model than the current one (a refit that moved a parameter)."""
    current = model_version(current_model(data_root, model).to_dict())
    done = set.intersection(*(_materialized(instance, a.key.to_user_string()) for a in AGAINST_MODEL))
    out = []
    for fid in ids:
        path = store.table_path(data_root.root_path, "residuals", fid)
        if fid in decoded_now or fid not in done or not path.is_file():
            out.append(fid)
            continue
        if model_version(store.read_metadata(path).get("model")) != current:
            out.append(fid)
    return out


def to_restat(data_root: DataRoot, model: ModelConfig, ids: list[str], decoded_now: list[str]) -> list[str]:
    """Flights whose sufficient or discovery statistics are missing, or older than their decode, or made for
    another vehicle, thrust map or effect library than the model file gives now."""
    spec = model.spec()
    current, library = sufficient.stored(data_root.root_path, spec), library_stats.stored(data_root.root_path, spec)
    return [f for f in ids if f in decoded_now or current(f) is None or library(f) is None]


def fleet_is_stale(root: Path, model: ModelConfig, changed: list[str]) -> bool:
    """Whether to refit and re-diagnose: flights were (re)decoded or their statistics recomputed
    (``changed``), or the fitted model or the diagnosis is missing, or the fit was made for another
    model spec than the model file's now."""
    if changed or not store.physics_model_path(root).is_file() or not store.diagnosis_path(root).is_file():
        return True
    return identify.fit_is_stale(root, model.spec())


class InputError(Exception):
    """The data root or the raw folder cannot be used as given (one line with the fix, exit 2)."""


def check_inputs(data_root: DataRoot, demo: bool = False) -> str:
    """Before anything is written: the raw folder exists and holds logs (the demo's may be
    empty: it simulates into it), the data root is one the project made or may adopt
    (:func:`quadcore.store.ownership.claim`), and its flights would not mix simulated and real
    ones (:func:`quadcore.workflows.demo.check_flight_kinds`). Returns a note ('' if none);
    :class:`InputError` with the reason and the fix."""
    raw, root = data_root.raw_path, data_root.root_path
    if not demo and not raw.is_dir():
        raise InputError(f"the raw log folder {raw} does not exist: check QUADCORE_RAW_DIR (the demo runs with "
                         "`make demo`)")
    logs = flight.discover_logs(raw) if raw.is_dir() else []
    if not demo and not logs:
        raise InputError(f"no logs in the raw log folder {raw}: put your flight logs there, or point QUADCORE_RAW_DIR "
                         "at them (the demo runs with `make demo`)")
    try:
        note = ownership.claim(root, "the data root")
        check_flight_kinds(root, logs, allow_simulated(), demo)
    except (ownership.ForeignFolderError, MixedFlightsError) as exc:
        raise InputError(str(exc)) from None
    return note


def run_all(data_root: DataRoot, model: ModelConfig, instance, log=print, demo: bool = False) -> int:
    """Every stage on every flight, holding the data root's lock (a second job on the same data
    root waits for this one), after sweeping what killed runs left behind. 2 when the inputs
    cannot be used (:func:`check_inputs`)."""
    try:
        note = check_inputs(data_root, demo)
    except InputError as exc:
        log(f"error: {exc}")
        return 2
    if note:
        log(f"note: {note}")
    with safewrite.data_root_lock(data_root.root_path, on_wait=log):
        swept = safewrite.sweep_stale(data_root.root_path)
        if swept:
            log(f"removed {len(swept)} temp file(s) or staging folder(s) left by killed runs")
        try:
            return _run_stages(data_root, model, instance, log, demo)
        finally:
            parallel.shutdown()


def _flight_ids(data_root: DataRoot, instance, log, demo: bool) -> list[str]:
    """The raw folder's flights (the demo's: simulated where it holds none yet), each
    registered as a flight partition."""
    raw = data_root.raw_path
    logs = flight.discover_logs(raw) if raw.is_dir() else []
    if demo and not logs:
        raw.mkdir(parents=True, exist_ok=True)
        logs = simulate_demo_flights(raw, log)
        ownership.record_flights_kind(data_root.root_path, "simulated")
    by_id, collisions = flight.flight_ids(logs)
    for note in collisions:
        log(f"flight id collision: {note}")
    ids = list(by_id)
    new = [f for f in ids if not instance.has_dynamic_partition(flights.name, f)]
    if new:
        instance.add_dynamic_partitions(flights.name, new)
    return ids


def _decode_stage(instance, resources: dict, ids: list[str], log) -> tuple[list[str], dict[str, str], list[str]]:
    """1/4: the flights to decode (all with QUADCORE_RECOMPUTE), decoded; returns them, the
    failures (flight -> reason) and the flights decoded now or before."""
    data_root = resources["data_root"]
    decode = ids if RECOMPUTE else to_decode(instance, data_root, ids)
    log(f"1/4 decode ({len(decode)} of {len(ids)} flights; the others are up to date)")
    failures = run_flights(instance, resources, decode, DECODE, "decode", log, parallel.DECODE_SPLIT_AT) \
        if decode else {}
    decoded = _materialized(instance, "decoded_flight")
    return decode, failures, [f for f in ids if f not in failures and f in decoded]


def _fleet_stage(instance, resources: dict, changed: list[str], log) -> tuple[dict | None, bool]:
    """2/4: refit and re-diagnose when the fleet is stale (``changed``: the flights decoded or
    whose statistics were recomputed in this job); returns the diagnosis (None if the run failed)
    and whether it was refitted."""
    root, model = resources["data_root"].root_path, resources["model"]
    refit = RECOMPUTE or fleet_is_stale(root, model, changed)
    if refit:
        log("2/4 fit the model, diagnose, record the error history")
        return run_fleet(instance, resources, log), refit
    diag = store.read_json(store.diagnosis_path(root))
    log(f"2/4 fitted model and diagnosis: up to date (no flight changed)\n  {diag['verdict']}")
    return diag, refit


def _demo_turn(instance, resources: dict, suggested: str, log) -> bool:
    """2b (the demo): the loop's next turn, the suggested effect added to the model (the demo's
    own model file, which later runs use; ``resources["model"]`` then names it) and the fleet
    fitted and diagnosed again; False if that run failed."""
    root, model = resources["data_root"].root_path, resources["model"]
    names = [*model.spec().effects, suggested]
    own = write_demo_model_file(root, model.model_file, names)
    log(f"2b  demo: adding {suggested!r} to the model, as a user would in model.toml (the demo's own "
        f"{own}, which later runs use), and diagnosing again")
    resources["model"] = ModelConfig(model_file=str(own), vehicle=model.vehicle, thrust_map=model.thrust_map,
                                     holdout=model.holdout, sessions_file=model.sessions_file)
    return run_fleet(instance, resources, log) is not None


def _against_model_stage(instance, resources: dict, good: list[str], decode: list[str], log) -> dict[str, str]:
    """3/4: residuals, rollouts and MCAP of the flights whose outputs are missing or stale;
    returns the failures."""
    stale = good if RECOMPUTE else to_recompute(instance, resources["data_root"], resources["model"], good, decode)
    log(f"3/4 residuals, rollouts and MCAP against the fitted model ({len(stale)} of {len(good)} flights; "
        "the others are up to date)")
    return run_flights(instance, resources, stale, AGAINST_MODEL, "flights", log) if stale else {}


def _learning_stage(instance, resources: dict, refit: bool, log) -> bool:
    """4/4: the learned residual models and the C model when learning is stale; else the C
    model alone after a refit. False if training failed."""
    root = resources["data_root"].root_path
    why = "recompute requested" if RECOMPUTE else learn.learning_is_stale(root)
    if why:
        log(f"4/4 learned residual models on top of the physics (XGBoost, MLP), with baselines, and the model "
            f"as C (training because: {why})")
        t0 = time.perf_counter()
        result = materialize([*LEARNING, *EXPORT], resources, instance)
        if not result.success:
            log(f"  FAILED: {failure_reason(result)}")
            return False
        _left_out_of_c(result, log)
        log(f"  (one run, {time.perf_counter() - t0:.1f} s)")
        return True
    log(f"4/4 learned models: trained on this physics model; new flights are learned by the schedule "
        f"nightly_retrain_learned_models ({retrain_cron()} UTC, QUADCORE_RETRAIN_CRON; `{make_command('ui')}` runs "
        "it) or by materialising learning_features")
    if refit:  # the C model carries the refitted parameters
        result = materialize(EXPORT, resources, instance)
        log(f"  the model as C, with the refitted parameters: {'ok' if result.success else 'FAILED'}"
            + ("" if result.success else f": {failure_reason(result)}"))
        if result.success:
            _left_out_of_c(result, log)
    return True


def _left_out_of_c(result, log) -> None:
    """The effects the C model leaves out (no C form), with why, from ``exported_model``'s metadata."""
    for mat in result.asset_materializations_for_node("exported_model"):
        entry = mat.metadata.get("left_out")
        text = str(entry.value) if entry is not None else ""
        for line in text.splitlines():
            if line.startswith("- "):
                log(f"  left out of the C model: {line[2:].replace('**', '')}")


def _closing(root: Path, model: ModelConfig, suggested: str | None, demo: bool, failures: dict[str, str],
             log) -> None:
    """Where the outputs are, the error history, the next step and the flights that failed."""
    for line in [*summary.outputs(root), *summary.error_history(root)]:
        log(line)
    if suggested and not demo:
        log(f"\nNext step: {identify.next_step(suggested, model.model_file, make_command('run'))}")
    if failures:  # each was said once, with its reason, where it was skipped
        named = ", ".join(list(failures)[:5]) + (", ..." if len(failures) > 5 else "")
        log(f"\n{len(failures)} flight(s) skipped ({named}): the reasons are above; quarantined logs in "
            f"{root / 'quarantine'}, the runs in the UI")
    port = int(os.environ.get("PORT", "3000"))
    log(f"\nSee it in the UI:  {make_command('ui', port)}   (Dagster UI on http://127.0.0.1:{port})")


def _run_stages(data_root: DataRoot, model: ModelConfig, instance, log, demo: bool) -> int:
    """The four stages in order, each materialising what is missing or stale; 1 when a stage
    that the next ones need failed."""
    ids = _flight_ids(data_root, instance, log, demo)
    resources: dict[str, Any] = {"data_root": data_root, "model": model}
    decode, failures, good = _decode_stage(instance, resources, ids, log)
    if len(good) < 2:
        log("fewer than two flights decoded: stopping before the fleet-wide stages")
        return 1
    restat = good if RECOMPUTE else to_restat(data_root, model, good, decode)
    if restat:
        failures.update(run_flights(instance, resources, restat, STATISTICS, "statistics", log))
    good = [f for f in good if f not in failures]  # a flight skipped once is not tried again in this job
    # the fit is made from the statistics: new ones (a new decode, or new code) mean a refit
    diag, refit = _fleet_stage(instance, resources, sorted({*decode, *restat}), log)
    if diag is None:
        return 1
    suggested = identify.suggestion(diag)
    if demo and suggested and not _demo_turn(instance, resources, suggested, log):
        return 1
    failures.update(_against_model_stage(instance, resources, good, decode, log))
    if not _learning_stage(instance, resources, refit, log):
        return 1
    _closing(data_root.root_path, resources["model"], suggested, demo, failures, log)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline", description="The main job: every flight of the "
                                     "raw folder through every stage.")
    parser.add_argument("--demo", action="store_true", help="the demo: six simulated flights with a hidden effect, "
                        "in a data root of their own (data/demo)")
    args = parser.parse_args(argv if argv is not None else [])
    try:
        executor_from_env()  # the definitions' executor: a bad QUADCORE_EXECUTOR is refused before any work
        learn_row_budget()  # and a bad QUADCORE_LEARN_ROWS before the learning stage would meet it
        if launch.cluster_url():
            launch.wait_timeout_s()  # and a bad QUADCORE_CLUSTER_TIMEOUT_S before the first run's wait
        demo = choose_demo(args.demo)
    except SettingError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    data_root = data_root_from_env()
    try:
        model = model_config_from_env()
        model.spec()  # a bad model file is a user error: say so before any work
    except (ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:  # before anything is written (the Dagster instance included)
        check_inputs(data_root, demo)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if demo:
        print(f"The demo: simulated flights in a data root of their own ({data_root.root_path}); your own logs go "
              f"into {Path(DEFAULT_ROOT, 'raw').resolve()} (or QUADCORE_RAW_DIR) and never mix with them.\n")
    home = ensure_dagster_home(data_root.root_path)
    unsynced_event_log(home)
    print(f"Data root: {data_root.root_path}\nRaw logs:  {data_root.raw_path}\nDagster:   {home}")
    path, origin = model_file_from_env()
    print(f"Model:     {path or '(none)'}\n           from {origin}\n")
    try:
        return run_all(data_root, model, dg.DagsterInstance.get(), demo=demo)
    except launch.ClusterUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
