"""Stage 1: raw uSD log -> SI Parquet, one partition per flight."""


import dagster as dg

from pipeline.partitions import flights
from pipeline.resources import DataRoot
from quadcore import checks, flight, logformat, store

MAIN_EVENT = "fixedFrequency"
CHECKS = [dg.AssetCheckSpec(name, asset="decoded_flight") for name in checks.ALL_CHECKS]


@dg.asset(partitions_def=flights, group_name="decode", check_specs=CHECKS, kinds={"parquet"})
def decoded_flight(context: dg.AssetExecutionContext, data_root: DataRoot) -> dg.MaterializeResult:
    """Decode one raw log into SI Parquet (one file per event type) with provenance metadata.

    A file with nothing recoverable is quarantined (``<root>/quarantine/<flight>.json``)
    and the run fails with the reason; earlier outputs of that flight stay untouched.
    """
    fid = context.partition_key
    path = data_root.raw_path / fid
    try:
        path = data_root.raw_log(fid)
        fl = flight.decode_flight(path)
    except (logformat.LogFormatError, OSError) as exc:
        store.write_quarantine(data_root.root_path, fid, str(path), str(exc), type(exc).__name__)
        raise dg.Failure(
            description=f"{fid} quarantined: {type(exc).__name__}: {exc}",
            metadata={"source_file": str(path), "reason": str(exc)},
            allow_retries=False,
        ) from None
    paths = store.write_decoded(data_root.root_path, fl)
    store.clear_quarantine(data_root.root_path, fid)
    for w in fl.warnings:
        context.log.warning(f"{fid}: {w}")

    main = fl.tables.get(MAIN_EVENT)
    stats = flight.sample_statistics(main["t_s"].to_numpy()) if main is not None else {}
    check_results = []
    for name, check in checks.ALL_CHECKS.items():
        passed, desc, metrics = check(main) if main is not None else (False, f"no {MAIN_EVENT} table", {})
        check_results.append(
            dg.AssetCheckResult(
                check_name=name, passed=passed, severity=dg.AssetCheckSeverity.WARN, description=desc, metadata=metrics
            )
        )
    return dg.MaterializeResult(
        metadata={
            **{f"rows_{e}": n for e, n in fl.provenance["rows"].items()},
            **stats,
            "decode_warnings": dg.MetadataValue.md("\n".join(f"- {w}" for w in fl.warnings) or "none"),
            "warning_count": len(fl.warnings),
            "crc_ok": str(fl.provenance["crc_ok"]),
            "bytes_dropped": fl.provenance["bytes_dropped"],
            "format_version": fl.provenance["format_version"],
            "source_sha256": fl.provenance["source_sha256"],
            "parquet": dg.MetadataValue.path(str(paths.get(MAIN_EVENT, next(iter(paths.values()), "")))),
        },
        check_results=check_results,
    )
