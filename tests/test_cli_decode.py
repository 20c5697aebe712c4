"""``quadcore decode``: real logs -> hive-partitioned SI Parquet, quarantine, user errors."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import shutil

import duckdb
import polars as pl
import pyarrow.parquet as pq
import pytest

from quadcore import cli
from quadcore.store import store

TOTAL_FIXED_FREQUENCY_ROWS = 175_473


@pytest.fixture(scope="module")
def decoded_all(real_logs, tmp_path_factory):
    """``quadcore decode <real logs folder> --out <tmp>``, once for the module.

    Returns (exit code, stdout, out dir)."""
    out = tmp_path_factory.mktemp("cli_out")
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = cli.main(["decode", str(real_logs), "--out", str(out)])
    return code, stdout.getvalue(), out


def _fixed_frequency_glob(out) -> str:
    return str(out / "decoded" / "fixedFrequency" / "**" / "*.parquet")


def test_decode_folder_writes_parquet_per_flight(decoded_all, real_logs):
    code, stdout, out = decoded_all
    assert code == 0
    flights = sorted(p.name for p in real_logs.iterdir())
    for event in ("fixedFrequency", "estPose"):
        written = sorted(p.parent.name for p in (out / "decoded" / event).glob("flight=*/data.parquet"))
        assert written == [f"flight={f}" for f in flights]
    assert not (out / "quarantine").exists()
    # the summary table ends with the total, and says where the files are
    total_line = next(line for line in stdout.splitlines() if line.startswith("TOTAL"))
    assert str(TOTAL_FIXED_FREQUENCY_ROWS) in total_line.split()
    assert f"{len(flights)} flights decoded" in stdout


def test_parquet_content_and_schema_metadata(decoded_all, real_logs):
    _, _, out = decoded_all
    path = out / "decoded" / "fixedFrequency" / "flight=jana02" / "data.parquet"
    assert path == store.decoded_path(out, "fixedFrequency", "jana02")
    df = pl.read_parquet(path)
    assert df.height == 3900
    assert "flight" not in df.columns  # the flight id lives in the path (hive), not in the file
    for col in ("t_s", "timestamp_us", "sf_b_z_mps2", "omega_b_x_radps", "pwm_1", "vbat_V", "motor_1_radps"):
        assert col in df.columns
    assert df["t_s"][0] == 0.0

    meta = store.read_metadata(path)
    assert meta["flight"] == "jana02" and meta["event"] == "fixedFrequency"
    assert meta["source_sha256"] == hashlib.sha256((real_logs / "jana02").read_bytes()).hexdigest()
    assert meta["decode_warnings"] == []
    assert meta["format_version"] == 2 and meta["crc_ok"] is True
    assert meta["rows"] == {"fixedFrequency": 3900, "estPose": 426}
    units = {col: spec["unit"] for col, spec in meta["columns"].items()}
    assert set(units) == set(df.columns)
    assert units["t_s"] == "s" and units["omega_b_x_radps"] == "rad/s" and units["sf_b_z_mps2"] == "m/s^2"
    assert units["vbat_V"] == "V" and units["pwm_1"] == "1" and units["p_w_x_m"] == "m"
    assert meta["columns"]["vbat_V"]["source"] == "pm.vbatMV"
    # metadata sits in the file's key-value metadata under one key, readable by pyarrow too
    assert store.METADATA_KEY in pq.ParquetFile(path).metadata.metadata


def test_polars_sees_every_flight_through_hive_partitioning(decoded_all, real_logs):
    _, _, out = decoded_all
    lf = pl.scan_parquet(_fixed_frequency_glob(out), hive_partitioning=True)
    counts = lf.group_by("flight").agg(pl.len().alias("n")).sort("flight").collect()
    assert counts.schema["flight"] == pl.String
    assert counts["flight"].to_list() == sorted(p.name for p in real_logs.iterdir())
    assert counts["n"].sum() == TOTAL_FIXED_FREQUENCY_ROWS
    assert dict(zip(counts["flight"], counts["n"]))["jana02"] == 3900
    # a filter on the partition column works
    assert lf.filter(pl.col("flight") == "jana20").select(pl.col("vbat_V").n_unique()).collect().item() == 1


def test_duckdb_sees_every_flight_through_hive_partitioning(decoded_all, real_logs):
    _, _, out = decoded_all
    con = duckdb.connect()
    rows = con.execute(
        "SELECT flight, count(*) FROM read_parquet(?, hive_partitioning = true) GROUP BY flight ORDER BY flight",
        [_fixed_frequency_glob(out)],
    ).fetchall()
    assert [r[0] for r in rows] == sorted(p.name for p in real_logs.iterdir())
    assert sum(r[1] for r in rows) == TOTAL_FIXED_FREQUENCY_ROWS
    assert dict(rows)["jana02"] == 3900
    estpose = con.execute(
        "SELECT count(DISTINCT flight) FROM read_parquet(?, hive_partitioning = true)",
        [str(out / "decoded" / "estPose" / "**" / "*.parquet")],
    ).fetchone()[0]
    assert estpose == len(rows)


def test_decode_individual_files(real_logs, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["decode", str(real_logs / "jana02"), str(real_logs / "jana20"), "--out", str(out)])
    assert code == 0
    written = sorted(p.parent.name for p in (out / "decoded" / "fixedFrequency").glob("*/data.parquet"))
    assert written == ["flight=jana02", "flight=jana20"]
    assert pl.read_parquet(store.decoded_path(out, "fixedFrequency", "jana20")).height == 7861
    assert "2 flights decoded" in capsys.readouterr().out


def _corrupt_copy(real_logs, tmp_path, name: str = "corrupt01"):
    """A copy of a real log, in tmp_path, whose first byte is no longer the magic byte."""
    bad = tmp_path / name
    bad.write_bytes(b"\x00" + (real_logs / "jana03").read_bytes()[1:])
    return bad


def test_corrupt_file_is_quarantined_and_the_good_one_decoded(real_logs, tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    shutil.copyfile(real_logs / "jana02", raw / "jana02")  # a copy: a link out of the raw folder is not followed
    _corrupt_copy(real_logs, raw)
    out = tmp_path / "out"

    code = cli.main(["decode", str(raw), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0
    assert "Traceback" not in captured.err + captured.out
    assert store.decoded_path(out, "fixedFrequency", "jana02").is_file()
    assert not store.decoded_path(out, "fixedFrequency", "corrupt01").exists()
    record = json.loads(store.quarantine_path(out, "corrupt01").read_text())
    assert record["flight"] == "corrupt01"
    assert record["error_type"] == "BadMagicError"
    assert record["source_file"] == str(raw / "corrupt01")
    assert "0xBC" in record["reason"]
    assert "corrupt01: QUARANTINED" in captured.out
    assert "1 file(s) quarantined" in captured.out

    # once the file is good, decoding it again lifts the quarantine
    (raw / "corrupt01").unlink()
    shutil.copyfile(real_logs / "jana03", raw / "corrupt01")
    assert cli.main(["decode", str(raw), "--out", str(out)]) == 0
    assert not store.quarantine_path(out, "corrupt01").exists()
    assert store.decoded_path(out, "fixedFrequency", "corrupt01").is_file()


def test_only_corrupt_files_exits_1(real_logs, tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    _corrupt_copy(real_logs, raw)
    (raw / "empty").write_bytes(b"")
    code = cli.main(["decode", str(raw), "--out", str(tmp_path / "out")])
    assert code == 1
    assert store.quarantine_path(tmp_path / "out", "corrupt01").is_file()
    assert json.loads(store.quarantine_path(tmp_path / "out", "empty").read_text())["error_type"] == "EmptyLogError"
    assert "Traceback" not in capsys.readouterr().err


def test_missing_path_is_a_user_error(tmp_path, capsys):
    missing = tmp_path / "no_such_folder"
    out = tmp_path / "out"
    code = cli.main(["decode", str(missing), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2
    assert "error" in captured.err and str(missing) in captured.err
    assert "Traceback" not in captured.err + captured.out
    assert not out.exists()


def test_folder_without_logs_is_a_user_error(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("sidecars only")
    (tmp_path / "truth.json").write_text("{}")
    code = cli.main(["decode", str(tmp_path), "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert code == 2
    assert "no log files found" in captured.err
    assert "Traceback" not in captured.err


def test_truncated_log_is_decoded_with_a_warning(real_logs, tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    buf = (real_logs / "jana02").read_bytes()
    (raw / "cut02").write_bytes(buf[: len(buf) - 4 - 47])  # trailer gone, last record cut in half
    out = tmp_path / "out"
    code = cli.main(["decode", str(raw), "--out", str(out)])
    assert code == 0
    meta = store.read_metadata(store.decoded_path(out, "fixedFrequency", "cut02"))
    assert any("partial" in w for w in meta["decode_warnings"])
    assert "Traceback" not in capsys.readouterr().err
