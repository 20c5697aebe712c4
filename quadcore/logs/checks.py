"""Plausibility checks on a decoded flight, as plain data (the pipeline turns them into
asset checks). Each returns ``(passed, description, metrics)``; none raises.

These look at the log alone. The gate before any physics (which flights the physics can use, and
the check ``usable_for_physics``) is :mod:`quadcore.physics.gate`, whose ``ALL_CHECKS`` adds it to
:data:`LOG_CHECKS`.
"""

from __future__ import annotations

import numpy as np
import polars as pl

# Physically plausible ranges for a small quadrotor (SI). Values outside are flagged, not dropped.
VALUE_RANGES = {
    "p_w_x_m": (-20.0, 20.0),
    "p_w_y_m": (-20.0, 20.0),
    "p_w_z_m": (-1.0, 20.0),
    "v_w_x_mps": (-15.0, 15.0),
    "v_w_y_mps": (-15.0, 15.0),
    "v_w_z_mps": (-15.0, 15.0),
    "omega_b_x_radps": (-35.0, 35.0),  # the gyro's 2000 deg/s full scale
    "omega_b_y_radps": (-35.0, 35.0),
    "omega_b_z_radps": (-35.0, 35.0),
    "sf_b_x_mps2": (-160.0, 160.0),  # the accelerometer's 16 g full scale
    "sf_b_y_mps2": (-160.0, 160.0),
    "sf_b_z_mps2": (-160.0, 160.0),
    "vbat_V": (2.5, 4.5),
    "pwm_1": (0.0, 1.0),
    "pwm_2": (0.0, 1.0),
    "pwm_3": (0.0, 1.0),
    "pwm_4": (0.0, 1.0),
}
GAP_WARN_S = 0.05


def monotonic_time(df: pl.DataFrame) -> tuple[bool, str, dict]:
    t = df["t_s"].to_numpy()
    backwards = int(np.count_nonzero(np.diff(t) <= 0)) if len(t) > 1 else 0
    return backwards == 0, f"{backwards} non-increasing timestamps", {"non_increasing": backwards}


def sample_gaps(df: pl.DataFrame, limit_s: float = GAP_WARN_S) -> tuple[bool, str, dict]:
    t = df["t_s"].to_numpy()
    dt = np.diff(t) if len(t) > 1 else np.zeros(1)
    n = int(np.count_nonzero(dt > limit_s))
    return n == 0, f"{n} gaps longer than {limit_s * 1e3:.0f} ms (longest {dt.max() * 1e3:.1f} ms)", {
        "gaps": n,
        "dt_max_ms": float(dt.max() * 1e3),
    }


def value_ranges(df: pl.DataFrame) -> tuple[bool, str, dict]:
    bad = {}
    for col, (lo, hi) in VALUE_RANGES.items():
        if col in df.columns:
            n = df.filter((pl.col(col) < lo) | (pl.col(col) > hi)).height
            if n:
                bad[col] = n
    desc = "all values in range" if not bad else "out of range: " + ", ".join(f"{c} ({n} rows)" for c, n in bad.items())
    return not bad, desc, {"columns_out_of_range": len(bad)}


def no_nans(df: pl.DataFrame) -> tuple[bool, str, dict]:
    counts = {c: int(df[c].is_nan().sum()) for c, dt in df.schema.items() if dt.is_float()}
    bad = {c: n for c, n in counts.items() if n}
    desc = "no NaN" if not bad else "NaN in " + ", ".join(f"{c} ({n})" for c, n in bad.items())
    return not bad, desc, {"nan_values": sum(bad.values())}


def stuck_sensors(df: pl.DataFrame, min_rows: int = 500) -> tuple[bool, str, dict]:
    """A sensor column that never changes over a whole flight is stuck (e.g. vbat at 3.7 V)."""
    if df.height < min_rows:
        return True, "too short to judge", {"stuck_columns": 0}
    skip = {"t_s", "timestamp_us"}
    stuck = [c for c, dt in df.schema.items() if dt.is_numeric() and c not in skip and df[c].n_unique() == 1]
    desc = "no stuck sensor" if not stuck else "constant over the whole flight: " + ", ".join(stuck)
    return not stuck, desc, {"stuck_columns": len(stuck)}


def has_flight_phase(df: pl.DataFrame, min_move_m: float = 0.05, min_height_m: float = 0.1,
                     min_pwm: float = 0.3) -> tuple[bool, str, dict]:
    """A flight log should contain flight: motors driven, and the vehicle moving or off the ground."""
    pos = [c for c in ("p_w_x_m", "p_w_y_m", "p_w_z_m") if c in df.columns]
    pwm_cols = [c for c in df.columns if c.startswith("pwm_")]
    if df.height == 0 or len(pos) < 3 or not pwm_cols:
        return False, "no position or PWM columns to judge", {}
    move = max(float(df.select(pl.col(c).max() - pl.col(c).min()).item()) for c in pos)
    z_max = float(df.select(pl.col("p_w_z_m").max()).item())
    pwm_max = float(df.select(pwm_cols).max().max_horizontal()[0])
    ok = pwm_max >= min_pwm and (move >= min_move_m or z_max >= min_height_m)
    desc = (f"largest position range {move:.2f} m, highest z {z_max:.2f} m, highest PWM {pwm_max:.2f}"
            + ("" if ok else ": no flight phase (motors idle, or the vehicle never moved nor left the ground)"))
    return ok, desc, {"position_range_m": move, "z_max_m": z_max, "pwm_max": pwm_max}


LOG_CHECKS = {
    "monotonic_time": monotonic_time,
    "sample_gaps": sample_gaps,
    "value_ranges": value_ranges,
    "no_nans": no_nans,
    "stuck_sensors": stuck_sensors,
    "has_flight_phase": has_flight_phase,
}

# What each check looks for, for the UI (every check is a warning: a flight that fails one is
# still decoded; the physics skips only the flights the physics gate refuses).
LOG_CHECK_DESCRIPTIONS = {
    "monotonic_time": "Timestamps always increase (a log whose clock runs backwards is broken).",
    "sample_gaps": f"No gap between samples longer than {GAP_WARN_S * 1e3:.0f} ms (the deck logs at 500 Hz; "
                   "long gaps blur derivatives, and rows near them are left out of fits).",
    "value_ranges": "Every SI value within what a small quadrotor can do (position, velocity, rates, "
                    "accelerometer full scale, battery 2.5-4.5 V, PWM 0-1).",
    "no_nans": "No NaN in any column.",
    "stuck_sensors": "No sensor constant over the whole flight (e.g. a battery voltage stuck at 3.70 V, "
                     "which makes the PWM/voltage thrust map see the wrong voltage).",
    "has_flight_phase": "The log holds flight: motors driven and the vehicle moving or off the ground.",
}
