"""The simulated flight as a uSD log: the real logs' header, dropped samples (gaps), sensor noise on the
logged state, motion-capture packets, encoded with :func:`quadcore.logs.logformat.encode`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from quadcore.logs import logformat
from quadcore.logs.units import DEG_TO_RAD, G0_MPS2, RPM_TO_RADPS


class MocapNoise(Protocol):
    """The motion-capture noise the log writer adds (standard deviations)."""

    @property
    def mocap_pos_m(self) -> float: ...

    @property
    def mocap_att_rad(self) -> float: ...


class LogSettings(Protocol):
    """What the log writer reads of a simulation's settings (:class:`quadcore.sim.simulation.SimConfig` is
    one): the dropped samples, the motion-capture packets and their noise. Named here, so that the writer
    imports nothing of the simulation above it."""

    @property
    def noise(self) -> MocapNoise: ...

    @property
    def drop_prob(self) -> float: ...

    @property
    def drop_max_samples(self) -> int: ...

    @property
    def mocap_rate_hz(self) -> float: ...

    @property
    def mocap_jitter_s(self) -> float: ...

    @property
    def mocap_drop_prob(self) -> float: ...

# The real logs' header (jana00..jana33), copied from ``logformat.parse_header``: event ids,
# names, variables, type characters and their order. Hard-coded so the simulator works
# without the shared data set.
FIXED_FREQUENCY = logformat.EventType(
    event_id=0xFFFF,
    name="fixedFrequency",
    variables=(
        "stateEstimate.x", "stateEstimate.y", "stateEstimate.z",
        "stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw",
        "stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz",
        "gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z",
        "rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4",
        "pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm", "pm.vbatMV",
    ),
    type_chars=("f",) * 16 + ("H",) * 4 + ("H", "H", "H", "I", "H"),
)


EST_POSE = logformat.EventType(
    event_id=8,
    name="estPose",
    variables=("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw"),
    type_chars=("f",) * 7,
)


LOG_EVENT_TYPES = (FIXED_FREQUENCY, EST_POSE)


LOG_VERSION = 2


def _quat_noise(q: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """(n, 4) q (x) exp(rotvec), vectorised (small rotations)."""
    th = np.linalg.norm(rotvec, axis=1, keepdims=True)
    s = np.where(th > 1e-12, np.sin(0.5 * th) / np.maximum(th, 1e-300), 0.5)
    d = np.concatenate([rotvec * s, np.cos(0.5 * th)], axis=1)
    x1, y1, z1, w1 = q.T
    x2, y2, z2, w2 = d.T
    out = np.column_stack([
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _drop_mask(n: int, config: LogSettings, rng: np.random.Generator) -> np.ndarray:
    """True for samples kept. Gaps start with probability ``drop_prob`` per sample and last
    1..``drop_max_samples`` samples; the first and last few samples are always kept."""
    kept = np.ones(n, dtype=bool)
    starts = np.flatnonzero(rng.random(n) < config.drop_prob)
    lengths = rng.integers(1, max(config.drop_max_samples, 1) + 1, size=len(starts))
    for s, L in zip(starts, lengths):
        kept[s:s + L] = False
    kept[:5] = True
    kept[-5:] = True
    return kept


def encode(config: LogSettings, t, P, V, Q, W, SF, F_ACT, PWM, VBAT_MV, motor_map, n_pos, n_vel, n_att, n_gyro,
           n_acc, n_rpm, drop_rng, mocap_rng, clock_rng) -> tuple[bytes, np.ndarray]:
    n = len(t)
    noise = config.noise
    kept = _drop_mask(n, config, drop_rng)
    t0_us = int(clock_rng.integers(5_000_000, 200_000_000))  # the deck's clock: time since boot
    ts = t0_us + np.rint(t * 1e6).astype(np.int64)

    q_est = _quat_noise(Q, n_att)
    if motor_map.k_F_N_per_radps2 > 0:
        rpm = motor_map.speed_for_thrust(F_ACT) / RPM_TO_RADPS + n_rpm
    else:
        rpm = np.zeros_like(F_ACT)
    ff = np.empty(n, dtype=FIXED_FREQUENCY.payload_dtype())
    cols = {
        "stateEstimate.x": P[:, 0] + n_pos[:, 0], "stateEstimate.y": P[:, 1] + n_pos[:, 1],
        "stateEstimate.z": P[:, 2] + n_pos[:, 2],
        "stateEstimate.qx": q_est[:, 0], "stateEstimate.qy": q_est[:, 1], "stateEstimate.qz": q_est[:, 2],
        "stateEstimate.qw": q_est[:, 3],
        "stateEstimate.vx": V[:, 0] + n_vel[:, 0], "stateEstimate.vy": V[:, 1] + n_vel[:, 1],
        "stateEstimate.vz": V[:, 2] + n_vel[:, 2],
        "gyro.x": (W[:, 0] + n_gyro[:, 0]) / DEG_TO_RAD, "gyro.y": (W[:, 1] + n_gyro[:, 1]) / DEG_TO_RAD,
        "gyro.z": (W[:, 2] + n_gyro[:, 2]) / DEG_TO_RAD,
        "acc.x": SF[:, 0] / G0_MPS2 + n_acc[:, 0], "acc.y": SF[:, 1] / G0_MPS2 + n_acc[:, 1],
        "acc.z": SF[:, 2] / G0_MPS2 + n_acc[:, 2],
    }
    for i in range(4):
        cols[f"rpm.m{i + 1}"] = np.clip(np.rint(rpm[:, i]), 0, 65535)
        cols[f"pwm.m{i + 1}_pwm"] = np.clip(PWM[:, i], 0, 65535)
    cols["pm.vbatMV"] = np.clip(VBAT_MV, 0, 65535)
    for var in FIXED_FREQUENCY.variables:
        ff[var] = cols[var]

    # motion capture: packets every 1/rate with jitter, some lost; pose interpolated + noise
    period = 1.0 / config.mocap_rate_hz
    tm = np.arange(0.0, t[-1], period)
    tm = tm + mocap_rng.uniform(0.0, config.mocap_jitter_s, size=len(tm))
    tm = tm[(tm >= t[0]) & (tm <= t[-1])]
    tm = tm[mocap_rng.random(len(tm)) >= config.mocap_drop_prob]
    pm = np.column_stack([np.interp(tm, t, P[:, i]) for i in range(3)])
    idx = np.clip(np.searchsorted(t, tm), 1, n - 1)
    frac = ((tm - t[idx - 1]) / (t[idx] - t[idx - 1]))[:, None]
    q0, q1 = Q[idx - 1], Q[idx]
    q1 = np.where((np.sum(q0 * q1, axis=1) < 0)[:, None], -q1, q1)
    qm = (1 - frac) * q0 + frac * q1
    qm /= np.linalg.norm(qm, axis=1, keepdims=True)
    pm = pm + mocap_rng.normal(0.0, noise.mocap_pos_m, pm.shape)
    qm = _quat_noise(qm, mocap_rng.normal(0.0, noise.mocap_att_rad, (len(tm), 3)))
    ep = np.empty(len(tm), dtype=EST_POSE.payload_dtype())
    for i, var in enumerate(("locSrv.x", "locSrv.y", "locSrv.z")):
        ep[var] = pm[:, i]
    for i, var in enumerate(("locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")):
        ep[var] = qm[:, i]
    ts_ep = t0_us + np.rint(tm * 1e6).astype(np.int64)

    data = logformat.encode(list(LOG_EVENT_TYPES),
                            [(FIXED_FREQUENCY.name, ts[kept], ff[kept]), (EST_POSE.name, ts_ep, ep)],
                            version=LOG_VERSION, with_crc=True)
    return data, kept
