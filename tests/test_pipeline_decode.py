"""The Dagster wiring of stage 1: the decoded_flight asset, its checks, the raw-folder sensor."""

from __future__ import annotations

import json
import shutil

import dagster as dg
import polars as pl
import pytest

from pipeline.assets.decode import decoded_flight
from pipeline.partitions import flights
from pipeline.resources import DataRoot
from pipeline.sensors import raw_log_sensor
from quadcore.physics import gate
from quadcore.store import store


@pytest.fixture
def instance():
    with dg.instance_for_test() as inst:
        yield inst


def _materialize(instance, data_root: DataRoot, fid: str, raise_on_error: bool = True):
    if not instance.has_dynamic_partition(flights.name, fid):
        instance.add_dynamic_partitions(flights.name, [fid])
    return dg.materialize(
        [decoded_flight],
        partition_key=fid,
        instance=instance,
        resources={"data_root": data_root},
        raise_on_error=raise_on_error,
    )


def _metadata(result) -> dict:
    (mat,) = result.asset_materializations_for_node("decoded_flight")
    return {k: v.value for k, v in mat.metadata.items()}


def _checks(result) -> dict:
    return {ev.check_name: ev for ev in result.get_asset_check_evaluations()}


def _failure_descriptions(result) -> list[str]:
    return [
        e.step_failure_data.user_failure_data.description
        for e in result.get_step_failure_events()
        if e.step_failure_data.user_failure_data is not None
    ]


@pytest.mark.slow  # Dagster runs on the real fleet
def test_decoded_flight_on_real_logs(instance, real_logs, tmp_path):
    data_root = DataRoot(root=str(tmp_path), raw=str(real_logs))

    r02 = _materialize(instance, data_root, "jana02")
    assert r02.success
    meta = _metadata(r02)
    assert meta["rows_fixedFrequency"] == 3900 and meta["rows_estPose"] == 426
    assert meta["format_version"] == 2 and meta["crc_ok"] == "True" and meta["warning_count"] == 0
    assert meta["bytes_dropped"] == 0 and len(meta["source_sha256"]) == 64
    assert meta["parquet"] == str(store.decoded_path(tmp_path, "fixedFrequency", "jana02"))
    assert 495 < meta["rate_hz_median"] < 515  # the deck logs at 500 Hz
    ev02 = _checks(r02)
    assert set(ev02) == set(gate.ALL_CHECKS)
    assert all(ev.passed for ev in ev02.values()), {n: ev.description for n, ev in ev02.items()}
    assert pl.read_parquet(store.decoded_path(tmp_path, "fixedFrequency", "jana02")).height == 3900

    r20 = _materialize(instance, data_root, "jana20")
    assert r20.success  # checks warn, they do not fail the run
    assert _metadata(r20)["rows_fixedFrequency"] == 7861
    ev20 = _checks(r20)
    stuck = ev20["stuck_sensors"]
    assert stuck.passed is False
    assert stuck.severity == dg.AssetCheckSeverity.WARN
    assert "vbat_V" in stuck.description
    assert ev20["monotonic_time"].passed and ev20["value_ranges"].passed and ev20["no_nans"].passed

    assert ev20["sample_gaps"].passed is False  # one ~71 ms gap in jana20 (the README: gaps up to ~80 ms)

    # both partitions are recorded in the instance
    records = instance.fetch_materializations(dg.AssetKey("decoded_flight"), limit=10).records
    assert {rec.partition_key for rec in records} == {"jana02", "jana20"}
    assert not (tmp_path / "quarantine").exists()


@pytest.mark.slow  # Dagster runs on the real fleet
def test_corrupt_raw_file_is_quarantined_and_fails_the_run(instance, real_logs, tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    shutil.copyfile(real_logs / "jana02", raw / "jana02")  # a copy: a link out of the raw folder is not followed
    (raw / "broken01").write_bytes(b"\x42" + (real_logs / "jana03").read_bytes()[1:])
    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(raw))

    assert _materialize(instance, data_root, "jana02").success
    good = store.decoded_path(root, "fixedFrequency", "jana02")
    before = (good.read_bytes(), good.stat().st_mtime_ns)

    result = _materialize(instance, data_root, "broken01", raise_on_error=False)
    assert not result.success
    (description,) = _failure_descriptions(result)
    assert "quarantined" in description and "BadMagicError" in description
    record = json.loads(store.quarantine_path(root, "broken01").read_text())
    assert record["error_type"] == "BadMagicError" and record["source_file"] == str(raw / "broken01")
    assert not store.decoded_path(root, "fixedFrequency", "broken01").exists()
    assert (good.read_bytes(), good.stat().st_mtime_ns) == before  # another flight's output untouched

    # the same flight's own earlier output is kept too when its raw file goes bad ...
    (raw / "jana02").unlink()
    (raw / "jana02").write_bytes(b"")
    result = _materialize(instance, data_root, "jana02", raise_on_error=False)
    assert not result.success
    assert any("quarantined" in d and "EmptyLogError" in d for d in _failure_descriptions(result))
    assert (good.read_bytes(), good.stat().st_mtime_ns) == before
    assert store.quarantine_path(root, "jana02").is_file()

    # ... and a good file again lifts the quarantine
    (raw / "jana02").unlink()
    shutil.copyfile(real_logs / "jana02", raw / "jana02")
    assert _materialize(instance, data_root, "jana02").success
    assert not store.quarantine_path(root, "jana02").exists()


def test_missing_raw_file_is_quarantined(instance, tmp_path):
    (tmp_path / "raw").mkdir()
    result = _materialize(instance, DataRoot(root=str(tmp_path)), "ghost", raise_on_error=False)
    assert not result.success
    assert any("quarantined" in d and "FileNotFoundError" in d for d in _failure_descriptions(result))
    assert json.loads(store.quarantine_path(tmp_path, "ghost").read_text())["error_type"] == "FileNotFoundError"


@pytest.mark.slow  # test_operations' bad-files test decodes a truncated (simulated) log in Dagster in the fast tier
def test_truncated_raw_file_decodes_with_a_warning(instance, real_logs, tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    buf = (real_logs / "jana02").read_bytes()
    (raw / "cut02").write_bytes(buf[: len(buf) - 4 - 47])
    result = _materialize(instance, DataRoot(root=str(tmp_path), raw=str(raw)), "cut02", raise_on_error=False)
    assert result.success
    assert _metadata(result)["warning_count"] >= 1


def _hover_log(path, seed: int) -> None:
    """A short simulated flight with every variable the physics needs, at ``path``."""
    from quadcore.sim import simulation

    folder = path.parent / f".sim{seed}"
    simulation.simulate_set(folder, [simulation.SimConfig(kind="hover", duration_s=1.0, seed=seed)], {})
    path.write_bytes((folder / "sim000").read_bytes())


def test_raw_log_sensor(instance, tmp_path, make_synthetic_log):
    raw = tmp_path / "raw"
    raw.mkdir()
    _hover_log(raw / "flight_v1", 1)
    _hover_log(raw / "flight_v2", 2)
    make_synthetic_log(version=2, name="raw/generic", seed=1)  # a readable log without fixedFrequency
    (raw / "foreign.bin").write_bytes(b"hello")
    (raw / "notes.txt").write_text("a sidecar: neither a run nor a quarantine")
    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(raw))

    result = raw_log_sensor(dg.build_sensor_context(instance=instance, resources={"data_root": data_root}))
    assert isinstance(result, dg.SensorResult)
    assert sorted(r.partition_key for r in result.run_requests) == ["flight_v1", "flight_v2"]
    assert len({r.run_key for r in result.run_requests}) == 2
    (add,) = result.dynamic_partitions_requests
    assert add.partitions_def_name == "flights" and sorted(add.partition_keys) == ["flight_v1", "flight_v2"]
    quarantined = json.loads(store.quarantine_path(root, "foreign.bin").read_text())
    assert "BadMagicError" in quarantined["reason"]
    generic = json.loads(store.quarantine_path(root, "generic").read_text())  # refused at the door, one message
    assert generic["reason"].startswith("MissingVariablesError: not usable for the physics: it has no "
                                        "'fixedFrequency' event (it has fast, slow)"), generic["reason"]
    assert not store.quarantine_path(root, "notes.txt").exists()
    assert set(json.loads(result.cursor)) == {"flight_v1", "flight_v2", "foreign.bin", "generic"}

    # nothing changed since the cursor: skip
    again = raw_log_sensor(
        dg.build_sensor_context(instance=instance, resources={"data_root": data_root}, cursor=result.cursor)
    )
    assert isinstance(again, dg.SkipReason)

    # a changed log is requested again; its partition is known by now, so no new partition
    instance.add_dynamic_partitions("flights", list(add.partition_keys))
    _hover_log(raw / "flight_v2", 3)
    third = raw_log_sensor(
        dg.build_sensor_context(instance=instance, resources={"data_root": data_root}, cursor=result.cursor)
    )
    assert [r.partition_key for r in third.run_requests] == ["flight_v2"]
    assert third.dynamic_partitions_requests == []


def test_log_without_fixed_frequency_is_quarantined_with_one_message(instance, tmp_path, make_synthetic_log):
    """A readable log the physics cannot use (events "fast" and "slow" only) is quarantined when the
    pipeline decodes it, with every missing variable in one message; `quadcore decode` still decodes it."""
    (tmp_path / "raw").mkdir()
    make_synthetic_log(version=1, name="raw/flight_v1")  # events "fast" and "slow" only
    run = _materialize(instance, DataRoot(root=str(tmp_path / "root"), raw=str(tmp_path / "raw")), "flight_v1",
                       raise_on_error=False)
    assert not run.success
    (record,) = store.quarantined(tmp_path / "root")
    assert record["error_type"] == "MissingVariablesError" and "must hold the 21 variables" in record["reason"]
    assert not store.decoded_path(tmp_path / "root", "fast", "flight_v1").exists()


def test_definitions_load():
    from pipeline.definitions import defs

    graph = defs.resolve_asset_graph()
    assert dg.AssetKey("decoded_flight") in graph.get_all_asset_keys()
    assert defs.resolve_sensor_def("raw_log_sensor") is not None
    check_keys = {k.name for k in graph.asset_check_keys}
    assert check_keys == set(gate.ALL_CHECKS)
