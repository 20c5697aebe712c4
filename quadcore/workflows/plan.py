"""The flight-planning workflow: diagnose the flights, plan the flight that answers the open
question (:func:`quadcore.plan.planner.plan`), and write the trajectory CSV, the JSON document
and the picture. ``quadcore plan`` and the ``flight_plan`` asset call these."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from quadcore.identify.diagnosis.results import CandidateScore, Diagnosis, Evaluation, ResidualRmse, Stability
from quadcore.identify.model import PhysicsModel
from quadcore.identify.settings import DiagnosisSettings
from quadcore.identify.stats import sufficient
from quadcore.plan import output, pieces, planner
from quadcore.store import store
from quadcore.workflows.fleet import Fleet, WorkflowError, sessions_of

if TYPE_CHECKING:
    from quadcore.plan.planner import FlightPlan, PlanRequest
    from quadcore.spec.model import ModelSpec

Log = Callable[[str], None]


def _quiet(msg: str) -> None:
    pass


def plan(fleet: Fleet, spec: ModelSpec, diag: Diagnosis, request: PlanRequest, log: Log = _quiet,
         stats=None) -> FlightPlan:
    """The plan for ``diag`` (a diagnosis of ``fleet``'s flights with ``spec``); ``stats``: the
    flights' stored statistics (:func:`quadcore.identify.stats.sufficient.stored`)."""
    seen = fleet.only(sorted({*diag.evaluation.train_flights, *diag.evaluation.eval_flights}))
    return planner.plan(seen.tables, spec, diag, request, sessions_of(spec, seen.ids), log, stats)


@dataclass(frozen=True)
class Written:
    """Where the plan went: the JSON, the CSV (None when nothing was planned) and the picture."""

    json: Path
    trajectory: Path | None
    plot: Path | None


def plot_png(result: FlightPlan) -> bytes | None:
    """The picture of a plan (None when nothing was planned)."""
    if not result.planned or result.path is None:
        return None
    path = result.path
    speed = np.linalg.norm(path.v_w_mps, axis=1)
    q = result.question
    title = (f"separate {q.candidates[0]} from {q.candidates[1]}" if q.kind == "separate"
             else f"pin down {q.parameter}")
    if result.manoeuvre is not None:
        title += f"\n{result.manoeuvre.describe()}"
    label = "where they differ most" if q.kind == "separate" else "where the parameter shows most"
    return output.plot_png(path.p_w_m, speed, result.differ, result.limits.arena, title, label, path.t_s)


def write(result: FlightPlan, json_path: Path, trajectory_path: Path | None, plot_path: Path | None = None) -> Written:
    """Write the CSV (where planned), the picture (beside the JSON as ``.png`` unless given) and
    the JSON, in that order: the JSON, written last, names only what exists."""
    csv = None
    png = None
    if result.planned and result.trajectory is not None and trajectory_path is not None:
        csv = pieces.write_csv(result.trajectory, trajectory_path)
        image = plot_png(result)
        if image is not None:
            png = output.write_plot(image, plot_path or Path(json_path).with_suffix(".png"))
    doc = result.to_dict(str(csv) if csv is not None else None)
    doc["plot"] = str(png) if png is not None else None
    return Written(output.write_json(doc, json_path), csv, png)


# --- a data root: the plan beside the diagnosis ---------------------------------------------

PLAN_JSON, PLAN_CSV, PLAN_PNG = "flight_plan.json", "flight_plan.csv", "flight_plan.png"


def diagnosis_from_document(doc: dict, spec: ModelSpec) -> Diagnosis:
    """The typed diagnosis from its JSON document (``reports/diagnosis.json``): the parts the
    planner reads (candidates, model, evaluation, residual and noise levels); the tables empty."""
    def rmse(d: dict) -> ResidualRmse:
        return ResidualRmse(tuple(d["force_rmse_N"]), tuple(d["torque_rmse_Nm"]))

    ev = doc["evaluation"]
    return Diagnosis(
        effects_in_model=tuple(doc["effects_in_model"]), model=PhysicsModel.from_dict(doc["model"], spec.vehicle),
        evaluation=Evaluation(ev["mode"], ev["folds"], tuple(ev["train_flights"]), tuple(ev["eval_flights"]),
                              ev["samples"]),
        baseline=rmse(doc["baseline"]), noise_floor=rmse(doc["noise_floor"]), at_noise_level=doc["at_noise_level"],
        residual_to_noise=doc["residual_to_noise"],
        candidates=tuple(CandidateScore.from_dict(c) for c in doc["candidates"]), sensitivity=doc["sensitivity"],
        sensitivity_basis=doc["sensitivity_basis"], verdict=doc["verdict"],
        stability=Stability.from_dict(doc.get("stability")), disagreements=(),
        regimes=pl.DataFrame(), flights=pl.DataFrame(), worst_segments=pl.DataFrame(), frequency={},
        settings=DiagnosisSettings.from_dict(doc.get("settings")))


def plan_data_root(root, fleet: Fleet, spec: ModelSpec, request: PlanRequest, log: Log = _quiet
                   ) -> tuple[FlightPlan, Written]:
    """The plan for a data root's stored diagnosis (``reports/diagnosis.json``, made for ``spec``'s
    effects), written under ``reports/`` as ``flight_plan.{json,csv,png}``."""
    path = store.diagnosis_path(root)
    if not path.is_file():
        raise WorkflowError("no diagnosis to plan from: materialise model_diagnosis first")
    doc = store.read_json(path)
    if doc.get("effects_in_model") != list(spec.effects):
        raise WorkflowError(f"the stored diagnosis is of {doc.get('effects_in_model')}, not of the model file's "
                            f"{spec.effects}: materialise model_diagnosis first")
    result = plan(fleet, spec, diagnosis_from_document(doc, spec), request, log, sufficient.stored(root, spec))
    reports = store.reports_dir(root)
    if not result.planned:  # no earlier plan's files left beside a document that plans nothing
        for name in (PLAN_CSV, PLAN_PNG):
            (reports / name).unlink(missing_ok=True)
    return result, write(result, reports / PLAN_JSON, reports / PLAN_CSV, reports / PLAN_PNG)
