"""Stage 4: what the physics cannot explain, learned. Fan-in over the residual tables of all
flights: feature sets -> trained models (XGBoost, MLP) -> report with baselines and plots."""

import dagster as dg
import polars as pl

from pipeline.assets.model import failing_on_user_errors
from pipeline.assets.physics import residual_table
from pipeline.plot_links import plot_md
from pipeline.resources import DataRoot, ModelConfig, learn_row_budget, retrain_cron
from quadcore.learn import features as feat, tables
from quadcore.report import render
from quadcore.store import store
from quadcore.workflows import learn

ALL_RESIDUALS = [dg.AssetDep(residual_table, partition_mapping=dg.AllPartitionMapping())]

# Learning costs tens of seconds on the whole fleet: the schedule nightly_retrain_learned_models
# (pipeline/schedules.py) runs it, or a manual materialisation; the models and the report follow
# the features, and say so in their automation label.
AFTER_FEATURES = dg.AutomationCondition.eager().with_label(
    f"after learning_features: the nightly_retrain_learned_models schedule ({retrain_cron()} UTC) or a manual run")


class FeatureConfig(dg.Config):
    """Feature sets to build: built-in names, or ``name=col1+col2`` (empty: every built-in set)."""

    feature_sets: list[str] = []


class LearningConfig(dg.Config):
    """What to train. ``holdout``: the flight the learned models are scored on (empty: the one
    ``QUADCORE_HOLDOUT`` names, else jana02, else the last flight: :func:`quadcore.workflows.learn.learning_holdout`);
    ``models``: model kinds; ``xgboost`` / ``mlp``: options such as ``depth=4,trees=300`` or
    ``hidden=64x64``; ``compare``: also the complexity and training-size comparisons; ``loo``:
    also leave-one-flight-out; ``flights_csv``: flight kinds (empty: ``flights.csv`` beside or
    above the raw folder); ``stride``: fit on every stride-th sample; ``max_rows``: the row budget of
    a training run (0: ``QUADCORE_LEARN_ROWS``, else the default); ``threads``: XGBoost threads."""

    holdout: str = ""  # empty: quadcore.workflows.learn.learning_holdout's default
    models: list[str] = ["xgboost", "mlp"]
    xgboost: str = ""
    mlp: str = ""
    compare: bool = True
    loo: bool = False
    flights_csv: str = ""
    stride: int = 5
    max_rows: int = 0  # 0: QUADCORE_LEARN_ROWS (pipeline.resources.learn_row_budget)
    seed: int = 0
    threads: int = 1  # XGBoost threads (one is faster on the 2-core machine; see quadcore.learn.learners.TrainConfig)


@dg.asset(group_name="learning", deps=ALL_RESIDUALS, kinds={"parquet"})
def learning_features(config: FeatureConfig, data_root: DataRoot) -> dg.MaterializeResult:
    """Named feature sets with their targets (residual force and torque, body frame) per flight:
    ``<root>/features/<set>/flight=<id>/data.parquet``. Retrained by the schedule
    ``nightly_retrain_learned_models`` when residual tables changed, or materialise it now."""
    root = data_root.root_path
    with failing_on_user_errors():
        sets, n_flights = learn.build_features(root, config.feature_sets)
    return dg.MaterializeResult(metadata={
        "feature_sets": dg.MetadataValue.md(render.markdown_table(pl.DataFrame(
            [{"set": fs.name, "columns": ", ".join(fs.columns), "causal": str(fs.causal), "note": fs.note}
             for fs in sets]))),
        "flights": n_flights,
        "targets": dg.MetadataValue.json(feat.TARGETS),
        "folder": dg.MetadataValue.path(str(store.features_dir(root))),
    })


@dg.asset(group_name="learning", deps=[learning_features], kinds={"xgboost", "pytorch"},
          automation_condition=AFTER_FEATURES)
def learned_models(
    context: dg.AssetExecutionContext, config: LearningConfig, data_root: DataRoot, model: ModelConfig
) -> dg.MaterializeResult:
    """XGBoost and MLP residual models per feature set (and the comparison runs), trained on all
    flights but the holdout with early stopping on validation flights; artefacts and held-out
    predictions under ``<root>/learned/<run>/``."""
    root = data_root.root_path
    csv_path = config.flights_csv or feat.find_flights_csv(data_root.raw_path, root)
    with failing_on_user_errors():
        request = learn.LearningRequest(tuple(config.models), {"xgboost": config.xgboost, "mlp": config.mlp},
                                        config.loo, config.compare, config.stride, config.seed, config.threads,
                                        config.max_rows or learn_row_budget())
        runs = learn.train_data_root(root, request, config.holdout, model.holdout_flights, csv_path, context.log.info)
    for note in runs.notes:
        context.log.warning(note)
    return dg.MaterializeResult(metadata={
        "holdout": runs.holdout,
        "models": len(runs.records),
        "runs": dg.MetadataValue.md(render.markdown_table(pl.DataFrame([
            {"run": r.name, "train s": r.train_time_s, "val loss": r.val_loss, "rows": r.rows_fit,
             "rows held": r.manifest["rows_held"], "µs/sample": r.latency_us} for r in runs.records]))),
        "row_budget": request.max_rows,
        "notes": dg.MetadataValue.md("\n".join(f"- {n}" for n in runs.notes) or "none"),
        "folder": dg.MetadataValue.path(str(store.learned_dir(root))),
    })


@dg.asset(group_name="learning", deps=[learned_models], kinds={"html"}, automation_condition=AFTER_FEATURES)
def learning_report(data_root: DataRoot) -> dg.MaterializeResult:
    """Held-out MAE / RMSE / R² per axis beside the baselines (physics-only, zero, training mean)
    and the study's figures; comparison tables and plots. Writes reports/learning.{md,html,json}
    and appends the headline results to the history (source ``learned``)."""
    with failing_on_user_errors():
        report, pngs, paths = learn.write_learning_report(data_root.root_path)
    md = {k: plot_md(data_root, v, k) for k, v in pngs.items()}
    return dg.MaterializeResult(metadata={
        "verdict": dg.MetadataValue.md(report["verdict"]),
        "headline": dg.MetadataValue.md(render.markdown_table(tables.frame(report["tables"]["headline"]))),
        "holdout_table": dg.MetadataValue.md(render.markdown_table(tables.frame(report["tables"]["holdout"]))),
        **{f"{k}_plot": v for k, v in md.items()},
        "report": dg.MetadataValue.path(str(paths["html"])),
    })
