"""What counts as evidence for a missing effect, and how small an effect could have been missed.

**Held-out significance.** A candidate fitted on training flights predicts a wrench ``p`` on
flights it never saw, whose residual is ``r``. If the effect is real, ``p`` points where ``r``
does: in the regression ``r = β p + e`` (summed over the chosen channels, each weighted) the
slope ``β`` is positive. Its t-statistic uses a cluster-robust variance with blocks of
``BLOCK_S`` seconds of one flight as clusters, because neighbouring samples of a smoothed
residual are not independent (the smoother spans 62 ms; blocks of 1 s are far apart)::

    β̂ = Σ p·r / Σ p·p,      se² = B/(B-1) Σ_b (Σ_{i∈b} p_i·e_i)² / (Σ p·p)²,      t = β̂ / se

and the one-sided p-value is that of Student's t with ``B - 1`` degrees of freedom (``B``
blocks). Unlike a fixed share of the residual, this does not care how small the effect is
next to the noise, only whether the held-out data confirm it.

**The noise floor.** A channel whose held-out residual RMS is within ``NOISE_MARGIN`` of
its sensor-noise floor (:func:`quadcore.identify.flightdata.sensor_noise_floor`) holds no evidence
*for* any effect. This is not a threshold on size but on what the data can say: the
controller closes its loop on the same noisy gyro the torque residual is computed from, so
commanded rotor torques correlate with the gyro noise in the "measured" torque (errors in
variables), and a thrust scale or motor lag then "explains", significantly, a third of pure
noise even on held-out flights. The margin covers the floor's own error (the residual of
simulated flights with nothing hidden lies within 4 % RMS of it).

**Sensitivity.** The smallest deviation ``v`` of one parameter from 'no effect' that these
flights would detect with probability ``POWER`` at false-alarm rate ``ALPHA``, by the
analytic variance of the test above with the effect injected into the flights' own
residual ``r0``. With ``u`` the held-out wrench per unit of the parameter (a secant over
``SECANT`` of its range) and the injected effect predicted exactly (``p = v u``):
``t = v S / sqrt(Q)`` with ``S = Σ u·u`` and ``Q = B/(B-1) Σ_b (Σ_{i∈b} u_i·e_i)²``, ``e`` the
residual with its projection on ``u`` removed (an effect already there is no noise to itself), so

    v_test  = (t_crit + z_power) sqrt(Q) / S
    v_sigma = (MIN_SIGMA + z_power) sqrt(ms W / S)     (the fit's own standard error)
    v_floor = sqrt(max(0, (1 + NOISE_MARGIN)² F - R) / S)   (lift the channel off its floor)

and the sensitivity in a channel is the largest of the three (all must pass), over channels
the smallest. ``ms`` is the residual's mean square, ``W`` the samples per independent one,
``F`` and ``R`` the channel's floor and residual sums of squares. For a nonlinear effect the
secant is all that is known: its sensitivity is never stated below the secant's step (for
``motor_lag``, 2 ms: its discrete lag adds a whole sample of delay for any τ > 0, so a lag
much shorter than a sample cannot be fitted).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from quadcore import effects as effectlib
from quadcore.identify import flightdata, ranges
from quadcore.identify.flightdata import (  # noqa: F401  (BLOCK_S, SECANT, unit_wrench: read from here too)
    BLOCK_S,
    SECANT,
    Flight,
    Signals,
    unit_wrench,
)
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.spec.model import ModelSpec

Flights = Sequence[Flight]

# The defaults of quadcore.identify.settings (their meaning there) under the names the code reads;
# the diagnosis takes its own DiagnosisSettings.
ALPHA = DEFAULT.alpha
POWER = DEFAULT.power
NOISE_MARGIN = DEFAULT.noise_margin
MIN_EXPLAINED = DEFAULT.min_explained
MIN_SIGMA = DEFAULT.min_sigma
LIBRARY_SHARE = DEFAULT.library_share
SAME_SIGNATURE = DEFAULT.same_signature
TIE_MARGIN = DEFAULT.tie_margin
LARGE_SNR = DEFAULT.large_snr
CHANNELS = {"force": slice(0, 3), "torque": slice(3, 6)}
SAME_TO_ROUNDING = 1e-18  # energy of a difference, relative: amplitudes equal to 1e-9 (rounding leaves ~1e-15)


@dataclass(frozen=True)
class HeldOutTest:
    """The held-out regression of the residual on a prediction: slope, t and p-value."""

    beta: float
    t: float
    p_value: float
    blocks: int

    def __post_init__(self) -> None:
        ranges.finite(self.beta, "the held-out slope")
        ranges.finite(self.t, "the held-out t statistic")
        ranges.probability(self.p_value, "the held-out p-value")


NO_TEST = HeldOutTest(0.0, 0.0, 1.0, 0)
MIN_BLOCKS = 3  # the fewest blocks a held-out t-test is made on


def channel_mask(channels) -> np.ndarray:
    """(6,) 1 on the channels named (``force`` / ``torque``), 0 elsewhere."""
    m = np.zeros(6)
    for ch in channels:
        m[CHANNELS[ch]] = 1.0
    return m


def memory_blocks(effects) -> int:
    """How many of a flight's first blocks (of ``BLOCK_S``) lie within the longest
    :meth:`~quadcore.effects.Effect.memory_s` of ``effects``: where an effect with memory predicts
    nothing (:func:`quadcore.identify.flightdata.prediction`) and a memoryless one, or one with a
    shorter memory, does. Comparing candidates on the samples after them compares them on the
    same samples (the diagnosis's evaluation, the planner's objective)."""
    memory = max((e.memory_s() for e in effects), default=0.0)
    return int(np.ceil(memory / BLOCK_S - 1e-9))


def default_candidates(spec: ModelSpec) -> list[str]:
    """The effects a diagnosis offers when not told which: the library's built-in effects, then
    the plugin effects of the spec's own model file (its ``plugins``), each offered and not
    already in the model. Not every effect this process has loaded: a long-lived process (the
    Dagster UI, a test run) keeps the plugins of every model file it ever read, and another
    model's plugin is no candidate for this one."""
    own = [src.effect for src in effectlib.plugins_from(spec.plugins)]
    return [n for n in (*effectlib.builtin_names(), *own) if n not in spec.effects and effectlib.get(n).offered]


def scored_after_blocks(spec: ModelSpec, candidates: list[str] | None = None) -> int:
    """How many first blocks of each evaluated flight a diagnosis of ``spec`` leaves out of its
    scores (:func:`quadcore.identify.diagnosis.problem._on_common_samples`): those within the longest
    memory (:func:`memory_blocks`) of the model's effects and the candidates (None: :func:`default_candidates`).
    Term discovery's held-out RMSE leaves out the same, so both score the same samples."""
    names = candidates if candidates is not None else default_candidates(spec)
    return memory_blocks([effectlib.get(n) for n in (*spec.effects, *names)])


def block_channel_sums(flights: Flights, pairs: Sequence[tuple[Signals, Signals]]) -> list[np.ndarray]:
    """Per pair ``(a, b)`` of signals (flight -> signal): (blocks of every flight, 6) ``Σ_i a_ic b_ic``
    per block and channel over its usable samples (:meth:`Flight.block_channel_sums`: on
    statistics from their Gram matrices, each flight's read once for all the pairs)."""
    with flightdata.one_blas_thread():  # G [b, ...] with many columns is a matrix product OpenBLAS would thread
        per_flight = [fd.block_channel_sums(pairs) for fd in flights]
    return [np.concatenate([sums[k] for sums in per_flight]) if per_flight else np.zeros((0, 6))
            for k in range(len(pairs))]


def block_sums(flights: Flights, a: Signals, b: Signals, weights: np.ndarray) -> np.ndarray:
    """Per block of every flight: ``Σ_i Σ_c w_c a_ic b_ic`` over its usable samples
    (:func:`block_channel_sums` weighted)."""
    return block_channel_sums(flights, [(a, b)])[0] @ weights


def _t_and_p(num: np.ndarray, den: float, scores: np.ndarray) -> HeldOutTest:
    n = len(scores)
    if n < MIN_BLOCKS or den <= 0:
        return NO_TEST
    beta = float(num.sum() / den)
    se = float(np.sqrt(n / (n - 1) * np.sum(scores**2)) / den)
    t = beta / se if se > 0 else (np.inf if beta > 0 else 0.0)
    return HeldOutTest(beta, float(min(t, 1e6)), float(stats.t.sf(t, n - 1)), n)


def held_out_test(flights: Flights, resid: dict[str, np.ndarray], pred: dict[str, np.ndarray],
                  weights: np.ndarray) -> HeldOutTest:
    """Is ``pred`` (n, 6 per flight) confirmed by ``resid`` on these flights? (see the module)"""
    return held_out_test_of(held_out_sums(flights, resid, [pred])[0], weights)


def held_out_sums(flights: Flights, resid: Signals, preds: Sequence[Signals]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per prediction: (residual·prediction, prediction·prediction) per block and channel
    (:func:`block_channel_sums`; on statistics one read of the Gram matrices for all of them)."""
    sums = block_channel_sums(flights, [pair for pred in preds for pair in ((resid, pred), (pred, pred))])
    return [(sums[2 * k], sums[2 * k + 1]) for k in range(len(preds))]


def held_out_test_of(sums: tuple[np.ndarray, np.ndarray], weights: np.ndarray) -> HeldOutTest:
    """:func:`held_out_test` from a prediction's :func:`held_out_sums`, weighted per channel."""
    pr, pp = (s @ weights for s in sums)
    den = float(pp.sum())
    if den <= 0:
        return NO_TEST
    beta = pr.sum() / den
    return _t_and_p(pr, den, pr - beta * pp)


def compare(flights: Flights, resid: dict[str, np.ndarray], pred_a: dict[str, np.ndarray],
            pred_b: dict[str, np.ndarray], weights: np.ndarray) -> HeldOutTest:
    """Does ``pred_a`` fit the held-out ``resid`` better than ``pred_b``? The difference of their
    weighted squared errors, ``|r - b|² - |r - a|² = 2 (a - b)·(r - (a + b)/2)``, summed per
    block; two-sided t-test of its mean (``t > 0``: ``a`` fits better). Two predictions equal to
    rounding (:func:`same_prediction`) are no test: the t of a rounding error is any number (2.9
    for a thrust scale and a payload fitted to the same force, their signals equal to 1e-15)."""
    d = {f: pred_a[f] - pred_b[f] for f in pred_a}
    centred = {f: resid[f] - 0.5 * (pred_a[f] + pred_b[f]) for f in pred_a}
    g = block_sums(flights, d, centred, weights)
    n = len(g)
    if n < MIN_BLOCKS or not np.any(g) or same_prediction(_energy(flights, d) @ weights,
                                                 (_energy(flights, pred_a) + _energy(flights, pred_b)) @ weights):
        return NO_TEST
    sd = float(np.std(g, ddof=1))
    t = float(np.mean(g) / (sd / np.sqrt(n))) if sd > 0 else 0.0
    return HeldOutTest(float(np.mean(g)), t, float(2 * stats.t.sf(abs(t), n - 1)), n)


def compared_weights(flights: Flights, resid: Signals, pred_a: Signals, pred_b: Signals, weights: np.ndarray,
                     at_noise: dict[str, bool]) -> np.ndarray:
    """The channel weights :func:`compare` takes two candidates' held-out predictions in: every
    channel above its sensor-noise floor, and one at its floor (``at_noise``) only where either
    prediction adds error there (``|r - p|² > |r|²`` summed over the held-out flights). In a
    channel at its floor a prediction counts only against a candidate, as in its score
    (:func:`quadcore.identify.diagnosis.scoring`): there the closed loop's errors in variables let
    a thrust scale's torque trims "explain" some gyro noise whichever is true (no evidence for it),
    while its torque on a manoeuvre, which a payload does not make, adds error when the payload is
    the truth (evidence against it).

    The choice is made on the predictions the comparison then tests, not on the training
    flights' (symmetric in the two, so it favours neither). Measured that this does not move it
    (2026-11-26, /work/coord/baseline/fixup_item1/: thrust scale 0.92 or a 3 g payload, three
    hovers, yaw0, circle0 or figure8 flights of 6-8 s, two seeds each, no model; per fold the
    choice made from each candidate fitted on and predicting the training flights): the same
    channels in all 48 folds; where torque was at its floor it was either out on both sides (hover:
    neither adds error) or in by far (payload true: the thrust scale's torque adds 0.40-0.44x
    (figure8), 41-45x (yaw0), 223-240x (circle0) the residual's energy there, held out and in
    training alike)."""
    quiet = [ch for ch, at in at_noise.items() if at]
    mask = channel_mask([ch for ch, at in at_noise.items() if not at])
    if quiet:
        before = _energy(flights, resid)
        added = [_energy(flights, {f: resid[f] - p[f] for f in resid}) - before for p in (pred_a, pred_b)]
        for ch in quiet:
            sl = CHANNELS[ch]
            if max(float(x[sl] @ weights[sl]) for x in added) > 0:
                mask[sl] = 1.0
    return weights * mask


def _energy(flights: Flights, signal: Signals) -> np.ndarray:
    """(6,) the signal's sum of squares per channel over the flights (their totals, no blocks read)."""
    return sum((fd.sum_of_squares(signal[fd.flight]) for fd in flights), np.zeros(6))


def same_prediction(diff_ss: float, total_ss: float) -> bool:
    """Two predictions whose difference's weighted sum of squares ``diff_ss`` is within
    ``SAME_TO_ROUNDING`` of theirs (``total_ss``) are the same signal, written differently (a
    thrust scale's coordinates and a payload's on the same thrust)."""
    return diff_ss <= SAME_TO_ROUNDING * total_ss


def critical_t(blocks: int, n_candidates: int = 1, alpha: float = ALPHA) -> float:
    return float(stats.t.isf(alpha_each(n_candidates, alpha), max(blocks - 1, 1)))


def alpha_each(n_candidates: int, alpha: float = ALPHA) -> float:
    """Per-candidate level of the held-out test: ``alpha`` for the whole library (Bonferroni)."""
    return alpha / max(n_candidates, 1)


@dataclass(frozen=True)
class LimitAsk:
    """One parameter's detection limit to find: its unit wrench (flight -> (n, 6), or signal
    vectors on statistics) and the share of the channel's residual plus ``base_ss`` (the energy
    of a reference effect it rides on) the injected part must also reach."""

    unit: Signals
    min_share: float = 0.0
    base_ss: float = 0.0


def detection_limits(flights: Flights, resid: Signals, asks: Sequence[LimitAsk], floor_ss: np.ndarray,
                     n_candidates: int = 1, settings: DiagnosisSettings = DEFAULT) -> list[float]:
    """Per ask: the smallest |deviation| of a parameter with its unit wrench that the test, the
    fit's significance and the noise floor all let through (see the module); inf if none. On
    statistics, every ask's sums come from one read of each flight's Gram matrices."""
    pairs = [pair for a in asks for pair in ((a.unit, resid), (a.unit, a.unit))]
    *sums, rr_c = block_channel_sums(flights, [*pairs, (resid, resid)])
    n = sum(fd.n for fd in flights)
    return [_limit(sums[2 * k], sums[2 * k + 1], rr_c, n, floor_ss, n_candidates, a, settings)
            for k, a in enumerate(asks)]


def _limit(ur_c: np.ndarray, uu_c: np.ndarray, rr_c: np.ndarray, n: int, floor_ss: np.ndarray,
           n_candidates: int, ask: LimitAsk, settings: DiagnosisSettings) -> float:
    """:func:`detection_limits` of one ask from its per-block, per-channel sums (unit·residual,
    unit·unit, residual·residual); each channel's sums are these weighted by its mask."""
    z_power = float(stats.norm.isf(1 - settings.power))
    best = np.inf
    for ch in CHANNELS:
        w = channel_mask([ch])
        ur, uu = ur_c @ w, uu_c @ w
        S = float(uu.sum())
        if S <= 0 or len(ur) < 3:
            continue
        # the effect may already be in the residual: its own share is no noise to it
        beta = float(ur.sum()) / S
        R = float((rr_c @ w).sum())
        F = float(floor_ss[CHANNELS[ch]].sum())
        Q = len(ur) / (len(ur) - 1) * float(np.sum((ur - beta * uu) ** 2))
        v_test = (critical_t(len(ur), n_candidates, settings.alpha) + z_power) * np.sqrt(Q) / S
        ms = max(R - beta**2 * S, 0.0) / (3 * n)
        v_sigma = (settings.min_sigma + z_power) * np.sqrt(ms * flightdata.SAMPLES_PER_INDEPENDENT / S)
        v_floor = np.sqrt(max(0.0, (1 + settings.noise_margin) ** 2 * F - R) / S)
        v_share = np.sqrt(ask.min_share * (R + ask.base_ss) / S)
        best = min(best, max(v_test, v_sigma, v_floor, v_share))
    return float(best)


def at_noise_level(resid_ss: np.ndarray, floor_ss: np.ndarray, margin: float = NOISE_MARGIN) -> dict[str, bool]:
    """Per channel: is the residual (sum of squares per axis) within ``margin`` (RMS) of its floor?"""
    return {ch: bool(resid_ss[sl].sum() <= (1 + margin) ** 2 * floor_ss[sl].sum())
            for ch, sl in CHANNELS.items()}
