"""Learning workflows: the residual tables the learned models learn from, the feature sets, the
training with its holdout checked against the physics fit, and the report. ``quadcore train``
and the learning assets call these."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from quadcore.identify import history
from quadcore.identify.model import PLUGINS, SPEC_DIGEST
from quadcore.learn import artefacts, evaluation, experiments, features as feat, learners, splits
from quadcore.learn.learners import DEFAULT_ROW_BUDGET
from quadcore.physics import decoded_store
from quadcore.store import store
from quadcore.store.names import MAIN_EVENT
from quadcore.workflows import identify, reports
from quadcore.workflows.fleet import Fleet, WorkflowError, _subset, duplicates, held_out

if TYPE_CHECKING:
    import polars as pl

    from quadcore.identify.model import PhysicsModel
    from quadcore.learn.experiments import Plan, RunRecord
    from quadcore.learn.features import FeatureSet
    from quadcore.learn.learners import LearnerSpec, TrainConfig
    from quadcore.spec.model import ModelSpec

Log = Callable[[str], None]


def _quiet(msg: str) -> None:
    pass


@dataclass(frozen=True)
class LearningRequest:
    """What to train: model kinds, each kind's options (``depth=4,trees=300``, ``hidden=64x64``),
    the comparisons, and the training settings (``max_rows``: the row budget, see
    :data:`quadcore.learn.learners.DEFAULT_ROW_BUDGET`)."""

    models: tuple[str, ...] = ("xgboost", "mlp")
    options: dict[str, str] = field(default_factory=dict)  # kind -> options
    loo: bool = False
    compare: bool = True
    stride: int = 5
    seed: int = 0
    threads: int = 1
    max_rows: int = DEFAULT_ROW_BUDGET

    def learner_specs(self) -> dict[str, LearnerSpec]:
        """Kind -> learner spec (:class:`quadcore.learn.learners.LearningError` for a bad option or kind)."""
        if not self.models:
            raise learners.LearningError("no model kind named")
        if self.stride < 1 or self.threads < 1:
            raise learners.LearningError("stride and threads must be at least 1")
        learners.check_row_budget(self.max_rows)
        return {k: learners.parse_spec(f"{k}:{self.options[k]}" if self.options.get(k) else k) for k in self.models}

    def config(self) -> TrainConfig:
        return learners.TrainConfig(stride=self.stride, max_rows=self.max_rows, seed=self.seed, threads=self.threads)


def residual_tables(tables: Mapping[str, pl.DataFrame], physics: PhysicsModel) -> dict[str, pl.DataFrame]:
    """Each flight's residual table against ``physics``, with its session's values and thrust map."""
    return {fid: physics.for_flight(fid).residual_table(df) for fid, df in tables.items()}


def physics_of_residuals(root) -> dict:
    """The physics model the data root's residual tables were computed against (their metadata),
    with the flights its effects were fitted on and the digest of the spec it was fitted for when
    the fitted model file is that model (the same values: a later refit of the same effects is not).
    :class:`WorkflowError` when the tables were computed against different models (some not
    refreshed after a refit)."""
    files = sorted((store.as_root(root) / "residuals").glob("flight=*/data.parquet"))
    models = {f.parent.name.split("=", 1)[1]: store.read_metadata(f).get("model", {}) for f in files}
    distinct = {json.dumps(m, sort_keys=True) for m in models.values()}
    if len(distinct) > 1:
        def users(d: str) -> int:
            return sum(json.dumps(m, sort_keys=True) == d for m in models.values())
        latest = json.loads(max(distinct, key=users))
        stale = sorted(f for f, m in models.items() if m != latest)
        raise WorkflowError(
            f"the residual tables were computed against different physics models (not refreshed after a "
            f"refit?): re-materialise residual_table for {', '.join(stale)}")
    physics: dict = next(iter(models.values()), {})
    fitted = store.physics_model_path(root)
    if fitted.is_file():
        saved = store.read_json(fitted)
        if physics and all(saved.get(k) == v for k, v in physics.items()):  # that fit, not a later one
            physics["trained_on"] = saved.get("trained_on")
            physics[SPEC_DIGEST] = saved.get(SPEC_DIGEST)
            if saved.get(PLUGINS):  # a learned model's manifest must name them for export-c
                physics[PLUGINS] = saved[PLUGINS]
    return physics


def _recorded_digest(root, fid: str) -> str | None:
    """The SHA-256 of the log a flight was decoded from, as its decoded main table records it."""
    recorded = decoded_store.recorded_provenance(root, MAIN_EVENT, fid)
    return recorded.source_sha256 if recorded is not None else None


def build_features(root, feature_sets: list[str]) -> tuple[list[FeatureSet], int]:
    """Every feature set's table per flight from the data root's residual tables (swapped in
    whole under ``features/``), each log once (a copy of another flight's log is left out, as
    :func:`quadcore.workflows.fleet.usable` leaves it out of the fit). Returns (the sets, the
    number of flights)."""
    physics = physics_of_residuals(root)  # every residual table against one physics model
    res = feat.read_residual_tables(root)
    copies = duplicates(res, lambda fid: _recorded_digest(root, fid))  # as the fleet stages skip them
    res = _subset(res, [fid for fid in res if fid not in copies])
    if not res:
        raise WorkflowError(f"no residual tables in {store.as_root(root) / 'residuals'}: materialise residual_table "
                            "first")
    try:
        sets = feat.parse(feature_sets)
        feat.replace_feature_tables(root, res, sets, {"model": physics.get("label", "")})
    except feat.FeatureError as exc:
        raise WorkflowError(str(exc)) from None
    return sets, len(res)


def learning_holdout(requested: str | None, flights: list[str], named_model_holdout: list[str] | None = None,
                     explicit: bool = False) -> tuple[str, str]:
    """(the flight the learned models are scored on, note). A learned model needs a flight it
    never saw to be scored: ``requested`` (with ``explicit``, it must exist), else the physics
    model's named held-out flight (``QUADCORE_HOLDOUT``: the first), else the learning's own
    default, :data:`quadcore.learn.splits.DEFAULT_HOLDOUT` (jana02, the reference data set's)
    where there is one, else the last flight in sorted order. The choice never changes the
    physics fit or the diagnosis: without a named holdout both use every flight."""
    if requested:
        return splits.resolve_holdout(requested, flights, explicit=explicit)
    named = held_out(list(named_model_holdout or []), flights)
    if named:
        return named[0], ""
    flight, _ = splits.resolve_holdout(splits.DEFAULT_HOLDOUT, flights)
    return flight, (f"the learned models are scored on {flight}, which they never see in training (the learning's "
                    f"default test flight: {splits.DEFAULT_HOLDOUT} where there is one, else the last flight); no "
                    "holdout is named (QUADCORE_HOLDOUT), so the physics model under them is fitted on every "
                    f"flight, {flight} included")


@dataclass(frozen=True)
class TrainedRuns:
    """What a training wrote under ``out_dir``: the run records, the holdout and the plan's notes."""

    records: tuple[RunRecord, ...]
    holdout: str
    notes: tuple[str, ...]
    out_dir: Path  # or a UPath in an object store


def train(tables_by_set: Mapping[str, Mapping[str, pl.DataFrame]], sets: list[FeatureSet], holdout: str, physics: dict,
          request: LearningRequest, flight_kinds: dict[str, str], out_dir, log: Log = _quiet,
          named: bool = True) -> TrainedRuns:
    """Plan the experiments (:func:`quadcore.learn.experiments.plan`) and run them into ``out_dir``.
    Refuses a ``named`` holdout (asked for, by the learning or ``QUADCORE_HOLDOUT``) that the
    physics model's effects were fitted on: the learned models would be scored on a flight the
    physics under them has seen although the user held it out. The default test flight
    (:func:`learning_holdout`, nothing named) sits on a physics model fitted on every flight:
    allowed, and the learning report says so."""
    flights = sorted(next(iter(tables_by_set.values())))
    if named and holdout in (physics.get("trained_on") or []):
        raise learners.LearningError(
            f"the physics model's effects were fitted on {holdout}, the flight the learned models are scored "
            f"on: re-materialise physics_model with the same holdout, then residual_table")
    plan: Plan = experiments.plan(flights, sets, list(request.models), holdout, flight_kinds, request.loo,
                               request.compare, request.learner_specs())
    log(f"training {len(plan.experiments)} models, holdout {holdout} -> {out_dir}")
    records = experiments.run_plan(plan, tables_by_set, out_dir, physics, request.config(), flight_kinds, log=log)
    return TrainedRuns(tuple(records), holdout, tuple(plan.notes), out_dir)


def train_data_root(root, request: LearningRequest, requested_holdout: str, model_holdout: list[str],
                    flights_csv, log: Log = _quiet) -> TrainedRuns:
    """The learning assets' training: the feature tables under ``root``, the physics model their
    residuals were computed against, the holdout (``requested_holdout``, else the physics
    model's), then :func:`train` into ``root/learned``. The holdout's note leads the notes."""
    sets, tables = feat.read_feature_tables(root)
    if not sets:
        raise WorkflowError(f"no feature tables in {store.features_dir(root)}: materialise learning_features first")
    physics = physics_of_residuals(root)
    holdout, note = learning_holdout(requested_holdout, sorted(next(iter(tables.values()))), model_holdout)
    runs = train(tables, sets, holdout, physics, request, feat.read_flight_kinds(flights_csv),
                 store.learned_dir(root), log, named=bool(requested_holdout or model_holdout))
    return replace(runs, notes=(note, *runs.notes)) if note else runs


@dataclass(frozen=True)
class Training:
    """What ``quadcore train`` did: the physics model under the learned ones, the holdout and the
    flights trained on, the runs, and the learning report (its document and files)."""

    physics: PhysicsModel
    holdout: str
    trained_on: tuple[str, ...]
    runs: TrainedRuns
    report: dict
    paths: dict[str, Path]


def train_on_flights(flights: Fleet, spec: ModelSpec, feature_sets: list[FeatureSet], request: LearningRequest,
                     holdout: str, flight_kinds: dict[str, str], out, log: Log = _quiet) -> Training:
    """``quadcore train``: fit the spec's effects on every flight but ``holdout``, build each
    flight's residual and feature tables against that fit (its session's values), train into
    ``out/learned`` and write the learning report (and the history) under ``out``."""
    fitted = identify.fit(flights, spec, [holdout], log if spec.effects else _quiet)
    res = residual_tables(flights.tables, fitted.model)
    try:
        by_set = feat.feature_tables(res, feature_sets)
    except feat.FeatureError as exc:
        raise WorkflowError(str(exc)) from None
    runs = train(by_set, feature_sets, holdout, fitted.to_dict(), request, flight_kinds, store.learned_dir(out), log)
    report, _, paths = write_learning_report(out, res, list(fitted.trained_on))
    return Training(fitted.model, holdout, fitted.trained_on, runs, report, paths)


def full_report(out_dir: str | Path, residual_tables: Mapping[str, pl.DataFrame], vehicle, report_dir: str | Path,
                root_for_history: str | Path | None = None,
                physics_trained_on: list[str] | None = None) -> tuple[dict, dict[str, bytes], dict[str, Path]]:
    """Evaluate (:func:`quadcore.learn.evaluation.evaluate`), record the history (when
    ``root_for_history``), plot and write the report (:mod:`quadcore.report.learning`).
    ``physics_trained_on``: the flights the physics model's effects were fitted on (default: as
    the index says). Returns (report, plots, paths)."""
    report = evaluation.evaluate(out_dir, residual_tables, vehicle, physics_trained_on)
    hist = None
    if root_for_history is not None:
        report["history_files"] = [str(p) for p in evaluation.record_history(root_for_history, report)]
        hist = history.read(root_for_history)
    pngs = reports.learning.make_plots(report, out_dir, residual_tables, vehicle, hist)
    paths = reports.learning.write_report(report, pngs, report_dir)
    return report, pngs, paths


def write_learning_report(root, residuals: Mapping[str, pl.DataFrame] | None = None,
                          trained_on: list[str] | None = None) -> tuple[dict, dict[str, bytes], dict[str, Path]]:
    """Evaluate the learned models under ``root/learned`` against ``residuals`` (default: the
    data root's residual tables), record the history and write ``reports/learning.{md,html,json}``.
    Returns (report, plots, paths)."""
    index, _ = experiments.read_runs(store.learned_dir(root))
    physics = index.get("physics_model", {})
    residuals = residuals if residuals is not None else feat.read_residual_tables(root)
    return full_report(store.learned_dir(root), residuals, artefacts.vehicle_of(physics),
                                  store.reports_dir(root), root, trained_on)


def learning_is_stale(root) -> str | None:
    """Why the learned models must be retrained now, or None: there are none yet; they were
    trained on top of another physics model than the residual tables' (other effects, vehicle
    or thrust map); or for another model spec than the current fit's (``spec_digest``: a fixed
    value, a per-session effect, a sessions file or a plugin's code changed). A refit on new
    flights alone waits for the nightly retraining."""
    index_path = store.learned_dir(root) / "index.json"
    if not index_path.is_file() or not store.learning_report_path(root).is_file():
        return "no learned models yet"
    tables = sorted((store.as_root(root) / "residuals").glob("flight=*/data.parquet"))
    if not tables:
        return None
    current = store.read_metadata(tables[-1]).get("model", {})
    trained = store.read_json(index_path).get("physics_model", {})

    def kind(m):
        return ([e["name"] for e in m.get("effects", [])], m.get("vehicle"), m.get("thrust_map"))

    if kind(current) != kind(trained):
        return f"the physics model changed ({trained.get('label')} -> {current.get('label')})"
    fitted = store.physics_model_path(root)
    digest = store.read_json(fitted).get(SPEC_DIGEST) if fitted.is_file() else None
    if digest is not None and trained.get(SPEC_DIGEST) != digest:
        return (f"the model spec changed since they were trained (spec {trained.get(SPEC_DIGEST) or 'unknown'} "
                f"-> {digest}: a fixed value, per-session effect, sessions file or plugin)")
    return None
