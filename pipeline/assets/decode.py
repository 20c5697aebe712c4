"""Stage 1: raw uSD log -> SI Parquet, one partition per flight."""

from datetime import UTC, datetime

import dagster as dg

from pipeline.partitions import ONE_RUN, flights, for_each_flight
from pipeline.plot_links import number
from pipeline.resources import DataRoot
from quadcore.learn.features import find_flights_csv
from quadcore.logs import flight, required
from quadcore.physics import decoded_store, gate
from quadcore.store import store
from quadcore.workflows.fleet import quarantine_reason

MAIN_EVENT = store.MAIN_EVENT
CHECKS = [dg.AssetCheckSpec(name, asset="decoded_flight", description=gate.DESCRIPTIONS[name])
          for name in gate.ALL_CHECKS]


def _decode_one(fid: str, data_root: DataRoot, given_starts: dict[str, int], log) -> tuple[dict, dict]:
    """Decode and write one flight; returns (its metadata, check name -> (passed, description, metrics)).
    Its start time is the user's (``given_starts``), else the one recorded at its first decode."""
    path = data_root.raw_path / fid
    try:  # any failure is this file's alone (quadcore.workflows.fleet.decode_logs does the same)
        path = data_root.raw_log(fid)
        fl = flight.decode_flight(path, fid)
        # every variable the physics needs that the log lacks, in one message (quarantined like a bad file)
        required.check({event: [c["source"] for c in cols.values()] for event, cols in fl.columns.items()})
    except Exception as exc:  # noqa: BLE001 (per-file isolation: quarantined with its reason)
        reason = quarantine_reason(exc)
        store.write_quarantine(data_root.root_path, fid, str(path), reason, type(exc).__name__)
        raise dg.Failure(
            description=f"{fid} quarantined: {reason}",
            metadata={"source_file": str(path), "reason": reason},
            allow_retries=False,
        ) from None
    recorded = decoded_store.recorded_provenance(data_root.root_path, MAIN_EVENT, fid)
    flight.settle_start_time(fl, recorded, given_starts.get(fid))
    paths = decoded_store.write_decoded(data_root.root_path, fl)
    store.clear_quarantine(data_root.root_path, fid)
    for w in fl.warnings:
        log.warning(f"{fid}: {w}")
    main = fl.tables.get(MAIN_EVENT)
    stats = flight.sample_statistics(main["t_s"].to_numpy()) if main is not None else {}
    outcomes = {name: check(main) if main is not None else (False, f"no {MAIN_EVENT} table", {})
                for name, check in gate.ALL_CHECKS.items()}
    metadata = {
        **{f"rows_{e}": n for e, n in fl.provenance.rows.items()},
        **stats,
        "decode_warnings": dg.MetadataValue.md("\n".join(f"- {w}" for w in fl.warnings) or "none"),
        "warning_count": len(fl.warnings),
        "crc_ok": str(fl.provenance.crc_ok),
        "bytes_dropped": fl.provenance.bytes_dropped,
        "format_version": fl.provenance.format_version,
        "source_sha256": fl.provenance.source_sha256,
        "start_utc": _utc(fl.provenance.start_ns),
        "start_source": fl.provenance.start_source,
        "checks_failed": ", ".join(n for n, (ok, _, _) in outcomes.items() if not ok) or "none",
        "parquet": dg.MetadataValue.path(str(paths.get(MAIN_EVENT, next(iter(paths.values()), "")))),
    }
    return metadata, outcomes


def _utc(ns: int | None) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds") if ns is not None else "unknown"


def check_outcomes_path(data_root: DataRoot, fid: str):
    """Where a flight's latest check outcomes are kept (a check result in Dagster is per asset,
    not per flight: this keeps every flight's, for the per-flight table)."""
    return store.check_outcomes_path(data_root.root_path, fid)


def _keep_outcomes(data_root: DataRoot, fid: str, outcomes: dict) -> None:
    store.write_json({name: {"passed": ok, "reason": desc} for name, (ok, desc, _) in outcomes.items()},
                     check_outcomes_path(data_root, fid))


def latest_outcomes(data_root: DataRoot) -> dict[str, dict[str, tuple[bool, str]]]:
    """Every decoded flight's latest check outcomes, read once: check -> flight -> (passed,
    reason) (flights whose decoded table is gone are left out)."""
    root = data_root.root_path
    out: dict[str, dict[str, tuple[bool, str]]] = {name: {} for name in gate.ALL_CHECKS}
    for path in sorted(store.checks_dir(root).glob("*.json")):
        if not store.decoded_path(root, MAIN_EVENT, path.stem).is_file():
            continue
        for name, outcome in store.read_json(path).items():
            if name in out:
                out[name][path.stem] = (bool(outcome["passed"]), str(outcome["reason"]))
    return out


def _flights_table(outcomes: dict[str, tuple[bool, str]]) -> str:
    """Flights' outcomes of one check as a Markdown table (failing flights first)."""
    rows = sorted((ok, fid, reason) for fid, (ok, reason) in outcomes.items())
    lines = [f"| {fid} | {'pass' if ok else 'WARN'} | {reason} |" for ok, fid, reason in rows]
    return "| flight | outcome | reason |\n|---|---|---|\n" + "\n".join(lines)


def check_summary(outcomes: dict[str, tuple[bool, str]], limit: int = 6) -> str:
    """One line for a check over every flight it speaks for: how many fail, which and why."""
    failing = [(fid, reason) for fid, (ok, reason) in sorted(outcomes.items()) if not ok]
    if not failing:
        return f"all {len(outcomes)} flights pass"
    named = "; ".join(f"{fid}: {reason}" for fid, reason in failing[:limit])
    more = f"; and {len(failing) - limit} more (see the flights table)" if len(failing) > limit else ""
    return f"{len(failing)} of {len(outcomes)} flights fail: {named}{more}"


def _check_results(outcomes: dict[str, dict], data_root: DataRoot) -> list[dg.AssetCheckResult]:
    """One result per check, over every decoded flight (this run's outcomes and the latest of the
    others, kept under ``checks/``): it passes only when every flight passes, with severity WARN
    (a warning, never a failed run) and the counts in the result itself, so that one good new
    flight cannot turn a check green while other flights fail it."""
    results = []
    latest = latest_outcomes(data_root)
    for name in gate.ALL_CHECKS:
        every = latest[name]
        every.update({fid: (ok, d) for fid, o in outcomes.items() for ok, d, _ in [o[name]]})
        failing = sorted(fid for fid, (ok, _) in every.items() if not ok)
        metrics = {k: number(v) if isinstance(v, float) else v
                   for k, v in (next(iter(outcomes.values()))[name][2] if len(outcomes) == 1 else {}).items()}
        results.append(dg.AssetCheckResult(
            check_name=name, passed=not failing, severity=dg.AssetCheckSeverity.WARN,
            description=check_summary(every),
            metadata={**metrics, "flights_checked": len(every), "flights_failing": len(failing),
                      "failing": ", ".join(failing) or "none", "flights_in_run": ", ".join(outcomes),
                      "flights": dg.MetadataValue.md(_flights_table(every))}))
    return results


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="decode", check_specs=CHECKS,
          kinds={"parquet"})
def decoded_flight(context: dg.AssetExecutionContext, data_root: DataRoot) -> dg.MaterializeResult:
    """Decode each raw log of the run into SI Parquet (one file per event type) with provenance
    metadata and plausibility checks.

    A file with nothing recoverable is quarantined (``<root>/quarantine/<flight>.json``)
    and its partition fails with the reason; earlier outputs of that flight stay untouched.
    """
    outcomes = {}
    try:
        local = [p for p in (data_root.raw_path, data_root.root_path) if not store.is_remote(p)]
        given_starts = flight.read_flight_starts(find_flights_csv(*local))
    except ValueError as exc:
        raise dg.Failure(description=str(exc)) from None

    def work(fid):
        metadata, outcomes[fid] = _decode_one(fid, data_root, given_starts, context.log)
        _keep_outcomes(data_root, fid, outcomes[fid])
        return metadata

    for_each_flight(context, work)
    return dg.MaterializeResult(check_results=_check_results(outcomes, data_root))
