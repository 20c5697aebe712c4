"""Which flights train, validate and test a learned model, and its training rows.

Test flights: the fixed holdout or leave-one-flight-out (:class:`Split`). The training flights split
again, by flight, into fitting and validation flights (:func:`validation_flights`); rows near logging
gaps are never used and fitting rows are subsampled (``docs/learning.md`` says why).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import polars as pl

from quadcore.learn import features as feat
from quadcore.learn.features import TARGETS, FeatureSet, Scaler
from quadcore.learn.learners import LearningError, TrainConfig

DEFAULT_HOLDOUT = "jana02"


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
