"""Issue 22: flight ids unique per data root (collisions resolved the same way whatever the
listing order, and reported), and each log used once (copies, same SHA-256, skipped with the
reason), so that no flight trains a model scored on a copy of itself."""

from __future__ import annotations

import contextlib
import io
import itertools
import shutil

import pytest

from quadcore import cli
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.store import store
from quadcore.workflows import fleet


def test_a_name_equal_to_another_files_stand_in_gets_its_own_id(tmp_path, make_synthetic_log):
    stand_in = flight.flight_id_of(tmp_path / "a b")
    assert stand_in == "a_b-c8687a08"  # the case of the issue: exactly the other file's safe stand-in
    (tmp_path / "a b").write_bytes(make_synthetic_log(name="s1", seed=1).data)
    (tmp_path / stand_in).write_bytes(make_synthetic_log(name="s2", seed=2).data)
    paths = [tmp_path / "a b", tmp_path / stand_in]
    results = [flight.flight_ids(order) for order in itertools.permutations(paths)]
    ids, notes = results[0]
    assert all(r == results[0] for r in results)  # independent of the listing order
    assert len(ids) == 2 and ids[stand_in] == tmp_path / stand_in  # the file named so keeps its name
    other = next(f for f in ids if f != stand_in)
    assert ids[other] == tmp_path / "a b" and other.startswith(stand_in + "+")
    assert len(notes) == 1 and other in notes[0]
    for fid, path in ids.items():  # and each id leads back to its file
        assert flight.find_log(tmp_path, fid) == path


def test_cli_decode_keeps_both_flights_and_reports_the_collision(tmp_path, make_synthetic_log):
    """Today one of the two overwrites the other's decoded tables."""
    raw, out = tmp_path / "raw", tmp_path / "out"
    raw.mkdir()
    a, b = make_synthetic_log(name="s1", seed=1), make_synthetic_log(name="s2", seed=2, n_fast=50)
    (raw / "a b").write_bytes(a.data)
    (raw / "a_b-c8687a08").write_bytes(b.data)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert cli.main(["decode", str(raw), "--out", str(out)]) == 0
    decoded = sorted((out / "decoded" / "fast").glob("flight=*/data.parquet"))
    assert len(decoded) == 2
    rows = sorted(store.read_parquet(p).height for p in decoded)
    assert rows == sorted([a.rows()["fast"], b.rows()["fast"]])
    assert "flight id collision" in stdout.getvalue()


def test_two_folders_with_the_same_file_name_get_two_ids(tmp_path, make_synthetic_log):
    for k in (1, 2):
        (tmp_path / f"d{k}").mkdir()
        (tmp_path / f"d{k}" / "log").write_bytes(make_synthetic_log(name=f"s{k}", seed=k).data)
    ids, notes = flight.flight_ids([tmp_path / "d2" / "log", tmp_path / "d1" / "log"])
    assert ids["log"] == tmp_path / "d1" / "log" and len(ids) == 2 and len(notes) == 1


@pytest.fixture(scope="module")
def with_copy(real_logs, tmp_path_factory):
    """Three real logs and a byte-identical copy of the held-out jana02 as jana99."""
    folder = tmp_path_factory.mktemp("raw")
    for name in ("jana02", "jana03", "jana11"):
        shutil.copyfile(real_logs / name, folder / name)
    shutil.copyfile(real_logs / "jana02", folder / "jana99")
    return folder


def test_a_copy_of_the_held_out_flight_is_not_a_training_flight(with_copy):
    """Today jana99 (jana02's bytes) is fitted on while jana02 is held out."""
    from quadcore.spec.model import spec_from
    from quadcore.workflows import identify

    warned: list[str] = []
    veh = vehicle.load(None)
    flights = fleet.fleet_from_logs([str(with_copy)], veh, warned.append)
    assert flights.ids == ["jana02", "jana03", "jana11"]
    assert flights.skipped["jana99"].startswith("duplicate of jana02")
    assert any(w.startswith("jana99 skipped: duplicate of jana02") for w in warned)
    fitted = identify.fit(flights, spec_from(veh, []), ["jana02"])  # jana02 held out, as the issue's
    assert fitted.trained_on == ("jana03", "jana11")


def test_the_data_root_skips_the_copy_too(with_copy, tmp_path):
    """The assets' path: decoded tables under a data root, judged from their footers."""
    said: list[str] = []
    flights, _ = fleet.decode_logs([str(with_copy)], tmp_path, said.append)
    assert any(m.startswith("jana99: duplicate of jana02") for m in said)  # reported when decoded
    fl = fleet.fleet_from_store(tmp_path, vehicle.load(None))
    assert fl.ids == ["jana02", "jana03", "jana11"] and "jana99" in fl.skipped
    assert len(flights) == 4  # decoded (and reported), just not used twice


def test_the_learning_stage_leaves_the_copy_out_of_its_feature_tables(with_copy, tmp_path):
    """The main job computes every flight's residual table, the copy's too; the learning stage
    builds its training tables from them (today jana99, a copy of the held-out jana02, was one)."""
    from quadcore.learn import features as feat
    from quadcore.physics import residuals
    from quadcore.workflows import learn

    flights, _ = fleet.decode_logs([str(with_copy)], tmp_path)
    veh = vehicle.load(None)
    for fl in flights:
        store.write_parquet(residuals.residual_table(fl.tables["fixedFrequency"], veh),
                            store.table_path(tmp_path, "residuals", fl.flight_id),
                            {"flight": fl.flight_id, "model": {"label": "nominal"}})
    sets, n = learn.build_features(tmp_path, ["vel_rate"])
    assert n == 3
    _, tables = feat.read_feature_tables(tmp_path)
    assert sorted(tables["vel_rate"]) == ["jana02", "jana03", "jana11"]
