"""Stage: a flight as MCAP for Foxglove (pose, IMU, motors, battery, model vs measured)."""

import dagster as dg

from pipeline.assets.decode import MAIN_EVENT
from pipeline.assets.model import REFRESH
from pipeline.assets.physics import residual_table
from pipeline.partitions import ONE_RUN, flights, for_each_flight
from pipeline.resources import DataRoot
from quadcore import export, store
from quadcore.names import check_component


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="export", deps=[residual_table], kinds={"mcap"},
          automation_condition=REFRESH)
def flight_mcap(context: dg.AssetExecutionContext, data_root: DataRoot) -> dg.MaterializeResult:
    """`<root>/mcap/<flight>.mcap` per flight: open it in Foxglove (3D panel: the /tf frame 'body').
    Anchored at the start time recorded in the flight's decoded provenance."""
    root = data_root.root_path

    def work(fid):
        table = store.read_table(root, "residuals", fid)
        provenance = store.recorded_provenance(root, MAIN_EVENT, fid) or {}
        if "start_ns" not in provenance:
            raise dg.Failure(
                description=f"{fid}: no start time in its decoded provenance: re-materialise decoded_flight")
        path = root / "mcap" / f"{check_component(fid, 'flight id')}.mcap"
        counts = export.write_mcap(table, path, int(provenance["start_ns"]),
                                   {"flight": fid, "start_source": provenance.get("start_source", "")})
        return {"messages": sum(counts.values()), "topics": dg.MetadataValue.json(counts),
                "path": dg.MetadataValue.path(str(path))}

    done = for_each_flight(context, work)
    return dg.MaterializeResult(metadata={"flights_in_run": len(done)})
