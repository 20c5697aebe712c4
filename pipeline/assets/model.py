"""Stage 3: the physics model (vehicle + fitted effects), its diagnosis, and the history of
its errors. Fan-in over all decoded flights."""


import dagster as dg
import polars as pl

from pipeline.assets.decode import MAIN_EVENT, decoded_flight
from pipeline.freshness import MODEL_VERSION, ModelFileChanged, model_version
from pipeline.plot_links import number, plot_md
from pipeline.resources import DataRoot, ModelConfig
from quadcore import checks, diagnosis, fitting, history, model as modelmod, plots, report, sessions, store, workflows

ALL_FLIGHTS = [dg.AssetDep(decoded_flight, partition_mapping=dg.AllPartitionMapping())]

# Retrain when flights have arrived or changed (not on every tick when nothing changed); a
# flight that was registered but never decoded (quarantined) does not block retraining.
RETRAIN = (
    dg.AutomationCondition.eager()
    .without(~dg.AutomationCondition.any_deps_missing())
    .with_label("retrain when flights arrive")
)


def usable_decoded(data_root: DataRoot, vehicle, log) -> tuple[store.FlightTables, dict[str, str]]:
    """Every decoded flight the physics can use (read one at a time as the stage walks them:
    :class:`quadcore.store.FlightTables`), and the skipped ones (flight -> reason, each logged
    as a warning): one bad flight never stops the fleet stages."""
    decoded = store.read_all_decoded(data_root.root_path, MAIN_EVENT)
    usable, skipped = checks.usable_flights(decoded, vehicle)
    for fid, why in skipped.items():
        log.warning(f"{fid} skipped: {why}")
    return decoded.subset(usable), skipped


def skipped_metadata(skipped: dict[str, str]) -> dict:
    rows = "\n".join(f"| {fid} | {why} |" for fid, why in skipped.items())
    return {"skipped_flights": dg.MetadataValue.md(f"| flight | reason |\n|---|---|\n{rows}" if skipped else "none"),
            "skipped_count": len(skipped)}


def held_out_or_fail(model: ModelConfig, decoded: dict) -> tuple[list[str], str]:
    """:meth:`ModelConfig.held_out` of the decoded flights; a bad ``QUADCORE_HOLDOUT`` fails the run
    with its reason."""
    try:
        return model.held_out(list(decoded))
    except workflows.HoldoutError as exc:
        raise dg.Failure(description=f"QUADCORE_HOLDOUT: {exc}") from None


def scored_flights(model: ModelConfig, decoded: store.FlightTables) -> tuple[store.FlightTables, list[str] | None]:
    """(the decoded flights a diagnosis or discovery sees, its holdout or None): see
    :func:`quadcore.workflows.scored_flights`."""
    held, _ = held_out_or_fail(model, decoded)
    seen, holdout = workflows.scored_flights(decoded, model.holdout_flights, held)
    return decoded.subset(seen), holdout or None


def fitted_model_path(data_root: DataRoot):
    return store.physics_model_path(data_root.root_path)


# The fit also follows the model file: an effect added to model.toml refits without a manual step.
REFIT = (RETRAIN | (ModelFileChanged() & ~dg.AutomationCondition.in_progress()
                    & ~dg.AutomationCondition.execution_failed())).with_label(
    "refit when flights arrive or the model file changes")


@dg.asset(group_name="model", deps=ALL_FLIGHTS, kinds={"json"}, automation_condition=REFIT)
def physics_model(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """The model file's effects, fitted on the training flights: every decoded flight but the
    held-out one(s) (``QUADCORE_HOLDOUT``, else jana02, else the last flight), which the
    learned models are scored on."""
    spec = model.spec()
    decoded, skipped = usable_decoded(data_root, spec.vehicle, context.log)
    if len(decoded) < 2:
        raise dg.Failure(description=f"need at least two usable decoded flights in {data_root.root_path / 'decoded'}")
    held, note = held_out_or_fail(model, decoded)
    if note:
        context.log.info(note)
    train = [f for f in decoded if f not in held]
    context.log.info(f"fitting {spec.effects or 'no effects'} on {len(train)} flights")
    try:
        groups = model.sessions(sorted(decoded))
    except sessions.SessionsFileError as exc:
        raise dg.Failure(description=str(exc)) from None
    fitted = fitting.fit_model(spec, decoded, train, groups, context.log.info)
    path = modelmod.save(fitted, fitted_model_path(data_root), train, spec)
    params = [{"effect": t.name, "session": "fleet", "parameter": k, "value": v, "std": t.std.get(k, 0.0)}
              for t in fitted.terms for k, v in t.params.items()]
    params += [{"effect": t.name, "session": s, "parameter": k, "value": v, "std": t.per_session_std[s].get(k, 0.0)}
               for t in fitted.terms for s, values in t.per_session.items() for k, v in values.items()]
    return dg.MaterializeResult(metadata={
        "model": fitted.label,
        MODEL_VERSION: model_version(current_model(data_root, model).to_dict()),
        "effects": dg.MetadataValue.json(fitted.effect_names),
        "parameters": dg.MetadataValue.md(
            plots.markdown_table(pl.DataFrame(params)) if params else "nominal model: no effects"),
        "trained_on": len(train),
        "held_out": ", ".join(held),
        "model_file": spec.source or "(none: nominal)",
        "path": dg.MetadataValue.path(str(path)),
        **skipped_metadata(skipped),
    })


def discovery_path(data_root: DataRoot):
    """Where the ``term_discovery`` asset writes its result."""
    return data_root.root_path / "reports" / "discovery.json"


def _discovery_for(data_root: DataRoot, effects: list[str]) -> dict | None:
    """The last discovery, if it was made on top of these effects (else it is stale)."""
    path = discovery_path(data_root)
    disc = store.read_json(path) if path.is_file() else None
    return disc if disc is not None and disc.get("effects_in_model") == list(effects) else None


def current_model(data_root: DataRoot, model: ModelConfig, log=None):
    """The fitted model if it was fitted for the model file as it is now
    (:func:`quadcore.model.fitted_for`), else the nominal vehicle (said in the log: physics_model
    has not fitted this model file yet)."""
    spec = model.spec()
    path = fitted_model_path(data_root)
    if path.is_file():
        saved = store.read_json(path)
        if modelmod.fitted_for(saved, spec):
            return modelmod.PhysicsModel.from_dict(saved, spec.vehicle)
    if spec.effects and log is not None:
        log.warning(f"physics_model has not fitted {spec.effects} as the model file now asks: using the "
                    "nominal model; materialise physics_model first")
    return modelmod.PhysicsModel(spec.vehicle, [])


@dg.asset(group_name="model", deps=[*ALL_FLIGHTS, physics_model, dg.AssetKey("term_discovery")], kinds={"html"},
          automation_condition=RETRAIN)
def model_diagnosis(context: dg.AssetExecutionContext, data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """Where the model fails (by regime, flight, segment) and which effect is missing, scored on
    held-out flights. Writes reports/diagnosis.{json,md,html} and appends to the history."""
    spec = model.spec()
    decoded, skipped = usable_decoded(data_root, spec.vehicle, context.log)
    if len(decoded) < 2:
        raise dg.Failure(
            description="the diagnosis needs at least two usable decoded flights (one to fit, one to score)")
    seen, holdout = scored_flights(model, decoded)
    try:
        groups = model.sessions(sorted(seen))
    except sessions.SessionsFileError as exc:
        raise dg.Failure(description=str(exc)) from None
    result = diagnosis.diagnose(seen, spec, holdout, log=context.log.info, sessions=groups)
    result["skipped_flights"] = skipped
    out = data_root.root_path / "reports"
    store.write_json(result, out / "diagnosis.json")
    b = result["baseline"]
    history.record(data_root.root_path, "diagnosis", result["model"]["label"], b["force_rmse_N"], b["torque_rmse_Nm"],
                   spec.effects, {e["name"]: e["params"] for e in result["model"]["effects"]},
                   result["evaluation"]["mode"], result["evaluation"]["eval_flights"])
    md, page = report.write(result, out, history.read(data_root.root_path), _discovery_for(data_root, spec.effects))
    top = result["candidates"][:5]
    return dg.MaterializeResult(metadata={
        "verdict": dg.MetadataValue.md(result["verdict"]),
        "model": result["model"]["label"],
        **{f"force_rmse_{a}_N": number(v) for a, v in zip("xyz", b["force_rmse_N"])},
        **{f"torque_rmse_{a}_Nm": number(v) for a, v in zip("xyz", b["torque_rmse_Nm"])},
        "candidates": dg.MetadataValue.md(plots.markdown_table(pl.DataFrame(
            diagnosis.candidate_summary({"candidates": top})))),
        "sensitivity": dg.MetadataValue.md(plots.markdown_table(pl.DataFrame(diagnosis.sensitivity_rows(result)))),
        "sensitivity_json": dg.MetadataValue.json(result["sensitivity"]),
        "disagreements": dg.MetadataValue.md(plots.markdown_table(pl.DataFrame(
            sessions.table_rows(result["disagreements"]))) if result["disagreements"] else "none: one value fits all"),
        "disagreements_json": dg.MetadataValue.json(result["disagreements"]),
        "candidates_plot": plot_md(data_root, report.candidates_plot(result), "candidates"),
        "regimes_plot": plot_md(data_root, report.regimes_plot(result), "regimes"),
        "worst_segments": dg.MetadataValue.md(plots.markdown_table(pl.DataFrame(result["worst_segments"]))),
        **_frequency_metadata(data_root, result.get("frequency")),
        "report": dg.MetadataValue.path(str(page)),
        **skipped_metadata(skipped),
    })


def _frequency_metadata(data_root: DataRoot, freq: dict | None) -> dict:
    """Where the model fails in frequency: the reading, and the band plot."""
    if not freq or not freq.get("channels"):
        return {}
    return {"frequency": dg.MetadataValue.md("\n\n".join(freq["reading"])),
            "frequency_plot": plot_md(data_root, report.frequency_plot(freq), "frequency")}


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
        **{c: number(last[c]) for c in history.RMSE_COLUMNS},
        "history_plot": plot_md(data_root, report.history_plot(hist), "history"),
        "folder": dg.MetadataValue.path(str(history.history_dir(data_root.root_path))),
    })
