"""XGBoost: squared error, ``hist``, one model with six outputs (one tree per output and round), early
stopping on the validation flights, the trees up to the best round kept. Imported through
:func:`quadcore.learn.backends.backend`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import xgboost as xgb

if TYPE_CHECKING:
    from quadcore.learn.learners import LearnerSpec
    from quadcore.learn.splits import TrainingData

FILE = "model.ubj"


def train(spec: LearnerSpec, d: TrainingData, seed: int, threads: int) -> tuple[xgb.Booster, dict]:
    params = {
        "objective": "reg:squarederror", "tree_method": "hist", "max_depth": spec.max_depth,
        "eta": spec.learning_rate, "subsample": spec.subsample, "min_child_weight": spec.min_child_weight,
        "nthread": threads, "seed": seed, "multi_strategy": "one_output_per_tree",
    }
    dfit = xgb.QuantileDMatrix(d.X_fit, d.Y_fit, nthread=threads)
    dval = xgb.QuantileDMatrix(d.X_val, d.Y_val, ref=dfit, nthread=threads)
    booster = xgb.train(params, dfit, num_boost_round=spec.n_estimators, evals=[(dval, "val")],
                        early_stopping_rounds=spec.early_stopping_rounds, verbose_eval=False)
    best = int(booster.best_iteration)
    booster = booster[: best + 1]  # keep the trees up to the best validation round
    val_loss = float(np.mean((booster.inplace_predict(d.X_val) - d.Y_val) ** 2))
    return booster, {"best_iteration": best, "trees_per_output": best + 1, "val_loss": val_loss}


def predict(impl: xgb.Booster, Z: np.ndarray) -> np.ndarray:
    """Scaled features (n, k) -> scaled outputs (n, 6)."""
    return np.asarray(impl.inplace_predict(Z))


def save(impl: xgb.Booster, folder: Path) -> None:
    impl.save_model(str(folder / FILE))


def load(folder: Path, spec: LearnerSpec, n_in: int, n_out: int, threads: int) -> xgb.Booster:
    impl = xgb.Booster(model_file=str(folder / FILE))
    impl.set_param({"nthread": threads})
    return impl
