"""Training: XGBoost (squared error, ``hist``, one model with six outputs, early stopping on the
validation flights) and a PyTorch MLP (Adam on the mean squared error, mini-batches, the best
epoch's weights kept), seeded and reproducible, and their prediction timings.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import numpy as np
import polars as pl

from quadcore.learn.artefacts import LearnedModel, mlp_module
from quadcore.learn.features import FeatureSet
from quadcore.learn.learners import LearnerSpec, LearningError, TrainConfig
from quadcore.learn.splits import TrainingData, training_data


def _train_xgboost(spec: LearnerSpec, d: TrainingData, seed: int, threads: int):
    import xgboost as xgb

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


def _train_mlp(spec: LearnerSpec, d: TrainingData, seed: int, threads: int):
    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    net = mlp_module(d.X_fit.shape[1], spec.hidden, d.Y_fit.shape[1])
    opt = torch.optim.Adam(net.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    xf, yf = torch.from_numpy(d.X_fit), torch.from_numpy(d.Y_fit.astype(np.float32))
    xv, yv = torch.from_numpy(d.X_val), torch.from_numpy(d.Y_val.astype(np.float32))
    n, bs = len(xf), max(1, spec.batch_size)
    best, best_state, best_epoch, bad, epochs = float("inf"), None, -1, 0, 0
    for epoch in range(spec.max_epochs):
        net.train()
        perm = torch.randperm(n, generator=gen)
        for i in range(0, n, bs):
            idx = perm[i: i + bs]
            loss = torch.nn.functional.mse_loss(net(xf[idx]), yf[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            vl = float(torch.nn.functional.mse_loss(net(xv), yv))
        epochs = epoch + 1
        if vl < best:
            best, best_epoch, bad = vl, epoch, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            bad += 1
            if bad >= spec.patience:
                break
    if best_state is None:  # no epoch ran, or every validation loss was NaN (diverged)
        raise LearningError(f"MLP {spec.label}: no epoch gave a finite validation loss "
                            f"({epochs} epoch(s) run): raise max_epochs or lower lr")
    net.load_state_dict(best_state)
    net.eval()
    return net, {"epochs": epochs, "best_epoch": best_epoch, "val_loss": best}


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
    if spec.kind == "xgboost":  # imported before the clock starts: the first import takes ~1 s
        import xgboost  # noqa: F401
    else:
        import torch  # noqa: F401
    t0 = time.perf_counter()
    d = training_data(tables, fs, list(train_flights), config, kinds)
    t1 = time.perf_counter()
    if spec.kind == "xgboost":
        impl, info = _train_xgboost(spec, d, config.seed, config.threads)
    else:
        impl, info = _train_mlp(spec, d, config.seed, config.torch_threads)
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
