"""``python -m pipeline.cluster up|run|down|status``: see :mod:`pipeline.cluster`."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from pipeline.cluster import services


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.cluster", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    start = sub.add_parser("up", help="start PostgreSQL, Redis, the S3 store, Celery workers, daemon and webserver")
    start.add_argument("--workers", type=int, default=int(os.environ.get("QUADCORE_CLUSTER_WORKERS", "2")))
    start.add_argument("--raw", type=Path, default=Path(os.environ.get("QUADCORE_RAW_DIR", "data/raw")),
                       help="the shared folder of raw logs the sensor watches (default data/raw)")
    sub.add_parser("run", help="the main job (python -m pipeline) with its runs on the cluster")
    stop = sub.add_parser("down", help="stop every service")
    stop.add_argument("--purge", action="store_true", help="also delete the cluster's folder (its database, store)")
    sub.add_parser("status", help="the services and where they listen")
    args = parser.parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except services.ClusterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _up(args) -> int:
    if args.workers < 1:
        print("error: --workers: at least 1", file=sys.stderr)
        return 2
    print(f"Starting the local cluster in {services.cluster_dir().home} ...")
    c = services.up(args.raw, args.workers)
    s = c.settings()
    print(f"UI: {s['QUADCORE_CLUSTER_URL']}   raw logs: {s['QUADCORE_RAW_DIR']}   outputs: {s['QUADCORE_DATA_ROOT']}"
          f" (S3 at {s['AWS_ENDPOINT_URL']})\nIts settings: . {c.env_file}   then: make cluster-run")
    return 0


def _run(_args) -> int:
    c = services.cluster_dir()
    if not c.settings():
        print("error: no cluster here: start it with `make cluster-up`", file=sys.stderr)
        return 2
    return subprocess.call([sys.executable, "-m", "pipeline"], env=c.environment())


def _down(args) -> int:
    services.down()
    c = services.cluster_dir()
    if args.purge and c.home.is_dir():
        shutil.rmtree(c.home)
        print(f"  removed {c.home}")
    return 0


def _status(_args) -> int:
    c = services.cluster_dir()
    s = c.settings()
    if not s:
        print("no cluster here")
        return 1
    for pidfile in sorted(c.pids.glob("*.pid")):
        alive = services._alive(int(pidfile.read_text()))
        print(f"  {pidfile.stem:10s} {'running' if alive else 'STOPPED'}")
    print(f"  UI {s['QUADCORE_CLUSTER_URL']}, PostgreSQL 127.0.0.1:{s['QUADCORE_CLUSTER_PG_PORT']}, "
          f"Redis 127.0.0.1:{s['QUADCORE_CLUSTER_REDIS_PORT']}, S3 {s['AWS_ENDPOINT_URL']}")
    return 0


_COMMANDS = {"up": _up, "run": _run, "down": _down, "status": _status}

if __name__ == "__main__":
    sys.exit(main())
