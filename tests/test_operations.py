"""Running it for real: new flights, retraining, bad input, atomic and idempotent outputs,
and the README's queries. Real Dagster instances, real files."""

from __future__ import annotations

import hashlib
import shutil
from datetime import UTC, datetime, timedelta
from pathlib import Path

import dagster as dg
import duckdb
import polars as pl
import pytest

from pipeline.assets import AGAINST_MODEL, FLEET, PER_FLIGHT
from pipeline.assets.decode import decoded_flight
from pipeline.definitions import defs
from pipeline.resources import DataRoot, ModelConfig
from pipeline.sensors import raw_log_sensor
from quadcore.logs import logformat
from quadcore.sim import usdlog
from quadcore.store import store

QUIET = {"loggers": {"console": {"config": {"log_level": "ERROR"}}}}


@pytest.fixture(scope="module")
def sim_logs(drag_fleet):
    return drag_fleet


def sensor_tick(instance, data_root, cursor=None):
    ctx = dg.build_sensor_context(instance=instance, cursor=cursor, resources={"data_root": data_root})
    result = raw_log_sensor(ctx)
    if isinstance(result, dg.SensorResult):
        for req in result.dynamic_partitions_requests or []:
            instance.add_dynamic_partitions(req.partitions_def_name, list(req.partition_keys))
    return result


def run(assets, resources, instance, key=None):
    res = dg.materialize(assets, partition_key=key, instance=instance, resources=resources, run_config=QUIET,
                         raise_on_error=False)
    assert res.success
    return res


def materialization_count(instance, asset: str, key: str) -> int:
    records = instance.fetch_materializations(dg.AssetRecordsFilter(asset_key=dg.AssetKey(asset),
                                                                    asset_partitions=[key]), limit=100)
    return len(records.records)


def nominal_lab(sim_logs: Path, tmp_path: Path, monkeypatch) -> tuple[Path, DataRoot, dict]:
    """A raw folder with two flights, the nominal model file (a refit leaves the model as it is) and
    the settings the automation's conditions and the schedule read: (raw folder, data root, resources)."""
    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("sim000", "sim001"):
        shutil.copyfile(sim_logs / name, raw / name)
    model_file = tmp_path / "model.toml"
    model_file.write_text("effects = []\n")
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(tmp_path / "root"))
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(raw))
    monkeypatch.setenv("QUADCORE_MODEL", str(model_file))
    monkeypatch.delenv("QUADCORE_EFFECTS", raising=False)
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    return raw, data_root, {"data_root": data_root, "model": ModelConfig(model_file=str(model_file))}


@pytest.mark.slow  # the sensor and every stage, twice
def test_new_flight_flows_through_without_rerunning_the_others(sim_logs, tmp_path, monkeypatch):
    """A new flight is decoded and computed alone; the refit it causes leaves the model as it was
    (the nominal model: nothing to fit), so no other flight's tables are recomputed; the learned
    models wait for the schedule nightly_retrain_learned_models, which skips a tick when no
    residual table changed since they trained."""
    from pipeline.assets.learning import learning_features
    from pipeline.schedules import nightly_retrain_learned_models

    raw, data_root, resources = nominal_lab(sim_logs, tmp_path, monkeypatch)

    def tick_at(when):
        return nightly_retrain_learned_models.evaluate_tick(
            dg.build_schedule_context(instance=instance, scheduled_execution_time=when))

    with dg.instance_for_test() as instance:
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance)  # the daemon's first tick
        assert auto.total_requested == 0
        first = sensor_tick(instance, data_root)
        assert sorted(r.partition_key for r in first.run_requests) == ["sim000", "sim001"]
        for r in first.run_requests:
            run(PER_FLIGHT, resources, instance, r.partition_key)
        # the automation refits once flights are there ...
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=auto.cursor)
        assert auto.get_num_requested(dg.AssetKey("physics_model")) == 1
        assert auto.get_num_requested(dg.AssetKey("learning_features")) == 0  # learning waits for the schedule
        fleet = run(FLEET, resources, instance)
        # two flights, nothing held out (no QUADCORE_HOLDOUT): discovery cross-validates over both
        disc = fleet.asset_materializations_for_node("term_discovery")[0].metadata["summary"].value
        assert not disc.startswith("skipped"), disc
        # ... a refit that leaves the model as it was recomputes no flight's tables, and then nothing runs
        for _ in range(2):
            auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=auto.cursor)
            assert auto.get_num_requested(dg.AssetKey("residual_table")) == 0
        assert auto.total_requested == 0
        assert isinstance(sensor_tick(instance, data_root, first.cursor), dg.SkipReason)

        shutil.copyfile(sim_logs / "sim002", raw / "sim002")
        second = sensor_tick(instance, data_root, first.cursor)
        assert [r.partition_key for r in second.run_requests] == ["sim002"]
        run(PER_FLIGHT, resources, instance, "sim002")
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=auto.cursor)
        assert auto.get_num_requested(dg.AssetKey("physics_model")) == 1  # a new flight: refit at once
        assert auto.get_num_requested(dg.AssetKey("learning_features")) == 0
        run(FLEET, resources, instance)
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=auto.cursor)
        for asset in ("residual_table", "rollout_errors", "flight_mcap"):
            assert auto.get_num_requested(dg.AssetKey(asset)) == 0, asset  # the model did not change
            for fid in ("sim000", "sim001", "sim002"):
                assert materialization_count(instance, asset, fid) == 1, (asset, fid)

        # the schedule: no learned models yet, so its tick runs them; then it skips until a residual table changes
        night = datetime.now(UTC).replace(hour=2, minute=0, second=0, microsecond=0) + timedelta(days=1)
        data = tick_at(night)
        assert len(data.run_requests) == 1 and data.run_requests[0].tags["quadcore/trigger"] == "no learned models yet"
        assert nightly_retrain_learned_models.job_name == "retrain_learned_models"
        run([learning_features], resources, instance)
        assert tick_at(night + timedelta(days=1)).skip_message == (
            "no residual table changed since the learned models last trained")
        run(AGAINST_MODEL, resources, instance, "sim001")
        assert len(tick_at(night + timedelta(days=2)).run_requests) == 1


@pytest.mark.slow  # the main job, then the sensor
def test_sensor_does_not_redo_flights_the_main_job_processed(sim_logs, tmp_path):
    """`make run` then `make ui`: the sensor's first tick (no cursor yet) sees every log, but
    runs only the flights whose decoded table is missing or from other bytes; its runs are
    filed under the process_flight job."""
    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("sim000", "sim001"):
        shutil.copyfile(sim_logs / name, raw / name)
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000", "sim001"])
        run([decoded_flight], {"data_root": data_root}, instance, "sim000")  # what `make run` did
        shutil.copyfile(sim_logs / "sim002", raw / "sim002")
        first = sensor_tick(instance, data_root)
        assert sorted(r.partition_key for r in first.run_requests) == ["sim001", "sim002"]
        assert raw_log_sensor.job_name == "process_flight"
        job = defs.resolve_job_def("process_flight")
        assert {k.to_user_string() for k in job.asset_layer.executable_asset_keys} == {
            "decoded_flight", "flight_statistics", "residual_table", "rollout_errors", "flight_mcap"}  # per flight only
        # the same flight id with other bytes is processed again
        (raw / "sim000").unlink()
        shutil.copyfile(sim_logs / "sim002", raw / "sim000")
        again = sensor_tick(instance, data_root, first.cursor)
        assert [r.partition_key for r in again.run_requests] == ["sim000"]


def settle(instance, resources, cursor, when=None, ticks=12):
    """Act as the daemon: evaluate the automation, run what it requests (fleet assets in one run,
    per-flight assets one run per flight), until it requests nothing. Returns the cursor."""
    from pipeline.assets import EXPORT, LEARNING

    assets = {a.key: a for a in [*PER_FLIGHT, *FLEET, *LEARNING, *EXPORT]}
    keys = list(assets)
    for _ in range(ticks):
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=cursor, evaluation_time=when)
        cursor = auto.cursor
        if auto.total_requested == 0:
            return cursor
        requested = {k: auto.get_requested_partitions(k) for k in keys if auto.get_num_requested(k)}
        fleet = [assets[k] for k, parts in requested.items() if parts == {None}]
        if fleet:
            run(fleet, resources, instance)
        for part in sorted({p for parts in requested.values() for p in parts if p is not None}):
            run([assets[k] for k, parts in requested.items() if part in parts], resources, instance, part)
    raise AssertionError(f"the automation still requests runs after {ticks} ticks")


@pytest.mark.slow  # many Dagster runs and automation ticks
def test_automation_converges_when_a_flight_run_overlaps_a_refit(sim_logs, tmp_path, monkeypatch):
    """A flight dropped in while the model is refitted, its run reading the old model but ending
    after the refit: the automation refreshes it (eager() alone counts that run as the refresh),
    every per-flight result ends against the current model, and learning waits for that."""
    from pipeline.freshness import current_model_version, versions_used
    from pipeline.resources import data_root_from_env, model_config_from_env

    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("sim000", "sim001"):
        shutil.copyfile(sim_logs / name, raw / name)
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(tmp_path / "root"))
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(raw))
    model_file = tmp_path / "model.toml"
    model_file.write_text('effects = ["rotor_drag"]\n')  # a refit on more flights moves its parameters
    monkeypatch.setenv("QUADCORE_MODEL", str(model_file))
    monkeypatch.delenv("QUADCORE_EFFECTS", raising=False)
    data_root = data_root_from_env()
    resources = {"data_root": data_root, "model": model_config_from_env()}
    fitted = data_root.root_path / "models" / "physics_model.json"
    with dg.instance_for_test() as instance:
        cursor = settle(instance, resources, None)  # the daemon's first tick: nothing yet
        tick = sensor_tick(instance, data_root)
        for r in tick.run_requests:
            run(PER_FLIGHT, resources, instance, r.partition_key)
        cursor = settle(instance, resources, cursor)
        assert fitted.is_file()
        before = current_model_version()

        # a third flight arrives; its per-flight run starts against the model of two flights ...
        shutil.copyfile(sim_logs / "sim002", raw / "sim002")
        tick = sensor_tick(instance, data_root, tick.cursor)
        assert [r.partition_key for r in tick.run_requests] == ["sim002"]
        run([decoded_flight], resources, instance, "sim002")
        old_model = fitted.read_bytes()
        run(FLEET, resources, instance)  # ... meanwhile the model is refitted on three flights
        new_model = fitted.read_bytes()
        fitted.write_bytes(old_model)  # what the flight's run read when it started
        run(PER_FLIGHT[1:], resources, instance, "sim002")  # ... and its run ends after the refit
        fitted.write_bytes(new_model)
        assert current_model_version() != before
        flights_now = {"sim000", "sim001", "sim002"}
        stale = versions_used(instance, dg.AssetKey("residual_table"), flights_now)
        assert stale["sim002"] == before  # computed against the old model, materialised last
        from pipeline.schedules import learning_due

        due, why = learning_due(instance)  # the schedule's tick would wait for the refresh, not mix two models
        assert not due and why.startswith("waiting: ") and "sim002" in why, why

        cursor = settle(instance, resources, cursor)
        current = current_model_version()
        for asset in ("residual_table", "rollout_errors", "flight_mcap"):
            used = versions_used(instance, dg.AssetKey(asset), flights_now)
            assert used == dict.fromkeys(flights_now, current), asset
        models = {store.read_metadata(store.table_path(data_root.root_path, "residuals", f))["model"]["label"]
                  for f in flights_now}
        assert models == {"nominal+rotor_drag"}
        # an effect added to the model file mid-way: refit, and every flight follows, with no manual step
        model_file.write_text('effects = ["rotor_drag", "thrust_scale"]\n')
        cursor = settle(instance, resources, cursor)
        assert current_model_version() != current
        for asset in ("residual_table", "rollout_errors", "flight_mcap"):
            assert set(versions_used(instance, dg.AssetKey(asset), flights_now).values()) == {current_model_version()}
        models = {store.read_metadata(store.table_path(data_root.root_path, "residuals", f))["model"]["label"]
                  for f in flights_now}
        assert models == {"nominal+rotor_drag+thrust_scale"}
        # the nightly schedule's tick runs the learning now that every flight is fresh, and it succeeds on one model
        from pipeline.assets.learning import learning_features

        assert learning_due(instance) == (True, "no learned models yet")
        run([learning_features], resources, instance)


def test_bad_files_are_quarantined_with_their_reason_and_the_rest_goes_on(sim_logs, tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    good = (sim_logs / "sim000").read_bytes()
    shutil.copyfile(sim_logs / "sim000", raw / "sim000")
    (raw / "empty").write_bytes(b"")
    (raw / "foreign").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    (raw / "cut_header").write_bytes(good[:40])
    (raw / "truncated").write_bytes(good[: len(good) // 2 + 7])
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    with dg.instance_for_test() as instance:
        result = sensor_tick(instance, data_root)
        assert sorted(r.partition_key for r in result.run_requests) == ["sim000", "truncated"]
        reasons = {r["flight"]: r["reason"] for r in store.quarantined(data_root.root_path)}
        assert set(reasons) == {"empty", "foreign", "cut_header"}
        assert "empty" in reasons["empty"] and "0xBC" in reasons["foreign"] and "truncated" in reasons["cut_header"]
        (event,) = result.asset_events
        assert event.asset_key == dg.AssetKey("quarantine")
        assert "foreign" in event.metadata["quarantined"].value

        # the truncated log still decodes, with what was dropped in its metadata and a warning
        res = run([decoded_flight], {"data_root": data_root}, instance, "truncated")
        meta = res.asset_materializations_for_node("decoded_flight")[0].metadata
        assert meta["warning_count"].value >= 1 and meta["bytes_dropped"].value > 0
        assert "truncated" in meta["decode_warnings"].value


@pytest.mark.slow  # a Dagster run per check
def test_implausible_flight_gets_check_warnings(sim_logs, tmp_path):
    log = logformat.decode_file(sim_logs / "sim000")
    ff = log.tables["fixedFrequency"].copy()
    ff["pm.vbatMV"] = 3700  # stuck battery voltage, as in jana20..33
    ff["stateEstimate.x"] = ff["stateEstimate.y"] = 0.0
    ff["stateEstimate.z"] = 0.01  # never left the ground
    t = log.timestamps_us["fixedFrequency"].copy()
    t[len(t) // 2:] += 200_000  # a 200 ms hole
    data = logformat.encode(list(usdlog.LOG_EVENT_TYPES), [("fixedFrequency", t, ff)])
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "odd").write_bytes(data)
    shutil.copyfile(sim_logs / "sim001", raw / "sim001")
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["odd", "sim001"])
        res = run([decoded_flight], {"data_root": data_root}, instance, "odd")  # warnings, not a crash
        checks = {e.check_name: e for e in res.get_asset_check_evaluations()}
        # a good flight decoded later does not turn the checks green: each speaks for every flight
        later = run([decoded_flight], {"data_root": data_root}, instance, "sim001")
        after = {e.check_name: e for e in later.get_asset_check_evaluations()}
    assert not checks["stuck_sensors"].passed and "vbat_V" in checks["stuck_sensors"].description
    # the check result names its flight, with the count
    assert checks["stuck_sensors"].description.startswith("1 of 1 flights fail: odd: constant over the whole flight")
    assert not checks["sample_gaps"].passed
    assert not checks["has_flight_phase"].passed
    assert all(c.severity == dg.AssetCheckSeverity.WARN for c in [*checks.values(), *after.values()])
    gaps, stuck = after["sample_gaps"], after["stuck_sensors"]
    assert not gaps.passed and gaps.description.startswith("1 of 2 flights fail: odd: 1 gaps longer than 50 ms")
    assert not stuck.passed and stuck.metadata["flights_failing"].value == 1
    assert stuck.metadata["flights_checked"].value == 2 and stuck.metadata["failing"].value == "odd"
    assert after["no_nans"].passed and after["no_nans"].description == "all 2 flights pass"
    table = gaps.metadata["flights"].value.splitlines()
    assert table[2].startswith("| odd | WARN |") and table[3].startswith("| sim001 | pass |")


@pytest.mark.slow  # Dagster runs, twice
def test_writes_are_atomic_and_reruns_idempotent(sim_logs, tmp_path, monkeypatch):
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(sim_logs))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim001"])
        run([decoded_flight], {"data_root": data_root}, instance, "sim001")
        path = store.decoded_path(data_root.root_path, "fixedFrequency", "sim001")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        run([decoded_flight], {"data_root": data_root}, instance, "sim001")
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest  # same bytes on a re-run

        def crash(self, file, **kwargs):  # a crash half-way through writing
            with open(file, "wb") as fh:
                fh.write(b"PAR1 half a file")
            raise OSError("disk full")

        monkeypatch.setattr(pl.DataFrame, "write_parquet", crash)
        res = dg.materialize([decoded_flight], partition_key="sim001", instance=instance,
                             resources={"data_root": data_root}, run_config=QUIET, raise_on_error=False)
        assert not res.success
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest  # the earlier output is intact
    assert not list(path.parent.glob(".*.tmp"))  # and no half-written file is left behind


@pytest.mark.slow  # every per-flight stage in Dagster
def test_readme_queries_run(sim_logs, tmp_path):
    root = tmp_path / "root"
    data_root = DataRoot(root=str(root), raw=str(sim_logs))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000", "sim001"])
        for key in ("sim000", "sim001"):
            run([decoded_flight, AGAINST_MODEL[0]], {"data_root": data_root, "model": ModelConfig()}, instance, key)
    speed = (pl.col("v_w_x_mps") ** 2 + pl.col("v_w_y_mps") ** 2 + pl.col("v_w_z_mps") ** 2).sqrt()
    by_polars = (
        pl.scan_parquet(root / "residuals" / "**" / "*.parquet", hive_partitioning=True,
                        hive_schema={"flight": pl.String})
        .with_columns((speed // 0.5 * 0.5).alias("speed_bin_mps"))
        .group_by("flight", "speed_bin_mps")
        .agg((pl.col("f_res_b_x_N") ** 2).mean().sqrt().alias("rmse_x_N"), pl.len().alias("n"))
        .sort("flight", "speed_bin_mps")
        .collect()
    )
    by_duckdb = duckdb.sql(f"""
        SELECT flight, floor(sqrt(v_w_x_mps^2 + v_w_y_mps^2 + v_w_z_mps^2) / 0.5) * 0.5 AS speed_bin_mps,
               sqrt(avg(f_res_b_x_N ^ 2)) AS rmse_x_N, count(*) AS n
        FROM read_parquet('{root}/residuals/*/*.parquet', hive_partitioning = true)
        GROUP BY ALL ORDER BY flight, speed_bin_mps
    """).pl()
    assert set(by_polars["flight"]) == {"sim000", "sim001"}
    assert by_polars["n"].sum() == by_duckdb["n"].sum()
    assert by_polars["rmse_x_N"].to_list() == pytest.approx(by_duckdb["rmse_x_N"].to_list(), rel=1e-6)
    # drag: the residual grows with speed
    one = by_polars.filter(pl.col("flight") == "sim000")
    assert one["rmse_x_N"][-1] > one["rmse_x_N"][0]


def test_every_output_has_the_mode_of_a_plain_file(tmp_path):
    """Atomic writes go through a temp file (mkstemp makes it 0600): the outputs must not keep
    that mode while the reports written directly get the usual one."""
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    written = [store.write_json({"a": 1}, tmp_path / "a.json"), store.write_text("t", tmp_path / "b.md"),
               store.write_parquet(pl.DataFrame({"x_m": [1.0]}), tmp_path / "c.parquet", {})]
    assert {p.stat().st_mode & 0o777 for p in written} == {plain.stat().st_mode & 0o777}


def test_every_parquet_output_states_the_unit_of_every_column(sim_logs, tmp_path):
    from quadcore.learn import features as feat

    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(sim_logs))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["sim000"])
        run(PER_FLIGHT, {"data_root": data_root, "model": ModelConfig()}, instance, "sim000")
    root = data_root.root_path
    feat.replace_feature_tables(root, {"sim000": store.read_table(root, "residuals", "sim000")}, feat.parse([]))
    files = sorted(root.glob("**/*.parquet"))
    stages = {p.relative_to(root).parts[0] for p in files}
    assert {"decoded", "residuals", "rollouts", "features"} <= stages
    for path in files:
        units = store.read_metadata(path)["units"]
        assert set(units) == set(pl.read_parquet_schema(path)), path
        assert units.get("timestamp_us", "us") == "us" and units.get("t_s", "s") == "s", path


def test_the_demo_keeps_its_own_model_file(tmp_path, monkeypatch):
    """The demo's next turn is written to <root>/model.toml (the repository's file untouched),
    and the model the pipeline loads from then on is that one: a second run continues the story."""
    from pipeline.resources import model_config_from_env
    from quadcore.spec.model import load_model_file
    from quadcore.workflows.demo import write_demo_model_file

    repo_file = Path(__file__).resolve().parents[1] / "model.toml"
    own = write_demo_model_file(tmp_path, str(repo_file), ["rotor_drag"])
    assert own == tmp_path / "model.toml" and load_model_file(own).effects == ["rotor_drag"]
    assert "# Fix a parameter instead of fitting it" in own.read_text()  # the template's comments kept
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(tmp_path))
    monkeypatch.delenv("QUADCORE_MODEL", raising=False)
    monkeypatch.delenv("QUADCORE_EFFECTS", raising=False)
    assert model_config_from_env().spec().effects == ["rotor_drag"]


@pytest.mark.slow  # the sensor, two flights' runs, a third flight's run and three automation ticks
def test_the_automation_leaves_a_new_flight_to_the_run_the_sensor_launched(sim_logs, tmp_path, monkeypatch):
    """The raw-log sensor's run for a new flight selects every per-flight asset (the daemon runs
    it as the process_flight job), so neither the partition appearing nor that run's decode arms
    the automation on the flight's other tables: where the run's later steps leave nothing the
    automation sees as done or in progress (here they fail: the motors never leave idle, so
    the physics refuses the flight), it requests none of them. With Dagster's eager() (the
    partition newly missing, the decode counted as made by another run) it requested the
    flight's statistics, residual table, rollouts and MCAP again: in a running UI, a new flight
    computed twice when a tick fell before the sensor's run had its later steps in progress."""
    from fuzz.badlogs import bad_logs

    raw, data_root, resources = nominal_lab(sim_logs, tmp_path, monkeypatch)
    # the sensor's job as the daemon runs it, with this test's resources
    process_flight = dg.define_asset_job("process_flight", selection=dg.AssetSelection.assets(*PER_FLIGHT))
    local = dg.Definitions(assets=[*PER_FLIGHT, *FLEET], resources=resources, jobs=[process_flight])
    job = local.resolve_job_def("process_flight")

    def launch(request):
        return job.execute_in_process(instance=instance, partition_key=request.partition_key, run_config=QUIET,
                                      asset_selection=request.asset_selection, raise_on_error=False)

    with dg.instance_for_test() as instance:
        first = sensor_tick(instance, data_root)
        for request in first.run_requests:
            assert launch(request).success
        run(FLEET, resources, instance)
        cursor = settle(instance, resources, None)
        (raw / "idle").write_bytes(bad_logs((sim_logs / "sim000").read_bytes())["motors_idle"])
        second = sensor_tick(instance, data_root, first.cursor)  # adds the partition
        [request] = second.run_requests
        assert set(request.asset_selection or []) == {a.key for a in PER_FLIGHT}
        auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=cursor)  # before the run
        result = launch(request)
        done = {m.asset_key.to_user_string() for m in result.get_asset_materialization_events()
                if m.asset_key is not None}
        assert "decoded_flight" in done and "residual_table" not in done, done  # decoded; the physics refused it
        for _ in range(2):
            auto = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=auto.cursor)
            again = {a.key.to_user_string() for a in PER_FLIGHT if "idle" in auto.get_requested_partitions(a.key)}
            assert not again, again
