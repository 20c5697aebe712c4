"""Stage 2: decoded flight -> residual table and open-loop rollout errors, per flight."""

import dagster as dg

from pipeline.assets.decode import MAIN_EVENT, decoded_flight
from pipeline.assets.model import current_model, physics_model
from pipeline.freshness import MODEL_VERSION, REFRESH, model_version
from pipeline.partitions import ONE_RUN, flights, for_each_flight
from pipeline.plot_links import number, plot_md
from pipeline.resources import DataRoot, ModelConfig
from quadcore.physics import dynamics, propagation, residuals
from quadcore.report import plots, render
from quadcore.store import store


def decoded_main_table(data_root: DataRoot, fid: str):
    """The flight's decoded ``fixedFrequency`` table, or a Failure saying it has none."""
    path = store.decoded_path(data_root.root_path, MAIN_EVENT, fid)
    if not path.is_file():
        raise dg.Failure(description=f"{fid}: the log has no {MAIN_EVENT!r} records", allow_retries=False)
    return store.read_decoded(data_root.root_path, MAIN_EVENT, fid)


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="physics", deps=[decoded_flight, physics_model],
          kinds={"parquet"}, automation_condition=REFRESH)
def residual_table(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Measured minus modelled force and torque per flight, body and world frames, against
    the current model (the vehicle plus the fitted effects of the model file)."""
    current = current_model(data_root, model, context.log)
    vehicle = current.vehicle

    def work(fid):
        decoded = decoded_main_table(data_root, fid)
        try:
            table = current.for_flight(fid).residual_table(decoded)  # its session's values, if any
        except dynamics.UnusableFlightError as exc:
            raise dg.Failure(description=f"{fid}: {exc}") from None
        path = store.write_parquet(
            table,
            store.table_path(data_root.root_path, "residuals", fid),
            {"flight": fid, "model": current.to_dict(), "units": residuals.column_units(table)},
        )
        png = plots.model_vs_measured(table, f"{fid}: model vs measured (body frame)")
        return {
            # torques in mN m, as everywhere people read them (the Parquet columns stay SI)
            **{k[:-3] + "_mNm" if k.endswith("_Nm") else k: number(v * 1e3 if k.endswith("_Nm") else v)
               for k, v in residuals.summary(table).items()},
            "rows": table.height,
            "model_vs_measured": plot_md(data_root, png, "model vs measured"),
            "parquet": dg.MetadataValue.path(str(path)),
        }

    done = for_each_flight(context, work)
    return dg.MaterializeResult(metadata={"model": current.label, MODEL_VERSION: model_version(current.to_dict()),
                                          "vehicle": vehicle.name, "thrust_map": vehicle.thrust_map_kind,
                                          "flights_in_run": len(done)})


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="physics", deps=[decoded_flight, physics_model],
          kinds={"parquet"}, automation_condition=REFRESH)
def rollout_errors(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Open-loop error growth of the current model from the logged state, per horizon, per flight."""
    current = current_model(data_root, model, context.log)

    def work(fid):
        decoded = decoded_main_table(data_root, fid)
        flight_model = current.for_flight(fid)  # its session's thrust map and values, as residual_table
        try:
            state = dynamics.flight_state(decoded, flight_model.vehicle)
        except dynamics.UnusableFlightError as exc:
            raise dg.Failure(description=f"{fid}: {exc}") from None
        extra = flight_model.rollout_wrench(state) if flight_model.terms else None
        growth = propagation.error_growth(state, flight_model.vehicle, extra_wrench=extra)
        path = store.write_parquet(
            growth, store.table_path(data_root.root_path, "rollouts", fid), {"flight": fid, "model": current.label}
        )
        if growth.height == 0:
            context.log.warning(f"{fid}: {state.n} samples, too short for an open-loop rollout")
            return {"rollout": f"none: {state.n} samples, too short", "parquet": dg.MetadataValue.path(str(path))}
        ends = propagation.horizon_summary(growth)
        meta = {}
        for row in ends.iter_rows(named=True):
            h = f"{row['horizon_s']:.3g}s"
            meta[f"pos_err_m@{h}"] = number(row["pos_err_m"])
            meta[f"att_err_deg@{h}"] = number(row["att_err_deg"])
        png = plots.error_growth(growth, f"{fid}: open-loop error growth")
        return {
            **meta,
            "horizons": dg.MetadataValue.md(render.markdown_table(ends)),
            "error_growth": plot_md(data_root, png, "error growth"),
            "parquet": dg.MetadataValue.path(str(path)),
        }

    done = for_each_flight(context, work)
    return dg.MaterializeResult(metadata={"model": current.label, MODEL_VERSION: model_version(current.to_dict()),
                                          "flights_in_run": len(done)})
