"""Scores of a residual prediction and the baselines every learned model is compared with.

Each row predicts the residual force ``f_res_b_{x,y,z}_N`` (N) and torque ``tau_res_b_{x,y,z}_Nm``
(N m), body frame, left after the physics model; the error is ``residual - prediction`` (see
:mod:`quadcore.learn.evaluation` for what is scored and why).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import polars as pl

from quadcore.learn import features as feat
from quadcore.learn.artefacts import PRED_COLUMNS
from quadcore.learn.features import TARGETS
from quadcore.physics import dynamics, residuals
from quadcore.physics.dynamics import XYZ

BASELINES = ("physics-only", "zero", "training mean")
AXES = [f"F{a}" for a in XYZ] + [f"τ{a}" for a in XYZ]


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


def nominal_residual(table: pl.DataFrame, vehicle) -> np.ndarray:
    """(n, 6) residual of the nominal model (no effects) from a residual table of any model.

    A residual table carries every input of :func:`quadcore.physics.dynamics.flight_state` (time,
    pose, velocity, rates, accelerometer, PWM, battery, motor speeds), so the nominal residual
    is recomputed exactly as :func:`quadcore.physics.residuals.residual_arrays` computes it, with the
    same filters."""
    state = dynamics.flight_state(table, vehicle)
    r = residuals.residual_arrays(state, vehicle)
    return np.concatenate([r["f_res_b"], r["tau_res_b"]], axis=1)


def training_mean(residual_tables: Mapping[str, pl.DataFrame], train: list[str]) -> np.ndarray:
    """(6,) mean residual over the usable rows of the ``train`` flights, one flight at a time
    (memory flat in the flights). The running sum carries on row by row through each flight
    (NumPy sums a C-ordered (n, 6) array down its rows in order), so it is the mean of every
    row stacked, to the bit (checked on the 19 real flights), without holding them."""
    total, rows = np.zeros(len(TARGETS)), 0
    for f in train:
        y = feat.targets(residual_tables[f])[feat.usable(residual_tables[f])]
        total = np.add.reduce(np.vstack([total[None], y]), axis=0)
        rows += len(y)
    return total / rows


def baseline_predictions(residual_tables: Mapping[str, pl.DataFrame], train: list[str], test: list[str],
                         vehicle) -> dict[str, pl.DataFrame]:
    """Baseline predictions on the usable rows of the ``test`` flights, in the layout of a
    run's ``predictions.parquet`` (flight, row, t_s, targets, predictions)."""
    mean = training_mean(residual_tables, train)
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
