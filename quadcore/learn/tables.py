"""The comparison tables of the learning report: every model beside the baselines and the study,
leave-one-flight-out summaries, error by regime, feature importance, the verdict sentence.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from quadcore.identify.describe import regimes
from quadcore.learn import artefacts, features as feat
from quadcore.learn.metrics import AXES, BASELINES, _yp, baseline_predictions, mae, metrics, r2
from quadcore.physics.dynamics import XYZ
from quadcore.store import store

STUDY: dict[str, dict[str, Any]] = {
    "xgboost": {"label": "study: best tree (XGBoost)", "force_mae_N": (0.021, 0.037, 0.011), "train_s": 41.9,
                "predict_s": 0.03},
    "mlp": {"label": "study: best MLP (PyTorch)", "force_mae_N": (0.022, 0.039, 0.077), "train_s": 66.9,
            "predict_s": 0.28},
}


def _model_has_effects(physics: dict) -> bool:
    return bool((physics or {}).get("effects"))


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


def _best_preds(report: dict, out_dir: str | Path) -> dict[str, pl.DataFrame]:
    return {k: store.read_parquet(store.as_root(out_dir) / name / "predictions.parquet")
            for k, name in report["best"].items()}


def report_run(report: dict, name: str) -> dict:
    return next(r for r in report["runs"] if r["name"] == name)


REGIME_BINS = {  # the diagnosis's bins, so both reports cut the flight envelope alike
    "speed [m/s]": regimes.SPEED_BINS,
    "height [m]": regimes.HEIGHT_BINS,
    "angular rate [rad/s]": regimes.RATE_BINS,
    "thrust / weight": regimes.THRUST_BINS,
}


def regime_values(table: pl.DataFrame, vehicle) -> dict[str, np.ndarray]:
    return {
        "speed [m/s]": np.linalg.norm(table.select([f"v_w_{a}_mps" for a in XYZ]).to_numpy(), axis=1),
        "height [m]": table["p_w_z_m"].to_numpy(),
        "angular rate [rad/s]": np.linalg.norm(table.select([f"omega_b_{a}_radps" for a in XYZ]).to_numpy(), axis=1),
        "thrust / weight": table["T_N"].to_numpy() / vehicle.weight_N,
    }


def regime_table(report: dict, out_dir: str | Path, residual_tables: Mapping[str, pl.DataFrame],
                 vehicle) -> pl.DataFrame:
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
            labels = regimes.bin_labels(edges)
            for b in np.unique(idx):
                sel = idx == b
                frames.append({"model": name, "regime": regime, "bin": labels[b], "bin_index": int(b),
                               "samples": int(sel.sum()), "force MAE [N]": float(e[sel, :3].mean()),
                               "torque MAE [mN m]": float(e[sel, 3:].mean() * 1e3)})
    return pl.DataFrame(frames)


# Permutation importance predicts the held-out rows once per input column: on a long held-out
# flight, on this many of its rows (evenly spaced), so that its cost has a ceiling.
PERMUTATION_ROWS = 50_000


def permutation_importance(model: artefacts.LearnedModel, table: pl.DataFrame, seed: int = 0,
                           max_rows: int = PERMUTATION_ROWS) -> dict[str, float]:
    """Increase of the held-out error (MSE in training-standardised target units, averaged over
    the six outputs) when one input column is shuffled, on the usable rows of ``table`` (at most
    ``max_rows`` of them, evenly spaced)."""
    rows = np.flatnonzero(feat.usable(table))
    if len(rows) > max_rows:
        rows = rows[np.linspace(0, len(rows) - 1, max_rows).astype(np.int64)]
    X = feat.matrix(table, model.feature_set)[rows]
    Y = model.y_scaler.transform(feat.targets(table)[rows], np.float64)

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


def importance(report: dict, out_dir: str | Path, residual_tables: Mapping[str, pl.DataFrame]) -> dict[str, dict]:
    """Per best model: permutation importance on the held-out flight, and XGBoost's gain."""
    out = {}
    for k, name in report["best"].items():
        mdl = artefacts.load(store.as_root(out_dir) / name)
        t = feat.with_derived(residual_tables[report["holdout"]])
        out[k] = {"feature_set": mdl.feature_set.name, "permutation": permutation_importance(mdl, t),
                  "gain": mdl.importance()}
    return out


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
