"""Where the model fails, and which physical effect is missing.

1. **Where it fails.** The residual of the model on the evaluated flights, broken down by
   flight regime (speed, height, thrust-to-weight, angular rate, battery voltage,
   acceleration, flight phase) and by flight, with the worst segments in time.

2. **What is missing.** Every effect of the library that is not yet in the model (built-in
   or plugin) is fitted on the training flights' residuals -- force and torque together,
   each weighted by the inverse of its mean square (:mod:`quadcore.fitting`) -- and scored
   on flights it never saw: either the held-out flights, or, with no holdout, a
   cross-validation over flights (the model's own effects are refitted inside each fold
   too). Per channel, the *explained variance* is the fraction of the held-out residual
   (sum over the three axes) it removes; a candidate's ``score`` is the mean over force and
   torque, so an effect that acts in both channels must explain both, and a candidate that
   adds error in a channel is penalised there. The reported parameters are those fitted on
   all training flights, with standard errors.

3. **What counts as evidence.**

   * *Sensor noise.* The white-noise floor of each residual channel is measured on the
     flights themselves (:func:`quadcore.fitting.sensor_noise_floor`). A channel whose
     held-out residual is within ``NOISE_LEVEL`` (RMS) of its floor holds no evidence FOR
     any effect: its explained variance is clipped to ``<= 0`` (it still counts AGAINST a
     candidate that would add error there). This is not cosmetic: the controller closes
     its loop on the same noisy gyro that the torque residual is computed from, so the
     commanded rotor torques correlate with the gyro noise in the "measured" torque (errors
     in variables). A thrust scale or a motor lag then "explains" a third of pure noise,
     even on held-out flights. With the clip, a hover flight does not invent a motor lag.
   * *Significance.* A fit whose parameters are all within ``MIN_SIGMA`` standard errors of
     "no effect" is flagged insignificant (noise fitted to noise).
   * *Physical values.* A fit outside the parameters' physical bounds (negative drag, a
     negative payload, less thrust near the ground) is not an explanation.
   A candidate is ``useful`` when it is physical, significant and removes at least
   ``MIN_EXPLAINED`` of its target residual. Candidates are ranked in tiers (physical and
   significant; physical; unphysical), by score within a tier.

4. **Honesty: explanations the data cannot tell apart.** Two candidates are *alike in a
   channel* when each can reproduce the other's held-out prediction there (at least
   ``1 - SAME_SIGNATURE`` of its energy) with physical parameter values -- a projection
   onto the other's basis, independent of how large either fit came out (so a thrust scale
   that the torque pulled to zero still shows that its force signature is a payload's).
   ``indistinguishable_from`` lists the candidates alike to this one in the channel it
   explains (its ``target``). If their scores are within ``TIE_MARGIN`` nothing else
   separates them: they are ``tied_with`` each other, the one with fewer parameters ranks
   first (parsimony; then the higher score), and the verdict says the data cannot choose.
   Otherwise the other channel separates them (``separated_by``) and the verdict says how.
   The physics behind the two pairs that matter:

   * **thrust_scale vs added_mass.** Less thrust than mapped (``s < 1``) and an unmodelled
     payload give the same force residual, ``-c T`` along body z with ``c = 1 - s =
     m_p / (m + m_p)``: in force they are one effect. Only the torque can tell them apart: a
     thrust-map error scales every rotor's thrust and hence the roll, pitch and yaw torques
     the model computes from them; a payload at the centre of mass changes no torque (its
     inertia is not modelled; a payload off the centre of mass is ``com_offset``). So when
     the torque residual is above the noise and the thrust scale explains it, thrust_scale
     ranks first; when a thrust scale large enough for the force would add a torque error
     that the gyros do not see, added_mass ranks first; and in hover, where the rotor
     torques are mere trims and 8 % of them is below the gyro-derivative noise, the two are
     a tie and the verdict says so (which one is listed first is then immaterial).
   * **rotor_drag vs wind.** A wind effect with ``w = 0`` *is* rotor drag with
     ``k_x = k_y``. When the fitted air speed is nil the two tie and rotor drag, with fewer
     parameters, ranks first: nothing in the data asks for a wind. A real wind is a force
     that does not vanish at zero ground speed and turns with the heading; rotor drag
     cannot reproduce it, and the wind ranks first by a wide margin.

5. **Beyond the best one.** For every other candidate, ``explained_after_top`` is the share
   of the baseline residual it can still remove once the best candidate's held-out
   prediction is subtracted (least squares on the evaluated flights: a screening number).
   The verdict lists those above ``MIN_EXPLAINED`` as "also missing" (e.g. a CoM offset
   found beside rotor drag) and the others as alternatives to the best one, not additions.
   When the best candidate explains nothing, or the residual is at the noise level, the
   verdict is that no effect of the library explains what is left.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from quadcore import effects as effectlib, fitting, rotations, signals, spectrum
from quadcore.dynamics import GRAVITY_W_MPS2, XYZ
from quadcore.fitting import FlightData
from quadcore.model import EffectTerm, ModelSpec, PhysicsModel

MIN_EXPLAINED = 0.05  # below this fraction of its target residual, a candidate explains nothing
MIN_SIGMA = 3.0  # a fit within this many standard errors of 'no effect' is not significant
SAME_SIGNATURE = 0.1  # share of one prediction another candidate cannot reproduce, below which they are alike
TIE_MARGIN = 0.02  # score difference within which two alike candidates are a tie (parsimony decides)
GRAM_STRIDE = 4  # sample thinning for the signature comparisons (see _SpanOverlap)
NOISE_LEVEL = 2.0  # a channel whose residual RMS is within this factor of the sensor-noise floor holds no evidence

SPEED_BINS = [0.0, 0.25, 0.5, 1.0, 1.5]
HEIGHT_BINS = [-np.inf, 0.1, 0.3, 0.6, 1.0]
THRUST_BINS = [0.0, 0.8, 0.95, 1.05, 1.2]
RATE_BINS = [0.0, 0.5, 1.0, 2.0, 4.0]
VBAT_BINS = [0.0, 3.5, 3.7, 3.9]
ACCEL_BINS = [0.0, 0.5, 1.0, 2.0, 4.0]


@dataclass
class RegimeColumns:
    """Per-sample regime variables of one flight."""

    speed_mps: np.ndarray
    height_m: np.ndarray
    thrust_to_weight: np.ndarray
    angular_rate_radps: np.ndarray
    vbat_V: np.ndarray
    acceleration_mps2: np.ndarray
    phase: np.ndarray


def regime_columns(fd: FlightData, vehicle) -> RegimeColumns:
    s = fd.state
    sf_w = rotations.body_to_world(s.R_wb, signals.smooth(s.sf_b_mps2))
    a_w = GRAVITY_W_MPS2 + sf_w  # kinematic acceleration, from the smoothed accelerometer
    speed = np.linalg.norm(s.v_w_mps, axis=1)
    vz = s.v_w_mps[:, 2]
    tw = s.f_rotor_N.sum(axis=1) / vehicle.weight_N
    phase = np.where(
        tw < 0.5, "ground",
        np.where(vz > 0.2, "climb", np.where(vz < -0.2, "descent", np.where(speed < 0.1, "hover", "cruise"))),
    )
    return RegimeColumns(speed, s.p_w_m[:, 2], tw, np.linalg.norm(s.omega_b_radps, axis=1), s.vbat_V,
                         np.linalg.norm(a_w, axis=1), phase)


def bin_labels(edges: list[float], unit: str = "") -> list[str]:
    """The label of each bin: ``<e1``, ``e1-e2``, ..., ``ek+`` (edges ascending, first may be -inf)."""
    labels = []
    for i, lo in enumerate(edges):
        if i + 1 == len(edges):
            labels.append(f"{lo:g}+ {unit}")
        elif np.isinf(lo):
            labels.append(f"<{edges[i + 1]:g} {unit}")
        else:
            labels.append(f"{lo:g}-{edges[i + 1]:g} {unit}")
    return [label.strip() for label in labels]


def _bin_labels(x: np.ndarray, edges: list[float], unit: str) -> np.ndarray:
    """Label each value with its bin (see :func:`bin_labels`)."""
    idx = np.searchsorted(np.asarray(edges[1:]), x, side="right")
    return np.asarray(bin_labels(edges, unit))[idx]


def long_table(flights: list[FlightData], resid: dict[str, np.ndarray], vehicle) -> pl.DataFrame:
    """One row per usable sample of the evaluated flights: regime labels and the residual."""
    frames = []
    for fd in flights:
        r = resid[fd.flight]
        rc = regime_columns(fd, vehicle)
        m = fd.mask
        frame = {
            "flight": np.full(m.sum(), fd.flight),
            "t_s": fd.state.t_s[m],
            "speed": _bin_labels(rc.speed_mps[m], SPEED_BINS, "m/s"),
            "height": _bin_labels(rc.height_m[m], HEIGHT_BINS, "m"),
            "thrust_to_weight": _bin_labels(rc.thrust_to_weight[m], THRUST_BINS, ""),
            "angular_rate": _bin_labels(rc.angular_rate_radps[m], RATE_BINS, "rad/s"),
            "battery": _bin_labels(rc.vbat_V[m], VBAT_BINS, "V"),
            "acceleration": _bin_labels(rc.acceleration_mps2[m], ACCEL_BINS, "m/s^2"),
            "phase": rc.phase[m],
        }
        for j, a in enumerate(XYZ):
            frame[f"f_res_b_{a}_N"] = r[m, j]
            frame[f"tau_res_b_{a}_Nm"] = r[m, 3 + j]
        frames.append(pl.DataFrame(frame))
    return pl.concat(frames)


REGIMES = ("speed", "height", "thrust_to_weight", "angular_rate", "battery", "acceleration", "phase")
RMSE_EXPRS = [
    *[(pl.col(f"f_res_b_{a}_N") ** 2).mean().sqrt().alias(f"force_rmse_{a}_N") for a in XYZ],
    *[(pl.col(f"tau_res_b_{a}_Nm") ** 2).mean().sqrt().alias(f"torque_rmse_{a}_Nm") for a in XYZ],
]


def regime_table(long: pl.DataFrame) -> pl.DataFrame:
    """Residual RMSE per axis in every bin of every regime variable, and the share of samples."""
    frames = []
    for regime in REGIMES:
        g = long.group_by(regime).agg(pl.len().alias("samples"), *RMSE_EXPRS).rename({regime: "bin"})
        frames.append(g.with_columns(pl.lit(regime).alias("regime")).sort("bin"))
    out = pl.concat(frames).select("regime", "bin", "samples", pl.exclude("regime", "bin", "samples"))
    return out.with_columns((pl.col("samples") / long.height).alias("share"))


def flight_table(long: pl.DataFrame) -> pl.DataFrame:
    return long.group_by("flight").agg(pl.len().alias("samples"), *RMSE_EXPRS).sort("flight")


def worst_segments(long: pl.DataFrame, window_s: float = 0.5, top: int = 10) -> pl.DataFrame:
    """The ``top`` windows (non-overlapping, per flight) with the largest force-residual RMS."""
    force_sq = functools.reduce(operator.add, [pl.col(f"f_res_b_{a}_N") ** 2 for a in XYZ])
    seg = (
        long.with_columns((pl.col("t_s") // window_s).alias("segment"), force_sq.alias("f2"))
        .group_by("flight", "segment")
        .agg(
            pl.col("t_s").min().alias("t_start_s"),
            pl.col("t_s").max().alias("t_end_s"),
            pl.col("f2").mean().sqrt().alias("force_rms_N"),
            pl.col("phase").mode().first().alias("phase"),
            pl.col("speed").mode().first().alias("speed"),
            pl.col("height").mode().first().alias("height"),
        )
        .sort("force_rms_N", descending=True)
        .head(top)
        .drop("segment")
    )
    return seg


def _total(parts: Iterable[np.ndarray]) -> np.ndarray:
    """Element-wise sum of per-flight arrays (the same additions, in the same order, as ``sum``)."""
    return functools.reduce(np.add, parts)


def _ss(resid: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sum of squares per channel (6,) on usable samples."""
    return (resid[mask] ** 2).sum(axis=0)


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


def diagnose(
    decoded: dict[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    candidates: list[str] | None = None,
    n_folds: int = 5,
    log=lambda msg: None,
) -> dict:
    """Fit the model, score it on held-out flights, rank the missing effects. JSON-ready dict."""
    vehicle = spec.vehicle
    ids = sorted(decoded)
    fds = {fid: fitting.flight_data(fid, decoded[fid], vehicle) for fid in ids}
    targets = dict(zip(ids, fitting.targets_of([fds[f] for f in ids])))
    model_effects = [effectlib.get(n) for n in spec.effects]
    names = candidates if candidates is not None else [n for n in effectlib.registry() if n not in spec.effects]
    cands = [effectlib.get(n) for n in names]

    holdout = [h for h in (holdout or [])]
    if holdout:
        train_all = [f for f in ids if f not in holdout]
        splits = [(train_all, holdout)]
        mode = "holdout"
    else:
        train_all = ids
        splits = ([([f for f in ids if f not in fold], fold) for fold in fitting.folds(ids, n_folds)]
                  if len(ids) > 1 else [(ids, ids)])
        mode = "cross-validation" if len(ids) > 1 else "in-sample (one flight only)"

    eval_resid: dict[str, np.ndarray] = {}
    cand_pred: dict[str, dict[str, np.ndarray]] = {c.name: {} for c in cands}
    fold_fits: dict[str, fitting.Fit] = {}
    fold_params: dict[str, list[dict]] = {c.name: [] for c in cands}  # per fold: the flight-to-flight spread
    for k, (train, test) in enumerate(splits, 1):
        log(f"fold {k}/{len(splits)}: fitting on {len(train)} flights, scoring {len(test)}")
        tr = [fds[f] for f in train]
        fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train], vehicle, spec.fixed)
        resid = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in {*train, *test}}
        for c in cands:
            fit_c = fold_fits[c.name] = fitting.fit_effects([c], tr, [resid[f] for f in train], vehicle)
            fold_params[c.name].append(fit_c.params[c.name])
            for f in test:
                cand_pred[c.name][f] = fit_c.predict([c], fds[f], vehicle)
        for f in test:
            eval_resid[f] = resid[f]
    # With a single split on all training flights (holdout), its fits are the final ones.
    reuse = len(splits) == 1 and splits[0][0] == train_all

    # Parameters reported: fitted on all training flights.
    tr = [fds[f] for f in train_all]
    if not reuse:
        fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train_all], vehicle, spec.fixed)
    model = PhysicsModel(vehicle, [EffectTerm(e.name, fit_m.params[e.name], fit_m.std[e.name], e.name in spec.fixed)
                                   for e in model_effects])
    resid_train = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in train_all}
    if reuse and len(train_all) >= 3:
        # one split only: refit each candidate leaving out groups of training flights, for the spread
        for group in fitting.folds(train_all, n_folds):
            sub = [f for f in train_all if f not in group]
            for c in cands:
                fit_g = fitting.fit_effects([c], [fds[f] for f in sub], [resid_train[f] for f in sub], vehicle)
                fold_params[c.name].append(fit_g.params[c.name])
        fold_params = {k: v[1:] for k, v in fold_params.items()}  # drop the all-training fit

    eval_ids = sorted(eval_resid)
    before = _total(_ss(eval_resid[f], fds[f].mask) for f in eval_ids)
    n_eval = sum(int(fds[f].mask.sum()) for f in eval_ids)
    baseline = {
        "force_rmse_N": [float(np.sqrt(before[j] / n_eval)) for j in range(3)],
        "torque_rmse_Nm": [float(np.sqrt(before[3 + j] / n_eval)) for j in range(3)],
    }

    # The sensor-noise floor: a channel whose residual is within NOISE_LEVEL of it holds no
    # evidence FOR an effect (only against one that would add error there).
    noise_ss = _total(fds[f].noise ** 2 * int(fds[f].mask.sum()) for f in eval_ids)
    at_noise = {ch: bool(before[sl].sum() <= NOISE_LEVEL**2 * noise_ss[sl].sum()) for ch, sl in TARGET_CHANNELS.items()}

    rows: list[dict[str, Any]] = []
    w = fitting.channel_weights([eval_resid[f][fds[f].mask] for f in eval_ids])
    for c in cands:
        after = _total(_ss(eval_resid[f] - cand_pred[c.name][f], fds[f].mask) for f in eval_ids)
        raw = {ch: _ev(before, after, sl) for ch, sl in TARGET_CHANNELS.items()}
        ev_f, ev_t = (min(raw[ch], 0.0) if at_noise[ch] else raw[ch] for ch in ("force", "torque"))
        target = c.target if c.target != "both" else ("force" if ev_f >= ev_t else "torque")
        fit_c = (fold_fits[c.name] if reuse
                 else fitting.fit_effects([c], tr, [resid_train[f] for f in train_all], vehicle))
        params = fit_c.params[c.name]
        spread = _jackknife_std(fold_params[c.name])
        # the larger of the sample-based error and the spread between groups of flights: flights
        # differ (battery, propellers, a stuck log variable) more than samples within a flight do
        std = {k: max(v, spread.get(k, 0.0)) for k, v in fit_c.std[c.name].items()}
        bounds = {p.name: (p.lower, p.upper) for p in c.parameters}
        outside = [k for k, v in params.items() if not bounds[k][0] <= v <= bounds[k][1]]
        at_bound = [k for k, v in params.items()
                    if k not in outside
                    and min(abs(v - bounds[k][0]), abs(v - bounds[k][1])) < 1e-6 * (bounds[k][1] - bounds[k][0])
                    and v != c.defaults()[k]]
        sigma = _significance(c, params, std)
        notes = ([f"fitted {', '.join(outside)} outside the physical bounds: not a physical explanation"]
                 if outside else [])
        notes += [f"{', '.join(at_bound)} at the bound of its range"] if at_bound else []
        if sigma < MIN_SIGMA:
            notes.append(f"not significant: the fit is only {sigma:.1f} standard errors from 'no effect'")
        rows.append({
            "effect": c.name,
            "target": target,
            "acts_on": c.target,
            "explained_variance": max(0.0, ev_f if target == "force" else ev_t),
            "explained_variance_force": ev_f,
            "explained_variance_torque": ev_t,
            "explained_variance_raw": raw,
            "score": 0.5 * (ev_f + ev_t),
            "force_rmse_N": [float(np.sqrt(after[j] / n_eval)) for j in range(3)],
            "torque_rmse_Nm": [float(np.sqrt(after[3 + j] / n_eval)) for j in range(3)],
            "parameters": params,
            "parameter_spread_between_flights": spread,
            "parameter_std": std,
            "n_parameters": len(c.parameters),
            "explained_variance_per_axis": {
                f"{q}_{a}": float(1 - after[i] / before[i]) if before[i] > 0 else 0.0
                for i, (q, a) in enumerate([("force", a) for a in XYZ] + [("torque", a) for a in XYZ])
            },
            "physical": not outside,
            "significance_sigma": sigma,
            "significant": sigma >= MIN_SIGMA,
            "notes": notes,
        })
    for r in rows:
        r["useful"] = r["physical"] and r["significant"] and r["explained_variance"] >= MIN_EXPLAINED

    # Which candidates leave the same signature on the evaluated flights?
    span = _SpanOverlap(cands, cand_pred, [fds[f] for f in eval_ids], eval_resid, w, vehicle)
    by_name = {r["effect"]: r for r in rows}
    effect_of = {c.name: c for c in cands}

    def can_mimic(a: str, b: str, ch: str) -> bool:
        """``b``, with physical parameter values, reproduces ``a``'s held-out prediction in ``ch``."""
        r2, beta = span.mimic(a, b, ch)
        if r2 < 1 - SAME_SIGNATURE:
            return False
        e = effect_of[b]
        if not e.linear:  # only its own fitted prediction is known to be physical
            return 0.5 <= float(beta[0]) <= 2.0
        params = e.from_linear(beta, vehicle)
        return all(p.lower <= params[p.name] <= p.upper for p in e.parameters)

    for r in rows:
        ch = r["target"]
        alike = []
        for o in rows:
            if o is r or not o["physical"] or _ev_on(o, ch) < MIN_EXPLAINED and _ev_on(r, ch) < MIN_EXPLAINED:
                continue
            if can_mimic(r["effect"], o["effect"], ch) and can_mimic(o["effect"], r["effect"], ch):
                alike.append(o["effect"])
        r["indistinguishable_from"] = alike
        r["tied_with"] = [o for o in alike if abs(by_name[o]["score"] - r["score"]) < TIE_MARGIN]
        # what separates alike candidates: the other channel when either acts there (for an
        # effect acting in both, through its joint fit), otherwise how well each fits this one
        r["separated_by"] = {o: _other(ch) if "both" in (r["acts_on"], by_name[o]["acts_on"]) else ch
                             for o in alike if o not in r["tied_with"]}
    for r in rows:  # a tie goes both ways
        for o in r["tied_with"]:
            if r["effect"] not in by_name[o]["tied_with"]:
                by_name[o]["tied_with"].append(r["effect"])
                by_name[o]["separated_by"].pop(r["effect"], None)
    rows = _rank(rows)
    for r in rows:  # what each could still explain once the best one is in the model
        r["explained_after_top"] = (r["explained_variance"] if r is rows[0] or at_noise[r["target"]]
                                    else span.left_after(r["effect"], rows[0]["effect"], r["target"]))

    long = long_table([fds[f] for f in eval_ids], eval_resid, vehicle)
    return {
        "effects_in_model": spec.effects,
        "model": model.to_dict(),
        "evaluation": {"mode": mode, "folds": len(splits), "train_flights": train_all, "eval_flights": eval_ids,
                       "samples": n_eval},
        "baseline": baseline,
        "noise_floor": {
            "force_rmse_N": [float(np.sqrt(noise_ss[j] / n_eval)) for j in range(3)],
            "torque_rmse_Nm": [float(np.sqrt(noise_ss[3 + j] / n_eval)) for j in range(3)],
        },
        "at_noise_level": at_noise,
        "candidates": rows,
        "verdict": verdict(rows, at_noise),
        "regimes": regime_table(long).to_dicts(),
        "flights": flight_table(long).to_dicts(),
        "worst_segments": worst_segments(long).to_dicts(),
        "frequency": spectrum.frequency_view([fds[f] for f in eval_ids], eval_resid, vehicle),
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


def _ev_on(row: dict, channel: str) -> float:
    return row["explained_variance_force"] if channel == "force" else row["explained_variance_torque"]


def _other(channel: str) -> str:
    return "torque" if channel == "force" else "force"


class _SpanOverlap:
    """Signatures compared on the evaluated flights, accumulated flight by flight as Gram
    matrices of ``[residual | held-out predictions | bases]`` per channel (no big arrays).

    * :meth:`r2`: how well one candidate's held-out prediction can be reproduced by another
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
            # every GRAM_STRIDE-th usable sample: the signals are smoothed over a 31-sample
            # window, so the thinned sums give the same energy ratios at a fraction of the cost
            m = np.flatnonzero(fd.mask)[::GRAM_STRIDE]
            blocks = [resid[fd.flight][m][:, :, None]] + [cand_pred[c.name][fd.flight][m][:, :, None] for c in cands]
            for c in cands:
                blocks.append(fd.basis(c, vehicle)[m] if c.linear else cand_pred[c.name][fd.flight][m][:, :, None])
            Z = np.concatenate(blocks, axis=2) * sw[None, :, None]  # (m, 6, k)
            for ch, sl in TARGET_CHANNELS.items():
                self.gram[ch] += np.einsum("nci,ncj->ij", Z[:, sl, :], Z[:, sl, :])

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

    def r2(self, a: str, b: str, channel: str | None) -> float:
        return self.mimic(a, b, channel)[0]

    def left_after(self, b: str, top: str, channel: str) -> float:
        """Share of the baseline ``channel`` residual that ``b`` removes from what ``top``
        leaves."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[0], y[1 + self.names.index(top)] = 1.0, -1.0
        base = G[0, 0]
        return float(np.clip(self._gain(G, y, b) / base, 0.0, 1.0)) if base > 0 else 0.0


def _tier(r: dict) -> int:
    """0: a physical, significant fit; 1: physical but within noise of 'no effect'; 2: unphysical."""
    return 0 if r["physical"] and r["significant"] else (1 if r["physical"] else 2)


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


def _one_per_tie(rows: list[dict]) -> list[dict]:
    """The first of each group of candidates the data cannot tell apart (rows best first)."""
    out, seen = [], set()
    for r in rows:
        if r["effect"] not in seen:
            out.append(r)
        seen |= {r["effect"], *r.get("tied_with", [])}
    return out


def _pct(x: float) -> str:
    return f"{max(x, 0.0):.0%}"


def verdict(rows: list[dict], at_noise: dict[str, bool] | None = None) -> str:
    """One paragraph a person reads first."""
    useful = [r for r in rows if r.get("useful", r["physical"] and r["explained_variance"] >= MIN_EXPLAINED)]
    if at_noise and all(at_noise.values()):
        return ("No effect of the library explains the residual on held-out flights: it is at the sensor-noise "
                "level in force and in torque; there is nothing left to explain.")
    if not useful:
        best = rows[0] if rows else None
        tail = ""
        if best:
            why = "" if best.get("significant", True) else ", within noise of no effect"
            tail = f" (best: {best['effect']}, {best['explained_variance']:.0%}{why})"
        return ("No effect of the library explains the residual on held-out flights" + tail +
                ": what is left is noise, or a physical effect outside the library.")
    top = useful[0]
    by_name = {r["effect"]: r for r in rows}
    params = ", ".join(
        f"{k} = {v:.4g} ± {top['parameter_std'].get(k, float('nan')):.2g}" for k, v in top["parameters"].items()
    )
    ch, other = top["target"], _other(top["target"])
    text = (f"Most likely missing: {top['effect']}: it removes {top['explained_variance']:.0%} of the held-out "
            f"{ch} residual")
    if top["acts_on"] == "both" and _ev_on(top, other) >= MIN_EXPLAINED:
        text += f" and {_ev_on(top, other):.0%} of the {other} residual"
    text += f" ({params})."
    if top["notes"]:
        text += " Note: " + "; ".join(top["notes"]) + "."
    tied = top.get("tied_with", [])
    if tied:
        fewer = all(by_name[o]["n_parameters"] > top["n_parameters"] for o in tied if o in by_name)
        text += (f" This data cannot tell it apart from {', '.join(tied)}: they explain the held-out residual equally "
                 f"well, with nearly the same predictions wherever the residual is above the sensor noise; it is "
                 f"ranked first "
                 + ("because it needs fewer parameters" if fewer else "by a margin within noise")
                 + ". Flights that separate them are needed (or knowledge of the vehicle) before choosing.")
    for o, by in top.get("separated_by", {}).items():
        r = by_name.get(o)
        if r is None:
            continue
        if by == ch:
            text += (f" Its {ch} signature resembles that of {o}, which explains less of it "
                     f"({_pct(_ev_on(r, ch))} against {_pct(_ev_on(top, ch))}).")
            continue
        text += f" In {ch} alone it is indistinguishable from {o}; the {by} residual tells them apart: "
        if _ev_on(top, by) >= MIN_EXPLAINED and _ev_on(top, by) - _ev_on(r, by) >= TIE_MARGIN:
            text += (f"{top['effect']} also removes {_pct(_ev_on(top, by))} of the held-out {by} residual, "
                     f"{o} {_pct(_ev_on(r, by))}.")
        else:
            text += (f"{o} cannot explain the {ch} residual without an error in {by} that is not there "
                     f"(fitted to both, it removes only {_pct(_ev_on(r, ch))} of the {ch} residual).")
    alike = set(top.get("indistinguishable_from", [])) | set(tied)
    others = [r for r in useful[1:] if r["effect"] not in alike]
    independent = _one_per_tie([r for r in others if r.get("explained_after_top", 0.0) >= MIN_EXPLAINED])
    overlapping = [r for r in others if r.get("explained_after_top", 0.0) < MIN_EXPLAINED]
    if independent:
        text += (" Also missing, beyond it: "
                 + ", ".join(f"{r['effect']} (removes {r['explained_after_top']:.0%} of the {r['target']} residual "
                             f"on top of {top['effect']}, {r['explained_variance']:.0%} alone"
                             + (f"; indistinguishable from {', '.join(r['tied_with'])}" if r.get("tied_with") else "")
                             + ")" for r in independent[:3]) + ".")
    if overlapping:
        text += (f" Explaining the same residual as {top['effect']} (alternatives, nothing left for them once it is "
                 "in the model): "
                 + ", ".join(f"{r['effect']} ({r['explained_variance']:.0%})" for r in overlapping[:3])
                 + ".")
    return text
