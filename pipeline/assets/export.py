"""Stage: a flight as MCAP for Foxglove (pose, IMU, motors, battery, model vs measured)."""

import dagster as dg

from pipeline.assets.model import REFRESH
from pipeline.assets.physics import residual_table
from pipeline.partitions import flights
from pipeline.resources import DataRoot
from quadcore import export, store
from quadcore.names import check_component


@dg.asset(partitions_def=flights, group_name="export", deps=[residual_table], kinds={"mcap"},
          automation_condition=REFRESH)
def flight_mcap(context: dg.AssetExecutionContext, data_root: DataRoot) -> dg.MaterializeResult:
    """`<root>/mcap/<flight>.mcap`: open it in Foxglove (3D panel: the /tf frame 'body')."""
    fid = context.partition_key
    table = store.read_table(data_root.root_path, "residuals", fid)
    start_ns = export.anchor_from_file(data_root.raw_log(fid), float(table["t_s"][-1]))
    path = data_root.root_path / "mcap" / f"{check_component(fid, 'flight id')}.mcap"
    counts = export.write_mcap(table, path, start_ns, {"flight": fid})
    return dg.MaterializeResult(metadata={
        "messages": sum(counts.values()),
        "topics": dg.MetadataValue.json(counts),
        "path": dg.MetadataValue.path(str(path)),
    })
