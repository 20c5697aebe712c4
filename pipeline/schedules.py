"""Retraining a person can see: the learned models retrain on a schedule the UI lists with its
next tick (Overview → Automation → Schedules), not on a condition hidden on an asset.

``nightly_retrain_learned_models`` runs the job ``retrain_learned_models`` (learning_features →
learned_models → learning_report, and the model as C) at ``QUADCORE_RETRAIN_CRON`` (02:00 UTC by
default), and only when a flight's residual table was (re)computed since the learned models last
trained, or there are none yet; otherwise the tick is skipped with that reason, which the UI shows.
Learning costs tens of seconds on the fleet, so it waits for the night; the fleet fit and the
diagnosis stay eager (they are cheap). Materialise ``learning_features`` to retrain at once.
"""

import dagster as dg

from pipeline.assets import EXPORT, LEARNING
from pipeline.freshness import current_model_version, versions_used
from pipeline.resources import automation_status, retrain_cron

retrain_learned_models = dg.define_asset_job(
    "retrain_learned_models", selection=dg.AssetSelection.assets(*LEARNING, *EXPORT),
    description="The learned residual models (XGBoost, MLP) on every flight's current residual table, "
                "their report, and the model as C.")


def learning_due(instance: dg.DagsterInstance) -> tuple[bool, str]:
    """(whether the learned models should retrain now, why): none trained yet, or a residual
    table materialised after the latest ``learning_features``; not while any flight's residual
    table was computed against an older physics model than the current one (the learning would
    mix two models: the automation refreshes those flights first)."""
    last = instance.get_latest_materialization_event(dg.AssetKey("learning_features"))
    if last is not None and not instance.fetch_materializations(
            dg.AssetRecordsFilter(asset_key=dg.AssetKey("residual_table"), after_timestamp=last.timestamp),
            limit=1).records:
        return False, "no residual table changed since the learned models last trained"
    try:
        current = current_model_version()
    except (ValueError, KeyError, OSError) as exc:  # a bad model file: the fit's run says why
        return False, f"cannot tell the current physics model: {exc}"
    flights = set(instance.get_dynamic_partitions("flights"))
    stale = sorted(f for f, v in versions_used(instance, dg.AssetKey("residual_table"), flights).items()
                   if v != current)
    if stale:
        return False, (f"waiting: {len(stale)} flight(s) computed against an older physics model "
                       f"({', '.join(stale[:5])}{' ...' if len(stale) > 5 else ''}) are being refreshed")
    return True, "no learned models yet" if last is None else "residual tables changed since the last training"


@dg.schedule(job=retrain_learned_models, cron_schedule=retrain_cron(), execution_timezone="UTC",
             name="nightly_retrain_learned_models",
             default_status=dg.DefaultScheduleStatus(automation_status().value),
             description=f"Retrains the learned residual models at {retrain_cron()} UTC (QUADCORE_RETRAIN_CRON) "
                         "when a flight's residual table changed since they last trained; skips the tick otherwise.")
def nightly_retrain_learned_models(context: dg.ScheduleEvaluationContext):
    due, why = learning_due(context.instance)
    return dg.RunRequest(tags={"quadcore/trigger": why}) if due else dg.SkipReason(why)
