"""Reports on disk: the diagnosis as Markdown and as a standalone HTML page, plots inline.

Both are generated from the same sections, so they always say the same thing.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import polars as pl  # noqa: E402

from quadcore import plots  # noqa: E402
from quadcore.history import RMSE_COLUMNS  # noqa: E402


def candidates_plot(d: dict) -> bytes:
    rows = d["candidates"]
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.2), layout="constrained")
    names = [r["effect"] for r in rows][::-1]
    ax.barh(np.arange(len(rows)) - 0.2, [r["explained_variance_force"] for r in rows][::-1], 0.4, label="force")
    ax.barh(np.arange(len(rows)) + 0.2, [r["explained_variance_torque"] for r in rows][::-1], 0.4, label="torque")
    ax.set_yticks(np.arange(len(rows)), names)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("fraction of held-out residual removed")
    ax.set_xlim(-0.1, 1.0)
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    return plots._png(fig)


def regimes_plot(d: dict) -> bytes:
    reg = pl.DataFrame(d["regimes"])
    regimes = reg["regime"].unique(maintain_order=True).to_list()
    fig, axes = plt.subplots(2, (len(regimes) + 1) // 2, figsize=(13, 5.5), layout="constrained")
    for ax, regime in zip(axes.flat, regimes):
        r = reg.filter(pl.col("regime") == regime)
        x = np.arange(r.height)
        for j, a in enumerate("xyz"):
            ax.bar(x + (j - 1) * 0.27, r[f"force_rmse_{a}_N"], 0.27, label=f"F_{a}")
        ax.set_xticks(x, r["bin"].to_list(), rotation=30, fontsize=7)
        ax.set_title(regime, fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    axes.flat[0].set_ylabel("force residual RMSE [N]")
    axes.flat[0].legend(fontsize=7)
    for ax in list(axes.flat)[len(regimes):]:
        ax.axis("off")
    return plots._png(fig)


def history_plot(hist: pl.DataFrame) -> bytes:
    """Error per axis for each evaluation, in order: the falling-error plot."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.8), layout="constrained")
    x = np.arange(hist.height)
    labels = [f"{i}: {lab}" for i, lab in enumerate(hist["model_label"].to_list())]
    for ax, kind, unit in ((axes[0], "force", "N"), (axes[1], "torque", "Nm")):
        for a in "xyz":
            ax.plot(x, hist[f"{kind}_rmse_{a}_{unit}"], "o-", label=f"{kind} {a}")
        ax.set_xticks(x, labels, rotation=35, ha="right", fontsize=7)
        ax.set_ylabel(f"held-out {kind} residual RMSE [{unit.replace('Nm', 'N m')}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_ylim(bottom=0)
    return plots._png(fig)


def _table(df: pl.DataFrame) -> pl.DataFrame:
    return df.with_columns(pl.col(pl.Float64).round_sig_figs(3))


def sections(d: dict, hist: pl.DataFrame | None = None) -> list[tuple[str, str, object]]:
    """(title, kind, content) with kind in text / table / image."""
    b = d["baseline"]
    ev = d["evaluation"]
    out: list[tuple[str, str, object]] = [
        ("Verdict", "text", d["verdict"]),
        ("Model", "text", f"{d['model']['label']} on vehicle {d['model']['vehicle']} "
                          f"(thrust map {d['model']['thrust_map']}); evaluated by {ev['mode']} over "
                          f"{len(ev['eval_flights'])} flights ({ev['samples']} samples)."),
        ("Baseline residual (held-out) and sensor-noise floor", "table", pl.DataFrame({
            "quantity": ["force RMSE [N]", "torque RMSE [N m]"]
            + (["force noise floor [N]", "torque noise floor [N m]"] if "noise_floor" in d else []),
            **{a: [b["force_rmse_N"][i], b["torque_rmse_Nm"][i]]
               + ([d["noise_floor"]["force_rmse_N"][i], d["noise_floor"]["torque_rmse_Nm"][i]] if "noise_floor" in d else [])
               for i, a in enumerate("xyz")},
        })),
    ]
    if d["model"]["effects"]:
        out.append(("Effects in the model", "table", pl.DataFrame([
            {"effect": e["name"], "parameter": k, "value": v, "std": e["std"].get(k, float("nan"))}
            for e in d["model"]["effects"] for k, v in e["params"].items()
        ])))
    cands = pl.DataFrame([{
        "effect": r["effect"], "target": r["target"], "explained": r["explained_variance"],
        "force": r["explained_variance_force"], "torque": r["explained_variance_torque"],
        "parameters": ", ".join(f"{k}={v:.4g}±{r['parameter_std'].get(k, float('nan')):.2g}" for k, v in r["parameters"].items()),
        "significance_sigma": r.get("significance_sigma", float("nan")),
        "useful": r.get("useful", True),
        "alike": ", ".join(r["indistinguishable_from"]),
        "tied_with": ", ".join(r.get("tied_with", [])),
        "notes": "; ".join(r["notes"]),
    } for r in d["candidates"]]) if d["candidates"] else pl.DataFrame()
    out += [
        ("Candidate effects, best first", "table", cands),
        ("Fraction of held-out residual each candidate removes", "image", candidates_plot(d)) if d["candidates"] else None,
        ("Where it fails: residual by regime", "image", regimes_plot(d)),
        ("Residual by regime", "table", pl.DataFrame(d["regimes"])),
        ("Residual by flight", "table", pl.DataFrame(d["flights"])),
        ("Worst segments", "table", pl.DataFrame(d["worst_segments"])),
    ]
    if hist is not None and hist.height:
        out.append(("History: the error, evaluation after evaluation", "image", history_plot(hist)))
        out.append(("History", "table", hist.select("evaluated_at", "source", "model_label", *RMSE_COLUMNS)))
    return [s for s in out if s is not None]


def to_markdown(secs) -> str:
    lines = ["# Dynamics model diagnosis", ""]
    for title, kind, content in secs:
        lines += [f"## {title}", ""]
        if kind == "text":
            lines.append(str(content))
        elif kind == "table":
            lines.append(plots.markdown_table(_table(content)) if content.height else "(none)")
        else:
            lines.append(plots.markdown_image(content, title))
        lines.append("")
    return "\n".join(lines)


def to_html(secs) -> str:
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>Dynamics model diagnosis</title>",
             "<style>body{font-family:sans-serif;max-width:1200px;margin:2em auto}table{border-collapse:collapse;"
             "font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}img{max-width:100%}</style>",
             "</head><body><h1>Dynamics model diagnosis</h1>"]
    for title, kind, content in secs:
        parts.append(f"<h2>{html.escape(title)}</h2>")
        if kind == "text":
            parts.append(f"<p>{html.escape(str(content))}</p>")
        elif kind == "table":
            t = _table(content)
            head = "".join(f"<th>{html.escape(c)}</th>" for c in t.columns)
            body = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>" for row in t.iter_rows())
            parts.append(f"<table><tr>{head}</tr>{body}</table>")
        else:
            parts.append(f"<img alt='{html.escape(title)}' src='data:image/png;base64,{base64.b64encode(content).decode()}'>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write(d: dict, out_dir: Path, hist: pl.DataFrame | None = None) -> tuple[Path, Path]:
    """Write ``diagnosis.md`` and ``diagnosis.html`` into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    secs = sections(d, hist)
    md, page = out_dir / "diagnosis.md", out_dir / "diagnosis.html"
    md.write_text(to_markdown(secs))
    page.write_text(to_html(secs))
    return md, page
