"""Experiments: the plan of models to train (kinds, feature sets, splits, training-set sizes,
complexity), running it into ``<root>/learned/`` and reading the runs back.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from quadcore.learn import features as feat
from quadcore.learn.artefacts import FORMAT, PRED_COLUMNS, LearnedModel
from quadcore.learn.backends import backend
from quadcore.learn.features import TARGETS, FeatureSet
from quadcore.learn.learners import KINDS, LearnerSpec, LearningError, TrainConfig, complexity_specs, default_spec
from quadcore.learn.splits import MAX_LOFO_FOLDS, Split, holdout_split, lofo_splits
from quadcore.learn.trainers import latency_us, time_predict, train
from quadcore.store import store


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
    * ``lofo`` (``loo``): leave each flight out in turn (at most ``MAX_LOFO_FOLDS`` of them:
      :func:`quadcore.learn.splits.lofo_left_out`), primary feature set, default specs.
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
        if len(flights) > MAX_LOFO_FOLDS:
            notes.append(f"leave-one-flight-out: {MAX_LOFO_FOLDS} folds (its cap) for {len(flights)} flights: "
                         f"{MAX_LOFO_FOLDS} flights evenly spread over the sorted ids are left out in turn, not all")
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
        for k in kinds:  # imported once here: two threads importing at once would wait on each other
            backend(k)
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
    for i, (e, model) in enumerate(zip(p.experiments, _each_released(models)), 1):
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


def _each_released(models: list[LearnedModel]):
    """The models in order, each dropped from ``models`` as it is handed out, so that it is freed
    once saved: a forest at its tree cap (6,000 trees of depth 8) holds about 230 MB once
    compiled for the latency path, and seven of them held together were most of the stage's peak."""
    while models:
        yield models.pop(0)


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
