"""The local cluster's services: start, check and stop them.

One folder of its own (``QUADCORE_CLUSTER_DIR``, default ``.cluster`` in the working directory)
holds everything they write apart from the object store's contents: PostgreSQL's data, Redis's
working folder, the Dagster home, the logs, the process ids and ``env``, the settings every
process of the cluster (and a user's shell: ``. .cluster/env``) shares. Every service binds
127.0.0.1 on a port chosen free at the first ``up`` and kept in ``env``.

=================  ==========================================================================
service            what it is for
=================  ==========================================================================
PostgreSQL         the Dagster instance (runs, event logs, sensor cursors): ``dagster-postgres``
Redis              the Celery broker and result backend
moto's S3 server   the object store: ``QUADCORE_DATA_ROOT=s3://quadcore/data``
Celery workers     execute the runs' steps (``dagster-celery worker``), ``--workers`` of them
dagster-daemon     drains the run queue, runs the sensors, retries failed runs
dagster-webserver  the UI, and the GraphQL endpoint the main job submits its runs to
=================  ==========================================================================
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import dagster as dg

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "deploy" / "local"
BUCKET = "quadcore"
# A start-up that takes longer than this (webserver: loading the definitions) is a failure.
START_TIMEOUT_S = 180.0
STOP_TIMEOUT_S = 20.0


# The Celery app's settings, the same for the run workers that send steps and the Celery workers
# that execute them. A step's task is acknowledged when it ends, not when a worker takes it, one
# at a time: a worker killed mid-step leaves its task in Redis, which hands it to another worker
# once the visibility timeout has passed, and the run goes on.
CELERY_SETTINGS = {
    "task_acks_late": True,
    "task_reject_on_worker_lost": True,
    "worker_prefetch_multiplier": 1,
    "broker_transport_options": {"visibility_timeout": 30},
    "result_expires": 86400,
}


# The daemon beats every few seconds; a run coordinator silent for longer is not running, and a
# queued run would wait for it for ever.
DAEMON_SILENT_S = 120.0


def daemon_beat(instance: dg.DagsterInstance) -> float | None:
    """When the daemon's run coordinator (the loop that launches queued runs) last beat, in
    seconds since the epoch; None when it never has."""
    beat = instance.get_daemon_heartbeats().get("QUEUED_RUN_COORDINATOR")
    return None if beat is None else float(beat.timestamp)


def celery_config(broker: str, backend: str) -> dict:
    """The ``celery_executor`` config (and ``dagster-celery worker -y``'s) for this broker."""
    return {"broker": broker, "backend": backend, "config_source": CELERY_SETTINGS}


class ClusterError(RuntimeError):
    """A service that cannot start or be reached (one line for the user)."""


@dataclass(frozen=True)
class Cluster:
    """The cluster's folder and the settings kept in its ``env`` file."""

    home: Path

    @property
    def env_file(self) -> Path:
        return self.home / "env"

    @property
    def logs(self) -> Path:
        return self.home / "logs"

    @property
    def pids(self) -> Path:
        return self.home / "pids"

    def settings(self) -> dict[str, str]:
        """The ``env`` file as a dict (empty before the first ``up``)."""
        if not self.env_file.is_file():
            return {}
        pairs = (line.removeprefix("export ").split("=", 1) for line in self.env_file.read_text().splitlines()
                 if "=" in line and not line.startswith("#"))
        return {k: v.strip("'") for k, v in pairs}

    def environment(self) -> dict[str, str]:
        """This process's environment with the cluster's settings on top, and this Python's
        scripts first on PATH (``dagster-celery`` starts ``celery`` from PATH)."""
        path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
        return {**os.environ, **self.settings(), "PATH": path}


def cluster_dir() -> Cluster:
    return Cluster(Path(os.environ.get("QUADCORE_CLUSTER_DIR", ".cluster")).resolve())


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _postgres_bin(name: str) -> str:
    """``initdb``/``pg_ctl``/``createdb`` of the installed PostgreSQL (Debian keeps them out of PATH)."""
    for folder in sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (folder / name).is_file():
            return str(folder / name)
    found = shutil.which(name)
    if not found:
        raise ClusterError(f"PostgreSQL's {name} is not installed (Debian: apt-get install postgresql)")
    return found


def _as_postgres_user(cmd: list[str]) -> list[str]:
    """PostgreSQL refuses to run as root: as root, run its commands as the ``postgres`` user."""
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


def write_settings(c: Cluster, raw_dir: Path, workers: int) -> dict[str, str]:
    """The cluster's ``env`` (ports chosen free now; kept for later ``up``s)."""
    old = c.settings()
    pg, redis, s3, web = (old.get(k) or str(free_port()) for k in (
        "QUADCORE_CLUSTER_PG_PORT", "QUADCORE_CLUSTER_REDIS_PORT", "QUADCORE_CLUSTER_S3_PORT",
        "QUADCORE_CLUSTER_WEB_PORT"))
    password = old.get("QUADCORE_CLUSTER_PG_PASSWORD") or secrets.token_hex(16)
    settings = {
        "QUADCORE_CLUSTER_DIR": str(c.home),
        "QUADCORE_CLUSTER_PG_PORT": pg,
        "QUADCORE_CLUSTER_PG_PASSWORD": password,
        "QUADCORE_CLUSTER_PG_URL": f"postgresql+psycopg2://quadcore:{password}@127.0.0.1:{pg}/dagster",
        "QUADCORE_CLUSTER_REDIS_PORT": redis,
        "QUADCORE_CLUSTER_S3_PORT": s3,
        "QUADCORE_CLUSTER_WEB_PORT": web,
        "QUADCORE_CLUSTER_WORKERS": str(workers),
        "QUADCORE_CLUSTER_URL": f"http://127.0.0.1:{web}",
        "DAGSTER_HOME": str(c.home / "dagster"),
        "QUADCORE_EXECUTOR": "celery",
        # every process of the cluster sees the sensors' default status alike (a sensor started
        # or stopped from a shell records it only where its default differs)
        "QUADCORE_AUTOMATION": os.environ.get("QUADCORE_AUTOMATION", "on"),
        "QUADCORE_CELERY_BROKER": f"redis://127.0.0.1:{redis}/0",
        "QUADCORE_CELERY_BACKEND": f"redis://127.0.0.1:{redis}/1",
        "QUADCORE_DATA_ROOT": f"s3://{BUCKET}/data",
        "QUADCORE_RAW_DIR": str(raw_dir.resolve()),
        "AWS_ENDPOINT_URL": f"http://127.0.0.1:{s3}",
        "AWS_ACCESS_KEY_ID": "quadcore-local",
        "AWS_SECRET_ACCESS_KEY": "quadcore-local",
        "AWS_DEFAULT_REGION": "us-east-1",
        # nothing of the cluster reaches outside this machine
        "NO_PROXY": "127.0.0.1,localhost",
    }
    c.home.mkdir(parents=True, exist_ok=True)
    lines = ["# The local cluster's settings: `. .cluster/env` in a shell uses it (written by `make cluster-up`)."]
    lines += [f"export {k}='{v}'" for k, v in settings.items()]
    tmp = c.env_file.with_suffix(".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.chmod(0o600)
    tmp.replace(c.env_file)
    return settings


def _wait(check, what: str, log: Path, timeout: float = START_TIMEOUT_S, pidfile: Path | None = None) -> None:
    """Until ``check()`` holds; a :class:`ClusterError` with the log's last lines when the
    process in ``pidfile`` ends first or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        if pidfile is not None and not _alive(int(pidfile.read_text())):
            timeout = 0.0
            break
        time.sleep(0.5)
    tail = log.read_text(errors="replace").splitlines()[-5:] if log.is_file() else []
    when = f" within {timeout:.0f} s" if timeout else " (it ended)"
    raise ClusterError(f"{what} did not start{when} (log {log}): " + " | ".join(tail))


def _port_open(port: int) -> bool:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.settimeout(0.5)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def start_postgres(c: Cluster, s: dict[str, str]) -> None:
    """Initialise (first time) and start PostgreSQL on 127.0.0.1, password-protected."""
    data = c.home / "postgres"
    sockets = c.home / "run"
    sockets.mkdir(exist_ok=True)
    log = c.logs / "postgres.log"
    if os.geteuid() == 0:
        reach = subprocess.run(["runuser", "-u", "postgres", "--", "test", "-x", str(c.home)], capture_output=True)
        if reach.returncode != 0:
            raise ClusterError(f"PostgreSQL runs as the user postgres, which cannot reach {c.home}: choose a "
                               "QUADCORE_CLUSTER_DIR whose every parent folder others may enter (mode o+x)")
        for path in (sockets, c.logs):
            shutil.chown(path, "postgres")
    if not (data / "PG_VERSION").is_file():
        data.mkdir(parents=True, exist_ok=True)
        pwfile = c.home / "pgpass.tmp"
        pwfile.write_text(s["QUADCORE_CLUSTER_PG_PASSWORD"] + "\n")
        if os.geteuid() == 0:
            shutil.chown(data, "postgres")
            shutil.chown(pwfile, "postgres")
        try:
            _run(_as_postgres_user([_postgres_bin("initdb"), "-D", str(data), "-U", "quadcore",
                                    "--auth=scram-sha-256", f"--pwfile={pwfile}", "--encoding=UTF8"]), c, "initdb")
        finally:
            pwfile.unlink(missing_ok=True)
    port = int(s["QUADCORE_CLUSTER_PG_PORT"])
    if not _port_open(port):
        _run(_as_postgres_user([_postgres_bin("pg_ctl"), "-D", str(data), "-l", str(log), "-w", "-t", "120", "-o",
                                f"-c listen_addresses=127.0.0.1 -p {port} -k {sockets}", "start"]), c, "pg_ctl start")
    env = {**os.environ, "PGPASSWORD": s["QUADCORE_CLUSTER_PG_PASSWORD"]}
    exists = subprocess.run([_postgres_bin("psql"), "-h", "127.0.0.1", "-p", str(port), "-U", "quadcore", "-d",
                             "postgres", "-tAc", "SELECT 1 FROM pg_database WHERE datname='dagster'"],
                            env=env, capture_output=True, text=True)
    if exists.stdout.strip() != "1":
        _run([_postgres_bin("createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "quadcore", "dagster"], c,
             "createdb", env=env)


def _run(cmd: list[str], c: Cluster, what: str, env: dict[str, str] | None = None) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=c.home)
    if done.returncode != 0:
        raise ClusterError(f"{what} failed: {(done.stderr or done.stdout).strip().splitlines()[-1:]}")


def start_redis(c: Cluster, s: dict[str, str]) -> None:
    """Redis on 127.0.0.1, no persistence (the broker's queue lives as long as the cluster)."""
    exe = shutil.which("redis-server")
    if not exe:
        raise ClusterError("redis-server is not installed (Debian: apt-get install redis-server)")
    port = int(s["QUADCORE_CLUSTER_REDIS_PORT"])
    if _port_open(port):
        return
    folder = c.home / "redis"
    folder.mkdir(exist_ok=True)
    _run([exe, "--bind", "127.0.0.1", "--port", str(port), "--daemonize", "yes", "--dir", str(folder),
          "--pidfile", str(c.pids / "redis.pid"), "--logfile", str(c.logs / "redis.log"), "--save", "",
          "--appendonly", "no", "--protected-mode", "yes"], c, "redis-server")
    _wait(lambda: _port_open(port), "Redis", c.logs / "redis.log")


def spawn(c: Cluster, name: str, cmd: list[str], env: dict[str, str]) -> bool:
    """A service in a process group of its own (so ``down`` ends it with everything it started),
    its output in ``logs/<name>.log`` and its pid in ``pids/<name>.pid``. False when it was
    running already (nothing started)."""
    pidfile = c.pids / f"{name}.pid"
    if pidfile.is_file() and _alive(int(pidfile.read_text())):
        return False
    with open(c.logs / f"{name}.log", "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                cwd=REPO, start_new_session=True)
    pidfile.write_text(str(proc.pid))
    return True


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    return True


def start_store(c: Cluster, s: dict[str, str], env: dict[str, str]) -> None:
    """moto's S3 server on 127.0.0.1 and the bucket the data root lives in."""
    port = int(s["QUADCORE_CLUSTER_S3_PORT"])
    spawn(c, "s3", [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)], env)
    # Up once it answers a request (the bucket listing), not once its port is open: under load its
    # first request, sent as the port opened, was closed unanswered and failed `up` (26 Nov).
    _wait(lambda: _http_ok(f"{s['AWS_ENDPOINT_URL']}/"), "the S3 server", c.logs / "s3.log",
          pidfile=c.pids / "s3.pid")
    import boto3  # type: ignore[import-untyped]  # moto's dependency; only the cluster needs it

    client = boto3.client("s3", endpoint_url=s["AWS_ENDPOINT_URL"], aws_access_key_id=s["AWS_ACCESS_KEY_ID"],
                          aws_secret_access_key=s["AWS_SECRET_ACCESS_KEY"], region_name=s["AWS_DEFAULT_REGION"])
    if BUCKET not in {b["Name"] for b in client.list_buckets().get("Buckets", [])}:
        client.create_bucket(Bucket=BUCKET)


def dagster_home(c: Cluster) -> Path:
    """The Dagster home with deploy/local/dagster.yaml (copied afresh at each ``up``)."""
    home = c.home / "dagster"
    home.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(CONFIG / "dagster.yaml", home / "dagster.yaml")
    return home


def start_workers(c: Cluster, s: dict[str, str], env: dict[str, str], workers: int) -> None:
    """``workers`` Celery workers, one step at a time each (``--concurrency 1``): the number of
    workers is the number of steps run at once."""
    config = c.home / "celery.yaml"  # JSON is YAML
    config.write_text(json.dumps({"execution": {"config": celery_config(s["QUADCORE_CELERY_BROKER"],
                                                                        s["QUADCORE_CELERY_BACKEND"])}}))
    names = [f"worker{i}" for i in range(1, workers + 1)]
    logs = {name: c.logs / f"{name}.log" for name in names}
    # A worker's log is appended to: a worker started again (after a kill) is ready once its new
    # part says so, not the "ready." of its earlier life.
    seen = {name: _size(log) for name, log in logs.items()}
    started = [name for name in names if spawn(c, name, [
        str(Path(sys.executable).with_name("dagster-celery")), "worker", "start", "-A", "dagster_celery.app",
        "-n", f"quadcore-{name}", "-y", str(config), "--", "--concurrency", "1"], env)]
    for name in started:  # Celery prints "ready." once it consumes from the broker
        _wait(lambda name=name: "ready." in _text_after(logs[name], seen[name]), f"Celery {name}", logs[name],
              pidfile=c.pids / f"{name}.pid")


def start_dagster(c: Cluster, s: dict[str, str], env: dict[str, str]) -> None:
    """The daemon (queue, sensors, run retries) and the webserver (UI and GraphQL); up once the
    daemon's run coordinator beats."""
    workspace = str(CONFIG / "workspace.yaml")
    bindir = Path(sys.executable).parent
    # the instance's tables first: the daemon and the webserver would both create them at once
    _run([str(bindir / "dagster"), "instance", "migrate"], c, "dagster instance migrate", env=env)
    t0 = time.time()
    new_daemon = spawn(c, "daemon", [str(bindir / "dagster-daemon"), "run", "-w", workspace], env)
    port = int(s["QUADCORE_CLUSTER_WEB_PORT"])
    spawn(c, "webserver", [str(bindir / "dagster-webserver"), "-h", "127.0.0.1", "-p", str(port), "-w", workspace],
          env)
    _wait(lambda: _http_ok(f"{s['QUADCORE_CLUSTER_URL']}/server_info"), "dagster-webserver",
          c.logs / "webserver.log", pidfile=c.pids / "webserver.pid")
    wait_for_run_queue(c, since=t0 if new_daemon else None)


def wait_for_run_queue(c: Cluster, since: float | None) -> None:
    """Until the daemon's run coordinator has beaten after ``since`` (a daemon started then), or
    within :data:`DAEMON_SILENT_S` (``since`` None: one already running): the heartbeat
    :func:`pipeline.cluster.launch.check_daemon` reads before it accepts a queued run. The daemon loads the code
    before its loops start (a minute after the webserver answers on a loaded machine), and a
    heartbeat left in the instance by an earlier daemon is no sign of this one."""
    settings = c.settings()
    with _environ({k: settings[k] for k in ("DAGSTER_HOME", "QUADCORE_CLUSTER_PG_URL")}), \
            dg.DagsterInstance.get() as instance:
        def beaten() -> bool:
            beat = daemon_beat(instance)
            after = time.time() - DAEMON_SILENT_S if since is None else since
            return beat is not None and beat >= after

        _wait(beaten, "dagster-daemon's run queue (its first heartbeat)", c.logs / "daemon.log",
              pidfile=c.pids / "daemon.pid")


@contextlib.contextmanager
def _environ(values: dict[str, str]):
    """This process's environment with ``values`` set, restored after."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else 0


def _text_after(log: Path, offset: int) -> str:
    """What ``log`` gained after its first ``offset`` bytes."""
    with open(log, "rb") as f:
        f.seek(offset)
        return f.read().decode(errors="replace")


def _http_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return bool(response.status == 200)
    except OSError:
        return False


def up(raw_dir: Path, workers: int, log=print) -> Cluster:
    """Start every service (those already running are left as they are)."""
    c = cluster_dir()
    for folder in (c.home, c.logs, c.pids):
        folder.mkdir(parents=True, exist_ok=True)
    raw_dir.mkdir(parents=True, exist_ok=True)
    s = write_settings(c, raw_dir, workers)
    env = c.environment()
    dagster_home(c)
    steps = [("PostgreSQL", lambda: start_postgres(c, s)), ("Redis", lambda: start_redis(c, s)),
             ("S3 store (moto)", lambda: start_store(c, s, env)),
             (f"{workers} Celery worker(s)", lambda: start_workers(c, s, env, workers)),
             ("dagster-daemon and dagster-webserver", lambda: start_dagster(c, s, env))]
    for what, start in steps:
        t0 = time.perf_counter()
        start()
        log(f"  {what}: up ({time.perf_counter() - t0:.1f} s)")
    return c


def down(log=print) -> None:
    """Stop every service: process groups first (TERM, then KILL after :data:`STOP_TIMEOUT_S`),
    then PostgreSQL (fast shutdown) and Redis. The cluster's folder is kept (``--purge`` removes it)."""
    c = cluster_dir()
    if not c.home.is_dir():
        log("no cluster here (nothing to stop)")
        return
    for pidfile in sorted(c.pids.glob("*.pid")) if c.pids.is_dir() else []:
        if pidfile.stem == "redis":
            continue
        _stop_group(int(pidfile.read_text()))
        pidfile.unlink(missing_ok=True)
        log(f"  {pidfile.stem}: stopped")
    redis = c.pids / "redis.pid"
    if redis.is_file():
        _stop_group(int(redis.read_text()), group=False)
        redis.unlink(missing_ok=True)
        log("  Redis: stopped")
    data = c.home / "postgres"
    if (data / "postmaster.pid").is_file():
        subprocess.run(_as_postgres_user([_postgres_bin("pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"]),
                       capture_output=True)
        log("  PostgreSQL: stopped")


def _stop_group(pid: int, group: bool = True) -> None:
    """TERM, then after :data:`STOP_TIMEOUT_S` (or once ``pid`` is gone) KILL to whatever of its
    group is left; returns once ``pid`` is gone (or :data:`STOP_TIMEOUT_S` after the KILL)."""
    kill = os.killpg if group else os.kill
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            kill(pid, sig)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        while time.monotonic() < deadline and _alive(pid):
            time.sleep(0.2)
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, os.WNOHANG)
