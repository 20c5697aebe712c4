"""Stage 2: decoded flight -> residual table and open-loop rollout errors, per flight."""

import dagster as dg

from pipeline.assets.decode import MAIN_EVENT, decoded_flight
from pipeline.partitions import flights
from pipeline.resources import DataRoot, PhysicsModel
from quadcore import dynamics, plots, propagation, residuals, store


@dg.asset(partitions_def=flights, group_name="physics", deps=[decoded_flight], kinds={"parquet"})
def residual_table(context: dg.AssetExecutionContext, data_root: DataRoot, physics: PhysicsModel) -> dg.MaterializeResult:
    """Measured minus modelled force and torque for one flight, body and world frames."""
    fid = context.partition_key
    vehicle = physics.load_vehicle()
    decoded = store.read_decoded(data_root.root_path, MAIN_EVENT, fid)
    table = residuals.residual_table(decoded, vehicle)
    path = store.write_parquet(
        table,
        store.table_path(data_root.root_path, "residuals", fid),
        {"flight": fid, "vehicle": vehicle.name, "vehicle_source": vehicle.source,
         "thrust_map": vehicle.thrust_map_kind, "units": residuals.column_units(table)},
    )
    stats = residuals.summary(table)
    png = plots.model_vs_measured(table, f"{fid}: model vs measured (body frame)")
    return dg.MaterializeResult(
        metadata={
            **{k: dg.MetadataValue.float(v) for k, v in stats.items()},
            "rows": table.height,
            "vehicle": vehicle.name,
            "thrust_map": vehicle.thrust_map_kind,
            "model_vs_measured": dg.MetadataValue.md(plots.markdown_image(png, "model vs measured")),
            "parquet": dg.MetadataValue.path(str(path)),
        }
    )


@dg.asset(partitions_def=flights, group_name="physics", deps=[decoded_flight], kinds={"parquet"})
def rollout_errors(context: dg.AssetExecutionContext, data_root: DataRoot, physics: PhysicsModel) -> dg.MaterializeResult:
    """Open-loop error growth of the model from the logged state, per horizon."""
    fid = context.partition_key
    vehicle = physics.load_vehicle()
    decoded = store.read_decoded(data_root.root_path, MAIN_EVENT, fid)
    growth = propagation.error_growth(dynamics.flight_state(decoded, vehicle), vehicle)
    path = store.write_parquet(
        growth, store.table_path(data_root.root_path, "rollouts", fid), {"flight": fid, "vehicle": vehicle.name}
    )
    ends = propagation.horizon_summary(growth)
    meta = {}
    for row in ends.iter_rows(named=True):
        h = f"{row['horizon_s']:.3g}s"
        meta[f"pos_err_m@{h}"] = dg.MetadataValue.float(row["pos_err_m"])
        meta[f"att_err_deg@{h}"] = dg.MetadataValue.float(row["att_err_deg"])
    png = plots.error_growth(growth, f"{fid}: open-loop error growth")
    return dg.MaterializeResult(
        metadata={
            **meta,
            "horizons": dg.MetadataValue.md(plots.markdown_table(ends)),
            "error_growth": dg.MetadataValue.md(plots.markdown_image(png, "error growth")),
            "parquet": dg.MetadataValue.path(str(path)),
        }
    )

