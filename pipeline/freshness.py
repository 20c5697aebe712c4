"""Which per-flight results were computed against an older physics model, as an automation condition.

Dagster's ``eager()`` reacts to an upstream *event*: when the model is refitted while a flight's
run is in progress, that run's later materialisation counts as the refresh although it used the
old model, and the flight stays stale. This condition looks at *state* instead: each per-flight
materialisation records the version of the model it used (metadata ``model_version``), and a
partition is stale while that differs from the model a run would use now. So every flight ends
against the current model whatever the timing, and the automation's evaluation in the UI lists
the stale flights with both versions.
"""

from __future__ import annotations

import hashlib
import json

import dagster as dg

from pipeline.resources import data_root_from_env, model_config_from_env
from quadcore.identify.discovery import library_stats
from quadcore.workflows import identify

MODEL_VERSION = "model_version"
STATS_VERSION = "stats_version"  # what a flight's sufficient statistics were computed for


def model_version(model_dict: dict | None) -> str:
    """A short content hash of a physics model (vehicle, thrust map, effects and their fitted
    parameters): equal exactly when the model is the same."""
    text = json.dumps(model_dict, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def current_model_version() -> str:
    """The version of the model a per-flight run would compute against now (the fitted model if
    it matches the model file, else the nominal vehicle: see ``current_model``)."""
    model = identify.current_model(data_root_from_env().root_path, model_config_from_env().spec())
    return model_version(model.to_dict())


def versions_used(instance: dg.DagsterInstance, key: dg.AssetKey, partitions: set[str],
                  entry_key: str = MODEL_VERSION) -> dict[str, str | None]:
    """Partition -> ``model_version`` (or ``entry_key``) of its latest materialisation (None:
    materialised before versions were recorded); partitions never materialised are left out."""
    used: dict[str, str | None] = {}
    cursor = None
    while len(used) < len(partitions):
        page = instance.fetch_materializations(
            dg.AssetRecordsFilter(asset_key=key, asset_partitions=sorted(partitions - set(used))),
            limit=200, cursor=cursor)
        for record in page.records:  # newest first: the first one seen per partition is its latest
            mat = record.asset_materialization
            if mat is not None and mat.partition is not None and mat.partition not in used:
                entry = mat.metadata.get(entry_key)
                used[mat.partition] = str(entry.value) if entry is not None else None
        if not page.has_more:
            break
        cursor = page.cursor
    return used


def _recorded_otherwise(context: dg.AutomationContext, partitions: dg.PartitionsDefinition, candidates,
                        entry_key: str, current_of):
    """(subset, partition -> recorded value, stale partitions): the candidate partitions (of the
    asset's ``partitions``) whose latest materialisation recorded another ``entry_key`` than
    ``current_of(partition)``."""
    used = versions_used(context.asset_graph_view.instance, context.key, set(candidates), entry_key)
    stale = sorted(p for p, v in used.items() if v != current_of(p))
    subset = context.asset_graph_view.get_subset_from_partition_keys(context.key, partitions, set(stale))
    return subset, used, stale


class ComputedAgainstOlderModel(dg.AutomationCondition):
    """True for the flight partitions whose latest materialisation used another physics model
    than the current one."""

    @property
    def name(self) -> str:
        return "computed_against_older_model"

    @property
    def description(self) -> str:
        return "computed against an older physics model"

    def evaluate(self, context: dg.AutomationContext) -> dg.AutomationResult:
        candidates = context.candidate_subset.expensively_compute_partition_keys()
        if not candidates or context.partitions_def is None:
            return dg.AutomationResult(context=context, true_subset=context.get_empty_subset())
        try:
            current = current_model_version()
        except (ValueError, KeyError, OSError) as exc:  # a bad model or vehicle file: the runs say why
            context.log.warning(f"cannot tell the current physics model: {exc}")
            return dg.AutomationResult(context=context, true_subset=context.get_empty_subset())
        subset, used, stale = _recorded_otherwise(context, context.partitions_def, candidates, MODEL_VERSION,
                                                  lambda p: current)
        why = {p: f"computed against model {used[p] or 'of unknown version'}, current is {current}" for p in stale}
        return dg.AutomationResult(context=context, true_subset=subset,
                                   metadata={"current_model_version": current, "stale_flights": len(stale),
                                             "why": dg.MetadataValue.json(why)})


class ModelFileChanged(dg.AutomationCondition):
    """True when the model file names another model than the one fitted
    (:func:`quadcore.workflows.identify.fit_is_stale`), so that editing model.toml (or the
    sessions file) refits without a manual step."""

    @property
    def name(self) -> str:
        return "model_file_changed"

    @property
    def description(self) -> str:
        return "the model file names another model than the one fitted"

    def evaluate(self, context: dg.AutomationContext) -> dg.AutomationResult:
        try:
            changed = identify.fit_is_stale(data_root_from_env().root_path, model_config_from_env().spec())
        except (ValueError, KeyError, OSError) as exc:  # a bad model file: physics_model's run says why
            context.log.warning(f"cannot read the model file: {exc}")
            changed = False
        subset = context.candidate_subset if changed else context.get_empty_subset()
        return dg.AutomationResult(context=context, true_subset=subset)


def inputs_updated(ignore: tuple[str, ...] = ()) -> dg.AutomationCondition:
    """Dagster's ``eager()`` without its "newly missing" trigger: true for a flight partition once
    an input was updated by a run that did not select this asset (``any_deps_updated``: an update
    made by a run that selected it is that run's own), until it is requested or updated; never
    while an input is missing or in progress, or the asset is.

    A new flight's tables are computed by the run that decodes it (the raw-log sensor's
    ``process_flight`` run, which selects every per-flight asset, or the main job). ``eager()``
    would also arm on the flight being *newly missing* when the sensor adds its partition, and
    request the flight again at any tick where that run's remaining steps are not seen as in
    progress: the new flight computed twice."""
    skip = dg.AssetSelection.assets(*ignore)
    return (dg.AutomationCondition.any_deps_updated().ignore(skip).since_last_handled()
            & ~dg.AutomationCondition.any_deps_missing().ignore(skip)
            & ~dg.AutomationCondition.any_deps_in_progress().ignore(skip)
            & ~dg.AutomationCondition.in_progress()).with_label("an input changed outside its own run")


# Recompute a flight's table when its own inputs changed outside the run that made it (its decoded
# table: a refit of physics_model alone is not a reason, as a new flight refits it without
# changing the model), and whenever it was computed against an older model than the current one
# (state, so a refit that moved a parameter, or a run that overlapped a refit, is caught); never
# while a run for it is going on, and not again after a failure.
REFRESH = (
    inputs_updated(ignore=("physics_model",))
    | (ComputedAgainstOlderModel()
       & ~dg.AutomationCondition.in_progress()
       & ~dg.AutomationCondition.any_deps_in_progress()
       & ~dg.AutomationCondition.execution_failed())
).with_label("recompute when its decoded table changes outside its own run, or when computed against an older model")


class StatisticsOutdated(dg.AutomationCondition):
    """True for the flight partitions whose statistics were computed for another vehicle,
    session thrust map or effect library than the model file gives now (metadata
    ``stats_version`` against :func:`quadcore.identify.discovery.library_stats.version`). Not the
    fitted model's version: the fit is made from the statistics, so that would be a cycle."""

    @property
    def name(self) -> str:
        return "statistics_outdated"

    @property
    def description(self) -> str:
        return "computed for another vehicle, thrust map or effect library"

    def evaluate(self, context: dg.AutomationContext) -> dg.AutomationResult:
        candidates = context.candidate_subset.expensively_compute_partition_keys()
        if not candidates or context.partitions_def is None:
            return dg.AutomationResult(context=context, true_subset=context.get_empty_subset())
        try:
            spec = model_config_from_env().spec()
        except (ValueError, KeyError, OSError) as exc:  # a bad model file: the runs say why
            context.log.warning(f"cannot read the model file: {exc}")
            return dg.AutomationResult(context=context, true_subset=context.get_empty_subset())
        subset, _, stale = _recorded_otherwise(context, context.partitions_def, candidates, STATS_VERSION,
                                               lambda p: library_stats.version(spec, p))
        return dg.AutomationResult(context=context, true_subset=subset, metadata={"stale_flights": len(stale)})


# A flight's statistics: computed with its decode (by that run), again when it is decoded outside
# that run or the model file names another vehicle, thrust map or effect library; never while a run
# for it is going on or after a failure.
STATS_REFRESH = (
    inputs_updated()
    | (StatisticsOutdated()
       & ~dg.AutomationCondition.in_progress()
       & ~dg.AutomationCondition.any_deps_in_progress()
       & ~dg.AutomationCondition.execution_failed())
).with_label("again when decoded outside its own run, or when the model file names another vehicle, thrust map "
              "or effect library")
