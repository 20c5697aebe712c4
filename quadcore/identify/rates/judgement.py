"""The rate level in the diagnosis: the timing candidates' rows fitted, compared and ranked.

:func:`judge` takes every flight's :data:`~quadcore.identify.rates.sums.FlightRates` (kept or
made), fits each timing candidate's one parameter (:func:`quadcore.identify.rates.sums.fit`:
``θ̂ = argmin J_rate(θ)`` over the training flights, body-frame torques integrated to N m s) and
compares every pair at fits on all the training flights, every flight's blocks scored
(:func:`quadcore.identify.rates.compare.timing_comparison`), and decides whether each is found
there (:class:`RateEvidence`: held out against no timing effect): a significant difference
ranks the better one above the other, a pair the noise model decides, or one not significant
where either is found, is tied (:data:`TIE`, :class:`Judged`). Used by
:func:`quadcore.identify.diagnosis.diagnose` for the candidates that re-time the rotors'
commanded thrust (:attr:`quadcore.effects.Effect.retimes_thrust`): their parameters, whether they
are found and how they rank against each other come from here (docs/diagnosis.md).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from quadcore.effects import Effect
from quadcore.identify import evidence
from quadcore.identify.fit import solve
from quadcore.identify.flightdata import FlightData
from quadcore.identify.rates.compare import PairComparison, effect_comparison, held_out_cost, timing_comparison
from quadcore.identify.rates.sums import (
    BelowCommandRate,
    FlightRates,
    RateFit,
    RatesCache,
    RateSums,
    fit,
    flight_inputs,
    flight_rates,
    split_weights,
    weights,
)

if TYPE_CHECKING:  # the diagnosis imports this module: its types only for the annotations
    from quadcore.identify.diagnosis.rows import CandidateRow
    from quadcore.identify.settings import DiagnosisSettings

# what separates two timing candidates (a row's ``separated_by``), and the level a timing row's held-out
# test and signal_to_noise are measured at (its ``held_out_level``; otherwise its target channel)
RATE_LEVEL = "angular rate"
NOT_SIGNIFICANT = "not significant:"  # how a row's note on its significance begins (quadcore.identify.diagnosis)

TIE = " = "  # joins the timing candidates a fold's answer names when the rate level prefers none of them


@dataclass(frozen=True)
class Judged:
    """What :func:`judge` measured: per pair ``(a, b)`` of timing candidates, each compared flight's
    per-block :func:`block_differences` (> 0: ``a`` fits better; :func:`timing_comparison`'s
    flights and fits); ``undecided``: the pairs whose
    answer the gyro noise model (:func:`noise_model_decides`) or the closed loop
    (:func:`closed_loop_decides`) decides, which prefer neither."""

    differences: dict[tuple[str, str], dict[str, np.ndarray]]
    undecided: frozenset[tuple[str, str]] = frozenset()
    # per timing candidate found at the rate level, each held-out flight's blocks' gain over no timing
    # effect (RateEvidence.gains): what a fold whose flights no other candidate explains answers by
    gains: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)

    def found_on(self, flights: Sequence[str]) -> str | None:
        """A timing candidate found at the rate level whose held-out fits predict the angular rates of
        ``flights`` better than no timing effect (its :attr:`gains` summed over them > 0), the first
        by name (:meth:`answer` then takes it to the one the pairs prefer on ``flights``); None: none."""
        better = sorted(n for n, per in self.gains.items() if sum(float(per[f].sum()) for f in flights if f in per) > 0)
        return better[0] if better else None

    def answer(self, effect: str, flights: Sequence[str]) -> str:
        """A fold's answer ``effect`` (the torque level's), as the rate level has it on ``flights``
        when ``effect`` is one of the timing candidates it compared: from every pair's difference
        summed over ``flights``, the candidate no other fits better; several (an exact tie: fits
        that predict alike) or, in a cycle, none: every candidate none fits better, or all of them,
        joined by :data:`TIE` (a tie stated as one); a pair in :attr:`undecided` beats neither.
        Symmetric: the same whatever the order of the pairs and of each pair's sides. ``effect``
        itself when it is no timing candidate or no pair was measured on ``flights``."""
        names = {n for pair in self.differences for n in pair}
        measured = [(a, b, per_flight) for (a, b), per_flight in self.differences.items()
                    if any(f in per_flight for f in flights)]
        if effect not in names or not measured:
            return effect
        beaten: set[str] = set()
        for a, b, per_flight in measured:
            if (a, b) in self.undecided:
                continue
            total = sum(float(per_flight[f].sum()) for f in flights if f in per_flight)
            beaten |= {b} if total > 0 else {a} if total < 0 else set()
        return TIE.join(sorted(names - beaten) or sorted(names))


@dataclass(frozen=True)
class RateEvidence:
    """What decides whether a timing candidate is found, at the rate level (:func:`_rate_evidence`):
    its fit against no timing effect on held-out flights (:func:`effect_comparison`), ``test``
    one-sided (``p`` of ``t`` or more, ``t > 0``: the fit predicts the held-out angular rates
    better than no timing effect); ``explained`` the share of the held-out rate-level residual with
    no timing effect (``Σ J_rate,b`` at the default) that the fits remove, ``size`` what they
    remove in RMS of what is left (``√(removed / left)``: the rate level's residual is white, its
    noise floor is what is left where the fit is right, so this is the size in noise floors where
    nothing else is missing and less where something is); ``undecided`` the comparison's note when
    the noise model or the closed loop decides it (then not confirmed), else ""."""

    test: evidence.HeldOutTest
    explained: float
    size: float
    undecided: str = ""
    better_than: str = ""  # a found timing candidate it fits significantly better than (_better_than_found)
    gains: Mapping[str, np.ndarray] = field(default_factory=dict)  # per held-out flight, its blocks' g


def judge(rows: list[CandidateRow], cands: Sequence[Effect], rows_of: Callable[[str], FlightData],
          release: Callable[[str], None], model, splits: Sequence[tuple[list[str], list[str]]], train_all: list[str],
          settings: DiagnosisSettings, decide: Callable[[CandidateRow], None],
          cache: RatesCache | None = None) -> tuple[list[CandidateRow], Judged]:
    """The ranked candidate rows of a diagnosis with its timing candidates (one parameter each,
    :attr:`~quadcore.effects.Effect.retimes_thrust`) fitted and compared at the rate level: each
    one's parameter, standard error (the larger of the profile's and the spread between the
    folds' fits) and significance from :func:`fit` on the training flights, and, per pair,
    :func:`timing_comparison`'s :func:`difference_test` (each candidate fitted on all the training
    flights, every flight's blocks scored; with held-out flights given, those): significant at
    ``settings.alpha``, the better one ranks above the
    other (within its tier) and the two are no longer tied; not, they are tied when either is
    found (undecided, whatever the torque level says). Every candidate on the same intervals
    (after the longest memory of them). The model's effects at their values fitted on all
    training flights. Each flight's rows (``rows_of``) are read once, reduced to its
    :class:`RateSums` and let go (``release``); ``cache``: those kept from an earlier diagnosis,
    each flight's rows read only when its are missing or stale. ``decide``: the diagnosis's
    decision (found, grade), taken again on each timing row with its significance and its held-out
    test from the rate level (:func:`_rate_evidence`: its folds' fits against no timing effect on
    their test flights, :func:`effect_comparison`), and on one the rate level prefers to a found one
    (:func:`_better_than_found`)."""
    timing = [c for c in cands if c.retimes_thrust and len(c.parameters) == 1]
    if not timing:
        return rows, Judged({})
    flights, slow = _reduced_flights(timing, splits, rows_of, release, model, cache)
    by_name = {r.effect: r for r in rows}
    if slow:
        first = sorted(slow)[0]
        return _undecided(rows, [by_name[c.name] for c in timing], sorted(slow), *slow[first]), Judged({})
    _fit_rows(timing, by_name, flights, splits, train_all, settings, decide)
    pairs = _compared_pairs(timing, by_name, flights, splits, settings.alpha)
    for better, worse in pairs.wins:
        _better_than_found(better, worse, decide)
    for ra, rb, note in pairs.open:
        if note:
            _undecided_tie(ra, rb, note)
        elif ra.found or rb.found:
            _tie(ra, rb)
    rows = sorted(rows, key=lambda r: r.tier())  # found ones first, as ranked (stable)
    gains = {r.effect: r.rate_level.gains for r in (by_name[c.name] for c in timing) if r.found and r.rate_level}
    return _ranked(rows, pairs.wins), Judged(pairs.differences, frozenset(pairs.undecided), gains)


def _reduced_flights(timing: Sequence[Effect], splits: Sequence[tuple[list[str], list[str]]],
                     rows_of: Callable[[str], FlightData], release: Callable[[str], None], model,
                     cache: RatesCache | None) -> tuple[dict[str, RateSums], dict[str, tuple[float, float]]]:
    """Every flight of ``splits`` as its :class:`RateSums` for ``timing`` (kept in ``cache`` or made
    from its rows, read once and let go), at the model's values; and the flights below the command
    rate, with their log period and the firmware's hold (they have no sums)."""
    skip = evidence.memory_blocks(timing)
    slow: dict[str, tuple[float, float]] = {}

    def compute(f: str) -> FlightRates:  # one flight's rows at a time, let go once its sums are taken
        out = flight_rates(rows_of(f), model, f, timing, skip)
        release(f)
        return out

    def reduced(f: str) -> RateSums | None:
        out = compute(f) if cache is None else cache(f, flight_inputs(model, f, timing, skip), lambda: compute(f))
        if isinstance(out, BelowCommandRate):
            slow[f] = (out.period_s, out.hold_s)
            return None
        return out.at_model(model, f)  # kept sums hold no value of the model's linear effects

    every = {f: reduced(f) for f in sorted({f for tr, te in splits for f in (*tr, *te)})}
    return {f: s for f, s in every.items() if s is not None}, slow


def _fit_rows(timing: Sequence[Effect], by_name: Mapping[str, CandidateRow], flights: Mapping[str, RateSums],
              splits: Sequence[tuple[list[str], list[str]]], train_all: list[str], settings: DiagnosisSettings,
              decide: Callable[[CandidateRow], None]) -> None:
    """Each timing candidate's row with its parameter and standard error from the rate level
    (:func:`timing_fit`), its held-out test against no timing effect (:func:`_rate_evidence`), and
    the diagnosis's decision on it taken again."""
    ws = split_weights(flights, splits)  # each fold's from its training flights (fold_fits')
    for c in timing:
        held = fold_fits(c, flights, splits, ws)
        _update_row(by_name[c.name], c, *timing_fit(c, flights, splits, train_all, settings.n_folds, held),
                    settings.min_sigma)
        _rate_evidence(by_name[c.name], effect_comparison(flights, splits, c, held, ws, settings.alpha),
                       held_out_cost(flights, splits, c, c.parameters[0].default, ws))
        decide(by_name[c.name])


@dataclass
class _Pairs:
    """Every pair of physical timing candidates compared (:func:`_compared_pairs`): per pair its
    flights' block differences, the ``wins`` (better, worse), the ``undecided`` pairs, and the
    ``open`` ones (a note: undecided, with why; "": not significant), tied once all are decided."""

    differences: dict[tuple[str, str], dict[str, np.ndarray]] = field(default_factory=dict)
    wins: list[tuple[CandidateRow, CandidateRow]] = field(default_factory=list)
    undecided: set[tuple[str, str]] = field(default_factory=set)
    open: list[tuple[CandidateRow, CandidateRow, str]] = field(default_factory=list)


def _compared_pairs(timing: Sequence[Effect], by_name: Mapping[str, CandidateRow], flights: Mapping[str, RateSums],
                    splits: Sequence[tuple[list[str], list[str]]], alpha: float) -> _Pairs:
    """Each pair of physical timing candidates by :func:`timing_comparison` at ``alpha``: the
    better one of a significant pair preferred (:func:`_prefer`), the others left open."""
    out = _Pairs()
    for i, a in enumerate(timing):
        for b in timing[i + 1:]:
            ra, rb = by_name[a.name], by_name[b.name]
            if not (ra.physical and rb.physical):
                continue
            pair = timing_comparison(flights, splits, a, b, alpha)
            out.differences[(a.name, b.name)] = {f: g for f, (g, _) in pair.per_flight.items()}
            if pair.undecided:
                out.undecided.add((a.name, b.name))
                out.open.append((ra, rb, pair.note()))
            elif pair.test.p_value < alpha:
                out.wins.append((ra, rb) if pair.test.t > 0 else (rb, ra))
                _prefer(*out.wins[-1])
            else:
                out.open.append((ra, rb, ""))
    return out


def fold_fits(c: Effect, flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
              ws: Sequence[np.ndarray]) -> list[RateFit]:
    """Per split, ``c`` fitted on its training flights, weighted by their noise (``ws``, the
    splits' :func:`split_weights`): what the split predicts its test flights with."""
    return [fit(c, [flights[f] for f in tr], wk) for (tr, _), wk in zip(splits, ws)]


def timing_fit(c: Effect, flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
               train_all: Sequence[str], n_folds: int, folds: Sequence[RateFit] | None = None
               ) -> tuple[RateFit, float]:
    """A timing candidate's parameter as the diagnosis reports it: :func:`fit` on all the training
    flights (weighted by their noise, none of the held-out ones'), and its spread between flights, the
    grouped jackknife over the folds' fits (:func:`fold_fits`; ``folds``: made already), or with
    one split, over fits that each leave out a group of its flights (``n_folds`` groups; none with
    fewer than three flights). The row's standard error is the larger of the two (:func:`_update_row`)."""
    w = weights([flights[f] for f in train_all])
    if len(splits) > 1:
        spread = list(folds) if folds is not None else fold_fits(c, flights, splits, split_weights(flights, splits))
    else:
        groups = ([[f for f in train_all if f not in g] for g in solve.folds(list(train_all), n_folds)]
                  if len(train_all) >= 3 else [])
        spread = [fit(c, [flights[f] for f in g], w) for g in groups]
    (p,) = c.parameters
    return (fit(c, [flights[f] for f in train_all], w),
            solve.jackknife_std([{p.name: f.value} for f in spread]).get(p.name, 0.0))


def _undecided(rows: list[CandidateRow], timing: list[CandidateRow], slow: list[str], dt: float, hold_s: float
               ) -> list[CandidateRow]:
    """The timing candidates of a fleet with flights :func:`below_command_rate`: not fitted or
    compared at the rate level (their parameters stay the torque level's), and tied where either
    is found. Between two log samples the firmware sets commands the log does not hold, each
    reacting to a fresh gyro sample; the interval integral gives the logged command's jitter
    the whole interval where it acted for one command period, and a lag (which smooths it
    away) fits that better than the truth (docs/timing.md: on simulated 100 Hz hover flights a
    lag came out at its 0.2 s bound whether a 10 ms lag or a 10 ms delay was true)."""
    note = (f"not compared with the other timing candidates at the angular-rate level: {', '.join(slow)} "
            f"log{'s' if len(slow) == 1 else ''} the commands every {dt * 1e3:.3g} ms, the firmware sets them "
            f"every {hold_s * 1e3:.3g} ms, and the commands between samples read as a lag "
            "(docs/timing.md); the parameter is the torque level's, which the closed loop biases")
    for i, a in enumerate(timing):
        a.notes = (*a.notes, note)
        for b in timing[i + 1:]:
            if a.physical and b.physical and (a.found or b.found):
                _tie(a, b)
    return rows


def _update_row(r: CandidateRow, c: Effect, rf: RateFit, spread: float, min_sigma: float) -> None:
    """A candidate row with its parameter from the rate level (the torque level's in a note),
    its standard error the larger of the profile's and ``spread``, the grouped jackknife's
    between flights (:func:`timing_fit`)."""
    (p,) = c.parameters
    std = max(rf.std, spread)
    torque_v, torque_s = r.parameters[p.name], r.parameter_std[p.name]
    r.parameters = {p.name: rf.value}
    r.parameter_std = {p.name: std}
    r.parameter_spread_between_flights = {p.name: spread}
    sigma = abs(rf.value - p.default) / std if std > 0 else (np.inf if rf.value != p.default else 0.0)
    r.significance_sigma = float(min(sigma, 1e6))
    r.significant = r.significance_sigma >= min_sigma
    r.notes = (*(n for n in r.notes if not n.startswith(NOT_SIGNIFICANT)),
               f"{p.name} fitted at the angular-rate level, {rf.value:.4g} ± {std:.2g} (on the torque channels, which "
               f"the closed loop biases, {torque_v:.4g} ± {torque_s:.2g}: docs/timing.md)")
    if rf.unwhitened is not None and rf.depends_on_noise_model and rf.std >= spread:
        r.notes = (*r.notes, f"{p.name} depends on the gyro noise model: {rf.value:.4g} with it, {rf.unwhitened:.4g} "
                             "without; the standard error spans both (docs/timing.md, 'A small delay')")
    if not r.significant:
        r.notes = (*r.notes, f"{NOT_SIGNIFICANT} the fit is only {r.significance_sigma:.1f} standard errors from "
                             "'no effect'")


def _rate_evidence(r: CandidateRow, comp: PairComparison, before: float) -> None:
    """A timing row's held-out test and size from the rate level (:class:`RateEvidence`, ``comp``
    its :func:`effect_comparison`, ``before`` the held-out blocks' cost with no timing effect),
    the torque level's held-out test in a note: the closed loop biases it (a 5 ms lag fitted
    5.000 ± 0.93 ms at the rate level removed none of the held-out torque residual, its score
    −1.5: docs/timing.md, "Found at the angular-rate level")."""
    test = comp.test
    g = np.concatenate([d for d, _ in comp.per_flight.values()]) if comp.per_flight else np.zeros(0)
    removed = float(g.sum())
    one_sided = (evidence.HeldOutTest(test.beta, test.t, float(stats.t.sf(test.t, test.blocks - 1)), test.blocks)
                 if test.blocks >= evidence.MIN_BLOCKS else evidence.NO_TEST)
    left = before - removed
    size = float(np.sqrt(removed / left)) if removed > 0 and left > 0 else 0.0
    r.rate_level = RateEvidence(one_sided, removed / before if before > 0 else 0.0, size,
                                comp.note() if comp.undecided else "",
                                gains={f: d for f, (d, _) in comp.per_flight.items()})
    r.notes = (*r.notes, f"found or not at the angular-rate level: held out against no timing effect, t = {test.t:.2f} "
                         f"(on the {r.held_out_level} channels, which the closed loop biases, t = {r.held_out_t:.2f}, "
                         f"p = {r.held_out_p_value:.2g}: docs/timing.md)"
                         + (f"; not confirmed, set aside: {comp.note()}" if comp.undecided else ""))
    r.held_out_level = RATE_LEVEL
    r.held_out_slope, r.held_out_t, r.held_out_p_value, r.held_out_blocks = (
        one_sided.beta, one_sided.t, one_sided.p_value, one_sided.blocks)
    r.signal_to_noise = size


def _better_than_found(better: CandidateRow, worse: CandidateRow, decide: Callable[[CandidateRow], None]) -> None:
    """``better``, which the rate level prefers significantly to ``worse``, decided again as
    significant (:attr:`RateEvidence.better_than`) when ``worse`` is found and ``better`` is not
    only because its fit is within ``min_sigma`` standard errors of 'no effect': its standard error
    is at least the spread of the folds' fits, and a fold without the one flight that moves fits it
    on hovers alone, which the closed loop biases (lag_firmware_5ms with the delay true: 4.997 ±
    0.003 ms on all the flights, 2.0 ms without the planned flight, a spread of 2.2 ms, while the
    lag, worse by t = 26, is found at 5.000 ± 0.26 ms). It must still be physical and confirmed
    against no timing effect on held-out flights."""
    ev = better.rate_level
    if better.found or not worse.found or ev is None or better.significant:
        return
    better.rate_level = replace(ev, better_than=worse.effect)
    decide(better)
    if better.found:
        better.notes = (*better.notes, f"found although its fit is {better.significance_sigma:.1f} standard errors "
                                       f"from 'no effect': it fits the angular rates significantly better than "
                                       f"{worse.effect}, which is found, and better than no timing effect on held-out "
                                       f"flights (t = {better.held_out_t:.1f}); its standard error is the spread of "
                                       "the folds' fits (docs/timing.md, 'Found at the angular-rate level')")


def _prefer(better: CandidateRow, worse: CandidateRow) -> None:
    """``better`` separated from ``worse`` by the rate level (:func:`_ranked` ranks it above)."""
    for r, o in ((better, worse), (worse, better)):
        r.tied_with = tuple(x for x in r.tied_with if x != o.effect)
        r.separated_by = {**r.separated_by, o.effect: RATE_LEVEL}


def _ranked(rows: list[CandidateRow], wins: Sequence[tuple[CandidateRow, CandidateRow]]) -> list[CandidateRow]:
    """``rows`` (in their tiers) with the better of each pair in ``wins`` (better, worse) ranked
    above the worse where both are in one tier, every other row in its order: row by row, the
    first row left, or, when a row left in its tier fits better than it, that one (the first
    such, followed up the chain; in a cycle, the first row left). A function of the set of wins,
    so the same whatever order the pairs were compared in. (Before, each significant pair moved
    its better one above the worse in turn, and with three timing candidates a later move could
    put a worse one back above its better: [c, a, b] with a > b > c became [b, a, c] when the
    pairs came as (a, b), (b, c), (a, c), and [a, b, c] in another order.)"""
    better = {(id(b), id(w)) for b, w in wins if b.tier() == w.tier()}
    left, out = list(rows), []
    while left:
        r, chain = left[0], []
        while r not in chain:
            chain.append(r)
            above = [o for o in left if (id(o), id(r)) in better]
            if not above:
                break
            r = above[0]
        else:  # a cycle: no row of it is above the others
            r = left[0]
        out.append(r)
        left.remove(r)
    return out


def _tie(a: CandidateRow, b: CandidateRow) -> None:
    """``a`` and ``b`` tied: the rate level prefers neither."""
    for r, o in ((a, b), (b, a)):
        if o.effect not in r.tied_with:
            r.tied_with = (*r.tied_with, o.effect)
        if o.effect not in r.indistinguishable_from:
            r.indistinguishable_from = (*r.indistinguishable_from, o.effect)
        r.separated_by = {k: v for k, v in r.separated_by.items() if k != o.effect}


def _undecided_tie(a: CandidateRow, b: CandidateRow, note: str) -> None:
    """``a`` and ``b`` tied because the noise model or the closed loop decides between them
    (:func:`quadcore.identify.rates.noise_model_decides`,
    :func:`quadcore.identify.rates.closed_loop_decides`): each row says so (``note``,
    :meth:`quadcore.identify.rates.compare.PairComparison.note`; they are tied, as an undecided pair
    is, when either is found)."""
    for r in (a, b):
        r.notes = (*r.notes, note)
    if a.found or b.found:
        _tie(a, b)
