"""Learned residual models: what the physics cannot explain, learned from flight state.

A learned model predicts the residual force and torque left after the current physics model
(nominal vehicle + the user's effects), body frame, SI, from a feature set of
:mod:`quadcore.learn.features`. Two kinds, as in the study this project grows from:

* ``xgboost``: gradient-boosted trees (squared error, ``hist``), one model with six outputs
  (``multi_strategy="one_output_per_tree"``), configurable depth and maximum number of trees;
  the number actually kept is chosen by early stopping on the validation flights.
* ``mlp``: a PyTorch multilayer perceptron (ReLU, 0, 1 or 2+ hidden layers), Adam on the
  mean squared error, mini-batches, early stopping on the validation flights (the weights
  of the best epoch are kept).

**Data.** Flights split into training and test flights (:class:`Split`: the fixed holdout,
or leave-one-flight-out). The training flights split again, by flight, into fitting and
validation flights (:func:`validation_flights`, 20 %, seeded, balanced over flight kinds
when those are known); with a single training flight the last 20 % of it validates.
Rows near logging gaps are never used. Fitting rows are **subsampled** (every
``stride``-th sample, default 5, i.e. 100 Hz out of 500 Hz): the residual is smoothed over a
62 ms window, so neighbouring samples at 500 Hz are nearly identical and using them all
costs time and adds nothing. Validation and test rows are not subsampled.

**Scaling.** Inputs and targets are standardised with a :class:`~quadcore.learn.features.Scaler`
fitted on the training flights' usable rows (fitting + validation flights, never a test
flight). The trees need the target scaling too: without it the torque's squared-error
gradients (~1e-4 N m) would be tiny next to XGBoost's L2 leaf regularisation and the torque
would barely be fitted.

**Reproducible.** Same data, spec and seed -> the same model: XGBoost's ``seed`` and a fixed
number of threads, torch's ``manual_seed`` and a seeded generator for the batch order;
XGBoost on ``threads`` and torch on ``torch.set_num_threads(torch_threads)``, one each by
default (:class:`TrainConfig` says why: measured faster than two on the 2-core machine).
:func:`run_plan` trains the XGBoost experiments and the MLPs at the same time, one thread
each, and the models are those of a sequential run (:func:`train_experiments`).

**Artefacts** (:meth:`LearnedModel.save`, :func:`load`), one folder per model under
``<root>/learned/<run name>/``: ``model.ubj`` (XGBoost) or ``model.pt`` (torch state dict),
``scaler.json`` (input and target scalers), ``features.json`` (the feature set),
``manifest.json`` (kind, hyper-parameters, the vehicle and effects of the physics model it was
trained against, training / validation / test flights, timings, metrics), and
``predictions.parquet`` (its predictions on its test flights).

**Predict API**::

    m = learning.load("data/learned/holdout-jana02__all__physics__xgboost-d6")
    f_N, tau_Nm = m.predict(table)        # (n, 3) each, body frame, SI
    m.predict_table(table)                 # t_s, f_learned_b_{x,y,z}_N, tau_learned_b_{x,y,z}_Nm

``table`` is a residual table of the same physics model (or a decoded ``fixedFrequency``
table, from which the manifest's physics model builds one). :meth:`LearnedModel.predict_one`
is the per-sample path: for trees a compiled NumPy forest (the same trees and thresholds,
evaluated level by level for all trees at once), because XGBoost's own Python call costs
~80 us per call before any tree is visited.

torch and xgboost are imported inside functions, so importing this module is cheap.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from quadcore.learn import features as feat
from quadcore.learn.features import TARGETS, FeatureSet, Scaler
from quadcore.store import safewrite, store

FORMAT = "quadcore-learned/1"
KINDS = ("xgboost", "mlp")
PRED_COLUMNS = [f"f_learned_b_{a}_N" for a in "xyz"] + [f"tau_learned_b_{a}_Nm" for a in "xyz"]
DEFAULT_HOLDOUT = "jana02"


class LearningError(ValueError):
    """A request the learning stage cannot meet (unknown kind, too few flights, ...)."""


# ---------------------------------------------------------------------------------------
# What to train
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LearnerSpec:
    """Hyper-parameters of one learned model (not to be confused with :class:`quadcore.identify.model.ModelSpec`,
    the physics model a model file asks for). XGBoost uses ``max_depth``, ``n_estimators`` (the most
    trees per output; early stopping keeps fewer), ``learning_rate``, ``subsample``,
    ``min_child_weight``, ``early_stopping_rounds``; the MLP ``hidden`` (widths of the hidden
    layers, () = linear), ``lr``, ``batch_size``, ``max_epochs``, ``patience``, ``weight_decay``."""

    kind: str
    max_depth: int = 6
    n_estimators: int = 1000
    learning_rate: float = 0.1
    subsample: float = 0.8
    min_child_weight: float = 5.0
    early_stopping_rounds: int = 30
    hidden: tuple[int, ...] = (64, 64)
    lr: float = 1e-3
    batch_size: int = 256
    max_epochs: int = 200
    patience: int = 20
    weight_decay: float = 0.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise LearningError(f"unknown model kind {self.kind!r}; known: {', '.join(KINDS)}")

    @property
    def slug(self) -> str:
        if self.kind == "xgboost":
            return f"xgboost-d{self.max_depth}"
        return "mlp-" + ("x".join(map(str, self.hidden)) if self.hidden else "linear")

    @property
    def label(self) -> str:
        if self.kind == "xgboost":
            return f"xgboost(depth {self.max_depth}, <= {self.n_estimators} trees/output, eta {self.learning_rate:g})"
        layers = f"{len(self.hidden)} hidden: {'x'.join(map(str, self.hidden))}" if self.hidden else "0 hidden (linear)"
        return f"mlp({layers})"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> LearnerSpec:
        d = dict(d)
        d["hidden"] = tuple(d.get("hidden", ()))
        return cls(**d)


def default_spec(kind: str) -> LearnerSpec:
    return LearnerSpec(kind)


def parse_spec(text: str) -> LearnerSpec:
    """``xgboost``, ``xgboost:depth=4,trees=300,eta=0.1``, ``mlp:hidden=64x64,epochs=100``."""
    kind, _, rest = text.strip().partition(":")
    kind = kind.strip()
    if kind not in KINDS:
        raise LearningError(f"unknown model kind {kind!r}; known: {', '.join(KINDS)}")
    aliases = {"depth": "max_depth", "trees": "n_estimators", "eta": "learning_rate", "epochs": "max_epochs",
               "batch": "batch_size"}
    kw: dict = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = aliases.get(key.strip(), key.strip())
        if not eq or key not in LearnerSpec.__dataclass_fields__ or key == "kind":
            raise LearningError(f"bad model option {item!r} in {text!r}")
        try:
            if key == "hidden":
                kw[key] = tuple(int(h) for h in value.split("x") if h.strip()) if value.strip() not in ("", "0") else ()
            elif key in ("max_depth", "n_estimators", "early_stopping_rounds", "batch_size", "max_epochs", "patience"):
                kw[key] = int(value)
            else:
                kw[key] = float(value)
        except ValueError:
            raise LearningError(f"bad value in model option {item!r}") from None
    return LearnerSpec(kind, **kw)


def complexity_specs(kind: str) -> list[LearnerSpec]:
    """The complexity sweep of the comparison tables: tree depth 2/4/6/8; MLP 0/1/2 hidden layers."""
    if kind == "xgboost":
        return [replace(default_spec(kind), max_depth=d) for d in (2, 4, 6, 8)]
    return [replace(default_spec(kind), hidden=h) for h in ((), (64,), (64, 64))]


@dataclass
class TrainConfig:
    stride: int = 5  # use every stride-th sample of the fitting flights
    val_fraction: float = 0.2
    seed: int = 0
    # Threads for XGBoost and for torch: one each by default, measured on the 2-core machine
    # with the real flights. These models are small (~28k rows, <= 21 inputs), so a second
    # thread saves little when the machine is quiet and costs a lot when the other core is busy
    # (OpenMP synchronisation): best XGBoost 1.3 s on one thread vs 0.8 s on two when quiet,
    # 1.5 s vs 5.6 s when loaded; one MLP epoch 0.05 s on one thread vs 0.2-1.9 s on two.
    threads: int = 1
    torch_threads: int = 1
    # run_plan trains the XGBoost experiments and the MLPs side by side, one thread each (the
    # trees' C++ and torch's kernels release the GIL): the learning stage's wall time is then
    # the slower kind's, not their sum. 1: one after the other. The models are the same either
    # way (each kind has its own seeded state); only their training times are longer.
    lanes: int = 2

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Split:
    """Train on ``train``, score on ``test`` (flight ids). ``name`` like ``holdout-jana02``."""

    name: str
    mode: str  # "holdout" or "lofo"
    train: tuple[str, ...]
    test: tuple[str, ...]


def resolve_holdout(requested: str | None, flights: list[str], explicit: bool = False) -> tuple[str, str]:
    """(holdout flight, note). The requested flight if present; otherwise, unless it was asked
    for explicitly (then :class:`LearningError`), the last flight in sorted order."""
    flights = sorted(flights)
    if len(flights) < 2:
        raise LearningError(f"learning needs at least two flights (one to train on, one to test); got {len(flights)}")
    requested = (requested or "").strip()
    if requested in flights:
        return requested, ""
    if requested and explicit:
        raise LearningError(f"holdout flight {requested!r} not found; flights: {', '.join(flights)}")
    note = (f"holdout {requested!r} is not among the flights; held out {flights[-1]!r} (the last) instead"
            if requested else f"held out {flights[-1]!r} (the last flight)")
    return flights[-1], note


def holdout_split(flights: list[str], holdout: str) -> Split:
    if holdout not in flights:
        raise LearningError(f"holdout flight {holdout!r} not found; flights: {', '.join(sorted(flights))}")
    return Split(f"holdout-{holdout}", "holdout", tuple(sorted(f for f in flights if f != holdout)), (holdout,))


def lofo_splits(flights: list[str]) -> list[Split]:
    """Leave one flight out, for every flight."""
    ids = sorted(flights)
    if len(ids) < 2:
        raise LearningError("leave-one-flight-out needs at least two flights")
    return [Split(f"lofo-{f}", "lofo", tuple(g for g in ids if g != f), (f,)) for f in ids]


def validation_flights(train: list[str], fraction: float = 0.2, seed: int = 0,
                       kinds: dict[str, str] | None = None) -> list[str]:
    """The training flights that early stopping watches: ``fraction`` of them (at least one,
    none when there is only one), drawn with ``seed``, round robin over flight kinds."""
    ids = sorted(train)
    if len(ids) < 2:
        return []
    n_val = min(len(ids) - 1, max(1, int(round(fraction * len(ids)))))
    perm = [ids[i] for i in np.random.default_rng(seed).permutation(len(ids))]
    kinds = kinds or {}
    groups: dict[str, list[str]] = {}
    for f in perm:
        groups.setdefault(kinds.get(f, ""), []).append(f)
    order, queues = [], [groups[k] for k in sorted(groups)]
    while any(queues):
        for q in queues:
            if q:
                order.append(q.pop(0))
    return sorted(order[:n_val])


# ---------------------------------------------------------------------------------------
# Data for one training run
# ---------------------------------------------------------------------------------------

def _rows(tables: Mapping[str, pl.DataFrame], flights, fs: FeatureSet,
          stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Usable rows (every ``stride``-th) of ``flights``: inputs (n, k) float32, targets (n, 6)."""
    Xs, Ys = [], []
    for f in flights:
        t = tables[f]
        m = feat.usable(t)
        Xs.append(feat.matrix(t, fs)[m][::stride])
        Ys.append(feat.targets(t)[m][::stride])
    if not Xs:
        return np.zeros((0, len(fs.columns)), np.float32), np.zeros((0, len(TARGETS)))
    return np.concatenate(Xs), np.concatenate(Ys)


@dataclass
class TrainingData:
    """Scaled matrices for fitting and validation, and the scalers (training flights only)."""

    x_scaler: Scaler
    y_scaler: Scaler
    X_fit: np.ndarray
    Y_fit: np.ndarray
    X_val: np.ndarray
    Y_val: np.ndarray
    fit_flights: list[str]
    val_flights: list[str]
    validation: str  # how the validation rows were chosen


def training_data(tables: Mapping[str, pl.DataFrame], fs: FeatureSet, train: list[str], config: TrainConfig,
                  kinds: dict[str, str] | None = None) -> TrainingData:
    missing = [f for f in train if f not in tables]
    if missing:
        raise LearningError(f"no table for training flight(s) {', '.join(missing)}")
    X_all, Y_all = _rows(tables, train, fs)
    if len(X_all) < 10:
        raise LearningError(f"too few usable rows on the training flights ({len(X_all)})")
    xs = Scaler.fit(X_all, list(fs.columns), sorted(train))
    ys = Scaler.fit(Y_all, TARGETS, sorted(train))
    val = validation_flights(train, config.val_fraction, config.seed, kinds)
    fit = [f for f in sorted(train) if f not in val]
    stride = max(1, int(config.stride))
    if val:
        Xf, Yf = _rows(tables, fit, fs, stride)
        Xv, Yv = _rows(tables, val, fs)
        how = f"flights {', '.join(val)}"
    else:  # one training flight: its last 20 % validates
        n = len(X_all)
        cut = int(n * (1 - config.val_fraction))
        Xf, Yf = X_all[:cut:stride], Y_all[:cut:stride]
        Xv, Yv = X_all[cut:], Y_all[cut:]
        how = f"last {config.val_fraction:.0%} of {train[0]} (a single training flight)"
    return TrainingData(xs, ys, xs.transform(Xf), ys.transform(Yf), xs.transform(Xv), ys.transform(Yv), fit, val, how)


# ---------------------------------------------------------------------------------------
# The two learners
# ---------------------------------------------------------------------------------------

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


def _mlp_module(n_in: int, hidden: tuple[int, ...], n_out: int):
    import torch.nn as nn

    layers, width = [], n_in
    for h in hidden:
        layers += [nn.Linear(width, h), nn.ReLU()]
        width = h
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


def _train_mlp(spec: LearnerSpec, d: TrainingData, seed: int, threads: int):
    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    net = _mlp_module(d.X_fit.shape[1], spec.hidden, d.Y_fit.shape[1])
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


# ---------------------------------------------------------------------------------------
# The per-sample tree path
# ---------------------------------------------------------------------------------------

class CompiledForest:
    """An XGBoost model's trees as flat NumPy arrays, evaluated level by level for all trees
    at once: ``depth`` vectorised steps per sample instead of one XGBoost call (~80 us of
    Python and C++ set-up before any tree is visited). Same thresholds (float32, ``x <
    split`` goes left, a missing value goes the default way), same leaf values; the sum is in
    float64, so results agree with XGBoost to float32 rounding."""

    def __init__(self, booster):
        m = json.loads(bytes(booster.save_raw("json")).decode())
        learner = m["learner"]
        model = learner["gradient_booster"]["model"]
        n_targets = max(1, int(learner["learner_model_param"].get("num_target", "1")))
        base = learner["learner_model_param"]["base_score"]
        base = json.loads(base) if base.strip().startswith("[") else [float(base)] * n_targets
        self.base = np.asarray(base, dtype=np.float64).reshape(-1)
        if self.base.size == 1 and n_targets > 1:
            self.base = np.full(n_targets, self.base[0])
        left, right, fidx, thr, dleft, value, roots, depth = [], [], [], [], [], [], [], 1
        offset = 0
        for tree in model["trees"]:
            lc = np.asarray(tree["left_children"], np.int64)
            rc = np.asarray(tree["right_children"], np.int64)
            leaf = lc < 0
            idx = np.arange(len(lc))
            left.append(np.where(leaf, idx, lc) + offset)
            right.append(np.where(leaf, idx, rc) + offset)
            fidx.append(np.where(leaf, 0, np.asarray(tree["split_indices"], np.int64)))
            cond = np.asarray(tree["split_conditions"], np.float32)
            thr.append(np.where(leaf, np.float32(0), cond))
            dleft.append(np.asarray(tree["default_left"], bool) | leaf)
            value.append(np.where(leaf, cond.astype(np.float64), 0.0))
            roots.append(offset)
            depth = max(depth, self._depth(lc, rc))
            offset += len(lc)
        self.left, self.right = np.concatenate(left), np.concatenate(right)
        self.feature, self.threshold = np.concatenate(fidx), np.concatenate(thr)
        self.default_left, self.value = np.concatenate(dleft), np.concatenate(value)
        self.roots = np.asarray(roots, np.int64)
        self.group = np.asarray(model["tree_info"], np.int64)
        self.depth = depth
        self.n_targets = len(self.base)

    @staticmethod
    def _depth(lc: np.ndarray, rc: np.ndarray) -> int:
        depth, frontier = 0, [0]
        while frontier:
            nxt = [c for i in frontier for c in (lc[i], rc[i]) if c >= 0]
            depth += 1 if nxt else 0
            frontier = nxt
        return max(depth, 1)

    def predict_one(self, x: np.ndarray) -> np.ndarray:
        """(k,) float32 -> (n_targets,)."""
        node = self.roots
        feature, threshold, left, right = self.feature, self.threshold, self.left, self.right
        if np.isnan(x).any():
            for _ in range(self.depth):
                xv = x[feature[node]]
                go = np.where(np.isnan(xv), self.default_left[node], xv < threshold[node])
                node = np.where(go, left[node], right[node])
        else:
            for _ in range(self.depth):
                node = np.where(x[feature[node]] < threshold[node], left[node], right[node])
        return self.base + np.bincount(self.group, self.value[node], minlength=self.n_targets)

    def predict(self, X: np.ndarray) -> np.ndarray:
        """(n, k) -> (n, n_targets), the same walk for many rows."""
        X = np.asarray(X, np.float32)
        node = np.broadcast_to(self.roots, (len(X), len(self.roots))).copy()
        rows = np.arange(len(X))[:, None]
        for _ in range(self.depth):
            xv = X[rows, self.feature[node]]
            go = np.where(np.isnan(xv), self.default_left[node], xv < self.threshold[node])
            node = np.where(go, self.left[node], self.right[node])
        vals = self.value[node]
        out = np.zeros((len(X), self.n_targets))
        for g in range(self.n_targets):
            out[:, g] = vals[:, self.group == g].sum(axis=1)
        return out + self.base


# ---------------------------------------------------------------------------------------
# A trained model and its predict API
# ---------------------------------------------------------------------------------------

class LearnedModel:
    """A trained residual model: predicts the body-frame residual force (N) and torque (N m)
    left after the physics model named in ``manifest["physics_model"]``."""

    def __init__(self, spec: LearnerSpec, feature_set: FeatureSet, x_scaler: Scaler, y_scaler: Scaler,
                 impl, manifest: dict | None = None):
        self.spec = spec
        self.feature_set = feature_set
        self.x_scaler = x_scaler
        self.y_scaler = y_scaler
        self.impl = impl  # xgboost.Booster or torch.nn.Module
        self.manifest = manifest or {}
        self._forest: CompiledForest | None = None

    @property
    def kind(self) -> str:
        return self.spec.kind

    @property
    def features(self) -> list[str]:
        return list(self.feature_set.columns)

    @property
    def label(self) -> str:
        return f"{self.kind}({self.feature_set.name})"

    # -- prediction ------------------------------------------------------------------
    def predict_matrix(self, X: np.ndarray) -> np.ndarray:
        """Raw feature matrix (n, k) -> (n, 6) residual [f_x, f_y, f_z, tau_x, tau_y, tau_z], SI."""
        Z = self.x_scaler.transform(X)
        if self.kind == "xgboost":
            out = self.impl.inplace_predict(Z)
        else:
            import torch

            with torch.no_grad():
                out = self.impl(torch.from_numpy(Z)).numpy()
        return self.y_scaler.inverse(np.asarray(out).reshape(len(Z), -1))

    def predict_one(self, x: np.ndarray) -> np.ndarray:
        """One sample (k,) -> (6,), the low-latency path: the compiled forest for trees, a
        (1, k) tensor under ``no_grad`` for the MLP."""
        z = ((np.asarray(x, np.float64) - self.x_scaler.mean) / self.x_scaler.std).astype(np.float32)
        if self.kind == "xgboost":
            if self._forest is None:
                self._forest = CompiledForest(self.impl)
            y = self._forest.predict_one(z)
        else:
            import torch

            with torch.no_grad():
                y = self.impl(torch.from_numpy(z[None, :]))[0].numpy()
        return y * self.y_scaler.std + self.y_scaler.mean

    def _feature_source(self, table: pl.DataFrame, flight: str | None = None) -> pl.DataFrame:
        t = feat.with_derived(table)
        if not feat.missing_columns(self.feature_set, t):
            return t
        if "pwm_1" in table.columns and "T_N" not in table.columns:  # a decoded table: build the residual table
            physics = self.physics_model()
            # the residuals it was trained on: each flight's session values and thrust map
            physics = physics.for_flight(flight) if flight is not None else physics
            t = feat.with_derived(physics.residual_table(table))
        feat.check(self.feature_set, t, "flight table")
        return t

    def predict(self, table: pl.DataFrame, flight: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A flight table (residual table of the same physics model, or a decoded
        ``fixedFrequency`` table) -> residual force (n, 3) in N and torque (n, 3) in N m,
        body frame. For a decoded table of a physics model with per-session values, name the
        ``flight``: its residual is built with its session's values, as in training (without,
        the fleet values). Rows with a missing input get NaN from the MLP and the trees'
        default branch from XGBoost."""
        y = self.predict_matrix(feat.matrix(self._feature_source(table, flight), self.feature_set))
        return y[:, :3], y[:, 3:]

    def predict_table(self, table: pl.DataFrame, flight: str | None = None) -> pl.DataFrame:
        f, tau = self.predict(table, flight)
        out = {"t_s": table["t_s"]} if "t_s" in table.columns else {}
        out.update({c: v for c, v in zip(PRED_COLUMNS, np.concatenate([f, tau], axis=1).T)})
        return pl.DataFrame(out)

    def physics_model(self):
        """The physics model this model was trained against (from the manifest)."""
        from quadcore.identify import model as modelmod

        pm = self.manifest.get("physics_model") or {}
        modelmod.load_plugins(pm)
        return modelmod.PhysicsModel.from_dict(pm, vehicle_of(pm))

    def importance(self) -> dict[str, float]:
        """XGBoost total gain per feature, normalised to sum 1 ({} for the MLP)."""
        if self.kind != "xgboost":
            return {}
        gain = self.impl.get_score(importance_type="total_gain")
        vals = np.array([gain.get(f"f{i}", 0.0) for i in range(len(self.features))])
        total = vals.sum() or 1.0
        return {n: float(v / total) for n, v in zip(self.features, vals)}

    # -- artefacts -------------------------------------------------------------------
    def save(self, folder: str | Path, predictions: pl.DataFrame | None = None) -> Path:
        """Write the artefacts (and ``predictions.parquet``) into a staging folder, the manifest
        last, and put it in place whole: a kill leaves the previous model or the new one, never
        a torn one."""
        folder = store.as_root(folder)
        if store.is_remote(folder):  # written here, then uploaded with the manifest last
            with tempfile.TemporaryDirectory(prefix="quadcore-model-") as local:
                self._write(Path(local), folder.name, predictions)
                return store.upload_folder(Path(local), folder, last="manifest.json")
        staging = safewrite.staging_folder(folder)
        try:
            self._write(staging, folder.name, predictions)
            return safewrite.replace_folder(staging, folder)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _write(self, folder: Path, run: str, predictions: pl.DataFrame | None) -> None:
        """The artefacts into the local folder ``folder``, the manifest last."""
        if predictions is not None:
            store.write_parquet(predictions, folder / "predictions.parquet", {"run": run})
        if self.kind == "xgboost":
            self.impl.save_model(str(folder / "model.ubj"))
        else:
            import torch

            torch.save(self.impl.state_dict(), folder / "model.pt")
        store.write_json({"x": self.x_scaler.to_dict(), "y": self.y_scaler.to_dict()}, folder / "scaler.json")
        store.write_json(self.feature_set.to_dict(), folder / "features.json")
        store.write_json({"format": FORMAT, **self.manifest, "kind": self.kind, "spec": self.spec.to_dict(),
                          "feature_set": self.feature_set.to_dict(), "targets": TARGETS}, folder / "manifest.json")


def vehicle_of(physics: dict):
    """The vehicle a physics-model dict (``PhysicsModel.to_dict()``) names, with its thrust map."""
    from quadcore.physics import vehicle as vehiclemod

    src = physics.get("vehicle_source") or physics.get("vehicle")
    name = src.split(":", 1)[1] if src and src.startswith("builtin:") else src
    veh = vehiclemod.load(name or None)
    return veh.with_thrust_map(physics["thrust_map"]) if physics.get("thrust_map") else veh


def load(folder: str | Path, threads: int = 1, torch_threads: int = 1) -> LearnedModel:
    """A model saved by :meth:`LearnedModel.save`; :class:`LearningError` for anything else
    (a missing or malformed manifest, scaler, feature list or weights)."""
    folder = store.as_root(folder)
    mpath = folder / "manifest.json"
    if not mpath.is_file():
        raise LearningError(f"no learned model in {folder} (no manifest.json)")
    try:
        if store.is_remote(folder):  # the weights load from local files: copied here first
            with tempfile.TemporaryDirectory(prefix="quadcore-model-") as local:
                here = store.download_folder(folder, Path(local))
                return _load(here, here / "manifest.json", threads, torch_threads)
        return _load(folder, mpath, threads, torch_threads)
    except LearningError:
        raise
    except Exception as exc:  # noqa: BLE001 (json, xgboost, torch and pickle each have their own errors)
        raise LearningError(f"{folder}: malformed learned model ({type(exc).__name__}: {str(exc)[:200]})") from None


def _load(folder: Path, mpath: Path, threads: int, torch_threads: int) -> LearnedModel:
    manifest = json.loads(mpath.read_text())
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise LearningError(f"{mpath}: not a {FORMAT} manifest")
    spec = LearnerSpec.from_dict(manifest["spec"])
    fs = FeatureSet.from_dict(json.loads((folder / "features.json").read_text()))
    sc = json.loads((folder / "scaler.json").read_text())
    xs, ys = Scaler.from_dict(sc["x"]), Scaler.from_dict(sc["y"])
    if spec.kind == "xgboost":
        import xgboost as xgb

        impl = xgb.Booster(model_file=str(folder / "model.ubj"))
        impl.set_param({"nthread": threads})
    else:
        import torch

        torch.set_num_threads(torch_threads)
        impl = _mlp_module(len(fs.columns), spec.hidden, len(TARGETS))
        impl.load_state_dict(torch.load(folder / "model.pt", weights_only=True))
        impl.eval()
    return LearnedModel(spec, fs, xs, ys, impl, manifest)


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


# ---------------------------------------------------------------------------------------
# Experiments: what the comparison tables need, trained once each
# ---------------------------------------------------------------------------------------

@dataclass
class Experiment:
    spec: LearnerSpec
    feature_set: FeatureSet
    split: Split
    train_group: str  # "all", "random", "preplanned", ...
    groups: list[str] = field(default_factory=list)  # comparison tables it appears in

    @property
    def name(self) -> str:
        return f"{self.split.name}__{self.train_group}__{self.feature_set.name}__{self.spec.slug}"

    @property
    def train(self) -> list[str]:
        return list(self.split.train)


@dataclass
class Plan:
    experiments: list[Experiment]
    holdout: str
    primary_feature_set: str
    notes: list[str] = field(default_factory=list)


def plan(flights: list[str], feature_sets: list[FeatureSet], kinds_of_model: list[str], holdout: str,
         flight_kinds: dict[str, str] | None = None, loo: bool = False, compare: bool = True,
         specs: dict[str, LearnerSpec] | None = None) -> Plan:
    """The experiments behind the report:

    * ``feature_sets``: every feature set x every model kind (default spec), holdout split;
    * ``complexity`` (``compare``): the primary feature set, tree depth 2/4/6/8 and MLP 0/1/2
      hidden layers;
    * ``training_size`` (``compare`` and flight kinds known): trained on the random flights
      only, the preplanned flights only, and all of them;
    * ``lofo`` (``loo``): leave each flight out in turn, primary feature set, default specs.
    """
    if not feature_sets:
        raise LearningError("no feature sets")
    for k in kinds_of_model:
        if k not in KINDS:
            raise LearningError(f"unknown model kind {k!r}; known: {', '.join(KINDS)}")
    specs = {k: (specs or {}).get(k, default_spec(k)) for k in kinds_of_model}
    names = [fs.name for fs in feature_sets]
    primary = next((fs for fs in feature_sets if fs.name == feature_sets_primary(names)), feature_sets[0])
    split = holdout_split(flights, holdout)
    exps: dict[tuple, Experiment] = {}
    notes: list[str] = []

    def add(spec, fs, sp, group_name, tag):
        key = (spec, fs.name, sp.train, sp.test)
        if key not in exps:
            exps[key] = Experiment(spec, fs, sp, group_name)
        if tag not in exps[key].groups:
            exps[key].groups.append(tag)

    for fs in feature_sets:
        for k in kinds_of_model:
            add(specs[k], fs, split, "all", "feature_sets")
    if compare:
        for k in kinds_of_model:
            for s in complexity_specs(k):
                base = specs[k]
                s = replace(base, max_depth=s.max_depth) if k == "xgboost" else replace(base, hidden=s.hidden)
                add(s, primary, split, "all", "complexity")
        if flight_kinds:
            for k in kinds_of_model:
                add(specs[k], primary, split, "all", "training_size")
            for group in sorted({flight_kinds[f] for f in split.train if f in flight_kinds}):
                members = tuple(f for f in split.train if flight_kinds.get(f) == group)
                if len(members) < 2:
                    notes.append(f"training-size comparison: only {len(members)} {group} flight(s); skipped")
                    continue
                sub = Split(split.name, "holdout", members, split.test)
                for k in kinds_of_model:
                    add(specs[k], primary, sub, group, "training_size")
        else:
            notes.append("training-size comparison (random vs preplanned vs all) skipped: no flight kinds "
                         "(no flights.csv with columns flight,kind was found)")
    if loo:
        for sp in lofo_splits(flights):
            for k in kinds_of_model:
                add(specs[k], primary, sp, "all", "lofo")
    return Plan(list(exps.values()), holdout, primary.name, notes)


def feature_sets_primary(names: list[str]) -> str:
    return feat.PRIMARY_FEATURE_SET if feat.PRIMARY_FEATURE_SET in names else names[0]


def _clear_runs(out: Path) -> None:
    """Remove earlier runs (folders holding one of our manifests) so the index is the truth;
    the index goes first, so that a run killed after this lists nothing that is gone."""
    if not out.is_dir():
        return
    if (out / "index.json").is_file():
        (out / "index.json").unlink()
    for d in out.iterdir():
        m = d / "manifest.json"
        if d.is_dir() and m.is_file():
            try:
                ours = json.loads(m.read_text()).get("format") == FORMAT
            except (OSError, json.JSONDecodeError):
                ours = False
            if ours:
                store.remove_tree(d)


def train_experiments(experiments: list[Experiment], tables_by_set: Mapping[str, Mapping[str, pl.DataFrame]],
                      config: TrainConfig, physics: dict | None = None,
                      flight_kinds: dict[str, str] | None = None) -> list[LearnedModel]:
    """The trained model of each experiment, in order. With ``config.lanes`` >= 2 the XGBoost
    experiments and the MLPs train at the same time, each kind in its own thread and in plan
    order within it: torch's global seed is then only ever set by the one MLP thread, so every
    model is the one a sequential run trains."""
    def lane(kind: str) -> list[tuple[int, LearnedModel]]:
        return [(i, train(e.spec, e.feature_set, tables_by_set[e.feature_set.name], e.train, config, physics,
                          flight_kinds))
                for i, e in enumerate(experiments) if e.spec.kind == kind]

    kinds = sorted({e.spec.kind for e in experiments})
    if config.lanes < 2 or len(kinds) < 2:
        done = [pair for k in kinds for pair in lane(k)]
    else:
        import torch  # noqa: F401  (imported once here: two threads importing at once would wait on each other)
        import xgboost  # noqa: F401

        with ThreadPoolExecutor(max_workers=len(kinds), thread_name_prefix="train") as pool:
            done = [pair for lane_result in pool.map(lane, kinds) for pair in lane_result]
    return [m for _, m in sorted(done, key=lambda pair: pair[0])]


@dataclass(frozen=True)
class RunRecord:
    """One trained model as :func:`run_plan` saved it under ``path``: what was trained (learner
    spec, feature set, split and training group, the comparison tables it appears in), on which
    flights, and how it went (training time, validation loss, rows fitted, latency per sample).
    ``manifest`` is the whole saved manifest (the JSON boundary: :meth:`to_dict`)."""

    name: str
    spec: LearnerSpec
    feature_set: FeatureSet
    split: Split
    train_group: str
    groups: tuple[str, ...]
    train_flights: tuple[str, ...]
    train_time_s: float
    val_loss: float
    rows_fit: int
    latency_us: float
    path: Path
    manifest: Mapping[str, Any]

    @property
    def kind(self) -> str:
        return self.spec.kind

    @classmethod
    def from_manifest(cls, m: Mapping[str, Any], path) -> RunRecord:
        split = m["split"]
        return cls(m["name"], LearnerSpec.from_dict(m["spec"]), FeatureSet.from_dict(m["feature_set"]),
                   Split(split["name"], split["mode"], tuple(m["train_flights"]), tuple(split["test"])),
                   m["train_group"], tuple(m["groups"]), tuple(m["train_flights"]), m["train_time_s"],
                   m["val_loss"], m["rows_fit"], m["latency_us"], path, m)

    def to_dict(self) -> dict:
        """The record as JSON: the manifest with the folder and the spec's label."""
        return {**self.manifest, "path": str(self.path), "spec_label": self.spec.label}


def run_plan(p: Plan, tables_by_set: Mapping[str, Mapping[str, pl.DataFrame]], out_dir: str | Path,
             physics: dict | None = None, config: TrainConfig | None = None,
             flight_kinds: dict[str, str] | None = None, log: Callable[[str], None] = print,
             latency_repeats: int = 300) -> list[RunRecord]:
    """Train every experiment, save its artefacts and its predictions on its test flights under
    ``out_dir/<experiment name>/``, and an index ``out_dir/index.json``. Returns the run records."""
    config = config or TrainConfig()
    out = store.as_root(out_dir)  # a folder here or in an object store
    _clear_runs(out)
    models = train_experiments(p.experiments, tables_by_set, config, physics, flight_kinds)
    records = []
    for i, (e, model) in enumerate(zip(p.experiments, models), 1):
        tables = tables_by_set[e.feature_set.name]
        test_tables = {f: tables[f] for f in e.split.test}
        X_test = np.concatenate([feat.matrix(t, e.feature_set)[feat.usable(t)] for t in test_tables.values()])
        y_pred, predict_s = time_predict(model, X_test)
        x1 = np.ascontiguousarray(X_test[:1])
        lat = latency_us(model.predict_one, x1[0], latency_repeats)
        lat_lib = latency_us(model.predict_matrix, x1, max(50, latency_repeats // 3))
        frames, j = [], 0
        for f, t in test_tables.items():
            m = feat.usable(t)
            n = int(m.sum())
            frame = {"flight": [f] * n, "row": np.flatnonzero(m), "t_s": t["t_s"].to_numpy()[m]}
            frame.update({c: feat.targets(t)[m][:, k] for k, c in enumerate(TARGETS)})
            frame.update({c: y_pred[j: j + n, k] for k, c in enumerate(PRED_COLUMNS)})
            frames.append(pl.DataFrame(frame))
            j += n
        model.manifest.update({
            "name": e.name, "split": {"name": e.split.name, "mode": e.split.mode, "test": list(e.split.test)},
            "train_group": e.train_group, "groups": e.groups, "test_flights": list(e.split.test),
            "predict_time_s": predict_s, "test_rows": int(len(X_test)),
            "latency_us": lat, "latency_library_us": lat_lib,
            "latency_path": "compiled NumPy forest" if e.spec.kind == "xgboost" else "torch (1, k) tensor, no_grad",
        })
        folder = model.save(out / e.name, pl.concat(frames))
        rec = RunRecord.from_manifest({**model.manifest, "kind": e.spec.kind, "spec": e.spec.to_dict(),
                                       "feature_set": e.feature_set.to_dict()}, folder)
        records.append(rec)
        log(f"  [{i}/{len(p.experiments)}] {e.name}: trained in {rec.train_time_s:.2f} s "
            f"({rec.rows_fit} rows), val loss {rec.val_loss:.4f}, predicted {len(X_test)} rows in "
            f"{predict_s * 1e3:.1f} ms, {lat:.0f} us/sample")
    store.write_json({"format": FORMAT, "holdout": p.holdout, "primary_feature_set": p.primary_feature_set,
                      "notes": p.notes, "config": config.to_dict(), "physics_model": physics or {},
                      "flight_kinds": flight_kinds or {}, "runs": [r.name for r in records]},
                     out / "index.json")
    return records


def read_runs(out_dir: str | Path) -> tuple[dict, list[dict]]:
    """(index, run records) written by :func:`run_plan`."""
    out = store.as_root(out_dir)
    ipath = out / "index.json"
    if not ipath.is_file():
        raise LearningError(f"no learned models in {out} (no index.json): train them first")
    try:
        index = json.loads(ipath.read_text())
        records = []
        for name in index["runs"]:
            m = json.loads((out / name / "manifest.json").read_text())
            records.append({**m, "path": str(out / name), "spec_label": LearnerSpec.from_dict(m["spec"]).label})
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise LearningError(f"{out}: malformed learned-model index or manifest ({type(exc).__name__}: {exc})") from None
    return index, records


def read_predictions(record: dict) -> pl.DataFrame:
    return store.read_parquet(store.as_root(record["path"]) / "predictions.parquet")
