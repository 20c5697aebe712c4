"""The headless main job's Dagster instance: its SQLite files are written without fsync, and
only its own (another SQLite file in the same process keeps the default)."""

from __future__ import annotations

import dagster as dg
from sqlalchemy import create_engine, text

from pipeline.instance import ensure_dagster_home, unsynced_event_log


def _synchronous(db) -> int:
    with create_engine(f"sqlite:///{db}").connect() as conn:
        return int(conn.execute(text("PRAGMA synchronous")).scalar_one())


def test_the_main_jobs_event_log_is_unsynced_and_nothing_else(tmp_path, monkeypatch):
    monkeypatch.delenv("DAGSTER_HOME", raising=False)
    home = ensure_dagster_home(tmp_path / "data")
    unsynced_event_log(home)
    unsynced_event_log(home)  # a second call adds no second listener

    @dg.asset
    def one() -> dg.MaterializeResult:
        return dg.MaterializeResult(metadata={"n": 1})

    with dg.DagsterInstance.from_config(str(home)) as instance:
        assert dg.materialize([one], instance=instance).success
        assert instance.get_latest_materialization_event(dg.AssetKey("one")) is not None
    runs = sorted(home.rglob("*.db"))
    assert runs and all(_synchronous(db) == 0 for db in runs)  # OFF
    assert _synchronous(tmp_path / "elsewhere.db") == 2  # FULL, SQLite's default
