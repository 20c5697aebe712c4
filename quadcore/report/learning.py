"""The learning report: its plots and its sections, written as Markdown, HTML and JSON
(``<root>/reports/learning.{md,html,json}``) by the one renderer, :mod:`quadcore.report.render`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import polars as pl

from quadcore.learn.artefacts import PRED_COLUMNS
from quadcore.learn.features import TARGETS
from quadcore.learn.metrics import AXES, mae
from quadcore.learn.tables import REGIME_BINS, TABLE_TITLES, _best_preds, frame, importance, regime_table, report_run
from quadcore.report import diagnosis as diagnosis_report, plots, render
from quadcore.store import store

TITLE = "Learned residual models"


def timeseries_plot(report: dict, out_dir: str | Path, max_points: int = 4000) -> bytes:
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


def _empty(text: str) -> bytes:
    fig, ax = plt.subplots(figsize=(4, 1))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.axis("off")
    return plots._png(fig)


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


def make_plots(report: dict, out_dir: str | Path, residual_tables: Mapping[str, pl.DataFrame], vehicle,
               hist: pl.DataFrame | None = None) -> dict[str, bytes]:
    """All plots as PNG bytes; also stores the regime table and importances in ``report``."""
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


def sections(report: dict, pngs: dict[str, bytes]) -> list[tuple[str, str, object]]:
    s = report["setup"]
    secs: list[tuple[str, str, object]] = [
        ("Verdict", "text", report["verdict"]),
        ("Setup", "text",
         f"Held out: {s['holdout']} (trained on the other {len(s['flights']) - 1} flights: a learned model needs a "
         "flight it never saw to be scored). Physics model: "
         f"{s['physics_model']} on vehicle {s['vehicle']} (thrust map {s['thrust_map']}); {s['physics_fit']}. "
         f"Fitting rows: every {s['stride']}th sample; validation: {s['validation_fraction']:.0%} of the training "
         f"flights; seed {s['seed']}. {len(report['runs'])} models trained"
         + (f"; {s['training_rows']}." if s.get("training_rows") else ".")),
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


def write_report(report: dict, pngs: dict[str, bytes], out_dir: str | Path) -> dict[str, Path]:
    """``learning.md``, ``learning.html`` and ``learning.json`` in ``out_dir``."""
    out = store.as_root(out_dir)  # a folder here or in an object store
    secs = sections(report, pngs)
    paths = {"md": out / "learning.md", "html": out / "learning.html", "json": out / "learning.json"}
    store.write_text(render.to_markdown(TITLE, secs), paths["md"])  # atomic, as every output
    store.write_text(render.to_html(TITLE, secs), paths["html"])
    store.write_json(json.loads(json.dumps(report, default=_jsonable)), paths["json"])
    return paths


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
