"""Hostile input: nothing a log or a file name holds can write outside the data root, repeated
names lose nothing, crafted headers fail fast, unreadable files and bad arguments are one line."""

from __future__ import annotations

import contextlib
import io
import os
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from conftest import FAST, SLOW

from quadcore import cli
from quadcore.logs import logformat
from quadcore.store import names, store


def _files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()}


def _log_with_event_names(fast_name: str, slow_name: str, n: int = 30) -> bytes:
    """A small valid log whose two event types carry the given names (which may be equal, which
    the encoder cannot write: it writes placeholders that are then replaced in the header)."""
    import struct
    import zlib

    fast = logformat.EventType(FAST.event_id, "\x01" * len(fast_name), FAST.variables, FAST.type_chars)
    slow = logformat.EventType(SLOW.event_id, "\x02" * len(slow_name), SLOW.variables, SLOW.type_chars)
    rng = np.random.default_rng(1)
    vf = np.zeros(n, FAST.payload_dtype())
    vf["f32"] = rng.normal(size=n)
    vs = np.zeros(n + 5, SLOW.payload_dtype())
    vs["pos.x"] = rng.normal(size=n + 5)
    data = logformat.encode([fast, slow], [(fast.name, 1000 * np.arange(n), vf),
                                           (slow.name, 700 * np.arange(n + 5), vs)], version=2, with_crc=False)
    data = data.replace(fast.name.encode() + b"\x00", fast_name.encode() + b"\x00", 1)
    data = data.replace(slow.name.encode() + b"\x00", slow_name.encode() + b"\x00", 1)
    return data + struct.pack("<I", zlib.crc32(data) & 0xFFFFFFFF)


def _run_cli(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------------------------------
# Names that become path components
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../x", "/etc/passwd", "a/b", "..", ".", "", ".hidden", "a=b", "x" * 250,
                                  "flight 1", "é", "a\\b", "a\x00b"])
def test_unsafe_names_map_to_safe_distinct_components(name):
    safe = names.safe_component(name)
    assert names.is_safe(safe) and safe != name
    assert len(safe) <= names.MAX_COMPONENT_CHARS and "/" not in safe and "=" not in safe
    assert names.safe_component(name) == safe  # deterministic
    with pytest.raises(names.UnsafeNameError):
        names.check_component(name, "flight id")


def test_safe_names_are_kept_and_collisions_are_impossible():
    assert names.safe_component("jana02") == "jana02"
    assert names.safe_component("sim000.bin") == "sim000.bin"
    assert names.safe_component("a=b") != names.safe_component("a_b")
    assert names.safe_component("a=b") != names.safe_component("a+b")
    unique, warnings = names.unique_safe_names(["e", "e", "e", "../e"])
    assert len(set(unique)) == 4 and len(warnings) == 3 and unique[0] == "e"


def test_store_refuses_unsafe_components(tmp_path):
    with pytest.raises(names.UnsafeNameError):
        store.decoded_path(tmp_path, "../escape", "f1")
    with pytest.raises(names.UnsafeNameError):
        store.table_path(tmp_path, "residuals", "a=b")
    with pytest.raises(names.UnsafeNameError):
        store.quarantine_path(tmp_path, "/abs")


# ---------------------------------------------------------------------------------------
# Event names from the header
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("fast_name,slow_name", [
    ("../../escaped", "slow"),
    ("/tmp/i12-absolute-escape", "slow"),
    ("fast", "fast"),  # two event types with one name
    ("a=b", "x" * 250),
])
def test_no_event_name_writes_outside_the_data_root(tmp_path, fast_name, slow_name):
    raw, out = tmp_path / "raw", tmp_path / "root" / "out"
    raw.mkdir()
    (raw / "f1").write_bytes(_log_with_event_names(fast_name, slow_name))
    outside_before = _files_under(tmp_path)

    code, stdout, _ = _run_cli("decode", str(raw), "--out", str(out))

    assert code == 0, stdout
    written = _files_under(tmp_path) - outside_before
    assert written and all(out.resolve() in p.resolve().parents for p in written), written
    assert not Path("/tmp/i12-absolute-escape").exists()
    # both tables are there with all their rows, whatever their names
    tables = {p.parent.parent.name: pl.read_parquet(p) for p in (out / "decoded").glob("*/flight=f1/data.parquet")}
    assert sorted(t.height for t in tables.values()) == [30, 35]
    log = logformat.decode_bytes((raw / "f1").read_bytes())
    assert set(log.tables) == set(tables)
    if fast_name == slow_name:
        assert any("declared more than once" in w for w in log.warnings), log.warnings
    else:
        assert any("not a safe path component" in w for w in log.warnings), log.warnings


def test_odd_file_names_get_safe_flight_ids_and_hive_queries_still_work(tmp_path, make_synthetic_log):
    raw, out = tmp_path / "raw", tmp_path / "out"
    raw.mkdir()
    odd = ["a=b", "y" * 250, "with space", "plain"]
    for i, name in enumerate(odd):
        (raw / name).write_bytes(make_synthetic_log(name=f"s{i}", seed=i).data)
    before = _files_under(tmp_path)

    code, stdout, _ = _run_cli("decode", str(raw), "--out", str(out))

    assert code == 0, stdout
    assert all(out.resolve() in p.resolve().parents for p in _files_under(tmp_path) - before)
    frame = pl.scan_parquet(out / "decoded" / "fast" / "**" / "*.parquet", hive_partitioning=True,
                            hive_schema={"flight": pl.String}).collect()
    ids = sorted(frame["flight"].unique())
    assert ids == sorted(names.safe_component(n) for n in odd)
    assert "plain" in ids and frame.height == 40 * len(odd)


# ---------------------------------------------------------------------------------------
# Crafted headers fail fast with a typed error
# ---------------------------------------------------------------------------------------

def _header(n_types: int, n_vars: int = 1, name: bytes = b"e", var: bytes = b"v(f)") -> bytes:
    import struct

    body = b"".join(struct.pack("<H", i) + name + b"\x00" + struct.pack("<H", n_vars) + (var + b"\x00") * n_vars
                    for i in range(n_types))
    return struct.pack("<BHH", 0xBC, 2, n_types) + body


@pytest.mark.parametrize("data,message", [
    (_header(65535), "event types"),
    (_header(1, n_vars=5000), "variables"),
    (_header(1, name=b"n" * 100_000), "longer than"),
    (_header(1, n_vars=2), "twice"),
    (_header(1, var=b"(f)"), "empty or reserved"),
    (_header(1, var=b"timestamp(f)"), "empty or reserved"),
])
def test_crafted_headers_fail_fast(data, message):
    t0 = time.perf_counter()
    with pytest.raises(logformat.CorruptHeaderError, match=message):
        logformat.decode_bytes(data + b"\x00" * 1000)
    assert time.perf_counter() - t0 < 1.0


def test_many_declared_event_types_cost_nothing_extra(make_synthetic_log):
    """The candidate scan is one pass whatever the header declares (here the maximum)."""
    import struct

    log = make_synthetic_log(n_fast=20_000, n_slow=8000)
    version, _, start = logformat.parse_header(log.data)
    ids = list(range(100, 100 + logformat.MAX_EVENT_TYPES - 2))
    extra = b"".join(struct.pack("<H", i) + f"x{i}".encode() + b"\x00" + struct.pack("<H", 1) + b"v(B)\x00"
                     for i in ids)
    header = struct.pack("<BHH", 0xBC, version, logformat.MAX_EVENT_TYPES)
    crafted = header + log.data[5:start] + extra + log.data[start:-4]
    t0 = time.perf_counter()
    decoded = logformat.decode_bytes(crafted)
    assert time.perf_counter() - t0 < 2.0
    assert decoded.rows()["fast"] + decoded.rows()["slow"] >= 27_000


# ---------------------------------------------------------------------------------------
# Files the CLI cannot read or write
# ---------------------------------------------------------------------------------------

def test_unreadable_file_is_quarantined_and_the_others_go_on(tmp_path, make_synthetic_log, monkeypatch):
    raw, out = tmp_path / "raw", tmp_path / "out"
    raw.mkdir()
    for name in ("good1", "locked", "good2"):
        (raw / name).write_bytes(make_synthetic_log(name=f"src_{name}").data)
    real_read = logformat.read_log

    def read_log(path):  # root reads chmod-000 files, so deny the read itself
        if Path(path).name == "locked":
            raise PermissionError(13, "Permission denied", str(path))
        return real_read(path)

    monkeypatch.setattr(logformat, "read_log", read_log)
    code, stdout, _ = _run_cli("decode", str(raw), "--out", str(out))
    assert code == 0
    assert "locked: QUARANTINED (PermissionError" in stdout
    assert sorted(p.parent.name for p in (out / "decoded" / "fast").glob("*/data.parquet")) == \
        ["flight=good1", "flight=good2"]
    assert store.quarantined(out)[0]["error_type"] == "PermissionError"


def test_out_pointing_at_a_file_is_one_line_and_exit_2(tmp_path, make_synthetic_log):
    log = make_synthetic_log()
    target = tmp_path / "a_file"
    target.write_text("x")
    code, _, stderr = _run_cli("decode", str(log.path), "--out", str(target))
    assert code == 2
    assert stderr.count("\n") == 1 and "is a file" in stderr


def test_read_only_out_folder_is_one_line_and_exit_2(tmp_path, make_synthetic_log, monkeypatch):
    log = make_synthetic_log()
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):  # root (as in CI) ignores the mode, so deny the call itself
        if Path(path).is_relative_to(ro):
            raise PermissionError(13, "Permission denied", str(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)
    code, _, stderr = _run_cli("decode", str(log.path), "--out", str(ro / "x"))
    assert code == 2 and stderr.count("\n") == 1
    assert "Permission denied" in stderr and not (ro / "x").exists()


def test_sensor_header_check_reports_an_unreadable_file_instead_of_raising(tmp_path):
    from pipeline.sensors import header_problem

    (tmp_path / "a_folder").mkdir()  # opening it fails with an OSError, as an unreadable file does
    assert header_problem(tmp_path / "a_folder").startswith("IsADirectoryError")


def test_variables_with_one_si_name_are_both_kept():
    from quadcore.logs import units

    values = np.zeros(3, dtype=[("a.b", "<f4"), ("a_b", "<f4")])
    values["a.b"], values["a_b"] = 1.0, 2.0
    table, columns = units.to_si(values, np.arange(3) * 1000, 0)
    assert table["a_b_raw"].to_list() == [1.0] * 3 and table["a_b_raw_2"].to_list() == [2.0] * 3
    assert columns["a_b_raw_2"]["source"] == "a_b"
