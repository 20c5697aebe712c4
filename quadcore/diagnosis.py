"""Where the model fails, and which physical effect is missing.

1. **Where it fails.** The residual of the model on the evaluated flights, broken down by
   flight regime (speed, height, thrust-to-weight, angular rate, battery voltage,
   acceleration, flight phase) and by flight, with the worst segments in time.
2. **What is missing.** Every effect of the library that is not yet in the model is fitted
   on the training flights' residuals and scored on flights it never saw: either the
   held-out flights, or, with no holdout, a cross-validation over flights (the model's own
   effects are refitted inside each fold too). Candidates are ranked by the fraction of
   held-out residual removed, force and torque counted alike.
3. **Honesty.** Two candidates whose held-out predictions are nearly the same cannot be
   told apart by this data (an unmodelled payload and a weaker thrust map; rotor drag and
   a wind too weak to matter); the result says so instead of picking one. When the best
   candidate removes less than ``MIN_EXPLAINED`` of its target residual, the verdict is
   that no effect of the library explains what is left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore import fitting, rotations
from quadcore.dynamics import GRAVITY_W_MPS2, XYZ
from quadcore.fitting import FlightData
from quadcore.model import EffectTerm, ModelSpec, PhysicsModel

MIN_EXPLAINED = 0.05  # below this fraction of its target residual, a candidate explains nothing
SAME_SIGNATURE = 0.1  # relative difference of predictions below which two candidates are alike
PARSIMONY_MARGIN = 0.01  # score difference within which the candidate with fewer parameters ranks first

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


def regime_columns(fd: FlightData, residual: np.ndarray, vehicle) -> RegimeColumns:
    s = fd.state
    f_meas_b = residual[:, :3] * 0 + vehicle.mass_kg * s.sf_b_mps2
    a_w = GRAVITY_W_MPS2 + rotations.body_to_world(s.R_wb, f_meas_b) / vehicle.mass_kg
    speed = np.linalg.norm(s.v_w_mps, axis=1)
    vz = s.v_w_mps[:, 2]
    tw = s.f_rotor_N.sum(axis=1) / vehicle.weight_N
    phase = np.where(
        tw < 0.5, "ground",
        np.where(vz > 0.2, "climb", np.where(vz < -0.2, "descent", np.where(speed < 0.1, "hover", "cruise"))),
    )
    return RegimeColumns(speed, s.p_w_m[:, 2], tw, np.linalg.norm(s.omega_b_radps, axis=1), s.vbat_V,
                         np.linalg.norm(a_w, axis=1), phase)


def _bin_labels(x: np.ndarray, edges: list[float], unit: str) -> np.ndarray:
    idx = np.searchsorted(np.asarray(edges[1:]), x, side="right")
    labels = [f"{'<' if np.isinf(edges[0]) else ''}{edges[i] if not np.isinf(edges[i]) else edges[i + 1]:g}"
              + (f"-{edges[i + 1]:g}" if i + 1 < len(edges) and not np.isinf(edges[i]) else ("+" if i + 1 >= len(edges) else ""))
              + f" {unit}" for i in range(len(edges))]
    return np.asarray(labels)[idx]


def long_table(flights: list[FlightData], resid: dict[str, np.ndarray], vehicle) -> pl.DataFrame:
    """One row per usable sample of the evaluated flights: regime labels and the residual."""
    frames = []
    for fd in flights:
        r = resid[fd.flight]
        rc = regime_columns(fd, r, vehicle)
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
    force_sq = sum(pl.col(f"f_res_b_{a}_N") ** 2 for a in XYZ)
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


def _ss(resid: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sum of squares per channel (6,) on usable samples."""
    return (resid[mask] ** 2).sum(axis=0)


def _ev(before: np.ndarray, after: np.ndarray, channels: slice) -> float:
    b = before[channels].sum()
    return float(1.0 - after[channels].sum() / b) if b > 0 else 0.0


TARGET_CHANNELS = {"force": slice(0, 3), "torque": slice(3, 6)}


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
        splits = [([f for f in ids if f not in fold], fold) for fold in fitting.folds(ids, n_folds)] if len(ids) > 1 else [(ids, ids)]
        mode = "cross-validation" if len(ids) > 1 else "in-sample (one flight only)"

    eval_resid: dict[str, np.ndarray] = {}
    cand_pred: dict[str, dict[str, np.ndarray]] = {c.name: {} for c in cands}
    for k, (train, test) in enumerate(splits, 1):
        log(f"fold {k}/{len(splits)}: fitting on {len(train)} flights, scoring {len(test)}")
        tr = [fds[f] for f in train]
        fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train], vehicle, spec.fixed)
        resid = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in {*train, *test}}
        for c in cands:
            fit_c = fitting.fit_effects([c], tr, [resid[f] for f in train], vehicle)
            for f in test:
                cand_pred[c.name][f] = fit_c.predict([c], fds[f], vehicle)
        for f in test:
            eval_resid[f] = resid[f]

    # Parameters reported: fitted on all training flights.
    tr = [fds[f] for f in train_all]
    fit_m = fitting.fit_effects(model_effects, tr, [targets[f] for f in train_all], vehicle, spec.fixed)
    model = PhysicsModel(vehicle, [EffectTerm(e.name, fit_m.params[e.name], fit_m.std[e.name], e.name in spec.fixed)
                                   for e in model_effects])
    resid_train = {f: targets[f] - fit_m.predict(model_effects, fds[f], vehicle) for f in train_all}

    eval_ids = sorted(eval_resid)
    before = sum(_ss(eval_resid[f], fds[f].mask) for f in eval_ids)
    n_eval = sum(int(fds[f].mask.sum()) for f in eval_ids)
    baseline = {
        "force_rmse_N": [float(np.sqrt(before[j] / n_eval)) for j in range(3)],
        "torque_rmse_Nm": [float(np.sqrt(before[3 + j] / n_eval)) for j in range(3)],
    }

    rows = []
    w = fitting.channel_weights([eval_resid[f][fds[f].mask] for f in eval_ids])
    for c in cands:
        after = sum(_ss(eval_resid[f] - cand_pred[c.name][f], fds[f].mask) for f in eval_ids)
        ev_f, ev_t = _ev(before, after, TARGET_CHANNELS["force"]), _ev(before, after, TARGET_CHANNELS["torque"])
        target = c.target if c.target != "both" else ("force" if ev_f >= ev_t else "torque")
        fit_c = fitting.fit_effects([c], tr, [resid_train[f] for f in train_all], vehicle)
        bounds = {p.name: (p.lower, p.upper) for p in c.parameters}
        outside = [k for k, v in fit_c.params[c.name].items() if not bounds[k][0] <= v <= bounds[k][1]]
        at_bound = [k for k, v in fit_c.params[c.name].items()
                    if k not in outside and min(abs(v - bounds[k][0]), abs(v - bounds[k][1])) < 1e-6 * (bounds[k][1] - bounds[k][0])
                    and v != c.defaults()[k]]
        rows.append({
            "effect": c.name,
            "target": target,
            "acts_on": c.target,
            "explained_variance": max(0.0, ev_f if target == "force" else ev_t),
            "explained_variance_force": ev_f,
            "explained_variance_torque": ev_t,
            "score": 0.5 * (ev_f + ev_t),
            "force_rmse_N": [float(np.sqrt(after[j] / n_eval)) for j in range(3)],
            "torque_rmse_Nm": [float(np.sqrt(after[3 + j] / n_eval)) for j in range(3)],
            "parameters": fit_c.params[c.name],
            "parameter_std": fit_c.std[c.name],
            "n_parameters": len(c.parameters),
            "explained_variance_per_axis": {
                f"{q}_{a}": float(1 - after[i] / before[i]) if before[i] > 0 else 0.0
                for i, (q, a) in enumerate([("force", a) for a in XYZ] + [("torque", a) for a in XYZ])
            },
            "physical": not outside,
            "notes": ([f"fitted {', '.join(outside)} outside the physical bounds: not a physical explanation"]
                      if outside else []) + ([f"{', '.join(at_bound)} at the bound of its range"] if at_bound else []),
        })

    # Which candidates leave the same signature on the evaluated flights?
    sig = {c.name: np.concatenate([cand_pred[c.name][f][fds[f].mask] for f in eval_ids]) * np.sqrt(w) for c in cands}
    for r in rows:
        a = sig[r["effect"]]
        na = float(np.mean(a**2))
        alike = []
        for o in rows:
            if o is r or na == 0:
                continue
            b = sig[o["effect"]]
            if float(np.mean((a - b) ** 2)) < SAME_SIGNATURE * max(na, float(np.mean(b**2))):
                alike.append(o["effect"])
        r["indistinguishable_from"] = alike

    def rank_key(r):
        return not r["physical"], -round(r["score"] / PARSIMONY_MARGIN), r["n_parameters"], -r["score"]

    rows.sort(key=rank_key)
    long = long_table([fds[f] for f in eval_ids], eval_resid, vehicle)
    return {
        "effects_in_model": spec.effects,
        "model": model.to_dict(),
        "evaluation": {"mode": mode, "folds": len(splits), "train_flights": train_all, "eval_flights": eval_ids,
                       "samples": n_eval},
        "baseline": baseline,
        "candidates": rows,
        "verdict": verdict(rows),
        "regimes": regime_table(long).to_dicts(),
        "flights": flight_table(long).to_dicts(),
        "worst_segments": worst_segments(long).to_dicts(),
    }


def verdict(rows: list[dict]) -> str:
    """One paragraph a person reads first."""
    useful = [r for r in rows if r["explained_variance"] >= MIN_EXPLAINED and r["physical"]]
    if not useful:
        best = rows[0] if rows else None
        tail = f" (best: {best['effect']}, {best['explained_variance']:.0%})" if best else ""
        return ("No effect of the library explains the residual on held-out flights" + tail +
                ": what is left is noise, or a physical effect outside the library.")
    top = useful[0]
    params = ", ".join(
        f"{k} = {v:.4g} ± {top['parameter_std'].get(k, float('nan')):.2g}" for k, v in top["parameters"].items()
    )
    text = (f"Most likely missing: {top['effect']}: it removes {top['explained_variance']:.0%} of the held-out "
            f"{top['target']} residual ({params}).")
    if top["notes"]:
        text += " Note: " + "; ".join(top["notes"]) + "."
    if top["indistinguishable_from"]:
        text += (f" This data cannot tell it apart from {', '.join(top['indistinguishable_from'])}: their "
                 "predictions on the held-out flights are nearly the same; flights that separate them are needed "
                 "(or knowledge of the vehicle) before choosing.")
    others = [r for r in useful[1:] if r["effect"] not in top["indistinguishable_from"]]
    if others:
        text += " Also helping: " + ", ".join(f"{r['effect']} ({r['explained_variance']:.0%})" for r in others[:3]) + "."
    return text
