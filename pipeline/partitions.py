"""One dynamic partition per flight; the key is the raw log's file name.

Per-flight assets take one flight per run (the sensor, a rerun from the UI) or a range of
flights in one run (the main job, a backfill: ``BackfillPolicy.single_run()``). Their bodies
loop over the run's flights with :func:`for_each_flight`, so each flight keeps its own
partition, metadata and failure, and a run costs its overhead once, not once per flight.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable, Mapping

import dagster as dg

# backfill_policy on an asset is "beta" in Dagster 1.13; it is what we want, so without the banner.
warnings.filterwarnings("ignore", message="Parameter `backfill_policy`", category=dg.BetaWarning)

FLIGHTS_PARTITION = "flights"
flights = dg.DynamicPartitionsDefinition(name=FLIGHTS_PARTITION)

# Every flight of a run in one step (the UI's backfills and the main job launch one run per range).
ONE_RUN = dg.BackfillPolicy.single_run()

# Metadata key of a failed step: flight -> reason, so that callers can retry the others.
FAILED_FLIGHTS = "failed_flights"


def for_each_flight(context: dg.AssetExecutionContext, work: Callable[[str], Mapping]) -> dict[str, Mapping]:
    """Run ``work(flight)`` for every flight partition of this run and attach what it returns
    as that flight's metadata. A flight that raises does not stop the others; the step then
    fails naming every failed flight and its reason (metadata ``failed_flights``), the other
    flights' outputs stay written. Returns flight -> metadata of the flights that succeeded."""
    done, failed = {}, {}
    for fid in context.partition_keys:
        try:
            done[fid] = work(fid)
        except Exception as exc:  # noqa: BLE001 (one bad flight never stops the others; reported below)
            reason = exc.description if isinstance(exc, dg.Failure) else f"{type(exc).__name__}: {exc}"
            failed[fid] = reason or type(exc).__name__
            context.log.error(f"{fid}: {failed[fid]}")
            continue
        context.add_asset_metadata(done[fid], partition_key=fid)
    if failed:
        raise dg.Failure(
            description="; ".join(f"{fid}: {why}" for fid, why in failed.items()),
            metadata={FAILED_FLIGHTS: dg.MetadataValue.json(failed), "succeeded": len(done)},
            allow_retries=False,
        )
    return done


def failed_flights(result) -> dict[str, str]:
    """Flight -> reason from the failed steps of a run (empty when a step failed for no flight)."""
    out = {}
    for event in result.get_step_failure_events():
        data = event.step_failure_data.user_failure_data
        if data is not None and FAILED_FLIGHTS in data.metadata:
            out.update(json.loads(json.dumps(data.metadata[FAILED_FLIGHTS].value)))
    return out
