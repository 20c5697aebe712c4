"""The append-only history of model evaluations: how the error falls, run after run.

Each evaluation of a model version (its effects and their parameters, or a learned
residual model on top) is one Parquet file of one row under ``<root>/history/``, never
rewritten::

    evaluated_at, source, model_label, effects, parameters (JSON), eval_mode, eval_flights,
    force_rmse_{x,y,z}_N, torque_rmse_{x,y,z}_Nm

Read them all with ``polars.scan_parquet("<root>/history/*.parquet")`` or :func:`read`.

Rows compare only within one *evaluation set* (the same mode on the same flights: cross-validated
on 3 flights and held out on jana02 are different questions). A row is added only when the model
(label, parameters) or the evaluation set changed since that set's last row with the same source:
re-running an unchanged model adds nothing, so a series reads as the steps of the improvement.
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path

import polars as pl

from quadcore.physics.dynamics import XYZ
from quadcore.store import store

RMSE_COLUMNS = [f"force_rmse_{a}_N" for a in XYZ] + [f"torque_rmse_{a}_Nm" for a in XYZ]


def history_dir(root: str | Path) -> Path:
    return store.as_root(root) / "history"


def record(
    root: str | Path,
    source: str,
    model_label: str,
    force_rmse_N: list[float],
    torque_rmse_Nm: list[float],
    effects: list[str] | None = None,
    parameters: dict | None = None,
    eval_mode: str = "",
    eval_flights: list[str] | None = None,
) -> Path | None:
    """Append one evaluation (a new file); returns its path, or None when the same model was
    already the latest evaluation of this source on this evaluation set (nothing changed)."""
    now = datetime.now(UTC)
    row = {
        "evaluated_at": [now],
        "source": [source],
        "model_label": [model_label],
        "effects": [",".join(effects or [])],
        "parameters": [json.dumps(parameters or {}, default=float)],
        "eval_mode": [eval_mode],
        "eval_flights": [",".join(eval_flights or [])],
        **{c: [float(v)] for c, v in zip(RMSE_COLUMNS, [*force_rmse_N, *torque_rmse_Nm])},
    }
    if _unchanged(read(root), row):
        return None
    slug = re.sub(r"[^0-9A-Za-z]+", "-", model_label).strip("-")[:60]
    path = history_dir(root) / f"{now.strftime('%Y%m%dT%H%M%S%fZ')}-{source}-{slug}.parquet"
    return store.write_parquet(pl.DataFrame(row), path, {"kind": "evaluation"})


def _unchanged(hist: pl.DataFrame, row: dict) -> bool:
    """Whether ``row`` repeats the latest row of its source on its evaluation set."""
    if hist.height == 0:
        return False
    same_set = hist.filter((pl.col("source") == row["source"][0]) & (pl.col("eval_mode") == row["eval_mode"][0])
                           & (pl.col("eval_flights") == row["eval_flights"][0]))
    same_model = same_set.filter(pl.col("model_label") == row["model_label"][0])
    if same_model.height == 0:
        return False
    last_of_set, last_of_model = same_set.row(-1, named=True), same_model.row(-1, named=True)
    return last_of_set == last_of_model and last_of_model["parameters"] == row["parameters"][0]


def evaluation_set(eval_mode: str, eval_flights: str) -> str:
    """A readable name of an evaluation set, e.g. ``holdout on jana02`` or
    ``cross-validation on 6 flights``."""
    flights = [f for f in eval_flights.split(",") if f]
    if not flights:
        return eval_mode or "unknown"
    on = ", ".join(flights) if len(flights) <= 2 else f"{len(flights)} flights"
    return f"{eval_mode} on {on}"


def series(hist: pl.DataFrame) -> dict[str, pl.DataFrame]:
    """The history split by evaluation set (name -> its rows, oldest first), most recently
    evaluated set first: each one a like-with-like series."""
    if hist.height == 0:
        return {}
    named = hist.with_columns(pl.struct("eval_mode", "eval_flights").map_elements(
        lambda s: evaluation_set(s["eval_mode"], s["eval_flights"]), return_dtype=pl.String).alias("evaluation_set"))
    latest = named.group_by("evaluation_set").agg(pl.col("evaluated_at").max()).sort("evaluated_at", descending=True)
    return {name: named.filter(pl.col("evaluation_set") == name).sort("evaluated_at")
            for name in latest["evaluation_set"]}


def read(root: str | Path) -> pl.DataFrame:
    """All evaluations, oldest first (empty frame if none)."""
    files = sorted(history_dir(root).glob("*.parquet"))  # a folder here or in an object store
    if not files:
        return pl.DataFrame()
    return pl.concat([store.read_parquet(p) for p in files]).sort("evaluated_at")
