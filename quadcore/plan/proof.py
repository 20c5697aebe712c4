"""Proof before the flight: the planned flight flown in the simulator under each explanation,
and the diagnosis run again on the old flights plus that one.

For each explanation (each side of a separation; the one effect of a parameter question) the
planned CSV is flown closed loop by :func:`quadcore.sim.simulation.simulate` (kind ``plan``,
real log format and noise) with the model's effects at their fitted values and that
explanation at its fitted values, decoded as a real log, added to the logged flights, and:

* diagnosed (:func:`quadcore.identify.diagnosis.diagnose`, cross-validation over flights): is
  the explanation flown ranked first, and is it still tied with the other?
* compared (:func:`quadcore.plan.separation.compare`): the held-out separation in σ, in favour
  of the explanation flown.

One explanation's flight that cannot be used does not stop the others: a flight the simulator
cannot fly (its closed loop loses control: :func:`quadcore.sim.simulation.lost_control`) or whose
log the physics gate refuses (:func:`quadcore.physics.gate.physics_problem`) is left out of the
proof with the reason (:class:`LeftOut`), and the proof goes on with the other explanation.

Both take the flights' statistics (:mod:`quadcore.identify.stats.sufficient`), made once: the
logged flights' (stored ones where given) for every explanation, the planned flight's once per
explanation flown (:func:`statistics`).

Nothing is written outside a temporary folder that is removed afterwards.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.identify import diagnosis as diagnosislib
from quadcore.identify.diagnosis.results import Diagnosis
from quadcore.identify.model import PhysicsModel
from quadcore.identify.stats import sufficient
from quadcore.logs import flight as flightlib
from quadcore.physics import gate
from quadcore.plan import pieces, separation
from quadcore.plan.signatures import Explanation
from quadcore.sim import simulation
from quadcore.sim.trajectories import PolyTrajectory
from quadcore.spec.model import ModelSpec


@dataclass(frozen=True)
class Flown:
    """The planned flight simulated under ``truth`` and diagnosed with the old flights: the
    diagnosis's first candidate, whether ``truth`` is first and tied with anything, the held-out
    separation in favour of ``truth`` (None for a parameter question), and ``truth``'s
    parameter standard errors after."""

    truth: str
    top: str
    first: bool
    tied_with: tuple[str, ...]
    sigma: float | None
    parameter_std: dict[str, float]
    score_gap: float | None = None  # the truth's score minus the other's (a tie within TIE_MARGIN)
    undecided: str = ""  # why the diagnosis prefers neither of the pair whatever the held-out t (sigma 0 then)

    def to_dict(self) -> dict:
        return {"truth": self.truth, "top": self.top, "ranked_first": self.first, "tied_with": list(self.tied_with),
                "separation_sigma": self.sigma, "score_gap": self.score_gap, "parameter_std": dict(self.parameter_std),
                "undecided": self.undecided or None}


@dataclass(frozen=True)
class LeftOut:
    """An explanation whose planned flight the proof could not use, and why (the simulator lost
    control of it, or the physics gate refuses its log)."""

    truth: str
    reason: str

    def to_dict(self) -> dict:
        return {"truth": self.truth, "reason": self.reason}


@dataclass(frozen=True)
class Proof:
    """The proof's outcome: each explanation flown and diagnosed, and those left out."""

    flown: tuple[Flown, ...] = ()
    left_out: tuple[LeftOut, ...] = ()


def flight_name(spec: ModelSpec) -> str:
    """The planned flight's name: one more flight of the model's last session where the model
    has sessions (a per-session parameter then has its session's value), else ``planned``."""
    if spec.session_patterns:
        pattern = list(spec.session_patterns.values())[-1][0]
        return pattern.replace("*", "") + "planned"
    return "planned"


def model_effects(model: PhysicsModel) -> dict[str, dict[str, float]]:
    """The model's effects at their fitted (fleet) values, as the simulator takes them."""
    return {t.name: dict(t.params) for t in model.terms}


def simulate_plan(traj: PolyTrajectory, truth: Explanation | None, model: PhysicsModel, out_dir: Path, name: str,
                  seed: int = 0):
    """Fly the plan (written as the lab's CSV in ``out_dir``, hover at its first point) with the
    model's effects and ``truth``; returns its decoded ``fixedFrequency`` table."""
    csv = pieces.write_csv(traj, out_dir / f"{name}.csv")
    start = traj.evaluate(np.zeros(1))[0]
    effects = model_effects(model)
    if truth is not None:
        effects[truth.name] = dict(truth.params)
    cfg = simulation.SimConfig(kind="plan", plan_file=str(csv), height_m=float(start[2]), seed=seed, name=name)
    path = out_dir / name
    simulation.write_flight(simulation.simulate(cfg, model.vehicle, effects), path)
    return flightlib.decode_flight(path).tables["fixedFrequency"]


StoredStats = Callable[[str], sufficient.FlightStats | None] | None  # a flight's stored statistics, if current


def statistics(tables: Mapping, spec: ModelSpec, stored: StoredStats = None
               ) -> Callable[[str], sufficient.FlightStats]:
    """``flight -> statistics``: its stored ones (``stored``), else computed from its decoded table
    for ``spec`` (:func:`quadcore.identify.stats.sufficient.spec_layout`: every built-in effect), each
    once when first asked for."""
    layout = sufficient.spec_layout(spec)

    @cache
    def of(flight: str) -> sufficient.FlightStats:
        s = stored(flight) if stored is not None else None
        return s if s is not None else sufficient.compute(spec, flight, tables[flight], layout)

    return of


def fly(traj: PolyTrajectory, tables: Mapping, spec: ModelSpec, model: PhysicsModel, truths: list[Explanation],
        pair: tuple[str, str] | None, seed: int = 0, log: Callable[[str], None] = lambda m: None,
        sessions: dict[str, list[str]] | None = None, stats: StoredStats = None) -> Proof:
    """The proof (see the module) for each of ``truths``; ``stats``: the logged flights' stored statistics."""
    out, left_out = [], []
    name = flight_name(spec)
    old = statistics(tables, spec, stats)
    with tempfile.TemporaryDirectory(prefix="quadcore-plan-") as tmp:
        for k, truth in enumerate(truths):
            log(f"proof: flying the plan in the simulator with {truth.name} as the truth")
            new, why = _flown_log(traj, truth, model, Path(tmp), name, seed + k)
            if new is None:
                left_out.append(LeftOut(truth.name, why))
                log(f"proof: WARNING: the flight with {truth.name} as the truth is left out of the proof: {why}")
                continue
            both = {**tables, name: new}
            planned = statistics({name: new}, spec)

            def of(f: str, planned=planned) -> sufficient.FlightStats:
                return planned(f) if f == name else old(f)

            diag = diagnosislib.diagnose(both, spec, sessions=sessions, stats=of)
            out.append(_flown(diag, truth, pair, both, spec, model, of))
    return Proof(tuple(out), tuple(left_out))


def _flown_log(traj: PolyTrajectory, truth: Explanation, model: PhysicsModel, out_dir: Path, name: str,
               seed: int) -> tuple[pl.DataFrame | None, str]:
    """(the planned flight's decoded table with ``truth``, "") or (None, why the proof cannot use it)."""
    try:
        table = simulate_plan(traj, truth, model, out_dir, name, seed)
    except simulation.SimulationError as exc:
        return None, f"the simulator cannot fly it: {exc}"
    problem = gate.physics_problem(table, gate.required_columns(model.vehicle))
    if problem is not None:
        return None, f"the physics gate refuses its simulated log: {problem}"
    return table, ""


def _flown(diag: Diagnosis, truth: Explanation, pair, tables, spec: ModelSpec, model: PhysicsModel,
           stats: StoredStats = None) -> Flown:
    top = diag.candidates[0] if diag.candidates else None
    row = next((c for c in diag.candidates if c.effect == truth.name), None)
    std = dict(row.parameter_std) if row is not None else next(
        (dict(t.std) for t in diag.model.terms if t.name == truth.name), {})
    sigma = gap = None
    undecided = ""
    if pair is not None:
        comp = separation.measured(tables, spec, diag, pair[0], pair[1], stats)
        sigma, undecided = comp.sigma_for(truth.name), comp.undecided
        gap = score_gap(diag, truth.name, pair[1] if pair[0] == truth.name else pair[0])
    return Flown(truth.name, top.effect if top else "", bool(top is not None and top.effect == truth.name),
                 tuple(row.tied_with) if row is not None else (), sigma, std, gap, undecided)


def score_gap(diag: Diagnosis, a: str, b: str) -> float | None:
    """``a``'s score minus ``b``'s in a diagnosis (None when either is not a candidate)."""
    scores = {c.effect: c.score for c in diag.candidates}
    return scores[a] - scores[b] if a in scores and b in scores else None


def before(tables: Mapping, spec: ModelSpec, diag: Diagnosis, pair: tuple[str, str],
           stats: StoredStats = None) -> separation.Comparison:
    """The held-out separation on the logged flights alone, in the statistic the diagnosis
    decides the pair by (:func:`quadcore.plan.separation.measured`; ``stats``: their stored
    statistics)."""
    return separation.measured(tables, spec, diag, *pair, stats=stats)


