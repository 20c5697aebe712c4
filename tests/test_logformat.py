"""The uSD log decoder and encoder (quadcore.logs.logformat) and the SI flight layer (quadcore.logs.flight)."""

from __future__ import annotations

import hashlib
import json
import math
import struct

import numpy as np
import pytest

from quadcore.logs import flight, logformat

TOTAL_FIXED_FREQUENCY_ROWS = 175_473  # the shared data set's README: 175,473 samples in all
REAL_LOG_NAMES = [
    "jana00", "jana01", "jana02", "jana03", "jana04", "jana05", "jana06", "jana10", "jana11",
    "jana20", "jana23", "jana24", "jana25", "jana27", "jana28", "jana29", "jana30", "jana32", "jana33",
]  # fmt: skip


def _assert_tables_equal(got: np.ndarray, expected: np.ndarray) -> None:
    """Same variables, same dtypes, same bits (so NaN, -0.0 and float16 subnormals count)."""
    assert got.dtype.names == expected.dtype.names
    for var in expected.dtype.names or ():
        assert got[var].dtype == expected[var].dtype, var
        assert got[var].tobytes() == expected[var].tobytes(), var


def _reencode(log: logformat.DecodedLog) -> bytes:
    """Encode a decoded log again, in the file's native timestamp unit."""
    to_native = logformat.TIMESTAMP_TO_US[log.version]
    records = [(name, log.timestamps_us[name] // to_native, log.tables[name]) for name in log.tables]
    return logformat.encode(list(log.event_types.values()), records, version=log.version, with_crc=True)


# ---------------------------------------------------------------------------------------
# The real data set
# ---------------------------------------------------------------------------------------

def test_real_logs_decode_to_the_documented_row_count(real_logs, record_offsets):
    names = sorted(p.name for p in flight.discover_logs(real_logs))
    assert names == REAL_LOG_NAMES

    total = 0
    for name in names:
        buf = (real_logs / name).read_bytes()
        log = logformat.decode_bytes(buf)
        rows = log.rows()
        assert log.version == 2, name
        assert set(rows) == {"fixedFrequency", "estPose"}, name
        assert rows["fixedFrequency"] > 0 and rows["estPose"] > 0, (name, rows)
        assert log.crc_ok is True, name
        assert log.warnings == [], (name, log.warnings)
        assert log.bytes_dropped == 0 and log.bytes_total == len(buf), name
        # the vectorised chain walk agrees with a plain record-by-record walk
        plain = record_offsets(buf)
        ids = {et.name: et.event_id for et in log.event_types.values()}
        for event, n in rows.items():
            assert n == sum(1 for _, eid, _ in plain if eid == ids[event]), (name, event)
        assert plain[-1][0] + plain[-1][2] == len(buf) - 4, name  # records end exactly at the CRC
        total += rows["fixedFrequency"]
    assert total == TOTAL_FIXED_FREQUENCY_ROWS


def test_real_log_event_types_come_from_the_header(real_logs):
    log = logformat.decode_file(real_logs / "jana02")
    ff = log.event_types["fixedFrequency"]
    assert ff.event_id == 0xFFFF and log.event_types["estPose"].event_id == 8
    types = dict(zip(ff.variables, ff.type_chars))
    assert types["acc.z"] == "f" and types["rpm.m1"] == "H" and types["pwm.m4_pwm"] == "I"
    assert log.tables["fixedFrequency"]["pwm.m4_pwm"].dtype == np.dtype("<u4")
    assert log.rows() == {"fixedFrequency": 3900, "estPose": 426}


# ---------------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("version", [1, 2])
def test_synthetic_round_trip(make_synthetic_log, record_offsets, version):
    syn = make_synthetic_log(version=version)
    # the records really are interleaved, with two record sizes, in the file
    plain = record_offsets(syn.data)
    id_sequence = [eid for _, eid, _ in plain]
    switches = sum(a != b for a, b in zip(id_sequence, id_sequence[1:]))
    assert switches > 10 and {size for _, _, size in plain} == {
        2 + {1: 4, 2: 8}[version] + 1 + 1 + 2 + 2 + 4 + 4 + 4 + 2,  # fast: B b H h I i f e
        2 + {1: 4, 2: 8}[version] + 4 + 2 + 1,  # slow: f e B
    }

    log = logformat.decode_file(syn.path)
    assert log.version == version
    assert log.crc_ok is True and log.warnings == [] and log.bytes_dropped == 0
    assert log.rows() == syn.rows()
    assert {n: et.event_id for n, et in log.event_types.items()} == {"fast": 0xFFFF, "slow": 8}
    for event in ("fast", "slow"):
        _assert_tables_equal(log.tables[event], syn.values[event])
        assert log.timestamps_us[event].dtype == np.int64
        np.testing.assert_array_equal(log.timestamps_us[event], syn.timestamps_us[event])
    # float16 values survive bit for bit, including the extremes and a subnormal
    f16 = log.tables["fast"]["f16"]
    assert f16.dtype == np.float16
    assert f16[4] == np.float16(65504) and 0 < f16[5] < np.finfo(np.float16).tiny
    assert math.copysign(1.0, float(f16[1])) == -1.0  # -0.0 kept its sign
    assert log.tables["fast"]["u32"][1] == 2**32 - 1 and log.tables["fast"]["i8"][0] == -128

    # encode(decode(x)) == x
    assert _reencode(log) == syn.data


@pytest.mark.parametrize("version", [1, 2])
def test_encode_without_crc_decodes_with_a_warning(make_synthetic_log, version):
    syn = make_synthetic_log(version=version, with_crc=False)
    log = logformat.decode_bytes(syn.data)
    assert log.crc_ok is None
    assert log.rows() == syn.rows()
    assert any("CRC" in w for w in log.warnings), log.warnings
    for event in ("fast", "slow"):
        _assert_tables_equal(log.tables[event], syn.values[event])


def test_real_log_round_trip_is_byte_identical(real_logs):
    original = (real_logs / "jana02").read_bytes()
    assert _reencode(logformat.decode_bytes(original)) == original


def test_real_logs_reencode_identically_exactly_when_records_are_in_time_order(real_logs, record_offsets):
    """The deck sometimes writes an estPose record after a fixedFrequency record with a later
    timestamp (arrival order); the encoder writes timestamp order, and the decoded tables do
    not keep file order. So decode -> encode reproduces a file byte for byte exactly when
    its records are in timestamp order, and otherwise still reproduces every value."""
    identical = []
    for name in REAL_LOG_NAMES:
        original = (real_logs / name).read_bytes()
        log = logformat.decode_bytes(original)
        again = _reencode(log)
        ts = [struct.unpack_from("<Q", original, off + 2)[0] for off, _, _ in record_offsets(original)]
        in_time_order = all(a < b for a, b in zip(ts, ts[1:]))
        assert (again == original) == in_time_order, name
        assert len(again) == len(original), name
        log2 = logformat.decode_bytes(again)
        for event in log.tables:
            _assert_tables_equal(log2.tables[event], log.tables[event])
            np.testing.assert_array_equal(log2.timestamps_us[event], log.timestamps_us[event])
        if again == original:
            identical.append(name)
    assert "jana02" in identical


# ---------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------

@pytest.fixture(params=["real", "v1", "v2"])
def good_log(request, make_synthetic_log) -> tuple[bytes, logformat.DecodedLog]:
    """A good log's bytes and its clean decoding: jana02, or a synthetic v1 / v2 log."""
    if request.param == "real":
        buf = (request.getfixturevalue("real_logs") / "jana02").read_bytes()
    else:
        buf = make_synthetic_log(version=int(request.param[1]), n_fast=300, n_slow=120).data
    clean = logformat.decode_bytes(buf)
    assert clean.crc_ok is True and clean.warnings == []
    return buf, clean


@pytest.mark.parametrize(
    "cls",
    [logformat.EmptyLogError, logformat.BadMagicError, logformat.UnsupportedVersionError, logformat.CorruptHeaderError],
)
def test_error_types_are_log_format_errors_and_value_errors(cls):
    assert issubclass(cls, logformat.LogFormatError)
    assert issubclass(cls, ValueError)
    assert issubclass(logformat.LogFormatError, ValueError)


def test_empty_file(tmp_path):
    (tmp_path / "empty").write_bytes(b"")
    with pytest.raises(logformat.EmptyLogError):
        logformat.decode_file(tmp_path / "empty")
    with pytest.raises(logformat.EmptyLogError):  # the magic byte and nothing else
        logformat.decode_bytes(b"\xbc")


def test_wrong_magic_byte(tmp_path, good_log):
    buf, _ = good_log
    (tmp_path / "bad_magic").write_bytes(b"\x42" + buf[1:])
    with pytest.raises(logformat.BadMagicError, match="0x42"):
        logformat.decode_file(tmp_path / "bad_magic")
    with pytest.raises(ValueError):  # callers that only know ValueError still catch it
        logformat.decode_bytes(b"hello")


@pytest.mark.parametrize("version", [0, 3, 0xFFFF])
def test_unknown_version(tmp_path, good_log, version):
    buf, _ = good_log
    path = tmp_path / "future"
    path.write_bytes(buf[:1] + struct.pack("<H", version) + buf[3:])
    with pytest.raises(logformat.UnsupportedVersionError, match=str(version)):
        logformat.decode_file(path)


def test_truncated_header(good_log):
    buf, _ = good_log
    with pytest.raises(logformat.CorruptHeaderError):
        logformat.decode_bytes(buf[:12])


def test_crc_mismatch_keeps_every_row(tmp_path, good_log, record_offsets):
    buf, clean = good_log
    records = record_offsets(buf)
    off, eid, _ = records[len(records) // 2]
    value_at = off + 2 + {1: 4, 2: 8}[clean.version]  # first byte of the first value
    damaged = bytearray(buf)
    damaged[value_at] ^= 0x5A
    (tmp_path / "flipped").write_bytes(damaged)

    log = logformat.decode_file(tmp_path / "flipped")
    assert log.crc_ok is False
    assert any("CRC" in w for w in log.warnings), log.warnings
    assert log.rows() == clean.rows() and log.bytes_dropped == 0
    # exactly one value changed: the flipped one
    n_changed = 0
    for event in clean.tables:
        np.testing.assert_array_equal(log.timestamps_us[event], clean.timestamps_us[event])
        for var in clean.tables[event].dtype.names:
            a, b = log.tables[event][var], clean.tables[event][var]
            n_changed += int(np.count_nonzero(a.view(f"u{a.itemsize}") != b.view(f"u{b.itemsize}")))
    assert n_changed == 1


def test_missing_crc_keeps_every_row(tmp_path, good_log):
    buf, clean = good_log
    (tmp_path / "no_trailer").write_bytes(buf[:-4])
    log = logformat.decode_file(tmp_path / "no_trailer")
    assert log.crc_ok is None
    assert any("CRC" in w for w in log.warnings), log.warnings
    assert log.rows() == clean.rows() and log.bytes_dropped == 0
    for event in clean.tables:
        _assert_tables_equal(log.tables[event], clean.tables[event])


def _cut_mid_last_record(buf: bytes, records: list) -> tuple[bytes, int, int]:
    """The file cut in the middle of its last record (trailer gone).
    Returns (cut bytes, complete records left, bytes of the partial record)."""
    off, _, size = records[-1]
    fragment = size // 2
    return buf[: off + fragment], len(records) - 1, fragment


def test_partial_last_record_keeps_all_complete_records(tmp_path, good_log, record_offsets):
    buf, clean = good_log
    cut, n_complete, _ = _cut_mid_last_record(buf, record_offsets(buf))
    (tmp_path / "cut").write_bytes(cut)
    log = logformat.decode_file(tmp_path / "cut")
    assert sum(log.rows().values()) == n_complete
    assert any("partial" in w and "dropped" in w for w in log.warnings), log.warnings
    assert log.bytes_dropped > 0
    for event in clean.tables:  # what was kept is the head of the clean decoding
        n = len(log.tables[event])
        _assert_tables_equal(log.tables[event], clean.tables[event][:n])
        np.testing.assert_array_equal(log.timestamps_us[event], clean.timestamps_us[event][:n])


def test_partial_last_record_reports_the_bytes_dropped(good_log, record_offsets):
    buf, _ = good_log
    cut, _, fragment = _cut_mid_last_record(buf, record_offsets(buf))
    log = logformat.decode_bytes(cut)
    assert log.crc_ok is None  # a cut file has no CRC trailer
    assert log.bytes_dropped == fragment
    assert any(f"dropped {fragment} bytes" in w for w in log.warnings), log.warnings
    assert not any("mismatch" in w for w in log.warnings), log.warnings


@pytest.mark.parametrize("how", ["overwrite", "insert"])
def test_garbage_in_the_middle_is_skipped_and_decoding_resynchronises(tmp_path, good_log, record_offsets, how):
    buf, clean = good_log
    records = record_offsets(buf)
    k = len(records) // 2
    at = records[k][0]  # garbage starts exactly where record k starts
    garbage = b"\xaa" * 30
    damaged = buf[:at] + garbage + buf[at + (len(garbage) if how == "overwrite" else 0):]
    (tmp_path / "garbage").write_bytes(damaged)
    # overwritten: the records the garbage touches are lost; inserted: none is
    lost = {i for i, (off, _, size) in enumerate(records) if how == "overwrite" and off < at + len(garbage)
            and off + size > at}

    log = logformat.decode_file(tmp_path / "garbage")
    assert sum(log.rows().values()) == len(records) - len(lost)
    assert log.crc_ok is False
    [skip] = log.skipped
    resume = max(lost) + 1 if lost else k
    assert skip.byte_start == at
    assert skip.byte_end == records[resume][0] + (len(garbage) if how == "insert" else 0)
    assert log.bytes_dropped == skip.byte_end - skip.byte_start
    # the time range skipped: from the last record kept before to the first one after
    ts_at = {off: ts for event in clean.tables for off, ts in zip(
        [o for o, e, _ in records if e == clean.event_types[event].event_id], clean.timestamps_us[event])}
    assert skip.t_before_us == ts_at[records[k - 1][0]]
    assert skip.t_after_us == ts_at[records[resume][0]]
    assert any("resynchronised after 1 corrupt stretch" in w for w in log.warnings), log.warnings
    for event in clean.tables:
        eid = clean.event_types[event].event_id
        wanted = [i for i, (_, e, _) in enumerate(records) if e == eid and i not in lost]
        _assert_tables_equal(log.tables[event], clean.tables[event][[
            sum(1 for _, e, _ in records[:i] if e == eid) for i in wanted]])
        assert np.all(np.diff(log.timestamps_us[event]) >= 0)


# ---------------------------------------------------------------------------------------
# The flight layer: SI tables and provenance
# ---------------------------------------------------------------------------------------

def test_decode_flight_gives_si_tables_with_provenance(real_logs):
    path = real_logs / "jana02"
    fl = flight.decode_flight(path)
    raw = logformat.decode_file(path)
    ff = fl.tables["fixedFrequency"]
    assert fl.flight_id == "jana02"
    assert ff.height == 3900 and fl.tables["estPose"].height == 426

    # one clock for the flight, starting at 0 s
    t0_us = min(int(ts[0]) for ts in raw.timestamps_us.values())
    assert min(df["t_s"].min() for df in fl.tables.values()) == 0.0
    for event, df in fl.tables.items():
        assert df["t_s"].min() >= 0.0
        np.testing.assert_allclose(df["t_s"].to_numpy(), (raw.timestamps_us[event] - t0_us) * 1e-6, atol=1e-9)
        np.testing.assert_array_equal(df["timestamp_us"].to_numpy(), raw.timestamps_us[event])
    assert np.all(np.diff(ff["t_s"].to_numpy()) > 0)

    # specific force in m/s^2: about +1 g on body z at the start (hovering / at rest)
    sf_z = ff["sf_b_z_mps2"].to_numpy()
    assert abs(float(np.median(sf_z[:50])) - 9.81) < 0.5
    np.testing.assert_allclose(sf_z, raw.tables["fixedFrequency"]["acc.z"].astype(np.float64) * 9.80665)

    # angular rates in rad/s (logged in deg/s)
    for axis in "xyz":
        omega = ff[f"omega_b_{axis}_radps"].to_numpy()
        deg = raw.tables["fixedFrequency"][f"gyro.{axis}"].astype(np.float64)
        assert omega.dtype == np.float32  # stored at the logged precision
        np.testing.assert_allclose(omega, np.deg2rad(deg), rtol=1e-6)
        assert np.abs(omega).max() < 35.0  # the gyro's 2000 deg/s full scale
    assert fl.columns["fixedFrequency"]["omega_b_x_radps"]["unit"] == "rad/s"

    # PWM as duty 0..1, battery in volts
    for m in range(1, 5):
        pwm = ff[f"pwm_{m}"].to_numpy()
        assert pwm.min() >= 0.0 and pwm.max() <= 1.0
        assert pwm.max() > 0.1  # flying, and scaled from 0..65535, not left raw or divided twice
    vbat = ff["vbat_V"].to_numpy()
    assert 3.0 <= vbat.min() and vbat.max() <= 4.3
    assert fl.columns["fixedFrequency"]["vbat_V"] == {
        "unit": "V", "description": "battery voltage (from mV)", "source": "pm.vbatMV",
    }
    assert "mocap_p_w_x_m" in fl.tables["estPose"].columns

    # provenance
    prov = fl.provenance
    assert prov.source_sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert prov.format_version == 2
    assert prov.crc_ok is True and prov.decode_warnings == () and prov.bytes_dropped == 0
    assert prov.rows == {"fixedFrequency": 3900, "estPose": 426}
    assert prov.source_file == str(path.resolve())
    assert prov.start_ns is not None and prov.start_source == flight.START_FROM_MTIME
    # the JSON form: the keys the decoded Parquet files carry, and back
    assert list(prov.to_dict()) == ["source_file", "source_sha256", "format_version", "crc_ok", "bytes_total",
                                    "bytes_dropped", "decode_warnings", "rows", "decoder", "start_ns", "start_source"]
    assert prov.decoder == flight.decoder_digest() and prov.current(prov.source_sha256)
    assert flight.Provenance.from_dict(json.loads(json.dumps(prov.to_dict()))) == prov
    assert fl.warnings == []
