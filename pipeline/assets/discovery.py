"""Stage 3b: terms the effect library lacks, found in the residual of the current model
(:mod:`quadcore.identify.discovery`). Fan-in over all decoded flights; the diagnosis report shows them."""

import dagster as dg

from pipeline.assets.model import (
    ALL_FLIGHTS,
    RETRAIN,
    failing_on_user_errors,
    load_fleet,
    physics_model,
    skipped_metadata,
)
from pipeline.plot_links import number, plot_md
from pipeline.resources import DataRoot, ModelConfig
from quadcore.report import diagnosis as diagnosis_report, render
from quadcore.store import store
from quadcore.workflows import identify

# After each refit (which follows every new or changed flight), not on the decode itself: a new
# flight would otherwise run discovery twice, once on its decode and once on the refit it causes.
AFTER_REFIT = RETRAIN.ignore(dg.AssetSelection.assets("decoded_flight")).with_label(
    "again when the model is refitted (which follows new flights)")


@dg.asset(group_name="model", deps=[*ALL_FLIGHTS, physics_model], kinds={"json"}, automation_condition=AFTER_REFIT)
def term_discovery(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Sparse regression of the model's residual on a library of candidate terms, grouped by
    flight: the formulas the model lacks, each with its coefficient, uncertainty, held-out
    share and stability, on the flights model_diagnosis sees (the flight the learned models are
    scored on is left out unless ``QUADCORE_HOLDOUT`` names the holdout). Writes reports/discovery.json."""
    spec = model.spec()
    flights = load_fleet(data_root, spec.vehicle, context.log)
    with failing_on_user_errors():  # a bad QUADCORE_HOLDOUT fails here, as in physics_model
        try:
            result = identify.discover(flights, spec, model.holdout_flights, context.log.info,
                                       root=data_root.root_path)
        except identify.TooFewFlights as exc:  # a young fleet: the diagnosis still runs, discovery waits
            why = f"skipped: {exc}; {len(flights.tables)} usable decoded"
            context.log.warning(why)
            return dg.MaterializeResult(metadata={"summary": why, **skipped_metadata(flights.skipped)})
    path = identify.write_discovery(result, store.discovery_path(data_root.root_path))
    b, a = result.baseline, result.after
    return dg.MaterializeResult(metadata={
        "summary": dg.MetadataValue.md(result.summary.replace("\n", "\n\n")),
        "terms": dg.MetadataValue.md(render.markdown_table(diagnosis_report.discovery_table(result.to_dict()))
                                     if result.terms else "no term kept"),
        "discovery_plot": plot_md(data_root, diagnosis_report.discovery_plot(result.to_dict()), "discovery"),
        "notes": dg.MetadataValue.md("\n\n".join(f"{x.target}: {n}" for x in result.axes for n in x.notes) or "none"),
        **{f"after_force_rmse_{ax}_N": number(v) for ax, v in zip("xyz", a["force_rmse_N"])},
        **{f"after_torque_rmse_{ax}_Nm": number(v) for ax, v in zip("xyz", a["torque_rmse_Nm"])},
        "baseline": dg.MetadataValue.json(b),
        "path": dg.MetadataValue.path(str(path)),
        "flights": len({*result.evaluation["train_flights"], *result.evaluation["eval_flights"]}),
        **skipped_metadata(flights.skipped),
    })

