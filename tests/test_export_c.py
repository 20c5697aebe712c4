"""`quadcore export-c`: the generated C compiles with ``-std=c99 -Wall -Wextra -Werror -pedantic``
and, run on every row of a held-out simulated flight, gives what the Python model gives (max
absolute error < 1e-5 N and < 1e-8 N m) for every effect's C form, a fitted physics model, the best
XGBoost and the best MLP; effects without a C form and features with no on-board form are refused
by name.
"""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from quadcore import cli, effects
from quadcore.export import c as export_c
from quadcore.export.c.learned import raw_thresholds
from quadcore.identify import model
from quadcore.identify.fit import model_fit
from quadcore.identify.model import EffectTerm, PhysicsModel
from quadcore.learn import artefacts, evaluation, experiments, features as feat, learners, trainers
from quadcore.logs import flight
from quadcore.physics import dynamics, vehicle
from quadcore.sim import simulation
from quadcore.sim.simulation import SimConfig
from quadcore.spec.model import spec_from
from quadcore.store import store

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler (install gcc: .ci/run does)")

VEHICLE = vehicle.load()
HOLDOUT = "sim002"
FORCE_TOL_N, TORQUE_TOL_NM = 1e-5, 1e-8
XGB = learners.LearnerSpec("xgboost", max_depth=4, n_estimators=40, early_stopping_rounds=8)
MLP = learners.LearnerSpec("mlp", hidden=(16, 16), max_epochs=15, patience=5, lr=3e-3)


@pytest.fixture(scope="module")
def decoded(tmp_path_factory) -> dict[str, pl.DataFrame]:
    """Three 5 s random flights with a hidden rotor drag and CoM offset, decoded."""
    out = tmp_path_factory.mktemp("sim_logs")
    configs = [SimConfig(kind="random", duration_s=5.0, seed=20 + i, speed_min_mps=0.5, speed_max_mps=1.5)
               for i in range(3)]
    hidden = {"rotor_drag": {"k_x_s_per_m": 0.3, "k_y_s_per_m": 0.3}, "com_offset": {"x_c_m": 0.002, "y_c_m": -0.001}}
    simulation.simulate_set(out, configs, hidden, VEHICLE)
    return {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in sorted(out.glob("sim00?"))}


def _every_effect(names) -> PhysicsModel:
    """Each effect at 30 % of the way from 'no effect' to a bound: a clearly non-zero wrench."""
    terms = []
    for name in names:
        eff = effects.get(name)
        params = {p.name: p.default + 0.3 * ((p.upper if p.upper != p.default else p.lower) - p.default)
                  for p in eff.parameters}
        terms.append(EffectTerm(name, params))
    return PhysicsModel(VEHICLE, terms)


def _run_c(exported: export_c.Exported, table: pl.DataFrame, workdir: Path) -> dict[str, np.ndarray]:
    host = export_c.HostModel(exported.header.parent, exported.generated, workdir)
    return host.run(export_c.input_rows(table, exported.fields))


def _assert_close(f_c, tau_c, f_py, tau_py, what: str) -> None:
    f_err, tau_err = np.abs(f_c - f_py).max(), np.abs(tau_c - tau_py).max()
    assert f_err < FORCE_TOL_N, f"{what}: force differs by {f_err:.3g} N"
    assert tau_err < TORQUE_TOL_NM, f"{what}: torque differs by {tau_err:.3g} N m"


# Built-in effects that cannot run on board as they are computed in Python, and why.
NO_C_FORM: dict[str, str] = {}
WITH_C_FORM = [n for n in effects.registry() if n not in NO_C_FORM]


# The fast tier keeps motor_lag (an effect with state); test_all_effects_together_... compares the
# sum of every effect's C form with Python in the fast tier too, each effect alone runs in the whole suite.
@pytest.mark.parametrize("name", [n if n == "motor_lag" else pytest.param(n, marks=pytest.mark.slow)
                                  for n in effects.registry()])
def test_every_effect_has_a_c_form_that_matches_python(name, decoded, tmp_path):
    pm = _every_effect([name])
    if name in NO_C_FORM:
        with pytest.raises(export_c.NoCFormError, match=f"'{name}' has no C form"):
            export_c.export_models(pm, None, tmp_path / "out", f"effect {name}")
        return
    exported = export_c.export_models(pm, None, tmp_path / "out", f"effect {name}")
    out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
    f_py, tau_py = pm.extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
    assert np.abs(f_py).max() + np.abs(tau_py).max() > 1e-4  # the effect does something on this flight
    _assert_close(out["f_effects_b_N"], out["tau_effects_b_Nm"], f_py, tau_py, name)
    np.testing.assert_array_equal(out["f_learned_b_N"], 0.0)
    np.testing.assert_array_equal(out["f_b_N"], out["f_effects_b_N"])


def test_all_effects_together_and_the_struct_carries_what_they_read(decoded, tmp_path):
    pm = _every_effect(WITH_C_FORM)
    exported = export_c.export_models(pm, None, tmp_path / "out", "all effects")
    out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
    f_py, tau_py = pm.extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
    _assert_close(out["f_b_N"], out["tau_b_Nm"], f_py, tau_py, "all effects")
    # motor_lag, thrust_delay and rotor_inertia read dt_s; rotor_inertia and inertia_scale the gyro,
    # rotor_inertia the motor speeds
    assert {f.name for f in exported.fields} == {"p_w_m", "v_w_mps", "q_xyzw", "pwm", "vbat_V", "dt_s",
                                                 "omega_b_radps", "motor_radps"}
    only_drag = export_c.export_models(_every_effect(["com_offset"]), None, tmp_path / "com", "com")
    assert [f.name for f in only_drag.fields] == ["pwm", "vbat_V"]


def test_fitted_physics_model_through_the_cli(decoded, tmp_path):
    spec = spec_from(VEHICLE, ["rotor_drag", "com_offset", "motor_lag"])
    train = [f for f in decoded if f != HOLDOUT]
    fitted = model_fit.fit_model(spec, decoded, train)
    path = model.save(fitted, tmp_path / "models" / "physics_model.json", train, spec)
    out_dir = tmp_path / "c"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert cli.main(["export-c", str(path), "--out", str(out_dir)]) == 0
    assert "nominal+rotor_drag+com_offset+motor_lag" in stdout.getvalue()
    source = (out_dir / "quadcore_model.c").read_text()
    k_x = fitted.terms[0].params["k_x_s_per_m"]
    assert f"const qc_real k_x_s_per_m = ((qc_real){k_x!r});" in source  # the fitted value, as a constant
    assert "Footprint" in source and "flash" in (out_dir / "quadcore_model.h").read_text()
    loaded = model.load_fitted(path, VEHICLE)
    exported = export_c.export(path, tmp_path / "again", "none")
    out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
    f_py, tau_py = loaded.extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
    _assert_close(out["f_b_N"], out["tau_b_Nm"], f_py, tau_py, "fitted model")


@pytest.fixture(scope="module")
def data_root(decoded, tmp_path_factory) -> tuple[Path, PhysicsModel]:
    """A data root with a fitted physics model (CoM offset; the hidden rotor drag is left for the
    learned models) and XGBoost and MLP runs on three feature sets, the holdout flight left out."""
    root = tmp_path_factory.mktemp("root")
    train = [f for f in decoded if f != HOLDOUT]
    spec = spec_from(VEHICLE, ["com_offset"])
    physics = model_fit.fit_model(spec, decoded, train)
    model.save(physics, root / "models" / "physics_model.json", train, spec)
    res = {f: physics.residual_table(df) for f, df in decoded.items()}
    sets = feat.parse("physics,vel_rate,full_state")
    plan = experiments.plan(sorted(res), sets, ["xgboost", "mlp"], HOLDOUT, compare=False,
                         specs={"xgboost": XGB, "mlp": MLP})
    physics_info = {**physics.to_dict(), "trained_on": train}
    experiments.run_plan(plan, feat.feature_tables(res, sets), root / "learned", physics_info,
                      learners.TrainConfig(stride=2), log=lambda m: None, latency_repeats=5)
    return root, physics


@pytest.mark.parametrize("kind", ["xgboost", "mlp"])
@pytest.mark.slow  # trains the learned models
def test_best_learned_model_on_top_of_the_physics_matches_python(kind, data_root, decoded, tmp_path):
    root, physics = data_root
    exported = export_c.export(root, tmp_path / "out", kind)
    index, records = experiments.read_runs(root / "learned")
    best = evaluation.best_runs([{**r, "causal": r["feature_set"]["causal"]} for r in records])[kind]
    learned = artefacts.load(best["path"])
    assert exported.generated.feature_columns == tuple(learned.features)
    assert exported.generated.label == f"{physics.label} + {kind}({learned.feature_set.name})"

    table = decoded[HOLDOUT]
    out = _run_c(exported, table, tmp_path / "build")
    f_learned, tau_learned = learned.predict(physics.residual_table(table))
    _assert_close(out["f_learned_b_N"], out["tau_learned_b_Nm"], f_learned, tau_learned, f"best {kind}")
    f_phys, tau_phys = physics.extra_wrench(dynamics.flight_state(table, VEHICLE))
    _assert_close(out["f_b_N"], out["tau_b_Nm"], f_phys + f_learned, tau_phys + tau_learned, f"physics + {kind}")
    assert np.abs(f_learned).max() > 0.01  # the learned part carries the rotor drag


@pytest.mark.slow  # the data_root fixture trains the learned models
def test_every_feature_set_the_exporter_can_compute(data_root, decoded, tmp_path):
    """Each causal feature set's learned model (not only the best) through the C feature code."""
    root, physics = data_root
    _, records = experiments.read_runs(root / "learned")
    table = physics.residual_table(decoded[HOLDOUT])
    for r in (r for r in records if r["kind"] == "xgboost"):
        learned = artefacts.load(r["path"])
        exported = export_c.export_models(physics, learned, tmp_path / r["name"], r["name"])
        out = _run_c(exported, decoded[HOLDOUT], tmp_path / f"build-{r['name']}")
        f_py, tau_py = learned.predict(table)
        _assert_close(out["f_learned_b_N"], out["tau_learned_b_Nm"], f_py, tau_py, r["feature_set"]["name"])


def _tether_plugin(tmp_path: Path, name: str) -> None:
    """Load a plugin effect ``name`` (a constant vertical pull) that has no C form."""
    plugin = tmp_path / f"{name}.py"
    plugin.write_text(
        "import numpy as np\n"
        "from quadcore.effects import Effect, Parameter\n"
        "class Tether(Effect):\n"
        f"    name = {name!r}\n"
        "    parameters = (Parameter('F_z_N', 'N', 0.0, -1.0, 1.0, 'pull'),)\n"
        "    def wrench(self, state, vehicle, params):\n"
        "        f = np.zeros((state.n, 3)); f[:, 2] = params['F_z_N']\n"
        "        return f, np.zeros((state.n, 3))\n"
        "EFFECT = Tether()\n")
    effects.load_plugin(plugin)


def test_effect_without_c_form_is_refused_by_name(tmp_path, decoded):
    _tether_plugin(tmp_path, "tether_no_c")
    try:
        pm = PhysicsModel(VEHICLE, [EffectTerm("rotor_drag", {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}),
                                    EffectTerm("tether_no_c", {"F_z_N": 0.1})])
        with pytest.raises(export_c.NoCFormError, match="'tether_no_c' has no C form") as info:
            export_c.export_models(pm, None, tmp_path / "out", "test")
        assert info.value.effect == "tether_no_c"
        assert not (tmp_path / "out").exists()  # nothing half-written
        path = model.save(pm, tmp_path / "physics_model.json", [], spec_from(VEHICLE, pm.effect_names))
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            assert cli.main(["export-c", str(path), "--out", str(tmp_path / "cli")]) == 2
        assert "tether_no_c" in err.getvalue() and "Traceback" not in err.getvalue()
    finally:
        effects.unregister("tether_no_c")


@pytest.mark.slow  # the data_root fixture trains the learned models
def test_leaky_feature_set_has_no_on_board_form(data_root, decoded, tmp_path):
    root, physics = data_root
    res = {f: physics.residual_table(df) for f, df in decoded.items()}
    fs = feat.FEATURE_SETS["acc_rate_rot"]
    tables = feat.feature_tables(res, [fs])[fs.name]
    learned = trainers.train(XGB, fs, tables, [f for f in res if f != HOLDOUT], learners.TrainConfig(stride=4))
    with pytest.raises(export_c.ExportError, match="'a_meas_w_x_mps2' has no on-board form"):
        export_c.export_models(physics, learned, tmp_path / "out", "leaky")


def test_bad_sources_are_user_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "garbage.json").write_text("{not json")
    # a fitted model naming a plugin effect whose module this process has not loaded
    plugin_model = PhysicsModel(VEHICLE, [EffectTerm("thrust_scale", {"scale": 1.02})]).to_dict()
    plugin_model["effects"][0]["name"] = "my_plugin_effect"
    store.write_json(plugin_model, tmp_path / "plugin_model.json")
    for args in (["export-c", str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
                 ["export-c", str(tmp_path / "empty"), "--out", str(tmp_path / "o")],
                 ["export-c", str(tmp_path / "garbage.json"), "--out", str(tmp_path / "o")],
                 ["export-c", str(tmp_path / "plugin_model.json"), "--out", str(tmp_path / "o")]):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            assert cli.main(args) == 2
        assert err.getvalue().startswith("quadcore export-c: error:")


def test_raw_thresholds_take_the_branches_of_the_standardised_model():
    """For random scalings and splits, ``float32((x - mean) / std) < t`` iff ``x < x*`` on
    the float32 values around every split."""
    rng = np.random.default_rng(0)
    n = 2000
    mean, std = rng.normal(0, 50, 5), rng.uniform(1e-4, 30, 5)
    feature = rng.integers(0, 5, n)
    t = rng.normal(0, 2, n).astype(np.float32)
    x_star = raw_thresholds(t, feature, mean, std)
    for step in range(-3, 4):
        x = x_star.copy()
        for _ in range(abs(step)):
            x = np.nextafter(x, np.float32(np.inf if step > 0 else -np.inf))
        z = ((x.astype(np.float64) - mean[feature]) / std[feature]).astype(np.float32)
        np.testing.assert_array_equal(z < t, x < x_star)


@pytest.mark.slow  # the data_root fixture trains the learned models
def test_dagster_asset_writes_the_c_files_under_the_data_root(data_root, tmp_path):
    import dagster as dg

    from pipeline.assets.export import exported_model
    from pipeline.resources import DataRoot, ModelConfig

    root, physics = data_root
    fitted = ModelConfig(effects="com_offset")  # the data root's model (the asset loads its spec's plugins)
    with dg.instance_for_test() as instance:
        result = dg.materialize([exported_model], instance=instance,
                                resources={"data_root": DataRoot(root=str(root)), "model": fitted},
                                run_config={"ops": {"exported_model": {"config": {"learned": "mlp"}}}})
        empty = dg.materialize([exported_model], instance=instance, raise_on_error=False,
                               resources={"data_root": DataRoot(root=str(tmp_path)), "model": fitted})
    (mat,) = result.asset_materializations_for_node("exported_model")
    meta = {k: v.value for k, v in mat.metadata.items()}
    assert meta["header"] == str(root / "export_c" / "quadcore_model.h") and Path(meta["source"]).is_file()
    assert meta["model"].startswith(f"{physics.label} + mlp(")
    assert 0 < meta["flash_bytes"] < 0.1 * 1024 * 1024 and "Footprint" in meta["footprint"]
    assert "stateEstimate.qx" in meta["inputs"]["q_xyzw"]
    assert not empty.success
    failure = next(e for e in empty.all_events if e.is_step_failure).event_specific_data.user_failure_data
    assert "no learned models" in failure.description and not (tmp_path / "export_c").exists()


def test_discovered_terms_export_when_they_have_an_on_board_form(decoded, tmp_path):
    terms = [("f_res_b_x_N", "T_N*v_b_x_mps", "fx_T_vbx", "s/m", 1.0),
             ("f_res_b_z_N", "(R/4h)^2*T_N", "fz_ground", "1", 100.0),
             ("f_res_b_y_N", "T_N*|v_h|^2", "fy_lift", "s2/m2", 1.0),
             ("tau_res_b_x_Nm", "Omega_net_radps*omega_b_y_radps", "tx_gyro", "kg m2", 1e-6),
             ("tau_res_b_y_Nm", "(f_rotor_1_N-f_rotor_3_N)", "ty_pair", "m", 0.1),
             ("tau_res_b_z_Nm", "v_b_x_mps*|omega_b_z_radps|", "tz_abs", "kg m", 1e-3),
             ("f_res_b_z_N", "1", "fz_const", "N", 1.0)]
    params = {"fx_T_vbx": -0.02, "fz_ground": 3.0, "fy_lift": 0.01, "tx_gyro": 2e-7, "ty_pair": 0.004,
              "tz_abs": 1e-4, "fz_const": 0.003}
    timing = [("tau_res_b_x_Nm", "d(tau_rotor_x_Nm)/dt", "tx_rate", "s", 1.0)]
    for name, rows in (("found_terms", terms), ("found_timing", timing)):  # modules as discover writes them
        (tmp_path / f"{name}.py").write_text("from quadcore.identify.discovery import DiscoveredEffect\n"
                                             f"EFFECT = DiscoveredEffect({name!r}, {rows!r})\n")
        effects.load_plugin(tmp_path / f"{name}.py")
    try:
        pm = PhysicsModel(VEHICLE, [EffectTerm("found_terms", params)])
        exported = export_c.export_models(pm, None, tmp_path / "out", "discovered")
        out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
        f_py, tau_py = pm.extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
        assert np.abs(tau_py[:, 0]).max() > 0 and np.abs(f_py[:, 1]).max() > 0
        _assert_close(out["f_b_N"], out["tau_b_Nm"], f_py, tau_py, "discovered terms")
        with pytest.raises(export_c.NoCFormError, match="'found_timing'"):
            export_c.export_models(PhysicsModel(VEHICLE, [EffectTerm("found_timing", {"tx_rate": 1e-3})]), None,
                                   tmp_path / "timing", "discovered")
    finally:
        effects.unregister("found_terms")
        effects.unregister("found_timing")


def test_the_documented_plugin_exports_and_comments_stay_comments(decoded, tmp_path):
    """examples/effects/linear_drag.py (docs/adding-an-effect.md) has a C form; text from users
    that would close a C comment stays inside it."""
    example = Path(__file__).resolve().parents[1] / "examples" / "effects" / "linear_drag.py"
    effects.load_plugin(example)
    try:
        pm = PhysicsModel(VEHICLE, [EffectTerm("linear_drag", {"d_xy_kg_per_s": 0.04, "d_z_kg_per_s": 0.06})])
        exported = export_c.export_models(pm, None, tmp_path / "out", "a path with */ in it")
        out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
        f_py, tau_py = pm.extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
        _assert_close(out["f_b_N"], out["tau_b_Nm"], f_py, tau_py, "linear_drag")
        assert "const qc_real d_xy_kg_per_s = ((qc_real)0.04);" in exported.source.read_text()
    finally:
        effects.unregister("linear_drag")


def test_a_per_session_model_exports_its_fleet_values_and_says_so(tmp_path):
    """C carries one set of constants: a model with per-session parameters is exported at its
    fleet values, with a warning and a note in the files."""
    term = EffectTerm("thrust_scale", {"scale": 1.0}, {}, False, {"late": {"scale": 1.1}}, {"late": {"scale": 0.01}})
    pm = PhysicsModel(VEHICLE, [term], {"late": ["jana20"]})
    with pytest.warns(UserWarning, match="thrust_scale.*fleet values"):
        exported = export_c.export_models(pm, None, tmp_path / "out", "a per-session fit")
    text = exported.source.read_text()
    assert "per-session parameters (thrust_scale) at their fleet values" in text
    assert "const qc_real scale = ((qc_real)1.0);" in text
    store.write_json(pm.to_dict(), tmp_path / "physics_model.json")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert cli.main(["export-c", str(tmp_path / "physics_model.json"), "--out", str(tmp_path / "cli")]) == 0
    assert err.getvalue().startswith("warning: export-c: per-session parameters (thrust_scale) at their fleet values")


def test_an_effect_without_c_form_is_left_out_by_name_when_asked(tmp_path, decoded):
    """What the pipeline's exported_model asks for: the export leaves the effect out, says which
    and why (in the files and the result), and the C gives the other effects' wrench."""
    _tether_plugin(tmp_path, "tether_left_out")
    try:
        drag = EffectTerm("rotor_drag", {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1})
        pm = PhysicsModel(VEHICLE, [drag, EffectTerm("tether_left_out", {"F_z_N": 0.1})])
        exported = export_c.export_models(pm, None, tmp_path / "out", "test", leave_out=True)
        (effect, why), = exported.generated.left_out
        assert effect == "tether_left_out" and "has no C form" in why
        assert "LEFT OUT: effect 'tether_left_out' has no C form" in exported.source.read_text()
        assert "LEFT OUT" in exported.header.read_text()
        out = _run_c(exported, decoded[HOLDOUT], tmp_path / "build")
        f_py, tau_py = PhysicsModel(VEHICLE, [drag]).extra_wrench(dynamics.flight_state(decoded[HOLDOUT], VEHICLE))
        _assert_close(out["f_b_N"], out["tau_b_Nm"], f_py, tau_py, "rotor drag without the tether")
    finally:
        effects.unregister("tether_left_out")


def test_write_effect_keeps_only_terms_with_a_c_form_and_says_which_it_left_out(tmp_path):
    """``discover --write-effect`` writes the terms with an on-board form; a zero-phase derivative
    is left out and named with why, in the module and the result."""
    from quadcore.identify import discovery
    from quadcore.identify.discovery import writer

    kept = [("tau_res_b_y_Nm", "v_b_x_mps"), ("f_res_b_x_N", "omega_dot_b_y_radps2")]
    terms = tuple(discovery.DiscoveredTerm(target=t, expression=e, variables=(e,), coefficient=1e-4, std=1e-5,
                                           unit="kg m/s", term_unit="m/s", explained_variance=0.5, stability=1.0,
                                           folds_selected=5, folds=5) for t, e in kept)
    result = discovery.Discovery(terms=terms, axes=(), baseline={}, after={}, noise_floor={},
                                 evaluation={"mode": "holdout", "eval_flights": ["jana02"]},
                                 effects_in_model=("thrust_scale",))
    written = discovery.write_effect(result, tmp_path / "found_terms.py", VEHICLE)
    assert list(written.left_out) == ["omega_dot_b_y_radps2"]
    assert "zero-phase smoothed time derivative" in written.left_out["omega_dot_b_y_radps2"]
    text = written.path.read_text()
    assert "left out here, as they have no C form" in text and "'omega_dot_b_y_radps2'" not in text
    effects.load_plugin(written.path)
    try:
        assert [p.name for p in effects.get("found_terms").parameters] == [
            writer.parameter_name("tau_res_b_y_Nm", "v_b_x_mps", "kg m/s")]
        assert effects.get("found_terms").c_code(VEHICLE, {p.name: 1e-4 for p in effects.get(
            "found_terms").parameters}) is not None
    finally:
        effects.unregister("found_terms")


@pytest.mark.slow  # decodes and fits the 19 real flights
def test_the_committed_real_flights_model_exports_whole_and_its_c_matches_python(real_logs, tmp_path):
    """examples/real-flights/model.toml (thrust scale per session, rotor drag, motor lag, and the
    terms `discover --write-effect` wrote) fitted on the real flights exports with every effect,
    discovered terms included, compiles with the strict flags, and gives on jana02 what the
    Python model gives (fleet values: C has one set of constants, and says so)."""
    from quadcore.workflows import fleet, identify, resolve_model

    spec = resolve_model(str(Path(__file__).resolve().parents[1] / "examples" / "real-flights" / "model.toml"))
    flights = fleet.fleet_from_logs([str(real_logs)], spec.vehicle)
    fitted = identify.fit(flights, spec, ["jana02"])
    path = identify.save_fit(tmp_path / "root", fitted)
    with pytest.warns(UserWarning, match="per-session parameters"):
        exported = export_c.export(path, tmp_path / "c", "none", leave_out=True)
    assert exported.generated.left_out == ()
    assert exported.generated.label == "nominal+thrust_scale+rotor_drag+motor_lag+discovered_terms"
    assert exported.footprint is not None  # compiled here (and checked with the strict flags)
    table = flights.tables["jana02"]
    out = _run_c(exported, table, tmp_path / "build")
    f_py, tau_py = fitted.model.extra_wrench(dynamics.flight_state(table, spec.vehicle))
    assert np.abs(tau_py).max() > 1e-5  # the discovered torque terms act on this flight
    # float32 inputs and derived quantities: agreement to float precision of the wrench's scale
    assert np.abs(out["f_b_N"] - f_py).max() < 1e-4 and np.abs(out["tau_b_Nm"] - tau_py).max() < 1e-6
