"""A fleet refresh under a data root decides from what each flight recorded once (the physics
gate's facts in the decoded table's footer), not from every flight's rows: real Parquet files."""

from __future__ import annotations

import polars as pl
import pytest

from quadcore.logs import checks, flight
from quadcore.physics import vehicle
from quadcore.store import store
from quadcore.workflows import fleet

MAIN_EVENT = store.MAIN_EVENT


@pytest.fixture(scope="module")
def decoded_root(drag_fleet, tmp_path_factory):
    """drag_fleet decoded under a data root, with sim001's battery voltage logged below 2.5 V
    in 7 rows (unusable: the thrust map cannot use it)."""
    root = tmp_path_factory.mktemp("root")
    fleet.decode_logs([str(drag_fleet)], out=root)
    low = flight.decode_flight(drag_fleet / "sim001")
    main = low.tables[MAIN_EVENT]
    low.tables[MAIN_EVENT] = main.with_columns(
        pl.when(pl.int_range(pl.len()) < 7).then(2.0).otherwise(pl.col("vbat_V")).alias("vbat_V"))
    store.write_decoded(root, low)
    return root


def _counting_reads(monkeypatch) -> list:
    reads: list = []
    real = store.read_parquet
    monkeypatch.setattr(store, "read_parquet", lambda path: reads.append(path) or real(path))
    return reads


def test_usability_is_decided_from_the_footers_with_the_same_reasons(decoded_root, monkeypatch):
    cf = vehicle.load()
    from_rows = checks.usable_flights(store.read_all_decoded(decoded_root, MAIN_EVENT), cf)
    reads = _counting_reads(monkeypatch)
    fl = fleet.fleet_from_store(decoded_root, cf)
    assert reads == []  # no decoded table read
    assert (fl.ids, fl.skipped) == from_rows
    assert fl.skipped == {"sim001": "battery voltage below 2.5 V in 7 rows: the thrust map cannot use it"}
    assert fl.ids == ["sim000", "sim002", "sim003"]


def test_a_table_rewritten_with_copied_metadata_is_read_again(decoded_root, tmp_path, monkeypatch):
    """Facts describe the rows written with them: a table rewritten elsewhere with its metadata
    copied (here: rows cut to 100) loses them, and is judged from its rows."""
    root = tmp_path / "copy"
    for fid in ("sim000", "sim002"):
        path = store.decoded_path(decoded_root, MAIN_EVENT, fid)
        df, meta = store.read_parquet(path), store.read_metadata(path)
        assert checks.PhysicsFacts.from_dict(meta[store.PHYSICS_FACTS]) is not None
        store.write_parquet(df.head(100) if fid == "sim002" else df, store.decoded_path(root, MAIN_EVENT, fid), meta)
    assert store.recorded_physics_facts(store.decoded_path(root, MAIN_EVENT, "sim002")) is None
    reads = _counting_reads(monkeypatch)
    fl = fleet.fleet_from_store(root, vehicle.load())
    assert len(reads) == 2  # both tables judged from their rows
    assert fl.ids == ["sim000"] and fl.skipped == {"sim002": "100 samples; the physics needs at least 250"}


def test_facts_answer_for_another_vehicles_columns(decoded_root):
    """A vehicle that reads columns the table lacks (motor speeds) is told which, from the facts."""
    path = store.decoded_path(decoded_root, MAIN_EVENT, "sim000")
    facts = checks.PhysicsFacts.from_dict(store.recorded_physics_facts(path))
    df = store.read_parquet(path)
    for columns in (["t_s", "vbat_V"], [c for c in df.columns if c.startswith("pwm_")] + ["t_s"]):
        assert facts.covers(columns) and facts.problem(columns) == checks.physics_problem(df, columns)
