"""The model a spec names, fitted (:func:`fit_model`) from the flights' statistics, per session
where the spec asks: linear effects from the normal equations, one effect with a single nonlinear
parameter from its profiles, any other nonlinear effects by the search whose predictions are made
on the training flights' rows (:mod:`quadcore.identify.fit`, chosen there by the effects' kinds).
Above the fits (:mod:`quadcore.identify.fit`) and per session (:mod:`quadcore.identify.fit.sessions`).
One case still fits on rows: a per-session effect that is nonlinear (its per-session prediction
is no signal vector of the statistics). :func:`from_statistics`: whether the statistics alone, no
row read, express a model (the diagnosis holds its flights as statistics then; a fixed profiled
effect beside per-session ones is subtracted as its column)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

from quadcore import effects as effectlib
from quadcore.effects import Effect
from quadcore.identify import fit as fitlib
from quadcore.identify.fit import sessions as sessionlib, solve
from quadcore.identify.flightdata import FlightData, flight_data, targets_of
from quadcore.identify.model import PhysicsModel
from quadcore.identify.stats import profiles, sufficient
from quadcore.spec.model import ModelSpec


def expressible(effects: list[Effect], fixed: Mapping[str, object]) -> bool:
    """Whether a joint fit of ``effects`` comes from the flights' statistics
    (:func:`quadcore.identify.fit.fit_effects`): linear effects, profiled nonlinear ones (one
    parameter each), at most one of them not in ``fixed``."""
    nonlinear = [e for e in effects if not e.linear]
    return all(profiles.profiled(e) for e in nonlinear) and sum(e.name not in fixed for e in nonlinear) <= 1


def from_statistics(spec: ModelSpec, effects: list[Effect]) -> bool:
    """Whether :func:`fit_model` fits ``effects`` from the flights' statistics: linear effects, and
    one profiled nonlinear effect beside them (fixed ones too), not itself fitted per session
    (the shared fits of a per-session model hold the per-session effects' predictions)."""
    return expressible(effects, spec.fixed) and not any(not e.linear and e.name in spec.per_session
                                                        for e in effects)


def rows_of(spec: ModelSpec, decoded: Mapping) -> Callable[[str], FlightData]:
    """``rows(flight)``: a flight's rows (its session's thrust map), made once when first asked for
    (the search's nonlinear predictions)."""
    return functools.cache(lambda f: flight_data(f, decoded[f], spec.vehicle_for(f)))


def fit_model(spec: ModelSpec, decoded: Mapping, train: list[str], sessions: dict[str, list[str]] | None = None,
              log: Callable[[str], None] | None = None, stats=None) -> PhysicsModel:
    """Fit the effects a :class:`quadcore.spec.model.ModelSpec` names on the ``train`` flights (its
    ``per_session`` effects per session: :func:`quadcore.identify.fit.sessions.fit_per_session`), within
    their parameters' physical bounds; a parameter held at a bound says so in its term
    (:func:`quadcore.identify.fit.solve.held_bounds`: its free value, and whether that is within
    noise of the bound).

    From the flights' sufficient statistics (:mod:`quadcore.identify.stats.sufficient`; ``stats(flight)``
    gives a flight's stored ones, None: computed from its decoded table) by
    :func:`quadcore.identify.fit.fit_effects`: a nonlinear effect with one parameter from its profiles,
    other nonlinear effects by the search, which reads the training flights' rows for their
    predictions. A nonlinear effect fitted per session reads every training flight's rows."""
    effect_list = [effectlib.get(n) for n in spec.effects]
    maps = ((spec.sessions_of(sorted(decoded)), spec.session_maps, spec.session_patterns) if spec.session_maps
            else ({}, {}, {}))
    if not effect_list:
        return PhysicsModel(spec.vehicle, [], *maps)
    if all(e.linear for e in effect_list if e.name in spec.per_session):
        by_id: dict = sufficient.for_flights(spec, decoded, train, sufficient.layout_of(effect_list), stats)
        targets = {f: s.layout.target() for f, s in by_id.items()}
        fit: sessionlib.FitEffects = functools.partial(fitlib.fit_effects, rows=rows_of(spec, decoded))
    else:
        by_id = {f: flight_data(f, decoded[f], spec.vehicle_for(f)) for f in train}
        targets = dict(zip(train, targets_of([by_id[f] for f in train])))
        fit = fitlib.fit_rows
    if spec.per_session:
        return sessionlib.fit_per_session(spec, by_id, targets, train, sessions, log or (lambda msg: None), fit)
    fitted = fit(effect_list, [by_id[f] for f in train], [targets[f] for f in train], spec.vehicle, spec.fixed,
                 bounded=True)
    return PhysicsModel(spec.vehicle, solve.model_terms(effect_list, fitted, spec.fixed), *maps)
