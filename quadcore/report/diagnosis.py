"""The diagnosis report: its plots and sections, kept on disk as Markdown and a standalone HTML page
(rendered by :mod:`quadcore.report.render`), plots inline or beside the Markdown."""

from __future__ import annotations

import functools
import hashlib
import json
import re
from collections import OrderedDict
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import polars as pl  # noqa: E402

from quadcore.commands import quadcore_command  # noqa: E402
from quadcore.identify import history
from quadcore.identify.diagnosis import verdict  # noqa: E402
from quadcore.identify.diagnosis.results import CandidateScore  # noqa: E402
from quadcore.identify.fit import sessions  # noqa: E402
from quadcore.identify.history import RMSE_COLUMNS  # noqa: E402
from quadcore.report import plots, render  # noqa: E402
from quadcore.store import store  # noqa: E402

TITLE = "Dynamics model diagnosis"

# How many plots each plot function remembers (see _drawn_once).
REMEMBERED_PLOTS = 4


def _drawn_once(fingerprint: Callable[..., bytes]):
    """A plot function that remembers its last few PNGs by a fingerprint of its input: the
    diagnosis asset attaches to its metadata the plots the report has just drawn (and
    error_history the history plot the report drew), so each is drawn once, not twice."""
    def wrap(draw: Callable[..., bytes]) -> Callable[..., bytes]:
        drawn: OrderedDict[str, bytes] = OrderedDict()

        @functools.wraps(draw)
        def plot(*args) -> bytes:
            key = hashlib.sha256(fingerprint(*args)).hexdigest()
            if key not in drawn:
                drawn[key] = draw(*args)
                while len(drawn) > REMEMBERED_PLOTS:
                    drawn.popitem(last=False)
            return drawn[key]
        return plot
    return wrap


def _json_of(*parts) -> bytes:
    return json.dumps(parts, sort_keys=True, default=str).encode()


def _frame_bytes(hist: pl.DataFrame) -> bytes:
    return _json_of(hist.columns, [str(t) for t in hist.dtypes], hist.rows())


@_drawn_once(lambda d: _json_of(d["candidates"]))
def candidates_plot(d: dict) -> bytes:
    """Share of the held-out residual each candidate removes, force and torque. Found
    candidates in full colour; the others faded and labelled with why (an unphysical fit is
    hatched: whatever it removes, it is no explanation)."""
    rows = d["candidates"][::-1]
    fig, ax = plt.subplots(figsize=(8, 0.4 * len(rows) + 1.3), layout="constrained")
    y = np.arange(len(rows))
    for offset, key, colour, label in ((-0.2, "explained_variance_force", "C0", "force"),
                                       (0.2, "explained_variance_torque", "C1", "torque")):
        for yi, r in zip(y, rows):
            found = r.get("found", r.get("useful", True))
            ax.barh(yi + offset, r[key], 0.4, color=colour, alpha=1.0 if found else 0.35,
                    hatch="//" if not r["physical"] else None, edgecolor="k" if not r["physical"] else None,
                    label=label if yi == y[-1] else None)
    ax.set_yticks(y, [f"{r['effect']} ({_short_status(r)})" for r in rows], fontsize=8)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("fraction of held-out residual removed (faded: not found; hatched: unphysical fit)")
    ax.set_xlim(-0.1, 1.0)
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    return plots._png(fig)


def _short_status(r: dict) -> str:
    status = r.get("status", "found" if r.get("useful") else "not found")
    if status == "tied":
        return f"tied, {r.get('grade', '')}"
    return r.get("grade", status) if status == "found" else status.replace("_", " ")


@_drawn_once(lambda d: _json_of(d["regimes"]))
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


@_drawn_once(lambda freq: _json_of(freq))
def frequency_plot(freq: dict) -> bytes:
    """Residual RMS of each flight's constant offset and by frequency band (top), coherence and
    gain of modelled vs measured by band (bottom); force left, torque right."""
    labels = ["mean"] + [f"{lo:g}-{hi:g}" for lo, hi in freq["bands_hz"]]
    x = np.arange(len(labels))
    rows = {r["channel"]: r for r in freq["channels"]}
    fig, axes = plt.subplots(2, 2, figsize=(12, 6), layout="constrained", sharex=True)
    for col, (kind, unit, scale) in enumerate((("force", "N", 1.0), ("torque", "mN m", 1e3))):
        for j, a in enumerate("xyz"):
            r = rows.get(f"{kind}_{a}")
            if r is None:
                continue
            rms = np.asarray([r.get("residual_mean_rms", np.nan), *r["residual_rms"]], dtype=float) * scale
            axes[0, col].bar(x + (j - 1) * 0.27, rms, 0.27, label=f"{kind} {a}")
            coherence, gain = (np.array(r[k], dtype=float) for k in ("coherence", "gain"))  # None (n/a): a gap
            line = axes[1, col].plot(x[1:], coherence, "o-", label=f"coherence {a}")[0]
            axes[1, col].plot(x[1:], gain, "s--", color=line.get_color(), alpha=0.6, label=f"gain {a}")
        axes[0, col].set_ylabel(f"residual RMS [{unit}]")
        axes[0, col].legend(fontsize=7)
        axes[1, col].set_ylabel("model vs measured")
        axes[1, col].set_ylim(0, 1.6)
        axes[1, col].axhline(1.0, color="k", lw=0.5)
        axes[1, col].legend(fontsize=6, ncol=3)
        axes[1, col].set_xticks(x, labels)
        axes[1, col].set_xlabel("each flight's mean, then frequency band [Hz]")
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
    return plots._png(fig)


def frequency_table(freq: dict) -> pl.DataFrame:
    """One row per channel and band: residual RMS (force in N, torque in mN m), its share,
    coherence, gain, phase (None where not defined: shown as n/a)."""
    scale = {r["channel"]: 1e3 if r["channel"].startswith("torque") else 1.0 for r in freq["channels"]}
    return pl.DataFrame([
        {"channel": r["channel"], "band_hz": f"{lo:g}-{hi:g}",
         "residual_rms": r["residual_rms"][i] * scale[r["channel"]],
         "share": r["residual_share"][i], "coherence": r["coherence"][i], "gain": r["gain"][i],
         "phase_deg": r["phase_deg"][i]}
        for r in freq["channels"] for i, (lo, hi) in enumerate(freq["bands_hz"])]
        + [{"channel": r["channel"], "band_hz": "mean per flight",
            "residual_rms": r["residual_mean_rms"] * scale[r["channel"]],
            "share": r["mean_share"], "coherence": None, "gain": None, "phase_deg": None}
           for r in freq["channels"]])


def discovery_table(disc: dict) -> pl.DataFrame:
    """The kept terms of a discovery (:mod:`quadcore.identify.discovery`), one row each."""
    return pl.DataFrame([
        {"target": t["target"], "term": t["expression"], "coefficient": t["coefficient"], "std": t["std"],
         "unit": t["unit"], "explained_held_out": t["explained_variance"], "stability": t["stability"],
         "matches": ", ".join(t.get("matches_effects", [])), "literature": t.get("literature", ""),
         "collinear_with": ", ".join(t.get("collinear_with", [])[:4])}
        for t in disc["terms"]])


def discovery_plot(disc: dict) -> bytes:
    """Held-out residual RMSE per axis before and after the discovered terms, relative."""
    fig, ax = plt.subplots(figsize=(7, 3), layout="constrained")
    labels = [f"F{a}" for a in "xyz"] + [f"τ{a}" for a in "xyz"]
    before = np.array(disc["baseline"]["force_rmse_N"] + disc["baseline"]["torque_rmse_Nm"])
    after = np.array(disc["after"]["force_rmse_N"] + disc["after"]["torque_rmse_Nm"])
    x = np.arange(6)
    ax.bar(x - 0.2, np.ones(6), 0.4, label="current model")
    ax.bar(x + 0.2, np.divide(after, before, out=np.ones(6), where=before > 0), 0.4, label="+ discovered terms")
    ax.set_xticks(x, labels)
    ax.set_ylabel("held-out residual RMSE (relative)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    return plots._png(fig)


def discovery_sections(disc: dict) -> list[tuple[str, str, object]]:
    """The discovery's part of the diagnosis report."""
    notes = [f"{a['target']}: {n}" for a in disc["axes"] for n in a["notes"]]
    out: list[tuple[str, str, object]] = [("Terms the library lacks (quadcore discover)", "text",
            f"On top of {'+'.join(['nominal', *disc['effects_in_model']])}, {disc['evaluation']['mode']}: "
            + ("; ".join(t["formula"] for t in disc["terms"]) if disc["terms"] else "no term kept") + "."
            + (" Notes: " + " ".join(notes) if notes else ""))]
    if disc["terms"]:
        out += [("Discovered terms", "table", discovery_table(disc)),
                ("Held-out error with the discovered terms", "image", discovery_plot(disc))]
    return out


# How many evaluation sets the history plot shows (the most recently evaluated ones).
HISTORY_PLOT_SETS = 3


@_drawn_once(_frame_bytes)
def history_plot(hist: pl.DataFrame) -> bytes:
    """The falling-error plot: per evaluation set (like with like), force [N] above torque
    [mN m], per axis, as steps from one model to the next."""
    sets = list(history.series(hist).items())[:HISTORY_PLOT_SETS]
    # force above torque, 8 inches wide: narrow enough for the asset page's metadata column
    fig, axes = plt.subplots(2 * len(sets), 1, figsize=(8, 3.2 * 2 * len(sets)), layout="constrained", squeeze=False)
    for (name, rows), ax_f, ax_t in zip(sets, axes[0::2, 0], axes[1::2, 0]):
        x = np.arange(rows.height)
        labels = [f"{i}: {lab}" for i, lab in enumerate(rows["model_label"].to_list())]
        for ax, kind, unit, scale in ((ax_f, "force", "N", 1.0), (ax_t, "torque", "mN m", 1e3)):
            for a in "xyz":
                col = f"{kind}_rmse_{a}_{'N' if kind == 'force' else 'Nm'}"
                ax.step(x, rows[col].to_numpy() * scale, where="post", marker="o", label=f"{kind} {a}")
            ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=7)
            ax.set_title(f"{name}: held-out {kind} residual RMSE", fontsize=9)
            ax.set_ylabel(f"RMSE [{unit}]")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            ax.set_ylim(bottom=0)
    return plots._png(fig)


def history_table(hist: pl.DataFrame) -> pl.DataFrame:
    """The history as a table: evaluation set, source, model, RMSE (force in N, torque in mN m)."""
    named = pl.concat([rows for rows in history.series(hist).values()]).sort("evaluated_at")
    return named.select(
        pl.col("evaluated_at").dt.strftime("%Y-%m-%d %H:%M:%S"), "evaluation_set", "source", "model_label",
        *[pl.col(c).round_sig_figs(3) for c in RMSE_COLUMNS if c.endswith("_N")],
        *[(pl.col(c) * 1e3).round_sig_figs(3).alias(c.replace("_Nm", "_mNm")) for c in RMSE_COLUMNS
          if c.endswith("_Nm")])


def headline(d: dict) -> str:
    """The verdict in one sentence: the effect most likely missing, how much it removes and how
    sure; or that none is found (the first sentence of the verdict, which says why); led by
    "Undecided between A and B" when the answer flips between folds (``stability``)."""
    stability = d.get("stability") or {}
    lead = stability["sentence"] + " " if stability.get("undecided_between") else ""
    found = [r for r in d["candidates"] if r.get("found", r.get("useful", False))]
    if not found:
        text = d["verdict"].removeprefix(lead)
        first = text.split(": ", 1)[0] if text.startswith("No effect") else text
        return lead + first.split(". ")[0].rstrip(".") + "."
    top = found[0]
    tied = top.get("tied_with", [])
    return lead + (f"Most likely missing: {top['effect']}, which removes {_percent(top['explained_variance'])} of the "
            f"held-out {top['target']} residual (p = {_p(top['held_out_p_value'])})"
            + (f"; these flights cannot tell it apart from {', '.join(tied)}" if tied else "") + ".")


def _percent(x: float) -> str:
    return f"{max(float(x), 0.0) * 100:.0f} %"


def _p(p: float) -> str:
    """A p-value for people: two significant digits (as the verdict writes it)."""
    return f"{p:.2g}"


def evidence_table(d: dict, limit: int = 6) -> pl.DataFrame:
    """The candidates best first, one row each: status, what each removes of the held-out force
    and torque residual, the test, the fitted parameters with their standard errors, and why."""
    return pl.DataFrame([{
        "effect": r["effect"], "status": r.get("status", "found" if r.get("useful") else "not found").replace("_", " "),
        "force removed": _percent(r["explained_variance_force"]),
        "torque removed": _percent(r["explained_variance_torque"]),
        "held-out p": _p(r["held_out_p_value"]),
        "parameters ± σ": ", ".join(f"{k} = {v:.4g} ± {r['parameter_std'].get(k, float('nan')):.2g}"
                                    for k, v in r["parameters"].items()),
        "why it ranks here": r.get("reason", ""),
    } for r in d["candidates"][:limit]], schema={c: pl.String for c in (
        "effect", "status", "force removed", "torque removed", "held-out p", "parameters ± σ", "why it ranks here")})


def next_step(d: dict, model_file: str = "", rerun: str = "") -> str:
    """What to do next, naming the file to edit and, given ``rerun``, the exact command that runs
    again on the same flights and settings (the main job's, with its variables)."""
    found = [r for r in d["candidates"] if r.get("found", r.get("useful", False))]
    where = model_file or "the model file (model.toml)"
    notes = _unique(n for dis in d.get("disagreements", []) for n in dis.get("notes", []))
    if found:
        again = f"`{rerun}`, or let the UI refit: it follows the model file" if rerun else \
            "the same command, or let the UI refit: it follows the model file"
        text = f"Add '{found[0]['effect']}' to `effects` in {where}, then run again ({again})."
    else:
        text = ("Nothing in the library to add. Look at where the model fails (regimes, frequency, worst segments "
                f"below), or search for terms the library lacks with `{quadcore_command()} discover ... "
                f"--write-effect DIR/NAME.py` and list the module under `plugins` and its name under `effects` in "
                f"{where}.")
    if notes:
        text += f" Parameters also differ between groups of flights: see that section (sessions go in {where})."
    return text


def _unique(items) -> list[str]:
    """Each text once, in first-seen order (the same note comes with every parameter it concerns)."""
    return list(dict.fromkeys(items))


def model_effects(m: dict) -> pl.DataFrame:
    """The fitted model's parameters (the JSON of :class:`quadcore.identify.model.PhysicsModel`),
    with what the fit says of each one held at a physical bound when there is one."""
    held = any(e.get("held_at_bound") for e in m["effects"])
    return pl.DataFrame([
        {"effect": e["name"], "parameter": k, "value": v, "std": e["std"].get(k, float("nan")),
         **({"held at a physical bound": e.get("held_at_bound", {}).get(k, {}).get("note", "")} if held else {})}
        for e in m["effects"] for k, v in e["params"].items()])


def session_values(d: dict) -> pl.DataFrame | None:
    """The values the model uses per session (``[per_session]`` in the model file), beside the
    fleet value a flight of no session gets; None when nothing is fitted per session."""
    rows = []
    for e in d["model"]["effects"]:
        for s, values in e.get("per_session", {}).items():
            flights = d["model"].get("sessions", {}).get(s, [])
            for k, v in values.items():
                rows.append({"effect": e["name"], "parameter": k, "session": s, "value": v,
                             "std": e.get("per_session_std", {}).get(s, {}).get(k, float("nan")),
                             "flights": f"{len(flights)}: {_flight_list(flights)}" if flights else "-",
                             "held at a physical bound":
                                 e.get("per_session_held_at_bound", {}).get(s, {}).get(k, {}).get("note", "")})
        if e.get("per_session"):
            for k, v in e["params"].items():
                rows.append({"effect": e["name"], "parameter": k, "session": "fleet (flights of no session)",
                             "value": v, "std": e["std"].get(k, float("nan")), "flights": "-",
                             "held at a physical bound": e.get("held_at_bound", {}).get(k, {}).get("note", "")})
    if rows and not any(r["held at a physical bound"] for r in rows):
        rows = [{k: v for k, v in r.items() if k != "held at a physical bound"} for r in rows]
    return pl.DataFrame(rows) if rows else None


def _flight_list(flights: list[str], limit: int = 8) -> str:
    return ", ".join(flights[:limit]) + (" ..." if len(flights) > limit else "")


def in_mNm(df: pl.DataFrame) -> pl.DataFrame:
    """A table's torque columns (``*_Nm``, SI) in mN m (``*_mNm``), the unit of every torque shown to people."""
    return df.with_columns(*[(pl.col(c) * 1e3).alias(c[:-3] + "_mNm") for c in df.columns if c.endswith("_Nm")]
                           ).drop([c for c in df.columns if c.endswith("_Nm")])


def sections(d: dict, hist: pl.DataFrame | None = None, disc: dict | None = None,
             model_file: str = "", rerun: str = "") -> list[tuple[str, str, object]]:
    """(title, kind, content) with kind in text / table / captioned / image: the headline, the
    evidence, the next step (naming ``model_file``), the sensitivity, then the details."""
    b = d["baseline"]
    ev = d["evaluation"]
    basis = d.get("sensitivity_basis", {})
    sens = verdict.sensitivity_rows(d.get("sensitivity", {}), basis)
    per_session = session_values(d)
    notes = _unique(n for dis in d.get("disagreements", []) for n in dis.get("notes", []))
    out: list[tuple[str, str, object] | None] = [
        ("Verdict", "text", headline(d)),
        ("How stable the answer is", "text", d["stability"]["sentence"]) if "stability" in d else None,
        ("Evidence: the candidate effects, best first", "table", evidence_table(d)) if d["candidates"] else None,
        ("Next step", "text", next_step(d, model_file, rerun)),
        ("Sensitivity: the smallest effect these flights would detect", "captioned", (
            f"Each parameter alone, detected {basis.get('detection_probability', 0.9):.0%} of the time at "
            f"{basis.get('false_alarm_probability', 0.01):.0%} false alarms for the whole library; below these "
            "values an effect would go unnoticed on these flights.", pl.DataFrame(sens))) if sens else None,
        ("The full reading", "text", d["verdict"]),
        ("Model", "text", f"{d['model']['label']} on vehicle {d['model']['vehicle']} "
                          f"(thrust map {d['model']['thrust_map']}); evaluated by "
                          f"{ev.get('protocol', ev['mode'])} ({ev['samples']} samples)"
                          + (f"; model file {model_file}" if model_file else "") + "."),
        ("Baseline residual (held-out) and sensor-noise floor", "table", pl.DataFrame({
            "quantity": ["force RMSE [N]", "torque RMSE [mN m]"]
            + (["force noise floor [N]", "torque noise floor [mN m]"] if "noise_floor" in d else []),
            **{a: [b["force_rmse_N"][i], b["torque_rmse_Nm"][i] * 1e3]
               + ([d["noise_floor"]["force_rmse_N"][i], d["noise_floor"]["torque_rmse_Nm"][i] * 1e3]
                  if "noise_floor" in d else [])
               for i, a in enumerate("xyz")},
        })),
    ]
    if d["model"]["effects"]:
        out.append(("Effects in the model (fleet values)", "table", model_effects(d["model"])))
    if per_session is not None:
        out.append(("Values per session, as the model uses them", "table", per_session))
    cands = (pl.DataFrame(verdict.candidate_summary(CandidateScore.from_dict(r) for r in d["candidates"]))
             if d["candidates"] else pl.DataFrame())
    out += [
        ("All candidate effects, and why each is ranked there", "table", cands) if d["candidates"] else None,
        ("Parameters that differ between groups of flights", "captioned",
         (" ".join(notes), pl.DataFrame(sessions.table_rows(d["disagreements"])))) if d.get("disagreements") else None,
        (("Fraction of held-out residual each candidate removes", "image", candidates_plot(d))
         if d["candidates"] else None),
        ("Where it fails: residual by regime", "image", regimes_plot(d)),
        ("Residual by regime (torque in mN m)", "table", in_mNm(pl.DataFrame(d["regimes"]))),
        ("Residual by flight (torque in mN m)", "table", in_mNm(pl.DataFrame(d["flights"]))),
        ("Worst segments (torque in mN m)", "table", in_mNm(pl.DataFrame(d["worst_segments"]))),
    ]
    freq = d.get("frequency")
    if freq and freq.get("channels"):
        out += [
            ("Where it fails, in frequency", "text", " ".join(freq["reading"])),
            ("Residual by frequency band; coherence and gain of modelled vs measured", "image", frequency_plot(freq)),
            ("Frequency bands (residual RMS: force in N, torque in mN m)", "table", frequency_table(freq)),
        ]
    if disc is not None:
        out += discovery_sections(disc)
    if hist is not None and hist.height:
        out.append(("History: the error, evaluation after evaluation", "image", history_plot(hist)))
        out.append(("History (torque in mN m)", "table", history_table(hist)))
    return [s for s in out if s is not None]


def write(d: dict, out_dir: Path, hist: pl.DataFrame | None = None, disc: dict | None = None,
          model_file: str = "", rerun: str = "") -> tuple[Path, Path]:
    """Write the report (with a discovery's section when ``disc`` is given), kept for good in
    ``out_dir/diagnosis/<UTC time>-<model>/`` (diagnosis.json, .md, .html and the plots as PNG
    beside the .md), and as the latest in ``out_dir/diagnosis.{md,html}`` (its .md links the kept
    PNGs). The .html is self-contained. Returns the latest (md, html)."""
    out_dir = store.as_root(out_dir)  # a folder here or in an object store
    secs = sections(d, hist, disc, model_file, rerun)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    kept = out_dir / "diagnosis" / f"{stamp}-{_slug(d['model']['label'])}"
    pngs = {title: f"{i:02d}-{_slug(title)}.png" for i, (title, kind, _) in enumerate(secs) if kind == "image"}
    for title, kind, content in secs:
        if kind == "image" and isinstance(content, bytes):
            store.write_bytes(content, kept / pngs[title])
    store.write_json(d, kept / "diagnosis.json")
    page_text = render.to_html(TITLE, secs)
    store.write_text(render.to_markdown(TITLE, secs, pngs), kept / "diagnosis.md")
    store.write_text(page_text, kept / "diagnosis.html")
    latest = {title: f"diagnosis/{kept.name}/{name}" for title, name in pngs.items()}
    md = store.write_text(render.to_markdown(TITLE, secs, latest), out_dir / "diagnosis.md")
    page = store.write_text(page_text, out_dir / "diagnosis.html")
    return md, page


def _slug(text: str) -> str:
    return re.sub(r"[^0-9A-Za-z]+", "-", text).strip("-")[:60] or "report"


def kept_reports(out_dir: Path) -> list[Path]:
    """Every kept diagnosis report folder under ``out_dir``, oldest first."""
    return sorted(p for p in (store.as_root(out_dir) / "diagnosis").glob("*") if p.is_dir())
