"""Incremental, truly, in a running UI: `make ui` with its automation on; a log dropped into the
raw folder is decoded and computed alone, and no other flight's tables are computed again while
the model does not change."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from quadcore.sim import simulation

sys.path.insert(0, str(Path(__file__).parent))
from cdp import free_port  # noqa: E402
from test_ui import _kill_everything_of, start_ui  # noqa: E402

pytestmark = pytest.mark.slow  # dagster dev in a subprocess, sensors and automation ticks in real time


@pytest.fixture(scope="module")
def live_ui(tmp_path_factory):
    """`make ui` with its automation on (sensors, daemon), on a data root whose three flights were
    processed and fitted with the nominal model; a fourth log waits beside the raw folder."""
    import dagster as dg

    from pipeline.assets import FLEET, PER_FLIGHT
    from pipeline.resources import DataRoot, ModelConfig

    base = tmp_path_factory.mktemp("live")
    logs = base / "logs"
    configs = [simulation.SimConfig(kind="random", duration_s=3.0, seed=s) for s in (41, 42, 43, 44)]
    simulation.simulate_set(logs, configs, {})
    raw = base / "raw"
    raw.mkdir()
    for name in ("sim000", "sim001", "sim002"):
        shutil.copyfile(logs / name, raw / name)
    home = base / "dagster_home"
    home.mkdir()
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
    model_file = base / "model.toml"
    model_file.write_text("effects = []\n")  # the nominal model: a refit on one more flight leaves it as it is
    env = {**os.environ, "DAGSTER_HOME": str(home), "QUADCORE_DATA_ROOT": str(base / "root"),
           "QUADCORE_RAW_DIR": str(raw), "QUADCORE_MODEL": str(model_file), "QUADCORE_AUTOMATION": "on"}
    env.pop("QUADCORE_EFFECTS", None)
    data_root = DataRoot(root=str(base / "root"), raw=str(raw))
    resources = {"data_root": data_root, "model": ModelConfig(model_file=str(model_file))}
    quiet = {"loggers": {"console": {"config": {"log_level": "ERROR"}}}}
    instance = dg.DagsterInstance.from_config(str(home))
    instance.add_dynamic_partitions("flights", ["sim000", "sim001", "sim002"])
    for key in ("sim000", "sim001", "sim002"):
        assert dg.materialize(PER_FLIGHT, partition_key=key, instance=instance, run_config=quiet,
                              resources=resources).success
    assert dg.materialize(FLEET, instance=instance, run_config=quiet, resources=resources).success
    instance.dispose()
    proc, log = start_ui(base, home, free_port(), env)
    yield base, logs, raw, home
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        pass
    _kill_everything_of(home)
    log.close()


def test_a_flight_dropped_into_a_running_ui_recomputes_only_its_own_tables(live_ui):
    """The raw-folder sensor decodes the new flight and computes its tables, each exactly once (the
    automation leaves the flight to the sensor's run); the automation refits, and discovery follows
    each refit once; the model version does not change (nominal model), so no other flight's
    residual table, rollouts or MCAP is computed again."""
    import dagster as dg

    base, logs, raw, home = live_ui
    per_flight = ("decoded_flight", "flight_statistics", "residual_table", "rollout_errors", "flight_mcap")

    def counts(instance) -> dict[tuple[str, str], int]:
        out = {}
        for asset in per_flight:
            for fid in ("sim000", "sim001", "sim002", "sim003"):
                records = instance.fetch_materializations(
                    dg.AssetRecordsFilter(asset_key=dg.AssetKey(asset), asset_partitions=[fid]), limit=20).records
                out[asset, fid] = len(records)
        return out

    def busy(instance) -> bool:
        return bool(instance.get_run_records(dg.RunsFilter(statuses=[
            dg.DagsterRunStatus.QUEUED, dg.DagsterRunStatus.STARTING, dg.DagsterRunStatus.STARTED]), limit=1))

    instance = dg.DagsterInstance.from_config(str(home))
    try:
        before = counts(instance)
        refits_before = len(instance.fetch_materializations(dg.AssetKey("physics_model"), limit=50).records)
        discoveries_before = len(instance.fetch_materializations(dg.AssetKey("term_discovery"), limit=50).records)
        shutil.copyfile(logs / "sim003", raw / "sim003")
        t0 = time.time()
        deadline = t0 + 600
        quiet_since = None
        while True:  # until sim003 is done, the refit happened, and nothing ran for two automation ticks
            now = counts(instance)
            refits = len(instance.fetch_materializations(dg.AssetKey("physics_model"), limit=50).records)
            done = all(now[a, "sim003"] >= 1 for a in per_flight) and refits > refits_before
            if done and not busy(instance):
                quiet_since = quiet_since or time.time()
                if time.time() - quiet_since > 75:
                    break
            else:
                quiet_since = None
            assert time.time() < deadline, (now, refits, (base / "dagster_dev.log").read_text()[-3000:])
            time.sleep(5)
        after = counts(instance)
        discoveries = len(instance.fetch_materializations(dg.AssetKey("term_discovery"), limit=50).records)
    finally:
        instance.dispose()
    recomputed = {k: after[k] - before[k] for k in after if after[k] != before[k]}
    sys.__stderr__.write(f"\nnew flight in a running UI: recomputed {recomputed} in {time.time() - t0:.0f} s "
                         f"(refits {refits - refits_before}, discoveries {discoveries - discoveries_before})\n")
    # only the new flight's own tables, each once: by the sensor's run, none again by the automation
    assert recomputed == {(a, "sim003"): 1 for a in per_flight}, recomputed
    assert discoveries - discoveries_before == refits - refits_before, (discoveries, refits)  # after each refit
