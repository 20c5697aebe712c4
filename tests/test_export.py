"""MCAP export, read back with the mcap reader and checked against the Parquet it came from."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from quadcore import cli
from quadcore.export import mcap as export
from quadcore.logs import flight as flightmod
from quadcore.physics import residuals, vehicle
from quadcore.sim import simulation


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("raw")
    simulation.simulate_set(folder, [simulation.SimConfig(kind="figure8", duration_s=5.0, seed=5)],
                            {"rotor_drag": {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}})
    decoded = flightmod.decode_flight(folder / "sim000").tables["fixedFrequency"]
    table = residuals.residual_table(decoded, vehicle.load())
    out = tmp_path_factory.mktemp("mcap")
    assert cli.main(["export", str(folder / "sim000"), "--out", str(out)]) == 0
    return table, out / "sim000.mcap", folder / "sim000"


def test_schemas_channels_and_counts(exported):
    table, path, _ = exported
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    schemas = {s.name for s in summary.schemas.values()}
    assert {"foxglove.FrameTransform", "foxglove.PoseInFrame"} <= schemas
    assert all(s.encoding == "protobuf" for s in summary.schemas.values())
    assert all(c.message_encoding == "protobuf" for c in summary.channels.values())
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == set(export.TOPICS)
    counts = summary.statistics.channel_message_counts
    for ch_id, ch in summary.channels.items():
        assert counts[ch_id] == table.height, ch.topic
    assert summary.statistics.message_count == table.height * len(export.TOPICS)


def test_values_match_the_parquet(exported):
    table, path, _ = exported
    rows = {20: None, table.height // 2: None, table.height - 1: None}
    seen: dict[str, list] = {}
    topics = ["/tf", "/pose", "/model/force", "/battery", "/motors", "/imu"]
    with open(path, "rb") as fh:  # decoded from the schemas in the file alone (no quadcore code)
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(topics=topics):
            seen.setdefault(channel.topic, []).append((message.log_time, decoded))
    for k in rows:
        r = table.row(k, named=True)
        t_ns, pose = seen["/pose"][k]
        assert pose.frame_id == "world"
        assert pose.pose.position.z == pytest.approx(r["p_w_z_m"], abs=1e-6)
        assert pose.pose.orientation.w == pytest.approx(r["q_w"], abs=1e-6)
        assert pose.timestamp.seconds * 10**9 + pose.timestamp.nanos == t_ns
        _, tf = seen["/tf"][k]
        assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "body")
        assert tf.translation.x == pytest.approx(r["p_w_x_m"], abs=1e-6)
        _, force = seen["/model/force"][k]
        assert force.residual.x == pytest.approx(r["f_res_b_x_N"], abs=1e-9)
        assert force.measured.z == pytest.approx(r["f_meas_b_z_N"], abs=1e-9)
        assert force.t_s == pytest.approx(r["t_s"], abs=1e-9)
        _, bat = seen["/battery"][k]
        assert bat.vbat_V == pytest.approx(r["vbat_V"], abs=1e-6)
        _, motors = seen["/motors"][k]
        assert list(motors.pwm) == pytest.approx([r[f"pwm_{i}"] for i in range(1, 5)], abs=1e-6)
        assert list(motors.thrust_N) == pytest.approx([r[f"f_rotor_{i}_N"] for i in range(1, 5)], abs=1e-9)
        _, imu = seen["/imu"][k]
        assert imu.gyro_b_radps.y == pytest.approx(r["omega_b_y_radps"], abs=1e-6)
    # log time: seconds from the first sample, anchored at a real date
    t0, _ = seen["/pose"][0]
    tk, _ = seen["/pose"][-1]
    assert (tk - t0) / 1e9 == pytest.approx(table["t_s"][-1] - table["t_s"][0], abs=1e-6)
    assert datetime.fromtimestamp(t0 / 1e9, UTC).year >= 2020


def _start_ns(path) -> int:
    with open(path, "rb") as fh:
        return int({m.name: m.metadata for m in make_reader(fh).iter_metadata()}["quadcore"]["start_ns"])


def test_anchor_is_the_file_time_at_the_end_of_the_flight(exported):
    _, path, log = exported
    fl = flightmod.decode_flight(log)
    start_ns = _start_ns(path)
    assert start_ns == fl.provenance.start_ns
    # the file was closed when logging stopped: its time is the end of the last sample of any event
    last_s = max(float(df["t_s"][-1]) for df in fl.tables.values() if df.height)
    assert abs(start_ns + int(last_s * 1e9) - log.stat().st_mtime_ns) < 1e3


def test_the_user_gives_the_start_time(exported, tmp_path):
    _, _, log = exported
    out = tmp_path / "given"
    assert cli.main(["export", str(log), "--out", str(out), "--start", "2024-05-01T12:00:00Z"]) == 0
    assert _start_ns(out / "sim000.mcap") == int(datetime(2024, 5, 1, 12, tzinfo=UTC).timestamp()) * 10**9
    flights_csv = tmp_path / "flights.csv"
    flights_csv.write_text("flight,kind,start_utc\nsim000,random,2023-01-02T03:04:05.5\n")
    assert cli.main(["export", str(log), "--out", str(out), "--flights", str(flights_csv)]) == 0
    start_s = int(datetime(2023, 1, 2, 3, 4, 5, tzinfo=UTC).timestamp())
    assert _start_ns(out / "sim000.mcap") == start_s * 10**9 + 500_000_000
    assert cli.main(["export", str(log), "--out", str(out), "--start", "yesterday"]) == 2


def test_a_copy_of_the_log_keeps_the_recorded_start_time(exported, tmp_path):
    _, _, log = exported
    first = flightmod.decode_flight(log)
    copy = tmp_path / "sim000"
    copy.write_bytes(log.read_bytes())  # a copy: a new modification time
    again = flightmod.decode_flight(copy)
    assert again.provenance.start_ns != first.provenance.start_ns
    flightmod.settle_start_time(again, first.provenance)
    assert again.provenance.start_ns == first.provenance.start_ns
    changed = flightmod.decode_flight(copy)
    flightmod.settle_start_time(changed, replace(first.provenance, source_sha256="another log"))
    assert changed.provenance.start_ns != first.provenance.start_ns


def test_export_of_a_missing_log_is_a_user_error(tmp_path, capsys):
    assert cli.main(["export", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
    assert "no such file" in capsys.readouterr().err
