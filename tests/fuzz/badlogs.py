"""Physically bad logs: a good log re-encoded with one defect each (values, time, structure).

Each kind is a function ``(event types, records) -> records`` over the decoded log in firmware
units; :func:`bad_logs` returns ``{kind: bytes}``. They decode without error: what is wrong is
the physics they carry, which every later stage must refuse for that flight alone.
"""

from __future__ import annotations

import numpy as np

from quadcore.logs import logformat

MAIN = "fixedFrequency"


def _records(log: logformat.DecodedLog) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """event -> (native timestamps, values as a plain structured array), copies."""
    to_native = logformat.TIMESTAMP_TO_US[log.version]
    out = {}
    for name, et in log.event_types.items():
        values = np.empty(len(log.tables[name]), et.payload_dtype())
        for var in et.variables:
            values[var] = log.tables[name][var]
        out[name] = (log.timestamps_us[name] // to_native, values)
    return out


def _mid(n: int, width: int) -> slice:
    return slice(n // 2, n // 2 + width)


def _set(var: str, value: float, rows=lambda n: _mid(n, 50)):
    def apply(rec):
        _, v = rec[MAIN]
        v[var][rows(len(v))] = value
        return rec
    return apply


def _keep(n_rows: int):
    def apply(rec):
        rec[MAIN] = (rec[MAIN][0][:n_rows], rec[MAIN][1][:n_rows])
        return rec
    return apply


def _time(change):
    def apply(rec):
        ts, v = rec[MAIN]
        rec[MAIN] = (change(ts.copy()), v)
        return rec
    return apply


def _stuck_clock(ts):
    m = _mid(len(ts), 50)
    ts[m] = ts[m][0]
    return ts


def _gap(seconds_native):
    def change(ts):
        ts[len(ts) // 2:] += seconds_native
        return ts
    return change


def _quaternion(scale: float):
    def apply(rec):
        _, v = rec[MAIN]
        m = _mid(len(v), 50)
        for c in ("stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw"):
            v[c][m] = v[c][m] * scale
        return rec
    return apply


def _nan_at_ends(rec):
    _, v = rec[MAIN]
    v["gyro.x"][:5] = np.nan
    v["gyro.x"][-5:] = np.nan
    return rec


def _rename_event(rec):
    rec["renamedEvent"] = rec.pop(MAIN)
    return rec


def _drop_variable(rec):
    ts, v = rec[MAIN]
    names = [n for n in v.dtype.names if n != "stateEstimate.vx"]
    rec[MAIN] = (ts, v[names])
    return rec


def _equal_times(ts):
    ts[:] = ts[0]
    return ts


KINDS = {
    "nan_values": _set("stateEstimate.vx", np.nan),
    "inf_values": _set("acc.z", np.inf),
    "nan_at_ends": _nan_at_ends,
    "huge_values": _set("stateEstimate.vy", 3e38),
    "one_record": _keep(1),
    "no_records": _keep(0),
    "short_flight": _keep(40),
    "equal_timestamps": _time(_equal_times),
    "stuck_clock": _time(_stuck_clock),
    "gap_10s": None,  # needs the time unit: see bad_logs
    "zero_quaternion": _quaternion(0.0),
    "unnormalised_quaternion": _quaternion(3.0),
    "zero_battery": _set("pm.vbatMV", 0, rows=lambda n: slice(None)),
    "stuck_battery": _set("pm.vbatMV", 3700, rows=lambda n: slice(None)),
    "motors_idle": None,
    "missing_event": _rename_event,
    "missing_variable": _drop_variable,
}


def _idle(rec):
    _, v = rec[MAIN]
    for c in v.dtype.names:
        if c.startswith("pwm."):
            v[c] = 0
    return rec


def bad_logs(good: bytes) -> dict[str, bytes]:
    """The 17 kinds of physically bad log, each made from the good log ``good``."""
    log = logformat.decode_bytes(good)
    per_second = 1_000_000 // logformat.TIMESTAMP_TO_US[log.version]
    kinds = {**KINDS, "gap_10s": _time(_gap(10 * per_second)), "motors_idle": _idle}
    out = {}
    for kind, apply in kinds.items():
        rec = apply(_records(log))
        types = []
        for name, (_, v) in rec.items():
            old = log.event_types.get(name, log.event_types[MAIN])  # a renamed event keeps its layout
            chars = tuple(old.type_chars[old.variables.index(n)] for n in v.dtype.names)
            types.append(logformat.EventType(old.event_id, name, tuple(v.dtype.names), chars))
        out[kind] = logformat.encode(types, [(name, ts, v) for name, (ts, v) in rec.items()], version=log.version)
    return out
