"""The identified model as C for a flight controller: ``quadcore export-c``.

Writes ``quadcore_model.h`` and ``quadcore_model.c``, self-contained C99: one function,
``quadcore_residual(&in, &mem, &out)``, takes the state and inputs the model uses (a struct
with SI units in its field names) and returns the residual force (N) and torque (N m) in the
body frame that the nominal model (thrust map and rigid body) misses:

    out = effects' wrench (physics model, fitted parameters as constants)
        + learned residual (XGBoost trees as node arrays, or the MLP's weights with its scaling)

Single precision, no heap, nothing but ``math.h``; the flash and RAM footprint, measured by
compiling it, is written in a comment at the top of both files. Every effect gives its own C
form through ``Effect.c_code`` (:mod:`quadcore.effects.ccode`); an effect without one stops the export
with :class:`NoCFormError` naming it, or (``leave_out``, what the pipeline's ``exported_model``
asks for, so that one plugin cannot fail the user's job) is left out and named at the top of the
files and in ``Generated.left_out``.

What to export (:func:`load_source`): a learned model's folder (its manifest names the physics
model it sits on), a fitted physics model's JSON file (``models/physics_model.json``), or a data
root / ``learned`` folder, from which the best learned run of the requested kind is taken (lowest
validation loss among causal feature sets, as in the learning report) with its physics model.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.effects.c_inputs import ExportError, Field
from quadcore.export.c.build import CompileError, Footprint, HostModel, check_strict, measure_footprint
from quadcore.export.c.generate import HEADER, SOURCE, Generated, NoCFormError, generate
from quadcore.identify.model import PhysicsModel, check_plugins
from quadcore.learn import artefacts, evaluation, experiments, learners
from quadcore.spec.model import ModelFileError
from quadcore.store import store

__all__ = ["ExportError", "NoCFormError", "CompileError", "Exported", "Footprint", "HostModel", "export",
           "export_models", "load_source", "input_rows", "LEARNED_KINDS"]

LEARNED_KINDS = ("xgboost", "mlp", "none")


@dataclass(frozen=True)
class Exported:
    """The written files and what they hold."""

    header: Path
    source: Path
    generated: Generated
    footprint: Footprint | None

    @property
    def fields(self) -> tuple[Field, ...]:
        return self.generated.fields

    def to_dict(self) -> dict:
        return {"header": str(self.header), "source": str(self.source), "model": self.generated.label,
                "inputs": {f.name: {"length": f.size, "columns": list(f.columns), "logged_as": f.logged_as()}
                           for f in self.fields},
                "features": list(self.generated.feature_columns), "learned": self.generated.learned,
                "footprint": self.footprint.to_dict() if self.footprint else None}


def _physics_from_json(path: Path) -> PhysicsModel:
    try:
        d = store.read_json(path)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ExportError(f"{path}: not a fitted physics model (not JSON: {exc})") from None
    if not isinstance(d, dict) or "effects" not in d or "vehicle" not in d:
        raise ExportError(f"{path}: not a fitted physics model (no 'vehicle' and 'effects')")
    try:
        check_plugins(d, str(path))  # plugin effects come from the user's model file, never from the JSON
    except ModelFileError as exc:
        raise ExportError(str(exc)) from None
    return PhysicsModel.from_dict(d, artefacts.vehicle_of(d))


def _best_run(learned_dir: Path, kind: str) -> Path:
    index, records = experiments.read_runs(learned_dir)
    hold = [{**r, "causal": r["feature_set"].get("causal", True)} for r in records
            if r["split"]["name"] == f"holdout-{index['holdout']}"]
    best = evaluation.best_runs(hold)
    if kind not in best:
        raise ExportError(f"no {kind} run on causal features in {learned_dir}: "
                          f"train one (quadcore train --models {kind})")
    return store.as_root(best[kind]["path"])


def load_source(path: str | Path, learned_kind: str = "xgboost"
                ) -> tuple[PhysicsModel, artefacts.LearnedModel | None, str]:
    """(physics model, learned model or None, a description of where they came from)."""
    if learned_kind not in LEARNED_KINDS:
        raise ExportError(f"unknown learned kind {learned_kind!r}; choose one of {', '.join(LEARNED_KINDS)}")
    where: Path = store.as_root(path)  # a local path, or a UPath in an object store
    if where.is_file():
        return _physics_from_json(where), None, f"physics model {where}"
    if not where.is_dir():
        raise ExportError(f"no model at {where}: give a learned model folder, a physics_model.json or a data root")
    if (where / "manifest.json").is_file():
        folder = where
    else:
        learned_dir = where / "learned" if (where / "learned" / "index.json").is_file() else where
        if learned_kind == "none" or not (learned_dir / "index.json").is_file():
            physics_file = store.physics_model_path(where)
            if not physics_file.is_file():
                raise ExportError(f"{where}: no learned models (learned/index.json) and no models/physics_model.json")
            return _physics_from_json(physics_file), None, f"physics model {physics_file}"
        folder = _best_run(learned_dir, learned_kind)
    try:
        model = artefacts.load(folder)
        physics = model.physics_model()
    except (learners.LearningError, ModelFileError, OSError, json.JSONDecodeError) as exc:
        raise ExportError(f"cannot load the learned model in {folder}: {exc}") from None
    if learned_kind == "none":
        return physics, None, f"the physics model of learned model {folder}"
    return physics, model, f"learned model {folder.name} and its physics model"


def export_models(physics: PhysicsModel, learned: artefacts.LearnedModel | None, out_dir: str | Path,
                  provenance: str = "", leave_out: bool = False) -> Exported:
    """Generate, check with the strict C99 flags when a compiler is present, measure the
    footprint, and write ``quadcore_model.{h,c}`` under ``out_dir`` (each atomically). An effect
    with no C form stops it (:class:`NoCFormError`), or with ``leave_out`` is left out and named
    in the files and ``generated.left_out``."""
    split = [t.name for t in physics.terms if t.per_session]
    if split or physics.session_maps:  # C has one set of constants: say which
        note = (f"per-session parameters ({', '.join(split)}) at their fleet values" if split else "") + (
            "; " if split and physics.session_maps else "") + (
            f"the fleet thrust map ({physics.vehicle.thrust_map_kind}), not the sessions' own"
            if physics.session_maps else "")
        warnings.warn(f"export-c: {note}: export a model fitted on one session for that session's values",
                      stacklevel=2)
        provenance = f"{provenance} ({note})"
    first = generate(physics, learned, provenance, leave_out=leave_out)
    footprint = measure_footprint(first)
    gen = generate(physics, learned, provenance, footprint.comment() if footprint else
                   "Footprint: not measured (no C compiler where this was exported).", leave_out)
    if footprint is not None:  # a compiler is here: refuse code that does not pass the strict flags
        check_strict(gen)
    out = store.as_root(out_dir)
    header = store.write_text(gen.header, out / HEADER)
    source = store.write_text(gen.source, out / SOURCE)
    return Exported(header, source, gen, footprint)


def export(path: str | Path, out_dir: str | Path, learned_kind: str = "xgboost", leave_out: bool = False) -> Exported:
    """``quadcore export-c``: :func:`load_source`, then :func:`export_models`."""
    physics, learned, provenance = load_source(path, learned_kind)
    return export_models(physics, learned, out_dir, provenance, leave_out)


def input_rows(table: pl.DataFrame, fields: tuple[Field, ...]) -> np.ndarray:
    """A decoded ``fixedFrequency`` (or residual) table as the rows the input struct takes,
    (n, width) float32, fields in struct order; ``dt_s`` is the flight's median sample period,
    as the Python model uses it."""
    blocks = []
    for f in fields:
        if f.name == "dt_s":
            t = table["t_s"].to_numpy()
            blocks.append(np.full((table.height, 1), float(np.median(np.diff(t))) if len(t) > 1 else 0.0))
            continue
        missing = [c for c in f.columns if c not in table.columns]
        if missing:
            raise ExportError(f"the table lacks {', '.join(missing)} for the input field {f.name}")
        blocks.append(table.select(f.columns).to_numpy().astype(np.float64))
    if not blocks:
        return np.zeros((table.height, 1), np.float32)
    return np.ascontiguousarray(np.concatenate(blocks, axis=1).astype(np.float32))
