"""Fleet stages read per-flight tables one at a time (store.FlightTables), not all at once:
real Parquet files under a hive-partitioned folder."""

from __future__ import annotations

import polars as pl
import pytest

from quadcore.logs import flight
from quadcore.physics import decoded_store, gate, vehicle
from quadcore.sim import simulation
from quadcore.store import store

MAIN_EVENT = "fixedFrequency"


def _write(root, flight: str, value: float, rows: int = 1000):
    df = pl.DataFrame({"t_s": [i * 0.002 for i in range(rows)], "x_m": [value] * rows})
    return store.write_parquet(df, store.table_path(root, "residuals", flight), {"flight": flight})


def test_tables_are_read_when_looked_up(tmp_path):
    for i, fid in enumerate(["b", "a", "c"]):
        _write(tmp_path, fid, float(i))
    tables = store.flight_tables(tmp_path / "residuals")
    assert list(tables) == ["a", "b", "c"] and len(tables) == 3
    store.table_path(tmp_path, "residuals", "c").unlink()  # listed, not read yet: its loss shows on lookup only
    assert tables["a"]["x_m"][0] == 1.0
    with pytest.raises(FileNotFoundError):
        tables["c"]


def test_the_cache_keeps_recent_tables_up_to_its_budget(tmp_path):
    for fid in ("a", "b"):
        _write(tmp_path, fid, 1.0)
    roomy = store.flight_tables(tmp_path / "residuals")
    tight = store.FlightTables({f: roomy.path(f) for f in roomy}, cache_bytes=1)
    for tables in (roomy, tight):
        tables["a"], tables["b"]
    _write(tmp_path, "a", 2.0)  # changed on disk after both read it
    assert roomy["a"]["x_m"][0] == 1.0  # kept: read once
    assert tight["a"]["x_m"][0] == 2.0  # one table at a time: "a" was dropped when "b" was read
    assert tight.subset(["b"])["b"]["x_m"][0] == 1.0  # a subset keeps what was read of its flights


def test_usable_flights_walks_a_lazy_fleet(tmp_path):
    simulation.simulate_set(tmp_path / "raw", [simulation.SimConfig(kind="random", duration_s=2.0, seed=5)])
    decoded = flight.decode_flight(tmp_path / "raw" / "sim000")
    decoded_store.write_decoded(tmp_path, decoded)
    broken = decoded.tables[MAIN_EVENT].drop("omega_b_x_radps")
    store.write_parquet(broken, store.decoded_path(tmp_path, MAIN_EVENT, "sim001"), {})
    tables = store.read_all_decoded(tmp_path, MAIN_EVENT)
    usable, skipped = gate.usable_flights(tables, vehicle.load())
    assert usable == ["sim000"] and list(skipped) == ["sim001"] and "omega_b_x_radps" in skipped["sim001"]
    assert tables.subset(usable)["sim000"].equals(decoded.tables[MAIN_EVENT])
