"""Whether a saved fit is still the fit of the model file: every part of the file that changes a
fit (not only the effect list) makes it stale, for the pipeline's refit trigger and for the model
the per-flight assets use alike."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from pipeline.assets.model import current_model
from pipeline.resources import DataRoot, ModelConfig
from quadcore.identify import model
from quadcore.store import store
from quadcore.workflows import identify

BASE = 'vehicle = "heavy.toml"\neffects = ["rotor_drag", "thrust_scale"]\nplugins = ["plugin.py"]\n'
PLUGIN = Path(__file__).parent / "plugins" / "hidden_terms.py"


def _write_model(folder, extra: str = "") -> ModelConfig:
    (folder / "model.toml").write_text(BASE + extra)
    return ModelConfig(model_file=str(folder / "model.toml"))


def _save_fit(root, spec) -> None:
    """A fit as physics_model saves it: here a per-session fit whose session had no training
    flight, so no per-session values were saved (the outcome must not decide freshness)."""
    terms = [model.EffectTerm("rotor_drag", {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}),
             model.EffectTerm("thrust_scale", {"scale": 1.0})]
    model.save(model.PhysicsModel(spec.vehicle, terms), store.physics_model_path(root), ["sim000"], spec)


@pytest.fixture
def folder(tmp_path):
    text = (resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text()
    (tmp_path / "heavy.toml").write_text(text.replace('name = "crazyflie21"', 'name = "heavy"'))
    (tmp_path / "plugin.py").write_text(PLUGIN.read_text())
    return tmp_path


EDITS = {
    "per_session added": '[per_session]\nthrust_scale = ["scale"]\n',
    "sessions added": '[sessions]\nearly = ["sim0*"]\n',
    "session thrust map added": '[sessions]\nearly = ["sim0*"]\n[session_thrust_map]\nearly = "motor_speed"\n',
    "fixed value changed": "[parameters.rotor_drag]\nk_x_s_per_m = 0.2\nk_y_s_per_m = 0.1\n",
}


@pytest.mark.parametrize("edit", EDITS)
def test_an_edit_of_the_model_file_makes_the_fit_stale(folder, edit):
    base = "[parameters.rotor_drag]\nk_x_s_per_m = 0.1\nk_y_s_per_m = 0.1\n" if "fixed" in edit else ""
    config = _write_model(folder, base)
    root = DataRoot(root=str(folder / "root"))
    _save_fit(root.root_path, config.spec())
    assert not identify.fit_is_stale(root.root_path, config.spec())
    assert current_model(root, config).effect_names == ["rotor_drag", "thrust_scale"]  # the fit is used
    _write_model(folder, EDITS[edit])
    assert identify.fit_is_stale(root.root_path, config.spec())
    assert current_model(root, config).terms == []  # stale: the nominal model until it is refitted


@pytest.mark.parametrize("what", ["vehicle file", "plugin source"])
def test_an_edit_of_a_file_the_model_names_makes_the_fit_stale(folder, what):
    config = _write_model(folder)
    spec = config.spec()
    _save_fit(folder, spec)
    fitted = store.read_json(store.physics_model_path(folder))
    assert model.fitted_for(fitted, config.spec())
    path = folder / ("heavy.toml" if what == "vehicle file" else "plugin.py")
    text = path.read_text()
    path.write_text(text.replace("mass_kg = 0.0347", "mass_kg = 0.05") if what == "vehicle file"
                    else text + "\n# a changed comment is changed source\n")
    assert not model.fitted_for(fitted, config.spec())


def test_a_fit_saved_without_a_digest_is_stale(folder):
    config = _write_model(folder)
    _save_fit(folder, config.spec())
    fitted = store.read_json(store.physics_model_path(folder))
    assert model.fitted_for(fitted, config.spec())
    del fitted[model.SPEC_DIGEST]
    assert not model.fitted_for(fitted, config.spec())


def test_the_model_version_follows_the_vehicles_content():
    """A vehicle file edited in place (another mass) is another model: the per-flight tables
    computed with the old mass must be stale (``model_version``), although the vehicle's name,
    file and the fitted parameters are unchanged (the diagnose JSON keeps its pinned keys:
    tests/test_json_contracts.py)."""
    import dataclasses

    from pipeline.freshness import model_version
    from quadcore.identify import model as modelmod
    from quadcore.physics import vehicle as vehiclemod

    v = vehiclemod.load()
    heavier = dataclasses.replace(v, mass_kg=v.mass_kg * 1.2)
    assert model_version(modelmod.PhysicsModel(v, []).to_dict()) != model_version(
        modelmod.PhysicsModel(heavier, []).to_dict())
    assert model_version(modelmod.PhysicsModel(v, []).to_dict()) == model_version(
        modelmod.PhysicsModel(vehiclemod.load(), []).to_dict())
