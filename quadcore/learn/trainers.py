"""Training: XGBoost (squared error, ``hist``, one model with six outputs, early stopping on the
validation flights) and a PyTorch MLP (Adam on the mean squared error, mini-batches, the best
epoch's weights kept), seeded and reproducible (each kind in :mod:`quadcore.learn.backends`), and their
prediction timings.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import numpy as np
import polars as pl

from quadcore.learn.artefacts import LearnedModel
from quadcore.learn.backends import backend
from quadcore.learn.features import FeatureSet
from quadcore.learn.learners import LearnerSpec, LearningError, TrainConfig
from quadcore.learn.splits import training_data


def train(spec: LearnerSpec, fs: FeatureSet, tables: Mapping[str, pl.DataFrame], train_flights: list[str],
          config: TrainConfig | None = None, physics: dict | None = None,
          kinds: dict[str, str] | None = None) -> LearnedModel:
    """Train one model on ``train_flights`` (feature or residual tables by flight id).

    The scalers are fitted here, on those flights only. ``physics``: the physics model the
    residuals are relative to (``PhysicsModel.to_dict()``), stored in the manifest.
    """
    config = config or TrainConfig()
    if not train_flights:
        raise LearningError("no training flights")
    kind = backend(spec.kind)  # imported before the clock starts: the first import takes ~1 s
    t0 = time.perf_counter()
    d = training_data(tables, fs, list(train_flights), config, kinds)
    t1 = time.perf_counter()
    impl, info = kind.train(spec, d, config.seed, config.threads if spec.kind == "xgboost" else config.torch_threads)
    t2 = time.perf_counter()
    manifest = {
        "physics_model": physics or {},
        "train_flights": sorted(train_flights),
        "fit_flights": d.fit_flights,
        "validation_flights": d.val_flights,
        "validation": d.validation,
        "rows_fit": int(len(d.X_fit)),
        "rows_validation": int(len(d.X_val)),
        **d.rows.to_dict(),
        "config": config.to_dict(),
        "train_time_s": t2 - t0,  # data preparation + fit, including early stopping
        "fit_time_s": t2 - t1,
        **info,
    }
    return LearnedModel(spec, fs, d.x_scaler, d.y_scaler, impl, manifest)


def latency_us(fn: Callable, x: np.ndarray, repeats: int = 300) -> float:
    """Median wall time of ``fn(x)`` in microseconds (after 20 warm-up calls)."""
    for _ in range(20):
        fn(x)
    ts = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn(x)
        ts[i] = time.perf_counter() - t0
    return float(np.median(ts) * 1e6)


def time_predict(model: LearnedModel, X: np.ndarray, repeats: int = 5) -> tuple[np.ndarray, float]:
    """Predictions of ``X`` and the median time of ``repeats`` calls after one warm-up, s."""
    y = model.predict_matrix(X)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.predict_matrix(X)
        ts.append(time.perf_counter() - t0)
    return y, float(np.median(ts))
