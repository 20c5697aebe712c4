"""The per-flight statistics asset, materialised for real: it writes each flight's statistics,
the fleet fit and term discovery combine them (no decoded table read), and a model file naming
another thrust map marks them stale."""

from __future__ import annotations

import dagster as dg
import pytest
from reference import rows as reference

from pipeline.assets.decode import decoded_flight
from pipeline.assets.discovery import term_discovery
from pipeline.assets.model import physics_model
from pipeline.assets.statistics import flight_statistics
from pipeline.freshness import STATS_VERSION, versions_used
from pipeline.resources import DataRoot, ModelConfig
from pipeline.run import main as job
from quadcore import effects
from quadcore.identify import flightdata
from quadcore.identify.discovery import library_stats
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.store import store

FLIGHTS = ["sim000", "sim001", "sim002", "sim003"]


def _run(assets, resources, instance, key=None):
    result = dg.materialize(assets, partition_key=key, instance=instance, resources=resources, raise_on_error=False)
    assert result.success, [e.message for e in result.all_events if e.is_failure]
    return result


def test_statistics_asset_feeds_the_fleet_fit(drag_fleet, tmp_path, monkeypatch):
    root = tmp_path / "root"
    resources = {"data_root": DataRoot(root=str(root), raw=str(drag_fleet)), "model": ModelConfig(effects="rotor_drag")}
    spec = resources["model"].spec()
    with dg.instance_for_test() as instance:
        # the flights in one run, as the main job runs them (a run per flight costs 0.7 s of CPU each)
        assert job.run_flights(instance, resources, FLIGHTS, [decoded_flight, flight_statistics], "decode",
                               log=lambda msg: None) == {}
        recorded = versions_used(instance, flight_statistics.key, set(FLIGHTS), STATS_VERSION)
        assert recorded == {f: library_stats.version(spec, f) for f in FLIGHTS}
        stored = [sufficient.load_current(root, f, sufficient.current_key(spec, f)) for f in FLIGHTS]
        assert all(stored) and all(s.summary() is not None for s in stored)  # the diagnosis's tables' sums too
        assert all(library_stats.stored(root, spec)(f) is not None for f in FLIGHTS)

        def no_rows(*args, **kwargs):
            raise AssertionError("a fleet asset read a flight's rows although its statistics were stored")

        with monkeypatch.context() as m:
            m.setattr(sufficient, "compute", no_rows)
            m.setattr(library_stats, "compute", no_rows)
            m.setattr(store, "read_parquet", no_rows)
            _run([physics_model, term_discovery], resources, instance)
        assert store.read_json(store.discovery_path(root))["effects_in_model"] == ["rotor_drag"]
        fitted = store.read_json(store.physics_model_path(root))
        train = fitted["trained_on"]
        veh = vehicle.load()
        fds = [flightdata.flight_data(f, flight.decode_flight(drag_fleet / f).tables["fixedFrequency"], veh)
               for f in train]
        # the model is fitted within its bounds (rotor_drag's k_z, ~0 here, is held at 0)
        rows = reference.fit_effects([effects.get("rotor_drag")], fds, flightdata.targets_of(fds), veh, bounded=True)
        got = fitted["effects"][0]["params"]
        for k, v in rows.params["rotor_drag"].items():
            assert got[k] == pytest.approx(v, rel=1e-9)


def test_another_thrust_map_makes_the_statistics_stale(drag_fleet, tmp_path, monkeypatch):
    root = tmp_path / "root"
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(root))
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(drag_fleet))
    monkeypatch.delenv("QUADCORE_MODEL", raising=False)
    resources = {"data_root": DataRoot(root=str(root), raw=str(drag_fleet)), "model": ModelConfig()}
    assets = [decoded_flight, flight_statistics]
    with dg.instance_for_test() as instance:
        assert job.run_flights(instance, resources, FLIGHTS[:2], assets, "decode", log=lambda msg: None) == {}
        defs = dg.Definitions(assets=assets, resources=resources)
        fresh = dg.evaluate_automation_conditions(defs=defs, instance=instance)
        assert fresh.get_num_requested(flight_statistics.key) == 0
        monkeypatch.setenv("QUADCORE_THRUST_MAP", "motor_speed")  # the model file now names another map
        stale = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=fresh.cursor)
        assert stale.get_requested_partitions(flight_statistics.key) == set(FLIGHTS[:2])
