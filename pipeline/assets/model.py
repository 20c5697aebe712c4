"""Stage 3: the physics model (vehicle + fitted effects), its diagnosis, and the history of
its errors. Fan-in over all decoded flights."""


import contextlib

import dagster as dg
import polars as pl

from pipeline.assets.decode import decoded_flight
from pipeline.assets.statistics import flight_statistics
from pipeline.freshness import MODEL_VERSION, ModelFileChanged, model_version
from pipeline.plot_links import number, plot_md
from pipeline.resources import DataRoot, ModelConfig, SettingError, make_command
from quadcore import workflows
from quadcore.identify import history
from quadcore.identify.diagnosis import verdict
from quadcore.identify.fit import sessions
from quadcore.identify.stats import sufficient
from quadcore.learn import learners
from quadcore.report import diagnosis as diagnosis_report, render
from quadcore.workflows import Fleet, fleet, identify

ALL_FLIGHTS = [dg.AssetDep(decoded_flight, partition_mapping=dg.AllPartitionMapping())]
# the fit and the diagnosis combine the flights' statistics (computed from the rows where missing)
ALL_STATISTICS = [dg.AssetDep(flight_statistics, partition_mapping=dg.AllPartitionMapping())]

# Retrain when flights have arrived or changed (not on every tick when nothing changed); a
# flight that was registered but never decoded (quarantined) does not block retraining.
RETRAIN = (
    dg.AutomationCondition.eager()
    .without(~dg.AutomationCondition.any_deps_missing())
    .with_label("again when flights arrive or the model is refitted (eager)")
)


@contextlib.contextmanager
def failing_on_user_errors():
    """A request the workflows refuse (a bad ``QUADCORE_HOLDOUT`` or sessions file, too few
    flights, a learning option, a bad ``QUADCORE_*`` setting) fails the run with its reason, in one line."""
    try:
        yield
    except workflows.HoldoutError as exc:
        raise dg.Failure(description=f"QUADCORE_HOLDOUT: {exc}") from None
    except (workflows.WorkflowError, learners.LearningError, SettingError) as exc:
        raise dg.Failure(description=str(exc)) from None


def load_fleet(data_root: DataRoot, vehicle, log) -> Fleet:
    """Every decoded flight the physics can use (the others logged as warnings, with why)."""
    return fleet.fleet_from_store(data_root.root_path, vehicle, log.warning)


def skipped_metadata(skipped: dict[str, str]) -> dict:
    rows = "\n".join(f"| {fid} | {why} |" for fid, why in skipped.items())
    return {"skipped_flights": dg.MetadataValue.md(f"| flight | reason |\n|---|---|\n{rows}" if skipped else "none"),
            "skipped_count": len(skipped)}


def current_model(data_root: DataRoot, model: ModelConfig, log=None):
    """:func:`quadcore.workflows.identify.current_model` for the model these settings name."""
    warn = log.warning if log is not None else (lambda m: None)
    return identify.current_model(data_root.root_path, model.spec(), warn)


# The fit also follows the model file: an effect added to model.toml refits without a manual step.
REFIT = (RETRAIN | (ModelFileChanged() & ~dg.AutomationCondition.in_progress()
                    & ~dg.AutomationCondition.execution_failed())).with_label(
    "refit when flights arrive or the model file changes")


@dg.asset(group_name="model", deps=[*ALL_FLIGHTS, *ALL_STATISTICS], kinds={"json"}, automation_condition=REFIT)
def physics_model(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """The model file's effects, fitted on every decoded flight but the held-out one(s) that
    ``QUADCORE_HOLDOUT`` names (by default none)."""
    spec = model.spec()
    context.log.info(f"model file: {spec.source or '(none: the nominal vehicle)'}")
    flights = load_fleet(data_root, spec.vehicle, context.log)
    with failing_on_user_errors():
        fitted = identify.fit(flights, spec, model.holdout_flights, context.log.info,
                              sufficient.stored(data_root.root_path, spec))
    path = identify.save_fit(data_root.root_path, fitted)
    params = fitted.parameter_rows()
    return dg.MaterializeResult(metadata={
        "model": fitted.model.label,
        MODEL_VERSION: model_version(current_model(data_root, model).to_dict()),
        "effects": dg.MetadataValue.json(fitted.model.effect_names),
        "parameters": dg.MetadataValue.md(
            render.markdown_table(pl.DataFrame(params)) if params else "nominal model: no effects"),
        "trained_on": len(fitted.trained_on),
        "held_out": ", ".join(fitted.held_out) or "none (QUADCORE_HOLDOUT not set)",
        "model_file": spec.source or "(none: nominal)",
        "path": dg.MetadataValue.path(str(path)),
        **skipped_metadata(flights.skipped),
    })


@dg.asset(group_name="model", deps=[*ALL_FLIGHTS, *ALL_STATISTICS, physics_model, dg.AssetKey("term_discovery")],
          kinds={"html"},
          automation_condition=RETRAIN)
def model_diagnosis(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Where the model fails (by regime, flight, segment) and which effect is missing, scored on
    held-out flights. Writes reports/diagnosis.{json,md,html} and appends to the history."""
    spec = model.spec()
    flights = load_fleet(data_root, spec.vehicle, context.log)
    with failing_on_user_errors():
        result = identify.diagnose(flights, spec, model.holdout_flights, context.log.info,
                                   stats=sufficient.stored(data_root.root_path, spec), root=data_root.root_path,
                                   discover_command=identify.discover_command(data_root.raw_path, spec,
                                                                              model.holdout_flights))
    md, page = identify.record_diagnosis(data_root.root_path, result, spec, make_command("run"))
    b, doc = result.baseline, result.to_dict()  # the plots draw the JSON document
    disagreements = [d.to_dict() for d in result.disagreements]
    per_session = diagnosis_report.session_values(doc)
    return dg.MaterializeResult(metadata={
        "headline": dg.MetadataValue.md(diagnosis_report.headline(doc)),
        "next_step": dg.MetadataValue.md(diagnosis_report.next_step(doc, spec.source, make_command("run"))),
        "evidence": dg.MetadataValue.md(render.markdown_table(diagnosis_report.evidence_table(doc, 5))),
        "verdict": dg.MetadataValue.md(result.verdict),
        "protocol": result.evaluation.protocol,
        "stability": result.stability.sentence(),
        "model": result.model.label,
        "model_file": spec.source or "(none: nominal)",
        **{f"force_rmse_{a}_N": number(v) for a, v in zip("xyz", b.force_rmse_N)},
        **{f"torque_rmse_{a}_mNm": number(v * 1e3) for a, v in zip("xyz", b.torque_rmse_Nm)},
        "candidates": dg.MetadataValue.md(render.markdown_table(pl.DataFrame(
            verdict.candidate_summary(result.candidates[:5])))),
        "values_per_session": dg.MetadataValue.md(render.markdown_table(per_session) if per_session is not None
                                                  else "none: one value per parameter for every flight"),
        "sensitivity": dg.MetadataValue.md(render.markdown_table(pl.DataFrame(
            verdict.sensitivity_rows(result.sensitivity, result.sensitivity_basis)))),
        "sensitivity_json": dg.MetadataValue.json(doc["sensitivity"]),
        "disagreements": dg.MetadataValue.md(render.markdown_table(pl.DataFrame(
            sessions.table_rows(disagreements))) if disagreements else "none: one value fits all"),
        "disagreements_json": dg.MetadataValue.json(disagreements),
        "candidates_plot": plot_md(data_root, diagnosis_report.candidates_plot(doc), "candidates"),
        "regimes_plot": plot_md(data_root, diagnosis_report.regimes_plot(doc), "regimes"),
        "worst_segments": dg.MetadataValue.md(render.markdown_table(diagnosis_report.in_mNm(result.worst_segments))),
        **_frequency_metadata(data_root, doc["frequency"]),
        "report": dg.MetadataValue.path(str(page)),
        **skipped_metadata(flights.skipped),
    })


def _frequency_metadata(data_root: DataRoot, freq: dict | None) -> dict:
    """Where the model fails in frequency: the reading, and the band plot."""
    if not freq or not freq.get("channels"):
        return {}
    return {"frequency": dg.MetadataValue.md("\n\n".join(freq["reading"])),
            "frequency_plot": plot_md(data_root, diagnosis_report.frequency_plot(freq), "frequency")}


@dg.asset(group_name="model", deps=[model_diagnosis], kinds={"parquet"}, automation_condition=RETRAIN)
def error_history(data_root: DataRoot) -> dg.MaterializeResult:
    """Every evaluation so far, oldest first: the error of nominal -> +effect -> ... -> +learned."""
    hist = history.read(data_root.root_path)
    if hist.height == 0:
        return dg.MaterializeResult(metadata={"evaluations": 0})
    last = hist.row(-1, named=True)
    return dg.MaterializeResult(metadata={
        "evaluations": hist.height,
        "latest_model": last["model_label"],
        **{c.replace("_Nm", "_mNm") if c.endswith("_Nm") else c: number(last[c] * (1e3 if c.endswith("_Nm") else 1))
           for c in history.RMSE_COLUMNS},
        "history_plot": plot_md(data_root, diagnosis_report.history_plot(hist), "history"),
        "folder": dg.MetadataValue.path(str(history.history_dir(data_root.root_path))),
    })
