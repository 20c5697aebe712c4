"""The diagnosis's problem: its flights (rows or statistics, :class:`_Flights`), their targets,
the model's effects and the candidates (:class:`_Problem`), the folds (:func:`fold_splits`), the
cross-fit of the model and of every candidate on each fold's training flights
(:func:`_cross_fit`), and the evaluated flights as the scores take them (:func:`_held_out`);
the same for a model fitted once, to compare two candidates against (:func:`held_out_of_model`:
the planner's measured separation)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore.identify import evidence, fit as fitlib, flightdata
from quadcore.identify.describe import summaries
from quadcore.identify.evidence import default_candidates, scored_after_blocks
from quadcore.identify.fit import model_fit, sessions as sessionlib, solve
from quadcore.identify.flightdata import FlightData
from quadcore.identify.model import PhysicsModel
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.identify.stats import profiles, sufficient
from quadcore.spec.model import ModelSpec

TARGET_CHANNELS = {"force": slice(0, 3), "torque": slice(3, 6)}
MODEL_COLUMN = "pred:model"  # a model fitted on rows: its prediction as a column of the statistics


def _total(parts: Iterable[np.ndarray]) -> np.ndarray:
    """Element-wise sum of per-flight arrays (the same additions, in the same order, as ``sum``)."""
    return functools.reduce(np.add, parts)


@dataclass(frozen=True)
class _Residual:
    """The model's residual on some flights: per flight its ``signal`` and the flight it is a
    signal of (``on``: from statistics, grown by the model's profiled prediction as an extra
    column, :func:`quadcore.identify.stats.sufficient.predicted`), and per flight the values of the
    model's profiled effects it was taken at (name -> value; empty for a model of linear effects),
    or the rows of its prediction (a model fitted on rows, :func:`_model_on_rows`)."""

    signal: dict[str, np.ndarray]
    on: dict[str, Any]
    values: dict[str, dict[str, float]]
    extras: dict[str, dict[str, np.ndarray]]  # per flight: the rows of its extra columns known only on rows


class _Flights:
    """The diagnosis's flights as their sufficient statistics (:mod:`quadcore.identify.stats.sufficient`:
    ``stats[f]`` a :class:`~quadcore.identify.stats.sufficient.FlightStats`, every residual and
    prediction a signal vector), and their rows where those are needed (:meth:`rows`,
    :meth:`signal_rows`): the evaluated flights' residual summaries where the stored ones cannot
    describe the residual, the rate level of timing candidates, and what the statistics cannot
    express yet (:func:`_model_on_rows`)."""

    def __init__(self, decoded, spec: ModelSpec, ids: list[str], layout, stored):
        self.decoded, self.spec, self.ids = decoded, spec, ids
        self._rows: dict[str, FlightData] = {}
        self.stats = sufficient.for_flights(spec, decoded, ids, layout, stored)

    def rows(self, f: str) -> FlightData:
        if f not in self._rows:  # a session's thrust map for its state
            self._rows[f] = flightdata.flight_data(f, self.decoded[f], self.spec.vehicle_for(f))
        return self._rows[f]

    def release(self, f: str) -> None:
        """Let a flight's rows go."""
        self._rows.pop(f, None)

    def summary(self, f: str) -> summaries.FlightSummary | None:
        """A flight's stored summary (:mod:`quadcore.identify.describe.summaries`), if its statistics have one."""
        return self.stats[f].summary()

    def target(self, f: str) -> np.ndarray:
        return self.stats[f].layout.target()

    def signal_rows(self, f: str, signal: np.ndarray, layout: sufficient.Layout,
                    values: Mapping[str, float] | None = None, extras: Mapping[str, np.ndarray] | None = None
                    ) -> np.ndarray:
        """(n, 6) a signal vector of ``layout`` (the flight's statistics' own, grown by extra
        columns) on the flight's samples; its extra columns, found by name: ``values``, the model's
        profiled effects' values, whose predictions ``pred:<effect>`` are made on the rows
        (:meth:`model_columns`), and ``extras`` (name -> (n, 6) rows); any other extra column it
        uses has no rows here (the evaluated flights' columns of candidates are no part of a residual)."""
        columns = {**self.model_columns(f, values or {}), **(extras or {})}
        missing = [n for n in layout.extras if signal[layout.extra(n)] and n not in columns]
        if missing:
            raise sufficient.StatsError(f"{f}: the signal's extra column(s) {', '.join(missing)} have no rows here")
        return sufficient.signal_rows(self.rows(f), self.spec.vehicle, layout, signal, columns)

    def model_columns(self, f: str, values: Mapping[str, float]) -> dict[str, np.ndarray]:
        """(n, 6) on the flight's rows, the extra columns ``pred:<effect>`` of the model's profiled
        effects at ``values`` (name -> value), as the residual's statistics hold them: the profile's
        interpolated signal (:func:`quadcore.identify.stats.profiles.interpolated_prediction`), not
        the exact prediction, so that the residual on rows (the regime tables, the search's extra
        columns) is the residual scored. Measured 2026-11-26: with the exact prediction the
        residual's sum of squares on its rows was off its statistics' by up to 9.9e-6 relative on the
        19 real flights (committed model), 3e-5 to 1.2e-3 on simulated lagged flights; now by 1e-12 or
        less. It moved the real model's residual tables by up to 4e-5 relative (the spectrum's quiet
        bins 1.6e-3), a searched candidate beside it by 0.002 σ; it costs 31 predictions for one
        (+1.1 s CPU of 12.1 s for the real model's diagnosis)."""
        fd = self.rows(f)
        return {f"pred:{name}": profiles.interpolated_prediction(effectlib.get(name), v, fd, self.spec.vehicle)
                for name, v in values.items()}

    def residual(self, model_of: Callable[[str], tuple[list, Mapping[str, dict], Any]],
                 targets: Mapping[str, np.ndarray], flights: Iterable[str]) -> _Residual:
        """The residual of a fitted model on ``flights`` (``model_of(flight)``: its effects, their
        parameters and the vehicle there): from statistics, in each flight's statistics grown by
        the profiled effects' predictions (:func:`quadcore.identify.stats.sufficient.predicted`)."""
        signal: dict[str, np.ndarray] = {}
        on: dict[str, Any] = {}
        values: dict[str, dict[str, float]] = {}
        for f in flights:
            effects, params, vehicle = model_of(f)
            on[f], v = sufficient.predicted(effects, params, self.stats[f], vehicle)
            signal[f] = on[f].layout.pad(targets[f]) - v
            values[f] = {e.name: params[e.name][e.parameters[0].name] for e in effects if not e.linear}
        return _Residual(signal, on, values, {f: {} for f in signal})

    def residual_of_rows(self, model_of: Callable[[str], tuple[list, Mapping[str, dict], Any]],
                         targets: Mapping[str, np.ndarray], flights: Iterable[str]) -> _Residual:
        """The residual of a model whose prediction the profiles cannot carry (two nonlinear effects,
        several parameters, a nonlinear one per session): its prediction made on each flight's rows
        as an extra column ``pred:model`` of the flight's statistics, made where
        rows become statistics (:func:`quadcore.identify.stats.sufficient.flight_stats`: the profiles of the
        candidates against it too); the prediction's rows kept (the residual's rows)."""
        signal: dict[str, np.ndarray] = {}
        on: dict[str, Any] = {}
        extras: dict[str, dict[str, np.ndarray]] = {}
        for f in flights:
            effects, params, vehicle = model_of(f)
            fd, base = self.rows(f), self.stats[f]
            extras[f] = {MODEL_COLUMN: fd.predict(effects, params, vehicle)}
            on[f] = sufficient.flight_stats(fd, self.spec.vehicle, base.layout.with_extras([MODEL_COLUMN]), base.key,
                                            extras[f])
            fd.forget_bases()
            signal[f] = on[f].layout.pad(targets[f]) - on[f].layout.unit(on[f].layout.extra(MODEL_COLUMN))
        return _Residual(signal, on, {f: {} for f in signal}, extras)


class _Problem:
    """One diagnosis's flights (:class:`_Flights`), their targets, the model's effects and the
    candidates, and how the model and a candidate are fitted and predict: from the flights'
    statistics (``in_statistics``: the model's prediction from its profiles,
    :func:`quadcore.identify.fit.model_fit.from_statistics`; otherwise made on the rows and entering
    the statistics as a column, :meth:`_Flights.residual_of_rows`), a nonlinear effect without a
    profile (``by_rows``, or in the model) by the search, its predictions made on the training
    flights' rows (:func:`quadcore.identify.fit.search.search_fit`); a model with a nonlinear
    effect per session on rows (:func:`_model_on_rows`)."""

    def __init__(self, decoded: Mapping[str, pl.DataFrame], spec: ModelSpec, candidates: list[str] | None, stats,
                 skip: int | None = None, bounded: bool = True, noise_margin: float = DEFAULT.noise_margin):
        self.spec, self.vehicle = spec, spec.vehicle
        self.noise_margin = noise_margin  # a channel within it of its sensor-noise floor informs no candidate's fit
        self.ids = sorted(decoded)
        self.model_effects = [effectlib.get(n) for n in spec.effects]
        names = candidates if candidates is not None else default_candidates(spec)
        self.cands = [effectlib.get(n) for n in names]
        self.skip = scored_after_blocks(spec, names) if skip is None else skip
        self.bounded = bounded  # the candidates fitted within their parameters' physical bounds
        self.effect_of = {c.name: c for c in self.cands}
        self.fl = _Flights(decoded, spec, self.ids, sufficient.layout_of(self.model_effects + self.cands), stats)
        self.fds = self.fl.stats  # by flight id, in the order of ids
        self.targets = {f: self.fl.target(f) for f in self.ids}
        self.in_statistics = model_fit.from_statistics(spec, self.model_effects)
        self.fit_effects = functools.partial(fitlib.fit_effects, rows=self.fl.rows)  # as fit_model fits
        # a nonlinear effect fitted per session: from rows, as fit_model fits it
        self.per_session_nonlinear = any(not e.linear for e in self.model_effects if e.name in spec.per_session)
        # a nonlinear candidate is fitted and predicted from its profiles (quadcore.identify.stats.profiles);
        # one with several nonlinear parameters from rows
        self.by_rows = {c.name: not c.linear and not profiles.profiled(c) for c in self.cands}

    def fit_candidate(self, c, flights: list[str], resid: _Residual) -> solve.Fit:
        """``c`` alone fitted to ``resid`` (the model's residual) on ``flights``, within its
        parameters' physical bounds (the free fit, when it left them, kept as ``free``; free only
        when the problem says so: ``bounded``), in the channels :meth:`fitted_channels` gives, from
        the statistics (:func:`quadcore.identify.fit.fit_effects`); a candidate without a profile
        (``by_rows``) by the search, its predictions made on the training flights' rows
        (:func:`quadcore.identify.fit.search.search_fit`, the residual's extra columns given as rows)."""
        return fitlib.fit_effects([c], [resid.on[f] for f in flights], [resid.signal[f] for f in flights],
                                  self.vehicle, bounded=self.bounded, rows=self.fl.rows,
                                  extras=lambda f: {**self.fl.model_columns(f, resid.values[f]), **resid.extras[f]},
                                  channels=self.fitted_channels(c, flights, resid))

    def fitted_channels(self, c, flights: list[str], resid: _Residual) -> np.ndarray | None:
        """The channels a one-parameter candidate acting on force and torque is fitted in: with one
        of the two at its sensor-noise floor on the training ``flights`` (the model's residual
        within ``noise_margin`` of it, :func:`quadcore.identify.evidence.at_noise_level`, on the
        blocks the scores count: without the first ``skip``, :func:`_on_common_samples`), the other
        alone (:func:`quadcore.identify.evidence.channel_mask`); None (every channel) otherwise.
        One parameter shapes both channels' prediction, so either channel alone pins it; several
        may not be pinned by one channel (``rotor_imbalance``'s force is the small part its
        thrust differences leave in the collective thrust: fitted on force alone in hover its
        factors came out ±1.2, and their torque wrecked the score), so those keep every channel.

        A channel at its floor holds no evidence for an effect (:mod:`quadcore.identify.evidence`),
        and none for its size either: there the closed loop's errors in variables pull a thrust
        scale's torque part to ``scale - 1`` of -0.6 whether the thrust is scaled by 0.92 or a
        payload of 3 g is carried (three 8 s hovers, 2026-11-26), so a joint fit moved the thrust
        scale's force prediction by 0.002 of the thrust, and the held-out comparison on force, the
        channel above the floor, then preferred the payload by 14-20 σ whichever was true
        (docs/flight-planning.md, "Thrust scale against added mass")."""
        if c.target != "both" or len(c.parameters) != 1:
            return None
        on = _on_common_samples([resid.on[f] for f in flights], self.skip)  # the blocks the scores count
        ss = _total(fd.sum_of_squares(resid.signal[f]) for f, fd in zip(flights, on))
        floor = _total(fd.noise ** 2 * fd.n for fd in on)
        above = [ch for ch, quiet in evidence.at_noise_level(ss, floor, self.noise_margin).items() if not quiet]
        return evidence.channel_mask(above) if len(above) == 1 else None

    def scored_flight(self, c, f: str):
        """The flight as ``c``'s prediction takes it (rows for a candidate fitted from rows)."""
        return self.fl.rows(f) if self.by_rows[c.name] else self.fds[f]


def fold_splits(ids: list[str], holdout: list[str] | None, n_folds: int
            ) -> tuple[list[tuple[list[str], list[str]]], list[str], str]:
    """The (training, test) flights of each fold, all the training flights, and the mode: the
    held-out flights when given, else folds over the flights (in-sample with one flight)."""
    holdout = [h for h in (holdout or [])]
    if holdout:
        train_all = [f for f in ids if f not in holdout]
        return [(train_all, holdout)], train_all, "holdout"
    splits = ([([f for f in ids if f not in fold], fold) for fold in solve.folds(ids, n_folds)]
              if len(ids) > 1 else [(ids, ids)])
    return splits, ids, "cross-validation" if len(ids) > 1 else "in-sample (one flight only)"


ModelOf = Callable[[str], tuple[list, dict, Any]]  # a fitted model's effects, parameters and vehicle on a flight


def _model_residuals(p: _Problem, train: list[str], test: list[str], sessions, log) -> tuple[Any, _Residual]:
    """The model fitted on ``train`` (per session for a model with per-session effects), and its
    residual (target minus prediction) on the ``train`` and ``test`` flights."""
    fit_m, model_of = _fit_model(p, train, sessions, log)
    return fit_m, _residual(p, model_of, sorted({*train, *test}))


def _fit_model(p: _Problem, train: list[str], sessions, log) -> tuple[Any, ModelOf]:
    """The model fitted on ``train`` within its bounds, as fit_model fits it (its per-session
    effects per session of the training flights): the fit (a per-session model: a
    :class:`~quadcore.identify.model.PhysicsModel`) and the model on each flight."""
    if p.per_session_nonlinear:
        return _model_on_rows(p, train, sessions, log)
    if p.spec.per_session:
        pm = sessionlib.fit_per_session(p.spec, p.fds, p.targets, train, sessions, log, p.fit_effects)
        return pm, _session_terms(pm, log)
    fit_m = p.fit_effects(p.model_effects, [p.fds[f] for f in train], [p.targets[f] for f in train], p.vehicle,
                         p.spec.fixed, bounded=True)
    return fit_m, _fit_terms(p, fit_m)


def _fit_terms(p: _Problem, fit: solve.Fit) -> ModelOf:
    return lambda f: (p.model_effects, fit.params, p.vehicle)


def _residual(p: _Problem, model_of: ModelOf, flights: list[str]) -> _Residual:
    """The fitted model's residual on ``flights``, as signals of the flights' statistics."""
    of = p.fl.residual if p.in_statistics else p.fl.residual_of_rows
    return of(model_of, p.targets, flights)


# ---------------------------------------------------------------------------------------
# What the statistics cannot fit yet: a nonlinear effect per session, on rows
# ---------------------------------------------------------------------------------------

def _model_on_rows(p: _Problem, train: list[str], sessions, log) -> tuple[Any, ModelOf]:
    """:func:`_fit_model` on the flights' rows, for a model with a nonlinear effect per session, as
    fit_model fits it: each flight's rows made into statistics with the target as a column
    (:func:`quadcore.identify.fit.fit_rows`); its prediction then enters the statistics as a column."""
    rows = {f: p.fl.rows(f) for f in p.ids}
    targets = dict(zip(p.ids, flightdata.targets_of([rows[f] for f in p.ids])))
    if p.spec.per_session:
        pm = sessionlib.fit_per_session(p.spec, rows, targets, train, sessions, log, fitlib.fit_rows)
        return pm, _session_terms(pm, log)
    fit_m = fitlib.fit_rows(p.model_effects, [rows[f] for f in train], [targets[f] for f in train], p.vehicle,
                            p.spec.fixed, bounded=True)
    return fit_m, _fit_terms(p, fit_m)


def _session_terms(pm: PhysicsModel, log) -> Callable[[str], tuple[list, dict, Any]]:
    """A per-session model's effects, parameters and vehicle on a flight (its session's)."""
    def of(f: str) -> tuple[list, dict, Any]:
        model = sessionlib.flight_model(pm, f, log)
        return [t.effect for t in model.terms], {t.name: t.params for t in model.terms}, model.vehicle

    return of


@dataclass(frozen=True)
class _Folds:
    """What the folds leave: each test flight's model residual and every candidate's prediction
    there (fitted without it; for a candidate fitted from its profiles, ``values``: its
    parameter's value there, the prediction made by :func:`_evaluated`), each candidate's
    parameters per fold (the flight-to-flight spread; ``free_params``: of its fits without the
    physical bounds), and the last fold's fits of the model and of each candidate."""

    eval_resid: dict[str, np.ndarray]
    cand_pred: dict[str, dict[str, np.ndarray]]
    values: dict[str, dict[str, float]]
    params: dict[str, list[dict]]
    free_params: dict[str, list[dict]]
    fits: dict[str, solve.Fit]
    model_fit: Any
    model_values: dict[str, dict[str, float]]  # per test flight: its fold's model's profiled values
    eval_on: dict[str, Any]  # per test flight: the statistics its residual is a signal of
    eval_extras: dict[str, dict[str, np.ndarray]]  # per test flight: its residual's extra columns' rows


def _cross_fit(p: _Problem, splits: list[tuple[list[str], list[str]]], sessions, log,
               fixed: _Residual | None = None) -> _Folds:
    """Per fold: the model and each candidate (on the model's residual) fitted on the training
    flights, and their residual and predictions on the test flights; ``fixed``: the residual of a
    model fitted once (on every flight), not refitted per fold (:func:`held_out_of_model`)."""
    eval_resid: dict[str, np.ndarray] = {}
    cand_pred: dict[str, dict[str, np.ndarray]] = {c.name: {} for c in p.cands}
    fold_fits: dict[str, solve.Fit] = {}
    fold_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    free_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    values: dict[str, dict[str, float]] = {}
    model_values: dict[str, dict[str, float]] = {}
    eval_on: dict[str, Any] = {}
    eval_extras: dict[str, dict[str, np.ndarray]] = {}
    model_fit = None
    for k, (train, test) in enumerate(splits, 1):
        log(f"fold {k}/{len(splits)}: fitting on {len(train)} flights, scoring {len(test)}")
        model_fit, resid = (None, fixed) if fixed is not None else _model_residuals(p, train, test, sessions, log)
        for c in p.cands:
            fit_c = fold_fits[c.name] = p.fit_candidate(c, train, resid)
            fold_params[c.name].append(fit_c.params[c.name])
            free_params[c.name].append((fit_c.free or fit_c).params[c.name])
            for f in test:
                if profiles.profiled(c):
                    values.setdefault(c.name, {})[f] = fit_c.params[c.name][c.parameters[0].name]
                else:
                    cand_pred[c.name][f] = fit_c.predict([c], p.scored_flight(c, f), p.vehicle)
        for f in test:
            eval_resid[f], model_values[f] = resid.signal[f], resid.values[f]
            eval_on[f], eval_extras[f] = resid.on[f], resid.extras[f]
    return _Folds(eval_resid, cand_pred, values, fold_params, free_params, fold_fits, model_fit, model_values,
                  eval_on, eval_extras)


def _training_model(p: _Problem, fold_fit, train_all: list[str], sessions, log) -> tuple[PhysicsModel, _Residual]:
    """The model fitted on all training flights (the parameters reported; ``fold_fit``, the only
    fold's fit, when it is that one) and its residual on them."""
    spec = p.spec
    fit_m, model_of = ((fold_fit, _session_terms(fold_fit, lambda msg: None) if spec.per_session
                        else _fit_terms(p, fold_fit)) if fold_fit is not None
                       else _fit_model(p, train_all, sessions, log))
    model = fit_m if spec.per_session else PhysicsModel(
        p.vehicle, solve.model_terms(p.model_effects, fit_m, spec.fixed),
        spec.sessions_of(p.ids) if spec.session_maps else {}, spec.session_maps)
    return model, _residual(p, model_of, train_all)


def _group_spread(p: _Problem, train_all: list[str], resid_train: _Residual, n_folds: int
                  ) -> tuple[dict[str, list[dict]], dict[str, list[dict]]]:
    """One split only: each candidate refitted leaving out groups of training flights, for the
    spread, in place of its fit on all of them: its parameters per group, within the bounds and
    free."""
    fold_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    free_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    for group in solve.folds(train_all, n_folds):
        sub = [f for f in train_all if f not in group]
        for c in p.cands:
            fit = p.fit_candidate(c, sub, resid_train)
            fold_params[c.name].append(fit.params[c.name])
            free_params[c.name].append((fit.free or fit).params[c.name])
    return fold_params, free_params


@dataclass(frozen=True)
class HeldOut:
    """The evaluated flights as the scores take them (:func:`_evaluated`), the model's residual
    and each candidate's prediction on them, the residual's sums of squares per channel
    (``before``) over ``n`` samples, the sensor-noise floor's, the channels at that floor, and
    the channel weights."""

    ids: list[str]
    flights: list
    resid: dict[str, np.ndarray]
    cand_pred: dict[str, dict[str, np.ndarray]]
    before: np.ndarray
    n: int
    noise_ss: np.ndarray
    at_noise: dict[str, bool]
    w: np.ndarray
    model_values: dict[str, dict[str, float]]  # per flight: the model's profiled values in ``resid``
    extras: dict[str, dict[str, np.ndarray]]  # per flight: the rows of ``resid``'s columns known only on rows


def _held_out(p: _Problem, folds: _Folds, settings: DiagnosisSettings) -> HeldOut:
    eval_ids = sorted(folds.eval_resid)
    eval_fds = _on_common_samples(_evaluated(p, eval_ids, folds), p.skip)
    before = _total(fd.sum_of_squares(folds.eval_resid[f]) for f, fd in zip(eval_ids, eval_fds))
    n_eval = sum(fd.n for fd in eval_fds)
    # The sensor-noise floor: a channel whose residual is within settings.noise_margin of it
    # holds no evidence FOR an effect (only against one that would add error there).
    noise_ss = _total(fd.noise ** 2 * fd.n for fd in eval_fds)
    at_noise = evidence.at_noise_level(before, noise_ss, settings.noise_margin)
    w = fitlib.channel_weights(eval_fds, [folds.eval_resid[f] for f in eval_ids])
    return HeldOut(eval_ids, eval_fds, folds.eval_resid, folds.cand_pred, before, n_eval, noise_ss, at_noise, w,
                    folds.model_values, folds.eval_extras)


def held_out_of_model(decoded: Mapping[str, pl.DataFrame], spec: ModelSpec, model: PhysicsModel,
                      candidates: list[str], n_folds: int, skip: int, bounded: bool = True, stats=None,
                      settings: DiagnosisSettings = DEFAULT) -> HeldOut:
    """The held-out comparison of ``candidates`` against the residual of a fitted ``model`` (its
    fleet, or each flight's session's, values; not refitted per fold), from the flights'
    statistics as the diagnosis takes them (:class:`_Problem`): folds over the flights
    (:func:`fold_splits`), each candidate fitted on the training flights' residual (``bounded``:
    within its physical bounds) and predicting the test flights' (a signal vector; a nonlinear
    one from its profiles or as an extra column, :func:`_evaluated`), every flight scored without
    its first ``skip`` blocks (:func:`_on_common_samples`). ``stats``: stored statistics, as for
    :func:`quadcore.identify.diagnosis.diagnose`."""
    p = _Problem(decoded, spec, candidates, stats, skip=skip, bounded=bounded, noise_margin=settings.noise_margin)
    splits, _, _ = fold_splits(p.ids, None, n_folds)
    resid = _residual(p, _session_terms(model, lambda msg: None), p.ids)
    folds = _cross_fit(p, splits, None, lambda msg: None, fixed=resid)
    return _held_out(p, folds, settings)


def _evaluated(p: _Problem, eval_ids: list[str], folds: _Folds) -> list[sufficient.FlightStats]:
    """The evaluated flights as the scores take them. From statistics, a nonlinear candidate's
    held-out prediction is an extra column ``pred:`` + its name of the evaluated flights'
    statistics: from its profile at the fitted value (:func:`quadcore.identify.stats.profiles.with_predictions`,
    no rows read), or, for a candidate without one (several nonlinear parameters), from the
    flight's rows with its unit wrenches (:func:`detection_limits`; ``unit:``, ``ref:``); the
    signals of ``cand_pred`` and ``eval_resid`` are moved into that layout. The residual's own
    columns (the model's prediction) come first: its profiled effects' at the fold's values, from
    their profiles with the candidates' in one go, or a model fitted on rows: the statistics the
    fold made with its prediction (their profiles hold the candidates' sums against it)."""
    fl, cand_pred, eval_resid = p.fl, folds.cand_pred, folds.eval_resid
    by_rows = [c for c in p.cands if p.by_rows[c.name]]
    if not by_rows and not folds.values and all(folds.eval_on[f] is fl.stats[f] for f in eval_ids):
        return [fl.stats[f] for f in eval_ids]
    out = []
    for f in eval_ids:
        model = folds.model_values[f]  # the model's profiled predictions, made again below
        base = fl.stats[f] if model else folds.eval_on[f]
        s = _with_row_predictions(fl, f, by_rows, cand_pred, base, folds.eval_extras[f]) if by_rows else base
        values = {**model, **{c: values[f] for c, values in folds.values.items()}}
        if values:
            s = profiles.with_predictions(s, values, signals=list(model))
        eval_resid[f] = _moved(eval_resid[f], folds.eval_on[f].layout, s.layout)
        for c in p.cands:
            cand_pred[c.name][f] = (s.layout.unit(s.layout.extra(f"pred:{c.name}")) if not c.linear
                                    else s.layout.pad(cand_pred[c.name][f]))
        out.append(s)
    return out


def _moved(v: np.ndarray, source: sufficient.Layout, to: sufficient.Layout) -> np.ndarray:
    """A signal vector of the layout ``source`` in the layout ``to`` (which holds every column of
    ``source`` it uses, by name)."""
    out = np.zeros(to.width)
    for name in source.effects:
        out[to.cols(name)] = v[source.cols(name)]
    out[to.y0] = v[source.y0]
    for name in source.extras:
        if v[source.extra(name)]:
            out[to.extra(name)] = v[source.extra(name)]
    return out


def _with_row_predictions(fl: _Flights, f: str, cands, cand_pred: dict, base: sufficient.FlightStats,
                          base_extras: Mapping[str, np.ndarray]) -> sufficient.FlightStats:
    """A flight's statistics ``base`` (its own columns, then ``base_extras``: name -> rows) with the
    held-out predictions of ``cands`` (no profile) and their unit wrenches as extra columns, from
    its rows (read once)."""
    vehicle, fd = fl.spec.vehicle, fl.rows(f)
    extras = dict(base_extras)
    for c in cands:  # its prediction, then its unit wrenches and reference as a profiled effect has them
        extras[f"pred:{c.name}"] = cand_pred[c.name][f]
        extras.update(profiles.fixed_signals([c.name], fd, vehicle))
    s = sufficient.flight_stats(fd, vehicle, fl.stats[f].layout.with_extras(list(extras)), base.key, extras)
    fd.forget_bases()  # every linear effect's basis on every evaluated flight: memory the statistics spare
    return s


def _on_common_samples(flights: list[sufficient.FlightStats], k: int) -> list[sufficient.FlightStats]:
    """The evaluated flights without the first ``k`` blocks (of ``BLOCK_S``, numbered as the held-out
    test numbers them): those within the longest :meth:`~quadcore.effects.Effect.memory_s` of the
    model's effects and the candidates (:func:`quadcore.identify.evidence.scored_after_blocks`):
    an effect with memory predicts nothing there (:func:`quadcore.identify.flightdata.prediction`),
    so a score over the whole flight would count that start against it and not against a
    memoryless candidate, or a shorter memory. Every candidate, the model's residual and the
    noise floor are scored on the same samples (and term discovery's held-out RMSE); whole blocks,
    so that the statistics (per-block Gram matrices) and the rows leave out the same. Flights too
    short to keep any sample after it are evaluated whole (nothing would be left to compare)."""
    if k <= 0:
        return flights
    out = [fd.after_blocks(k) for fd in flights]
    return out if sum(fd.n for fd in out) > 0 else flights
