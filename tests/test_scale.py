"""Per-flight stages in few runs: a range of flight partitions in one run (single-run backfill),
one bad flight isolated, and the multiprocess executor. Real Dagster instances, real files."""

from __future__ import annotations

import os
import shutil

import dagster as dg
import pytest

from pipeline.assets import DECODE, PER_FLIGHT
from pipeline.assets.decode import decoded_flight
from pipeline.definitions import process_flight_job
from pipeline.partitions import flights
from pipeline.resources import DataRoot, ModelConfig
from pipeline.run import main, parallel
from quadcore.identify.stats import sufficient
from quadcore.logs import flight as flightmod
from quadcore.sim import simulation
from quadcore.store import store
from quadcore.workflows import learn

pytestmark = pytest.mark.slow  # whole per-flight runs, one with the multiprocess executor

QUIET = parallel.QUIET


@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("simlogs")
    configs = [simulation.SimConfig(kind="random", duration_s=3.0, seed=s) for s in (31, 32, 33)]
    simulation.simulate_set(folder, configs)
    return folder


def _raw(tmp_path, sim_logs, bad: bool):
    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("sim000", "sim001", "sim002"):
        shutil.copyfile(sim_logs / name, raw / name)
    if bad:
        (raw / "sim001b").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))  # between sim001 and sim002
    return raw


def _materializations(instance, asset: str) -> dict[str, dict]:
    records = instance.fetch_materializations(dg.AssetKey(asset), limit=100).records
    return {r.partition_key: {k: v.value for k, v in r.asset_materialization.metadata.items()} for r in records}


def test_every_flight_in_one_run_with_its_own_metadata(sim_logs, tmp_path):
    raw = _raw(tmp_path, sim_logs, bad=False)
    resources = {"data_root": DataRoot(root=str(tmp_path / "root"), raw=str(raw)), "model": ModelConfig()}
    ids = ["sim000", "sim001", "sim002"]
    with dg.instance_for_test() as instance:
        failures = main.run_flights(instance, resources, ids, PER_FLIGHT, "flights", log=lambda *_: None)
        assert failures == {}
        assert len(instance.get_runs()) == 1
        for asset in ("decoded_flight", "residual_table", "rollout_errors", "flight_mcap"):
            assert set(_materializations(instance, asset)) == set(ids), asset
        decoded = _materializations(instance, "decoded_flight")
        rows = {fid: m["rows_fixedFrequency"] for fid, m in decoded.items()}
        assert rows == {fid: store.read_decoded(tmp_path / "root", "fixedFrequency", fid).height for fid in ids}
        assert len({m["source_sha256"] for m in decoded.values()}) == 3  # each partition has its own flight's
        residual_meta = _materializations(instance, "residual_table").values()
        assert all(m["model_vs_measured"].startswith("![") for m in residual_meta)
        assert all((tmp_path / "root" / "mcap" / f"{fid}.mcap").is_file() for fid in ids)


def test_a_bad_flight_fails_alone_and_the_others_succeed(sim_logs, tmp_path):
    raw = _raw(tmp_path, sim_logs, bad=True)
    resources = {"data_root": DataRoot(root=str(tmp_path / "root"), raw=str(raw)), "model": ModelConfig()}
    ids = ["sim000", "sim001", "sim001b", "sim002"]
    with dg.instance_for_test() as instance:
        failures = main.run_flights(instance, resources, ids, [decoded_flight], "decode", log=lambda *_: None)
        assert list(failures) == ["sim001b"] and "quarantined" in failures["sim001b"]
        assert set(_materializations(instance, "decoded_flight")) == {"sim000", "sim001", "sim002"}
        # the batch that failed, the bad flight alone, then the two ranges around it
        assert len(instance.get_runs()) == 4
        assert [r["flight"] for r in store.quarantined(tmp_path / "root")] == ["sim001b"]


def test_a_split_range_runs_on_both_cores_and_a_bad_flight_still_fails_alone(sim_logs, tmp_path, monkeypatch):
    """A range of four flights split in two runs at once (the second half in a second process,
    on the same instance): every good flight materialised once, the bad one (in the second
    half) retried alone and reported alone."""
    monkeypatch.setattr(parallel, "SPLIT_AT_FLIGHTS", 2)
    monkeypatch.delenv("QUADCORE_EXECUTOR", raising=False)
    raw = _raw(tmp_path, sim_logs, bad=True)
    resources = {"data_root": DataRoot(root=str(tmp_path / "root"), raw=str(raw)), "model": ModelConfig()}
    ids = ["sim000", "sim001", "sim001b", "sim002"]
    lines: list[str] = []
    with dg.instance_for_test() as instance:
        try:
            failures = main.run_flights(instance, resources, ids, [decoded_flight], "decode", log=lines.append)
        finally:
            parallel.shutdown()
        assert list(failures) == ["sim001b"] and "quarantined" in failures["sim001b"]
        records = instance.fetch_materializations(dg.AssetKey("decoded_flight"), limit=100).records
        assert sorted(r.partition_key for r in records) == ["sim000", "sim001", "sim002"]  # each once
        # the two halves, then the bad flight alone and the flight after it
        runs = instance.get_runs()
        assert len(runs) == 4
        pids = set()
        for run in runs:
            starts = [e for e in instance.all_logs(run.run_id) if e.dagster_event and e.dagster_event.is_step_start]
            pids.update(e.dagster_event.pid for e in starts)
        assert os.getpid() in pids and len(pids) == 2  # this process and the second one
    assert [line.split(":")[0] for line in lines] == ["  decode sim000..sim001", "  decode sim002", "  decode sim001b"]
    assert "quarantined" in lines[2]


def test_in_process_executor_keeps_one_process(monkeypatch):
    keys = [f"f{i:02d}" for i in range(parallel.SPLIT_AT_FLIGHTS)]
    half = len(keys) // 2
    assert parallel.halves(keys) == [keys[:half], keys[half:]]
    sizes = [len(keys) - 1.0] + [1.0] * (len(keys) - 1)  # a long flight first: as much work as the rest
    assert parallel.halves(keys, sizes) == [keys[:1], keys[1:]]
    assert parallel.halves(keys[:-1]) == [keys[:-1]]  # too few to repay a second process
    for kind in ("in_process", "multiprocess"):  # multiprocess: Dagster's executor spreads the steps instead
        monkeypatch.setenv("QUADCORE_EXECUTOR", kind)
        assert parallel.halves(keys) == [keys]


def test_per_flight_stage_with_the_multiprocess_executor(sim_logs, tmp_path, monkeypatch):
    """process_flight over two flights in one run, its steps in separate processes, as a cluster
    executor would run them (they load the definitions and the data root from the environment)."""
    raw = _raw(tmp_path, sim_logs, bad=False)
    root = tmp_path / "root"
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(root))
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(raw))
    monkeypatch.setenv("QUADCORE_AUTOMATION", "off")
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions(flights.name, ["sim000", "sim001", "sim002"])
        result = dg.execute_job(
            dg.reconstructable(process_flight_job), instance=instance,
            run_config={"execution": {"config": {"multiprocess": {"max_concurrent": 2}}}, **QUIET},
            tags=parallel.range_tags(["sim000", "sim001"]),
        )
        assert result.success
        steps = {e.step_key: e.pid for e in result.all_events if e.event_type_value == "STEP_START"}
        per_flight = ("decoded_flight", "flight_statistics", "residual_table", "rollout_errors", "flight_mcap")
        assert set(steps) == set(per_flight)
        assert len(set(steps.values())) == len(per_flight)  # each step in a process of its own
        for asset in per_flight:
            assert set(_materializations(instance, asset)) == {"sim000", "sim001"}, asset
        assert sorted(p.name for p in (root / "mcap").glob("*.mcap")) == ["sim000.mcap", "sim001.mcap"]


def test_the_main_job_redoes_only_what_changed(sim_logs, tmp_path, monkeypatch):
    """Unchanged flights are not decoded or recomputed again; a new one costs its own work, the
    refit and the diagnosis; a new decoder decodes every flight again; learning waits for its
    nightly tick while the physics model is the same."""
    raw = _raw(tmp_path, sim_logs, bad=False)
    (raw / "sim002").unlink()
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    lines: list[str] = []
    with dg.instance_for_test() as instance:
        ids = ["sim000", "sim001"]
        instance.add_dynamic_partitions(flights.name, ids)
        assert main.to_decode(instance, data_root, ids) == ids
        main.run_flights(instance, {"data_root": data_root, "model": ModelConfig()}, ids, PER_FLIGHT, "f", lines.append)
        assert main.to_decode(instance, data_root, ids) == []
        with monkeypatch.context() as m:  # a release changed the decoder: its tables are not the same logs' now
            m.setattr(flightmod, "decoder_digest", lambda: "another decoder")
            assert main.to_decode(instance, data_root, ids) == ids
        assert main.to_recompute(instance, data_root, ModelConfig(), ids, []) == []
        assert main.to_recompute(instance, data_root, ModelConfig(), ids, ["sim001"]) == ["sim001"]
        # another model than the tables were computed against: every table is stale
        assert main.to_recompute(instance, data_root, ModelConfig(thrust_map="motor_speed"), ids, []) == ids
        (raw / "sim001").unlink()
        (raw / "sim001").write_bytes((sim_logs / "sim002").read_bytes())  # the log changed
        assert main.to_decode(instance, data_root, ids) == ["sim001"]
    assert main.fleet_is_stale(tmp_path / "root", ModelConfig(), []) is True  # not fitted yet
    assert learn.learning_is_stale(tmp_path / "root") == "no learned models yet"


def test_new_statistics_refit_the_fleet(sim_logs, tmp_path):
    """Statistics recomputed without a new decode (here: one removed; after an upgrade: made by
    other code) are what the fit combines, so the next main job refits instead of calling the
    old fit up to date."""
    raw = _raw(tmp_path, sim_logs, bad=False)
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    with dg.instance_for_test() as instance:
        assert main.run_all(data_root, ModelConfig(), instance, log=[].append) == 0
        again: list[str] = []
        assert main.run_all(data_root, ModelConfig(), instance, log=again.append) == 0
        assert any("fitted model and diagnosis: up to date" in line for line in again), again
        sufficient.stats_path(tmp_path / "root", "sim001").unlink()
        third: list[str] = []
        assert main.run_all(data_root, ModelConfig(), instance, log=third.append) == 0
    assert any(line.startswith("2/4 fit the model") for line in third), third
    assert sufficient.stats_path(tmp_path / "root", "sim001").is_file()


def test_the_main_job_through_dagsters_multiprocess_executor(sim_logs, tmp_path, monkeypatch):
    """QUADCORE_EXECUTOR=multiprocess (what benchmarks/bench_executors.py measures against our
    split): the main job's decoding, each step in a process of its own, one bad flight named and
    skipped, the others decoded into their own partitions."""
    raw = _raw(tmp_path, sim_logs, bad=True)
    monkeypatch.setenv("QUADCORE_EXECUTOR", "multiprocess")
    resources = {"data_root": DataRoot(root=str(tmp_path / "root"), raw=str(raw)), "model": ModelConfig()}
    ids = ["sim000", "sim001", "sim001b", "sim002"]
    with dg.instance_for_test() as instance:
        failures = main.run_flights(instance, resources, ids, DECODE, "decode", log=lambda *_: None)
        assert list(failures) == ["sim001b"]
        assert set(_materializations(instance, "decoded_flight")) == {"sim000", "sim001", "sim002"}
        starts = [e for r in instance.get_runs() for e in instance.all_logs(r.run_id)
                  if e.dagster_event is not None and e.dagster_event.event_type_value == "STEP_START"]
        assert starts and all(e.dagster_event.pid != os.getpid() for e in starts)
