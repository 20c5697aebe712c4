"""Stage 1b: each flight's sufficient statistics of the linear effects (:mod:`quadcore.identify.stats.sufficient`),
one partition per flight. The fleet fit and the diagnosis combine them instead of re-reading
every flight's rows: a new flight costs its own statistics plus a combine."""

import dagster as dg

from pipeline.assets.decode import decoded_flight
from pipeline.freshness import STATS_REFRESH, STATS_VERSION
from pipeline.partitions import ONE_RUN, flights, for_each_flight
from pipeline.resources import DataRoot, ModelConfig
from quadcore.identify import flightdata
from quadcore.identify.discovery import library_stats
from quadcore.identify.stats import sufficient
from quadcore.physics import dynamics
from quadcore.store import store
from quadcore.workflows.fleet import MAIN_EVENT


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="physics", deps=[decoded_flight],
          kinds={"numpy"}, automation_condition=STATS_REFRESH)
def flight_statistics(context: dg.AssetExecutionContext, data_root: DataRoot,
                      model: ModelConfig) -> dg.MaterializeResult:
    """Per 1 s block of the flight, the Gram matrix of [every linear effect's basis | the nominal
    residual] per channel, with the sensor-noise floor and sample counts: what the fleet fit,
    its folds and the held-out tests need of this flight (``stats/flight=<id>/stats.bin``); and
    the Gram matrices of term discovery's candidate library (``library.bin``,
    :mod:`quadcore.identify.discovery.library_stats`); and its summary (``summary.bin``,
    :mod:`quadcore.identify.describe.summaries`): what the diagnosis's regime, flight, segment and
    frequency tables need of it as an evaluated flight."""
    spec = model.spec()

    def work(fid):
        path = store.decoded_path(data_root.root_path, MAIN_EVENT, fid)
        if not path.is_file():
            raise dg.Failure(description=f"{fid}: the log has no {MAIN_EVENT!r} records", allow_retries=False)
        try:
            source = sufficient.decoded_source(data_root.root_path, fid) or ""
            decoded = store.read_parquet(path)
            fd = flightdata.flight_data(fid, decoded, spec.vehicle_for(fid))  # once for both (and its cached bases)
            s = sufficient.compute_current(spec, fid, decoded, source, fd)
            library = library_stats.compute(spec, fid, decoded, source, fd)
        except dynamics.UnusableFlightError as exc:
            raise dg.Failure(description=f"{fid}: {exc}") from None
        written = sufficient.save(s, data_root.root_path)
        library_stats.save(library, data_root.root_path)
        return {STATS_VERSION: library_stats.version(spec, fid), "blocks": s.blocks, "samples": s.n,
                "columns": s.layout.width, "discovery_columns": len(library.labels),
                "path": dg.MetadataValue.path(str(written))}

    done = for_each_flight(context, work)
    layout = sufficient.spec_layout(spec)
    return dg.MaterializeResult(metadata={"flights_in_run": len(done),
                                          "linear_effects": dg.MetadataValue.json(list(layout.effects)),
                                          "profiled_effects": dg.MetadataValue.json(list(layout.profiled))})
