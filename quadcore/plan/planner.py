"""The planner: from a diagnosis of the logged flights to the flight that answers its open
question, with the prediction and the proof (:func:`plan`, the typed :class:`FlightPlan`).

Steps: the question (:mod:`quadcore.plan.question`); the noise the comparison fights and the
old flights' part of the objective (:mod:`quadcore.plan.objective`); the search over the
family (:mod:`quadcore.plan.search`); the separation measured on the old flights
(:mod:`quadcore.plan.separation`) and the proof in the simulator (:mod:`quadcore.plan.proof`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import evidence, flightdata, rates
from quadcore.identify.diagnosis.results import Diagnosis
from quadcore.physics.vehicle import Vehicle
from quadcore.plan import (
    family,
    flatness,
    objective,
    proof,
    question as questionlib,
    ratelevel,
    search,
    separation,
    signatures,
)
from quadcore.plan.limits import LimitCheck, Limits, check, largest_scale
from quadcore.plan.proof import LeftOut
from quadcore.plan.question import Question
from quadcore.plan.signatures import Explanation
from quadcore.sim.trajectories import PolyTrajectory
from quadcore.spec.model import ModelSpec

DEFAULT_DURATION_S = 20.0
MIN_PROBE_SIGMA = 1.0  # a rival no probe flight separates by this much is nested in the top candidate


@dataclass(frozen=True)
class PlanRequest:
    """What the user asks: the question (or None: from the diagnosis), limits, flight time,
    whether to prove the plan in the simulator, and the simulator's seed."""

    between: tuple[str, str] | None = None
    parameter: str | None = None
    limits: Limits = field(default_factory=Limits)
    duration_s: float = DEFAULT_DURATION_S
    prove: bool = True
    seed: int = 0


@dataclass(frozen=True)
class FlightPlan:
    """The plan: the question, and (unless there is nothing to plan) the manoeuvre, its pieces,
    the limits checked on them, the objective's prediction before and after, the separation
    measured on the logged flights, and the proof (each explanation flown)."""

    question: Question
    limits: Limits
    duration_s: float
    manoeuvre: family.Manoeuvre | None = None
    trajectory: PolyTrajectory | None = None
    checked: LimitCheck | None = None
    design: dict[str, Any] = field(default_factory=dict)
    measured_before: float | None = None
    gap_before: float | None = None  # |score difference| of the two candidates in the diagnosis
    measured_by_flight: separation.ByFlight | None = None  # the measured comparison with flights as clusters
    proof: tuple[proof.Flown, ...] = ()
    proof_left_out: tuple[LeftOut, ...] = ()  # explanations whose flight the proof could not use
    differ: np.ndarray | None = None  # per sample of the planned path: how much the explanations differ
    path: flatness.FlatPath | None = None
    undecided_before: str = ""  # why the diagnosis prefers neither on the logged flights (measured_before 0)

    @property
    def planned(self) -> bool:
        return self.trajectory is not None

    def predicted(self) -> dict[str, float | None]:
        """The contract's ``predicted``: measured before and proven after where every explanation was
        flown, else both designed (without the proof, or with an explanation left out of it): a
        before and an after of one measure (the measured before is under ``measured``)."""
        q = self.question
        proven = self.proof if not self.proof_left_out else ()
        if q.kind == "separate":
            if proven:
                return {"separation_sigma_before": self.measured_before,
                        "separation_sigma_after": min(f.sigma for f in proven if f.sigma is not None),
                        "score_gap_before": self.gap_before,
                        "score_gap_after": min(f.score_gap for f in proven if f.score_gap is not None)}
            pre, post = self.design.get("before", {}), self.design.get("after", {})
            return {"separation_sigma_before": pre.get("sigma"), "separation_sigma_after": post.get("sigma"),
                    "score_gap_before": pre.get("score_gap"), "score_gap_after": post.get("score_gap")}
        if q.kind == "parameter":
            name = q.parameter.partition(".")[2]
            after = (proven[0].parameter_std.get(name) if proven else self.design.get("std_after"))
            return {"parameter_std_before": self.design.get("std_before"), "parameter_std_after": after}
        return {}

    def to_dict(self, trajectory_path: str | None) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "question": self.question.to_dict(),
            "trajectory": trajectory_path if self.planned else None,
            "duration_s": self.duration_s if self.planned else 0.0,
            "limits": self.limits.to_dict(),
            "predicted": self.predicted(),
            "why": self.question.why,
        }
        if self.question.kind == "separate" and self.measured_before is not None:
            doc["measured"] = {"separation_sigma_before": self.measured_before, "score_gap_before": self.gap_before,
                               "undecided": self.undecided_before or None}
            if self.measured_by_flight is not None:
                doc["measured"]["by_flight"] = self.measured_by_flight.to_dict()
        if self.planned and self.manoeuvre is not None and self.checked is not None:
            doc["manoeuvre"] = {**self.manoeuvre.to_dict(), "description": self.manoeuvre.describe(),
                                "pieces": len(self.trajectory.durations) if self.trajectory is not None else 0}
            doc["checked"] = self.checked.to_dict()
            doc["design"] = self.design
            doc["proof"] = [f.to_dict() for f in self.proof]
            doc["proof_left_out"] = [f.to_dict() for f in self.proof_left_out]
        return doc


def noise_sigma(diag: Diagnosis, names: list[str]) -> np.ndarray:
    """(6,) per axis: the held-out residual the diagnosis leaves after the best of ``names`` (the
    model's residual for an effect of the model), never below the sensor-noise floor."""
    floor = np.array([*diag.noise_floor.force_rmse_N, *diag.noise_floor.torque_rmse_Nm])
    left = [np.array([*c.force_rmse_N, *c.torque_rmse_Nm]) for c in diag.candidates if c.effect in names]
    base = np.array([*diag.baseline.force_rmse_N, *diag.baseline.torque_rmse_Nm])
    return np.maximum(floor, np.min(left, axis=0) if left else base)


def old_energy(diag: Diagnosis) -> np.ndarray:
    """(6,) the model's held-out residual energy on the logged flights (sum of squares per axis)."""
    base = np.array([*diag.baseline.force_rmse_N, *diag.baseline.torque_rmse_Nm])
    return base**2 * diag.evaluation.samples


def separation_objective(a: Explanation, b: Explanation, flights: Mapping[str, flightdata.FlightData],
                         diag: Diagnosis, vehicle: Vehicle) -> objective.SeparationObjective | ratelevel.RateSeparation:
    """The objective for separating ``a`` and ``b``, in the statistic the diagnosis decides them by:
    the angular-rate level's comparison for two timing candidates
    (:class:`quadcore.plan.ratelevel.RateSeparation`), else the held-out comparison and score gap on
    the force and torque channels (:class:`quadcore.plan.objective.SeparationObjective`)."""
    if separation.timing_pair(a.name, b.name):
        return ratelevel.RateSeparation(a, b, flights, diag.model, vehicle)
    return objective.SeparationObjective(a, b, list(flights.values()), vehicle, noise_sigma(diag, [a.name, b.name]),
                                         old_energy(diag), separation.skipped_blocks(diag))


def _differ_separate(a: Explanation, b: Explanation, fd: flightdata.FlightData, vehicle: Vehicle,
                     sigma: np.ndarray) -> np.ndarray:
    d = signatures.predict(a, fd, vehicle) - signatures.predict(b, fd, vehicle)
    return (d**2) @ (1.0 / sigma**2)


def plan(tables: Mapping, spec: ModelSpec, diag: Diagnosis, request: PlanRequest,
         sessions: dict[str, list[str]] | None = None, log: Callable[[str], None] = lambda m: None,
         stats: proof.StoredStats = None) -> FlightPlan:
    """The flight that answers the diagnosis's open question (or the one asked); see the module.
    ``stats``: the flights' stored statistics (:func:`quadcore.identify.stats.sufficient.stored`),
    for the measured separation and the proof."""
    q = questionlib.ask(diag, request.between, request.parameter)
    limits, duration = request.limits, float(request.duration_s)
    if q.kind == "none":
        return FlightPlan(q, limits, duration)
    log(f"plan: {q.why}")
    if q.kind == "separate":
        return _separate(q, tables, spec, diag, request, sessions, log, stats)
    return _parameter(q, tables, spec, diag, request, spec.vehicle, sessions, log, stats)


def fitting_flights(tables: Mapping, spec: ModelSpec) -> dict[str, flightdata.FlightData]:
    return separation.flights_of(tables, spec)


def _probe(limits: Limits, duration_s: float, vehicle: Vehicle, loop: np.ndarray) -> flightdata.FlightData | None:
    """A middle member of the family, to tell a rival a flight can separate from one it cannot."""
    half = limits.half_extent_m
    m = family.Manoeuvre("figure8", 0.3, 2.0, float(min(half[0], half[1])), 0.6 * half[2], limits.centre_m,
                         duration_s)
    unit = family.trajectory(m)
    s = largest_scale(unit, m.centre_m, vehicle, limits)
    return signatures.planned_flight(family.scaled_trajectory(unit, m.centre_m, s), vehicle, loop) if s > 0 else None


def _choose_rival(q: Question, diag: Diagnosis, flights: Mapping[str, flightdata.FlightData], vehicle,
                  limits: Limits, duration_s: float, log) -> Question:
    """For the default question: the first rival of the top candidate that a flight can separate
    from it (a wind with zero air speed *is* rotor drag: no flight tells them apart)."""
    probe = _probe(limits, duration_s, vehicle, signatures.activity(list(flights.values())))
    top = questionlib.explanation(diag, q.candidates[0])
    for rival in q.alternatives:
        b = questionlib.explanation(diag, rival)
        sep = separation_objective(top, b, flights, diag, vehicle).evaluate(probe)
        if sep.sigma >= MIN_PROBE_SIGMA:
            return q.with_rival(rival, f"{q.why.rsplit(' ', 1)[0]} {rival}" if rival != q.candidates[1] else q.why)
        log(f"plan: no flight separates {top.name} from {rival} (a flight of the family gives {sep.sigma:.2f} σ): "
            "skipped")
    return Question("none", why=f"{q.why}, but no flight of the family separates {top.name} from "
                                f"{', '.join(q.alternatives)}: the one contains the other (a wind with zero air speed "
                                "is rotor drag); knowledge of the vehicle or the room must decide")


def _unlogged_timing(q: Question, flights: Mapping[str, flightdata.FlightData]) -> Question | None:
    """Nothing to plan when both sides re-time the rotors' thrust and flights log the commands
    less often than the firmware sets them: the diagnosis does not compare the two there, and
    no flight logged the same way would tell them apart (docs/timing.md)."""
    if not all(effectlib.get(n).retimes_thrust for n in q.candidates):
        return None
    slow = sorted(f for f, fd in flights.items() if rates.below_command_rate(fd))
    if not slow:
        return None
    st = flights[slow[0]].state
    dt_ms, hold_ms = float(np.median(np.diff(st.t_s))) * 1e3, st.thrust_hold_s * 1e3
    return Question("none", why=(
        f"{' and '.join(q.candidates)} both re-time the rotors' thrust, and {', '.join(slow)} log the commands "
        f"every {dt_ms:.3g} ms where the firmware sets them every {hold_ms:.3g} ms: no flight logged so tells "
        f"the two apart (docs/timing.md). Log at the command rate ({1e3 / hold_ms:.0f} Hz): there hover flights "
        "decide a lag or delay of 10 ms (docs/flight-planning.md)"))


def _separate(q: Question, tables, spec: ModelSpec, diag: Diagnosis, request: PlanRequest, sessions,
              log, stats: proof.StoredStats = None) -> FlightPlan:
    """The flight that separates the question's two candidates: the pair (nothing to plan when no
    flight tells them apart), the search on their objective, the design, the separation measured
    on the logged flights and the proof."""
    vehicle, limits = spec.vehicle, request.limits
    flights = fitting_flights(tables, spec)
    q = _separable(q, diag, flights, request, vehicle, log)
    if q.kind == "none":
        return FlightPlan(q, limits, request.duration_s)
    a, b = (questionlib.explanation(diag, n) for n in q.candidates)
    sigma = noise_sigma(diag, list(q.candidates))
    obj = separation_objective(a, b, flights, diag, vehicle)
    best, fd = _search(obj.value, vehicle, signatures.activity(list(flights.values())), request, log)
    design = _separation_design(obj, fd, sigma, request.duration_s)
    if design.get("advice"):
        log(f"plan: {design['advice']}")
    measured = proof.before(tables, spec, diag, (a.name, b.name), stats)
    if measured.undecided:
        log(f"plan: on the logged flights {measured.undecided}")
    note = _measured_note(obj, diag, measured, design["before"]["sigma"])
    if note:
        design["note"] = note
        log(f"plan: {note}")
    log(f"plan: {best.manoeuvre.describe()}; predicted separation {design['before']['sigma']:.1f} -> "
        f"{design['after']['sigma']:.1f} σ (measured before: {abs(measured.sigma_for(a.name)):.1f} σ"
        f"{', undecided' if measured.undecided else ''})")
    flown = (proof.fly(best.trajectory, tables, spec, diag.model, [a, b], (a.name, b.name), request.seed, log,
                       sessions, stats) if request.prove else proof.Proof())
    return FlightPlan(
        q, limits, request.duration_s, manoeuvre=best.manoeuvre, trajectory=best.trajectory,
        checked=check(best.trajectory, vehicle, limits), design=design,
        measured_before=abs(measured.sigma_for(a.name)),
        gap_before=abs(proof.score_gap(diag, a.name, b.name) or 0.0), measured_by_flight=measured.by_flight,
        proof=flown.flown, proof_left_out=flown.left_out,
        differ=_differ_separate(a, b, signatures.planned_flight(best.trajectory, vehicle), vehicle, sigma),
        path=flatness.flat_path(best.trajectory, vehicle), undecided_before=measured.undecided)


def _separable(q: Question, diag: Diagnosis, flights: Mapping[str, flightdata.FlightData], request: PlanRequest,
               vehicle: Vehicle, log) -> Question:
    """The pair to separate: the question, with the rival a flight can separate from the top
    candidate when none was asked; a question of kind ``"none"`` (with its reason) where the
    flights' logging cannot tell the two apart or no flight of the family separates any rival."""
    unlogged = _unlogged_timing(q, flights)
    if unlogged:
        return unlogged
    if request.between is None:
        return _choose_rival(q, diag, flights, vehicle, request.limits, request.duration_s, log)
    return q


def _search(value: Callable[[flightdata.FlightData], float], vehicle: Vehicle, loop: np.ndarray,
            request: PlanRequest, log) -> tuple[search.Candidate, flightdata.FlightData]:
    """The best flight of the family for the objective's ``value`` within the request's limits and
    flight time, and that flight as the planner predicts it (flown by the logged flights' control
    ``loop``)."""
    best = search.search(lambda tr: value(signatures.planned_flight(tr, vehicle, loop)), vehicle, request.limits,
                         request.duration_s, log)
    return best, signatures.planned_flight(best.trajectory, vehicle, loop)


def _separation_design(obj: objective.SeparationObjective | ratelevel.RateSeparation, fd: flightdata.FlightData,
                       sigma: np.ndarray, duration_s: float) -> dict[str, Any]:
    """The design's part of the plan: the objective's separation on the logged flights alone
    (``before``) and with the planned flight ``fd`` (``after``), whether that is expected to
    decide, the noise it fights, the statistic, and the outlook (:func:`_outlook`)."""
    before, after = obj.evaluate(), obj.evaluate(fd)
    return {"before": before.to_dict(), "after": after.to_dict(), "expected_to_decide": bool(after.value >= 1.0),
            "noise_per_axis": [float(v) for v in sigma],
            "statistic": "angular rate" if isinstance(obj, ratelevel.RateSeparation) else "force and torque",
            **_outlook(obj, fd, before, after, duration_s)}


def _measured_note(obj: objective.SeparationObjective | ratelevel.RateSeparation, diag: Diagnosis,
                   measured: separation.Comparison, expected: float) -> str | None:
    """Why the separation measured on the logged flights says less than the design's ``expected``
    (σ before): at the rate level, non-white gyro noise or biased fits; else no comparison at all
    (:func:`_no_comparison_note`), or flights that disagree (:func:`_flights_note`); None when
    neither applies."""
    if isinstance(obj, ratelevel.RateSeparation) and abs(measured.t) < 0.5 * expected:
        return (f"the logged flights separate the two by {abs(measured.t):.1f} σ at the angular-rate level "
                f"where the objective expects {expected:.1f} σ: the gyro noise is not white "
                "there or biases the fits (docs/timing.md), so the prediction after is optimistic "
                "(docs/flight-planning.md)")
    if measured.blocks == 0:
        return _no_comparison_note(diag, measured, expected)
    by = _disagreeing_flights(measured)
    return _flights_note(measured, by) if by is not None else None


def _no_comparison_note(diag: Diagnosis, measured: separation.Comparison, expected: float) -> str:
    """Why the measured separation is 0 where the design expects more: the held-out comparison
    (:func:`quadcore.plan.separation.compare`) had too few blocks to test on (fewer than
    ``evidence.MIN_BLOCKS``: too little data, which says nothing of the predictions), or nothing
    to compare, the two predicting the same in the channels the diagnosis takes evidence from
    (above the sensor-noise floor), while the objective counts every channel (in hover a thrust
    scale's torque trims, below the gyro noise, against a payload's none; docs/flight-planning.md);
    at the rate level (no block count) neither is claimed."""
    tail = f", so there is no held-out comparison (0 σ) where the objective, which counts every channel, " \
           f"expects {expected:.1f} σ"
    available = measured.available_blocks
    if available is None:
        return "the logged flights give no comparison of the two at the angular-rate level" + tail
    if available < evidence.MIN_BLOCKS:
        return (f"the logged flights are too short to compare the two: {available} held-out "
                f"block{'' if available == 1 else 's'} where the test needs at least {evidence.MIN_BLOCKS}") + tail
    quiet = [ch for ch, at in diag.at_noise_level.items() if at]
    return ("the logged flights do not separate the two at all: they predict the same where the residual stands "
            "above the sensor-noise floor" + (f" ({' and '.join(quiet)} at the floor, where the diagnosis takes no "
                                              "evidence)" if quiet else "") + tail)


def _disagreeing_flights(measured: separation.Comparison) -> separation.ByFlight | None:
    """The comparison with the flights as the clusters (:class:`quadcore.plan.separation.ByFlight`)
    where the held-out comparison separates the two at the diagnosis's level and it does not; else None."""
    by = measured.by_flight
    return by if by is not None and measured.p_value < evidence.ALPHA <= by.p_value else None


def _flights_note(measured: separation.Comparison, by: separation.ByFlight) -> str:
    first, second = (measured.a, measured.b) if measured.t > 0 else (measured.b, measured.a)
    count = by.for_first if measured.t > 0 else by.flights - by.for_first
    return (f"the logged flights separate the two by {abs(measured.t):.1f} σ in the held-out comparison, "
            f"but {first} fits {count} of {by.flights} better, {second} the others, and with "
            f"each flight as one cluster the separation is {abs(by.t):.1f} σ (p {by.p_value:.2g}), "
            "not significant (docs/flight-planning.md)")


def _flying(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def _outlook(obj, fd: flightdata.FlightData, before: objective.Separation, after: objective.Separation,
             duration_s: float) -> dict[str, Any]:
    """What the design says beyond its value (see docs/flight-planning.md): whether the planned
    flight raises both of the diagnosis's measures (``improves``), and, where one flight is not
    expected to decide, how many such flights would (``repeated``, force and torque statistic
    only) and a plain ``advice``."""
    gaps = (before.score_gap, after.score_gap)
    improves = after.sigma >= before.sigma and (None in gaps or gaps[1] >= gaps[0])  # type: ignore[operator]
    out: dict[str, Any] = {"improves": bool(improves)}
    if after.value >= 1.0:
        return out
    said = []
    if not improves:
        said.append(f"the best flight found does not raise both measures on the logged flights: expected separation "
                    f"{before.sigma:.2f} -> {after.sigma:.2f} σ, score gap "
                    + (f"{gaps[0]:.2g} -> {gaps[1]:.2g}" if None not in gaps else "n/a"))
    if isinstance(obj, objective.SeparationObjective):
        copies, there = obj.copies_to_decide(fd)
        out["repeated"] = {"copies": copies, "flying_s": None if copies is None else copies * duration_s,
                           "max_copies": objective.MAX_COPIES, "at": there.to_dict()}
        said.append(f"flown {copies} times ({_flying(copies * duration_s)}) it is expected to decide"
                    if copies is not None else
                    f"even flown {objective.MAX_COPIES} times it is not expected to decide: the score gap tends to "
                    f"{there.score_gap:.2g} where the diagnosis needs {evidence.TIE_MARGIN:g} "
                    f"({objective.GAP_GOAL:g} with the design's margin; more such flying does not raise it); "
                    "explain more of the residual first, or decide by knowledge of the vehicle")
    out["advice"] = "; ".join(["one such flight does not decide it", *said])
    return out


def _parameter(q: Question, tables, spec: ModelSpec, diag: Diagnosis, request: PlanRequest, vehicle: Vehicle,
               sessions, log, stats: proof.StoredStats = None) -> FlightPlan:
    effect, _, name = q.parameter.partition(".")
    expl = questionlib.explanation(diag, effect)
    std_before = float(expl.std.get(name, float("nan")))
    sigma = noise_sigma(diag, [effect])
    obj: objective.Information
    if expl.effect.retimes_thrust and len(expl.effect.parameters) == 1:  # decided at the rate level
        obj = ratelevel.RateInformation(expl, std_before, fitting_flights(tables, spec), diag.model, vehicle)
    else:
        obj = objective.InformationObjective(expl, name, std_before, vehicle, sigma)
    loop = signatures.activity(list(fitting_flights({f: tables[f] for f in sorted(tables)[:3]}, spec).values()))
    best, fd = _search(obj.value, vehicle, loop, request, log)
    design: dict[str, Any] = {"std_before": std_before, "std_after": obj.std_after(fd),
                              "noise_per_axis": [float(v) for v in sigma]}
    log(f"plan: {best.manoeuvre.describe()}; predicted std of {q.parameter} {std_before:.3g} -> "
        f"{design['std_after']:.3g}")
    flown = (proof.fly(best.trajectory, tables, spec, diag.model, [expl], None, request.seed, log, sessions, stats)
             if request.prove else proof.Proof())
    u = signatures.unit_wrench(expl, name, fd, vehicle)
    return FlightPlan(
        q, request.limits, request.duration_s, manoeuvre=best.manoeuvre, trajectory=best.trajectory,
        checked=check(best.trajectory, vehicle, request.limits), design=design, proof=flown.flown,
        proof_left_out=flown.left_out, differ=(u**2) @ (1.0 / sigma**2),
        path=flatness.flat_path(best.trajectory, vehicle))
