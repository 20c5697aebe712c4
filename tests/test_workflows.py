"""The decisions the CLI and the assets share (quadcore.workflows): which flights are held out,
checked the same way everywhere, which model file a run used, when a fit or the learned models
are stale, and the outputs both write."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import dagster as dg
import polars as pl
import pytest

from pipeline.assets.model import failing_on_user_errors
from pipeline.resources import ModelConfig
from quadcore import cli, effects, workflows
from quadcore.identify import model
from quadcore.physics import vehicle
from quadcore.spec.model import ModelFileError, load_model_file, spec_from
from quadcore.store import store
from quadcore.workflows import Fleet, identify, learn

FLIGHTS = ["sim000", "sim001", "sim002"]


def _decoded(names=FLIGHTS) -> Fleet:
    return Fleet({f: pl.DataFrame({"t_s": [0.0]}) for f in names})


def _held_out(config: ModelConfig, fleet: Fleet):
    with failing_on_user_errors():
        return workflows.held_out(config.holdout_flights, fleet.ids)


def diagnosis_flights(config: ModelConfig, fleet: Fleet):
    """The flights model_diagnosis and term_discovery see, failing as they fail."""
    with failing_on_user_errors():
        return identify.diagnosis_flights(fleet, config.holdout_flights)


def test_named_holdout_is_checked_not_filtered():
    assert workflows.named_holdout(["sim001"], FLIGHTS) == ["sim001"]
    assert workflows.named_holdout([], FLIGHTS) == []
    with pytest.raises(workflows.HoldoutError, match="not found in the flights: jana99"):
        workflows.named_holdout(["sim001", "jana99"], FLIGHTS)
    with pytest.raises(workflows.HoldoutError, match="every flight is held out"):
        workflows.named_holdout(FLIGHTS, FLIGHTS)


@pytest.mark.parametrize("holdout", ["jana99", "sim001,quarantined"])
def test_an_unknown_or_quarantined_holdout_fails_the_model_assets_with_its_reason(holdout):
    """physics_model, term_discovery and model_diagnosis all check the holdout through these:
    one clear failure (no bare KeyError, no silent filtering)."""
    config = ModelConfig(holdout=holdout)
    with pytest.raises(workflows.HoldoutError):
        workflows.held_out(config.holdout_flights, FLIGHTS)
    for resolve in (_held_out, diagnosis_flights):
        with pytest.raises(dg.Failure, match="QUADCORE_HOLDOUT: holdout flight.* not found"):
            resolve(config, _decoded())


def test_without_a_holdout_nothing_is_held_out_and_the_diagnosis_cross_validates_over_every_flight():
    """The README's default: no QUADCORE_HOLDOUT / --holdout, nothing held out, the same for the
    assets and the CLI (one function): a fleet never silently loses a flight (before, jana02 or
    the last flight was left out of the fit and of the diagnosis's cross-validation)."""
    assert workflows.held_out([], FLIGHTS) == []
    for fleet_ in (_decoded(), _decoded(["jana00", "jana02", "jana03"])):
        seen, holdout = diagnosis_flights(ModelConfig(), fleet_)
        assert seen.ids == fleet_.ids and holdout is None


def test_the_learned_models_pick_their_own_test_flight_and_say_why():
    """A learned model needs a flight it never saw: the named holdout, else jana02, else the last
    flight; the note says so and that the physics uses every flight."""
    assert learn.learning_holdout("", ["jana00", "jana02", "jana03"])[0] == "jana02"
    flight, note = learn.learning_holdout("", FLIGHTS)
    assert flight == "sim002" and "never see" in note and "every flight" in note
    assert learn.learning_holdout("", FLIGHTS, ["sim000"]) == ("sim000", "")


def test_a_named_holdout_is_scored_on_with_every_flight_seen():
    seen, holdout = diagnosis_flights(ModelConfig(holdout="sim000"), _decoded())
    assert seen.ids == FLIGHTS and holdout == ["sim000"]


def test_effects_override_keeps_the_model_files_source(tmp_path):
    """``QUADCORE_EFFECTS`` / ``--effects`` replace a model file's effect list, not its source (the
    physics_model metadata names the file)."""
    path = tmp_path / "model.toml"
    path.write_text('vehicle = "crazyflie21"\neffects = ["rotor_drag"]\n'
                    '[parameters.rotor_drag]\nk_x_s_per_m = 0.1\n')
    spec = ModelConfig(model_file=str(path), effects="rotor_drag,motor_lag").spec()
    assert spec.source == str(path) and spec.effects == ["rotor_drag", "motor_lag"]
    assert spec.fixed == {"rotor_drag": {"k_x_s_per_m": 0.1}}
    assert load_model_file(path).with_effects(["motor_lag"]).fixed == {}


def test_the_cli_and_the_assets_resolve_the_same_model(tmp_path):
    path = tmp_path / "model.toml"
    path.write_text('vehicle = "crazyflie21"\neffects = ["rotor_drag"]\n')
    asset = ModelConfig(model_file=str(path), effects="motor_lag", thrust_map="pwm_vbat").spec()
    cli_like = workflows.resolve_model(str(path), None, "pwm_vbat", ["motor_lag"])
    assert (asset.effects, asset.source, asset.vehicle.thrust_map_kind) == (
        cli_like.effects, cli_like.source, cli_like.vehicle.thrust_map_kind) == (["motor_lag"], str(path), "pwm_vbat")
    nominal = workflows.resolve_model(None)
    assert nominal.effects == [] and nominal.source == "" and nominal.vehicle.name == "crazyflie21"


# ---------------------------------------------------------------------------------------
# Staleness follows the whole spec: the sessions file, and the learned models' spec digest
# ---------------------------------------------------------------------------------------

def _save_fit(root, spec, scale: float = 1.0) -> None:
    fitted = model.PhysicsModel(spec.vehicle, [model.EffectTerm("thrust_scale", {"scale": scale})])
    model.save(fitted, store.physics_model_path(root), ["sim000"], spec)


def test_editing_the_sessions_file_makes_the_fit_stale(tmp_path):
    """``QUADCORE_SESSIONS`` / ``--sessions`` group the flights a per-session fit uses: a fit
    made for other groups is stale (the automation and ``make run`` refit)."""
    groups = tmp_path / "sessions.toml"
    groups.write_text('[sessions]\nearly = ["sim000"]\n')
    config = ModelConfig(effects="thrust_scale", sessions_file=str(groups))
    _save_fit(tmp_path, config.spec())
    assert not identify.fit_is_stale(tmp_path, config.spec())
    groups.write_text('[sessions]\nearly = ["sim000", "sim001"]\n')
    assert identify.fit_is_stale(tmp_path, config.spec())
    assert identify.current_model(tmp_path, config.spec()).terms == []  # not used until refitted


def _residuals_and_learned_models(root, physics: model.PhysicsModel) -> None:
    """A data root whose residual tables were computed against ``physics`` and whose learned
    models (index and report) were trained on them, as the learning assets record it."""
    table = pl.DataFrame({"t_s": [0.0, 0.01]})
    store.write_parquet(table, store.table_path(root, "residuals", "sim000"), {"model": physics.to_dict()})
    store.write_json({"physics_model": learn.physics_of_residuals(root)}, store.learned_dir(root) / "index.json")
    store.write_json({}, store.learning_report_path(root))


def test_learned_models_are_stale_when_the_model_spec_changes_not_on_a_refit(tmp_path):
    """The same effects fitted for another spec (here a fixed parameter value) retrain the
    learned models at once; a refit of the same spec on new flights waits for the nightly run."""
    spec = spec_from(vehicle.load(), ["thrust_scale"])
    _save_fit(tmp_path, spec)
    _residuals_and_learned_models(tmp_path, identify.current_model(tmp_path, spec))
    assert learn.learning_is_stale(tmp_path) is None
    _save_fit(tmp_path, spec, scale=1.02)  # a refit: other values, same spec
    assert learn.learning_is_stale(tmp_path) is None
    fixed = spec_from(vehicle.load(), ["thrust_scale"], {"thrust_scale": {"scale": 0.95}})
    _save_fit(tmp_path, fixed, scale=0.95)  # the residual tables keep the same effects and labels
    assert "the model spec changed" in learn.learning_is_stale(tmp_path)


# ---------------------------------------------------------------------------------------
# One report path: the CLI's report has the discovery section the asset's has
# ---------------------------------------------------------------------------------------

def test_the_cli_diagnosis_report_shows_the_discovery_beside_it(drag_fleet, tmp_path, capsys):
    reports = tmp_path / "reports"
    options = [str(drag_fleet), "--holdout", "sim003", "--quiet"]
    assert cli.main(["diagnose", *options, "--json", str(tmp_path / "d.json"), "--report", str(reports)]) == 0
    assert "no discovery section" in capsys.readouterr().out
    assert "Terms the library lacks" not in (reports / "diagnosis.md").read_text()
    assert cli.main(["discover", *options, "--json", str(reports / "discovery.json")]) == 0
    assert cli.main(["diagnose", *options, "--json", str(tmp_path / "d.json"), "--report", str(reports)]) == 0
    text = (reports / "diagnosis.md").read_text()
    assert "## Terms the library lacks (quadcore discover)" in text and "v_b_x_mps*T_N" in text
    # a discovery on top of another model is about another residual: left out
    assert cli.main(["diagnose", *options, "--effects", "rotor_drag", "--json", str(tmp_path / "d.json"),
                     "--report", str(reports)]) == 0
    assert "Terms the library lacks" not in (reports / "diagnosis.md").read_text()


# ---------------------------------------------------------------------------------------
# export-c reads a fitted model with plugin effects in a process that never saw the model file
# ---------------------------------------------------------------------------------------

@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
def test_export_c_takes_plugins_from_the_model_file_given_never_from_the_saved_model(tmp_path):
    example = Path(__file__).resolve().parents[1] / "examples" / "effects" / "linear_drag.py"
    shutil.copy(example, tmp_path / "linear_drag.py")
    (tmp_path / "model.toml").write_text('effects = ["linear_drag"]\nplugins = ["linear_drag.py"]\n')
    spec = workflows.resolve_model(str(tmp_path / "model.toml"))
    fitted = model.PhysicsModel(spec.vehicle, [model.EffectTerm("linear_drag", {"d_xy_kg_per_s": 0.04,
                                                                                 "d_z_kg_per_s": 0.06})])
    try:
        path = model.save(fitted, store.physics_model_path(tmp_path / "root"), ["sim000"], spec)
    finally:
        effects.unregister("linear_drag")
    digest = hashlib.sha256(example.read_bytes()).hexdigest()
    assert store.read_json(path)["plugins"] == [{"effect": "linear_drag", "module": "linear_drag.py",
                                                 "sha256": digest}]

    def export_c(*extra):
        return subprocess.run([sys.executable, "-m", "quadcore.cli", "export-c", str(path), "--out",
                               str(tmp_path / "c"), *extra], capture_output=True, text=True)

    run = export_c()  # without the model file: refused with the reason, nothing imported
    assert run.returncode == 2 and "'linear_drag'" in run.stderr and "--model" in run.stderr, run.stderr
    run = export_c("--model-file", str(tmp_path / "model.toml"))
    assert run.returncode == 0, run.stderr
    assert "d_xy_kg_per_s = ((qc_real)0.04)" in (tmp_path / "c" / "quadcore_model.c").read_text()
    (tmp_path / "linear_drag.py").write_text(example.read_text() + "\n# edited since the fit\n")
    run = export_c("--model-file", str(tmp_path / "model.toml"))  # another version of the plugin: refit first
    assert run.returncode == 2 and "another version" in run.stderr, run.stderr


SENTINEL_PLUGIN = """from pathlib import Path
Path({sentinel!r}).write_text("ran")
"""


def test_a_saved_model_naming_code_elsewhere_never_runs_it(tmp_path):
    """An edited physics_model.json (and a learned model's manifest) naming a module outside the
    project: export-c, the pipeline's current model and LearnedModel.physics_model() refuse it
    with the reason, and the module never runs (it would write a sentinel file)."""
    from quadcore.learn import artefacts

    sentinel = tmp_path / "sentinel"
    evil = tmp_path / "elsewhere" / "evil.py"
    evil.parent.mkdir()
    evil.write_text(SENTINEL_PLUGIN.format(sentinel=str(sentinel)))
    root = tmp_path / "root"
    spec = workflows.resolve_model(None)
    path = model.save(model.PhysicsModel(spec.vehicle, []), store.physics_model_path(root), ["a", "b"], spec)
    saved = store.read_json(path)
    for plugins in ([str(evil)], [{"effect": "evil", "module": str(evil), "sha256": "0" * 64}]):
        store.write_json({**saved, "plugins": plugins, "effects": [{"name": "evil", "params": {}}]}, path)
        run = subprocess.run([sys.executable, "-m", "quadcore.cli", "export-c", str(path), "--out",
                              str(tmp_path / "c"), "--learned", "none"], capture_output=True, text=True)
        assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
        assert "evil" in run.stderr and not sentinel.exists()
        with pytest.raises(ModelFileError):
            identify.current_model(root, spec)  # the saved spec digest is this spec's: it is read
        with pytest.raises(ModelFileError):
            artefacts.LearnedModel.physics_model(_Manifest({"physics_model": store.read_json(path)}))
        assert not sentinel.exists()


class _Manifest:
    def __init__(self, manifest):
        self.manifest = manifest


# ---------------------------------------------------------------------------------------
# The layering itself: the CLI and the Dagster wiring leave the decisions to the workflows
# ---------------------------------------------------------------------------------------

# Calls that fit, pick or check a holdout, or write a report or the history: each belongs in
# quadcore.workflows, which both the CLI and the assets call (the learning's experiments.plan, not
# quadcore.workflows.plan, the flight planner's workflow, which they call).
ORCHESTRATION = ("fit_model", "fit_effects", "diagnosis.diagnose(", "discovery.discover(", "resolve_holdout",
                 "named_holdout", "report.write(", "history.record(", "full_report(", "run_plan(", "experiments.plan(",
                 "split_usable", "usable_flights", "read_sessions_file", "fitted_for", "write_report(")


def test_the_cli_and_the_assets_leave_fitting_holdout_and_reports_to_the_workflows():
    repo = Path(__file__).resolve().parents[1]
    sources = [*sorted((repo / "quadcore" / "cli").rglob("*.py")), *sorted((repo / "pipeline").rglob("*.py"))]
    found = [f"{path.relative_to(repo)}:{i}: {line.strip()}" for path in sources
             for i, line in enumerate(path.read_text().splitlines(), 1)
             if any(name in line for name in ORCHESTRATION) and not line.lstrip().startswith("#")]
    assert not found, "orchestration outside quadcore.workflows:\n" + "\n".join(found)


def test_residuals_against_an_older_fit_do_not_take_the_new_fits_flights(tmp_path):
    """The learned models record (and check their holdout against) the flights the physics under
    them was fitted on: residual tables computed against an earlier fit of the same effects must
    not be credited with the new fit's flights and spec digest."""
    spec = spec_from(vehicle.load(), ["thrust_scale"])
    older = model.PhysicsModel(spec.vehicle, [model.EffectTerm("thrust_scale", {"scale": 0.95})])
    table = pl.DataFrame({"t_s": [0.0, 0.01]})
    store.write_parquet(table, store.table_path(tmp_path, "residuals", "sim000"), {"model": older.to_dict()})
    _save_fit(tmp_path, spec, scale=0.9)  # refitted since, on sim000
    physics = learn.physics_of_residuals(tmp_path)
    assert physics["effects"][0]["params"] == {"scale": 0.95}
    assert "trained_on" not in physics and "spec_digest" not in physics
    _save_fit(tmp_path, spec, scale=0.95)  # the fit the tables were computed against
    assert learn.physics_of_residuals(tmp_path)["trained_on"] == ["sim000"]
