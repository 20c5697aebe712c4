"""A fleet refresh under a data root decides from what each flight recorded once (the physics
gate's facts in the decoded table's footer), not from every flight's rows: real Parquet files."""

from __future__ import annotations

import polars as pl
import pytest

from quadcore.logs import flight
from quadcore.physics import decoded_store, gate, vehicle
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
    decoded_store.write_decoded(root, low)
    return root


def _counting_reads(monkeypatch) -> list:
    reads: list = []
    real = store.read_parquet

    def counted(path):
        reads.append(path)
        return real(path)

    monkeypatch.setattr(store, "read_parquet", counted)
    return reads


def test_usability_is_decided_from_the_footers_with_the_same_reasons(decoded_root, monkeypatch):
    cf = vehicle.load()
    from_rows = gate.usable_flights(store.read_all_decoded(decoded_root, MAIN_EVENT), cf)
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
        assert gate.PhysicsFacts.from_dict(meta[store.PHYSICS_FACTS]) is not None
        store.write_parquet(df.head(100) if fid == "sim002" else df, store.decoded_path(root, MAIN_EVENT, fid), meta)
    assert decoded_store.recorded_physics_facts(store.decoded_path(root, MAIN_EVENT, "sim002")) is None
    reads = _counting_reads(monkeypatch)
    fl = fleet.fleet_from_store(root, vehicle.load())
    assert len(reads) == 2  # both tables judged from their rows
    assert fl.ids == ["sim000"] and fl.skipped == {"sim002": "100 samples; the physics needs at least 250"}


def test_facts_answer_for_another_vehicles_columns(decoded_root):
    """A vehicle that reads columns the table lacks (motor speeds) is told which, from the facts."""
    path = store.decoded_path(decoded_root, MAIN_EVENT, "sim000")
    facts = gate.PhysicsFacts.from_dict(decoded_store.recorded_physics_facts(path))
    df = store.read_parquet(path)
    for columns in (["t_s", "vbat_V"], [c for c in df.columns if c.startswith("pwm_")] + ["t_s"]):
        assert facts.covers(columns) and facts.problem(columns) == gate.physics_problem(df, columns)


# ---------------------------------------------------------------------------------------
# Term discovery from the flights' stored library statistics
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stats_root(drag_fleet, tmp_path_factory):
    """drag_fleet decoded, with every flight's sufficient and discovery statistics stored (what
    the flight_statistics asset writes)."""
    from quadcore.identify.discovery import library_stats
    from quadcore.identify.stats import sufficient
    from quadcore.spec.model import spec_from

    root = tmp_path_factory.mktemp("stats_root")
    fleet.decode_logs([str(drag_fleet)], out=root)
    for spec in (spec_from(vehicle.load(), []), spec_from(vehicle.load(), ["rotor_drag"])):
        for fid in store.decoded_flights(root, MAIN_EVENT):
            df, source = store.read_decoded(root, MAIN_EVENT, fid), sufficient.decoded_source(root, fid)
            sufficient.save(sufficient.compute_current(spec, fid, df, source), root)
            library_stats.save(library_stats.compute(spec, fid, df, source), root)
    return root


def _discoveries(root, effects, holdout, monkeypatch) -> tuple[dict, dict, list]:
    """(without a data root: every flight's statistics computed from its rows; from the stored
    statistics; the decoded tables read for the second)."""
    from quadcore.spec.model import spec_from
    from quadcore.workflows import identify

    spec = spec_from(vehicle.load(), effects)
    rows = identify.discover(fleet.fleet_from_store(root, spec.vehicle), spec, holdout)
    reads = _counting_reads(monkeypatch)
    stored = identify.discover(fleet.fleet_from_store(root, spec.vehicle), spec, holdout, root=root)
    return rows.to_dict(), stored.to_dict(), reads


@pytest.mark.parametrize("holdout", [["sim003"], []])
def test_discovery_from_stored_statistics_is_discovery_from_rows(stats_root, monkeypatch, holdout):
    rows, stored, reads = _discoveries(stats_root, [], holdout, monkeypatch)
    assert reads == []  # neither usability nor discovery read a decoded table
    assert rows["terms"], "drag_fleet hides rotor drag: discovery finds terms"
    after_rows, after_stored = rows.pop("after"), stored.pop("after")
    assert stored == rows  # terms, coefficients, errors, shares, baseline RMSE: the same sums in the same order
    # the RMSE after the terms is a quadratic form of the Gram matrices instead of a sum over rows
    for key in ("force_rmse_N", "torque_rmse_Nm"):
        assert after_stored[key] == pytest.approx(after_rows[key], rel=1e-10)


def test_discovery_under_a_linear_model_subtracts_its_fit_from_the_stored_sums(stats_root, monkeypatch):
    """Under rotor_drag (fitted from the sufficient statistics), the residual's Gram matrix is
    TᵀGT: the same discovery as from the rows' residual, to rounding."""
    rows, stored, reads = _discoveries(stats_root, ["rotor_drag"], ["sim003"], monkeypatch)
    assert reads == []
    assert [t["expression"] for t in stored["terms"]] == [t["expression"] for t in rows["terms"]]
    for key in ("baseline", "after"):
        for unit in ("force_rmse_N", "torque_rmse_Nm"):
            assert stored[key][unit] == pytest.approx(rows[key][unit], rel=1e-9)
    assert stored["axes"] == rows["axes"] and stored["noise_floor"] == rows["noise_floor"]


def test_discovery_scores_the_samples_the_diagnosis_scores(stats_root, monkeypatch):
    """Under rotor_drag with sim003 held out (the default candidates: motor_lag's 1 s memory), the
    diagnosis scores sim003 after its first block; discovery, from rows and from the stored
    statistics, starts from the same held-out residual on the same samples."""
    from quadcore.identify import diagnosis, evidence
    from quadcore.spec.model import spec_from

    rows, stored, _ = _discoveries(stats_root, ["rotor_drag"], ["sim003"], monkeypatch)
    spec = spec_from(vehicle.load(), ["rotor_drag"])
    tables = fleet.fleet_from_store(stats_root, spec.vehicle).tables
    diagnosed = diagnosis.diagnose(dict(tables), spec, ["sim003"]).to_dict()["baseline"]
    assert evidence.scored_after_blocks(spec) == 1
    for key in ("force_rmse_N", "torque_rmse_Nm"):
        assert rows["baseline"][key] == pytest.approx(diagnosed[key], rel=1e-9)
        assert stored["baseline"][key] == pytest.approx(diagnosed[key], rel=1e-9)


def test_stale_or_cut_statistics_are_computed_from_rows(stats_root, tmp_path, monkeypatch):
    """A flight decoded again from other bytes (another SHA-256 in its footer), whose file is
    cut short, or written in an earlier format (without the sums after the first blocks) is not
    trusted: its rows are read, and the result is unchanged."""
    import dataclasses
    import shutil

    from quadcore.identify.discovery import library_stats
    from quadcore.spec.model import spec_from

    root = tmp_path / "root"
    shutil.copytree(stats_root, root)
    path = library_stats.library_path(root, "sim001")
    path.write_bytes(path.read_bytes()[:-100])
    spec = spec_from(vehicle.load(), [])
    assert library_stats.stored(root, spec)("sim001") is not None  # the header is whole: caught when read
    other_log = dataclasses.replace(library_stats.load(root, "sim002"), source="0" * 64)
    library_stats.save(other_log, root)
    assert library_stats.stored(root, spec)("sim002") is None
    current = library_stats.load(root, "sim000")
    monkeypatch.setattr(library_stats, "FORMAT", library_stats.FORMAT - 1)
    library_stats.save(dataclasses.replace(current, key=library_stats.library_key(spec, "sim000")), root)
    monkeypatch.undo()
    with pytest.raises(library_stats.sufficient.StatsError, match="format"):
        library_stats.load(root, "sim000")
    assert library_stats.stored(root, spec)("sim000") is None
    rows, stored, reads = _discoveries(root, [], ["sim003"], monkeypatch)
    assert sorted(p.parent.name for p in reads) == ["flight=sim000", "flight=sim001", "flight=sim002"]
    rows.pop("after"), stored.pop("after")
    assert stored == rows


def test_the_library_statistics_key_covers_the_modules_that_compute_them():
    """The key of stored discovery statistics hashes the source of the modules that compute them: each is
    found (a renamed or moved one would hash as "missing", and statistics would outlive a change of their
    code), and they are the candidate terms, the Gram matrices and the statistics' own module."""
    import importlib.util
    from pathlib import Path

    from quadcore.identify.discovery import grams, library_stats, terms

    assert {terms.__name__, grams.__name__, library_stats.__name__} <= set(library_stats._MODULES)
    for name in library_stats._MODULES:
        found = importlib.util.find_spec(name)
        assert found is not None and found.origin is not None and Path(found.origin).is_file(), name
