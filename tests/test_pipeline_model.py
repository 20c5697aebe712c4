"""The per-flight physics assets and the fleet-wide model assets, materialised for real
on simulated flights with a hidden effect."""

from __future__ import annotations

import json

import dagster as dg
import polars as pl
import pytest

from pipeline.assets.decode import decoded_flight
from pipeline.assets.discovery import term_discovery
from pipeline.assets.model import error_history, model_diagnosis, physics_model
from pipeline.assets.physics import residual_table, rollout_errors
from pipeline.resources import DataRoot, ModelConfig
from quadcore.identify import history
from quadcore.report.diagnosis import kept_reports
from quadcore.store import store

pytestmark = pytest.mark.slow  # the whole loop materialised in Dagster

PER_FLIGHT = [decoded_flight, residual_table, rollout_errors]
FLEET = [physics_model, term_discovery, model_diagnosis, error_history]


@pytest.fixture(scope="module")
def raw(drag_fleet):
    return drag_fleet


def materialize(assets, resources, instance, key=None):
    result = dg.materialize(assets, partition_key=key, instance=instance, resources=resources, raise_on_error=False)
    assert result.success, [e.message for e in result.all_events if e.is_failure]
    return result


def metadata(result, asset):
    return {k: v.value for k, v in result.asset_materializations_for_node(asset)[0].metadata.items()}


def test_the_loop_in_dagster(raw, tmp_path):
    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(raw))
    nominal = {"data_root": data_root, "model": ModelConfig()}
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000", "sim001", "sim002", "sim003"])
        for key in ("sim000", "sim001", "sim002", "sim003"):
            res = materialize(PER_FLIGHT, nominal, instance, key)
        meta = metadata(res, "residual_table")
        assert meta["model"] == "nominal"
        link = meta["model_vs_measured"]  # a link the UI serves from this data root, on any port
        assert link.startswith("![model vs measured](/quadcore-plots/") and len(link) < 1000
        assert (root / "plots" / link[link.rindex("/") + 1:-1]).is_file()
        assert meta["force_rmse_x_N"] > 0.0015  # the hidden drag is there (noise alone: ~0.0005 N)
        table = pl.read_parquet(store.table_path(root, "residuals", "sim002"))
        assert {"f_res_b_x_N", "f_res_w_x_N", "tau_res_b_z_Nm", "f_model_b_z_N", "f_meas_b_z_N"} <= set(table.columns)
        assert store.read_metadata(store.table_path(root, "residuals", "sim002"))["units"]["f_res_b_x_N"] == "N"
        roll = metadata(res, "rollout_errors")
        assert roll["pos_err_m@0.1s"] < roll["pos_err_m@1s"]

        # the nominal model, diagnosed: rotor drag is what is missing
        res = materialize(FLEET, nominal, instance)
        diag = metadata(res, "model_diagnosis")
        assert "rotor_drag" in diag["verdict"]
        # the UI says why each candidate ranks where it does, and how small an effect would be missed
        assert "| rank | effect | status |" in diag["candidates"] and "| found |" in diag["candidates"]
        assert "| com_offset | x_c_m |" in diag["sensitivity"]
        assert set(diag["sensitivity_json"]["com_offset"]) == {"x_c_m", "y_c_m"}
        before = diag["force_rmse_x_N"]
        report = json.loads((root / "reports" / "diagnosis.json").read_text())
        assert report["candidates"][0]["effect"] == "rotor_drag"
        assert (root / "reports" / "diagnosis.html").stat().st_size > 10_000
        # beside the library's candidates: the terms discovery finds, and where it fails in frequency
        found = metadata(res, "term_discovery")
        assert "v_b_x_mps" in found["terms"] and found["discovery_plot"].startswith("![")
        disc = json.loads((root / "reports" / "discovery.json").read_text())
        # discovery sees what the diagnosis sees: every flight, nothing held out (no QUADCORE_HOLDOUT)
        assert disc["evaluation"]["train_flights"] == report["evaluation"]["train_flights"] == [
            "sim000", "sim001", "sim002", "sim003"]
        assert report["evaluation"]["protocol"].startswith("4-fold cross-validation over 4 flights")
        assert report["stability"]["total"] == 4 and report["stability"]["sentence"] in diag["verdict"]
        assert found["flights"] == 4
        assert any(t["target"] == "f_res_b_x_N" and "v_b_x_mps" in t["variables"] for t in disc["terms"])
        md = (root / "reports" / "diagnosis.md").read_text()
        assert "Terms the library lacks" in md and "Where it fails, in frequency" in md
        assert diag["frequency_plot"].startswith("![frequency](/quadcore-plots/") and "force_x" in diag["frequency"]

        # the user adds it: the model is refitted, the error falls, the history shows both
        with_drag = {"data_root": data_root, "model": ModelConfig(effects="rotor_drag")}
        res = materialize(FLEET, with_drag, instance)
        fitted = json.loads((root / "models" / "physics_model.json").read_text())
        k = fitted["effects"][0]["params"]["k_x_s_per_m"]
        assert k == pytest.approx(0.15, rel=0.15)
        after = metadata(res, "model_diagnosis")["force_rmse_x_N"]
        assert after < 0.5 * before
        hist = history.read(root)
        assert hist["model_label"].to_list() == ["nominal", "nominal+rotor_drag"]
        assert metadata(res, "error_history")["evaluations"] == 2
        # both diagnoses kept (by time and model), the latest beside them, PNGs as files beside the .md
        kept = kept_reports(root / "reports")
        assert [p.name.split("-", 1)[1] for p in kept] == ["nominal", "nominal-rotor-drag"]
        assert json.loads((kept[1] / "diagnosis.json").read_text())["model"]["label"] == "nominal+rotor_drag"
        latest = (root / "reports" / "diagnosis.md").read_text()
        assert "base64" not in latest and latest == (kept[1] / "diagnosis.md").read_text().replace(
            "](", f"](diagnosis/{kept[1].name}/")
        for folder in kept:
            pngs = sorted(folder.glob("*.png"))
            assert pngs and all(p.read_bytes()[:4] == b"\x89PNG" for p in pngs)
            assert all(f"]({p.name})" in (folder / "diagnosis.md").read_text() for p in pngs)

        # residual tables now use the fitted model
        res = materialize(PER_FLIGHT[1:], with_drag, instance, "sim000")
        assert metadata(res, "residual_table")["model"] == "nominal+rotor_drag"
        assert metadata(res, "residual_table")["force_rmse_x_N"] < 0.5 * before


def test_a_user_vehicle_file_reaches_the_assets(raw, tmp_path):
    from importlib import resources

    text = (resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text()
    vfile = tmp_path / "heavy.toml"
    vfile.write_text(text.replace('name = "crazyflie21"', 'name = "heavy"')
                     .replace("mass_kg = 0.0347", "mass_kg = 0.05"))
    root = tmp_path / "root"
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000"])
        res = materialize(PER_FLIGHT, {"data_root": DataRoot(root=str(root), raw=str(raw)),
                                       "model": ModelConfig(vehicle=str(vfile))}, instance, "sim000")
        meta = metadata(res, "residual_table")
    assert meta["vehicle"] == "heavy"
    assert meta["force_mean_z_N"] > 0.1  # 50 g measured against a 34.7 g thrust model


def test_a_discovered_effect_joins_the_model_and_the_history(raw, tmp_path):
    """The loop with a term the user did not know: discovery on the nominal model writes an
    effect module; named in a model file (plugins + effects, unedited) the fleet assets fit it,
    the held-out error falls and the history records both evaluations."""
    from quadcore import effects
    from quadcore.identify import discovery
    from quadcore.physics import vehicle
    from quadcore.spec.model import spec_from

    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(raw))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000", "sim001", "sim002"])
        for key in ("sim000", "sim001", "sim002"):
            materialize([decoded_flight], {"data_root": data_root, "model": ModelConfig()}, instance, key)
        res = materialize(FLEET, {"data_root": data_root, "model": ModelConfig()}, instance)
        before = metadata(res, "model_diagnosis")["force_rmse_x_N"]
        decoded = store.read_all_decoded(root, "fixedFrequency")
        found = discovery.discover(decoded, spec_from(vehicle.load(), []))
        module = discovery.write_effect(found, tmp_path / "fx" / "found_drag.py").path
        model_file = tmp_path / "fx" / "model.toml"
        model_file.write_text('effects = ["found_drag"]\nplugins = ["found_drag.py"]\n')
        try:
            res = materialize(FLEET, {"data_root": data_root, "model": ModelConfig(model_file=str(model_file))},
                              instance)
        finally:
            effects.unregister("found_drag")
        assert module.is_file()
        after = metadata(res, "model_diagnosis")["force_rmse_x_N"]
        assert after < 0.5 * before
        assert history.read(root)["model_label"].to_list() == ["nominal", "nominal+found_drag"]


def test_rollouts_use_each_flights_session_values(raw, tmp_path):
    """A model with a per-session thrust scale: a flight's open-loop rollout flies its
    session's value, as its residual table does, not the fleet value."""
    from quadcore.identify import model
    from quadcore.identify.model import EffectTerm, PhysicsModel
    from quadcore.physics import vehicle

    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(raw))
    config = {"data_root": data_root, "model": ModelConfig(effects="thrust_scale")}
    per_session = PhysicsModel(vehicle.load(), [EffectTerm("thrust_scale", {"scale": 1.0}, {}, False,
                                                           {"mine": {"scale": 1.3}}, {"mine": {"scale": 0.01}})],
                               {"mine": ["sim000"]})
    same_fleet_wide = PhysicsModel(vehicle.load(), [EffectTerm("thrust_scale", {"scale": 1.3})])
    errors = []
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000"])
        materialize([decoded_flight], config, instance, "sim000")
        for fitted in (per_session, same_fleet_wide):
            model.save(fitted, store.physics_model_path(root), ["sim000"], config["model"].spec())
            roll = metadata(materialize([rollout_errors], config, instance, "sim000"), "rollout_errors")
            used = store.read_metadata(store.table_path(root, "rollouts", "sim000"))["model"]
            assert used == "nominal+thrust_scale"  # the saved fit is current, not set aside as stale
            errors.append(roll["pos_err_m@1s"])
    assert errors[0] == pytest.approx(errors[1], rel=1e-9)
