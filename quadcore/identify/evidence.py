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

**Where the flights disagree.** Blocks of one flight share what sets it apart (its battery,
its propellers, what the model leaves out of its manoeuvres), so blocks of different flights
may scatter about different slopes. Flights that differ only in how much they show (a hover
against a manoeuvre) leave the answer for these flights as the blocks give it; flights that
differ in its sign make it an answer about which flights were flown, and counting blocks as
independent then overstates it (the 19 real flights: com_offset against rotor_imbalance 5.0 σ by
blocks, with 11 of 19 flights for com_offset and some of each side on their own significant).
Each held-out test (a candidate's slope, and :func:`compare`'s mean score) is therefore checked
the way a meta-analysis checks its studies: per flight ``f`` with at least two blocks its own
slope ``β_f``, variance ``v_f`` (the formula above on its blocks alone) and ``t_f``, and Gail and
Simon's (1985) test of a qualitative interaction (:func:`crossover_p`: do flights disagree in
sign beyond chance?) at ``HETEROGENEITY_ALPHA``. Where they do not, the block test stands as
above. Where they do, the slope ``β̂ = Σ_f D_f β_f / D`` (``D_f`` a flight's ``Σ p·p``, or its
number of blocks for :func:`compare`'s mean; ``D`` their sum) is kept and its variance widened by
DerSimonian and Laird's (1986) between-flight variance ``τ² = max(0, (Q - (k - 1)) / (Σ w_f -
Σ w_f² / Σ w_f))`` (Cochran's ``Q = Σ_f w_f (β_f - β_w)²``, ``w_f = 1/v_f``, ``β_w`` their
weighted mean, on ``k`` such flights), with the flights, not the blocks, as what is counted::

    se² = se_blocks² + τ² Σ_f D_f² / D²,      Student's t with F - 1 degrees of freedom

(``F`` the flights holding blocks). Clustering every test by flight instead would need many
flights to decide anything (a fleet of three or four leaves two or three degrees of freedom
even where its flights agree); this widens only where they disagree in sign.

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
HETEROGENEITY_ALPHA = 0.05  # Gail and Simon's test at which a held-out test's flights disagree in sign (see the module)


@dataclass(frozen=True)
class HeldOutTest:
    """The held-out regression of the residual on a prediction: slope, t and p-value, over
    ``blocks`` blocks; ``flights_disagree``: its flights disagree in sign beyond chance
    (:func:`crossover_p`), so its variance was widened by theirs and its degrees of freedom are
    the flights' (see the module)."""

    beta: float
    t: float
    p_value: float
    blocks: int
    flights_disagree: bool = False

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
    return _block_channel_sums(flights, pairs)[0]


def _block_channel_sums(flights: Flights, pairs: Sequence[tuple[Signals, Signals]]
                        ) -> tuple[list[np.ndarray], np.ndarray]:
    """:func:`block_channel_sums` and, per block, the index of its flight in ``flights``."""
    with flightdata.one_blas_thread():  # G [b, ...] with many columns is a matrix product OpenBLAS would thread
        per_flight = [fd.block_channel_sums(pairs) for fd in flights]
    counts = [len(sums[0]) if sums else 0 for sums in per_flight]
    flight = np.repeat(np.arange(len(per_flight)), counts)
    return [np.concatenate([sums[k] for sums in per_flight]) if per_flight else np.zeros((0, 6))
            for k in range(len(pairs))], flight


def block_sums(flights: Flights, a: Signals, b: Signals, weights: np.ndarray) -> np.ndarray:
    """Per block of every flight: ``Σ_i Σ_c w_c a_ic b_ic`` over its usable samples
    (:func:`block_channel_sums` weighted)."""
    return block_channel_sums(flights, [(a, b)])[0] @ weights


@dataclass(frozen=True)
class BlockSums:
    """A prediction's held-out sums per block (rows) and channel (6 columns): residual·prediction
    ``pr`` and prediction·prediction ``pp``, and per block the index of its flight (``flight``)."""

    pr: np.ndarray
    pp: np.ndarray
    flight: np.ndarray


def held_out_test(flights: Flights, resid: dict[str, np.ndarray], pred: dict[str, np.ndarray],
                  weights: np.ndarray) -> HeldOutTest:
    """Is ``pred`` (n, 6 per flight) confirmed by ``resid`` on these flights? (see the module)"""
    return held_out_test_of(held_out_sums(flights, resid, [pred])[0], weights)


def held_out_sums(flights: Flights, resid: Signals, preds: Sequence[Signals]) -> list[BlockSums]:
    """Per prediction: its :class:`BlockSums` (:func:`block_channel_sums`; on statistics one read
    of the Gram matrices for all of them)."""
    sums, flight = _block_channel_sums(flights, [pair for pred in preds for pair in ((resid, pred), (pred, pred))])
    return [BlockSums(sums[2 * k], sums[2 * k + 1], flight) for k in range(len(preds))]


def held_out_test_of(sums: BlockSums, weights: np.ndarray) -> HeldOutTest:
    """:func:`held_out_test` from a prediction's :func:`held_out_sums`, weighted per channel:
    one-sided (``β > 0``)."""
    return slope_test(sums.pr @ weights, sums.pp @ weights, sums.flight, two_sided=False)


def slope_test(x: np.ndarray, c: np.ndarray, flight: np.ndarray, two_sided: bool) -> HeldOutTest:
    """The ratio ``β̂ = Σ x / Σ c`` of per-block sums ``x`` (residual·prediction, or a comparison's
    score) to ``c`` (prediction·prediction, or 1 for a mean) and its t, with the blocks as
    clusters, widened where the flights disagree about its sign (``flight``: per block the index of
    its flight; see the module). Fewer than ``MIN_BLOCKS`` blocks, or no ``c``, is no test."""
    n, den = len(x), float(c.sum())
    if n < MIN_BLOCKS or den <= 0:
        return NO_TEST
    beta = float(x.sum() / den)
    var = n / (n - 1) * float(np.sum((x - beta * c) ** 2)) / den**2
    dof = n - 1
    tau2 = between_flights_variance(x, c, flight)
    if tau2 is not None:
        var += tau2 * float(np.sum(np.bincount(flight, weights=c) ** 2)) / den**2
        dof = len(np.unique(flight)) - 1
    se = float(np.sqrt(var))
    t = beta / se if se > 0 else (np.inf if beta > 0 else 0.0)
    p = 2 * stats.t.sf(abs(t), dof) if two_sided else stats.t.sf(t, dof)
    return HeldOutTest(beta, float(np.clip(t, -1e6, 1e6)), float(p), n, tau2 is not None)


def between_flights_variance(x: np.ndarray, c: np.ndarray, flight: np.ndarray,
                             alpha: float = HETEROGENEITY_ALPHA) -> float | None:
    """DerSimonian and Laird's variance ``τ²`` of the flights' own ratios ``Σ_f x / Σ_f c`` about
    their common one where the flights disagree about its sign (:func:`crossover_p` below
    ``alpha``); None where they do not, or fewer than two flights hold two blocks and some ``c``
    (see the module)."""
    nf = np.bincount(flight)
    xf, cf = np.bincount(flight, weights=x), np.bincount(flight, weights=c)
    ok = (nf >= 2) & (cf > 0)
    beta_f = np.divide(xf, cf, out=np.zeros_like(xf), where=ok)
    ssf = np.bincount(flight, weights=(x - beta_f[flight] * c) ** 2)
    v = np.divide(nf * ssf, np.maximum(nf - 1, 1) * cf**2, out=np.zeros_like(xf), where=ok)
    ok &= v > 0
    k = int(ok.sum())
    if k < 2 or crossover_p(beta_f[ok] / np.sqrt(v[ok]), nf[ok] - 1) >= alpha:
        return None
    w, b = 1.0 / v[ok], beta_f[ok]
    q = float(np.sum(w * (b - np.sum(w * b) / w.sum()) ** 2))
    return max(0.0, (q - (k - 1)) / float(w.sum() - np.sum(w**2) / w.sum()))


def crossover_p(t: np.ndarray, dof: np.ndarray) -> float:
    """Do ``k`` flights disagree about the sign of what they measure (``t``: each flight's own t,
    on ``dof`` degrees of freedom)? Gail and Simon's (1985) test of a qualitative interaction:
    ``Q+ = Σ_{t_f > 0} z_f²`` and ``Q- = Σ_{t_f < 0} z_f²``, ``m = min(Q+, Q-)``, and
    ``p = Σ_{h=1}^{k-1} C(k-1, h) 2^{1-k} P(χ²_h > m)`` (the least favourable case of no
    disagreement: every flight's true value 0). ``z_f`` is the normal deviate of ``t_f``'s own
    tail probability, so that a flight of a few blocks counts for what its t is worth."""
    k = len(t)
    z = stats.norm.isf(np.maximum(stats.t.sf(np.abs(t), dof), 1e-300))
    m = min(float(np.sum(z[t > 0] ** 2)), float(np.sum(z[t < 0] ** 2)))
    h = np.arange(1, k)
    return float(np.sum(stats.binom.pmf(h, k - 1, 0.5) * stats.chi2.sf(m, h)))


def compare(flights: Flights, resid: dict[str, np.ndarray], pred_a: dict[str, np.ndarray],
            pred_b: dict[str, np.ndarray], weights: np.ndarray) -> HeldOutTest:
    """Does ``pred_a`` fit the held-out ``resid`` better than ``pred_b``? The difference of their
    weighted squared errors, ``|r - b|² - |r - a|² = 2 (a - b)·(r - (a + b)/2)``, summed per
    block; two-sided t-test of its mean (``t > 0``: ``a`` fits better), widened where the flights
    disagree about which fits better (:func:`slope_test` on 1). ``weights``: per channel (6,), or
    per flight and channel (flights, 6; :func:`compared_weights`). Two predictions equal to
    rounding (:func:`same_prediction`) are no test: the t of a rounding error is any number (2.9
    for a thrust scale and a payload fitted to the same force, their signals equal to 1e-15)."""
    w = np.broadcast_to(weights, (len(flights), 6))
    d = {f: pred_a[f] - pred_b[f] for f in pred_a}
    centred = {f: resid[f] - 0.5 * (pred_a[f] + pred_b[f]) for f in pred_a}
    (g_c,), flight = _block_channel_sums(flights, [(d, centred)])
    g = np.einsum("bc,bc->b", g_c, w[flight])
    diff_ss, a_ss, b_ss = (float(np.sum(_energies(flights, s) * w)) for s in (d, pred_a, pred_b))
    if len(g) < MIN_BLOCKS or not np.any(g) or same_prediction(diff_ss, a_ss + b_ss):
        return NO_TEST
    if np.ptp(g) == 0:  # every block scores the same: no spread to test against
        return HeldOutTest(float(np.mean(g)), 0.0, 1.0, len(g))
    return slope_test(g, np.ones(len(g)), flight, two_sided=True)


def compared_weights(flights: Flights, resid: Signals, pred_a: Signals, pred_b: Signals, weights: np.ndarray,
                     at_noise: dict[str, bool]) -> np.ndarray:
    """The channel weights :func:`compare` takes two candidates' held-out predictions in, per
    flight (flights, 6): every channel above its sensor-noise floor, and one at its floor
    (``at_noise``) only on the flights where either prediction adds error there (``|r - p|² >
    |r|²`` over the flight). In a channel at its floor a prediction counts only against a
    candidate, as in its score (:func:`quadcore.identify.diagnosis.scoring`): there the closed
    loop's errors in variables let a thrust scale's torque trims "explain" some gyro noise
    whichever is true (no evidence for it), while its torque on a manoeuvre, which a payload does
    not make, adds error when the payload is the truth (evidence against it). Per flight, because
    a hover's trims would otherwise count for the thrust scale wherever a manoeuvre's torque
    counts against it (a payload true, three hovers and a planned flight: each hover preferred the
    thrust scale at t -9 to -17 on its own, the planned flight the payload at +5.7).

    The choice is made on the predictions the comparison then tests, not on the training
    flights' (symmetric in the two, so it favours neither). Measured that this does not move it
    (2026-11-26, /work/coord/baseline/fixup_item1/, the choice then summed over the flights:
    thrust scale 0.92 or a 3 g payload, three hovers, yaw0, circle0 or figure8 flights of 6-8 s,
    two seeds each, no model; per fold the choice made from each candidate fitted on and
    predicting the training flights): the same channels in all 48 folds; where torque was at its
    floor it was either out on both sides (hover: neither adds error) or in by far (payload true:
    the thrust scale's torque adds 0.40-0.44x (figure8), 41-45x (yaw0), 223-240x (circle0) the
    residual's energy there, held out and in training alike)."""
    quiet = [ch for ch, at in at_noise.items() if at]
    mask = np.tile(channel_mask([ch for ch, at in at_noise.items() if not at]), (len(flights), 1))
    if quiet:
        before = _energies(flights, resid)
        added = [_energies(flights, {f: resid[f] - p[f] for f in resid}) - before for p in (pred_a, pred_b)]
        for ch in quiet:
            sl = CHANNELS[ch]
            mask[:, sl] = np.maximum.reduce([x[:, sl] @ weights[sl] for x in added])[:, None] > 0
    return weights * mask


def _energies(flights: Flights, signal: Signals) -> np.ndarray:
    """(flights, 6) the signal's sum of squares per flight and channel (their totals, no blocks read)."""
    return np.array([fd.sum_of_squares(signal[fd.flight]) for fd in flights]).reshape(len(flights), 6)


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
