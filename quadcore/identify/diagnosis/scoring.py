"""A candidate's row: its held-out score, parameters and their uncertainty (:func:`_score`), the
decision (:func:`_decide`), the candidates the data cannot tell apart (:func:`_mark_alike`), the
ranking (:func:`_rank`) and what each could still explain beside the best (:func:`_beyond_the_best`).
The thresholds are in :mod:`quadcore.identify.evidence`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadcore.effects import Effect
from quadcore.identify import evidence, rates
from quadcore.identify.diagnosis.problem import (
    TARGET_CHANNELS,
    HeldOut,
    _Problem,
    _total,
)
from quadcore.identify.diagnosis.rows import CandidateRow
from quadcore.identify.diagnosis.sensitivity import detection_limits
from quadcore.identify.diagnosis.span import _SpanOverlap
from quadcore.identify.diagnosis.verdict import _other, rank_reasons
from quadcore.identify.fit import solve
from quadcore.identify.settings import DiagnosisSettings
from quadcore.physics.dynamics import XYZ


def _ev(before: np.ndarray, after: np.ndarray, channels: slice) -> float:
    b = before[channels].sum()
    return float(1.0 - after[channels].sum() / b) if b > 0 else 0.0


def _score(c: Effect, held: HeldOut, fit_c: solve.Fit,
           fold_params: tuple[list[dict[str, float]], list[dict[str, float]]],
           test_sums: evidence.BlockSums, settings: DiagnosisSettings) -> CandidateRow:
    """A candidate's row: what its held-out prediction removes (raw, per channel and axis), the
    channel it explains, its parameters (``fit_c``: on all training flights, within the physical
    bounds) with their uncertainty (``fold_params``: per fold, for the spread, bounded and free)
    and checks, and the held-out test (``test_sums``: its
    :func:`quadcore.identify.evidence.held_out_sums`). A free fit beyond a bound by more than
    ``settings.bound_sigma`` standard errors is unphysical; one within noise of it is judged as fitted
    with the bound active (``active_bounds``)."""
    before, at_noise = held.before, held.at_noise
    after = _total(fd.sum_of_squares(held.resid[f] - held.cand_pred[c.name][f])
                   for f, fd in zip(held.ids, held.flights))
    raw = {ch: _ev(before, after, sl) for ch, sl in TARGET_CHANNELS.items()}
    ev_f, ev_t = (min(raw[ch], 0.0) if at_noise[ch] else raw[ch] for ch in ("force", "torque"))
    target = c.target if c.target != "both" else ("force" if ev_f >= ev_t else "torque")
    params = fit_c.params[c.name]
    spread = solve.jackknife_std(fold_params[0])
    # the larger of the sample-based error and the spread between groups of flights: flights
    # differ (battery, propellers, a stuck log variable) more than samples within a flight do
    std = {k: max(v, spread.get(k, 0.0)) for k, v in fit_c.std[c.name].items()}
    free_spread = solve.jackknife_std(fold_params[1])
    bounds = _bounds(c, fit_c, free_spread, settings.bound_sigma)
    active = fit_c.active.get(c.name, {})
    # a parameter held at its bound: how well the data pin it is its free fit's error and spread
    std.update({k: max(std[k], free_spread.get(k, 0.0)) for k in active})
    sigma = _significance(c, params, std)
    test = evidence.held_out_test_of(test_sums, evidence.channel_mask([target]))
    above_noise, signal_to_noise = _above_noise(before, after, held.noise_ss, target)
    return CandidateRow(
        effect=c.name,
        target=target,
        acts_on=c.target,
        explained_variance=max(0.0, ev_f if target == "force" else ev_t),
        explained_variance_force=ev_f,
        explained_variance_torque=ev_t,
        explained_variance_raw=raw,
        score=0.5 * (ev_f + ev_t),
        force_rmse_N=tuple(float(np.sqrt(after[j] / held.n)) for j in range(3)),
        torque_rmse_Nm=tuple(float(np.sqrt(after[3 + j] / held.n)) for j in range(3)),
        parameters=params,
        parameter_spread_between_flights=spread,
        parameter_std=std,
        n_parameters=len(c.parameters),
        explained_variance_per_axis={
            f"{q}_{a}": float(1 - after[i] / before[i]) if before[i] > 0 else 0.0
            for i, (q, a) in enumerate([("force", a) for a in XYZ] + [("torque", a) for a in XYZ])
        },
        physical=not bounds.unphysical,
        active_bounds=dict(active),
        significance_sigma=sigma,
        significant=sigma >= settings.min_sigma,
        notes=tuple(_parameter_notes(bounds, active, _at_bound(c, params, active), sigma, settings.min_sigma)),
        held_out_level=target,
        held_out_slope=test.beta,
        held_out_t=test.t,
        held_out_p_value=test.p_value,
        held_out_blocks=test.blocks,
        explained_above_noise=above_noise,
        signal_to_noise=signal_to_noise,
    )


def _above_noise(before: np.ndarray, after: np.ndarray, noise_ss: np.ndarray, target: str) -> tuple[float, float]:
    """In a candidate's target channel: the share of the residual *above the noise floor* it
    removes, and the size of what it removes in noise floors (RMS)."""
    sl = TARGET_CHANNELS[target]
    floor = noise_ss[sl].sum()
    removed, excess = before[sl].sum() - after[sl].sum(), before[sl].sum() - floor
    return (float(np.clip(removed / excess, 0.0, 1.0)) if excess > 0 else 0.0,
            float(np.sqrt(max(removed, 0.0) / floor)) if floor > 0 else 0.0)


def _significance(effect: Effect, params: dict[str, float], std: dict[str, float]) -> float:
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


def _at_bound(c: Effect, params: dict[str, float], held: dict[str, float]) -> list[str]:
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
    bound_sigma: float

    @property
    def beyond(self) -> float:
        return max((z for *_, z in self.outside.values()), default=0.0)

    @property
    def unphysical(self) -> bool:
        """Beyond a bound by clearly more than its noise: the data ask for values the effect
        cannot have (``bound_sigma`` standard errors)."""
        return self.beyond > self.bound_sigma


def _bounds(c: Effect, fit_c: solve.Fit, free_spread: dict[str, float], bound_sigma: float) -> _Bounds:
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
    return _Bounds(out, bound_sigma)


def _parameter_notes(bounds: _Bounds, active: dict[str, float], at_bound: list[str], sigma: float,
                     min_sigma: float) -> list[str]:
    def free(k: str) -> str:
        v, s, bound, z = bounds.outside[k]
        return f"{k} = {v:.3g} ± {s:.2g}, {z:.2g} σ beyond its bound {bound:g}"

    if bounds.unphysical:
        notes = [f"fitted outside the physical bounds by more than {bounds.bound_sigma:g} standard errors ("
                 + "; ".join(free(k) for k in bounds.outside) + "): not a physical explanation"]
    elif active:
        beyond = [free(k) for k in active if k in bounds.outside]
        notes = [", ".join(f"{k} held at its bound {v:g}" for k, v in active.items())
                 + (f" (fitted free: {'; '.join(beyond)}, within noise of it)" if beyond else "")]
    else:
        notes = []
    notes += [f"{', '.join(at_bound)} at the bound of its range"] if at_bound else []
    if sigma < min_sigma:
        notes.append(f"{rates.NOT_SIGNIFICANT} the fit is only {sigma:.1f} standard errors from 'no effect'")
    return notes


def _decide(r: CandidateRow, at_noise: dict[str, bool], n_candidates: int, settings: DiagnosisSettings) -> None:
    """``found`` (the JSON's older name ``useful``): physical, its parameters significant,
    confirmed on the held-out flights (:func:`quadcore.identify.evidence.held_out_test`),
    removing some of a target residual that stands above the noise floor. A timing candidate
    decided at the angular-rate level (``r.rate_level``, :func:`quadcore.identify.rates.judge`):
    its held-out test is there, against no timing effect, and not confirmed where the noise model
    or the closed loop decides it; the torque residual's share and floor, which the closed loop
    biases, do not decide it, and one the rate level prefers significantly to a found one counts as
    significant (:func:`quadcore.identify.rates.judgement._better_than_found`). ``grade`` says how
    large it is."""
    r.held_out_alpha = evidence.alpha_each(n_candidates, settings.alpha)
    rate = r.rate_level
    confirmed = r.held_out_p_value < r.held_out_alpha and r.held_out_slope > 0 and not (rate and rate.undecided)
    above_noise = rate is not None or (r.explained_variance > 0 and not at_noise[r.target])
    significant = r.significant or bool(rate and rate.better_than)
    r.found = bool(r.physical and significant and confirmed and above_noise)
    if not r.physical:
        r.grade = "unphysical"
    elif not r.found:
        r.grade = "indistinguishable from noise"
    elif r.signal_to_noise >= settings.large_snr:
        r.grade = "large"
    elif r.signal_to_noise >= 1.0:
        r.grade = "clear"
    else:
        r.grade = "small but certain"


def _mark_alike(rows: list[CandidateRow], span: _SpanOverlap, held: HeldOut, p: _Problem,
                settings: DiagnosisSettings) -> None:
    """Which candidates leave the same signature on the evaluated flights: per row, the physical
    ones that reproduce its prediction in its channel and it theirs (``indistinguishable_from``),
    those of them it ties with (scores within ``tie_margin``, or the held-out flights prefer
    neither; a tie goes both ways), and what separates it from the others (``separated_by``)."""
    def separated(a: str, b: str) -> bool:
        """The held-out flights prefer one of ``a`` and ``b`` significantly (channels above the
        noise, and one at it where either adds error: :func:`quadcore.identify.evidence.compared_weights`)."""
        pa, pb = held.cand_pred[a], held.cand_pred[b]
        w = evidence.compared_weights(held.flights, held.resid, pa, pb, held.w, held.at_noise)
        return evidence.compare(held.flights, held.resid, pa, pb, w).p_value < settings.alpha
    by_name = {r.effect: r for r in rows}

    def can_mimic(a: str, b: str, ch: str) -> bool:
        """``b``, with physical parameter values, reproduces ``a``'s held-out prediction in ``ch``."""
        r2, beta = span.mimic(a, b, ch)
        if r2 < 1 - settings.same_signature:
            return False
        e = p.effect_of[b]
        if not e.linear:  # only its own fitted prediction is known to be physical
            return 0.5 <= float(beta[0]) <= 2.0
        params = e.from_linear(beta, p.vehicle)
        return all(q.lower <= params[q.name] <= q.upper for q in e.parameters)

    for r in rows:
        ch = r.target
        alike = []
        for o in rows:
            if (o is r or not o.physical
                    or o.explained_in(ch) < settings.min_explained and r.explained_in(ch) < settings.min_explained):
                continue
            if can_mimic(r.effect, o.effect, ch) and can_mimic(o.effect, r.effect, ch):
                alike.append(o.effect)
        r.indistinguishable_from = tuple(alike)
        r.tied_with = tuple(o for o in alike
                            if abs(by_name[o].score - r.score) < settings.tie_margin or not separated(r.effect, o))
        # what separates alike candidates: the other channel when either acts there (for an
        # effect acting in both, through its joint fit), otherwise how well each fits this one
        r.separated_by = {o: _other(ch) if "both" in (r.acts_on, by_name[o].acts_on) else ch
                          for o in alike if o not in r.tied_with}
    for r in rows:  # a tie goes both ways
        for name in r.tied_with:
            o = by_name[name]
            if r.effect not in o.tied_with:
                o.tied_with = (*o.tied_with, r.effect)
                o.separated_by = {k: v for k, v in o.separated_by.items() if k != r.effect}


def _beyond_the_best(rows: list[CandidateRow], span: _SpanOverlap, held: HeldOut, p: _Problem,
                     settings: DiagnosisSettings) -> dict[str, dict[str, float | None]]:
    """On the ranked rows: what each could still explain once the best one is in the model
    (``explained_after_top``), why each is ranked where it is, and how small an effect could
    hide in what is left then (``sensitivity``, also returned)."""
    for r in rows:
        r.explained_after_top = (r.explained_variance if r is rows[0] or held.at_noise[r.target]
                                 else span.left_after(r.effect, rows[0].effect, r.target))
        # what it removes alone by the same screen (not its held-out share): the verdict compares the two
        r.explained_alone_screen = (r.explained_variance if r is rows[0] or held.at_noise[r.target]
                                    else span.left_after(r.effect, None, r.target))
    rank_reasons(rows, held.at_noise, settings)
    left = ({f: held.resid[f] - held.cand_pred[rows[0].effect][f] for f in held.ids}
            if rows and rows[0].found else held.resid)
    sensitivity = detection_limits(p.cands, held.flights, left, held.noise_ss, p.vehicle, len(p.cands), settings,
                                   all_at_once=True)  # the flights are statistics
    for r in rows:
        r.sensitivity = sensitivity[r.effect]
    return sensitivity


def _rank(rows: list[CandidateRow]) -> list[CandidateRow]:
    """Best first: by tier, then by score (force and torque explained, averaged); among
    candidates the data cannot tell apart (``tied_with``) the one with fewer parameters
    comes first (parsimony), then the higher score."""
    pending = sorted(rows, key=lambda r: (r.tier(), -r.score))
    ordered = []
    while pending:
        head = pending[0]
        group = [r for r in pending if r is head or (r.effect in head.tied_with and r.tier() == head.tier())]
        best = min(group, key=lambda r: (r.n_parameters, -r.score))
        ordered.append(best)
        pending.remove(best)
    return ordered
