"""The headless main job's Dagster instance: its SQLite files are written without fsync, and
only its own (another SQLite file in the same process keeps the default)."""

from __future__ import annotations

import dagster as dg
from sqlalchemy import create_engine, text

from pipeline.run.instance import ensure_dagster_home, unsynced_event_log


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


def test_an_object_store_data_root_keeps_its_dagster_home_on_this_machine(tmp_path, monkeypatch):
    """``QUADCORE_DATA_ROOT=s3://...`` without ``DAGSTER_HOME``: the instance is a local folder
    named after the URL (as the main job's lock is), never an ``s3:`` folder made in the working
    directory from the URL's text."""
    from quadcore.store import store

    monkeypatch.setenv("DAGSTER_HOME", "unset-below")
    monkeypatch.delenv("DAGSTER_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    home = ensure_dagster_home(store.as_root("s3://lab/quadcore"))
    assert list(work.iterdir()) == []
    assert home.is_relative_to(tmp_path / "home") and (home / "dagster.yaml").is_file()
    monkeypatch.delenv("DAGSTER_HOME")  # as a new process would start
    assert ensure_dagster_home(store.as_root("s3://lab/quadcore")) == home  # the same instance next time
    monkeypatch.delenv("DAGSTER_HOME")
    assert ensure_dagster_home(store.as_root("s3://lab/other")) != home


def test_a_write_of_dagster_yaml_cut_short_leaves_no_partial_file(tmp_path, monkeypatch):
    """A kill while dagster.yaml is written must not leave half a config that every later run
    fails to parse: it is written to a temp file and renamed."""
    from pathlib import Path

    monkeypatch.delenv("DAGSTER_HOME", raising=False)
    real = Path.write_text

    def cut_short(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2], *args, **kwargs)
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(Path, "write_text", cut_short)
    try:
        ensure_dagster_home(tmp_path / "data")
    except KeyboardInterrupt:
        pass
    monkeypatch.setattr(Path, "write_text", real)
    assert not (tmp_path / "data" / ".dagster" / "dagster.yaml").exists()
    home = ensure_dagster_home(tmp_path / "data")
    assert (home / "dagster.yaml").read_text().endswith("enabled: false\n")
