"""MCAP export, read back with the mcap reader and checked against the Parquet it came from."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import pytest
from mcap.reader import make_reader

from quadcore import cli, export, residuals, simulation, vehicle
from quadcore import flight as flightmod


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("raw")
    simulation.simulate_set(folder, [simulation.SimConfig(kind="figure8", duration_s=5.0, seed=5)],
                            {"rotor_drag": {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}})
    table = residuals.residual_table(flightmod.decode_flight(folder / "sim000").tables["fixedFrequency"], vehicle.load())
    out = tmp_path_factory.mktemp("mcap")
    assert cli.main(["export", str(folder / "sim000"), "--out", str(out)]) == 0
    return table, out / "sim000.mcap", folder / "sim000"


def test_schemas_channels_and_counts(exported):
    table, path, _ = exported
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    schemas = {s.name for s in summary.schemas.values()}
    assert {"foxglove.FrameTransform", "foxglove.PoseInFrame"} <= schemas
    assert all(s.encoding == "jsonschema" for s in summary.schemas.values())
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
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages(topics=["/pose", "/model/force", "/battery"]):
            seen.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    for k in rows:
        r = table.row(k, named=True)
        _, pose = seen["/pose"][k]
        assert pose["frame_id"] == "world"
        assert pose["pose"]["position"]["z"] == pytest.approx(r["p_w_z_m"], abs=1e-6)
        assert pose["pose"]["orientation"]["w"] == pytest.approx(r["q_w"], abs=1e-6)
        _, force = seen["/model/force"][k]
        assert force["residual"]["x"] == pytest.approx(r["f_res_b_x_N"], abs=1e-9)
        assert force["measured"]["z"] == pytest.approx(r["f_meas_b_z_N"], abs=1e-9)
        _, bat = seen["/battery"][k]
        assert bat["vbat_V"] == pytest.approx(r["vbat_V"], abs=1e-6)
    # log time: seconds from the first sample, anchored at a real date
    t0, _ = seen["/pose"][0]
    tk, _ = seen["/pose"][-1]
    assert (tk - t0) / 1e9 == pytest.approx(table["t_s"][-1] - table["t_s"][0], abs=1e-6)
    assert datetime.fromtimestamp(t0 / 1e9, timezone.utc).year >= 2020


def test_anchor_is_the_file_time_at_the_end_of_the_flight(exported):
    table, path, log = exported
    with open(path, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    start_ns = int(meta["quadcore"]["start_ns"])
    end_ns = start_ns + int(table["t_s"][-1] * 1e9)
    assert abs(end_ns - log.stat().st_mtime_ns) < 1e6
    assert meta["quadcore"]["flight"] == "sim000"


def test_export_of_a_missing_log_is_a_user_error(tmp_path, capsys):
    assert cli.main(["export", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
    assert "no such file" in capsys.readouterr().err
