"""Where the model fails, and which physical effect is missing.

1. **Where it fails.** The residual of the model on the evaluated flights, broken down by
   flight regime (speed, height, thrust-to-weight, angular rate, battery voltage,
   acceleration, flight phase) and by flight, with the worst segments in time.

2. **What is missing.** Every effect of the library that is not yet in the model (built-in
   or plugin) is fitted on the training flights' residuals -- force and torque together,
   each weighted by the inverse of its mean square (:mod:`quadcore.identify.fitting`) -- and scored
   on flights it never saw: either the held-out flights, or, with no holdout, a
   cross-validation over flights (the model's own effects are refitted inside each fold
   too). Per channel, the *explained variance* is the fraction of the held-out residual
   (sum over the three axes) it removes; a candidate's ``score`` is the mean over force and
   torque, so an effect that acts in both channels must explain both, and a candidate that
   adds error in a channel is penalised there. The reported parameters are those fitted on
   all training flights, with standard errors.

3. **What counts as evidence** (:mod:`quadcore.identify.evidence`). A candidate is *found*
   (``found``, alias ``useful``) when all of these hold -- whatever its size next to the noise:

   * *Held-out significance.* Its held-out prediction is confirmed by the held-out residual
     of its target channel: a regression of the residual on the prediction with a
     cluster-robust t-test over 1 s blocks, one-sided, at ``ALPHA`` for the whole library
     (Bonferroni over the candidates).
   * *Significant parameters.* A fit whose parameters are all within ``MIN_SIGMA`` standard
     errors of "no effect" is noise fitted to noise.
   * *Physical values.* A fit outside the parameters' physical bounds (negative drag, a
     negative payload, less thrust near the ground) is never an explanation, whatever it
     removes.
   * *Above the sensor noise.* The white-noise floor of each residual channel is measured on
     the flights themselves (:func:`quadcore.identify.fitting.sensor_noise_floor`). A channel whose
     held-out residual is within ``evidence.NOISE_MARGIN`` (RMS) of its floor holds no
     evidence FOR any effect: its explained variance is clipped to ``<= 0`` (it still counts
     AGAINST a candidate that would add error there). The controller closes its loop on the
     same noisy gyro that the torque residual is computed from, so the commanded rotor
     torques correlate with the gyro noise in the "measured" torque (errors in variables): a
     thrust scale or a motor lag "explains", significantly, a third of pure noise even on
     held-out flights. With the clip, a hover flight does not invent a motor lag.

   Beside the raw share of the residual it removes, each candidate states the share of the
   part *above the noise floor* (``explained_above_noise``) and its size in noise floors
   (``signal_to_noise``), graded ``large`` (>= ``LARGE_SNR``), ``clear`` (>= 1) or ``small
   but certain`` (weaker than the sensor noise, yet confirmed). Candidates are ranked in
   tiers (found; physical; unphysical), by score within a tier, and each gets a ``status``
   and a ``reason``: why it is ranked where it is. ``sensitivity`` states, for every
   candidate and parameter, the smallest value these flights would have detected
   (:func:`quadcore.identify.evidence.detection_limit`); every verdict carries it.

4. **Honesty: explanations the data cannot tell apart.** Two candidates are *alike in a
   channel* when each can reproduce the other's held-out prediction there (at least
   ``1 - SAME_SIGNATURE`` of its energy) with physical parameter values -- a projection
   onto the other's basis, independent of how large either fit came out (so a thrust scale
   that the torque pulled to zero still shows that its force signature is a payload's).
   ``indistinguishable_from`` lists the candidates alike to this one in the channel it
   explains (its ``target``). If their scores are within ``TIE_MARGIN``, or the held-out
   flights do not prefer either significantly (:func:`quadcore.identify.evidence.compare`, in the
   channels above the noise), nothing else separates them: they are ``tied_with`` each other, the one
   with fewer parameters ranks first (parsimony; then the higher score), and the verdict says the
   data cannot choose.
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
   When nothing is found, the verdict says that no effect of the library explains what is
   left, and says "at the noise level" only when the residual is also within the margin of
   the floor in both channels.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore.identify import evidence, fitting, sessions as sessionlib, spectrum, sufficient
from quadcore.identify.fitting import FlightData
from quadcore.identify.model import EffectTerm, ModelSpec, PhysicsModel
from quadcore.identify.results import CandidateScore, Diagnosis, Evaluation, ResidualRmse
from quadcore.physics import rotations, signals
from quadcore.physics.dynamics import GRAVITY_W_MPS2, XYZ

MIN_EXPLAINED = 0.05  # screening: below this share of the residual a candidate adds nothing beyond the best one
MIN_SIGMA = 3.0  # a fit within this many standard errors of 'no effect' is not significant
SAME_SIGNATURE = 0.1  # share of one prediction another candidate cannot reproduce, below which they are alike
TIE_MARGIN = 0.02  # score difference within which two alike candidates are a tie (parsimony decides)
LARGE_SNR = 3.0  # a found effect whose removed residual exceeds this many noise floors (RMS) is "large"

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
    Rows are read only when asked for (:meth:`rows`, :meth:`signal_rows`): nonlinear candidates
    on their training flights, and the evaluated flights' tables and spectra."""

    def __init__(self, decoded, spec: ModelSpec, ids: list[str], layout, stored):
        self.decoded, self.spec, self.ids = decoded, spec, ids
        self._rows: dict[str, FlightData] = {}
        self.linear = all(effectlib.get(n).linear for n in spec.effects)
        self.stats = sufficient.for_flights(spec, decoded, ids, layout, stored) if self.linear else None

    def rows(self, f: str) -> FlightData:
        if f not in self._rows:  # a session's thrust map for its state
            self._rows[f] = fitting.flight_data(f, self.decoded[f], self.spec.vehicle_for(f))
        return self._rows[f]

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


def _evaluated(fl: _Flights, eval_ids: list[str], cands, cand_pred: dict, eval_resid: dict, by_rows: dict) -> list:
    """The evaluated flights as the scores take them. From statistics, a nonlinear candidate's
    held-out prediction (and its unit wrenches, :func:`detection_limits`) are extra columns
    of the evaluated flights' statistics (``pred:``, ``unit:``, ``ref:`` + its name; their rows
    read once), and the signals of ``cand_pred`` and ``eval_resid`` are moved into that layout."""
    if fl.stats is None:
        return [fl.rows(f) for f in eval_ids]
    nonlinear = [c for c in cands if by_rows[c.name]]
    if not nonlinear:
        return [fl.stats[f] for f in eval_ids]
    vehicle, out = fl.spec.vehicle, []
    for f in eval_ids:
        fd, base = fl.rows(f), fl.stats[f]
        extras = {}
        for c in nonlinear:
            extras[f"pred:{c.name}"] = cand_pred[c.name][f]
            extras.update({f"unit:{c.name}:{p.name}": evidence.unit_wrench(c, p, fd, vehicle) for p in c.parameters})
            if c.sensitivity_reference:
                ref = {**c.defaults(), **c.sensitivity_reference}
                extras[f"ref:{c.name}"] = fitting.prediction(c, ref, fd, vehicle)
        layout = base.layout.with_extras(list(extras))
        s = sufficient.flight_stats(fd, vehicle, layout, base.key, extras)
        eval_resid[f] = layout.pad(eval_resid[f])
        for c in cands:
            cand_pred[c.name][f] = (layout.unit(layout.extra(f"pred:{c.name}")) if by_rows[c.name]
                                    else layout.pad(cand_pred[c.name][f]))
        out.append(s)
    return out


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


def diagnose(
    decoded: Mapping[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    candidates: list[str] | None = None,
    n_folds: int = 5,
    log=lambda msg: None,
    sessions: dict[str, list[str]] | None = None,
    stats=None,
) -> Diagnosis:
    """Fit the model, score it on held-out flights, rank the missing effects, and find the
    parameters that differ between groups of flights (``sessions``: name -> flights, from a
    sessions file; None: groups found from the data). Its ``to_dict()`` is the JSON document.

    With a model of linear effects, fits, folds and held-out tests combine the flights'
    sufficient statistics (``stats(flight)``: stored ones, None to compute them from the
    decoded table); nonlinear candidates read their training flights' rows, and the evaluated
    flights' rows give the regime tables and spectra."""
    vehicle = spec.vehicle
    ids = sorted(decoded)
    model_effects = [effectlib.get(n) for n in spec.effects]
    names = candidates if candidates is not None else [n for n, e in effectlib.registry().items()
                                                       if n not in spec.effects and e.offered]
    cands = [effectlib.get(n) for n in names]
    fl = _Flights(decoded, spec, ids, sufficient.layout_of(model_effects + cands), stats)
    fds = {f: fl.flight(f) for f in ids}
    targets = {f: fl.target(f) for f in ids}
    by_rows = {c.name: fl.stats is not None and not c.linear for c in cands}  # fitted from rows, not statistics

    def fit_candidate(c, flights: list[str], resid: dict) -> fitting.Fit:
        if by_rows[c.name]:
            return fitting.fit_effects([c], [fl.rows(f) for f in flights], [row_resid(f, resid) for f in flights],
                                       vehicle)
        return fitting.fit_effects([c], [fds[f] for f in flights], [resid[f] for f in flights], vehicle)

    row_cache: dict[tuple[int, str], np.ndarray] = {}

    def row_resid(f: str, resid: dict) -> np.ndarray:
        key = (id(resid), f)  # a fold's residual turned into rows once for all nonlinear candidates
        if key not in row_cache:
            row_cache[key] = fl.signal_rows(f, resid[f])
        return row_cache[key]

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
        if spec.per_session:  # the model's per-session effects fitted per session of the training flights
            pm = sessionlib.fit_per_session(spec, fds, targets, train, sessions, log)
            resid = {f: targets[f] - sessionlib.model_prediction(pm, fds[f], log) for f in {*train, *test}}
        else:
            fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train], vehicle, spec.fixed)
            resid = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in {*train, *test}}
        for c in cands:
            fit_c = fold_fits[c.name] = fit_candidate(c, train, resid)
            fold_params[c.name].append(fit_c.params[c.name])
            for f in test:
                cand_pred[c.name][f] = fit_c.predict([c], fl.rows(f) if by_rows[c.name] else fds[f], vehicle)
        for f in test:
            eval_resid[f] = resid[f]
    # With a single split on all training flights (holdout), its fits are the final ones.
    reuse = len(splits) == 1 and splits[0][0] == train_all

    # Parameters reported: fitted on all training flights.
    tr = [fds[f] for f in train_all]
    if spec.per_session:
        model = pm if reuse else sessionlib.fit_per_session(spec, fds, targets, train_all, sessions, log)
        resid_train = {f: targets[f] - sessionlib.model_prediction(model, fds[f]) for f in train_all}
    else:
        if not reuse:
            fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train_all], vehicle, spec.fixed)
        model = PhysicsModel(vehicle, [EffectTerm(e.name, fit_m.params[e.name], fit_m.std[e.name],
                                                  e.name in spec.fixed) for e in model_effects],
                             spec.sessions_of(ids) if spec.session_maps else {}, spec.session_maps)
        resid_train = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in train_all}
    if reuse and len(train_all) >= 3:
        # one split only: refit each candidate leaving out groups of training flights, for the spread
        for group in fitting.folds(train_all, n_folds):
            sub = [f for f in train_all if f not in group]
            for c in cands:
                fold_params[c.name].append(fit_candidate(c, sub, resid_train).params[c.name])
        fold_params = {k: v[1:] for k, v in fold_params.items()}  # drop the all-training fit

    eval_ids = sorted(eval_resid)
    eval_fds = _evaluated(fl, eval_ids, cands, cand_pred, eval_resid, by_rows)
    before = _total(_ss(eval_resid[f], fd) for f, fd in zip(eval_ids, eval_fds))
    n_eval = sum(fd.n for fd in eval_fds)

    # The sensor-noise floor: a channel whose residual is within evidence.NOISE_MARGIN of it
    # holds no evidence FOR an effect (only against one that would add error there).
    noise_ss = _total(fd.noise ** 2 * fd.n for fd in eval_fds)
    at_noise = evidence.at_noise_level(before, noise_ss)

    rows: list[dict[str, Any]] = []
    w = _weights(eval_fds, [eval_resid[f] for f in eval_ids])
    for c in cands:
        after = _total(_ss(eval_resid[f] - cand_pred[c.name][f], fd) for f, fd in zip(eval_ids, eval_fds))
        raw = {ch: _ev(before, after, sl) for ch, sl in TARGET_CHANNELS.items()}
        ev_f, ev_t = (min(raw[ch], 0.0) if at_noise[ch] else raw[ch] for ch in ("force", "torque"))
        target = c.target if c.target != "both" else ("force" if ev_f >= ev_t else "torque")
        fit_c = fold_fits[c.name] if reuse else fit_candidate(c, train_all, resid_train)
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
            **_held_out_evidence(evidence.held_out_test(eval_fds, eval_resid, cand_pred[c.name],
                                                        evidence.channel_mask([target])),
                                 before, after, noise_ss, target),
        })
    for r in rows:
        _decide(r, at_noise, len(rows))

    # Which candidates leave the same signature on the evaluated flights?
    span = _SpanOverlap(cands, cand_pred, eval_fds, eval_resid, w, vehicle)
    evidence_w = w * evidence.channel_mask([ch for ch, quiet in at_noise.items() if not quiet])

    def separated(a: str, b: str) -> bool:
        """The held-out flights prefer one of ``a`` and ``b`` significantly (channels above the noise)."""
        return evidence.compare(eval_fds, eval_resid, cand_pred[a], cand_pred[b], evidence_w).p_value < evidence.ALPHA
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
    rows = _rank(rows)
    for r in rows:  # what each could still explain once the best one is in the model
        r["explained_after_top"] = (r["explained_variance"] if r is rows[0] or at_noise[r["target"]]
                                    else span.left_after(r["effect"], rows[0]["effect"], r["target"]))
    rank_reasons(rows, at_noise)
    # how small an effect could hide in what is left once the best one found is in the model
    left = ({f: eval_resid[f] - cand_pred[rows[0]["effect"]][f] for f in eval_ids} if rows and rows[0]["found"]
            else eval_resid)
    sensitivity = detection_limits(cands, eval_fds, left, noise_ss, vehicle, len(cands))
    for r in rows:
        r["sensitivity"] = sensitivity[r["effect"]]

    # Parameters that differ between sessions: the model's effects, and the best candidate beside them
    best = [effect_of[rows[0]["effect"]]] if rows and rows[0]["useful"] else []
    if all(e.linear for e in model_effects + best):
        disagree = sessionlib.disagreements(model_effects + best, fds, targets, vehicle, spec.fixed, sessions, log)
    else:  # a nonlinear effect: fitted on each flight's rows
        disagree = sessionlib.disagreements(model_effects + best, {f: fl.rows(f) for f in ids},
                                            {f: fl.signal_rows(f, targets[f]) for f in ids}, vehicle, spec.fixed,
                                            sessions, log)

    # the evaluated flights' rows: the residual by regime, by flight, in time and in frequency
    eval_rows = [fl.rows(f) for f in eval_ids]
    resid_rows = {f: fl.signal_rows(f, eval_resid[f]) for f in eval_ids}
    long = long_table(eval_rows, resid_rows, vehicle)
    text = verdict(rows, at_noise, sensitivity)
    if disagree:
        text += " Parameters differ between groups of flights: " + "; ".join(d.summary() for d in disagree) + "."
    return Diagnosis(
        effects_in_model=tuple(spec.effects),
        model=model,
        evaluation=Evaluation(mode, len(splits), tuple(train_all), tuple(eval_ids), n_eval),
        baseline=_rmse(before, n_eval),
        noise_floor=_rmse(noise_ss, n_eval),
        at_noise_level=at_noise,
        residual_to_noise={ch: float(np.sqrt(before[sl].sum() / noise_ss[sl].sum())) if noise_ss[sl].sum() > 0
                           else None for ch, sl in TARGET_CHANNELS.items()},
        candidates=tuple(CandidateScore.from_dict(r) for r in rows),
        sensitivity=sensitivity,
        sensitivity_basis=sensitivity_basis(cands),
        verdict=text,
        disagreements=tuple(disagree),
        regimes=regime_table(long),
        flights=flight_table(long),
        worst_segments=worst_segments(long),
        frequency=spectrum.frequency_view(eval_rows, resid_rows, vehicle),
    )


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


def _why_not(r: dict, at_noise: dict[str, bool]) -> tuple[str, str]:
    """(status, reason) of a candidate that is not found."""
    ch = r["target"]
    if not r["physical"]:
        return "unphysical", "unphysical fit: " + "; ".join(n for n in r["notes"] if "outside" in n)
    if at_noise[ch]:
        return "noise_level", (f"no evidence: the held-out {ch} residual is within {evidence.NOISE_MARGIN:.0%} "
                               "of the sensor-noise floor")
    if r["explained_variance"] <= 0:
        return "no_gain", f"removes nothing from the held-out {ch} residual"
    if r["significance_sigma"] >= MIN_SIGMA:
        return "not_significant", (f"indistinguishable from noise on held-out flights "
                                   f"(p = {r['held_out_p_value']:.2g}, needs p < {r['held_out_alpha']:.2g})")
    return "not_significant", f"its fit is within noise of 'no effect' ({r['significance_sigma']:.1f} σ)"


def rank_reasons(rows: list[dict], at_noise: dict[str, bool]) -> None:
    """Give every candidate (best first) a ``status`` and a ``reason``: why it is ranked where
    it is (found and how large; tied with; an alternative to the best one; unphysical; not
    significant; at the noise level)."""
    top = rows[0] if rows and rows[0]["found"] else None
    for i, r in enumerate(rows):
        if not r["found"]:
            r["status"], r["reason"] = _why_not(r, at_noise)
            above = [o["effect"] for o in rows[:i] if o["effect"] in r.get("indistinguishable_from", [])]
            if above and r["physical"]:
                r["reason"] += f"; indistinguishable from {', '.join(above)}"
            continue
        size = (f"{r['grade']}: removes {_pct(r['explained_variance'])} of the held-out {r['target']} residual "
                f"({_pct(r['explained_above_noise'])} of what lies above the noise floor), "
                f"p = {r['held_out_p_value']:.2g}")
        assert top is not None  # rows are ranked: a found candidate never follows one not found
        if r is top:
            r["status"], r["reason"] = "found", size
        elif top["effect"] in r.get("tied_with", []):
            r["status"] = "tied"
            r["reason"] = (f"tied with {top['effect']} (held-out flights prefer neither), which has fewer or as "
                           f"many parameters; {size}")
        elif r.get("explained_after_top", 0.0) >= MIN_EXPLAINED:
            r["status"], r["reason"] = "found", f"also missing beyond {top['effect']}; {size}"
        else:
            r["status"] = "alternative"
            r["reason"] = f"an alternative to {top['effect']} (explains the same residual, less well); {size}"


def detection_limits(cands, flights: list[FlightData], resid: dict[str, np.ndarray], noise_ss: np.ndarray,
                     vehicle, n_candidates: int) -> dict[str, dict[str, float | None]]:
    """Per candidate and parameter: the smallest |deviation from 'no effect'| these flights
    would detect (:func:`quadcore.identify.evidence.detection_limit`); None when no value within the
    parameter's range would be. A parameter stated at a reference point of the others (a
    wind, at a rotor drag) must also lift the score by ``2 TIE_MARGIN`` above the simpler
    effect it then resembles (a wind above rotor drag), or the two are a tie."""
    out: dict[str, dict[str, float | None]] = {}
    for c in cands:
        out[c.name] = {}
        reference = c.sensitivity_reference
        base_ss = 0.0
        if reference:
            base_ss = sum(_reference_ss(c, fd, vehicle) for fd in flights)
        for p in c.parameters:
            unit = {fd.flight: _unit(c, p, fd, vehicle) for fd in flights}
            conditional = bool(reference) and p.name not in reference
            v = evidence.detection_limit(flights, resid, unit, noise_ss, MIN_SIGMA, n_candidates,
                                         min_share=2 * TIE_MARGIN if conditional else 0.0,
                                         base_ss=base_ss if conditional else 0.0)
            if not c.linear:  # the unit wrench is a secant: nothing is known below its step
                v = max(v, evidence.SECANT * (p.upper - p.lower))
            out[c.name][p.name] = float(v) if v <= max(p.upper - p.default, p.default - p.lower) else None
    return out


def sensitivity_basis(cands) -> dict:
    """What the sensitivity values mean (for the JSON and the reports)."""
    return {
        "meaning": "smallest |parameter - its 'no effect' value| these flights would detect, each parameter alone",
        "detection_probability": evidence.POWER,
        "false_alarm_probability": evidence.ALPHA,
        "noise_margin": evidence.NOISE_MARGIN,
        "conditions": {c.name: dict(c.sensitivity_reference) for c in cands if c.sensitivity_reference},
    }


def _below(p, v: float | None) -> str:
    """``k_x_s_per_m < 0.003 s/m`` or ``|scale - 1| < 0.006``: a deviation below ``v``."""
    if v is None:
        return f"{p.name} not detectable in its range"
    name = p.name if p.default == 0 else f"|{p.name} - {p.default:g}|"
    return f"{name} < {v:.2g} {p.unit if p.unit != '1' else ''}".rstrip()


def sensitivity_text(sensitivity: dict, effects: list[str] | None = None) -> str:
    """``rotor_drag k_x_s_per_m < 0.003 s/m, ...`` for the named effects (all by default)."""
    parts = []
    for name in effects or list(sensitivity):
        if name not in effectlib.registry():
            continue
        params = {p.name: p for p in effectlib.get(name).parameters}
        vals = ", ".join(_below(params[k], v) for k, v in sensitivity.get(name, {}).items() if k in params)
        parts.append(f"{name} ({vals})")
    return "; ".join(parts)


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

    def left_after(self, b: str, top: str, channel: str) -> float:
        """Share of the baseline ``channel`` residual that ``b`` removes from what ``top``
        leaves."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[0], y[1 + self.names.index(top)] = 1.0, -1.0
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


def verdict(rows: list[dict], at_noise: dict[str, bool] | None = None, sensitivity: dict | None = None) -> str:
    """One paragraph a person reads first: what is missing and how sure, or why nothing is,
    and how small an effect these flights could have missed."""
    found = [r for r in rows if r.get("found", r.get("useful", False))]
    unseen = [r["effect"] for r in rows if r not in found[:1]]
    missed = (f" Smaller effects would go unnoticed on these flights ({evidence.POWER:.0%} detection, "
              f"{evidence.ALPHA:.0%} false alarms): " + sensitivity_text(sensitivity, unseen) + "."
              if sensitivity else "")
    if not found:
        if at_noise and all(at_noise.values()):
            return ("No effect of the library explains the residual on held-out flights: none improves it "
                    f"significantly, and it is within {evidence.NOISE_MARGIN:.0%} (RMS) of the sensor-noise floor in "
                    "force and in torque; there is nothing left to explain at what these flights can resolve." + missed)
        best = rows[0] if rows else None
        tail = f" (best: {best['effect']}, {best.get('reason', best.get('grade', ''))})" if best else ""
        return ("No effect of the library explains the residual on held-out flights" + tail +
                ": what is left is a physical effect outside the library, or one below what these flights can "
                "detect." + missed)
    top = found[0]
    grade = top.get("grade", "clear")
    size = {"small but certain": "small but certain (weaker than the sensor noise, confirmed on held-out flights"}.get(
        grade, grade + " (confirmed on held-out flights") + f", p = {top.get('held_out_p_value', 0.0):.2g})"
    by_name = {r["effect"]: r for r in rows}
    params = ", ".join(
        f"{k} = {v:.4g} ± {top['parameter_std'].get(k, float('nan')):.2g}" for k, v in top["parameters"].items()
    )
    ch, other = top["target"], _other(top["target"])
    text = (f"Most likely missing: {top['effect']}: {size}: it removes {top['explained_variance']:.0%} of the held-out "
            f"{ch} residual ({_pct(top.get('explained_above_noise', top['explained_variance']))} of what lies above "
            "the sensor-noise floor)")
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
    others = [r for r in found[1:] if r["effect"] not in alike]
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
    return text + missed


def candidate_summary(candidates: Iterable[CandidateScore]) -> list[dict]:
    """One row per candidate, best first, for people: its status and why it is ranked there
    (the console, the reports and the UI show the same)."""
    return [{
        "rank": i,
        "effect": c.effect,
        "status": c.status,
        "target": c.target,
        "explained": round(c.explained_variance, 3),
        "above_noise": round(c.explained_above_noise, 3),
        "held_out_p": float(f"{c.held_out_p_value:.2g}"),
        "parameters": ", ".join(f"{k}={v:.4g}±{c.parameter_std.get(k, float('nan')):.2g}"
                                for k, v in c.parameters.items()),
        "why": c.reason,
    } for i, c in enumerate(candidates, 1)]


def sensitivity_rows(sensitivity: Mapping[str, Mapping[str, float | None]],
                     basis: Mapping[str, Any]) -> list[dict]:
    """One row per effect and parameter: the smallest deviation these flights would detect
    (``sensitivity`` and ``sensitivity_basis`` of a :class:`Diagnosis`)."""
    rows = []
    for name, params in sensitivity.items():
        known = {p.name: p for p in effectlib.get(name).parameters} if name in effectlib.registry() else {}
        cond = basis.get("conditions", {}).get(name, {})
        for k, v in params.items():
            p = known.get(k)
            rows.append({
                "effect": name, "parameter": k,
                "undetected_below": None if v is None else float(f"{v:.2g}"),
                "unit": p.unit if p and p.unit != "1" else "",
                "of": (f"|{k} - {p.default:g}|" if p and p.default != 0 else k)
                + (", at " + ", ".join(f"{c}={x:g}" for c, x in cond.items()) if cond and k not in cond else ""),
            })
    return rows
