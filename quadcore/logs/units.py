"""Firmware units -> SI, with column names that carry frame and unit.

Naming: ``<quantity>_<frame>_<axis>_<unit>``; frames are ``w`` (world, z up) and
``b`` (body: x forward, y left, z up). Quaternions are body-to-world, stored
``q_x, q_y, q_z, q_w`` (scalar last, as logged). Motors are numbered as in the
firmware (1 front-right, 2 back-right, 3 back-left, 4 front-left).

Each logged variable maps to ``(column, scale, unit, description)``; the SI value
is ``raw * scale``. Variables not listed pass through unscaled with unit ``raw``.
"""

from __future__ import annotations

import math
import re

import numpy as np
import polars as pl

G0_MPS2 = 9.80665  # standard gravity: the firmware's accelerometer unit "g"
DEG_TO_RAD = math.pi / 180.0
RPM_TO_RADPS = 2.0 * math.pi / 60.0
PWM_FULL_SCALE = 65535.0

# logged name -> (SI column, scale, unit, description)
SI_COLUMNS: dict[str, tuple[str, float, str, str]] = {
    "stateEstimate.x": ("p_w_x_m", 1.0, "m", "estimated position, world x"),
    "stateEstimate.y": ("p_w_y_m", 1.0, "m", "estimated position, world y"),
    "stateEstimate.z": ("p_w_z_m", 1.0, "m", "estimated position, world z (up)"),
    "stateEstimate.qx": ("q_x", 1.0, "1", "attitude quaternion body->world, x"),
    "stateEstimate.qy": ("q_y", 1.0, "1", "attitude quaternion body->world, y"),
    "stateEstimate.qz": ("q_z", 1.0, "1", "attitude quaternion body->world, z"),
    "stateEstimate.qw": ("q_w", 1.0, "1", "attitude quaternion body->world, w (scalar)"),
    "stateEstimate.vx": ("v_w_x_mps", 1.0, "m/s", "estimated velocity, world x"),
    "stateEstimate.vy": ("v_w_y_mps", 1.0, "m/s", "estimated velocity, world y"),
    "stateEstimate.vz": ("v_w_z_mps", 1.0, "m/s", "estimated velocity, world z"),
    "gyro.x": ("omega_b_x_radps", DEG_TO_RAD, "rad/s", "gyro angular rate, body x (from deg/s)"),
    "gyro.y": ("omega_b_y_radps", DEG_TO_RAD, "rad/s", "gyro angular rate, body y (from deg/s)"),
    "gyro.z": ("omega_b_z_radps", DEG_TO_RAD, "rad/s", "gyro angular rate, body z (from deg/s)"),
    "acc.x": ("sf_b_x_mps2", G0_MPS2, "m/s^2", "accelerometer specific force, body x (from g)"),
    "acc.y": ("sf_b_y_mps2", G0_MPS2, "m/s^2", "accelerometer specific force, body y (from g)"),
    "acc.z": ("sf_b_z_mps2", G0_MPS2, "m/s^2", "accelerometer specific force, body z (from g)"),
    "rpm.m1": ("motor_1_radps", RPM_TO_RADPS, "rad/s", "motor 1 speed (front-right), from rpm"),
    "rpm.m2": ("motor_2_radps", RPM_TO_RADPS, "rad/s", "motor 2 speed (back-right), from rpm"),
    "rpm.m3": ("motor_3_radps", RPM_TO_RADPS, "rad/s", "motor 3 speed (back-left), from rpm"),
    "rpm.m4": ("motor_4_radps", RPM_TO_RADPS, "rad/s", "motor 4 speed (front-left), from rpm"),
    "pwm.m1_pwm": ("pwm_1", 1.0 / PWM_FULL_SCALE, "1", "motor 1 PWM duty, 0..1"),
    "pwm.m2_pwm": ("pwm_2", 1.0 / PWM_FULL_SCALE, "1", "motor 2 PWM duty, 0..1"),
    "pwm.m3_pwm": ("pwm_3", 1.0 / PWM_FULL_SCALE, "1", "motor 3 PWM duty, 0..1"),
    "pwm.m4_pwm": ("pwm_4", 1.0 / PWM_FULL_SCALE, "1", "motor 4 PWM duty, 0..1"),
    "pm.vbatMV": ("vbat_V", 1e-3, "V", "battery voltage (from mV)"),
    "locSrv.x": ("mocap_p_w_x_m", 1.0, "m", "motion-capture position, world x"),
    "locSrv.y": ("mocap_p_w_y_m", 1.0, "m", "motion-capture position, world y"),
    "locSrv.z": ("mocap_p_w_z_m", 1.0, "m", "motion-capture position, world z"),
    "locSrv.qx": ("mocap_q_x", 1.0, "1", "motion-capture quaternion body->world, x"),
    "locSrv.qy": ("mocap_q_y", 1.0, "1", "motion-capture quaternion body->world, y"),
    "locSrv.qz": ("mocap_q_z", 1.0, "1", "motion-capture quaternion body->world, z"),
    "locSrv.qw": ("mocap_q_w", 1.0, "1", "motion-capture quaternion body->world, w"),
}

TIME_COLUMN = "t_s"
RAW_TIME_COLUMN = "timestamp_us"


def si_name(variable: str) -> str:
    """The SI column name of a logged variable (unknown ones are sanitised, unit raw)."""
    if variable in SI_COLUMNS:
        return SI_COLUMNS[variable][0]
    return re.sub(r"[^0-9A-Za-z]+", "_", variable).strip("_") + "_raw"


def to_si(
    values: np.ndarray, timestamps_us: np.ndarray, t0_us: int
) -> tuple[pl.DataFrame, dict[str, dict[str, str]]]:
    """Convert one event table (structured array, firmware units) to SI.

    Returns the table and ``{column: {"unit": ..., "description": ..., "source": ...}}``.
    ``t_s`` is seconds since ``t0_us`` (the flight's first timestamp over all event types);
    the raw timestamp is kept as integer microseconds.
    """
    columns: dict[str, np.ndarray] = {
        TIME_COLUMN: (timestamps_us - t0_us).astype(np.float64) * 1e-6,
        RAW_TIME_COLUMN: timestamps_us.astype(np.int64),
    }
    units: dict[str, dict[str, str]] = {
        TIME_COLUMN: {"unit": "s", "description": "time since flight start", "source": "timestamp"},
        RAW_TIME_COLUMN: {"unit": "us", "description": "raw log timestamp", "source": "timestamp"},
    }
    for var in values.dtype.names or ():
        name, scale, unit, desc = SI_COLUMNS.get(var, (si_name(var), 1.0, "raw", "unconverted"))
        base, k = name, 2
        while name in columns:  # two variables with one SI name ("a.b", "a_b"): keep both
            name, k = f"{base}_{k}", k + 1
        # float32 keeps the logged precision (float32 or 16-bit values, scaled); time stays float64
        col = values[var].astype(np.float32)
        with np.errstate(over="ignore", invalid="ignore"):  # a damaged value becomes inf: the checks say so
            columns[name] = col if scale == 1.0 else col * np.float32(scale)
        units[name] = {"unit": unit, "description": desc, "source": var}
    return pl.DataFrame(columns), units

