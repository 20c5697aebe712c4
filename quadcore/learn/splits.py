"""Which flights train, validate and test a learned model, and its training rows.

Test flights: the fixed holdout or leave-one-flight-out (:class:`Split`). The training flights split
again, by flight, into fitting and validation flights (:func:`validation_flights`); rows near logging
gaps are never used and fitting rows are subsampled (``docs/learning.md`` says why).
"""

from __future__ import annotations

import zlib
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


# Leave-one-flight-out trains a fold per left-out flight: beyond this many flights, this many
# folds (each bounded by the row budget), so that its cost stops growing with the fleet.
MAX_LOFO_FOLDS = 20


def lofo_left_out(flights: list[str], max_folds: int = MAX_LOFO_FOLDS) -> list[str]:
    """The flights leave-one-flight-out leaves out in turn: every flight, or beyond
    ``max_folds`` flights, ``max_folds`` of them evenly spread over the sorted ids."""
    ids = sorted(flights)
    if len(ids) <= max_folds:
        return ids
    return [ids[i * len(ids) // max_folds] for i in range(max_folds)]


def lofo_splits(flights: list[str], max_folds: int = MAX_LOFO_FOLDS) -> list[Split]:
    """Leave one flight out, for every flight (at most ``max_folds`` of them: :func:`lofo_left_out`)."""
    ids = sorted(flights)
    if len(ids) < 2:
        raise LearningError("leave-one-flight-out needs at least two flights")
    return [Split(f"lofo-{f}", "lofo", tuple(g for g in ids if g != f), (f,)) for f in lofo_left_out(ids, max_folds)]


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


def usable_counts(tables: Mapping[str, pl.DataFrame], flights) -> dict[str, int]:
    """Usable rows (not near a logging gap) of each flight."""
    return {f: int(feat.usable(tables[f]).sum()) for f in flights}


def budget_quota(counts: Mapping[str, int], budget: int) -> int | None:
    """Rows each flight may give so that they fit ``budget``: None when all of them fit, else
    the largest ``q`` with ``sum(min(n_f, q)) <= budget`` (flights shorter than ``q`` give all
    their rows, the others ``q`` each: even per flight, the budget used up to the last share)."""
    if sum(counts.values()) <= budget:
        return None
    left, flights_left = budget, len(counts)
    for n in sorted(counts.values()):
        q = left // flights_left
        if n > q:
            return q
        left, flights_left = left - n, flights_left - 1
    return left  # unreachable: the counts exceed the budget, so some flight is longer than its share


def budget_rows(counts: Mapping[str, int], quota: int | None, seed: int) -> dict[str, np.ndarray] | None:
    """Which of its usable rows each flight gives a training run: None (all of them) when
    ``quota`` is None (:func:`budget_quota`: they fit the budget); else ``min(n_f, quota)``
    rows of each flight, drawn without replacement with a generator seeded by ``(seed,
    flight)`` and kept in time order: the same seed and flights give the same rows, and a new
    flight changes the others' rows only through the quota. Indices count usable rows."""
    if quota is None:
        return None
    picks = {}
    for f, n in counts.items():
        rng = np.random.default_rng([seed, zlib.crc32(f.encode())])
        picks[f] = np.arange(n) if n <= quota else np.sort(rng.choice(n, quota, replace=False))
    return picks


def _rows(tables: Mapping[str, pl.DataFrame], flights, fs: FeatureSet,
          picks: Mapping[str, np.ndarray] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each flight's usable rows (those ``picks`` names, when given): inputs (n, k) float32,
    targets (n, 6); every table is read once."""
    out = {}
    for f in flights:
        t = tables[f]
        rows = np.flatnonzero(feat.usable(t))
        rows = rows if picks is None else rows[picks[f]]
        out[f] = feat.matrix(t, fs)[rows], feat.targets(t)[rows]
    return out


def _stack(parts, fs: FeatureSet, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The (X, Y) pairs of ``parts`` one under the other, every ``stride``-th row of each."""
    parts = list(parts)
    if not parts:
        return np.zeros((0, len(fs.columns)), np.float32), np.zeros((0, len(TARGETS)))
    return np.concatenate([X[::stride] for X, _ in parts]), np.concatenate([Y[::stride] for _, Y in parts])


@dataclass(frozen=True)
class RowBudget:
    """How many usable rows of the training flights a run held: all of them (``quota`` None),
    or at most ``budget``, ``quota`` of each longer flight."""

    budget: int
    usable: int
    held: int
    quota: int | None

    def to_dict(self) -> dict:
        return {"row_budget": self.budget, "rows_usable": self.usable, "rows_held": self.held,
                "rows_per_flight": self.quota}


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
    rows: RowBudget


def training_data(tables: Mapping[str, pl.DataFrame], fs: FeatureSet, train: list[str], config: TrainConfig,
                  kinds: dict[str, str] | None = None) -> TrainingData:
    missing = [f for f in train if f not in tables]
    if missing:
        raise LearningError(f"no table for training flight(s) {', '.join(missing)}")
    counts = usable_counts(tables, train)
    quota = budget_quota(counts, config.max_rows)
    picks = budget_rows(counts, quota, config.seed)
    by_flight = _rows(tables, train, fs, picks)
    X_all, Y_all = _stack(by_flight.values(), fs)
    budget = RowBudget(config.max_rows, sum(counts.values()), len(X_all), quota)
    if len(X_all) < 10:
        raise LearningError(f"too few usable rows on the training flights ({len(X_all)})")
    xs = Scaler.fit(X_all, list(fs.columns), sorted(train))
    ys = Scaler.fit(Y_all, TARGETS, sorted(train))
    val = validation_flights(train, config.val_fraction, config.seed, kinds)
    fit = [f for f in sorted(train) if f not in val]
    stride = max(1, int(config.stride))
    if val:
        Xf, Yf = _stack((by_flight[f] for f in fit), fs, stride)
        Xv, Yv = _stack((by_flight[f] for f in val), fs)
        how = f"flights {', '.join(val)}"
    else:  # one training flight: its last 20 % validates
        n = len(X_all)
        cut = int(n * (1 - config.val_fraction))
        Xf, Yf = X_all[:cut:stride], Y_all[:cut:stride]
        Xv, Yv = X_all[cut:], Y_all[cut:]
        how = f"last {config.val_fraction:.0%} of {train[0]} (a single training flight)"
    return TrainingData(xs, ys, xs.transform(Xf), ys.transform(Yf), xs.transform(Xv), ys.transform(Yv), fit, val, how,
                        budget)
