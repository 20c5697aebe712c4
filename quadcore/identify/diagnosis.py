"""Where the model fails, and which physical effect is missing: :func:`diagnose` fits every effect
of the library that the model lacks on the training flights and scores it on flights it never saw.

How it decides (held-out significance, the noise floor, ties the data cannot break, what is
missing beside the best one) is in ``docs/diagnosis.md``; the regime tables are in
:mod:`quadcore.identify.regimes`, the verdict text and report rows in :mod:`quadcore.identify.verdict`,
the thresholds in :mod:`quadcore.identify.evidence`.
"""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore.identify import evidence, fitting, profiles, sessions as sessionlib, spectrum, sufficient, summaries
from quadcore.identify.evidence import (
    BOUND_SIGMA,
    LARGE_SNR,
    LIBRARY_SHARE,
    MIN_EXPLAINED,
    MIN_SIGMA,
    SAME_SIGNATURE,
    TIE_MARGIN,
)
from quadcore.identify.fitting import FlightData
from quadcore.identify.model import EffectTerm, PhysicsModel
from quadcore.identify.regimes import flight_table, long_frame, regime_table, worst_segments
from quadcore.identify.results import (
    NO_EVIDENCE,
    NOTHING,
    CandidateScore,
    Diagnosis,
    Evaluation,
    ResidualRmse,
    Stability,
)
from quadcore.identify.verdict import _ev_on, _other, rank_reasons, verdict
from quadcore.physics.dynamics import XYZ
from quadcore.spec.model import ModelSpec


def _total(parts: Iterable[np.ndarray]) -> np.ndarray:
    """Element-wise sum of per-flight arrays (the same additions, in the same order, as ``sum``)."""
    return functools.reduce(np.add, parts)


def _ev(before: np.ndarray, after: np.ndarray, channels: slice) -> float:
    b = before[channels].sum()
    return float(1.0 - after[channels].sum() / b) if b > 0 else 0.0


TARGET_CHANNELS = {"force": slice(0, 3), "torque": slice(3, 6)}


def _jackknife_std(fold_params: list[dict]) -> dict[str, float]:
    """Grouped-jackknife standard error of each parameter from fits that each leave out one
    group of flights: ``sqrt((K-1)/K Σ_k (θ_k - θ̄)²)``; empty with fewer than two groups."""
    if len(fold_params) < 2:
        return {}
    k = len(fold_params)
    out = {}
    for name in fold_params[0]:
        vals = np.array([p[name] for p in fold_params])
        out[name] = float(np.sqrt((k - 1) / k * np.sum((vals - vals.mean()) ** 2)))
    return out


class _Flights:
    """The diagnosis's flights, in one of two forms, and the rows where they are needed.

    A model of linear effects is scored from the flights' sufficient statistics
    (:mod:`quadcore.identify.sufficient`: ``flight(f)`` a :class:`~quadcore.identify.sufficient.FlightStats`,
    every residual and linear prediction a signal vector); a model with a nonlinear effect
    from rows (``flight(f)`` a :class:`~quadcore.identify.fitting.FlightData`, signals (n, 6) arrays).
    Rows are read only when asked for (:meth:`rows`, :meth:`signal_rows`): the evaluated
    flights' tables and spectra, and candidates with several nonlinear parameters (a
    one-parameter nonlinear candidate comes from the flights' profiles,
    :mod:`quadcore.identify.profiles`)."""

    def __init__(self, decoded, spec: ModelSpec, ids: list[str], layout, stored):
        self.decoded, self.spec, self.ids = decoded, spec, ids
        self._rows: dict[str, FlightData] = {}
        self._rates: dict[str, float] = {}  # each flight's sample rate, kept when its rows go
        self.linear = all(effectlib.get(n).linear for n in spec.effects)
        self.stats = sufficient.for_flights(spec, decoded, ids, layout, stored) if self.linear else None

    def rows(self, f: str) -> FlightData:
        if f not in self._rows:  # a session's thrust map for its state
            self._rows[f] = fitting.flight_data(f, self.decoded[f], self.spec.vehicle_for(f))
            self._rates[f] = spectrum.sample_rate_hz(self._rows[f].state.t_s)
        return self._rows[f]

    def release(self, f: str) -> None:
        """Let a flight's rows go (from statistics; from rows the flight is the statistics)."""
        if self.stats is not None:
            self._rows.pop(f, None)

    def sample_rate_hz(self, f: str) -> float:
        if f not in self._rates:
            self.rows(f)
            self.release(f)
        return self._rates[f]

    def statistics(self, f: str) -> sufficient.FlightStats:
        """A flight's statistics (only a model of linear effects is scored from them)."""
        if self.stats is None:
            raise sufficient.StatsError(f"{f}: a model with a nonlinear effect is scored from rows, not statistics")
        return self.stats[f]

    def flight(self, f: str):
        return self.stats[f] if self.stats is not None else self.rows(f)

    def target(self, f: str) -> np.ndarray:
        if self.stats is not None:
            return self.stats[f].layout.target()
        fd = self.rows(f)
        return np.concatenate([fd.r_f, fd.r_tau], axis=1)

    def signal_rows(self, f: str, signal: np.ndarray) -> np.ndarray:
        """(n, 6) a signal on the flight's samples (a vector turned into rows; rows as they are)."""
        if self.stats is None or signal.ndim == 2:
            return signal
        layout = self.stats[f].layout  # the evaluated flights' extra columns are no part of a residual
        if np.any(signal[layout.width:]):
            raise sufficient.StatsError(f"{f}: a signal on extra columns has no rows here")
        return sufficient.signal_rows(self.rows(f), self.spec.vehicle, layout, signal[: layout.width])


def _ss(resid: np.ndarray, flight) -> np.ndarray:
    """Sum of squares per channel (6,) on usable samples (of a signal vector: from statistics)."""
    if resid.ndim == 1:
        return sufficient.sum_of_squares(flight, resid)
    return (resid[flight.mask] ** 2).sum(axis=0)


def _weights(flights: list, signals: list[np.ndarray]) -> np.ndarray:
    if signals and signals[0].ndim == 1:
        return sufficient.channel_weights(flights, signals)
    return fitting.channel_weights([y[fd.mask] for fd, y in zip(flights, signals)])


def _evaluated(p: _Problem, eval_ids: list[str], folds: _Folds) -> list:
    """The evaluated flights as the scores take them. From statistics, a nonlinear candidate's
    held-out prediction is an extra column ``pred:`` + its name of the evaluated flights'
    statistics: from its profile at the fitted value (:func:`quadcore.identify.profiles.with_predictions`,
    no rows read), or, for a candidate without one (several nonlinear parameters), from the
    flight's rows with its unit wrenches (:func:`detection_limits`; ``unit:``, ``ref:``); the
    signals of ``cand_pred`` and ``eval_resid`` are moved into that layout."""
    fl, cand_pred, eval_resid = p.fl, folds.cand_pred, folds.eval_resid
    if fl.stats is None:
        return [fl.rows(f) for f in eval_ids]
    by_rows = [c for c in p.cands if p.by_rows[c.name]]
    if not by_rows and not folds.values:
        return [fl.stats[f] for f in eval_ids]
    out = []
    for f in eval_ids:
        s = _with_row_predictions(fl, f, by_rows, cand_pred) if by_rows else fl.stats[f]
        if folds.values:
            s = profiles.with_predictions(s, {c: values[f] for c, values in folds.values.items()})
        eval_resid[f] = s.layout.pad(eval_resid[f])
        for c in p.cands:
            cand_pred[c.name][f] = (s.layout.unit(s.layout.extra(f"pred:{c.name}")) if not c.linear
                                    else s.layout.pad(cand_pred[c.name][f]))
        out.append(s)
    return out


def _with_row_predictions(fl: _Flights, f: str, cands, cand_pred: dict) -> sufficient.FlightStats:
    """A flight's statistics with the held-out predictions of ``cands`` (no profile) and their
    unit wrenches as extra columns, from its rows (read once)."""
    vehicle, fd, base = fl.spec.vehicle, fl.rows(f), fl.statistics(f)
    extras = {}
    for c in cands:  # its prediction, then its unit wrenches and reference as a profiled effect has them
        extras[f"pred:{c.name}"] = cand_pred[c.name][f]
        extras.update(profiles.fixed_signals([c.name], fd, vehicle))
    s = sufficient.flight_stats(fd, vehicle, base.layout.with_extras(list(extras)), base.key, extras)
    fd.forget_bases()  # every linear effect's basis on every evaluated flight: memory the statistics spare
    return s


def _unit(c, p, fd, vehicle) -> np.ndarray:
    """:func:`quadcore.identify.evidence.unit_wrench` on rows, or as a signal vector on statistics."""
    if isinstance(fd, FlightData):
        return evidence.unit_wrench(c, p, fd, vehicle)
    if c.linear:
        return sufficient.unit_vector(c, p, fd, vehicle, evidence.SECANT)
    return fd.layout.unit(fd.layout.extra(f"unit:{c.name}:{p.name}"))


def _reference_ss(c, fd, vehicle) -> float:
    """Energy of a candidate's prediction at its sensitivity reference on a flight's usable samples."""
    ref = {**c.defaults(), **c.sensitivity_reference}
    if isinstance(fd, FlightData):
        return float((fitting.prediction(c, ref, fd, vehicle)[fd.mask] ** 2).sum())
    v = (fd.layout.coefficients(c, ref, vehicle) if c.linear else fd.layout.unit(fd.layout.extra(f"ref:{c.name}")))
    return float(sufficient.sum_of_squares(fd, v).sum())


class _Problem:
    """One diagnosis's flights in the form it scores them (:class:`_Flights`), their targets, the
    model's effects and the candidates, and how a candidate is fitted: from the flights'
    statistics, or (``by_rows``: a nonlinear candidate beside statistics) from its training
    flights' rows."""

    def __init__(self, decoded: Mapping[str, pl.DataFrame], spec: ModelSpec, candidates: list[str] | None, stats):
        self.spec, self.vehicle = spec, spec.vehicle
        self.ids = sorted(decoded)
        self.model_effects = [effectlib.get(n) for n in spec.effects]
        names = candidates if candidates is not None else default_candidates(spec)
        self.cands = [effectlib.get(n) for n in names]
        self.effect_of = {c.name: c for c in self.cands}
        self.fl = _Flights(decoded, spec, self.ids, sufficient.layout_of(self.model_effects + self.cands), stats)
        self.fds = {f: self.fl.flight(f) for f in self.ids}
        self.targets = {f: self.fl.target(f) for f in self.ids}
        # from statistics, a nonlinear candidate is fitted and predicted from its profiles
        # (quadcore.identify.profiles); one with several nonlinear parameters from rows
        self.by_rows = {c.name: self.fl.stats is not None and not c.linear and not profiles.profiled(c)
                        for c in self.cands}
        # the latest residual turned into rows once for all nonlinear candidates (a fold's
        # candidates share it; later fits never come back to an older one), so rows of one
        # residual are held, not one per fold; the residual is kept so its id cannot be reused
        self._row_resid_of: tuple[dict, dict[str, np.ndarray]] = ({}, {})

    def fit_candidate(self, c, flights: list[str], resid: dict) -> fitting.Fit:
        """``c`` alone fitted to ``resid`` (the model's residual) on ``flights``, within its
        parameters' physical bounds (the free fit, when it left them, kept as ``free``)."""
        if self.by_rows[c.name]:
            return fitting.fit_effects([c], [self.fl.rows(f) for f in flights],
                                       [self._row_resid(f, resid) for f in flights], self.vehicle, bounded=True)
        return fitting.fit_effects([c], [self.fds[f] for f in flights], [resid[f] for f in flights], self.vehicle,
                                   bounded=True)

    def _row_resid(self, f: str, resid: dict) -> np.ndarray:
        if self._row_resid_of[0] is not resid:
            self._row_resid_of = (resid, {})
        rows = self._row_resid_of[1]
        if f not in rows:
            rows[f] = self.fl.signal_rows(f, resid[f])
        return rows[f]

    def forget_row_resid(self) -> None:
        """Drop the residual rows the nonlinear candidates' fits kept (after the last fit)."""
        self._row_resid_of = ({}, {})

    def from_profile(self, c) -> bool:
        """Whether ``c`` is fitted and predicted from the flights' profiles."""
        return self.fl.stats is not None and profiles.profiled(c)

    def scored_flight(self, c, f: str):
        """The flight as ``c``'s prediction takes it (rows for a candidate fitted from rows)."""
        return self.fl.rows(f) if self.by_rows[c.name] else self.fds[f]


def default_candidates(spec: ModelSpec) -> list[str]:
    """The effects a diagnosis offers when not told which: the library's built-in effects, then
    the plugin effects of the spec's own model file (its ``plugins``), each offered and not
    already in the model. Not every effect this process has loaded: a long-lived process (the
    Dagster UI, a test run) keeps the plugins of every model file it ever read, and another
    model's plugin is no candidate for this one."""
    own = [src.effect for src in effectlib.plugins_from(spec.plugins)]
    return [n for n in (*effectlib.builtin_names(), *own) if n not in spec.effects and effectlib.get(n).offered]


def _splits(ids: list[str], holdout: list[str] | None, n_folds: int
            ) -> tuple[list[tuple[list[str], list[str]]], list[str], str]:
    """The (training, test) flights of each fold, all the training flights, and the mode: the
    held-out flights when given, else folds over the flights (in-sample with one flight)."""
    holdout = [h for h in (holdout or [])]
    if holdout:
        train_all = [f for f in ids if f not in holdout]
        return [(train_all, holdout)], train_all, "holdout"
    splits = ([([f for f in ids if f not in fold], fold) for fold in fitting.folds(ids, n_folds)]
              if len(ids) > 1 else [(ids, ids)])
    return splits, ids, "cross-validation" if len(ids) > 1 else "in-sample (one flight only)"


def _model_residuals(p: _Problem, train: list[str], test: list[str], sessions, log) -> tuple[Any, dict]:
    """The model fitted on ``train`` (per session for a model with per-session effects), and its
    residual (target minus prediction) on the ``train`` and ``test`` flights."""
    fds, targets = p.fds, p.targets
    tr = [fds[f] for f in train]
    if p.spec.per_session:  # the model's per-session effects fitted per session of the training flights
        pm = sessionlib.fit_per_session(p.spec, fds, targets, train, sessions, log)
        return pm, {f: targets[f] - sessionlib.model_prediction(pm, fds[f], log) for f in {*train, *test}}
    fit_m = fitting.fit_effects(p.model_effects, tr, [targets[f] for f in train], p.vehicle, p.spec.fixed)
    return fit_m, {f: targets[f] - fit_m.predict(p.model_effects, fds[f], p.vehicle) for f in {*train, *test}}


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
    fits: dict[str, fitting.Fit]
    model_fit: Any


def _cross_fit(p: _Problem, splits: list[tuple[list[str], list[str]]], sessions, log) -> _Folds:
    """Per fold: the model and each candidate (on the model's residual) fitted on the training
    flights, and their residual and predictions on the test flights."""
    eval_resid: dict[str, np.ndarray] = {}
    cand_pred: dict[str, dict[str, np.ndarray]] = {c.name: {} for c in p.cands}
    fold_fits: dict[str, fitting.Fit] = {}
    fold_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    free_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    values: dict[str, dict[str, float]] = {}
    model_fit = None
    for k, (train, test) in enumerate(splits, 1):
        log(f"fold {k}/{len(splits)}: fitting on {len(train)} flights, scoring {len(test)}")
        model_fit, resid = _model_residuals(p, train, test, sessions, log)
        for c in p.cands:
            fit_c = fold_fits[c.name] = p.fit_candidate(c, train, resid)
            fold_params[c.name].append(fit_c.params[c.name])
            free_params[c.name].append((fit_c.free or fit_c).params[c.name])
            for f in test:
                if p.from_profile(c):
                    values.setdefault(c.name, {})[f] = fit_c.params[c.name][c.parameters[0].name]
                else:
                    cand_pred[c.name][f] = fit_c.predict([c], p.scored_flight(c, f), p.vehicle)
        for f in test:
            eval_resid[f] = resid[f]
    return _Folds(eval_resid, cand_pred, values, fold_params, free_params, fold_fits, model_fit)


def _training_model(p: _Problem, fold_fit, train_all: list[str], sessions, log) -> tuple[PhysicsModel, dict]:
    """The model fitted on all training flights (the parameters reported; ``fold_fit``, the only
    fold's fit, when it is that one) and its residual on them."""
    fds, targets, spec = p.fds, p.targets, p.spec
    tr = [fds[f] for f in train_all]
    if spec.per_session:
        model = fold_fit if fold_fit is not None else sessionlib.fit_per_session(spec, fds, targets, train_all,
                                                                                 sessions, log)
        return model, {f: targets[f] - sessionlib.model_prediction(model, fds[f]) for f in train_all}
    fit_m = (fold_fit if fold_fit is not None
             else fitting.fit_effects(p.model_effects, tr, [targets[f] for f in train_all], p.vehicle, spec.fixed))
    model = PhysicsModel(p.vehicle, [EffectTerm(e.name, fit_m.params[e.name], fit_m.std[e.name],
                                                e.name in spec.fixed) for e in p.model_effects],
                         spec.sessions_of(p.ids) if spec.session_maps else {}, spec.session_maps)
    return model, {f: targets[f] - fit_m.predict(p.model_effects, fds[f], p.vehicle) for f in train_all}


def _group_spread(p: _Problem, train_all: list[str], resid_train: dict, n_folds: int
                  ) -> tuple[dict[str, list[dict]], dict[str, list[dict]]]:
    """One split only: each candidate refitted leaving out groups of training flights, for the
    spread, in place of its fit on all of them: its parameters per group, within the bounds and
    free."""
    fold_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    free_params: dict[str, list[dict]] = {c.name: [] for c in p.cands}
    for group in fitting.folds(train_all, n_folds):
        sub = [f for f in train_all if f not in group]
        for c in p.cands:
            fit = p.fit_candidate(c, sub, resid_train)
            fold_params[c.name].append(fit.params[c.name])
            free_params[c.name].append((fit.free or fit).params[c.name])
    return fold_params, free_params


@dataclass(frozen=True)
class _HeldOut:
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


def _held_out(p: _Problem, folds: _Folds) -> _HeldOut:
    eval_ids = sorted(folds.eval_resid)
    eval_fds = _on_common_samples(_evaluated(p, eval_ids, folds), p.model_effects + p.cands)
    before = _total(_ss(folds.eval_resid[f], fd) for f, fd in zip(eval_ids, eval_fds))
    n_eval = sum(fd.n for fd in eval_fds)
    # The sensor-noise floor: a channel whose residual is within evidence.NOISE_MARGIN of it
    # holds no evidence FOR an effect (only against one that would add error there).
    noise_ss = _total(fd.noise ** 2 * fd.n for fd in eval_fds)
    at_noise = evidence.at_noise_level(before, noise_ss)
    w = _weights(eval_fds, [folds.eval_resid[f] for f in eval_ids])
    return _HeldOut(eval_ids, eval_fds, folds.eval_resid, folds.cand_pred, before, n_eval, noise_ss, at_noise, w)


def _on_common_samples(flights: list, effects) -> list:
    """The evaluated flights without the first blocks (of ``BLOCK_S``, numbered as the held-out
    test numbers them) within the longest :meth:`~quadcore.effects.Effect.memory_s` of
    ``effects``: an effect with memory predicts nothing there (:func:`quadcore.identify.fitting.prediction`),
    so a score over the whole flight would count that start against it and not against a
    memoryless candidate, or a shorter memory. Every candidate, the model's residual and the
    noise floor are scored on the same samples; whole blocks, so that the statistics (per-block
    Gram matrices) and the rows leave out the same. Flights too short to keep any sample
    after it are evaluated whole (nothing would be left to compare)."""
    k = evidence.memory_blocks(effects)
    if k <= 0:
        return flights
    out = [_after_blocks(fd, k) for fd in flights]
    return out if sum(fd.n for fd in out) > 0 else flights


def _after_blocks(fd, k: int):
    """A flight's rows (:class:`FlightData`) or statistics without its first ``k`` blocks."""
    if isinstance(fd, FlightData):
        return evidence.after_blocks(fd, k)
    gram = fd.gram[k:]
    return replace(fd, total=gram.sum(axis=0), rows=fd.rows[k:], blocks_source=lambda: gram)


def _at_bound(c, params: dict[str, float], held: dict[str, float]) -> list[str]:
    """The parameters a search left at a bound of their range (and moved from 'no effect'), but
    those the bounded fit holds there (``held``)."""
    bounds = {p.name: (p.lower, p.upper) for p in c.parameters}
    return [k for k, v in params.items()
            if k not in held
            and min(abs(v - bounds[k][0]), abs(v - bounds[k][1])) < 1e-6 * (bounds[k][1] - bounds[k][0])
            and v != c.defaults()[k]]


@dataclass(frozen=True)
class _Bounds:
    """How a candidate's free fit (without bounds, on all training flights) stands to its
    parameters' physical bounds: per parameter outside them, its free value, standard error,
    the bound and how many standard errors beyond it (``beyond``)."""

    outside: dict[str, tuple[float, float, float, float]]

    @property
    def beyond(self) -> float:
        return max((z for *_, z in self.outside.values()), default=0.0)

    @property
    def unphysical(self) -> bool:
        """Beyond a bound by clearly more than its noise: the data ask for values the effect
        cannot have (``BOUND_SIGMA`` standard errors)."""
        return self.beyond > BOUND_SIGMA


def _bounds(c, fit_c: fitting.Fit, free_spread: dict[str, float]) -> _Bounds:
    free = fit_c.free or fit_c
    values, std = free.params[c.name], free.std[c.name]
    out = {}
    for p in c.parameters:
        v = values[p.name]
        if p.lower <= v <= p.upper:
            continue
        bound = p.lower if v < p.lower else p.upper
        s = max(std.get(p.name, 0.0), free_spread.get(p.name, 0.0))
        out[p.name] = (v, s, bound, abs(v - bound) / s if s > 0 else np.inf)
    return _Bounds(out)


def _parameter_notes(bounds: _Bounds, active: dict[str, float], at_bound: list[str], sigma: float) -> list[str]:
    def free(k: str) -> str:
        v, s, bound, z = bounds.outside[k]
        return f"{k} = {v:.3g} ± {s:.2g}, {z:.2g} σ beyond its bound {bound:g}"

    if bounds.unphysical:
        notes = [f"fitted outside the physical bounds by more than {BOUND_SIGMA:g} standard errors ("
                 + "; ".join(free(k) for k in bounds.outside) + "): not a physical explanation"]
    elif active:
        beyond = [free(k) for k in active if k in bounds.outside]
        notes = [", ".join(f"{k} held at its bound {v:g}" for k, v in active.items())
                 + (f" (fitted free: {'; '.join(beyond)}, within noise of it)" if beyond else "")]
    else:
        notes = []
    notes += [f"{', '.join(at_bound)} at the bound of its range"] if at_bound else []
    if sigma < MIN_SIGMA:
        notes.append(f"not significant: the fit is only {sigma:.1f} standard errors from 'no effect'")
    return notes


def _score(c, held: _HeldOut, fit_c: fitting.Fit, fold_params: tuple[list[dict], list[dict]],
           test_sums: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    """A candidate's row: what its held-out prediction removes (raw, per channel and axis), the
    channel it explains, its parameters (``fit_c``: on all training flights, within the physical
    bounds) with their uncertainty (``fold_params``: per fold, for the spread, bounded and free)
    and checks, and the held-out test (``test_sums``: its
    :func:`quadcore.identify.evidence.held_out_sums`). A free fit beyond a bound by more than
    ``BOUND_SIGMA`` standard errors is unphysical; one within noise of it is judged as fitted
    with the bound active (``active_bounds``)."""
    before, at_noise = held.before, held.at_noise
    after = _total(_ss(held.resid[f] - held.cand_pred[c.name][f], fd) for f, fd in zip(held.ids, held.flights))
    raw = {ch: _ev(before, after, sl) for ch, sl in TARGET_CHANNELS.items()}
    ev_f, ev_t = (min(raw[ch], 0.0) if at_noise[ch] else raw[ch] for ch in ("force", "torque"))
    target = c.target if c.target != "both" else ("force" if ev_f >= ev_t else "torque")
    params = fit_c.params[c.name]
    spread = _jackknife_std(fold_params[0])
    # the larger of the sample-based error and the spread between groups of flights: flights
    # differ (battery, propellers, a stuck log variable) more than samples within a flight do
    std = {k: max(v, spread.get(k, 0.0)) for k, v in fit_c.std[c.name].items()}
    free_spread = _jackknife_std(fold_params[1])
    bounds = _bounds(c, fit_c, free_spread)
    active = fit_c.active.get(c.name, {})
    # a parameter held at its bound: how well the data pin it is its free fit's error and spread
    std.update({k: max(std[k], free_spread.get(k, 0.0)) for k in active})
    sigma = _significance(c, params, std)
    return {
        "effect": c.name,
        "target": target,
        "acts_on": c.target,
        "explained_variance": max(0.0, ev_f if target == "force" else ev_t),
        "explained_variance_force": ev_f,
        "explained_variance_torque": ev_t,
        "explained_variance_raw": raw,
        "score": 0.5 * (ev_f + ev_t),
        "force_rmse_N": [float(np.sqrt(after[j] / held.n)) for j in range(3)],
        "torque_rmse_Nm": [float(np.sqrt(after[3 + j] / held.n)) for j in range(3)],
        "parameters": params,
        "parameter_spread_between_flights": spread,
        "parameter_std": std,
        "n_parameters": len(c.parameters),
        "explained_variance_per_axis": {
            f"{q}_{a}": float(1 - after[i] / before[i]) if before[i] > 0 else 0.0
            for i, (q, a) in enumerate([("force", a) for a in XYZ] + [("torque", a) for a in XYZ])
        },
        "physical": not bounds.unphysical,
        "active_bounds": dict(active),
        "significance_sigma": sigma,
        "significant": sigma >= MIN_SIGMA,
        "notes": _parameter_notes(bounds, active, _at_bound(c, params, active), sigma),
        **_held_out_evidence(evidence.held_out_test_of(test_sums, evidence.channel_mask([target])),
                             before, after, held.noise_ss, target),
    }


def _mark_alike(rows: list[dict], span: _SpanOverlap, held: _HeldOut, p: _Problem) -> None:
    """Which candidates leave the same signature on the evaluated flights: per row, the physical
    ones that reproduce its prediction in its channel and it theirs (``indistinguishable_from``),
    those of them it ties with (scores within TIE_MARGIN, or the held-out flights prefer
    neither; a tie goes both ways), and what separates it from the others (``separated_by``)."""
    evidence_w = held.w * evidence.channel_mask([ch for ch, quiet in held.at_noise.items() if not quiet])

    def separated(a: str, b: str) -> bool:
        """The held-out flights prefer one of ``a`` and ``b`` significantly (channels above the noise)."""
        return (evidence.compare(held.flights, held.resid, held.cand_pred[a], held.cand_pred[b], evidence_w).p_value
                < evidence.ALPHA)
    by_name = {r["effect"]: r for r in rows}

    def can_mimic(a: str, b: str, ch: str) -> bool:
        """``b``, with physical parameter values, reproduces ``a``'s held-out prediction in ``ch``."""
        r2, beta = span.mimic(a, b, ch)
        if r2 < 1 - SAME_SIGNATURE:
            return False
        e = p.effect_of[b]
        if not e.linear:  # only its own fitted prediction is known to be physical
            return 0.5 <= float(beta[0]) <= 2.0
        params = e.from_linear(beta, p.vehicle)
        return all(q.lower <= params[q.name] <= q.upper for q in e.parameters)

    for r in rows:
        ch = r["target"]
        alike = []
        for o in rows:
            if o is r or not o["physical"] or _ev_on(o, ch) < MIN_EXPLAINED and _ev_on(r, ch) < MIN_EXPLAINED:
                continue
            if can_mimic(r["effect"], o["effect"], ch) and can_mimic(o["effect"], r["effect"], ch):
                alike.append(o["effect"])
        r["indistinguishable_from"] = alike
        r["tied_with"] = [o for o in alike
                          if abs(by_name[o]["score"] - r["score"]) < TIE_MARGIN or not separated(r["effect"], o)]
        # what separates alike candidates: the other channel when either acts there (for an
        # effect acting in both, through its joint fit), otherwise how well each fits this one
        r["separated_by"] = {o: _other(ch) if "both" in (r["acts_on"], by_name[o]["acts_on"]) else ch
                             for o in alike if o not in r["tied_with"]}
    for r in rows:  # a tie goes both ways
        for o in r["tied_with"]:
            if r["effect"] not in by_name[o]["tied_with"]:
                by_name[o]["tied_with"].append(r["effect"])
                by_name[o]["separated_by"].pop(r["effect"], None)


def _beyond_the_best(rows: list[dict], span: _SpanOverlap, held: _HeldOut, p: _Problem
                     ) -> dict[str, dict[str, float | None]]:
    """On the ranked rows: what each could still explain once the best one is in the model
    (``explained_after_top``), why each is ranked where it is, and how small an effect could
    hide in what is left then (``sensitivity``, also returned)."""
    for r in rows:
        r["explained_after_top"] = (r["explained_variance"] if r is rows[0] or held.at_noise[r["target"]]
                                    else span.left_after(r["effect"], rows[0]["effect"], r["target"]))
        # what it removes alone by the same screen (not its held-out share): the verdict compares the two
        r["explained_alone_screen"] = (r["explained_variance"] if r is rows[0] or held.at_noise[r["target"]]
                                       else span.left_after(r["effect"], None, r["target"]))
    rank_reasons(rows, held.at_noise)
    left = ({f: held.resid[f] - held.cand_pred[rows[0]["effect"]][f] for f in held.ids}
            if rows and rows[0]["found"] else held.resid)
    sensitivity = detection_limits(p.cands, held.flights, left, held.noise_ss, p.vehicle, len(p.cands))
    for r in rows:
        r["sensitivity"] = sensitivity[r["effect"]]
    return sensitivity


def _discover_placeholder(spec: ModelSpec) -> str:
    model_arg = f"--model {spec.source}" if spec.source else (
        f"--effects {','.join(spec.effects)}" if spec.effects else "--model MODEL.toml")
    return f"quadcore discover LOGS {model_arg} --json discovery.json"


def _outside_library(rows: list[dict], held: _HeldOut, command: str) -> dict[str, Any] | None:
    """Whether what the library finds is only a small part of what is left, per channel: the
    share of the held-out residual *above the sensor-noise floor* that the found candidates of
    that channel remove -- the best of them alone (held out), and in the best candidate's channel
    plus what the others also missing there remove on top of it (``explained_after_top``, as a
    share above the floor) -- is below ``LIBRARY_SHARE``. Then those candidates are ``partial``
    (not found: an effect may be real and still not be what is missing) and the verdict says that
    the rest is outside the library and how to search for it (``command``). Returns
    ``{"channels": [{channel, best, explained_above_noise, residual_to_noise_after,
    held_out_p_value}, ...], "command"}``; None when the library explains most of what is
    above the floor (or there is nothing above it), ``{"channels": [], "command"}`` when nothing
    is found in a channel above the floor."""
    found = [r for r in rows if r["found"]]
    if not found:
        return {"channels": [], "command": command} if not all(held.at_noise.values()) else None
    top, out = found[0], []
    for ch, sl in TARGET_CHANNELS.items():
        mine = [r for r in found if r["target"] == ch]
        before, floor = float(held.before[sl].sum()), float(held.noise_ss[sl].sum())
        if not mine or before <= floor:
            continue
        best = mine[0]
        share = best["explained_above_noise"] + (sum(r["explained_after_top"] * before / (before - floor)
                                                     for r in mine[1:] if r["status"] == "found")
                                                 if best is top else 0.0)
        if share >= LIBRARY_SHARE:
            continue
        for r in mine:
            r["found"] = r["useful"] = False
            r["status"] = "partial"
            r["reason"] = (f"the library's findings remove only {min(share, 1.0):.0%} of what lies above the noise "
                           f"floor of the held-out {ch} residual: most of it is outside the library; " + r["reason"])
        left = before * (1.0 - best["explained_variance"])
        out.append({"channel": ch, "best": best["effect"], "explained_above_noise": float(min(share, 1.0)),
                    "residual_to_noise_after": float(np.sqrt(max(left, 0.0) / floor)) if floor > 0 else None,
                    "held_out_p_value": best["held_out_p_value"]})
    return {"channels": out, "command": command} if out else None


def _session_disagreements(p: _Problem, rows: list[dict], sessions, log) -> list:
    """Parameters that differ between sessions: the model's effects, and the best candidate
    beside them (from the flights' statistics when they are linear, the best one perhaps
    profiled; otherwise fitted on each flight's rows)."""
    best = [p.effect_of[rows[0]["effect"]]] if rows and rows[0]["useful"] else []
    if all(e.linear for e in p.model_effects) and (not best or best[0].linear or p.from_profile(best[0])):
        return sessionlib.disagreements(p.model_effects + best, p.fds, p.targets, p.vehicle, p.spec.fixed, sessions,
                                        log)
    return sessionlib.disagreements(p.model_effects + best, {f: p.fl.rows(f) for f in p.ids},
                                    {f: p.fl.signal_rows(f, p.targets[f]) for f in p.ids}, p.vehicle, p.spec.fixed,
                                    sessions, log)


def _fold_answer(rows: list[dict], held: _HeldOut, flights: list[str]) -> str:
    """The answer of one fold (its test ``flights``): the physical candidate whose held-out
    prediction (fitted without them) removes the largest share of their residual, scored as the
    ranking scores (force and torque averaged, channels at the fleet's or the fold's noise floor
    clipped), :data:`NOTHING` when none removes ``MIN_EXPLAINED`` of its channel, or
    :data:`NO_EVIDENCE` when the fold's residual is at its own noise floor on every channel (a
    hover shows no drag: that is no vote against it)."""
    index = {f: i for i, f in enumerate(held.ids)}
    fds = [held.flights[index[f]] for f in flights]
    before = _total(_ss(held.resid[f], fd) for f, fd in zip(flights, fds))
    # The fold's own noise floor: a channel at it holds no evidence for an effect in these
    # flights (as the fleet's in the ranking); with every channel there, the fold abstains.
    at_noise = evidence.at_noise_level(before, _total(fd.noise ** 2 * fd.n for fd in fds))
    if all(at_noise.values()):
        return NO_EVIDENCE
    best, best_score, best_ev = NOTHING, 0.0, 0.0
    for r in rows:
        if not r["physical"]:
            continue
        pred = held.cand_pred[r["effect"]]
        after = _total(_ss(held.resid[f] - pred[f], fd) for f, fd in zip(flights, fds))
        ev = [min(x, 0.0) if held.at_noise[ch] or at_noise[ch] else x
              for ch, x in ((ch, _ev(before, after, sl)) for ch, sl in TARGET_CHANNELS.items())]
        if 0.5 * sum(ev) > best_score:
            best, best_score, best_ev = r["effect"], 0.5 * sum(ev), max(ev)
    return best if best_ev >= MIN_EXPLAINED else NOTHING


def _stability(rows: list[dict], splits: list[tuple[list[str], list[str]]], held: _HeldOut) -> Stability:
    """How many folds agree on the top answer (:class:`quadcore.identify.results.Stability`): the
    cross-validation's folds, or with one split each held-out flight. From the held-out
    predictions the scores already hold: no refit."""
    top = rows[0] if rows and rows[0]["found"] else None
    answer = top["effect"] if top else NOTHING
    group = (answer, *top["tied_with"]) if top else (NOTHING,)
    units, unit = (([test for _, test in splits], "fold") if len(splits) > 1
                   else ([[f] for f in held.ids], "held-out flight"))
    votes = Counter(_fold_answer(rows, held, flights) for flights in units)
    return Stability(answer, tuple(group), unit, dict(votes.most_common()), len(units))


def _assemble(p: _Problem, held: _HeldOut, model: PhysicsModel, evaluation: Evaluation, rows: list[dict],
              sensitivity: dict, disagree: list, outside: dict[str, Any] | None,
              stability: Stability) -> Diagnosis:
    """The typed diagnosis, with the evaluated flights' residual by regime, by flight, in time
    and in frequency (from their rows) and the verdict: how stable its answer is leads it when
    the answer flips between folds, and closes it otherwise, with the protocol."""
    described = _by_flight(p, held)
    text = verdict(rows, held.at_noise, sensitivity, outside)
    if disagree:
        text += " Parameters differ between groups of flights: " + "; ".join(d.summary() for d in disagree) + "."
    if stability.undecided_between:
        text = stability.sentence() + " " + text
    else:
        text += " " + stability.sentence()
    text += f" Evaluated by {evaluation.protocol}."
    before, noise_ss = held.before, held.noise_ss
    return Diagnosis(
        effects_in_model=tuple(p.spec.effects),
        model=model,
        evaluation=evaluation,
        baseline=_rmse(before, held.n),
        noise_floor=_rmse(noise_ss, held.n),
        at_noise_level=held.at_noise,
        residual_to_noise={ch: float(np.sqrt(before[sl].sum() / noise_ss[sl].sum())) if noise_ss[sl].sum() > 0
                           else None for ch, sl in TARGET_CHANNELS.items()},
        candidates=tuple(CandidateScore.from_dict(r) for r in rows),
        sensitivity=sensitivity,
        sensitivity_basis=sensitivity_basis(p.cands),
        verdict=text,
        stability=stability,
        disagreements=tuple(disagree),
        regimes=described.regimes,
        flights=described.flights,
        worst_segments=described.worst_segments,
        frequency=described.frequency,
        outside_library=outside if outside is not None and outside["channels"] else None,
    )


def _by_flight(p: _Problem, held: _HeldOut) -> summaries.Tables:
    """The evaluated flights' residual by regime, by flight, in time and in frequency: from their
    stored summaries where they have them (:func:`_from_summaries`), else from their long table
    (:func:`~quadcore.identify.regimes.long_table`) and spectra, one flight's rows at a time:
    each flight's rows go once its part of both is taken, so the tables after it do not sit
    beside every flight's rows."""
    p.forget_row_resid()
    for f in set(p.ids) - set(held.ids):  # the training flights' rows, read for nonlinear candidates
        p.fl.release(f)
    if p.fl.stats is not None and any(p.fl.stats[f].summary_source is not None for f in held.ids):
        return _from_summaries(p, held)
    sums = spectrum.SpectrumSums(float(np.median([p.fl.sample_rate_hz(f) for f in held.ids])), p.vehicle)
    frames = []
    for f in held.ids:
        fd, r = p.fl.rows(f), p.fl.signal_rows(f, held.resid[f])
        frames.append(long_frame(fd, r, p.vehicle))
        sums.add(fd, r)
        p.fl.release(f)
    long = pl.concat(frames)
    return summaries.Tables(regime_table(long), flight_table(long), worst_segments(long), sums.view())


def _from_summaries(p: _Problem, held: _HeldOut) -> summaries.Tables:
    """The same tables from the evaluated flights' summaries (:mod:`quadcore.identify.summaries`):
    the residual, a signal vector, summed as quadratic forms of each flight's summary; a flight
    without one (missing or stale) from its rows, one at a time."""
    def from_rows(f: str) -> summaries.ResidualSums:
        fd, r = p.fl.rows(f), p.fl.signal_rows(f, held.resid[f])
        out = summaries.of_rows(fd, r, p.vehicle).residual(np.ones(1))
        p.fl.release(f)
        return out

    sums = []
    for f in held.ids:
        summary, v = p.fl.statistics(f).summary(), held.resid[f]
        sums.append(summary.residual(v) if summary is not None and summary.describes(v) else from_rows(f))
    return summaries.tables(sums, from_rows, p.vehicle)


def diagnose(
    decoded: Mapping[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    candidates: list[str] | None = None,
    n_folds: int = 5,
    log=lambda msg: None,
    sessions: dict[str, list[str]] | None = None,
    stats=None,
    discover_command: str | None = None,
) -> Diagnosis:
    """Fit the model, score it on held-out flights, rank the missing effects, and find the
    parameters that differ between groups of flights (``sessions``: name -> flights, from a
    sessions file; None: groups found from the data). Its ``to_dict()`` is the JSON document.

    With a model of linear effects, fits, folds and held-out tests combine the flights'
    sufficient statistics (``stats(flight)``: stored ones, None to compute them from the
    decoded table), one-parameter nonlinear candidates from the flights' profiles
    (:mod:`quadcore.identify.profiles`; a candidate with several nonlinear parameters reads its
    training flights' rows), and the evaluated flights' stored summaries
    (:mod:`quadcore.identify.summaries`) give the regime tables and spectra (their rows where a
    flight has no current summary, and for every flight of a model with a nonlinear effect).
    ``discover_command``: the ``quadcore discover`` command the verdict points to when what is
    left is outside the library (None: one with placeholders for the logs and the model file)."""
    p = _Problem(decoded, spec, candidates, stats)
    splits, train_all, mode = _splits(p.ids, holdout, n_folds)
    folds = _cross_fit(p, splits, sessions, log)
    # With a single split on all training flights (holdout), its fits are the final ones.
    reuse = len(splits) == 1 and splits[0][0] == train_all
    model, resid_train = _training_model(p, folds.model_fit if reuse else None, train_all, sessions, log)
    fold_params, free_params = (_group_spread(p, train_all, resid_train, n_folds) if reuse and len(train_all) >= 3
                                else (folds.params, folds.free_params))

    held = _held_out(p, folds)
    rows: list[dict[str, Any]] = []
    # every candidate's held-out sums at once (on statistics: one read of the Gram matrices)
    tests = evidence.held_out_sums(held.flights, held.resid, [held.cand_pred[c.name] for c in p.cands])
    for c, test_sums in zip(p.cands, tests):
        fit_c = folds.fits[c.name] if reuse else p.fit_candidate(c, train_all, resid_train)
        rows.append(_score(c, held, fit_c, (fold_params[c.name], free_params[c.name]), test_sums))
    for r in rows:
        _decide(r, held.at_noise, len(rows))
    span = _SpanOverlap(p.cands, held.cand_pred, held.flights, held.resid, held.w, p.vehicle)
    _mark_alike(rows, span, held, p)
    rows = _rank(rows)
    sensitivity = _beyond_the_best(rows, span, held, p)
    outside = _outside_library(rows, held, discover_command or _discover_placeholder(spec))
    disagree = _session_disagreements(p, rows, sessions, log)
    evaluation = Evaluation(mode, len(splits), tuple(train_all), tuple(held.ids), held.n)
    return _assemble(p, held, model, evaluation, rows, sensitivity, disagree, outside,
                     _stability(rows, splits, held))


def _rmse(ss: np.ndarray, n: int) -> ResidualRmse:
    """Per-axis RMS from the sums of squares (6,) over ``n`` samples."""
    return ResidualRmse(tuple(float(np.sqrt(ss[j] / n)) for j in range(3)),
                        tuple(float(np.sqrt(ss[3 + j] / n)) for j in range(3)))


# ---------------------------------------------------------------------------------------
# Evidence: the held-out test, the noise floor, the grade, and why each is ranked where it is
# ---------------------------------------------------------------------------------------

def _held_out_evidence(test: evidence.HeldOutTest, before: np.ndarray, after: np.ndarray,
                       noise_ss: np.ndarray, target: str) -> dict:
    """The held-out test of a candidate in its target channel, the share of the residual
    *above the noise floor* it removes, and the size of what it removes in noise floors (RMS)."""
    sl = TARGET_CHANNELS[target]
    floor = noise_ss[sl].sum()
    removed, excess = before[sl].sum() - after[sl].sum(), before[sl].sum() - floor
    return {
        "held_out_slope": test.beta,
        "held_out_t": test.t,
        "held_out_p_value": test.p_value,
        "held_out_blocks": test.blocks,
        "explained_above_noise": float(np.clip(removed / excess, 0.0, 1.0)) if excess > 0 else 0.0,
        "signal_to_noise": float(np.sqrt(max(removed, 0.0) / floor)) if floor > 0 else 0.0,
    }


def _decide(r: dict, at_noise: dict[str, bool], n_candidates: int) -> None:
    """``found`` (alias ``useful``): physical, its parameters significant, confirmed on the
    held-out flights (:func:`quadcore.identify.evidence.held_out_test`), removing some of a target
    residual that stands above the noise floor. ``grade`` says how large it is."""
    r["held_out_alpha"] = evidence.alpha_each(n_candidates)
    confirmed = r["held_out_p_value"] < r["held_out_alpha"] and r["held_out_slope"] > 0
    r["found"] = bool(r["physical"] and r["significant"] and confirmed and r["explained_variance"] > 0
                      and not at_noise[r["target"]])
    r["useful"] = r["found"]
    if not r["physical"]:
        r["grade"] = "unphysical"
    elif not r["found"]:
        r["grade"] = "indistinguishable from noise"
    elif r["signal_to_noise"] >= LARGE_SNR:
        r["grade"] = "large"
    elif r["signal_to_noise"] >= 1.0:
        r["grade"] = "clear"
    else:
        r["grade"] = "small but certain"


def detection_limits(cands, flights: sufficient.Flights, resid: dict[str, np.ndarray], noise_ss: np.ndarray,
                     vehicle, n_candidates: int) -> dict[str, dict[str, float | None]]:
    """Per candidate and parameter: the smallest |deviation from 'no effect'| these flights
    would detect (:func:`quadcore.identify.evidence.detection_limits`); None when no value within the
    parameter's range would be. A parameter stated at a reference point of the others (a
    wind, at a rotor drag) must also lift the score by ``2 TIE_MARGIN`` above the simpler
    effect it then resembles (a wind above rotor drag), or the two are a tie."""
    jobs = [(c, p) for c in cands for p in c.parameters]
    base_ss = {c.name: sum(_reference_ss(c, fd, vehicle) for fd in flights) for c in cands if c.sensitivity_reference}
    # statistics: every parameter's sums from one read of the Gram matrices; rows: one unit
    # wrench (a signal per flight) in memory at a time
    batch = max(len(jobs), 1) if sufficient.are_stats(flights) else 1
    out: dict[str, dict[str, float | None]] = {c.name: {} for c in cands}
    for start in range(0, len(jobs), batch):
        part = jobs[start: start + batch]
        asks = [_limit_ask(c, p, flights, vehicle, base_ss.get(c.name, 0.0)) for c, p in part]
        limits = evidence.detection_limits(flights, resid, asks, noise_ss, MIN_SIGMA, n_candidates)
        for (c, p), v in zip(part, limits):
            if not c.linear:  # the unit wrench is a secant: nothing is known below its step
                v = max(v, evidence.SECANT * (p.upper - p.lower))
            out[c.name][p.name] = float(v) if v <= max(p.upper - p.default, p.default - p.lower) else None
    return out


def _limit_ask(c, p, flights: sufficient.Flights, vehicle, base_ss: float) -> evidence.LimitAsk:
    """A parameter's detection limit to find: stated at a reference point of the others (a wind,
    at a rotor drag), it must also lift the score by ``2 TIE_MARGIN`` above the effect it then
    resembles."""
    unit = {fd.flight: _unit(c, p, fd, vehicle) for fd in flights}
    if c.sensitivity_reference and p.name not in c.sensitivity_reference:
        return evidence.LimitAsk(unit, 2 * TIE_MARGIN, base_ss)
    return evidence.LimitAsk(unit)


def sensitivity_basis(cands) -> dict:
    """What the sensitivity values mean (for the JSON and the reports)."""
    return {
        "meaning": "smallest |parameter - its 'no effect' value| these flights would detect, each parameter alone",
        "detection_probability": evidence.POWER,
        "false_alarm_probability": evidence.ALPHA,
        "noise_margin": evidence.NOISE_MARGIN,
        "conditions": {c.name: dict(c.sensitivity_reference) for c in cands if c.sensitivity_reference},
    }


def _significance(effect, params: dict, std: dict) -> float:
    """How many standard errors the fitted effect is from 'no effect': the largest
    ``|p - default| / std`` over its parameters (inf when a parameter has zero std but moved)."""
    best = 0.0
    for p in effect.parameters:
        d = abs(params[p.name] - p.default)
        s = std.get(p.name, float("nan"))
        if d == 0 or not np.isfinite(d):
            continue
        z = d / s if s > 0 and np.isfinite(s) else (np.inf if s == 0 else 0.0)
        best = max(best, float(z))
    return min(best, 1e6)  # finite, for JSON


class _SpanOverlap:
    """Signatures compared on the evaluated flights, accumulated flight by flight as Gram
    matrices of ``[residual | held-out predictions | bases]`` per channel (no big arrays).

    * :meth:`mimic`: how well one candidate's held-out prediction can be reproduced by another
      candidate with *any* parameter values: the share of the prediction's energy in the span
      of the other's basis (linear effects) or along its prediction (nonlinear ones).
      Independent of how large either fit is, so a fit that the other channel pulled to zero
      still shows its shape.
    * :meth:`left_after`: the share of the baseline residual a candidate can still remove
      once another one's held-out prediction is subtracted (least squares on its basis over
      the evaluated flights: in-sample, so it is a screening number; a few parameters on
      thousands of samples barely overfit).
    """

    def __init__(self, cands, cand_pred, flights, resid, w, vehicle):
        self.names = [c.name for c in cands]
        self.cols: dict[str, list[int]] = {}
        k = 1 + len(cands)
        for c in cands:
            n_basis = len(c.parameters) if c.linear else 1
            self.cols[c.name] = list(range(k, k + n_basis))
            k += n_basis
        sw = np.sqrt(w)
        self.gram = {"force": np.zeros((k, k)), "torque": np.zeros((k, k))}
        for fd in flights:
            if not isinstance(fd, FlightData):  # statistics: the same Gram from the strided one
                self._add_stats(fd, cands, cand_pred, resid, w, vehicle)
                continue
            # every GRAM_STRIDE-th usable sample: the signals are smoothed over a 31-sample
            # window, so the thinned sums give the same energy ratios at a fraction of the cost
            m = np.flatnonzero(fd.mask)[::sufficient.GRAM_STRIDE]
            blocks = [resid[fd.flight][m][:, :, None]] + [cand_pred[c.name][fd.flight][m][:, :, None] for c in cands]
            for c in cands:
                blocks.append(fd.basis(c, vehicle)[m] if c.linear else cand_pred[c.name][fd.flight][m][:, :, None])
            Z = np.concatenate(blocks, axis=2) * sw[None, :, None]  # (m, 6, k)
            for ch, sl in TARGET_CHANNELS.items():
                self.gram[ch] += np.einsum("nci,ncj->ij", Z[:, sl, :], Z[:, sl, :])

    def _add_stats(self, s, cands, cand_pred, resid, w, vehicle) -> None:
        """One flight's part from its statistics: the columns above as signal vectors ``T``,
        ``Tᵀ (Σ_c w_c G_c) T`` per channel group, ``G`` the strided Gram matrix."""
        cols = [resid[s.flight]] + [cand_pred[c.name][s.flight] for c in cands]
        for c in cands:
            cols += ([s.layout.unit(i) for i in s.layout.cols(c.name)] if c.linear
                     else [cand_pred[c.name][s.flight]])
        T = np.stack(cols, axis=1)
        for ch, sl in TARGET_CHANNELS.items():
            self.gram[ch] += T.T @ np.tensordot(w[sl], s.strided[sl], axes=1) @ T

    def _G(self, channel: str | None) -> np.ndarray:
        return self.gram[channel] if channel else self.gram["force"] + self.gram["torque"]

    def _fit(self, G: np.ndarray, y: np.ndarray, b: str) -> tuple[float, np.ndarray]:
        """Least-squares fit of the combination ``y`` of columns on ``b``'s basis: the
        energy it reproduces and the coefficients."""
        cols = self.cols[b]
        A, c = G[np.ix_(cols, cols)], G[cols] @ y
        beta = np.linalg.lstsq(A, c, rcond=1e-10)[0]
        return float(c @ beta), beta

    def _gain(self, G: np.ndarray, y: np.ndarray, b: str) -> float:
        return self._fit(G, y, b)[0]

    def mimic(self, a: str, b: str, channel: str | None) -> tuple[float, np.ndarray]:
        """Share of ``a``'s prediction (in ``channel``, or both channels when None) that
        ``b`` can reproduce, and the coefficients of ``b`` that do it (its linear
        coordinates for a linear effect; a factor on its own prediction otherwise)."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[1 + self.names.index(a)] = 1.0
        yy = float(y @ G @ y)
        if yy <= 0:
            return 0.0, np.zeros(len(self.cols[b]))
        gain, beta = self._fit(G, y, b)
        return float(np.clip(gain / yy, 0.0, 1.0)), beta

    def left_after(self, b: str, top: str | None, channel: str) -> float:
        """Share of the baseline ``channel`` residual that ``b`` removes from what ``top``
        leaves (from the whole residual: ``top`` None; the same screen, to compare with)."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[0] = 1.0
        if top is not None:
            y[1 + self.names.index(top)] = -1.0
        base = G[0, 0]
        return float(np.clip(self._gain(G, y, b) / base, 0.0, 1.0)) if base > 0 else 0.0


def _tier(r: dict) -> int:
    """0: found (physical, significant, confirmed on held-out flights); 1: physical but not
    found; 2: unphysical (never an explanation, whatever it removes)."""
    return 0 if r["found"] else (1 if r["physical"] else 2)


def _rank(rows: list[dict]) -> list[dict]:
    """Best first: by tier, then by score (force and torque explained, averaged); among
    candidates the data cannot tell apart (``tied_with``) the one with fewer parameters
    comes first (parsimony), then the higher score."""
    pending = sorted(rows, key=lambda r: (_tier(r), -r["score"]))
    ordered = []
    while pending:
        head = pending[0]
        group = [r for r in pending if r is head or (r["effect"] in head["tied_with"] and _tier(r) == _tier(head))]
        best = min(group, key=lambda r: (r["n_parameters"], -r["score"]))
        ordered.append(best)
        pending.remove(best)
    return ordered


