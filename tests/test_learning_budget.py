"""The learning stage at lab scale: the row budget of a training run (evenly per flight, seeded,
stated in the report), the default budget leaving a small fleet as it was, the setting's check,
and the cap on leave-one-flight-out folds. Four short simulated flights (the session's
``drag_fleet``); budgets far below the default make them exceed it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from quadcore.identify import model
from quadcore.learn import experiments, features as feat, learners, metrics, splits, trainers
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.workflows import learn as learn_workflow

REPO = Path(__file__).resolve().parents[1]
VEHICLE = vehicle.load()
FS = feat.FEATURE_SETS["physics"]
HOLDOUT = "sim003"
XGB = learners.LearnerSpec("xgboost", max_depth=3, n_estimators=40, early_stopping_rounds=8)
MLP = learners.LearnerSpec("mlp", hidden=(16,), max_epochs=15, patience=5)


@pytest.fixture(scope="module")
def residuals(drag_fleet) -> dict[str, pl.DataFrame]:
    nominal = model.PhysicsModel(VEHICLE, [])
    return {p.name: nominal.residual_table(flight.decode_flight(p).tables["fixedFrequency"])
            for p in sorted(drag_fleet.glob("sim00?"))}


@pytest.fixture(scope="module")
def tables(residuals) -> dict[str, pl.DataFrame]:
    return feat.feature_tables(residuals, [FS])[FS.name]


def _train_flights(tables) -> list[str]:
    return [f for f in tables if f != HOLDOUT]


def _usable(tables, f) -> int:
    return int(feat.usable(tables[f]).sum())


def test_a_small_budget_holds_at_most_that_many_rows_evenly_per_flight(tables):
    train = _train_flights(tables)
    counts = {f: _usable(tables, f) for f in train}
    budget = 1200
    assert sum(counts.values()) > budget and min(counts.values()) > budget // len(train)  # each flight is cut
    config = learners.TrainConfig(stride=1, max_rows=budget)
    d = splits.training_data(tables, FS, train, config)
    assert d.rows == splits.RowBudget(budget, sum(counts.values()), budget, budget // len(train))
    assert len(d.X_fit) + len(d.X_val) == budget  # stride 1: every held row fits or validates
    assert len(d.X_val) == budget // len(train) * len(d.val_flights)  # the same share of every flight
    assert d.x_scaler.rows == budget  # the scalers see the held rows only

    # the held rows are rows of the flights, in time order: the fitting rows of the first fitting flight
    first = d.fit_flights[0]
    usable_t = tables[first]["t_s"].to_numpy()[feat.usable(tables[first])]
    picks = splits.budget_rows(counts, d.rows.quota, config.seed)[first]
    expected = d.x_scaler.transform(feat.matrix(tables[first], FS)[feat.usable(tables[first])][picks])
    np.testing.assert_array_equal(d.X_fit[: len(picks)], expected)
    assert np.all(np.diff(usable_t[picks]) > 0) and usable_t[picks][-1] > 0.8 * usable_t[-1]  # spread over the flight

    again = splits.training_data(tables, FS, train, config)
    np.testing.assert_array_equal(again.X_fit, d.X_fit)  # same seed, same rows
    other = splits.training_data(tables, FS, train, learners.TrainConfig(stride=1, max_rows=budget, seed=1))
    assert other.rows.held == budget and not np.array_equal(other.X_fit, d.X_fit)


def test_uneven_flights_share_the_budget_up_to_the_last_row():
    counts = {"a": 100, "b": 5000, "c": 3000, "d": 8000}
    assert splits.budget_quota(counts, 16100) is None  # everything fits
    quota = splits.budget_quota(counts, 10000)
    picks = splits.budget_rows(counts, quota, seed=0)
    assert quota == 3450 and {f: len(p) for f, p in picks.items()} == {"a": 100, "b": 3450, "c": 3000, "d": 3450}
    assert all(np.all(np.diff(p) > 0) and p[-1] < counts[f] for f, p in picks.items())


def test_the_default_budget_leaves_a_small_fleet_as_it_was(tables):
    """Below the budget a run holds every usable row, as before the budget: every stride-th
    usable row of each fitting flight, all of the validation flights'; the same model as with
    no budget at all."""
    train = _train_flights(tables)
    config = learners.TrainConfig(stride=3)
    assert config.max_rows == learners.DEFAULT_ROW_BUDGET
    d = splits.training_data(tables, FS, train, config)
    assert d.rows.quota is None and d.rows.held == d.rows.usable == sum(_usable(tables, f) for f in train)
    expected_fit = np.concatenate([feat.matrix(tables[f], FS)[feat.usable(tables[f])][::3] for f in d.fit_flights])
    expected_val = np.concatenate([feat.matrix(tables[f], FS)[feat.usable(tables[f])] for f in d.val_flights])
    np.testing.assert_array_equal(d.X_fit, d.x_scaler.transform(expected_fit))
    np.testing.assert_array_equal(d.X_val, d.x_scaler.transform(expected_val))

    test = tables[HOLDOUT]
    X = feat.matrix(test, FS)[feat.usable(test)]
    budgeted = trainers.train(XGB, FS, tables, train, config)
    unbounded = trainers.train(XGB, FS, tables, train, learners.TrainConfig(stride=3, max_rows=10**12))
    np.testing.assert_array_equal(budgeted.predict_matrix(X), unbounded.predict_matrix(X))
    assert budgeted.manifest["rows_held"] == budgeted.manifest["rows_usable"]


def test_the_report_says_what_the_budget_left(tmp_path, tables, residuals):
    train = _train_flights(tables)
    plan = experiments.plan(list(tables), [FS], ["xgboost", "mlp"], HOLDOUT, compare=False,
                            specs={"xgboost": XGB, "mlp": MLP})
    config = learners.TrainConfig(stride=2, max_rows=1500)
    physics = model.PhysicsModel(VEHICLE, []).to_dict()
    records = experiments.run_plan(plan, {FS.name: tables}, tmp_path / "learned", physics, config,
                                   log=lambda m: None, latency_repeats=5)
    usable = sum(_usable(tables, f) for f in train)
    assert all(r.manifest["rows_held"] == 1500 and r.manifest["rows_usable"] == usable for r in records)
    assert all(r.rows_fit <= 1500 for r in records)
    report, _, paths = learn_workflow.full_report(tmp_path / "learned", residuals, VEHICLE, tmp_path / "reports")
    sentence = report["setup"]["training_rows"]
    assert sentence.startswith(f"trained on 1,500 of {usable:,} usable rows of the training flights: the row budget")
    assert "500 rows of each flight" in sentence and sentence in paths["md"].read_text()


def test_a_bad_row_budget_is_refused_in_one_line(monkeypatch):
    from pipeline import resources

    monkeypatch.setenv("QUADCORE_LEARN_ROWS", "300_000")
    assert resources.learn_row_budget() == 300_000
    monkeypatch.delenv("QUADCORE_LEARN_ROWS")
    assert resources.learn_row_budget() == learners.DEFAULT_ROW_BUDGET
    for bad in ("lots", "10", "-5", "2.5e5"):
        monkeypatch.setenv("QUADCORE_LEARN_ROWS", bad)
        with pytest.raises(resources.SettingError, match=f"QUADCORE_LEARN_ROWS='{bad}': give a whole number"):
            resources.learn_row_budget()
    with pytest.raises(learners.LearningError, match="at least 1000"):
        learners.check_row_budget(999)


def test_the_main_job_refuses_a_bad_row_budget_before_any_work(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "QUADCORE_DATA_ROOT": str(tmp_path / "data"),
           "QUADCORE_LEARN_ROWS": "lots"}
    env.pop("DAGSTER_HOME", None)
    done = subprocess.run([sys.executable, "-m", "pipeline"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"error: QUADCORE_LEARN_ROWS='lots': give a whole number of rows, at least 1000 "
        f"(default {learners.DEFAULT_ROW_BUDGET})"]
    assert not (tmp_path / "data").exists()


def test_leave_one_flight_out_is_capped_and_the_plan_says_so():
    flights = [f"f{i:03d}" for i in range(50)]
    left_out = splits.lofo_left_out(flights)
    assert len(left_out) == splits.MAX_LOFO_FOLDS and left_out[0] == "f000" and left_out[-1] == "f047"
    assert len(set(left_out)) == splits.MAX_LOFO_FOLDS
    plan = experiments.plan(flights, [FS], ["xgboost"], "f049", loo=True, compare=False)
    lofo = [e for e in plan.experiments if "lofo" in e.groups]
    assert [e.split.test for e in lofo] == [(f,) for f in left_out]
    assert any(f"{splits.MAX_LOFO_FOLDS} folds (its cap) for 50 flights" in n for n in plan.notes)
    few = [f"f{i:03d}" for i in range(splits.MAX_LOFO_FOLDS)]
    assert splits.lofo_left_out(few) == few  # the 19 real flights: every one, as before


def test_the_training_mean_baseline_is_summed_flight_by_flight_to_the_bit(residuals):
    train = [f for f in residuals if f != HOLDOUT]
    stacked = np.concatenate([feat.targets(residuals[f])[feat.usable(residuals[f])] for f in train])
    np.testing.assert_array_equal(metrics.training_mean(residuals, train), stacked.mean(axis=0))
