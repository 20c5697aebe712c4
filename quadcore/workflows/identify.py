"""Identification workflows: fit the model a spec names, diagnose what it misses, discover the
terms the library lacks, and write each result where it belongs under the data root (or where
the CLI was told to). The CLI and the assets call these; they only print or attach metadata."""

from __future__ import annotations

import json
import shlex
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from quadcore.commands import quadcore_command
from quadcore.identify import diagnosis, history, model
from quadcore.identify.diagnosis import rate_cache
from quadcore.identify.fit import model_fit
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.identify.stats import sufficient
from quadcore.store import store
from quadcore.workflows import reports
from quadcore.workflows.fleet import Fleet, WorkflowError, held_out, sessions_of

if TYPE_CHECKING:
    from quadcore.identify.diagnosis.results import Diagnosis
    from quadcore.identify.discovery import Discovery
    from quadcore.identify.model import FittedModel, PhysicsModel
    from quadcore.spec.model import ModelSpec

Log = Callable[[str], None]


def _quiet(msg: str) -> None:
    pass


def fit(fleet: Fleet, spec: ModelSpec, holdout: list[str], log: Log = _quiet, stats=None) -> FittedModel:
    """The spec's effects fitted on every flight of the fleet but the named held-out ones
    (:func:`quadcore.workflows.fleet.held_out`: by default none), per session where the spec asks
    (sessions from its sessions file, its model file, or the data). ``stats``: the flights' stored
    sufficient statistics (:func:`quadcore.identify.stats.sufficient.stored`), combined for linear
    effects instead of reading rows."""
    if not fleet.tables:
        raise WorkflowError("fitting needs at least one usable decoded flight")
    held = held_out(holdout, fleet.ids)
    train = [f for f in fleet.tables if f not in held]
    log(f"fitting {spec.effects or 'no effects'} on {len(train)} flights"
        + (f" (held out: {', '.join(held)})" if held else " (every flight: nothing held out)"))
    fitted = model_fit.fit_model(spec, fleet.tables, train, sessions_of(spec, fleet.ids), log, stats)
    return model.FittedModel.of(fitted, spec, train, held)


def save_fit(root, fitted: FittedModel) -> Path:
    """Write the fitted model file (``store.physics_model_path``)."""
    return store.write_json(fitted.to_dict(), store.physics_model_path(root))


def current_model(root, spec: ModelSpec, warn: Log = _quiet) -> PhysicsModel:
    """The fitted model under ``root`` if it was fitted for ``spec`` as it is now
    (:func:`quadcore.identify.model.fitted_for`), else the nominal vehicle (said through ``warn`` when
    the spec has effects: the fit has not been made for it yet)."""
    path = store.physics_model_path(root)
    if path.is_file():
        saved = store.read_json(path)
        if model.fitted_for(saved, spec):  # the spec's digest covers its plugins' content: they are loaded
            model.check_plugins(saved, str(path))
            return model.PhysicsModel.from_dict(saved, spec.vehicle)
    if spec.effects:
        warn(f"physics_model has not fitted {spec.effects} as the model file now asks: using the "
             "nominal model; materialise physics_model first")
    return model.PhysicsModel(spec.vehicle, [])


def fit_is_stale(root, spec: ModelSpec) -> bool:
    """Whether the saved fit was made for another spec than ``spec`` (an effect added, a fixed
    value changed, a sessions file edited...). False when nothing is fitted."""
    path = store.physics_model_path(root)
    return path.is_file() and not model.fitted_for(store.read_json(path), spec)


# --- diagnosis -----------------------------------------------------------------------------

class TooFewFlights(WorkflowError):
    """Too few flights for the diagnosis or the discovery (a young fleet)."""


def diagnosis_flights(fleet: Fleet, named: list[str], where: str = "the decoded flights"
                      ) -> tuple[Fleet, list[str] | None]:
    """(the flights a diagnosis or discovery sees, its holdout or None for cross-validation):
    every flight; scored on the named holdout (checked) when there is one, else cross-validated
    over them all. The one protocol of ``quadcore diagnose`` / ``discover`` and the assets."""
    holdout = held_out(named, fleet.ids, where)
    return fleet, holdout or None


def diagnose(fleet: Fleet, spec: ModelSpec, named_holdout: list[str], log: Log = _quiet,
             where: str = "the decoded flights", stats=None, discover_command: str | None = None,
             settings: DiagnosisSettings = DEFAULT, root=None) -> Diagnosis:
    """:func:`quadcore.identify.diagnosis.diagnose` on the flights :func:`diagnosis_flights` picks,
    with the flights skipped on the way (``skipped_flights``). ``stats`` as for :func:`fit`;
    ``discover_command``: the command the verdict points to when what is left is outside the library;
    ``settings``: its thresholds and folds; ``root``: the data root the flights are decoded under,
    where the rate level's per-flight sums are kept between diagnoses
    (:mod:`quadcore.identify.diagnosis.rate_cache`: a new flight's rows are read, the others' sums reused)."""
    seen, holdout = diagnosis_flights(fleet, named_holdout, where)
    log(f"diagnosing {len(seen.tables)} flights against {spec.effects or 'the nominal model'}")
    result = diagnosis.diagnose(seen.tables, spec, holdout, log=log, sessions=sessions_of(spec, seen.ids),
                                stats=stats, discover_command=discover_command, settings=settings,
                                rate_cache=rate_cache.stored(root) if root is not None else None)
    return result.with_skipped(fleet.skipped)


def discover_command(data, spec: ModelSpec, holdout: list[str]) -> str:
    """The ``quadcore discover`` command on the logs in ``data`` with the model ``spec`` (its
    file, or its effects) and ``holdout``: what a diagnosis points to when what is left is
    outside the library."""
    parts = [quadcore_command(), "discover", str(data), "--json", "discovery.json"]
    if spec.source:
        parts += ["--model", spec.source]
    elif spec.effects:
        parts += ["--effects", ",".join(spec.effects)]
    if holdout:
        parts += ["--holdout", ",".join(holdout)]
    return shlex.join(parts)


def diagnosis_json(result: Diagnosis) -> str:
    """The diagnosis as its JSON text, the document ``quadcore diagnose --json`` and
    ``reports/diagnosis.json`` hold (``tests/test_json_contracts.py`` pins it)."""
    return json.dumps(result.to_dict(), indent=2, default=float)


def write_diagnosis_json(result: Diagnosis, path) -> Path:
    return store.write_text(diagnosis_json(result), path)


def discovery_for(reports_dir, effects: list[str]) -> dict | None:
    """The discovery kept in ``reports_dir`` (``discovery.json``), if it was made on top of these
    effects (otherwise it is about another model, and left out)."""
    path = store.as_root(reports_dir) / store.DISCOVERY_FILE  # a folder here or in an object store
    disc = store.read_json(path) if path.is_file() else None
    return disc if disc is not None and disc.get("effects_in_model") == list(effects) else None


def write_diagnosis_report(result: Diagnosis, reports_dir, root=None, model_file: str = "",
                           rerun: str = "") -> tuple[Path, Path]:
    """The diagnosis report (Markdown and HTML, with the plots) in ``reports_dir``, with the
    discovery kept beside it (:func:`discovery_for`) and, given the data ``root``, the error
    history; ``model_file``: the file its next step tells to edit, ``rerun``: the command it
    tells to run again. The one report path of ``quadcore diagnose --report`` and ``model_diagnosis``."""
    hist = history.read(root) if root is not None else None
    return reports.diagnosis.write(result.to_dict(), reports_dir, hist,
                                  discovery_for(reports_dir, list(result.effects_in_model)), model_file, rerun)


def record_diagnosis(root, result: Diagnosis, spec: ModelSpec, rerun: str = "") -> tuple[Path, Path]:
    """Write a data root's diagnosis: ``reports/diagnosis.json``, a row of the error history and
    the report (its next step naming ``rerun``, the command that runs again). Returns the report's (md, html)."""
    write_diagnosis_json(result, store.diagnosis_path(root))
    b, ev = result.baseline, result.evaluation
    history.record(root, "diagnosis", result.model.label, list(b.force_rmse_N), list(b.torque_rmse_Nm),
                   spec.effects, {t.name: t.params for t in result.model.terms}, ev.mode, list(ev.eval_flights))
    return write_diagnosis_report(result, store.reports_dir(root), root, spec.source, rerun)


def suggestion(result: dict) -> str | None:
    """The top candidate of a diagnosis document (``reports/diagnosis.json``) if it is found
    (explains something, significantly)."""
    useful = [r for r in result["candidates"] if r["useful"]]
    return useful[0]["effect"] if useful else None


def next_step(effect: str, model_file: str, rerun: str = "") -> str:
    """The hint that follows a diagnosis suggesting ``effect``, naming the model file to edit
    (the one the run used: see ``pipeline.resources.model_file_from_env``) and ``rerun``, the
    command that runs again with the same settings."""
    again = f"run again: {rerun}" if rerun else "run again."
    if model_file:
        return f"add {effect!r} to `effects` in {model_file} and {again}"
    return (f"write a model file with effects = [\"{effect}\"] (copy the repository's model.toml) and name it with "
            f"QUADCORE_MODEL=FILE (or --model FILE), then {again}")


# --- discovery -----------------------------------------------------------------------------

MIN_DISCOVERY_TRAINING = 2  # discovery's folds are grouped by flight


def discover(fleet: Fleet, spec: ModelSpec, named_holdout: list[str], log: Log = _quiet,
             where: str = "the decoded flights", root=None, settings: DiagnosisSettings = DEFAULT) -> Discovery:
    """:func:`quadcore.identify.discovery.discover` on the flights the diagnosis sees (:func:`diagnosis_flights`);
    with a data ``root``, from the flights' stored statistics there (:mod:`quadcore.identify.discovery.library_stats`).
    ``settings``: its folds and thresholds. Raises :class:`TooFewFlights` with fewer than two training flights."""
    # scikit-learn (the discovery package's selection): ~0.7 s CPU that fit and diagnose do not need
    from quadcore.identify import discovery

    seen, holdout = diagnosis_flights(fleet, named_holdout, where)
    if len(seen.tables) - len(holdout or []) < MIN_DISCOVERY_TRAINING:
        raise TooFewFlights("discovery needs at least two training flights besides the held-out ones (its folds "
                            "are grouped by flight)")
    stored = stats = None
    if root is not None:
        stored, stats = discovery.library_stats.stored(root, spec), sufficient.stored(root, spec)
    return discovery.discover(seen.tables, spec, holdout, log=log, sessions=sessions_of(spec, seen.ids),
                              stored=stored, stats=stats, settings=settings)


def write_discovery(result: Discovery, path) -> Path:
    return store.write_json(result.to_dict(), path)
