"""Export a flight as MCAP for Foxglove, protobuf-encoded.

Channels (one message per logged sample)::

    /tf               foxglove.FrameTransform   world -> body: the 3D panel shows the vehicle
    /pose             foxglove.PoseInFrame      the same pose, for plots and the pose panel
    /imu              quadcore.Imu              gyro rad/s, specific force m/s^2 (body frame)
    /motors           quadcore.Motors           PWM 0..1, rotor thrust from the map N, motor speed rad/s
    /battery          quadcore.Battery          voltage V
    /model/force      quadcore.Wrench3          measured, modelled, residual body force N
    /model/torque     quadcore.Wrench3          measured, modelled, residual body torque N m

The pose topics use Foxglove's well-known schemas (``foxglove-schemas-protobuf``), which
Foxglove renders natively; the others are small ``quadcore.*`` messages built on
``foxglove.Vector3`` and ``google.protobuf.Timestamp``. Each schema record holds the full
``FileDescriptorSet``, so any protobuf reader decodes the file without our code.

Time: the logs count from power-on; ``start_ns`` (ns since the Unix epoch) anchors the first
sample. The decoder records it once per flight in its provenance (see
:func:`quadcore.logs.flight.settle_start_time`); it and the flight-relative ``t_s`` are in the file's
metadata record ``quadcore``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import foxglove
import numpy as np
import polars as pl
from foxglove.mcap import MCAPWriteOptions
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.timestamp_pb2 import Timestamp

from quadcore.store import store

XYZ = "xyz"
_F = descriptor_pb2.FieldDescriptorProto

# Our own messages: field name -> (type, repeated). Vectors are foxglove.Vector3.
QUADCORE_MESSAGES = {
    "Imu": {"gyro_b_radps": ".foxglove.Vector3", "specific_force_b_mps2": ".foxglove.Vector3"},
    "Motors": {"pwm": "repeated double", "thrust_N": "repeated double", "speed_radps": "repeated double"},
    "Battery": {"vbat_V": "double"},
    "Wrench3": {"measured": ".foxglove.Vector3", "model": ".foxglove.Vector3", "residual": ".foxglove.Vector3"},
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


def _quadcore_file() -> descriptor_pb2.FileDescriptorProto:
    """``quadcore/flight.proto``: every message has ``timestamp`` and the flight-relative ``t_s``."""
    fdp = descriptor_pb2.FileDescriptorProto(
        name="quadcore/flight.proto", package="quadcore", syntax="proto3",
        dependency=["google/protobuf/timestamp.proto", "foxglove/Vector3.proto"])
    for name, fields in QUADCORE_MESSAGES.items():
        msg = fdp.message_type.add(name=name)
        msg.field.add(name="timestamp", number=1, type=_F.TYPE_MESSAGE, type_name=".google.protobuf.Timestamp",
                      label=_F.LABEL_OPTIONAL)
        msg.field.add(name="t_s", number=2, type=_F.TYPE_DOUBLE, label=_F.LABEL_OPTIONAL)
        for number, (field, kind) in enumerate(fields.items(), start=3):
            if kind.startswith("."):
                msg.field.add(name=field, number=number, type=_F.TYPE_MESSAGE, type_name=kind, label=_F.LABEL_OPTIONAL)
            else:
                label = _F.LABEL_REPEATED if kind.startswith("repeated") else _F.LABEL_OPTIONAL
                msg.field.add(name=field, number=number, type=_F.TYPE_DOUBLE, label=label)
    return fdp


def _file_protos(descriptor) -> list[descriptor_pb2.FileDescriptorProto]:
    """The file of a message descriptor and every file it imports, dependencies first."""
    out, seen = [], set()

    def visit(file):
        if file.name in seen:
            return
        seen.add(file.name)
        for dep in file.dependencies:
            visit(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        file.CopyToProto(proto)
        out.append(proto)

    visit(descriptor.file)
    return out


def _build_classes() -> tuple[dict[str, Any], dict[str, bytes]]:
    """Message classes and schema records (serialized ``FileDescriptorSet``) by full name."""
    pool = descriptor_pool.DescriptorPool()
    for proto in [*_file_protos(Vector3.DESCRIPTOR), *_file_protos(Timestamp.DESCRIPTOR), _quadcore_file()]:
        try:
            pool.Add(proto)
        except TypeError:  # already added (Timestamp is a dependency of several files)
            pass
    classes: dict[str, Any] = {"foxglove.FrameTransform": FrameTransform, "foxglove.PoseInFrame": PoseInFrame}
    for name in QUADCORE_MESSAGES:
        classes[f"quadcore.{name}"] = message_factory.GetMessageClass(pool.FindMessageTypeByName(f"quadcore.{name}"))
    schemas = {name: descriptor_pb2.FileDescriptorSet(file=_file_protos(cls.DESCRIPTOR)).SerializeToString()
               for name, cls in classes.items()}
    return classes, schemas


CLASSES, SCHEMAS = _build_classes()



def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def _constant(data: bytes, n: int) -> np.ndarray:
    return np.tile(np.frombuffer(data, np.uint8), (n, 1))


def _varint5(values: np.ndarray) -> np.ndarray:
    """Integers 0 <= v < 2**35 as five-byte varints (padded with continuation bytes, which every
    protobuf parser accepts), so that every message of a topic has the same length."""
    v = np.asarray(values, np.int64)
    if v.size and (v.min() < 0 or v.max() >= 1 << 35):
        raise ValueError("timestamp out of range for the MCAP export (before 1970 or after 3058)")
    return np.stack([((v >> (7 * k)) & 0x7F) | (0x80 if k < 4 else 0) for k in range(5)], axis=1).astype(np.uint8)


def _encode(descriptor, values: dict, n: int) -> np.ndarray:
    """``n`` protobuf messages of type ``descriptor`` as an (n, width) byte array, built column by
    column (no per-row Python). ``values``: field name -> a constant string, an (n,) or (n, k)
    array (scalar or repeated double, integer), or a dict for a message field. Field numbers
    and types come from the descriptor; every field is written, so each row has one width."""
    blocks = []
    for name, value in values.items():
        field = descriptor.fields_by_name[name]
        if field.type == _F.TYPE_MESSAGE:
            body = _encode(field.message_type, value, n)
            blocks += [_constant(_varint(field.number << 3 | 2) + _varint(body.shape[1]), n), body]
        elif field.type == _F.TYPE_STRING:
            data = value.encode()
            blocks.append(_constant(_varint(field.number << 3 | 2) + _varint(len(data)) + data, n))
        elif field.type == _F.TYPE_DOUBLE:
            arr = np.ascontiguousarray(np.asarray(value, "<f8").reshape(n, -1))
            raw = arr.view(np.uint8).reshape(n, -1)
            if field.is_repeated:  # packed
                head = _varint(field.number << 3 | 2) + _varint(raw.shape[1])
            else:
                head = _varint(field.number << 3 | 1)
            blocks += [_constant(head, n), raw]
        else:  # int32 / int64 (the Timestamp's seconds and nanos)
            blocks += [_constant(_varint(field.number << 3 | 0), n), _varint5(value)]
    return np.hstack(blocks) if blocks else np.zeros((n, 0), np.uint8)


def _cols(table: pl.DataFrame, names: list[str]) -> np.ndarray:
    return table.select(names).to_numpy().astype(np.float64)


def _vec(table: pl.DataFrame, names: list[str], keys: str = "xyz") -> dict:
    arr = _cols(table, names)
    return {k: arr[:, i] for i, k in enumerate(keys)}


def topic_values(table: pl.DataFrame, stamp: dict) -> dict[str, dict]:
    """Topic -> field values for :func:`_encode`, from a residual table; ``stamp`` is the
    Timestamp's {seconds, nanos} per row."""
    p = _vec(table, ["p_w_x_m", "p_w_y_m", "p_w_z_m"])
    q = _vec(table, ["q_x", "q_y", "q_z", "q_w"], "xyzw")
    t = {"timestamp": stamp, "t_s": table["t_s"].to_numpy()}
    pwm = sorted(c for c in table.columns if c.startswith("pwm_"))
    rotors = range(1, len(pwm) + 1)
    speed = [f"motor_{i}_radps" for i in rotors]
    motors = {"pwm": _cols(table, pwm), "thrust_N": _cols(table, [f"f_rotor_{i}_N" for i in rotors])}
    if all(c in table.columns for c in speed):
        motors["speed_radps"] = _cols(table, speed)
    out: dict[str, dict] = {
        "/tf": {"timestamp": stamp, "parent_frame_id": "world", "child_frame_id": "body", "translation": p,
                "rotation": q},
        "/pose": {"timestamp": stamp, "frame_id": "world", "pose": {"position": p, "orientation": q}},
        "/imu": {**t, "gyro_b_radps": _vec(table, [f"omega_b_{a}_radps" for a in XYZ]),
                 "specific_force_b_mps2": _vec(table, [f"sf_b_{a}_mps2" for a in XYZ])},
        "/motors": {**t, **motors},
        "/battery": {**t, "vbat_V": table["vbat_V"].to_numpy()},
    }
    for topic, kind, unit in (("/model/force", "f", "N"), ("/model/torque", "tau", "Nm")):
        out[topic] = {**t, **{field: _vec(table, [f"{kind}_{col}_b_{a}_{unit}" for a in XYZ])
                              for field, col in (("measured", "meas"), ("model", "model"), ("residual", "res"))}}
    return out


def write_mcap(table: pl.DataFrame, path: str | Path, start_ns: int,
               metadata: dict[str, str] | None = None) -> dict[str, int]:
    """Write a residual table as MCAP (protobuf messages, zstd chunks, written by the Foxglove
    SDK's MCAP writer); returns messages per topic. Log time of a sample = ``start_ns`` + its ``t_s``."""
    t_ns = start_ns + np.round(table["t_s"].to_numpy() * 1e9).astype(np.int64)
    stamp = {"seconds": t_ns // 1_000_000_000, "nanos": t_ns % 1_000_000_000}
    times = t_ns.tolist()
    counts = {}

    def write(tmp: str) -> None:
        context = foxglove.Context()  # this file's channels only
        options = MCAPWriteOptions(profile="", compression_threads=0)
        with foxglove.open_mcap(tmp, allow_overwrite=True, context=context, writer_options=options) as writer:
            for topic, values in topic_values(table, stamp).items():
                name = TOPICS[topic]
                schema = foxglove.Schema(name=name, encoding="protobuf", data=SCHEMAS[name])
                channel = foxglove.Channel(topic, message_encoding="protobuf", schema=schema, context=context)
                rows = _encode(CLASSES[name].DESCRIPTOR, values, table.height)
                data, width = rows.tobytes(), rows.shape[1]
                log = channel.log
                for i, t in enumerate(times):
                    log(data[i * width:(i + 1) * width], log_time=t)
                counts[topic] = len(times)
            writer.write_metadata("quadcore", {"start_ns": str(start_ns), **(metadata or {})})

    store.atomic_write(path, write)
    return counts
