"""The diagnosis from end to end (:func:`diagnose`): the folds, the scores, the ranking, the
session disagreements, how stable the answer is, and the typed :class:`~quadcore.identify.diagnosis.results.Diagnosis`
with the evaluated flights' residual by regime, by flight, in time and in frequency."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import polars as pl

from quadcore.identify import evidence, rates
from quadcore.identify.describe import summaries
from quadcore.identify.diagnosis.problem import (
    TARGET_CHANNELS,
    HeldOut,
    _cross_fit,
    _group_spread,
    _held_out,
    _Problem,
    _total,
    _training_model,
    fold_splits,
)
from quadcore.identify.diagnosis.results import (
    NO_EVIDENCE,
    NOTHING,
    Diagnosis,
    Evaluation,
    ResidualRmse,
    Stability,
)
from quadcore.identify.diagnosis.rows import CandidateRow
from quadcore.identify.diagnosis.scoring import _beyond_the_best, _decide, _ev, _mark_alike, _rank, _score
from quadcore.identify.diagnosis.sensitivity import sensitivity_basis
from quadcore.identify.diagnosis.span import _SpanOverlap
from quadcore.identify.diagnosis.verdict import verdict
from quadcore.identify.fit import sessions as sessionlib
from quadcore.identify.fit.sessions import Disagreement
from quadcore.identify.model import PhysicsModel
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.identify.stats import sufficient
from quadcore.spec.model import ModelSpec

Log = Callable[[str], None]  # progress, one line at a time
Sessions = dict[str, list[str]] | None  # name -> flights (a sessions file), None: groups found from the data
StoredStats = Callable[[str], sufficient.FlightStats | None] | None  # a flight's stored statistics, if current


def diagnose(
    decoded: Mapping[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    candidates: list[str] | None = None,
    settings: DiagnosisSettings = DEFAULT,
    log: Log = lambda msg: None,
    sessions: Sessions = None,
    stats: StoredStats = None,
    discover_command: str | None = None,
    rate_cache: rates.RatesCache | None = None,
) -> Diagnosis:
    """Fit the model, score it on held-out flights, rank the missing effects, and find the
    parameters that differ between groups of flights (``sessions``: name -> flights, from a
    sessions file; None: groups found from the data). Its ``to_dict()`` is the JSON document.

    With a model of linear effects, fits, folds and held-out tests combine the flights'
    sufficient statistics (``stats(flight)``: stored ones, None to compute them from the
    decoded table), one-parameter nonlinear candidates from the flights' profiles
    (:mod:`quadcore.identify.stats.profiles`; a candidate with several nonlinear parameters reads its
    training flights' rows), and the evaluated flights' stored summaries
    (:mod:`quadcore.identify.describe.summaries`) give the regime tables and spectra (their rows where a
    flight has no current summary, and for every flight of a model with a nonlinear effect).
    ``discover_command``: the ``quadcore discover`` command the verdict points to when what is
    left is outside the library (None: one with placeholders for the logs and the model file).
    ``settings``: the thresholds and folds it decides by (:class:`~quadcore.identify.settings.DiagnosisSettings`),
    recorded in the result. ``rate_cache``: the timing candidates' rate-level sums kept from an
    earlier diagnosis (:func:`quadcore.identify.diagnosis.rate_cache.stored`), so that only the
    flights whose sums are missing or stale are read."""
    p = _Problem(decoded, spec, candidates, stats, noise_margin=settings.noise_margin)
    splits, train_all, mode = fold_splits(p.ids, holdout, settings.n_folds)
    folds = _cross_fit(p, splits, sessions, log)
    # With a single split on all training flights (holdout), its fits are the final ones.
    reuse = len(splits) == 1 and splits[0][0] == train_all
    model, resid_train = _training_model(p, folds.model_fit if reuse else None, train_all, sessions, log)
    fold_params, free_params = (_group_spread(p, train_all, resid_train, settings.n_folds)
                                if reuse and len(train_all) >= 3 else (folds.params, folds.free_params))

    held = _held_out(p, folds, settings)
    rows: list[CandidateRow] = []
    # every candidate's held-out sums at once (on statistics: one read of the Gram matrices)
    tests = evidence.held_out_sums(held.flights, held.resid, [held.cand_pred[c.name] for c in p.cands])
    for c, test_sums in zip(p.cands, tests):
        fit_c = folds.fits[c.name] if reuse else p.fit_candidate(c, train_all, resid_train)
        rows.append(_score(c, held, fit_c, (fold_params[c.name], free_params[c.name]), test_sums,
                           settings))
    for r in rows:
        _decide(r, held.at_noise, len(rows), settings)
    span = _SpanOverlap(p.cands, held.cand_pred, held.flights, held.resid, held.w, p.vehicle)
    _mark_alike(rows, span, held, p, settings)
    # a lag, a delay: fitted and compared at the angular-rate level, which the closed loop biases less
    rows, timing = rates.judge(_rank(rows), p.cands, p.fl.rows, p.fl.release, model, splits, train_all, settings,
                               lambda r: _decide(r, held.at_noise, len(rows), settings), rate_cache)
    for f in p.ids:
        p.fl.release(f)
    sensitivity = _beyond_the_best(rows, span, held, p, settings)
    outside = _outside_library(rows, held, discover_command or _discover_placeholder(spec), settings.library_share)
    disagree = _session_disagreements(p, rows, sessions, log)
    evaluation = Evaluation(mode, len(splits), tuple(train_all), tuple(held.ids), held.n)
    return _assemble(p, held, model, evaluation, rows, sensitivity, disagree, outside,
                     _stability(rows, splits, held, timing, settings), settings)


def _assemble(p: _Problem, held: HeldOut, model: PhysicsModel, evaluation: Evaluation, rows: list[CandidateRow],
              sensitivity: dict, disagree: list, outside: dict[str, Any] | None,
              stability: Stability, settings: DiagnosisSettings) -> Diagnosis:
    """The typed diagnosis, with the evaluated flights' residual by regime, by flight, in time
    and in frequency (from their rows) and the verdict: how stable its answer is leads it when
    the answer flips between folds, and closes it otherwise, with the protocol."""
    described = _by_flight(p, held)
    text = verdict(rows, held.at_noise, sensitivity, outside, settings)
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
        candidates=tuple(r.result() for r in rows),
        sensitivity=sensitivity,
        sensitivity_basis=sensitivity_basis(p.cands, settings),
        verdict=text,
        stability=stability,
        disagreements=tuple(disagree),
        regimes=described.regimes,
        flights=described.flights,
        worst_segments=described.worst_segments,
        frequency=described.frequency,
        outside_library=outside if outside is not None and outside["channels"] else None,
        settings=settings,
    )


def _rmse(ss: np.ndarray, n: int) -> ResidualRmse:
    """Per-axis RMS from the sums of squares (6,) over ``n`` samples."""
    return ResidualRmse(tuple(float(np.sqrt(ss[j] / n)) for j in range(3)),
                        tuple(float(np.sqrt(ss[3 + j] / n)) for j in range(3)))


def _by_flight(p: _Problem, held: HeldOut) -> summaries.Tables:
    """The evaluated flights' residual by regime, by flight, in time and in frequency, from their
    summaries (:mod:`quadcore.identify.describe.summaries`): the residual, a signal vector, summed as
    quadratic forms of each flight's stored summary; a flight whose summary cannot describe it
    (missing or stale, or a residual with an extra column: a model's profiled prediction, or a
    residual on rows) from the summary of its residual's rows (:func:`quadcore.identify.describe.summaries.of_rows`,
    the one place rows become summaries), one flight at a time: each flight's rows go once its
    sums are taken."""
    for f in set(p.ids) - set(held.ids):  # the training flights' rows, read for nonlinear candidates
        p.fl.release(f)

    layouts = {f: fd.layout for f, fd in zip(held.ids, held.flights)}  # the residuals' own

    def from_rows(f: str) -> summaries.ResidualSums:
        fd, r = p.fl.rows(f), p.fl.signal_rows(f, held.resid[f], layouts[f], held.model_values.get(f),
                                               held.extras.get(f))
        out = summaries.of_rows(fd, r, p.vehicle).residual(np.ones(1))
        p.fl.release(f)
        return out

    sums = []
    for f in held.ids:
        summary, v = p.fl.summary(f), held.resid[f]
        sums.append(summary.residual(v) if summary is not None and summary.describes(v) else from_rows(f))
    return summaries.tables(sums, from_rows, p.vehicle)


def _session_disagreements(p: _Problem, rows: list[CandidateRow], sessions: Sessions, log: Log
                           ) -> list[Disagreement]:
    """Parameters that differ between sessions: the model's effects, and the best candidate
    beside them, fitted per flight and per group from the flights' statistics (a nonlinear effect
    from its profiles, or by the search on the flights' rows)."""
    best = [p.effect_of[rows[0].effect]] if rows and rows[0].found else []
    return sessionlib.disagreements(p.model_effects + best, p.fds, p.targets, p.vehicle, p.spec.fixed, sessions,
                                    log, p.fit_effects)


def _discover_placeholder(spec: ModelSpec) -> str:
    model_arg = f"--model {spec.source}" if spec.source else (
        f"--effects {','.join(spec.effects)}" if spec.effects else "--model MODEL.toml")
    return f"quadcore discover LOGS {model_arg} --json discovery.json"


def _outside_library(rows: list[CandidateRow], held: HeldOut, command: str, library_share: float
                     ) -> dict[str, Any] | None:
    """Whether what the library finds is only a small part of what is left, per channel: the
    share of the held-out residual *above the sensor-noise floor* that the found candidates of
    that channel remove -- the best of them alone (held out), and in the best candidate's channel
    plus what the others also missing there remove on top of it (``explained_after_top``, as a
    share above the floor) -- is below ``library_share``. Then those candidates are ``partial``
    (not found: an effect may be real and still not be what is missing) and the verdict says that
    the rest is outside the library and how to search for it (``command``). Returns
    ``{"channels": [{channel, best, explained_above_noise, residual_to_noise_after,
    held_out_p_value}, ...], "command"}``; None when the library explains most of what is
    above the floor (or there is nothing above it), ``{"channels": [], "command"}`` when nothing
    is found in a channel above the floor. A channel above its floor (not at the noise level)
    where nothing is found while something is found in the other gets an entry too, after the
    others, with ``best``/``held_out_p_value`` None, ``explained_above_noise`` 0 and the
    residual's RMS over the floor's (:func:`_nothing_confirmed`)."""
    found = [r for r in rows if r.found]
    if not found:
        return {"channels": [], "command": command} if not all(held.at_noise.values()) else None
    top, out = found[0], []
    bare = _nothing_confirmed(found, held)
    for ch, sl in TARGET_CHANNELS.items():
        mine = [r for r in found if r.target == ch and r.rate_level is None]  # not one found at the rate level
        before, floor = float(held.before[sl].sum()), float(held.noise_ss[sl].sum())
        if not mine or before <= floor:
            continue
        best = mine[0]
        share = best.explained_above_noise + (sum(r.explained_after_top * before / (before - floor)
                                                  for r in mine[1:] if r.status == "found")
                                              if best is top else 0.0)
        if share >= library_share:
            continue
        for r in mine:
            r.found = False
            r.status = "partial"
            r.reason = (f"the library's findings remove only {min(share, 1.0):.0%} of what lies above the noise "
                        f"floor of the held-out {ch} residual: most of it is outside the library; " + r.reason)
        left = before * (1.0 - best.explained_variance)
        out.append({"channel": ch, "best": best.effect, "explained_above_noise": float(min(share, 1.0)),
                    "residual_to_noise_after": float(np.sqrt(max(left, 0.0) / floor)) if floor > 0 else None,
                    "held_out_p_value": best.held_out_p_value})
    out += bare
    return {"channels": out, "command": command} if out else None


def _nothing_confirmed(found: list[CandidateRow], held: HeldOut) -> list[dict[str, Any]]:
    """The channels above their sensor-noise floor (not ``held.at_noise``) in which no candidate
    is ``found`` (at either level), while one is found in another channel: what is left there,
    ``residual_to_noise_after`` = sqrt(SS_residual / SS_floor) of the held-out residual, is
    outside the library or below what these flights detect (an entry of
    :func:`_outside_library` with no best candidate)."""
    out: list[dict[str, Any]] = []
    for ch, sl in TARGET_CHANNELS.items():
        before, floor = float(held.before[sl].sum()), float(held.noise_ss[sl].sum())
        if held.at_noise[ch] or floor <= 0 or before <= floor or any(r.target == ch for r in found):
            continue
        out.append({"channel": ch, "best": None, "explained_above_noise": 0.0,
                    "residual_to_noise_after": float(np.sqrt(before / floor)), "held_out_p_value": None})
    return out


def _fold_answer(rows: list[CandidateRow], held: HeldOut, flights: list[str], settings: DiagnosisSettings) -> str:
    """The answer of one fold (its test ``flights``): the physical candidate whose held-out
    prediction (fitted without them) removes the largest share of their residual, scored as the
    ranking scores (force and torque averaged, channels at the fleet's or the fold's noise floor
    clipped), :data:`NOTHING` when none removes ``min_explained`` of its channel, or
    :data:`NO_EVIDENCE` when the fold's residual is at its own noise floor on every channel (a
    hover shows no drag: that is no vote against it)."""
    index = {f: i for i, f in enumerate(held.ids)}
    fds = [held.flights[index[f]] for f in flights]
    before = _total(fd.sum_of_squares(held.resid[f]) for f, fd in zip(flights, fds))
    # The fold's own noise floor: a channel at it holds no evidence for an effect in these
    # flights (as the fleet's in the ranking); with every channel there, the fold abstains.
    at_noise = evidence.at_noise_level(before, _total(fd.noise ** 2 * fd.n for fd in fds), settings.noise_margin)
    if all(at_noise.values()):
        return NO_EVIDENCE
    best, best_score, best_ev = NOTHING, 0.0, 0.0
    for r in rows:
        if not r.physical or r.rate_level is not None:  # a timing candidate answers at the rate level (_stability)
            continue
        pred = held.cand_pred[r.effect]
        after = _total(fd.sum_of_squares(held.resid[f] - pred[f]) for f, fd in zip(flights, fds))
        ev = [min(x, 0.0) if held.at_noise[ch] or at_noise[ch] else x
              for ch, x in ((ch, _ev(before, after, sl)) for ch, sl in TARGET_CHANNELS.items())]
        if 0.5 * sum(ev) > best_score:
            best, best_score, best_ev = r.effect, 0.5 * sum(ev), max(ev)
    return best if best_ev >= settings.min_explained else NOTHING


def _stability(rows: list[CandidateRow], splits: list[tuple[list[str], list[str]]], held: HeldOut,
               timing: rates.Judged, settings: DiagnosisSettings) -> Stability:
    """How many folds agree on the top answer (:class:`quadcore.identify.diagnosis.results.Stability`): the
    cross-validation's folds, or with one split each held-out flight. From the held-out
    predictions the scores already hold: no refit; between timing candidates, as the rate level
    prefers on those flights (``timing``). A timing candidate decided at the rate level answers a
    fold only there (its torque-level score, which the closed loop biases, is left out of
    :func:`_fold_answer`): where no other candidate explains the fold's flights, the found one whose
    held-out fits predict their angular rates better than no timing effect
    (:meth:`quadcore.identify.rates.Judged.found_on`)."""
    top = rows[0] if rows and rows[0].found else None
    answer = top.effect if top else NOTHING
    group = (answer, *top.tied_with) if top else (NOTHING,)
    units, unit = (([test for _, test in splits], "fold") if len(splits) > 1
                   else ([[f] for f in held.ids], "held-out flight"))

    def vote(flights: list[str]) -> str:  # where no other candidate explains them, a timing one found at the rate level
        fold = _fold_answer(rows, held, flights, settings)
        return timing.answer(timing.found_on(flights) or fold if fold in (NOTHING, NO_EVIDENCE) else fold, flights)

    votes = Counter(vote(flights) for flights in units)
    return Stability(answer, tuple(group), unit, dict(votes.most_common()), len(units))
