"""The decisions the CLI and the assets share (quadcore.workflows): which flights are held out,
checked the same way everywhere, and which model file a run used."""

from __future__ import annotations

import dagster as dg
import polars as pl
import pytest

from pipeline.assets.model import held_out_or_fail, scored_flights
from pipeline.resources import ModelConfig
from quadcore import model, workflows

FLIGHTS = ["sim000", "sim001", "sim002"]


def _decoded(names=FLIGHTS) -> dict[str, pl.DataFrame]:
    return {f: pl.DataFrame({"t_s": [0.0]}) for f in names}


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
        config.held_out(FLIGHTS)
    for resolve in (held_out_or_fail, scored_flights):
        with pytest.raises(dg.Failure, match="QUADCORE_HOLDOUT: holdout flight.* not found"):
            resolve(config, _decoded())


def test_without_a_holdout_the_diagnosis_never_sees_the_learned_models_test_flight():
    config = ModelConfig()
    held, _ = config.held_out(FLIGHTS)
    seen, holdout = scored_flights(config, _decoded())
    assert held == ["sim002"] and holdout is None  # cross-validation ...
    assert sorted(seen) == ["sim000", "sim001"]  # ... over the flights the model is fitted on
    with_jana = _decoded(["jana00", "jana02", "jana03"])
    seen, _ = scored_flights(config, with_jana)
    assert sorted(seen) == ["jana00", "jana03"]  # the project's default test flight


def test_a_named_holdout_is_scored_on_with_every_flight_seen():
    seen, holdout = scored_flights(ModelConfig(holdout="sim000"), _decoded())
    assert sorted(seen) == FLIGHTS and holdout == ["sim000"]


def test_effects_override_keeps_the_model_files_source(tmp_path):
    """``QUADCORE_EFFECTS`` / ``--effects`` replace a model file's effect list, not its source (the
    physics_model metadata names the file)."""
    path = tmp_path / "model.toml"
    path.write_text('vehicle = "crazyflie21"\neffects = ["rotor_drag"]\n'
                    '[parameters.rotor_drag]\nk_x_s_per_m = 0.1\n')
    spec = ModelConfig(model_file=str(path), effects="rotor_drag,motor_lag").spec()
    assert spec.source == str(path) and spec.effects == ["rotor_drag", "motor_lag"]
    assert spec.fixed == {"rotor_drag": {"k_x_s_per_m": 0.1}}
    assert model.load_model_file(path).with_effects(["motor_lag"]).fixed == {}


def test_the_cli_and_the_assets_resolve_the_same_model(tmp_path):
    path = tmp_path / "model.toml"
    path.write_text('vehicle = "crazyflie21"\neffects = ["rotor_drag"]\n')
    asset = ModelConfig(model_file=str(path), effects="motor_lag", thrust_map="pwm_vbat").spec()
    cli_like = workflows.resolve_model(str(path), None, "pwm_vbat", ["motor_lag"])
    assert (asset.effects, asset.source, asset.vehicle.thrust_map_kind) == (
        cli_like.effects, cli_like.source, cli_like.vehicle.thrust_map_kind) == (["motor_lag"], str(path), "pwm_vbat")
    nominal = workflows.resolve_model(None)
    assert nominal.effects == [] and nominal.source == "" and nominal.vehicle.name == "crazyflie21"
