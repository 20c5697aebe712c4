"""Watch the raw folder: every new or changed log becomes a flight partition and a run."""


import json
from pathlib import Path

import dagster as dg

from pipeline.assets import PER_FLIGHT
from pipeline.assets.decode import MAIN_EVENT
from pipeline.partitions import FLIGHTS_PARTITION, flights
from pipeline.resources import DataRoot, automation_status
from quadcore.logs import flight, logformat, required
from quadcore.physics import decoded_store
from quadcore.store import store

# What the sensor's run for a flight computes: every per-flight asset.
PER_FLIGHT_KEYS = [a.key for a in PER_FLIGHT]


def raw_logs(data_root: DataRoot) -> dict[str, Path]:
    """Flight id -> path of every candidate log in the raw folder."""
    if not data_root.raw_path.is_dir():
        return {}
    return flight.flight_ids(flight.discover_logs(data_root.raw_path))[0]


def fingerprint(path: Path) -> str:
    """Size and mtime: a changed file is a new version of the flight."""
    try:
        st = path.stat()
    except OSError:  # removed since the listing: the next tick will not see it
        return "gone"
    return f"{st.st_size}-{st.st_mtime_ns}"


def header_problem(path) -> str | None:
    """The reason a file cannot be a log, or a log the physics cannot use (checked on its header
    only: the format, and every variable :mod:`quadcore.logs.required` names, in one message; an
    unreadable file is one), or None."""
    try:
        flight.check_inside_folder(path)  # a symlink out of the raw folder is not followed
        with open(path, "rb") as f:
            _, types, _ = logformat.parse_header(f.read(64 * 1024))
        required.check({t.name: t.variables for t in types.values()})
    except (logformat.LogFormatError, OSError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def new_flight_requests(context: dg.SensorEvaluationContext, data_root: DataRoot):
    seen = json.loads(context.cursor) if context.cursor else {}
    paths = raw_logs(data_root)
    current = {fid: fingerprint(p) for fid, p in paths.items()}
    changed = {fid: fp for fid, fp in current.items() if seen.get(fid) != fp}
    if not changed:
        return dg.SkipReason(f"no new logs in {data_root.raw_path}")
    known = set(context.instance.get_dynamic_partitions(FLIGHTS_PARTITION))
    decoded = context.instance.get_materialized_partitions(dg.AssetKey("decoded_flight"))
    runs, add, refused = [], [], {}
    for fid, fp in sorted(changed.items()):
        problem = header_problem(paths[fid])
        if problem:
            store.write_quarantine(data_root.root_path, fid, str(paths[fid]), problem, "header")
            context.log.warning(f"quarantined {fid}: {problem}")
            refused[fid] = problem
            continue
        if fid not in known:
            add.append(fid)
        elif fid in decoded and decoded_store.decoded_from(data_root.root_path, MAIN_EVENT, fid, paths[fid]):
            continue  # processed already (by `make run`, or before a restart): same bytes, nothing to redo
        # every per-flight asset named: Dagster's automation then knows the decode was this run's own
        # (executed_with_root_target), so it does not compute the flight's other tables again
        runs.append(dg.RunRequest(run_key=f"{fid}:{fp}", partition_key=fid, asset_selection=PER_FLIGHT_KEYS))
    events = [quarantine_report(data_root)] if refused else []
    return dg.SensorResult(
        run_requests=runs,
        cursor=json.dumps(current),
        dynamic_partitions_requests=[flights.build_add_request(add)] if add else [],
        asset_events=events,
    )


# Files refused at the door: not assets we compute, but a record the UI shows with the reasons.
QUARANTINE = dg.AssetSpec(
    "quarantine", group_name="decode", description="Raw files that are not readable logs, with the reason. "
    "Fix or remove the file; a readable replacement is picked up and leaves quarantine."
)


def quarantine_report(data_root: DataRoot) -> dg.AssetMaterialization:
    records = store.quarantined(data_root.root_path)
    rows = "\n".join(f"| {r['flight']} | {r['error_type']} | {r['reason']} |" for r in records)
    return dg.AssetMaterialization(
        asset_key="quarantine",
        metadata={
            "files": len(records),
            "quarantined": dg.MetadataValue.md("| file | kind | reason |\n|---|---|---|\n" + rows),
            "folder": dg.MetadataValue.path(str(data_root.root_path / "quarantine")),
        },
    )


PER_FLIGHT_ASSETS = dg.AssetSelection.assets(*PER_FLIGHT)


# One flight through every per-flight stage: what the sensor launches (its runs are filed under
# this job in the UI), and a button in the UI.
process_flight = dg.define_asset_job("process_flight", selection=PER_FLIGHT_ASSETS)


@dg.sensor(job=process_flight, minimum_interval_seconds=30, default_status=automation_status())
def raw_log_sensor(context: dg.SensorEvaluationContext, data_root: DataRoot):
    """New or changed files in the raw folder -> flight partitions and runs; bad files -> quarantine."""
    return new_flight_requests(context, data_root)
