"""How good the learned residual models are: the evaluation of a training run's models on the held-out
flight, its record in the history, and the report (scores in :mod:`quadcore.learn.metrics`, tables in
:mod:`quadcore.learn.tables`, plots and sections in :mod:`quadcore.report.learning`).

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

**Learned models** (:mod:`quadcore.learn.trainers` (``docs/learning.md``)): ``P`` plus the model's predicted residual.
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

from collections.abc import Mapping
from pathlib import Path

import polars as pl

from quadcore.identify import history
from quadcore.learn import experiments, learners
from quadcore.learn.metrics import BASELINES, _yp, baseline_predictions, metrics, rmse
from quadcore.learn.tables import (
    _model_has_effects,
    _run_row,
    captured_share,
    headline_table,
    lofo_summary,
    results_table,
    verdict,
)


def evaluate(out_dir: str | Path, residual_tables: Mapping[str, pl.DataFrame], vehicle,
             physics_trained_on: list[str] | None = None) -> dict:
    """Score every run of ``out_dir`` (see :func:`quadcore.learn.experiments.run_plan`) and the baselines
    on the same held-out rows; build the comparison tables. Returns the report as a dict
    (JSON-able; tables as lists of rows)."""
    index, runs = experiments.read_runs(out_dir)
    physics = index.get("physics_model") or {}
    holdout = index["holdout"]
    missing = sorted({f for r in runs for f in r["test_flights"] + r["train_flights"]} - set(residual_tables))
    if missing:
        raise learners.LearningError(f"no residual table for flight(s) {', '.join(missing)}")
    preds = {r["name"]: experiments.read_predictions(r) for r in runs}
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
    elif holdout in trained_on:  # the default: no holdout named (a named one the physics saw is refused)
        leak = (f"the physics model's effects were fitted on flights that include {holdout} (no holdout was "
                f"named: the physics and its diagnosis use every flight); the learned models never saw {holdout}, "
                "so what they add is scored out of sample, while the physics-only row is in-sample for the "
                f"physics's few parameters (QUADCORE_HOLDOUT={holdout} keeps it out of the physics fit too)")
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
        "row_budget": cfg.get("max_rows"),
        "training_rows": training_rows(runs, holdout, cfg.get("seed")),
        "validation_fraction": cfg.get("val_fraction"),
        "flight_kinds": index.get("flight_kinds", {}),
    }


def training_rows(runs: list[dict], holdout: str, seed) -> str:
    """"trained on N of M rows: the row budget" for the held-out split's runs on all training
    flights (:func:`quadcore.learn.splits.budget_rows`), or "" for runs that did not record it."""
    run = next((r for r in runs if r["split"]["name"] == f"holdout-{holdout}" and r["train_group"] == "all"
                and "rows_held" in r), None)
    if run is None:
        return ""
    held, usable, budget, quota = run["rows_held"], run["rows_usable"], run["row_budget"], run["rows_per_flight"]
    if quota is None:
        return (f"trained on all {usable:,} usable rows of the training flights (within the row budget of "
                f"{budget:,} rows, QUADCORE_LEARN_ROWS)")
    return (f"trained on {held:,} of {usable:,} usable rows of the training flights: the row budget of {budget:,} "
            f"rows (QUADCORE_LEARN_ROWS), at most {quota:,} rows of each flight, drawn with seed {seed}")


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
        "subsampling": "fitting rows: every stride-th sample of the fitting flights; validation and test rows: all; "
                       "above the row budget, the training flights' rows are first drawn evenly per flight",
    }


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
