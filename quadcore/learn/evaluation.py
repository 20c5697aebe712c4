"""How good the learned residual models are: metrics, comparison tables, plots, the report.

**What is scored.** Every row of a table predicts the same thing: the residual force
``f_res_b_{x,y,z}_N`` (N) and torque ``tau_res_b_{x,y,z}_Nm`` (N m), **body frame**, left after
the *current* physics model ``P`` (the nominal vehicle plus the effects of the model file,
fitted), on the usable samples (away from logging gaps) of flights the model never saw.
The error of a row is ``residual - prediction``: what is still unexplained of the measured
force and torque once ``P`` and the row's correction are applied. Per axis: mean absolute
error (MAE), root mean square error (RMSE), both in N and N m, and R² (``1 - SS_err /
SS_tot`` about the held-out mean; below 0 means worse than predicting the held-out mean).

**Baselines** (in the same tables as the learned models):

* ``physics-only``: ``P`` alone, no learned correction (the predicted residual is 0). Its
  error is ``P``'s own residual. This is the bar a learned model has to clear.
* ``zero``: the *nominal* vehicle alone, no effects and nothing learned: zero force and torque
  beyond the rigid body and the thrust map. Its error is the nominal model's residual. When
  ``P`` has no effects (the default model file), ``zero`` and ``physics-only`` are the same
  model, and the tables say so.
* ``training mean``: ``P`` plus a constant per-axis correction, the mean residual of the
  training flights (a bias trim: the simplest thing a "learned" model could do).

**Learned models** (:mod:`quadcore.learn.learning`): ``P`` plus the model's predicted residual.
Timings: training (data preparation + fitting with early stopping), prediction of the whole
held-out flight (median of 5 calls after a warm-up), and per single sample (median of 300
calls with one row: the compiled NumPy forest for trees, a (1, k) torch tensor under
``no_grad`` for the MLP; XGBoost's own ``inplace_predict`` on one row is reported beside it).

**"Best"** models are chosen by their *validation* loss (validation flights drawn from the
training flights), never by the held-out score, and only among causal feature sets (see
:mod:`quadcore.learn.features`: ``acc_rate_rot`` sees the target and is reported, flagged, but never
chosen).

**The study** this project grows from reported, for its best tree, force MAE 0.021 / 0.037 /
0.011 N (x, y, z), 41.9 s training and 0.03 s to predict the held-out flight; for its best MLP
0.022 / 0.039 / 0.077 N, 66.9 s and 0.28 s. Its residual mixed frames, its torque scaling used
test data and it used a '+' rotor layout for an 'X' vehicle, so its numbers are shown beside
ours, not as targets: our residual is a different (smaller) quantity.

Reports go to ``<root>/reports/learning.{md,html,json}`` and the headline results to the
history (:mod:`quadcore.identify.history`, source ``learned``), so that ``+xgboost(physics)`` shows as a
step in the falling-error plot.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import polars as pl  # noqa: E402

from quadcore.identify import diagnosis, history
from quadcore.learn import features as feat, learning
from quadcore.learn.features import TARGETS  # noqa: E402
from quadcore.learn.learning import PRED_COLUMNS  # noqa: E402
from quadcore.physics import dynamics, residuals
from quadcore.physics.dynamics import XYZ  # noqa: E402
from quadcore.report import plots
from quadcore.store import store

STUDY: dict[str, dict[str, Any]] = {
    "xgboost": {"label": "study: best tree (XGBoost)", "force_mae_N": (0.021, 0.037, 0.011), "train_s": 41.9,
                "predict_s": 0.03},
    "mlp": {"label": "study: best MLP (PyTorch)", "force_mae_N": (0.022, 0.039, 0.077), "train_s": 66.9,
            "predict_s": 0.28},
}
BASELINES = ("physics-only", "zero", "training mean")
AXES = [f"F{a}" for a in XYZ] + [f"τ{a}" for a in XYZ]


# ---------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------

def metrics(y: np.ndarray, p: np.ndarray) -> dict[str, float]:
    """MAE, RMSE (N, N m) and R² per axis of (n, 6) residuals and predictions."""
    y, p = np.asarray(y, float), np.asarray(p, float)
    e = y - p
    out: dict[str, float] = {}
    for j, (name, unit) in enumerate([("force", "N")] * 3 + [("torque", "Nm")] * 3):
        a = XYZ[j % 3]
        ss_tot = float(((y[:, j] - y[:, j].mean()) ** 2).sum())
        out[f"{name}_mae_{a}_{unit}"] = float(np.abs(e[:, j]).mean())
        out[f"{name}_rmse_{a}_{unit}"] = float(np.sqrt((e[:, j] ** 2).mean()))
        out[f"{name}_r2_{a}"] = float(1 - (e[:, j] ** 2).sum() / ss_tot) if ss_tot > 0 else float("nan")
    out["rows"] = int(len(y))
    return out


def mae(m: dict) -> list[float]:
    return [m[f"force_mae_{a}_N"] for a in XYZ] + [m[f"torque_mae_{a}_Nm"] for a in XYZ]


def rmse(m: dict) -> tuple[list[float], list[float]]:
    return [m[f"force_rmse_{a}_N"] for a in XYZ], [m[f"torque_rmse_{a}_Nm"] for a in XYZ]


def r2(m: dict) -> list[float]:
    return [m[f"force_r2_{a}"] for a in XYZ] + [m[f"torque_r2_{a}"] for a in XYZ]


# ---------------------------------------------------------------------------------------
# Baselines
# ---------------------------------------------------------------------------------------

def nominal_residual(table: pl.DataFrame, vehicle) -> np.ndarray:
    """(n, 6) residual of the nominal model (no effects) from a residual table of any model.

    A residual table carries every input of :func:`quadcore.physics.dynamics.flight_state` (time,
    pose, velocity, rates, accelerometer, PWM, battery, motor speeds), so the nominal residual
    is recomputed exactly as :func:`quadcore.physics.residuals.residual_arrays` computes it, with the
    same filters."""
    state = dynamics.flight_state(table, vehicle)
    r = residuals.residual_arrays(state, vehicle)
    return np.concatenate([r["f_res_b"], r["tau_res_b"]], axis=1)


def baseline_predictions(residual_tables: dict[str, pl.DataFrame], train: list[str], test: list[str],
                         vehicle) -> dict[str, pl.DataFrame]:
    """Baseline predictions on the usable rows of the ``test`` flights, in the layout of a
    run's ``predictions.parquet`` (flight, row, t_s, targets, predictions)."""
    y_train = np.concatenate([feat.targets(residual_tables[f])[feat.usable(residual_tables[f])] for f in train])
    mean = y_train.mean(axis=0)
    out: dict[str, list[pl.DataFrame]] = {b: [] for b in BASELINES}
    for f in test:
        t = residual_tables[f]
        m = feat.usable(t)
        y = feat.targets(t)[m]
        base = {"flight": [f] * int(m.sum()), "row": np.flatnonzero(m), "t_s": t["t_s"].to_numpy()[m],
                **{c: y[:, k] for k, c in enumerate(TARGETS)}}
        preds = {
            "physics-only": np.zeros_like(y),
            "zero": y - nominal_residual(t, vehicle)[m],
            "training mean": np.broadcast_to(mean, y.shape),
        }
        for b, p in preds.items():
            out[b].append(pl.DataFrame({**base, **{c: p[:, k] for k, c in enumerate(PRED_COLUMNS)}}))
    return {b: pl.concat(v) for b, v in out.items()}


def _yp(pred: pl.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    return pred.select(TARGETS).to_numpy(), pred.select(PRED_COLUMNS).to_numpy()


# ---------------------------------------------------------------------------------------
# The evaluation
# ---------------------------------------------------------------------------------------

def _model_has_effects(physics: dict) -> bool:
    return bool((physics or {}).get("effects"))


def evaluate(out_dir: str | Path, residual_tables: dict[str, pl.DataFrame], vehicle,
             physics_trained_on: list[str] | None = None) -> dict:
    """Score every run of ``out_dir`` (see :func:`quadcore.learn.learning.run_plan`) and the baselines
    on the same held-out rows; build the comparison tables. Returns the report as a dict
    (JSON-able; tables as lists of rows)."""
    index, runs = learning.read_runs(out_dir)
    physics = index.get("physics_model") or {}
    holdout = index["holdout"]
    missing = sorted({f for r in runs for f in r["test_flights"] + r["train_flights"]} - set(residual_tables))
    if missing:
        raise learning.LearningError(f"no residual table for flight(s) {', '.join(missing)}")
    preds = {r["name"]: learning.read_predictions(r) for r in runs}
    for r in runs:
        r["metrics"] = metrics(*_yp(preds[r["name"]]))
        r["causal"] = r["feature_set"].get("causal", True)

    # Baselines per split (the training flights of the split's "all" group)
    splits: dict[str, dict] = {}
    for r in runs:
        s = r["split"]["name"]
        if s not in splits or r["train_group"] == "all":
            splits[s] = {"mode": r["split"]["mode"], "test": r["test_flights"], "train": r["train_flights"]}
    base_preds = {s: baseline_predictions(residual_tables, v["train"], v["test"], vehicle) for s, v in splits.items()}
    baselines = {s: {b: metrics(*_yp(p)) for b, p in bp.items()} for s, bp in base_preds.items()}

    hold = f"holdout-{holdout}"
    hold_runs = [r for r in runs if r["split"]["name"] == hold]
    best = best_runs(hold_runs)
    report = {
        "format": "quadcore-learning-report/1",
        "setup": setup_summary(index, runs, residual_tables, physics, physics_trained_on),
        "definitions": definitions(physics),
        "holdout": holdout,
        "runs": [_run_row(r) for r in runs],
        "baselines": baselines,
        "best": {k: r["name"] for k, r in best.items()},
        "tables": {},
        "notes": list(index.get("notes", [])),
    }
    t = report["tables"]
    base_h = baselines.get(hold, {})
    t["headline"] = headline_table(best, base_h)
    t["holdout"] = results_table(hold_runs, base_h, physics)
    t["feature_sets"] = results_table([r for r in hold_runs if "feature_sets" in r["groups"]], base_h, physics)
    t["complexity"] = results_table([r for r in hold_runs if "complexity" in r["groups"]], base_h, physics)
    size_runs = [r for r in hold_runs if "training_size" in r["groups"]]
    t["training_size"] = results_table(size_runs, {}, physics) if size_runs else []
    if not size_runs and not any("training-size" in n for n in report["notes"]):
        report["notes"].append("training-size comparison not run (comparisons off, or no flight kinds)")
    lofo_runs = [r for r in runs if "lofo" in r["groups"]]
    if lofo_runs:
        report["lofo"] = lofo_summary(lofo_runs, baselines, preds, base_preds)
        t["lofo"] = report["lofo"]["table"]
        t["lofo_flights"] = report["lofo"]["flights"]
    report["verdict"] = verdict(best, base_h, report.get("lofo"))
    report["physics_captures"] = captured_share(best, base_h)
    report["history_rows"] = _history_rows(physics, holdout, best, base_h, report.get("lofo"))
    return report


def best_runs(hold_runs: list[dict]) -> dict[str, dict]:
    """Per model kind: the run with the lowest validation loss among causal feature sets,
    trained on all training flights (validation losses compare: same training flights, same
    target scaling)."""
    best: dict[str, dict] = {}
    for r in hold_runs:
        if not r["causal"] or r["train_group"] != "all":
            continue
        k = r["kind"]
        if k not in best or r["val_loss"] < best[k]["val_loss"]:
            best[k] = r
    return best


def setup_summary(index, runs, residual_tables, physics, physics_trained_on) -> dict:
    holdout = index["holdout"]
    trained_on = physics_trained_on if physics_trained_on is not None else physics.get("trained_on")
    if not _model_has_effects(physics):
        leak = "the physics model has no fitted effects, so nothing of it was fitted on the held-out flight"
    elif trained_on is None:
        leak = "unknown which flights the physics model's effects were fitted on"
    elif holdout in trained_on:
        leak = (f"WARNING: the physics model's effects were fitted on flights that include {holdout} "
                "(a few parameters; set the model's holdout to exclude it)")
    else:
        leak = f"the physics model's effects were fitted without {holdout}"
    cfg = index.get("config", {})
    return {
        "flights": sorted(residual_tables),
        "holdout": holdout,
        "physics_model": physics.get("label", "nominal"),
        "vehicle": physics.get("vehicle", ""),
        "thrust_map": physics.get("thrust_map", ""),
        "effects": [e["name"] for e in physics.get("effects", [])],
        "physics_fit": leak,
        "runs": len(runs),
        "stride": cfg.get("stride"),
        "seed": cfg.get("seed"),
        "validation_fraction": cfg.get("val_fraction"),
        "flight_kinds": index.get("flight_kinds", {}),
    }


def definitions(physics: dict) -> dict[str, str]:
    same = "" if _model_has_effects(physics) else " (the same as zero here: the physics model has no effects)"
    return {
        "target": "residual force f_res_b_{x,y,z}_N [N] and torque tau_res_b_{x,y,z}_Nm [N m], body frame, left "
                  f"after the physics model {physics.get('label', 'nominal')}; rows near logging gaps excluded",
        "physics-only": "the physics model alone, no learned correction (predicted residual 0)" + same,
        "zero": "the nominal vehicle alone (no effects, nothing learned): the nominal model's residual",
        "training mean": "the physics model plus the training flights' mean residual (a constant per axis)",
        "learned": "the physics model plus the learned model's predicted residual",
        "scaling": "inputs and targets standardised with statistics of the training flights only",
        "best": "lowest validation loss (validation flights drawn from the training flights), causal feature sets only",
        "subsampling": "fitting rows: every stride-th sample of the fitting flights; validation and test rows: all",
    }


def _run_row(r: dict) -> dict:
    keep = ("name", "kind", "spec_label", "train_group", "groups", "train_flights", "validation_flights",
            "test_flights", "rows_fit", "rows_validation", "test_rows", "val_loss", "train_time_s", "fit_time_s",
            "predict_time_s", "latency_us", "latency_library_us", "latency_path", "best_iteration",
            "trees_per_output", "epochs", "best_epoch", "metrics", "causal", "path")
    out = {k: r[k] for k in keep if k in r}
    out["feature_set"] = r["feature_set"]["name"]
    out["split"] = r["split"]["name"]
    return out


def _fmt_row(label: str, features: str, train: str, m: dict, extra: dict | None = None) -> dict:
    a = mae(m)
    row = {"model": label, "features": features, "trained on": train,
           **{f"{ax} MAE [{'N' if i < 3 else 'mN m'}]": (v if i < 3 else v * 1e3)
              for i, (ax, v) in enumerate(zip(AXES, a))},
           **{f"{ax} R²": v for ax, v in zip(AXES, r2(m))}}
    row.update(extra or {"train [s]": None, "predict [s]": None, "µs/sample": None, "val loss": None})
    return row


def _complexity(r: dict) -> str:
    if r["kind"] == "xgboost":
        return f"{r['spec_label']} -> {r.get('trees_per_output', '?')} trees/output"
    return f"{r['spec_label']}, best epoch {r.get('best_epoch', '?')}"


def results_table(rs: list[dict], base: dict, physics: dict) -> list[dict]:
    """Rows: the baselines, then the runs (MAE per axis, R², timings)."""
    rows = []
    labels = {"physics-only": f"physics-only ({physics.get('label', 'nominal')})",
              "zero": "zero (nominal only)" + ("" if _model_has_effects(physics) else " = physics-only"),
              "training mean": "training mean"}
    for b in BASELINES:
        if b in base:
            rows.append(_fmt_row(labels[b], "-", "-", base[b]))
    for r in sorted(rs, key=lambda r: (r["kind"], r["feature_set"]["name"], r["train_group"], r["name"])):
        flag = "" if r["causal"] else " (sees target)"
        rows.append(_fmt_row(_complexity(r), r["feature_set"]["name"] + flag,
                             f"{r['train_group']} ({len(r['train_flights'])})", r["metrics"],
                             {"train [s]": r["train_time_s"], "predict [s]": r["predict_time_s"],
                              "µs/sample": r["latency_us"], "val loss": r["val_loss"]}))
    return rows


def headline_table(best: dict[str, dict], base: dict) -> list[dict]:
    """Our best models beside the study's figures (force MAE in N)."""
    rows = []
    for k in ("xgboost", "mlp"):
        s = STUDY[k]
        rows.append({"model": s["label"], "features": "(study)",
                     **{f"F{a} MAE [N]": v for a, v in zip(XYZ, s["force_mae_N"])},
                     **{f"τ{a} MAE [mN m]": None for a in XYZ},
                     "train [s]": s["train_s"], "predict held-out [s]": s["predict_s"],
                     "µs/sample": None, "µs/sample (library call)": None})
        if k in best:
            r = best[k]
            a = mae(r["metrics"])
            rows.append({"model": f"ours: best {k} — {_complexity(r)}", "features": r["feature_set"]["name"],
                         **{f"F{ax} MAE [N]": v for ax, v in zip(XYZ, a[:3])},
                         **{f"τ{ax} MAE [mN m]": v * 1e3 for ax, v in zip(XYZ, a[3:])},
                         "train [s]": r["train_time_s"], "predict held-out [s]": r["predict_time_s"],
                         "µs/sample": r["latency_us"], "µs/sample (library call)": r["latency_library_us"]})
    for b in ("physics-only", "training mean"):
        if b in base:
            a = mae(base[b])
            rows.append({"model": f"ours: {b} baseline", "features": "-",
                         **{f"F{ax} MAE [N]": v for ax, v in zip(XYZ, a[:3])},
                         **{f"τ{ax} MAE [mN m]": v * 1e3 for ax, v in zip(XYZ, a[3:])}, "train [s]": None,
                         "predict held-out [s]": None, "µs/sample": None, "µs/sample (library call)": None})
    return rows


def lofo_summary(lofo_runs, baselines, preds, base_preds) -> dict:
    """Leave-one-flight-out: per model and baseline, the mean and spread over folds (one per
    left-out flight) of the per-fold MAE, the pooled metrics, and per flight the force MAE."""
    by_model: dict[str, dict[str, dict]] = {}  # model -> left-out flight -> run
    split_of: dict[str, str] = {}  # left-out flight -> split name (for its baselines)
    for r in lofo_runs:
        f = r["test_flights"][0]
        by_model.setdefault(f"{r['kind']}({r['feature_set']['name']})", {})[f] = r
        split_of[f] = r["split"]["name"]
    folds = sorted(split_of)
    names = list(by_model) + list(BASELINES)
    table, pooled, flights = [], {}, []
    for name in names:
        if name in by_model:
            per_fold = {f: r["metrics"] for f, r in by_model[name].items()}
            pool = pl.concat([preds[r["name"]] for r in by_model[name].values()])
        else:
            per_fold = {f: baselines[split_of[f]][name] for f in folds}
            pool = pl.concat([base_preds[split_of[f]][name] for f in folds])
        pooled[name] = metrics(*_yp(pool))
        A = np.array([mae(m) for m in per_fold.values()])
        beats = sum(1 for f, m in per_fold.items()
                    if np.mean(mae(m)[:3]) < np.mean(mae(baselines[split_of[f]]["physics-only"])[:3]))
        row = {"model": name, "folds": len(per_fold)}
        for j, ax in enumerate(AXES):
            scale, unit = (1.0, "N") if j < 3 else (1e3, "mN m")
            row[f"{ax} MAE [{unit}] mean"] = float(A[:, j].mean() * scale)
            row[f"{ax} MAE [{unit}] std"] = float(A[:, j].std() * scale)
        row["folds beating physics-only (force MAE)"] = beats if name != "physics-only" else None
        table.append(row)
    for f in folds:
        row = {"flight": f}
        for name in names:
            m = by_model[name][f]["metrics"] if name in by_model else baselines[split_of[f]][name]
            row[f"{name} force MAE [N]"] = float(np.mean(mae(m)[:3]))
        flights.append(row)
    return {"folds": len(folds), "table": table, "flights": flights, "pooled": pooled}


def verdict(best: dict[str, dict], base: dict, lofo: dict | None) -> str:
    """Plain words: per best model and axis, does it beat physics-only, and the training mean?"""
    if not best or "physics-only" not in base:
        return "no learned model to judge"
    b = mae(base["physics-only"])
    tm = mae(base["training mean"]) if "training mean" in base else None
    parts = []
    for k, r in best.items():
        a = mae(r["metrics"])
        worse = [ax for ax, x, y in zip(AXES, a, b) if x >= y]
        gain_f = 1 - np.mean(a[:3]) / np.mean(b[:3])
        gain_t = 1 - np.mean(a[3:]) / np.mean(b[3:])
        s = (f"Best {k} ({r['feature_set']['name']}) on the held-out flight: force MAE {gain_f:.0%} and torque MAE "
             f"{gain_t:.0%} lower than physics-only" if gain_f > 0 and gain_t > 0 else
             f"Best {k} ({r['feature_set']['name']}) on the held-out flight: force MAE {-gain_f:+.0%}, torque MAE "
             f"{-gain_t:+.0%} against physics-only (positive = worse)")
        s += f"; not better than physics-only on {', '.join(worse)}" if worse else "; better on every axis"
        if tm:
            not_tm = [ax for ax, x, y in zip(AXES, a, tm) if x >= y]
            s += (f"; not better than the training mean on {', '.join(not_tm)}" if not_tm
                  else "; better than the training mean on every axis")
        parts.append(s + ".")
    parts += [captured_sentence(k, c) for k, c in captured_share(best, base).items()]
    if lofo:
        for row in lofo["table"]:
            if row["folds beating physics-only (force MAE)"] is not None and row["model"] not in BASELINES:
                parts.append(f"Leave-one-flight-out: {row['model']} beats physics-only on the force in "
                             f"{row['folds beating physics-only (force MAE)']} of {row['folds']} flights.")
    return " ".join(parts)


def captured_share(best: dict[str, dict], base: dict) -> dict[str, dict[str, float]]:
    """How much of each best learned model's gain over the nominal model the interpretable
    physics model already captures, on the held-out flight, force and torque (mean MAE over
    axes): ``(MAE_nominal - MAE_physics) / (MAE_nominal - MAE_learned)``; learned models sit
    on top of the physics model, so their gain includes the physics'. Empty without a physics
    model that has effects (the nominal model then is the physics)."""
    if "zero" not in base or "physics-only" not in base:
        return {}
    nominal, physics = np.array(mae(base["zero"])), np.array(mae(base["physics-only"]))
    if np.allclose(nominal, physics):
        return {}
    out: dict[str, dict[str, float]] = {}
    for k, r in best.items():
        learned = np.array(mae(r["metrics"]))
        out[k] = {}
        for ch, sl in (("force", slice(0, 3)), ("torque", slice(3, 6))):
            gain = nominal[sl].mean() - learned[sl].mean()
            out[k][ch] = float((nominal[sl].mean() - physics[sl].mean()) / gain) if gain > 0 else float("nan")
    return out


def captured_sentence(kind: str, share: dict[str, float]) -> str:
    def one(ch: str) -> str:
        x = share[ch]
        return f"{x:.0%} in {ch}" + (" (more than all of it: the learned model loses some of the physics' gain there)"
                                     if x > 1 else "")

    return (f"Of the best {kind}'s gain over the nominal model (MAE), the interpretable physics model alone "
            f"captures {one('force')} and {one('torque')}.")


def _history_rows(physics, holdout, best, base, lofo) -> list[dict]:
    label = physics.get("label", "nominal")
    params = {e["name"]: e.get("params", {}) for e in physics.get("effects", [])}
    rows = []
    if "physics-only" in base:
        f, t = rmse(base["physics-only"])
        rows.append({"model_label": label, "force": f, "torque": t, "eval_mode": "holdout", "eval_flights": [holdout],
                     "parameters": params})
    for k, r in best.items():
        f, t = rmse(r["metrics"])
        rows.append({"model_label": f"{label}+{k}({r['feature_set']['name']})", "force": f, "torque": t,
                     "eval_mode": "holdout", "eval_flights": [holdout],
                     "parameters": {**params, "learned": {"run": r["name"], "spec": r["spec_label"]}}})
    if lofo:
        for name in ["physics-only", *[n for n in lofo["pooled"] if n not in BASELINES]]:
            f, t = rmse(lofo["pooled"][name])
            rows.append({"model_label": label if name == "physics-only" else f"{label}+{name}", "force": f,
                         "torque": t, "eval_mode": "leave-one-flight-out", "eval_flights": [],
                         "parameters": params})
    return rows


def record_history(root: str | Path, report: dict) -> list[Path]:
    """Append the report's headline results to the history (source ``learned``): the
    physics-only baseline and the best model of each kind on the held-out flight, and the
    pooled leave-one-flight-out results when they were run. Rows that repeat an unchanged model
    on the same flights are not added; returns the files written."""
    eff = report["setup"]["effects"]
    written = [history.record(root, "learned", h["model_label"], h["force"], h["torque"], eff,
                              h["parameters"], h["eval_mode"], h["eval_flights"]) for h in report["history_rows"]]
    return [p for p in written if p is not None]


# ---------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------

def _best_preds(report: dict, out_dir: Path) -> dict[str, pl.DataFrame]:
    return {k: store.read_parquet(store.as_root(out_dir) / name / "predictions.parquet")
            for k, name in report["best"].items()}


def timeseries_plot(report: dict, out_dir: Path, max_points: int = 4000) -> bytes:
    """Measured residual and the best models' predictions over time on the held-out flight."""
    preds = _best_preds(report, out_dir)
    fig, axes = plt.subplots(3, 2, figsize=(12, 7), sharex=True, layout="constrained")
    if not preds:
        plt.close(fig)
        return _empty("no learned model")
    first = next(iter(preds.values()))
    step = max(1, first.height // max_points)
    t = first["t_s"].to_numpy()[::step]
    for j, c in enumerate(TARGETS):
        ax = axes[j % 3, j // 3]
        scale = 1.0 if j < 3 else 1e3
        ax.plot(t, first[c].to_numpy()[::step] * scale, color="k", lw=0.9, label="measured residual")
        for k, p in preds.items():
            ax.plot(p["t_s"].to_numpy()[::step], p[PRED_COLUMNS[j]].to_numpy()[::step] * scale, lw=0.8,
                    label=f"{k} ({report_run(report, report['best'][k])['feature_set']})")
        ax.set_ylabel(f"{AXES[j]} body [{'N' if j < 3 else 'mN m'}]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t [s]")
    axes[-1, 1].set_xlabel("t [s]")
    fig.suptitle(f"{report['holdout']} (held out): residual after {report['setup']['physics_model']} "
                 "vs learned prediction")
    return plots._png(fig)


def report_run(report: dict, name: str) -> dict:
    return next(r for r in report["runs"] if r["name"] == name)


def _empty(text: str) -> bytes:
    fig, ax = plt.subplots(figsize=(4, 1))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.axis("off")
    return plots._png(fig)


REGIME_BINS = {  # the diagnosis's bins, so both reports cut the flight envelope alike
    "speed [m/s]": diagnosis.SPEED_BINS,
    "height [m]": diagnosis.HEIGHT_BINS,
    "angular rate [rad/s]": diagnosis.RATE_BINS,
    "thrust / weight": diagnosis.THRUST_BINS,
}


def regime_values(table: pl.DataFrame, vehicle) -> dict[str, np.ndarray]:
    return {
        "speed [m/s]": np.linalg.norm(table.select([f"v_w_{a}_mps" for a in XYZ]).to_numpy(), axis=1),
        "height [m]": table["p_w_z_m"].to_numpy(),
        "angular rate [rad/s]": np.linalg.norm(table.select([f"omega_b_{a}_radps" for a in XYZ]).to_numpy(), axis=1),
        "thrust / weight": table["T_N"].to_numpy() / vehicle.weight_N,
    }


def regime_table(report: dict, out_dir: Path, residual_tables: dict[str, pl.DataFrame], vehicle) -> pl.DataFrame:
    """Force and torque MAE (mean over axes) of the baselines and best models per regime bin,
    on the held-out flight."""
    holdout = report["holdout"]
    table = residual_tables[holdout]
    train = (report_run(report, next(iter(report["best"].values())))["train_flights"] if report["best"]
             else [f for f in residual_tables if f != holdout])
    base = baseline_predictions(residual_tables, train, [holdout], vehicle)
    models = {"physics-only": base["physics-only"], "training mean": base["training mean"]}
    models.update({f"{k} ({report_run(report, n)['feature_set']})": p for (k, n), p in
                   zip(report["best"].items(), _best_preds(report, out_dir).values())})
    values = regime_values(table, vehicle)
    frames = []
    for name, p in models.items():
        rows = p["row"].to_numpy()
        y, q = _yp(p)
        e = np.abs(y - q)
        for regime, edges in REGIME_BINS.items():
            x = values[regime][rows]
            idx = np.clip(np.searchsorted(np.asarray(edges[1:]), x, side="right"), 0, len(edges) - 1)
            labels = diagnosis.bin_labels(edges)
            for b in np.unique(idx):
                sel = idx == b
                frames.append({"model": name, "regime": regime, "bin": labels[b], "bin_index": int(b),
                               "samples": int(sel.sum()), "force MAE [N]": float(e[sel, :3].mean()),
                               "torque MAE [mN m]": float(e[sel, 3:].mean() * 1e3)})
    return pl.DataFrame(frames)


def regime_plot(reg: pl.DataFrame) -> bytes:
    regimes = list(REGIME_BINS)
    fig, axes = plt.subplots(2, len(regimes), figsize=(14, 6), layout="constrained")
    models = reg["model"].unique(maintain_order=True).to_list()
    w = 0.8 / max(1, len(models))
    for col, regime in enumerate(regimes):
        r = reg.filter(pl.col("regime") == regime)
        bins = r.select("bin", "bin_index").unique().sort("bin_index")
        x = np.arange(bins.height)
        for row, q in enumerate(("force MAE [N]", "torque MAE [mN m]")):
            ax = axes[row, col]
            for i, m in enumerate(models):
                rm = r.filter(pl.col("model") == m)
                vals = {b: v for b, v in zip(rm["bin"], rm[q])}
                ax.bar(x + (i - (len(models) - 1) / 2) * w, [vals.get(b, np.nan) for b in bins["bin"]], w, label=m)
            ax.set_xticks(x, bins["bin"].to_list(), fontsize=7, rotation=20)
            ax.grid(alpha=0.3, axis="y")
            if col == 0:
                ax.set_ylabel(q)
            if row == 0:
                ax.set_title(regime, fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("held-out error by flight regime")
    return plots._png(fig)


def permutation_importance(model: learning.LearnedModel, table: pl.DataFrame, seed: int = 0) -> dict[str, float]:
    """Increase of the held-out error (MSE in training-standardised target units, averaged over
    the six outputs) when one input column is shuffled."""
    m = feat.usable(table)
    X = feat.matrix(table, model.feature_set)[m]
    Y = model.y_scaler.transform(feat.targets(table)[m], np.float64)

    def err(Xp):
        return float(np.mean((model.y_scaler.transform(model.predict_matrix(Xp), np.float64) - Y) ** 2))

    base = err(X)
    rng = np.random.default_rng(seed)
    out = {}
    for j, name in enumerate(model.features):
        Xp = X.copy()
        Xp[:, j] = rng.permutation(Xp[:, j])
        out[name] = err(Xp) - base
    return out


def importance(report: dict, out_dir: Path, residual_tables: dict[str, pl.DataFrame]) -> dict[str, dict]:
    """Per best model: permutation importance on the held-out flight, and XGBoost's gain."""
    out = {}
    for k, name in report["best"].items():
        mdl = learning.load(store.as_root(out_dir) / name)
        t = feat.with_derived(residual_tables[report["holdout"]])
        out[k] = {"feature_set": mdl.feature_set.name, "permutation": permutation_importance(mdl, t),
                  "gain": mdl.importance()}
    return out


def importance_plot(imp: dict[str, dict]) -> bytes:
    panels = [(k, "permutation", v["permutation"], v["feature_set"]) for k, v in imp.items()]
    panels += [(k, "gain", v["gain"], v["feature_set"]) for k, v in imp.items() if v["gain"]]
    if not panels:
        return _empty("no learned model")
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4), layout="constrained", squeeze=False)
    for ax, (k, what, vals, fs) in zip(axes[0], panels):
        names = sorted(vals, key=vals.get)
        ax.barh(np.arange(len(names)), [vals[n] for n in names])
        ax.set_yticks(np.arange(len(names)), names, fontsize=7)
        what_label = ("permutation (held-out Δ MSE, std. units)" if what == "permutation"
                      else "XGBoost total gain (share)")
        ax.set_title(f"{k} ({fs}): {what_label}", fontsize=8)
        ax.grid(alpha=0.3, axis="x")
    return plots._png(fig)


def comparison_plot(report: dict) -> bytes:
    """Force and torque MAE (mean over axes) of every held-out run, the physics-only level dashed."""
    rows = [r for r in report["runs"] if r["split"] == f"holdout-{report['holdout']}"]
    base = report["baselines"].get(f"holdout-{report['holdout']}", {}).get("physics-only")
    if not rows:
        return _empty("no runs")
    rows = sorted(rows, key=lambda r: (r["kind"], r["feature_set"], r["train_group"], r["name"]))
    labels = [f"{r['kind']} {r['feature_set']}{'' if r['causal'] else '*'} {r['train_group']} "
              f"{r['name'].rsplit('__', 1)[-1].split('-', 1)[-1]}" for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(13, 0.28 * len(rows) + 1.8), layout="constrained")
    for ax, sl, scale, unit in ((axes[0], slice(0, 3), 1.0, "N"), (axes[1], slice(3, 6), 1e3, "mN m")):
        vals = [np.mean(mae(r["metrics"])[sl]) * scale for r in rows]
        colours = ["tab:blue" if r["kind"] == "xgboost" else "tab:orange" for r in rows]
        ax.barh(np.arange(len(rows)), vals, color=colours)
        if base:
            ax.axvline(np.mean(mae(base)[sl]) * scale, color="k", ls="--", lw=1, label="physics-only")
            ax.legend(fontsize=7)
        ax.set_yticks(np.arange(len(rows)), labels if ax is axes[0] else [""] * len(rows), fontsize=7)
        ax.set_xlabel(f"held-out {'force' if unit == 'N' else 'torque'} MAE, mean over axes [{unit}]")
        ax.grid(alpha=0.3, axis="x")
    fig.suptitle(f"every run on {report['holdout']} (* = feature set sees the target)")
    return plots._png(fig)


def make_plots(report: dict, out_dir: Path, residual_tables: dict[str, pl.DataFrame], vehicle,
               hist: pl.DataFrame | None = None) -> dict[str, bytes]:
    """All plots as PNG bytes; also stores the regime table and importances in ``report``."""
    from quadcore.report import report as diagnosis_report

    out = {"comparison": comparison_plot(report), "timeseries": timeseries_plot(report, out_dir)}
    if report["best"]:
        reg = regime_table(report, out_dir, residual_tables, vehicle)
        report["regimes"] = reg.to_dicts()
        out["regimes"] = regime_plot(reg)
        imp = importance(report, out_dir, residual_tables)
        report["importance"] = imp
        out["importance"] = importance_plot(imp)
    if hist is not None and hist.height:
        out["history"] = diagnosis_report.history_plot(hist)
    return out


# ---------------------------------------------------------------------------------------
# The report on disk
# ---------------------------------------------------------------------------------------

TABLE_TITLES = {
    "headline": "Our best models beside the study's (held-out flight)",
    "holdout": "Every model on the held-out flight, with the baselines",
    "feature_sets": "Feature sets (default model of each kind, all training flights)",
    "training_size": "Training set: random flights vs preplanned flights vs all",
    "complexity": "Model complexity (primary feature set)",
    "lofo": "Leave-one-flight-out cross-validation (per-fold MAE, mean and spread over folds)",
    "lofo_flights": "Leave-one-flight-out: force MAE (mean over axes) per left-out flight",
}


def frame(rows: list[dict]) -> pl.DataFrame:
    if not rows:
        return pl.DataFrame()
    df = pl.DataFrame(rows, infer_schema_length=None)
    return df.with_columns(pl.col(pl.Float64).round_sig_figs(3))


def markdown_table(df: pl.DataFrame, digits: int = 4) -> str:
    """A table as Markdown; missing values show as '-'."""
    def fmt(v):
        return "-" if v is None else (f"{v:.{digits}g}" if isinstance(v, float) else str(v))

    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.iter_rows()]
    return "\n".join(lines)


def sections(report: dict, pngs: dict[str, bytes]) -> list[tuple[str, str, object]]:
    s = report["setup"]
    secs: list[tuple[str, str, object]] = [
        ("Verdict", "text", report["verdict"]),
        ("Setup", "text",
         f"Held out: {s['holdout']} (trained on the other {len(s['flights']) - 1} flights). Physics model: "
         f"{s['physics_model']} on vehicle {s['vehicle']} (thrust map {s['thrust_map']}); {s['physics_fit']}. "
         f"Fitting rows: every {s['stride']}th sample; validation: {s['validation_fraction']:.0%} of the training "
         f"flights; seed {s['seed']}. {len(report['runs'])} models trained."),
        ("Definitions", "list", report["definitions"]),
        (TABLE_TITLES["headline"], "table", frame(report["tables"]["headline"])),
        ("What the study's numbers are", "text",
         "The study's residual mixed frames, its torque scaling used test data and it used a '+' rotor layout "
         "for this 'X' vehicle: its MAE is of a larger, different residual, so the figures stand beside ours for "
         "orientation, not as a target. Compare ours with our physics-only row."),
    ]
    if "comparison" in pngs:
        secs.append(("Every model on the held-out flight", "image", pngs["comparison"]))
    for key in ("holdout", "feature_sets", "training_size", "complexity", "lofo", "lofo_flights"):
        rows = report["tables"].get(key)
        if rows:
            secs.append((TABLE_TITLES[key], "table", frame(rows)))
    for key, title in (("timeseries", "Predicted vs measured residual over time (held-out flight)"),
                       ("regimes", "Error by flight regime (held-out flight)"),
                       ("importance", "Feature importance (best models)"),
                       ("history", "History: the error, evaluation after evaluation")):
        if key in pngs:
            secs.append((title, "image", pngs[key]))
    if report["notes"]:
        secs.append(("Notes", "list", {str(i + 1): n for i, n in enumerate(report["notes"])}))
    return secs


def to_markdown(secs, title: str = "Learned residual models") -> str:
    lines = [f"# {title}", ""]
    for t, kind, content in secs:
        lines += [f"## {t}", ""]
        if kind == "text":
            lines.append(str(content))
        elif kind == "list":
            lines += [f"- **{k}**: {v}" for k, v in content.items()]
        elif kind == "table":
            lines.append(markdown_table(content) if content.height else "(none)")
        else:
            lines.append(plots.markdown_image(content, t))
        lines.append("")
    return "\n".join(lines)


def to_html(secs, title: str = "Learned residual models") -> str:
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1400px;margin:2em auto}table{border-collapse:collapse;"
             "font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}img{max-width:100%}</style>",
             f"</head><body><h1>{html.escape(title)}</h1>"]
    for t, kind, content in secs:
        parts.append(f"<h2>{html.escape(t)}</h2>")
        if kind == "text":
            parts.append(f"<p>{html.escape(str(content))}</p>")
        elif kind == "list":
            parts.append("<ul>" + "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(str(v))}</li>"
                                          for k, v in content.items()) + "</ul>")
        elif kind == "table":
            head = "".join(f"<th>{html.escape(c)}</th>" for c in content.columns)
            body = "".join("<tr>" + "".join(f"<td>{html.escape('-' if v is None else str(v))}</td>" for v in row)
                           + "</tr>" for row in content.iter_rows())
            parts.append(f"<table><tr>{head}</tr>{body}</table>")
        else:
            b64 = base64.b64encode(content).decode()
            parts.append(f"<img alt='{html.escape(t)}' src='data:image/png;base64,{b64}'>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(report: dict, pngs: dict[str, bytes], out_dir: str | Path) -> dict[str, Path]:
    """``learning.md``, ``learning.html`` and ``learning.json`` in ``out_dir``."""
    out = store.as_root(out_dir)  # a folder here or in an object store
    secs = sections(report, pngs)
    paths = {"md": out / "learning.md", "html": out / "learning.html", "json": out / "learning.json"}
    store.write_text(to_markdown(secs), paths["md"])  # atomic, as every output
    store.write_text(to_html(secs), paths["html"])
    store.write_json(json.loads(json.dumps(report, default=_jsonable)), paths["json"])
    return paths


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def text_table(rows: list[dict], digits: int = 3) -> str:
    """A plain-text table for the terminal."""
    if not rows:
        return "(none)"
    cols = list(rows[0])

    def fmt(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.{digits}g}" if abs(v) < 1e4 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


def full_report(out_dir: str | Path, residual_tables: dict[str, pl.DataFrame], vehicle, report_dir: str | Path,
                root_for_history: str | Path | None = None,
                physics_trained_on: list[str] | None = None) -> tuple[dict, dict[str, bytes], dict[str, Path]]:
    """Evaluate, record the history (when ``root_for_history``), plot and write the report.
    ``physics_trained_on``: the flights the physics model's effects were fitted on (default: as
    the index says). Returns (report, plots, paths)."""
    report = evaluate(out_dir, residual_tables, vehicle, physics_trained_on)
    hist = None
    if root_for_history is not None:
        report["history_files"] = [str(p) for p in record_history(root_for_history, report)]
        hist = history.read(root_for_history)
    pngs = make_plots(report, out_dir, residual_tables, vehicle, hist)
    paths = write_report(report, pngs, report_dir)
    return report, pngs, paths
