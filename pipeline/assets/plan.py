"""The next flight to fly: the trajectory that separates what the diagnosis cannot tell apart
(:mod:`quadcore.plan`, ``docs/flight-planning.md``), beside the diagnosis, with its picture."""

import dagster as dg

from pipeline.assets.model import RETRAIN, failing_on_user_errors, load_fleet, model_diagnosis
from pipeline.plot_links import number, plot_md
from pipeline.resources import DataRoot, ModelConfig
from quadcore.plan.planner import PlanRequest
from quadcore.workflows import plan as planflow


@dg.asset(group_name="model", deps=[model_diagnosis], kinds={"csv"}, automation_condition=RETRAIN)
def flight_plan(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Not in the main job (``make run``): materialise it in the UI, or let the automation sensor
    do it after the diagnosis. The flight that answers the diagnosis's open question (two candidates it cannot tell
    apart, or a parameter known too loosely), in the lab's trajectory format, within the default
    limits and arena, with the separation it is predicted to bring (the simulator's proof is
    ``quadcore plan``'s). Writes reports/flight_plan.{json,csv,png}; plans nothing, and says
    so, when nothing needs separating."""
    spec = model.spec()
    flights = load_fleet(data_root, spec.vehicle, context.log)
    with failing_on_user_errors():
        result, written = planflow.plan_data_root(data_root.root_path, flights, spec, PlanRequest(prove=False),
                                                  context.log.info)
    meta: dict = {"question": result.question.why, "planned": result.planned,
                  "json": dg.MetadataValue.path(str(written.json))}
    if result.planned:
        png = planflow.plot_png(result)
        meta |= {
            "manoeuvre": result.manoeuvre.describe() if result.manoeuvre else "",
            "trajectory": dg.MetadataValue.path(str(written.trajectory)),
            **{k: number(v) for k, v in result.predicted().items() if v is not None},
            **({"advice": result.design["advice"]} if result.design.get("advice") else {}),
            **({"plan_plot": plot_md(data_root, png, "flight plan")} if png is not None else {}),
        }
    return dg.MaterializeResult(metadata=meta)
