"""Export a flight as MCAP for Foxglove.

Channels (JSON-encoded, one message per logged sample)::

    /tf               foxglove.FrameTransform   world -> body: the 3D panel shows the vehicle
    /pose             foxglove.PoseInFrame      the same pose, for plots and the pose panel
    /imu              quadcore.Imu              gyro rad/s, specific force m/s^2 (body frame)
    /motors           quadcore.Motors           PWM 0..1, rotor thrust from the map N, motor speed rad/s
    /battery          quadcore.Battery          voltage V
    /model/force      quadcore.Wrench3          measured, modelled, residual body force N
    /model/torque     quadcore.Wrench3          measured, modelled, residual body torque N m

Time: the logs count from power-on, so absolute time is anchored at the log file's
modification time taken as the end of the flight (the deck closes the file when logging
stops); the anchor and the flight-relative ``t_s`` are in the file's metadata record
``quadcore``. Pass ``start_ns`` to anchor elsewhere.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl

TIME_SCHEMA = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
VEC3 = {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}}
QUAT = {"type": "object", "properties": {a: {"type": "number"} for a in "xyzw"}}


def _obj(**props) -> dict:
    return {"type": "object", "properties": props}


SCHEMAS = {
    "foxglove.FrameTransform": _obj(timestamp=TIME_SCHEMA, parent_frame_id={"type": "string"},
                                    child_frame_id={"type": "string"}, translation=VEC3, rotation=QUAT),
    "foxglove.PoseInFrame": _obj(timestamp=TIME_SCHEMA, frame_id={"type": "string"},
                                 pose=_obj(position=VEC3, orientation=QUAT)),
    "quadcore.Imu": _obj(t_s={"type": "number"}, gyro_b_radps=VEC3, specific_force_b_mps2=VEC3),
    "quadcore.Motors": _obj(t_s={"type": "number"}, pwm={"type": "array"}, thrust_N={"type": "array"},
                            speed_radps={"type": "array"}),
    "quadcore.Battery": _obj(t_s={"type": "number"}, vbat_V={"type": "number"}),
    "quadcore.Wrench3": _obj(t_s={"type": "number"}, measured=VEC3, model=VEC3, residual=VEC3),
}
TOPICS = {
    "/tf": "foxglove.FrameTransform",
    "/pose": "foxglove.PoseInFrame",
    "/imu": "quadcore.Imu",
    "/motors": "quadcore.Motors",
    "/battery": "quadcore.Battery",
    "/model/force": "quadcore.Wrench3",
    "/model/torque": "quadcore.Wrench3",
}


def _vec(arr: np.ndarray, keys: str = "xyz") -> list[dict]:
    return [dict(zip(keys, row)) for row in arr.tolist()]


def _cols(table: pl.DataFrame, names: list[str]) -> np.ndarray:
    return table.select(names).to_numpy().astype(float)


def messages(table: pl.DataFrame, start_ns: int) -> dict[str, tuple[np.ndarray, list[dict]]]:
    """Topic -> (log times in ns, message dicts), from a residual table."""
    t_ns = start_ns + np.round(table["t_s"].to_numpy() * 1e9).astype(np.int64)
    stamps = [{"sec": int(v // 1_000_000_000), "nsec": int(v % 1_000_000_000)} for v in t_ns.tolist()]
    t_s = table["t_s"].to_list()
    p = _vec(_cols(table, ["p_w_x_m", "p_w_y_m", "p_w_z_m"]))
    q = _vec(_cols(table, ["q_x", "q_y", "q_z", "q_w"]), "xyzw")
    xyz = "xyz"
    motors = sorted(c for c in table.columns if c.startswith("pwm_"))
    n_rot = len(motors)
    speed_cols = [f"motor_{i}_radps" for i in range(1, n_rot + 1)]
    speed = _cols(table, speed_cols).tolist() if all(c in table.columns for c in speed_cols) else [[]] * table.height
    out = {
        "/tf": [{"timestamp": s, "parent_frame_id": "world", "child_frame_id": "body", "translation": a, "rotation": b}
                for s, a, b in zip(stamps, p, q)],
        "/pose": [{"timestamp": s, "frame_id": "world", "pose": {"position": a, "orientation": b}}
                  for s, a, b in zip(stamps, p, q)],
        "/imu": [{"t_s": t, "gyro_b_radps": g, "specific_force_b_mps2": f} for t, g, f in zip(
            t_s, _vec(_cols(table, [f"omega_b_{a}_radps" for a in xyz])), _vec(_cols(table, [f"sf_b_{a}_mps2" for a in xyz])))],
        "/motors": [{"t_s": t, "pwm": a, "thrust_N": b, "speed_radps": c} for t, a, b, c in zip(
            t_s, _cols(table, motors).tolist(), _cols(table, [f"f_rotor_{i}_N" for i in range(1, n_rot + 1)]).tolist(), speed)],
        "/battery": [{"t_s": t, "vbat_V": v} for t, v in zip(t_s, table["vbat_V"].to_list())],
    }
    for topic, kind, unit in (("/model/force", "f", "N"), ("/model/torque", "tau", "Nm")):
        meas, mod, res = (_vec(_cols(table, [f"{kind}_{w}_b_{a}_{unit}" for a in xyz])) for w in ("meas", "model", "res"))
        out[topic] = [{"t_s": t, "measured": a, "model": b, "residual": c} for t, a, b, c in zip(t_s, meas, mod, res)]
    return {topic: (t_ns, msgs) for topic, msgs in out.items()}


def write_mcap(table: pl.DataFrame, path: str | Path, start_ns: int, metadata: dict[str, str] | None = None) -> dict[str, int]:
    """Write a residual table as MCAP; returns messages per topic."""
    from mcap.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    counts = {}
    with open(tmp, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="quadcore")
        schema_ids = {name: writer.register_schema(name, "jsonschema", json.dumps(s).encode()) for name, s in SCHEMAS.items()}
        channels = {topic: writer.register_channel(topic, "json", schema_ids[schema]) for topic, schema in TOPICS.items()}
        for topic, (t_ns, msgs) in messages(table, start_ns).items():
            ch = channels[topic]
            for seq, (t, m) in enumerate(zip(t_ns.tolist(), msgs)):
                writer.add_message(ch, log_time=t, data=json.dumps(m).encode(), publish_time=t, sequence=seq)
            counts[topic] = len(msgs)
        writer.add_metadata("quadcore", {"start_ns": str(start_ns), **(metadata or {})})
        writer.finish()
    tmp.replace(path)
    return counts


def anchor_from_file(log_path: str | Path, duration_s: float) -> int:
    """Start time (ns since the Unix epoch): the log file's mtime taken as the end of the flight."""
    return Path(log_path).stat().st_mtime_ns - int(duration_s * 1e9)
