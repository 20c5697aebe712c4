"""Learned residual models: feature sets, training-only scaling, XGBoost and MLP training
(reproducible, and learning a hidden effect), artefacts and the predict API, leave-one-flight-out,
the report and the history, the CLI and the Dagster assets; one run on the real logs.

The simulated flights carry a hidden rotor drag (``f_b,xy = -k T v_b,xy``) that the nominal
model lacks, so the residual force along body x and y is learnable from the flight state.
"""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from quadcore import cli
from quadcore.identify import history, model
from quadcore.identify.fit import model_fit
from quadcore.learn import (
    artefacts,
    evaluation,
    experiments,
    features as feat,
    learners,
    metrics,
    splits,
    tables as learn_tables,
    trainers,
    trees,
)
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.sim import simulation
from quadcore.sim.simulation import SimConfig
from quadcore.spec.model import spec_from
from quadcore.store import store
from quadcore.workflows import fleet, learn as learn_workflow

VEHICLE = vehicle.load()
HIDDEN = {"rotor_drag": {"k_x_s_per_m": 0.3, "k_y_s_per_m": 0.3}}
SIM_KINDS = {"sim000": "random", "sim001": "random", "sim002": "preplanned", "sim003": "preplanned"}
HOLDOUT = "sim003"
# Small, quick models; threads=1 keeps the tests fast on a busy 2-core machine.
XGB = learners.LearnerSpec("xgboost", max_depth=3, n_estimators=60, early_stopping_rounds=10)
MLP = learners.LearnerSpec("mlp", hidden=(32,), max_epochs=40, patience=8, batch_size=256, lr=3e-3)
CONFIG = learners.TrainConfig(stride=2, threads=1)


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory) -> Path:
    """Four 8 s random go-to flights (0.5-1.5 m/s) with the hidden rotor drag, as uSD logs."""
    out = tmp_path_factory.mktemp("sim_logs")
    configs = [SimConfig(kind="random", duration_s=8.0, seed=10 + i, speed_min_mps=0.5, speed_max_mps=1.5)
               for i in range(4)]
    simulation.simulate_set(out, configs, HIDDEN, VEHICLE)
    (out / "flights.csv").write_text("flight,kind\n" + "".join(f"{f},{k}\n" for f, k in SIM_KINDS.items()))
    return out


@pytest.fixture(scope="module")
def decoded(sim_dir) -> dict[str, pl.DataFrame]:
    return {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in sorted(sim_dir.glob("sim00?"))}


@pytest.fixture(scope="module")
def residual_tables(decoded) -> dict[str, pl.DataFrame]:
    """Residual tables against the NOMINAL model (which lacks the hidden drag)."""
    nominal = model.PhysicsModel(VEHICLE, [])
    return {f: nominal.residual_table(df) for f, df in decoded.items()}


@pytest.fixture(scope="module")
def physics_tables(residual_tables):
    return {fs: feat.feature_tables(residual_tables, [feat.FEATURE_SETS[fs]])[fs] for fs in ("physics", "vel_rate")}


def _train(kind_spec, tables, seed=0, fs="physics"):
    train = [f for f in tables if f != HOLDOUT]
    return trainers.train(kind_spec, feat.FEATURE_SETS[fs], tables, train, replace(CONFIG, seed=seed),
                          model.PhysicsModel(VEHICLE, []).to_dict(), SIM_KINDS)


def _holdout(tables, fs="physics"):
    t = tables[HOLDOUT]
    m = feat.usable(t)
    return feat.matrix(t, feat.FEATURE_SETS[fs])[m], feat.targets(t)[m]


# ---------------------------------------------------------------------------------------
# Feature sets
# ---------------------------------------------------------------------------------------

def test_feature_sets_have_their_columns_and_no_nan(residual_tables):
    table = residual_tables["sim000"]
    assert set(feat.DEFAULT_FEATURE_SETS) >= {"vel_rate", "acc_rate_rot", "full_state", "physics"}
    for fs in feat.parse(None):
        ft = feat.feature_table(table, fs)
        assert ft.columns == ["t_s", "near_gap", *fs.columns, *feat.TARGETS], fs.name
        assert ft.height == table.height
        ok = feat.usable(ft)
        assert ok.sum() > 0.9 * ft.height
        X = feat.matrix(ft, fs)[ok]
        assert X.dtype == np.float32 and X.shape[1] == len(fs.columns)
        assert np.isfinite(X).all() and np.isfinite(feat.targets(ft)[ok]).all(), fs.name
    assert feat.FEATURE_SETS["physics"].columns == ("v_b_x_mps", "v_b_y_mps", "v_b_z_mps", "T_N", "motor_1_radps",
                                                   "motor_2_radps", "motor_3_radps", "motor_4_radps", "p_w_z_m")
    assert not feat.FEATURE_SETS["acc_rate_rot"].causal  # the measured acceleration sees the target
    assert all(feat.FEATURE_SETS[n].causal for n in ("vel_rate", "full_state", "physics", "physics_rate"))
    # derived columns: the first two columns of R_wb are orthonormal; the quaternion has q_w >= 0
    d = feat.with_derived(table)
    c0 = d.select("R_wb_00", "R_wb_10", "R_wb_20").to_numpy()
    c1 = d.select("R_wb_01", "R_wb_11", "R_wb_21").to_numpy()
    np.testing.assert_allclose(np.linalg.norm(c0, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose((c0 * c1).sum(axis=1), 0.0, atol=1e-6)
    assert (d["qc_w"].to_numpy() >= 0).all()
    # the targets are the body-frame residual, by name
    assert feat.TARGETS == ["f_res_b_x_N", "f_res_b_y_N", "f_res_b_z_N", "tau_res_b_x_Nm", "tau_res_b_y_Nm",
                            "tau_res_b_z_Nm"]


def test_feature_set_parsing_and_errors(residual_tables):
    sets = feat.parse("physics, mine=v_b_x_mps+T_N")
    assert [s.name for s in sets] == ["physics", "mine"]
    assert sets[1].columns == ("v_b_x_mps", "T_N") and sets[1].causal
    assert not feat.parse("leaky=sf_b_x_mps2+T_N")[0].causal
    with pytest.raises(feat.FeatureError, match="unknown feature set 'nope'"):
        feat.parse("nope")
    with pytest.raises(feat.FeatureError, match="no column"):
        feat.feature_table(residual_tables["sim000"], feat.custom("bad", ["not_a_column"]))


def test_feature_tables_on_disk_round_trip(tmp_path, residual_tables):
    sets = feat.parse("physics,vel_rate")
    feat.write_feature_tables(tmp_path, residual_tables, sets)
    got_sets, tables = feat.read_feature_tables(tmp_path)
    assert sorted(s.name for s in got_sets) == ["physics", "vel_rate"]
    assert sorted(tables["physics"]) == sorted(residual_tables)
    assert tables["physics"]["sim001"].equals(feat.feature_table(residual_tables["sim001"], sets[0]))


def test_scaling_is_fitted_on_training_flights_only(physics_tables):
    tables = physics_tables["physics"]
    fs = feat.FEATURE_SETS["physics"]
    m = _train(XGB, tables)
    train = sorted(f for f in tables if f != HOLDOUT)
    X = np.concatenate([feat.matrix(tables[f], fs)[feat.usable(tables[f])] for f in train])
    Y = np.concatenate([feat.targets(tables[f])[feat.usable(tables[f])] for f in train])
    np.testing.assert_allclose(m.x_scaler.mean, X.astype(np.float64).mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(m.x_scaler.std, X.astype(np.float64).std(axis=0), rtol=1e-9)
    np.testing.assert_allclose(m.y_scaler.mean, Y.mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(m.y_scaler.std, Y.std(axis=0), rtol=1e-9)
    assert m.x_scaler.fitted_on == train and m.y_scaler.fitted_on == train and HOLDOUT not in train
    # ... and they differ from statistics that include the held-out flight
    X_all = np.concatenate([X, feat.matrix(tables[HOLDOUT], fs)[feat.usable(tables[HOLDOUT])]])
    assert not np.allclose(m.x_scaler.mean, X_all.astype(np.float64).mean(axis=0), rtol=1e-6)
    # the validation flights are training flights, never the held-out one
    assert set(m.manifest["validation_flights"]) < set(train) and m.manifest["validation_flights"]
    assert set(m.manifest["fit_flights"]) | set(m.manifest["validation_flights"]) == set(train)


def test_validation_flights_are_seeded_and_balanced_over_kinds():
    flights = [f"f{i:02d}" for i in range(18)]
    kinds = {f: ("random" if i < 10 else "preplanned") for i, f in enumerate(flights)}
    v = splits.validation_flights(flights, 0.2, 0, kinds)
    assert v == splits.validation_flights(flights, 0.2, 0, kinds) and len(v) == 4
    assert {kinds[f] for f in v} == {"random", "preplanned"}
    assert splits.validation_flights(["a"], 0.2, 0) == []
    assert len(splits.lofo_splits(flights)) == 18
    assert splits.holdout_split(flights, "f03").train == tuple(f for f in flights if f != "f03")


# ---------------------------------------------------------------------------------------
# Models: reproducible, and they learn the hidden drag
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("options", ["epochs=0", "lr=1e30"], ids=["no epoch", "diverged"])
def test_mlp_without_a_finite_validation_loss_is_a_learning_error(options, physics_tables):
    """No epoch run, or a loss that is NaN from the first epoch: no weights worth keeping."""
    spec = learners.parse_spec(f"mlp:hidden=8,patience=1,epochs=2,{options}")
    with pytest.raises(learners.LearningError, match="no epoch gave a finite validation loss"):
        _train(spec, physics_tables["physics"])


@pytest.mark.parametrize("spec", [XGB, MLP], ids=["xgboost", "mlp"])
def test_models_are_reproducible_and_learn_the_hidden_drag(spec, physics_tables):
    tables = physics_tables["physics"]
    X, Y = _holdout(tables)
    a = _train(spec, tables, seed=0)
    b = _train(spec, tables, seed=0)
    pa, pb = a.predict_matrix(X), b.predict_matrix(X)
    np.testing.assert_array_equal(pa, pb)  # same seed, same model
    c = _train(spec, tables, seed=1)
    assert not np.array_equal(pa, c.predict_matrix(X))  # the seed matters (subsampling / init)
    m = metrics.metrics(Y, pa)
    zero = metrics.metrics(Y, np.zeros_like(Y))
    mean = metrics.metrics(Y, np.broadcast_to(Y.mean(axis=0) * 0 + a.y_scaler.mean, Y.shape))
    assert m["force_r2_x"] > 0.5 and m["force_r2_y"] > 0.5, m
    for ax in "xy":
        assert m[f"force_mae_{ax}_N"] < 0.6 * zero[f"force_mae_{ax}_N"]
        assert m[f"force_mae_{ax}_N"] < mean[f"force_mae_{ax}_N"]
    assert a.manifest["train_time_s"] > 0 and a.manifest["val_loss"] < 1.0


def test_two_lanes_train_the_models_one_lane_trains(physics_tables):
    """XGBoost and MLP experiments trained side by side (two MLPs, so torch's seed is set twice
    in the MLP lane) give bit-for-bit the models of a sequential run, in plan order."""
    sets = [feat.FEATURE_SETS["physics"]]
    p = experiments.plan(sorted(physics_tables["physics"]), sets, ["xgboost", "mlp"], HOLDOUT, None, compare=False,
                      specs={"xgboost": XGB, "mlp": replace(MLP, max_epochs=6)})
    exps = p.experiments + [replace(p.experiments[1], spec=replace(MLP, hidden=(8,), max_epochs=4))]
    tables = {"physics": physics_tables["physics"]}
    X, _ = _holdout(physics_tables["physics"])
    one = experiments.train_experiments(exps, tables, replace(CONFIG, lanes=1))
    two = experiments.train_experiments(exps, tables, replace(CONFIG, lanes=2))
    assert [m.kind for m in two] == [e.spec.kind for e in exps] == ["xgboost", "mlp", "mlp"]
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a.predict_matrix(X), b.predict_matrix(X))


def test_artefacts_save_load_and_predict_api(tmp_path, physics_tables, residual_tables, decoded):
    tables = physics_tables["physics"]
    X, _ = _holdout(tables)
    for spec in (XGB, MLP):
        m = _train(spec, tables)
        folder = m.save(tmp_path / spec.kind)
        assert {p.name for p in folder.iterdir()} >= {"manifest.json", "scaler.json", "features.json",
                                                     "model.ubj" if spec.kind == "xgboost" else "model.pt"}
        manifest = json.loads((folder / "manifest.json").read_text())
        assert manifest["physics_model"]["vehicle"] == "crazyflie21" and manifest["physics_model"]["effects"] == []
        assert manifest["feature_set"]["name"] == "physics"
        assert manifest["train_flights"] == ["sim000", "sim001", "sim002"]
        columns = json.loads((folder / "features.json").read_text())["columns"]
        assert columns == list(feat.FEATURE_SETS["physics"].columns)
        loaded = artefacts.load(folder, threads=1)
        np.testing.assert_allclose(loaded.predict_matrix(X), m.predict_matrix(X), rtol=1e-6, atol=1e-12)
        # the predict API: a flight table in, residual force (N) and torque (N m) out
        f, tau = loaded.predict(residual_tables[HOLDOUT])
        assert f.shape == tau.shape == (residual_tables[HOLDOUT].height, 3)
        full = m.predict_matrix(feat.matrix(tables[HOLDOUT], m.feature_set))
        np.testing.assert_allclose(np.concatenate([f, tau], axis=1), full, rtol=1e-6, atol=1e-12)
        # a decoded table works too: the manifest's physics model builds the residual table
        f2, tau2 = loaded.predict(decoded[HOLDOUT])
        np.testing.assert_allclose(f2, f, rtol=1e-5, atol=1e-9)
        pt = loaded.predict_table(residual_tables[HOLDOUT])
        assert pt.columns == ["t_s", *artefacts.PRED_COLUMNS]
        # the per-sample path gives the same answer
        np.testing.assert_allclose(loaded.predict_one(X[7]), full[feat.usable(tables[HOLDOUT])][7],
                                   rtol=1e-4, atol=1e-7)
    with pytest.raises(learners.LearningError, match="no learned model"):
        artefacts.load(tmp_path / "nothing")


def test_a_decoded_flight_is_predicted_on_its_sessions_physics(tmp_path, physics_tables, decoded):
    """Under a physics model whose session flies another thrust map, a decoded flight of that
    session gets the residual features the models were trained on (its session's map, as
    ``residual_table`` computes them), not the fleet's."""
    per_session = model.PhysicsModel(VEHICLE, [], {"late": [HOLDOUT]}, {"late": "motor_speed"})
    trained = _train(XGB, physics_tables["physics"])
    trained.manifest["physics_model"] = per_session.to_dict()
    loaded = artefacts.load(trained.save(tmp_path / "xgb"))
    f, tau = loaded.predict(decoded[HOLDOUT], HOLDOUT)
    f_ref, tau_ref = loaded.predict(per_session.for_flight(HOLDOUT).residual_table(decoded[HOLDOUT]))
    np.testing.assert_array_equal(np.concatenate([f, tau], axis=1), np.concatenate([f_ref, tau_ref], axis=1))
    f_fleet, _ = loaded.predict(decoded[HOLDOUT])  # without the flight: the fleet's map, other features
    assert not np.allclose(f_fleet, f)


def test_compiled_forest_matches_xgboost(physics_tables):
    m = _train(replace(XGB, max_depth=5), physics_tables["physics"])
    X, _ = _holdout(physics_tables["physics"])
    Z = m.x_scaler.transform(X[:300])
    Z[::7, 2] = np.nan  # missing values take the trees' default branch
    forest = trees.CompiledForest(m.impl)
    ref = m.impl.inplace_predict(Z)
    np.testing.assert_allclose(forest.predict(Z), ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.array([forest.predict_one(z) for z in Z[:40]]), ref[:40], rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------
# Experiments, leave-one-flight-out, the report and the history
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def report_run(tmp_path_factory, residual_tables):
    root = tmp_path_factory.mktemp("learn_root")
    sets = feat.parse("physics,vel_rate")
    p = experiments.plan(sorted(residual_tables), sets, ["xgboost", "mlp"], HOLDOUT, SIM_KINDS, loo=True, compare=True,
                      specs={"xgboost": XGB, "mlp": replace(MLP, max_epochs=15)})
    physics = {**model.PhysicsModel(VEHICLE, []).to_dict(), "trained_on": [f for f in residual_tables if f != HOLDOUT]}
    records = experiments.run_plan(p, feat.feature_tables(residual_tables, sets), root / "learned", physics, CONFIG,
                                SIM_KINDS, log=lambda m: None, latency_repeats=30)
    report, pngs, paths = learn_workflow.full_report(root / "learned", residual_tables, VEHICLE, root / "reports", root)
    return root, p, records, report, pngs, paths


@pytest.mark.slow  # the whole learning plan and report
def test_plan_covers_the_comparisons(report_run):
    _, p, records, *_ = report_run
    groups = {g for r in records for g in r.groups}
    assert groups == {"feature_sets", "complexity", "training_size", "lofo"}
    names = [r.name for r in records]
    assert len(names) == len(set(names))  # shared runs are trained once
    complexity = {r.spec.max_depth for r in records if r.kind == "xgboost" and "complexity" in r.groups}
    assert complexity == {2, 4, 6, 8}
    assert {tuple(r.spec.hidden) for r in records if r.kind == "mlp" and "complexity" in r.groups} == \
        {(), (64,), (64, 64)}
    # training size: random flights only (sim000, sim001) vs all; one preplanned training flight is too few
    assert {r.train_group for r in records if "training_size" in r.groups} == {"all", "random"}
    assert any("only 1 preplanned" in n for n in p.notes)
    lofo = [r for r in records if "lofo" in r.groups]
    assert sorted({r.split.test[0] for r in lofo}) == sorted(SIM_KINDS)
    assert all(r.split.test[0] not in r.train_flights for r in records)


@pytest.mark.slow  # the whole learning plan and report
def test_report_tables_baselines_and_files(report_run, residual_tables):
    root, _, records, report, pngs, paths = report_run
    for ext in ("md", "html", "json"):
        assert paths[ext].is_file() and paths[ext].stat().st_size > 1000
    on_disk = json.loads(paths["json"].read_text())
    assert set(on_disk["tables"]) >= {"headline", "holdout", "feature_sets", "complexity", "training_size", "lofo"}
    assert set(pngs) >= {"timeseries", "regimes", "importance", "comparison", "history"}
    md = paths["md"].read_text()
    assert "study: best tree (XGBoost)" in md and "physics-only" in md and "data:image/png;base64" in md
    # baselines on the held-out flight: physics-only predicts zero, so its MAE is the mean |residual|
    t = residual_tables[HOLDOUT]
    y = feat.targets(t)[feat.usable(t)]
    base = report["baselines"][f"holdout-{HOLDOUT}"]
    assert base["physics-only"]["force_mae_x_N"] == pytest.approx(np.abs(y[:, 0]).mean())
    assert base["zero"]["force_mae_x_N"] == pytest.approx(base["physics-only"]["force_mae_x_N"])  # no effects
    train = [f for f in residual_tables if f != HOLDOUT]
    mean = np.concatenate([feat.targets(residual_tables[f])[feat.usable(residual_tables[f])] for f in train]).mean(0)
    assert base["training mean"]["force_mae_y_N"] == pytest.approx(np.abs(y[:, 1] - mean[1]).mean())
    # every run's metrics are finite; the best models beat physics-only on the drag axes
    for r in report["runs"]:
        assert all(np.isfinite(v) for v in metrics.mae(r["metrics"]))
        assert r["train_time_s"] > 0 and r["predict_time_s"] > 0 and r["latency_us"] > 0
    for kind, name in report["best"].items():
        r = learn_tables.report_run(report, name)
        assert r["causal"]
        for ax in "xy":
            assert r["metrics"][f"force_mae_{ax}_N"] < base["physics-only"][f"force_mae_{ax}_N"], (kind, ax)
    lofo = report["lofo"]
    assert lofo["folds"] == 4 and {row["model"] for row in lofo["table"]} >= {"physics-only", "xgboost(physics)"}
    assert "Leave-one-flight-out" in report["verdict"]
    headline = report["tables"]["headline"]
    assert headline[0]["Fx MAE [N]"] == 0.021 and headline[0]["train [s]"] == 41.9


@pytest.mark.slow  # the whole learning plan and report
def test_history_rows_are_written(report_run):
    root, *_ , report, _, _ = report_run
    hist = history.read(root)
    learned = hist.filter(pl.col("source") == "learned")
    labels = learned["model_label"].to_list()
    assert "nominal" in labels
    assert any(lab.startswith("nominal+xgboost(") for lab in labels)
    assert any(lab.startswith("nominal+mlp(") for lab in labels)
    assert set(learned["eval_mode"].to_list()) == {"holdout", "leave-one-flight-out"}
    assert learned.select(history.RMSE_COLUMNS).to_numpy().min() > 0


def test_nominal_baseline_with_effects_in_the_model(decoded, residual_tables):
    """With effects in the physics model, 'zero' is the nominal model's residual, exactly."""
    train = [f for f in decoded if f != HOLDOUT]
    fitted = model_fit.fit_model(spec_from(VEHICLE, ["rotor_drag"]), decoded, train)
    with_drag = fitted.residual_table(decoded[HOLDOUT])
    np.testing.assert_allclose(metrics.nominal_residual(with_drag, VEHICLE),
                               feat.targets(residual_tables[HOLDOUT]), atol=1e-9)
    tables = {f: fitted.residual_table(df) for f, df in decoded.items()}
    base = metrics.baseline_predictions(tables, train, [HOLDOUT], VEHICLE)
    zero = metrics.metrics(*metrics._yp(base["zero"]))
    phys = metrics.metrics(*metrics._yp(base["physics-only"]))
    assert phys["force_mae_x_N"] < 0.5 * zero["force_mae_x_N"]  # the fitted drag explains most of it


# ---------------------------------------------------------------------------------------
# The CLI and the Dagster assets
# ---------------------------------------------------------------------------------------

def _cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, out.getvalue(), err.getvalue()


@pytest.mark.slow  # the whole train command
def test_cli_train(tmp_path, sim_dir):
    code, out, err = _cli("train", str(sim_dir), "--holdout", HOLDOUT, "--feature-sets", "physics", "--no-compare",
                          "--xgboost", "depth=3,trees=40", "--mlp", "hidden=16,epochs=10", "--out", str(tmp_path),
                          "--threads", "1", "--quiet")
    assert code == 0, err
    assert "study: best tree (XGBoost)" in out and "ours: best xgboost" in out and "physics-only" in out
    assert (tmp_path / "reports" / "learning.html").is_file()
    index = json.loads((tmp_path / "learned" / "index.json").read_text())
    assert index["holdout"] == HOLDOUT and index["flight_kinds"] == SIM_KINDS  # flights.csv found beside the logs
    assert len(index["runs"]) == 2
    # no jana02 among simulated flights: the default holdout falls back to the last flight, with a note
    code, out, err = _cli("train", str(sim_dir), "--models", "xgboost", "--feature-sets", "vel_rate", "--no-compare",
                          "--xgboost", "trees=20", "--out", str(tmp_path / "b"), "--threads", "1", "--quiet")
    assert code == 0 and "held out 'sim003'" in err


@pytest.mark.parametrize("argv, message", [
    (["--holdout", "nosuch"], "holdout flight 'nosuch' not found"),
    (["--feature-sets", "bogus"], "unknown feature set 'bogus'"),
    (["--models", "forest"], "unknown model kind 'forest'"),
    (["--effects", "warp_drive"], "warp_drive"),
    (["--xgboost", "depth=deep"], "bad value"),
    (["--stride", "0"], "at least 1"),
    (["--max-rows", "5"], "row budget 5: give a whole number of rows, at least 1000"),
    (["--thrust-map", "bogus"], "unknown thrust map 'bogus'"),
    (["--model", "no_such_model.toml"], "no_such_model.toml"),
])
def test_cli_train_user_errors(tmp_path, sim_dir, argv, message):
    code, out, err = _cli("train", str(sim_dir), "--out", str(tmp_path), *argv)
    assert code == 2 and message in err and "Traceback" not in err


def test_cli_train_missing_data(tmp_path):
    code, _, err = _cli("train", str(tmp_path / "absent"), "--out", str(tmp_path))
    assert code == 2 and "no such folder" in err


@pytest.mark.slow  # the learning assets materialised
def test_dagster_assets(tmp_path, residual_tables):
    import dagster as dg

    from pipeline.assets.learning import learned_models, learning_features, learning_report
    from pipeline.resources import DataRoot, ModelConfig

    physics = model.PhysicsModel(VEHICLE, []).to_dict()
    for f, t in residual_tables.items():
        store.write_parquet(t, store.table_path(tmp_path, "residuals", f), {"flight": f, "model": physics})
    run_config = {"ops": {
        "learning_features": {"config": {"feature_sets": ["physics"]}},
        "learned_models": {"config": {"holdout": HOLDOUT, "compare": False, "xgboost": "depth=3,trees=30",
                                      "mlp": "hidden=16,epochs=8", "threads": 1, "stride": 3}},
    }}
    with dg.instance_for_test() as instance:
        resources = {"data_root": DataRoot(root=str(tmp_path)), "model": ModelConfig()}
        assets = [learning_features, learned_models, learning_report]
        result = dg.materialize(assets, instance=instance, resources=resources, run_config=run_config)
        # a named holdout (here the learning config's) that the physics model was fitted on would leak
        # it: refused with the reason. With nothing named, the physics is fitted on every flight and
        # the report says so (test_a_physics_fit_on_every_flight_is_said_in_the_setup)
        store.write_json({**physics, "trained_on": sorted(residual_tables)}, tmp_path / "models" / "physics_model.json")
        leaky = dg.materialize(assets, instance=instance, resources=resources, run_config=run_config,
                               raise_on_error=False)
        # residual tables against different models: refused, naming the stale flights
        store.write_json({**physics, "trained_on": []}, tmp_path / "models" / "physics_model.json")
        stale_flight = sorted(residual_tables)[0]
        other = model.PhysicsModel(VEHICLE, [model.EffectTerm("rotor_drag", {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1})])
        store.write_parquet(residual_tables[stale_flight], store.table_path(tmp_path, "residuals", stale_flight),
                            {"flight": stale_flight, "model": other.to_dict()})
        mixed = dg.materialize(assets, instance=instance, resources=resources, run_config=run_config,
                               raise_on_error=False)
    failures = {name: [e.event_specific_data.user_failure_data.description for e in r.all_events
                       if e.is_step_failure and e.event_specific_data.user_failure_data]
                for name, r in (("leaky", leaky), ("mixed", mixed))}
    assert not leaky.success and "fitted on" in failures["leaky"][0] and HOLDOUT in failures["leaky"][0]
    assert not mixed.success and stale_flight in failures["mixed"][0]
    assert result.success
    assert (tmp_path / "features" / "physics" / f"flight={HOLDOUT}" / "data.parquet").is_file()
    (mat,) = result.asset_materializations_for_node("learning_report")
    meta = {k: v.value for k, v in mat.metadata.items()}
    assert meta["timeseries_plot"].startswith("![timeseries](/quadcore-plots/") and "study" in meta["headline"]
    assert (tmp_path / "reports" / "learning.json").is_file()
    assert history.read(tmp_path).filter(pl.col("source") == "learned").height == 3  # physics-only + 2 best


# ---------------------------------------------------------------------------------------
# The real logs
# ---------------------------------------------------------------------------------------

@pytest.mark.slow  # the real fleet
def test_real_logs_holdout_jana02(real_logs, tmp_path):
    flights, _ = fleet.decode_logs([str(real_logs)], None, log=lambda m: None)
    nominal = model.PhysicsModel(VEHICLE, [])
    res = {f.flight_id: nominal.residual_table(f.tables["fixedFrequency"]) for f in flights}
    assert len(res) == 19
    kinds = feat.read_flight_kinds(real_logs.parent / "flights.csv")
    sets = feat.parse("physics")
    p = experiments.plan(sorted(res), sets, ["xgboost", "mlp"], "jana02", kinds, compare=False,
                      specs={"xgboost": replace(XGB, max_depth=4, n_estimators=80),
                             "mlp": replace(MLP, max_epochs=8)})
    records = experiments.run_plan(p, feat.feature_tables(res, sets), tmp_path / "learned",
                                {**nominal.to_dict(), "trained_on": [f for f in res if f != "jana02"]},
                                learners.TrainConfig(threads=1), kinds, log=lambda m: None, latency_repeats=30)
    assert len(records) == 2 and all(len(r.train_flights) == 18 for r in records)
    report, _, paths = learn_workflow.full_report(tmp_path / "learned", res, VEHICLE, tmp_path / "reports", tmp_path)
    assert paths["html"].is_file()
    base = report["baselines"]["holdout-jana02"]
    assert base["physics-only"]["rows"] == report["runs"][0]["metrics"]["rows"] > 3800
    for r in report["runs"]:
        vals = metrics.mae(r["metrics"]) + metrics.r2(r["metrics"])
        assert np.isfinite(vals).all()
        assert r["train_time_s"] < 60
    assert set(report["best"]) == {"xgboost", "mlp"}
    models = [row["model"] for row in report["tables"]["headline"]]
    assert models[0].startswith("study") and any(m.startswith("ours: best xgboost") for m in models)
    # the nominal model's residual on jana02 (what the learned models improve on): force MAE of mN
    assert 0.002 < base["physics-only"]["force_mae_x_N"] < 0.05


def test_share_of_the_learned_gain_the_physics_captures():
    """(MAE nominal - MAE physics) / (MAE nominal - MAE learned), per channel: 2/3 here."""
    y = np.random.default_rng(0).normal(size=(200, 6))

    def m(err):
        return metrics.metrics(y, y + err)

    base = {"zero": m(1.0), "physics-only": m(0.5), "training mean": m(2.0)}
    best = {"xgboost": {"metrics": m(np.array([0.25, 0.25, 0.25, 0.75, 0.75, 0.75])), "feature_set": {"name": "f"}}}
    share = learn_tables.captured_share(best, base)["xgboost"]
    assert share["force"] == pytest.approx(2 / 3) and share["torque"] == pytest.approx(2.0)
    assert "captures 67% in force" in learn_tables.verdict(best, base, None)
    assert learn_tables.captured_share(best, {**base, "zero": m(0.5)}) == {}  # no effects: nothing to compare


def test_a_physics_fit_on_every_flight_is_said_in_the_setup():
    """Without a named holdout the physics model is fitted on every flight (the default): the
    learning report's Setup says that its test flight was in the physics fit, and how to keep it out."""
    physics = model.PhysicsModel(VEHICLE, [model.EffectTerm("rotor_drag", {"k_x_s_per_m": 0.1,
                                                                           "k_y_s_per_m": 0.1})]).to_dict()
    flights = {f: None for f in ("sim000", "sim001", HOLDOUT)}
    index = {"holdout": HOLDOUT, "config": {}}
    every = evaluation.setup_summary(index, [], flights, physics, sorted(flights))["physics_fit"]
    assert "every flight" in every and f"QUADCORE_HOLDOUT={HOLDOUT}" in every and "never saw" in every
    clean = evaluation.setup_summary(index, [], flights, physics, ["sim000", "sim001"])["physics_fit"]
    assert clean == f"the physics model's effects were fitted without {HOLDOUT}"
