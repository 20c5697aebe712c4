"""The local cluster for real (issue 26): PostgreSQL, Redis, moto's S3 server, two Celery workers,
the daemon and the webserver started by ``python -m pipeline.cluster up`` (what ``make
cluster-up`` runs), the main job through the daemon's queue with its steps on the workers, then
``down``. Skipped, with the reason, where PostgreSQL or Redis is not installed (``.ci/run``
installs both)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

pytest.importorskip("dagster_celery", reason="the cluster extra (dagster-celery) is not installed")

from pipeline.cluster import services  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
HAS_SERVERS = bool(list(Path("/usr/lib/postgresql").glob("*/bin/initdb"))) and shutil.which("redis-server")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not HAS_SERVERS, reason="PostgreSQL or Redis is not installed (apt-get install postgresql "
                                               "redis-server; .ci/run does)"),
]
RUN_TIMEOUT_S = 1500


def _cli(env: dict[str, str], *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cluster", *args], env=env, cwd=REPO, text=True,
                          capture_output=True, timeout=timeout)


def _simulate(raw: Path, first: int, count: int) -> None:
    from quadcore.sim import simulation

    configs = simulation.default_flights(seed=0)[first:first + count]
    drag = {"rotor_drag": {"k_x_s_per_m": 0.12, "k_y_s_per_m": 0.12}}
    simulation.simulate_set(raw, configs, drag, prefix=f"sim{first}")


def _tree(folder: Path) -> dict[str, float]:
    return {str(p.relative_to(folder)): p.stat().st_mtime for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def cluster():
    """A cluster with two workers over four simulated flights; stopped (and checked stopped) after.
    In a folder of its own under /tmp that the postgres user can enter (pytest's are private to root)."""
    base = Path(tempfile.mkdtemp(prefix="quadcore-cluster-", dir="/tmp"))
    base.chmod(0o755)
    raw = base / "raw"
    raw.mkdir()
    _simulate(raw, 0, 4)
    home = base / "state"
    env = {**os.environ, "QUADCORE_CLUSTER_DIR": str(home), "QUADCORE_AUTOMATION": "off"}
    for key in ("QUADCORE_DATA_ROOT", "QUADCORE_RAW_DIR", "DAGSTER_HOME", "QUADCORE_EXECUTOR", "QUADCORE_CLUSTER_URL"):
        env.pop(key, None)
    started = _cli(env, "up", "--workers", "2", "--raw", str(raw))
    try:
        assert started.returncode == 0, started.stdout + started.stderr
        yield base, raw, services.Cluster(home), env
    finally:
        pids = [int(p.read_text()) for p in (home / "pids").glob("*.pid")]
        stopped = _cli(env, "down")
        assert stopped.returncode == 0, stopped.stderr
        assert not [p for p in pids if services._alive(p)], "a service outlived `down`"
        shutil.rmtree(base, ignore_errors=True)


def _storage(settings: dict[str, str]):
    import s3fs  # type: ignore[import-untyped]

    return s3fs.S3FileSystem(key=settings["AWS_ACCESS_KEY_ID"], secret=settings["AWS_SECRET_ACCESS_KEY"],
                             client_kwargs={"endpoint_url": settings["AWS_ENDPOINT_URL"]})


def _numbers(doc, prefix=""):
    """Every number in a JSON document by its path."""
    if isinstance(doc, dict):
        return {k: v for key, value in doc.items() for k, v in _numbers(value, f"{prefix}/{key}").items()}
    if isinstance(doc, list):
        return {k: v for i, value in enumerate(doc) for k, v in _numbers(value, f"{prefix}/{i}").items()}
    return {prefix: float(doc)} if isinstance(doc, int | float) and not isinstance(doc, bool) else {}


def _worker_tasks(c: services.Cluster) -> dict[str, int]:
    return {log.stem: log.read_text(errors="replace").count("succeeded in") for log in c.logs.glob("worker*.log")}


def test_the_main_job_on_the_cluster_equals_the_main_job_in_one_process(cluster):
    base, raw, c, env = cluster
    before = _tree(raw)
    ran = _cli(env, "run", timeout=RUN_TIMEOUT_S)
    assert ran.returncode == 0, ran.stdout[-3000:] + ran.stderr[-3000:]
    assert "1/4 decode" in ran.stdout and "4/4" in ran.stdout
    tasks = _worker_tasks(c)
    assert len(tasks) == 2 and all(n > 0 for n in tasks.values()), f"steps per worker: {tasks}"
    assert _tree(raw) == before, "the run wrote into the shared raw folder"

    local = base / "local"
    alone = {k: v for k, v in env.items() if not k.startswith("QUADCORE_CLUSTER")}
    alone.update(QUADCORE_DATA_ROOT=str(local), QUADCORE_RAW_DIR=str(raw), QUADCORE_EXECUTOR="in_process")
    one = subprocess.run([sys.executable, "-m", "pipeline"], cwd=REPO, text=True, capture_output=True,
                         timeout=RUN_TIMEOUT_S, env=alone)
    assert one.returncode == 0, one.stdout[-3000:] + one.stderr[-3000:]

    s3 = _storage(c.settings())
    remote = json.loads(s3.cat_file("quadcore/data/models/physics_model.json"))
    here = json.loads((local / "models" / "physics_model.json").read_text())
    a, b = _numbers(remote), _numbers(here)
    assert a.keys() == b.keys()
    for key in a:
        assert a[key] == pytest.approx(b[key], rel=1e-9, abs=1e-12), key
    flight = sorted(p.name for p in raw.iterdir() if not p.name.endswith(".json"))[0]
    with s3.open(f"quadcore/data/residuals/flight={flight}/data.parquet", "rb") as f:
        remote_table = pl.read_parquet(f)
    local_table = pl.read_parquet(local / "residuals" / f"flight={flight}" / "data.parquet")
    assert remote_table.columns == local_table.columns and remote_table.height == local_table.height
    for name in remote_table.columns:
        if remote_table[name].dtype.is_float():
            np.testing.assert_allclose(remote_table[name].to_numpy(), local_table[name].to_numpy(), rtol=1e-9,
                                       atol=1e-12, err_msg=name)


def _submit(c: services.Cluster, assets_names: list[str], tags: dict[str, str], count: int = 1) -> list[str]:
    """``count`` runs of the named assets submitted back to back (one process: a second or two
    apart); their ids."""
    code = ("import sys, json; from pipeline.cluster import launch; from pipeline import assets as A; "
            "names = json.loads(sys.argv[1]); every = [*A.PER_FLIGHT, *A.FLEET, *A.LEARNING, *A.EXPORT]; "
            "chosen = [a for a in every if a.key.to_user_string() in names]; "
            "[print(launch.submit(chosen, json.loads(sys.argv[2]))) for _ in range(int(sys.argv[3]))]")
    done = subprocess.run([sys.executable, "-c", code, json.dumps(assets_names), json.dumps(tags), str(count)],
                          cwd=REPO, env=c.environment(), text=True, capture_output=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-count:]


def _instance(c: services.Cluster):
    import dagster as dg

    os.environ.update({k: v for k, v in c.settings().items() if k.startswith(("QUADCORE_CLUSTER_PG", "DAGSTER"))})
    return dg.DagsterInstance.get()


def _status(instance, run_id: str):
    return instance.get_run_by_id(run_id).status


def _flight_range(c: services.Cluster, raw: Path) -> dict[str, str]:
    """The tags of a run over every flight in ``raw``, its partitions registered (as the main job
    registers them) so that a test also runs alone, without the main job's test before it."""
    from pipeline.partitions import FLIGHTS_PARTITION

    flights = sorted(p.name for p in raw.iterdir() if not p.name.endswith(".json"))
    instance = _instance(c)
    known = set(instance.get_dynamic_partitions(FLIGHTS_PARTITION))
    instance.add_dynamic_partitions(FLIGHTS_PARTITION, [f for f in flights if f not in known])
    return {"dagster/asset_partition_range_start": flights[0], "dagster/asset_partition_range_end": flights[-1]}


def test_a_second_job_started_meanwhile_queues_and_then_runs(cluster):
    import dagster as dg

    _, raw, c, _ = cluster
    tags = _flight_range(c, raw)
    runs = _submit(c, ["decoded_flight"], tags, count=3)  # two slots: the third waits for one
    instance = _instance(c)
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        statuses = [_status(instance, r) for r in runs]
        if all(s in (dg.DagsterRunStatus.SUCCESS, dg.DagsterRunStatus.FAILURE) for s in statuses):
            break
        time.sleep(0.5)
    assert statuses == [dg.DagsterRunStatus.SUCCESS] * 3, statuses
    # From the run records and the queue's own events, not from polling: the first two were
    # launched at once (taken off the queue while neither had ended), and the third only once one
    # of them had ended (max_concurrent_runs: 2 in deploy/local/dagster.yaml). The launch is the
    # coordinator's RUN_STARTING event; a run's start_time is when its process began, which on a
    # loaded machine can come after the other run has ended although both were launched together
    # (a fresh clone beside another test suite: the second process began 6 s after the first ended).
    records = sorted(instance.get_run_records(dg.RunsFilter(run_ids=runs)), key=lambda r: _launched_at(instance, r))
    first, second, third = records
    assert _launched_at(instance, second) < first.end_time, "the first two runs were not launched at once"
    assert _launched_at(instance, third) >= min(first.end_time, second.end_time), \
        "a third run launched with two running"
    assert third.start_time >= min(first.end_time, second.end_time), "a third run started with two running"
    assert third.create_timestamp.timestamp() < min(first.end_time, second.end_time), \
        "the third run was submitted after a slot was free: nothing queued"


def _launched_at(instance, record) -> float:
    """When the run queue's coordinator took ``record``'s run off the queue and launched it (its
    RUN_STARTING event, seconds since the epoch)."""
    import dagster as dg

    (event,) = instance.all_logs(record.dagster_run.run_id, of_type=dg.DagsterEventType.RUN_STARTING)
    return float(event.timestamp)


def _tasks(log: Path, what: str) -> set[str]:
    """The ids of the Celery tasks a worker's log says were ``what`` ("received", "succeeded")."""
    return set(re.findall(rf"Task \S+\[([0-9a-f-]+)\] {what}", log.read_text(errors="replace")))


def test_a_worker_killed_mid_step_is_replaced_and_the_run_completes(cluster):
    import dagster as dg

    _, raw, c, env = cluster
    tags = _flight_range(c, raw)
    logs = sorted(c.logs.glob("worker*.log"))
    received = {log: _tasks(log, "received") for log in logs}
    [run] = _submit(c, ["decoded_flight"], tags)
    instance = _instance(c)
    victim, task = None, None
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while victim is None and time.monotonic() < deadline:  # the worker that took the step
        for log in logs:
            new = _tasks(log, "received") - received[log]
            if new:
                victim, task = log, new.pop()
        time.sleep(0.2)
    assert victim is not None, "no worker received the step"
    os.killpg(int((c.pids / f"{victim.stem}.pid").read_text()), signal.SIGKILL)
    assert task not in _tasks(victim, "succeeded"), "the step had ended before the kill: nothing was tested"
    while time.monotonic() < deadline and _status(instance, run) not in (dg.DagsterRunStatus.SUCCESS,
                                                                            dg.DagsterRunStatus.FAILURE):
        time.sleep(0.5)
    assert _status(instance, run) == dg.DagsterRunStatus.SUCCESS
    survivors = [log for log in logs if log != victim]
    assert any(task in _tasks(log, "succeeded") for log in survivors), "the killed step was not run again elsewhere"
    restarted = _cli(env, "up", "--workers", "2", "--raw", str(raw))  # brings the killed worker back
    assert restarted.returncode == 0, restarted.stderr
    assert all(services._alive(int(p.read_text())) for p in c.pids.glob("worker*.pid"))


def test_the_sensor_picks_up_a_new_log(cluster):
    import dagster as dg

    _, raw, c, _ = cluster
    started = subprocess.run([str(Path(sys.executable).with_name("dagster")), "sensor", "start", "raw_log_sensor",
                              "-w", str(services.CONFIG / "workspace.yaml")], cwd=REPO, env=c.environment(),
                             text=True, capture_output=True, timeout=300)
    assert started.returncode == 0, started.stderr[-2000:]
    new = raw.parent / "incoming"
    new.mkdir()
    _simulate(new, 4, 1)
    log = next(p for p in new.iterdir() if not p.name.endswith(".json"))
    shutil.copyfile(log, raw / log.name)
    instance = _instance(c)
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        if log.name in instance.get_materialized_partitions(dg.AssetKey("decoded_flight")):
            break
        time.sleep(1)
    assert log.name in instance.get_materialized_partitions(dg.AssetKey("decoded_flight"))
