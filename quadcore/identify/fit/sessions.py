"""Parameters that differ between sessions of flights.

A fleet-wide fit hides a parameter that changes between sessions (another battery, other
propellers, a log variable stuck in one session). Here every flight's parameters are fitted
on that flight alone, and flights are grouped where their values disagree beyond their
uncertainty:

* **From the data** (no sessions file): the flights' values, sorted, are split in two where
  the groups are most distinct, and then each group again, while a split is both certain,
  ``t = |m_1 - m_2| / sqrt(se_1² + se_2²) > SPLIT_SIGMA`` (``se`` a group mean's standard
  error from the between-flight scatter and the fits' own errors), and large next to the
  flight-to-flight spread, ``d = |m_1 - m_2| / sd_pooled > DISTINCT``, with ``MIN_GROUP``
  flights per group. Both thresholds are strict because the split point is searched; where
  flights spread along a continuum rather than fall into sessions, the groups say so by
  their number and their neighbouring values.
* **From a sessions file** (TOML, ``[sessions] NAME = ["jana00", "jana1*", ...]``, shell
  patterns allowed; read by :func:`quadcore.spec.sessions.read_sessions_file`): the groups are the
  sessions; they disagree when two of them differ by more than ``SESSION_SIGMA``.

Each group's value is the parameter fitted jointly on the group's flights, its ``std`` the
larger of that fit's error and the between-flight standard error. Where a disagreeing
group's flights log a battery voltage that never moves, the PWM/voltage thrust map cannot
be right there, and the disagreement says so (a map error, not physics).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from quadcore import effects as effectlib
from quadcore.effects import Effect
from quadcore.identify.fit import fit_effects, solve
from quadcore.identify.flightdata import Predicting
from quadcore.identify.model import EffectTerm, PhysicsModel
from quadcore.physics.vehicle import Vehicle

# a joint fit of effects to targets on flights: quadcore.identify.fit.fit_rows (rows) or
# quadcore.identify.fit.fit_effects (statistics), as whoever holds the flights chose by the effects' kinds
FitEffects = Callable[..., solve.Fit]

SPLIT_SIGMA = 5.0
DISTINCT = 3.0
SESSION_SIGMA = 3.0
MIN_GROUP = 3
STUCK_VBAT_V = 0.001  # a logged voltage whose in-flight standard deviation is below this is stuck


@dataclass(frozen=True)
class ParameterGroup:
    flights: tuple[str, ...]
    value: float
    std: float
    session: str = ""

    def to_dict(self) -> dict:
        out = {"flights": list(self.flights), "value": self.value, "std": self.std}
        return {**out, "session": self.session} if self.session else out


@dataclass(frozen=True)
class Disagreement:
    """One parameter whose value differs between groups of flights beyond their uncertainty."""

    effect: str
    parameter: str
    groups: tuple[ParameterGroup, ...]
    source: str  # "data" or "sessions file"
    separation_sigma: float  # the largest difference between two groups, in standard errors
    per_flight: tuple[tuple[str, float, float], ...] = ()  # (flight, value, std) fitted on each flight alone
    notes: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict:
        return {"effect": self.effect, "parameter": self.parameter, "groups": [g.to_dict() for g in self.groups],
                "source": self.source, "separation_sigma": self.separation_sigma,
                "per_flight": [{"flight": f, "value": v, "std": s} for f, v, s in self.per_flight],
                "notes": list(self.notes)}

    def summary(self) -> str:
        groups = "; ".join(f"{_flight_range(g.flights)}: {g.value:.4g} ± {g.std:.2g}" for g in self.groups)
        return f"{self.effect}.{self.parameter} differs between groups of flights ({groups})"


def _flight_range(flights: tuple[str, ...]) -> str:
    return flights[0] if len(flights) == 1 else f"{flights[0]}…{flights[-1]} ({len(flights)} flights)"


def session_of(flight: str, sessions: dict[str, list[str]]) -> str | None:
    return next((name for name, members in sessions.items() if flight in members), None)


def per_flight_fits(effects: list[Effect], fds: dict, targets: dict, vehicle: Vehicle,
                    fixed: dict | None = None, fit: FitEffects = fit_effects) -> dict[str, solve.Fit]:
    """The effects fitted on each flight alone (``fit``: on the flights' rows or statistics)."""
    return {f: fit(effects, [fds[f]], [targets[f]], vehicle, fixed) for f in sorted(fds)}


def _group_sd(values: np.ndarray, stds: np.ndarray) -> float:
    """A group's flight-to-flight spread: the scatter of its values and the fits' own errors."""
    scatter = float(np.var(values, ddof=1)) if len(values) > 1 else 0.0
    return float(np.sqrt(scatter + np.mean(stds**2)))


def _group_se(values: np.ndarray, stds: np.ndarray) -> float:
    return _group_sd(values, stds) / np.sqrt(len(values))


def _separation(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """The difference of two groups' means in standard errors."""
    se = np.hypot(_group_se(*a), _group_se(*b))
    diff = abs(float(a[0].mean() - b[0].mean()))
    return diff / se if se > 0 else (np.inf if diff > 0 else 0.0)


def _distinctness(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """The difference of two groups' means in pooled flight-to-flight spreads."""
    sd = np.sqrt(0.5 * (_group_sd(*a) ** 2 + _group_sd(*b) ** 2))
    diff = abs(float(a[0].mean() - b[0].mean()))
    return diff / sd if sd > 0 else (np.inf if diff > 0 else 0.0)


def split_by_value(values: dict[str, float], stds: dict[str, float]) -> list[list[str]]:
    """Groups of flights whose values disagree beyond their uncertainty (see module docstring)."""
    order = sorted(values, key=lambda f: values[f])
    v = np.array([values[f] for f in order])
    s = np.array([stds.get(f, 0.0) for f in order])
    best, at = 0.0, None
    for i in range(MIN_GROUP, len(order) - MIN_GROUP + 1):
        a, b = (v[:i], s[:i]), (v[i:], s[i:])
        d = _distinctness(a, b)
        if d > max(best, DISTINCT) and _separation(a, b) > SPLIT_SIGMA:
            best, at = d, i
    if at is None:
        return [sorted(order)]
    left = {f: values[f] for f in order[:at]}
    right = {f: values[f] for f in order[at:]}
    return split_by_value(left, stds) + split_by_value(right, stds)


def stuck_voltage_flights(fds: dict) -> list[str]:
    """Flights whose logged battery voltage does not move in flight (a stuck log variable);
    ``fds``: :class:`quadcore.identify.flightdata.FlightData` or
    :class:`quadcore.identify.stats.sufficient.FlightStats`."""
    return sorted(f for f, fd in fds.items() if fd.vbat_std_V < STUCK_VBAT_V)


def _map_note(groups: list[ParameterGroup], fds: dict, vehicle: Vehicle) -> list[str]:
    if vehicle.thrust_map_kind != "pwm_vbat":
        return []
    stuck = set(stuck_voltage_flights(fds))
    notes = []
    for g in groups:
        hit = [f for f in g.flights if f in stuck]
        if hit and len(hit) >= len(g.flights) / 2:
            volts = float(np.median([fds[f].vbat_median_V for f in hit]))  # each flight's own, stuck: one value
            notes.append(
                f"{len(hit)} of the {len(g.flights)} flights valued {g.value:.4g} ({_flight_range(tuple(hit))}) log a "
                f"battery voltage stuck at {volts:.2f} V: the PWM/voltage thrust map sees the wrong voltage there, so "
                "the thrust map, not a physical effect, is likely what differs. Switch that session to the "
                "motor-speed map in the model file ([sessions] NAME = [...]; [session_thrust_map] NAME = "
                "\"motor_speed\"; with [per_session] thrust_scale = [\"scale\"] if its k_F differs too) instead "
                "of fitting a physical effect to the map's error.")
    return notes


def disagreements(effects: list[Effect], fds: dict, targets: dict, vehicle: Vehicle,
                  fixed: dict | None = None, sessions: dict[str, list[str]] | None = None,
                  log=lambda msg: None, fit: FitEffects = fit_effects) -> list[Disagreement]:
    """Parameters of ``effects`` (fitted jointly, per flight and per group) that differ
    between groups of flights: from the data, or between the given ``sessions``."""
    fixed = fixed or {}
    free = [(e, p.name) for e in effects for p in e.parameters if e.name not in fixed]
    if not free or len(fds) < 2:
        return []
    log(f"fitting {', '.join(e.name for e in effects)} on each of {len(fds)} flights")
    per_flight = per_flight_fits(effects, fds, targets, vehicle, fixed, fit)
    out = []
    for effect, name in free:
        values = {f: fit.params[effect.name][name] for f, fit in per_flight.items()}
        stds = {f: fit.std[effect.name][name] for f, fit in per_flight.items()}
        if sessions:
            named = [(s, members) for s, members in sessions.items() if len([f for f in members if f in values]) > 0]
            found = [[f for f in members if f in values] for _, members in named]
            labels = [s for s, _ in named]
            source, threshold = "sessions file", SESSION_SIGMA
        else:
            found, labels, source, threshold = split_by_value(values, stds), None, "data", SPLIT_SIGMA
        if len(found) < 2:
            continue
        arrays = [(np.array([values[f] for f in g]), np.array([stds[f] for f in g])) for g in found]
        sep = max(_separation(a, b) for i, a in enumerate(arrays) for b in arrays[i + 1:])
        if sep <= threshold:
            continue
        groups = []
        for k, (members, (vals, sds)) in enumerate(zip(found, arrays)):
            fit_g = fit(effects, [fds[f] for f in members], [targets[f] for f in members], vehicle, fixed)
            std = max(fit_g.std[effect.name][name], _group_se(vals, sds))
            groups.append(ParameterGroup(tuple(sorted(members)), float(fit_g.params[effect.name][name]), float(std),
                                         labels[k] if labels else ""))
        groups.sort(key=lambda g: g.value)
        notes = _map_note(groups, fds, vehicle)
        per_flight_rows = tuple((f, float(values[f]), float(stds[f])) for f in sorted(values))
        out.append(Disagreement(effect.name, name, tuple(groups), source, float(min(sep, 1e6)), per_flight_rows,
                                tuple(notes)))
    return out


def table_rows(disagreements: list[dict]) -> list[dict]:
    """One row per group of each disagreement (the JSON form), for the report and the UI."""
    return [{"parameter": f"{d['effect']}.{d['parameter']}", "group": g.get("session") or str(i + 1),
             "value": float(f"{g['value']:.4g}"), "std": float(f"{g['std']:.3g}"), "flights": ", ".join(g["flights"]),
             "found from": d["source"]}
            for d in disagreements for i, g in enumerate(d["groups"])]


# ---------------------------------------------------------------------------------------
# Fitting parameters per session ([per_session] in a model file)
# ---------------------------------------------------------------------------------------

ROUNDS = 3  # alternations between the per-session and the shared parameters


def found_sessions(effects: list[Effect], fds: dict, targets: dict, flights: list[str], vehicle: Vehicle,
                   fixed: dict | None = None, fit: FitEffects = fit_effects) -> dict[str, list[str]]:
    """Sessions as the data show them: the groups of the per-flight values of the first
    parameter of ``effects`` (named ``group1``, ``group2``, ... by increasing value)."""
    fits = per_flight_fits(effects, {f: fds[f] for f in flights}, targets, vehicle, fixed, fit)
    e, name = effects[0], effects[0].parameters[0].name
    values = {f: fit.params[e.name][name] for f, fit in fits.items()}
    stds = {f: fit.std[e.name][name] for f, fit in fits.items()}
    groups = sorted(split_by_value(values, stds), key=lambda g: float(np.mean([values[f] for f in g])))
    return {f"group{i + 1}": g for i, g in enumerate(groups)}


def fit_per_session(spec, fds: dict, targets: dict, train: list[str],
                    sessions: dict[str, list[str]] | None = None, log=lambda msg: None,
                    fit: FitEffects = fit_effects) -> PhysicsModel:
    """Fit ``spec`` (a :class:`quadcore.spec.model.ModelSpec` with ``per_session`` effects) on the
    ``train`` flights: the per-session effects on each session's flights, the others on all,
    alternating ``ROUNDS`` times, every fit within the parameters' physical bounds (a parameter
    held at one says so in its term: :func:`quadcore.identify.fit.solve.held_bounds`). Sessions:
    ``sessions``, else the model file's, else the groups the data show. Returns a
    :class:`quadcore.identify.model.PhysicsModel` whose per-session terms carry the fleet value (for
    flights of no session) and one value per session."""
    vehicle = spec.vehicle
    every = [effectlib.get(n) for n in spec.effects]
    split = [e for e in every if e.name in spec.per_session]
    shared = [e for e in every if e.name not in spec.per_session]
    fleet = fit(every, [fds[f] for f in train], [targets[f] for f in train], vehicle, spec.fixed, bounded=True)
    if sessions is None:
        sessions = spec.sessions_of(sorted(fds)) or found_sessions(split, fds, targets, train, vehicle, spec.fixed, fit)
    members = {s: [f for f in fl if f in train] for s, fl in sessions.items()}
    empty = sorted(s for s, fl in members.items() if not fl)
    members = {s: fl for s, fl in members.items() if fl}
    split_names = ", ".join(e.name for e in split)
    if empty:  # a misspelt pattern, or a session held out whole: said, not silently fleet-wide
        log(f"warning: session(s) {', '.join(empty)} have no training flight: {split_names} at the fleet value there")
    log(f"fitting {split_names} per session: "
        + ("; ".join(f"{s}: {len(fl)} flights" for s, fl in members.items()) or "no session has a training flight"))
    shared_params = {e.name: fleet.params[e.name] for e in shared}
    shared_std = {e.name: fleet.std[e.name] for e in shared}
    shared_fit = fleet
    by_session: dict[str, solve.Fit] = {}
    session_of = {f: s for s, fl in members.items() for f in fl}
    for _ in range(ROUNDS):
        for s, fl in members.items():
            by_session[s] = fit(every, [fds[f] for f in fl], [targets[f] for f in fl], vehicle,
                                {**spec.fixed, **shared_params}, bounded=True)
        if not shared or all(e.name in spec.fixed for e in shared):
            break
        ys = []
        for f in train:
            source = by_session[session_of[f]] if f in session_of else fleet
            ys.append(targets[f] - source.predict(split, fds[f], vehicle))
        shared_fit = fit(shared, [fds[f] for f in train], ys, vehicle, spec.fixed, bounded=True)
        shared_params, shared_std = shared_fit.params, shared_fit.std
    terms = []
    for e in every:
        if e in split:
            terms.append(EffectTerm(e.name, fleet.params[e.name], fleet.std[e.name], False,
                                    {s: fit.params[e.name] for s, fit in by_session.items()},
                                    {s: fit.std[e.name] for s, fit in by_session.items()},
                                    solve.held_bounds(fleet, e),
                                    {s: h for s, fit in by_session.items() if (h := solve.held_bounds(fit, e))}))
        else:
            terms.append(EffectTerm(e.name, shared_params[e.name], shared_std[e.name], e.name in spec.fixed,
                                    held=solve.held_bounds(shared_fit, e)))
    return PhysicsModel(vehicle, terms, {s: sorted(fl) for s, fl in sessions.items()}, dict(spec.session_maps),
                        dict(spec.session_patterns))


def model_prediction(pm: PhysicsModel, fd: Predicting, log=lambda msg: None) -> np.ndarray:
    """The smoothed wrench of a fitted model on one flight, with its session's values and thrust
    map (the fleet value, said in ``log``, for a flight of no fitted session):
    :meth:`~quadcore.identify.flightdata.Flight.predict`, (n, 6) on its rows, a signal vector on
    its statistics."""
    model = flight_model(pm, fd.flight, log)
    return fd.predict([t.effect for t in model.terms], {t.name: t.params for t in model.terms}, model.vehicle)


def flight_model(pm: PhysicsModel, flight: str, log=lambda msg: None) -> PhysicsModel:
    """The fitted model of one flight (:meth:`~quadcore.identify.model.PhysicsModel.for_flight`: its
    session's values and thrust map), a flight of no fitted session said in ``log``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = pm.for_flight(flight)
    for w in caught:
        log(str(w.message))
    return model
