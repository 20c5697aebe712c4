"""The persistent Dagster instance that ``make run`` and ``make ui`` share."""

import hashlib
import os
import sqlite3
from pathlib import Path

from sqlalchemy import event
from sqlalchemy.engine import Engine

from quadcore.store import store

# Two cores: at most two runs at once; the others wait in the queue (``dg dev`` and the daemon
# use the queued run coordinator). SQLite storage also locks under more concurrent writers.
DAGSTER_YAML = """\
# Written by quadcore (`make run` / `make ui`). Two cores: at most two runs at once, the rest queue.
concurrency:
  runs:
    max_concurrent_runs: 2
telemetry:
  enabled: false
"""


def ensure_dagster_home(root: Path) -> Path:
    """Use ``$DAGSTER_HOME`` or ``<root>/.dagster``; create it with our dagster.yaml if it has none
    (written by rename: a kill never leaves half of it). The instance stays on this machine: for
    an object-store root (``s3://...``) the default is ``~/.quadcore/dagster-<digest of the URL>``."""
    if os.environ.get("DAGSTER_HOME"):
        home = Path(os.environ["DAGSTER_HOME"]).resolve()
    elif store.is_remote(store.as_root(root)):
        digest = hashlib.sha256(str(root).encode()).hexdigest()[:16]
        home = Path.home() / ".quadcore" / f"dagster-{digest}"
    else:
        home = (Path(root) / ".dagster").resolve()
    home.mkdir(parents=True, exist_ok=True)
    if not (home / "dagster.yaml").exists():
        store.write_text(DAGSTER_YAML, home / "dagster.yaml")
    os.environ["DAGSTER_HOME"] = str(home)
    return home


# Dagster homes whose SQLite files this process writes without fsync (see unsynced_event_log).
_UNSYNCED_HOMES: set[str] = set()


def unsynced_event_log(home: Path) -> None:
    """Dagster's SQLite files under ``home`` written without fsync (``PRAGMA synchronous=OFF``)
    for the rest of this process. Dagster opens a connection per event and checkpoints the
    write-ahead log when it closes it: about ten fsyncs per event, two thirds of the cost of a
    run of 19 flight partitions here. Without them a killed job still loses nothing (SQLite
    hands every commit to the OS); only an OS crash or a power cut during a run could lose or
    corrupt its run records, as it could our own files (written by rename, not fsynced either).
    For the headless main job; the UI and its daemon keep SQLite's default."""
    _UNSYNCED_HOMES.add(str(home.resolve()) + os.sep)
    if not event.contains(Engine, "connect", _unsynced_if_in_home):
        event.listen(Engine, "connect", _unsynced_if_in_home)


def unsynced_homes() -> set[str]:
    """The homes :func:`unsynced_event_log` was called for in this process (a second process of
    the main job writes the same way)."""
    return set(_UNSYNCED_HOMES)


def _unsynced_if_in_home(dbapi_connection, _record) -> None:
    if not isinstance(dbapi_connection, sqlite3.Connection):
        return
    cursor = dbapi_connection.cursor()
    try:
        files = [row[2] or "" for row in cursor.execute("PRAGMA database_list")]
        if files and any(files[0].startswith(home) for home in _UNSYNCED_HOMES):
            cursor.execute("PRAGMA synchronous=OFF")
    finally:
        cursor.close()
