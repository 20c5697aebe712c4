"""The append-only history of model evaluations: how the error falls, run after run.

Each evaluation of a model version (its effects and their parameters, or a learned
residual model on top) is one Parquet file of one row under ``<root>/history/``, never
rewritten::

    evaluated_at, source, model_label, effects, parameters (JSON), eval_mode, eval_flights,
    force_rmse_{x,y,z}_N, torque_rmse_{x,y,z}_Nm

Read them all with ``polars.scan_parquet("<root>/history/*.parquet")`` or :func:`read`.
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path

import polars as pl

from quadcore import store
from quadcore.dynamics import XYZ

RMSE_COLUMNS = [f"force_rmse_{a}_N" for a in XYZ] + [f"torque_rmse_{a}_Nm" for a in XYZ]


def history_dir(root: Path) -> Path:
    return Path(root) / "history"


def record(
    root: Path,
    source: str,
    model_label: str,
    force_rmse_N: list[float],
    torque_rmse_Nm: list[float],
    effects: list[str] | None = None,
    parameters: dict | None = None,
    eval_mode: str = "",
    eval_flights: list[str] | None = None,
) -> Path:
    """Append one evaluation (a new file); returns its path."""
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
    slug = re.sub(r"[^0-9A-Za-z]+", "-", model_label).strip("-")[:60]
    path = history_dir(root) / f"{now.strftime('%Y%m%dT%H%M%S%fZ')}-{source}-{slug}.parquet"
    return store.write_parquet(pl.DataFrame(row), path, {"kind": "evaluation"})


def read(root: Path) -> pl.DataFrame:
    """All evaluations, oldest first (empty frame if none)."""
    folder = history_dir(root)
    if not folder.is_dir() or not any(folder.glob("*.parquet")):
        return pl.DataFrame()
    return pl.read_parquet(folder / "*.parquet").sort("evaluated_at")
