"""MCAP export per flight: protobuf (quadcore.export.mcap) against JSON messages, the way it was written before.

    python benchmarks/bench_export.py [LOGS_FOLDER]

Both write the same seven topics, one message per sample, from the residual table of each real
flight: ``quadcore.export.mcap.write_mcap`` (protobuf, Foxglove's schemas, the Foxglove SDK's writer)
and the reference below (one ``json.dumps`` per message and the ``mcap`` package's Python writer,
the exporter before protobuf). Target: at least 5x faster per flight. Best of 3 each; the
ratio is reference / protobuf. A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from _common import best_of, logs_folder
from _jobs import REPO, report

sys.path.insert(0, str(REPO))

from quadcore.export import mcap as export  # noqa: E402
from quadcore.logs import flight  # noqa: E402
from quadcore.physics import residuals, vehicle  # noqa: E402

XYZ = "xyz"


def _vec(table, names, keys=XYZ):
    return [dict(zip(keys, row)) for row in table.select(names).to_numpy().astype(float).tolist()]


def write_json_mcap(table, path: Path, start_ns: int) -> int:
    """The reference: JSON messages, Python writer (what quadcore.export.mcap did before protobuf)."""
    from mcap.writer import Writer

    t_ns = [start_ns + round(t * 1e9) for t in table["t_s"].to_list()]
    stamps = [{"sec": t // 10**9, "nsec": t % 10**9} for t in t_ns]
    t_s = table["t_s"].to_list()
    p, q = _vec(table, ["p_w_x_m", "p_w_y_m", "p_w_z_m"]), _vec(table, ["q_x", "q_y", "q_z", "q_w"], "xyzw")
    pwm = sorted(c for c in table.columns if c.startswith("pwm_"))
    rotor = table.select([f"f_rotor_{i}_N" for i in range(1, len(pwm) + 1)]).to_numpy().tolist()
    topics = {
        "/tf": [{"timestamp": s, "parent_frame_id": "world", "child_frame_id": "body", "translation": a, "rotation": b}
                for s, a, b in zip(stamps, p, q)],
        "/pose": [{"timestamp": s, "frame_id": "world", "pose": {"position": a, "orientation": b}}
                  for s, a, b in zip(stamps, p, q)],
        "/imu": [{"t_s": t, "gyro_b_radps": g, "specific_force_b_mps2": f} for t, g, f in zip(
            t_s, _vec(table, [f"omega_b_{a}_radps" for a in XYZ]), _vec(table, [f"sf_b_{a}_mps2" for a in XYZ]))],
        "/motors": [{"t_s": t, "pwm": a, "thrust_N": b}
                    for t, a, b in zip(t_s, table.select(pwm).to_numpy().tolist(), rotor)],
        "/battery": [{"t_s": t, "vbat_V": v} for t, v in zip(t_s, table["vbat_V"].to_list())],
    }
    for topic, kind, unit in (("/model/force", "f", "N"), ("/model/torque", "tau", "Nm")):
        m, mo, r = (_vec(table, [f"{kind}_{w}_b_{a}_{unit}" for a in XYZ]) for w in ("meas", "model", "res"))
        topics[topic] = [{"t_s": t, "measured": a, "model": b, "residual": c} for t, a, b, c in zip(t_s, m, mo, r)]
    n = 0
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="reference")
        schema = writer.register_schema("any", "jsonschema", b"{}")
        for topic, msgs in topics.items():
            channel = writer.register_channel(topic, "json", schema)
            for seq, (t, m) in enumerate(zip(t_ns, msgs)):
                writer.add_message(channel, log_time=t, data=json.dumps(m).encode(), publish_time=t, sequence=seq)
                n += 1
        writer.finish()
    return n


def main() -> None:
    logs = logs_folder()
    veh = vehicle.load()
    total_ref = total_pb = 0.0
    samples = 0
    with tempfile.TemporaryDirectory(prefix="bench_export_") as tmp:
        for log in sorted(p for p in logs.iterdir() if p.is_file()):
            table = residuals.residual_table(flight.decode_flight(log).tables["fixedFrequency"], veh)
            t_ref, _ = best_of(lambda t=table: write_json_mcap(t, Path(tmp) / "ref.mcap", 0))
            t_pb, _ = best_of(lambda t=table: export.write_mcap(t, Path(tmp) / "pb.mcap", 0))
            total_ref, total_pb, samples = total_ref + t_ref, total_pb + t_pb, samples + table.height
            size = (Path(tmp) / "pb.mcap").stat().st_size / 1e6
            print(f"  {log.name}: {table.height:6d} samples  JSON {t_ref:6.3f} s  protobuf {t_pb:6.3f} s "
                  f"({t_ref / t_pb:4.1f}x, {size:.1f} MB)")
    n = len([p for p in logs.iterdir() if p.is_file()])
    print(f"  per sample (7 messages): JSON {total_ref / samples * 1e6:.1f} us, "
          f"protobuf {total_pb / samples * 1e6:.1f} us")
    report(f"MCAP export speed-up per flight (mean of {n} flights)", total_ref / total_pb, 5.0, "x",
           lower_is_better=False)


if __name__ == "__main__":
    main()
