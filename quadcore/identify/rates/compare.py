"""Which of two timing candidates the rate level prefers: the held-out comparison.

Per block ``b`` of a held-out flight, with both candidates fitted on the training flights
(:mod:`quadcore.identify.rates.sums`), the difference of their weighted costs

    g_b = J_rate,b(B) − J_rate,b(A),   D_b = Σ_(k∈b) Σ_axis w_a (C̃_A,ka − C̃_B,ka)²      (body frame)

(:func:`block_differences`; ``E g_b = D_b`` if ``A`` is the truth, ``−D_b`` if ``B`` is), and the
slope ``β = Σ g / Σ D`` t-tested over the blocks as independent clusters
(:func:`difference_test`; ``t > 0``: ``A`` fits better). The same comparison without the gyro
noise model's whitening filters (:func:`unwhitened_comparison`) decides nothing alone: when the
two are both significant and opposite, the noise model decides the answer and the rate level
prefers neither (:func:`noise_model_decides`, docs/timing.md "A small delay"). Nor does the
comparison with the whitened direction one interval back as the instrument
(:func:`instrumented_differences`), which the noise the commands react to reaches far less than the
direction itself: when the whitened slope differs from it significantly and it does not confirm the
whitened answer, the closed loop's response to its own noise decides the answer, and the rate level
prefers neither (:func:`closed_loop_decides`, docs/timing.md "The closed loop's share").

The diagnosis and the planner compare the pair at fits on all the training flights
(:func:`pair_splits`, :func:`timing_comparison`), every flight's blocks scored: two non-nested
candidates with one parameter each gain alike, in expectation, from fitting the flights they are
scored on (Vuong 1989, the likelihood-ratio test of non-nested models of equal dimension needs no
correction), while leaving one flight out lets the fold that holds out the one informative flight
(a flight that moves, among hovers) fit both on the others alone, biased, and that flight's blocks
then ask only which biased fit is nearer (docs/timing.md, "The closed loop's share").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from quadcore.effects import Effect
from quadcore.identify import evidence
from quadcore.identify.rates.sums import RateFit, RateSums, fit, split_weights

NO_TIMING = "no timing effect"  # the other side of :func:`effect_comparison`


def block_differences(flights: Sequence[RateSums], a: Effect, pa: dict[str, float], b: Effect,
                      pb: dict[str, float], w: np.ndarray, unwhitened: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per block of ``flights``: ``g``, ``b``'s weighted ``J_rate`` minus ``a``'s (> 0: ``a`` fits
    better), and ``D``, the weighted ``Σ (C_a − C_b)²`` (block means removed) that ``g`` is made of:
    with ``e = R − (C_a + C_b)/2``, ``g = 2 Σ (C_a − C_b) e`` and, if ``a`` is the truth,
    ``E g = D``; if ``b`` is, ``−D``. ``unwhitened``: without the flights' whitening filters
    (:attr:`RateSums.unwhitened_blocks`)."""
    g, D = [], []
    for s in flights:
        gs, Ds = s.differences(a, pa[a.parameters[0].name], b, pb[b.parameters[0].name], unwhitened)
        g.append(gs @ w)
        D.append(Ds @ w)
    return np.concatenate(g), np.concatenate(D)


def difference_test(g: np.ndarray, D: np.ndarray) -> evidence.HeldOutTest:
    """Which of two candidates the blocks prefer: the slope ``β = Σ g / Σ D`` of the residual on
    the direction from ``b``'s prediction to ``a``'s (+1: ``a`` is right, −1: ``b`` is, 0: neither
    fits better), its standard error from the blocks' scores ``g − β D`` (blocks as independent
    clusters, as :func:`quadcore.identify.evidence.held_out_test_of` takes them), two-sided
    (``t > 0``: ``a`` fits better). A t-test of the mean of ``g`` instead would count the spread
    of ``D`` between blocks (a manoeuvre's blocks against a hover's) as noise."""
    n, den = len(g), float(D.sum())
    if n < 3 or den <= 0:
        return evidence.NO_TEST
    beta = float(g.sum() / den)
    se = float(np.sqrt(n / (n - 1) * np.sum((g - beta * D) ** 2)) / den)
    t = beta / se if se > 0 else (np.inf if beta > 0 else -np.inf if beta < 0 else 0.0)
    t = float(np.clip(t, -1e6, 1e6))
    return evidence.HeldOutTest(beta, t, float(2 * stats.t.sf(abs(t), n - 1)), n)


def compare_pair(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]], a: Effect,
                 b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit], ws: Sequence[np.ndarray]
                 ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], evidence.HeldOutTest]:
    """The held-out comparison of two timing candidates: per test flight of each split its
    :func:`block_differences` with both candidates fitted on the split's training flights
    (``fits_a``, ``fits_b``, one per split) and weighted as there (``ws``, one per split:
    :func:`quadcore.identify.rates.sums.split_weights`), and the :func:`difference_test` over all
    of them (``t > 0``: ``a`` fits better)."""
    per_flight = {f: block_differences([flights[f]], a, {fa.parameter: fa.value}, b, {fb.parameter: fb.value}, w)
                  for (_, te), fa, fb, w in zip(splits, fits_a, fits_b, ws) for f in te}
    return per_flight, difference_test(*(np.concatenate(x) for x in zip(*per_flight.values())))


def unwhitened_comparison(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                          a: Effect, b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit],
                          ws: Sequence[np.ndarray]) -> evidence.HeldOutTest | None:
    """:func:`compare_pair`'s test without the whitening filters: each candidate at its value fitted
    without them (:attr:`RateFit.unwhitened`), the blocks' differences from the unfiltered Grams
    (:attr:`RateSums.unwhitened_blocks`). None when no test flight went through a filter (the two
    are then the same test)."""
    if not any(flights[f].filtered for _, te in splits for f in te):
        return None

    def at(fit: RateFit) -> dict[str, float]:
        return {fit.parameter: fit.value if fit.unwhitened is None else fit.unwhitened}

    per_flight = [block_differences([flights[f]], a, at(fa), b, at(fb), w, unwhitened=True)
                  for (_, te), fa, fb, w in zip(splits, fits_a, fits_b, ws) for f in te]
    return difference_test(*(np.concatenate(x) for x in zip(*per_flight)))


def noise_model_decides(test: evidence.HeldOutTest, unwhitened: evidence.HeldOutTest, alpha: float) -> bool:
    """True when the comparison's answer depends on the gyro noise model: ``test`` (whitened) prefers
    one candidate at ``alpha`` and the same comparison without the filters (``unwhitened``) prefers
    the other at ``alpha``. The gyro cannot tell which filter is right (it holds the closed loop's
    response to its own noise, docs/timing.md "A small delay"), so two defensible noise models
    that significantly contradict each other leave the pair undecided; an unwhitened test that
    merely fails to confirm (not significant, or significant the same way) leaves the whitened
    answer standing (its error bar already spans the noise model: :attr:`RateFit.unwhitened`)."""
    return test.p_value < alpha and unwhitened.p_value < alpha and bool(np.sign(test.t) != np.sign(unwhitened.t))


def instrumented_differences(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                             a: Effect, b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit],
                             ws: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`compare_pair`'s per-block ``g`` and ``D``, block for block in its order, with the
    direction one interval back as the instrument (:meth:`RateSums.instrumented`): each candidate
    at its whitened fit and weighted as there. None when no test flight went through a whitening
    filter."""
    if not any(flights[f].lagged_blocks is not None for _, te in splits for f in te):
        return None
    per_flight = {f: tuple(x @ w for x in flights[f].instrumented(a, fa.value, b, fb.value))
                  for (_, te), fa, fb, w in zip(splits, fits_a, fits_b, ws) for f in te}
    g, D = (np.concatenate(x) for x in zip(*per_flight.values()))
    return g, D


def instrument_test(g: np.ndarray, D: np.ndarray, gi: np.ndarray, Di: np.ndarray
                    ) -> tuple[evidence.HeldOutTest, evidence.HeldOutTest]:
    """The instrumented :func:`difference_test` of the blocks' ``gi``, ``Di``
    (:func:`instrumented_differences`), and the test of the whitened slope (``g``, ``D``: the same
    blocks) against it, ``β_W − β_IV`` with its standard error from the difference of the two
    slopes' block scores (blocks as independent clusters): a Durbin-Wu-Hausman test, the whitened
    slope the efficient one where the noise left after the filter is uncorrelated with the
    direction, the instrumented one consistent where it is not. ``t > 0``: the whitened slope
    leans more to ``a``."""
    iv = difference_test(gi, Di)
    n, den, den_i = len(g), float(D.sum()), float(Di.sum())
    if n < 3 or den <= 0 or den_i <= 0:
        return iv, evidence.NO_TEST
    beta, beta_i = float(g.sum() / den), float(gi.sum() / den_i)
    score = (g - beta * D) / den - (gi - beta_i * Di) / den_i
    se = float(np.sqrt(n / (n - 1) * np.sum(score**2)))
    t = float(np.clip((beta - beta_i) / se, -1e6, 1e6)) if se > 0 else 0.0
    return iv, evidence.HeldOutTest(beta - beta_i, t, float(2 * stats.t.sf(abs(t), n - 1)), n)


def closed_loop_decides(test: evidence.HeldOutTest, iv: evidence.HeldOutTest, shift: evidence.HeldOutTest,
                        alpha: float) -> bool:
    """True when the whitened comparison's answer is the closed loop's: ``test`` prefers one
    candidate at ``alpha``, its slope differs from the instrumented one's at ``alpha`` (``shift``,
    :func:`instrument_test`), and the instrumented comparison (``iv``) does not prefer the same one
    at ``alpha``. The whitening filter leaves the gyro noise correlated with itself one interval
    apart (its white floor, and the loop's response to its own noise that the gyro holds and the
    filter takes for colour), and the commands that make the direction react to that noise; the
    direction one interval back, which the noise reaches far less, is the instrument
    (docs/timing.md, "The closed loop's share")."""
    return (test.p_value < alpha and shift.p_value < alpha
            and not (iv.p_value < alpha and bool(np.sign(iv.t) == np.sign(test.t))))


@dataclass(frozen=True)
class PairComparison:
    """The rate level's held-out comparison of two timing candidates ``a`` and ``b`` as it decides
    them: each test flight's :func:`block_differences` (> 0: ``a`` fits better), the test with the
    gyro noise model's whitening (``test``) and without it (``unwhitened``; None: no test flight went
    through a filter), and ``undecided``: the two significant and opposite, so that the noise model
    decides it (:func:`noise_model_decides`), or the closed loop does (``closed_loop``,
    :func:`closed_loop_decides`, ``instrumented`` the test with the direction one interval back as
    the instrument; None: no test flight went through a filter), and neither is preferred."""

    a: str
    b: str
    per_flight: dict[str, tuple[np.ndarray, np.ndarray]]
    test: evidence.HeldOutTest
    unwhitened: evidence.HeldOutTest | None
    undecided: bool
    instrumented: evidence.HeldOutTest | None = None
    closed_loop: bool = False

    @property
    def undecided_by(self) -> str:
        """What decides an undecided comparison in its place, in a few words: ``the closed loop``
        (:func:`closed_loop_decides`) or ``the noise model`` (:func:`noise_model_decides`); "" when
        the comparison decides."""
        return "" if not self.undecided else "the closed loop" if self.closed_loop else "the noise model"

    def note(self) -> str:
        """What an undecided comparison says: which candidate each test prefers, and that neither is."""
        first, second = (self.a, self.b) if self.test.t > 0 else (self.b, self.a)
        if self.closed_loop and self.instrumented is not None:
            iv = self.instrumented.t
            lean = first if iv * self.test.t > 0 else second if iv * self.test.t < 0 else "neither"
            return (f"the angular-rate level prefers {first} to {second} with the gyro noise model "
                    f"(t = {abs(self.test.t):.1f}), but significantly less so with the timing direction one sample "
                    f"back as the instrument, which leans to {lean} (t = {abs(iv):.1f}): the closed loop's "
                    "response to its own noise decides it, so neither is preferred (docs/timing.md, "
                    "'The closed loop's share')")
        raw = self.unwhitened.t if self.unwhitened is not None else float("nan")
        return (f"the angular-rate level prefers {first} to {second} with the gyro noise model "
                f"(t = {abs(self.test.t):.1f}) and {second} without it (t = {abs(raw):.1f}): the noise model "
                "decides it, so neither is preferred (docs/timing.md, 'A small delay')")


def pair_comparison(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                    a: Effect, b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit],
                    ws: Sequence[np.ndarray], alpha: float) -> PairComparison:
    """Two timing candidates at the given fits compared on the test flights of ``splits``, with
    every rule that leaves a pair undecided: :func:`compare_pair`, :func:`unwhitened_comparison`
    and :func:`instrumented_differences` on the same splits, and whether the noise model
    (:func:`noise_model_decides`) or else the closed loop (:func:`closed_loop_decides`) decides it
    at ``alpha``. Held out or in-sample as the splits are: the diagnosis's folds for a candidate
    against no timing effect (:func:`effect_comparison`), :func:`pair_splits` (fits on all the
    flights, every one scored) for two candidates (:func:`timing_comparison`, which the diagnosis
    decides them by and the planner measures them by)."""
    per_flight, test = compare_pair(flights, splits, a, b, fits_a, fits_b, ws)
    raw = unwhitened_comparison(flights, splits, a, b, fits_a, fits_b, ws)
    noise_model = raw is not None and noise_model_decides(test, raw, alpha)
    lagged = instrumented_differences(flights, splits, a, b, fits_a, fits_b, ws)
    if lagged is None:
        return PairComparison(a.name, b.name, per_flight, test, raw, noise_model)
    g, D = (np.concatenate(x) for x in zip(*per_flight.values()))
    iv, shift = instrument_test(g, D, *lagged)
    closed_loop = not noise_model and closed_loop_decides(test, iv, shift, alpha)
    return PairComparison(a.name, b.name, per_flight, test, raw, noise_model or closed_loop, iv, closed_loop)


def effect_comparison(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                      c: Effect, fits: Sequence[RateFit], ws: Sequence[np.ndarray], alpha: float) -> PairComparison:
    """The held-out test of a timing candidate ``c`` against no timing effect: ``c`` at each split's
    fit (``fits``, on its training flights, weighted by ``ws``) against ``c`` at its parameter's
    default (a nested pair), :func:`pair_comparison` on the test flights of ``splits`` at
    ``alpha`` with every rule that leaves a pair undecided (``t > 0``: the fitted effect fits
    better; ``b``: ``"no timing effect"``). On held-out flights, not :func:`pair_splits`: a fit on
    the flights it is scored on always favours the bigger of two nested models (in-sample only
    where the diagnosis is: one flight)."""
    (p,) = c.parameters
    none = [RateFit(c.name, p.name, p.default, 0.0, 0.0, 0) for _ in fits]
    return replace(pair_comparison(flights, splits, c, c, fits, none, ws, alpha), b=NO_TIMING)


def held_out_cost(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]], c: Effect,
                  value: float, ws: Sequence[np.ndarray]) -> float:
    """``Σ J_rate,b`` over every block of the test flights of ``splits`` with ``c`` at ``value``
    (its default: the residual with no timing effect), weighted as each split's (``ws``)."""
    return sum(float((flights[f].costs(c, value) @ w).sum()) for (_, te), w in zip(splits, ws) for f in te)


def pair_splits(splits: Sequence[tuple[Sequence[str], Sequence[str]]]) -> list[tuple[list[str], list[str]]]:
    """The one split two timing candidates are compared on: the diagnosis's folds' flights, each
    candidate fitted on all of them and every one scored (in-sample, :mod:`this module's
    <quadcore.identify.rates.compare>` note); a single split (held-out flights given, or one
    flight) as it is."""
    if len(splits) == 1:
        return [(list(splits[0][0]), list(splits[0][1]))]
    ids = sorted({f for tr, te in splits for f in (*tr, *te)})
    return [(ids, ids)]


def timing_comparison(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                      a: Effect, b: Effect, alpha: float) -> PairComparison:
    """How the diagnosis (:func:`quadcore.identify.rates.judge`) and the planner
    (:func:`quadcore.plan.separation.rate_compare`) decide two timing candidates: on
    :func:`pair_splits` of the diagnosis's ``splits``, each candidate fitted on the split's training
    flights and weighted by their noise (:func:`~quadcore.identify.rates.sums.fit`,
    :func:`~quadcore.identify.rates.sums.split_weights`), :func:`pair_comparison` at ``alpha``
    with every rule that leaves the pair undecided."""
    pair = pair_splits(splits)
    ws = split_weights(flights, pair)
    fits_a, fits_b = ([fit(e, [flights[f] for f in tr], w) for (tr, _), w in zip(pair, ws)] for e in (a, b))
    return pair_comparison(flights, pair, a, b, fits_a, fits_b, ws, alpha)
