"""The physics gate: which decoded flights the physics can use, and why not.

:func:`physics_problem` is the gate before any physics: a flight it refuses (too few rows,
time not increasing, non-finite or absurd values, quaternions far from unit length, a state
estimate whose position or velocity its own velocity or accelerometer cannot explain) is
skipped by every fleet stage with its reason, and the per-flight stages fail for it alone
(:func:`quadcore.physics.dynamics.flight_state` raises). The columns the physics reads
(:data:`NOMINAL_COLUMNS`, :func:`required_columns`) live here too, so that the gate sits below the
dynamics that call it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import polars as pl

from quadcore.logs.checks import LOG_CHECK_DESCRIPTIONS, LOG_CHECKS, has_flight_phase
from quadcore.logs.required import logged_as
from quadcore.physics import rotations
from quadcore.physics.vehicle import Vehicle
from quadcore.store import codedigest

XYZ = ("x", "y", "z")


def cols(prefix: str, unit: str) -> list[str]:
    """``cols("v_w", "mps")`` -> ``["v_w_x_mps", "v_w_y_mps", "v_w_z_mps"]``."""
    return [f"{prefix}_{a}_{unit}" for a in XYZ]


NOMINAL_COLUMNS = ["t_s", *cols("p_w", "m"), *cols("v_w", "mps"), "q_x", "q_y", "q_z", "q_w",
                   *cols("omega_b", "radps"), *cols("sf_b", "mps2"), "vbat_V", "pwm_1", "pwm_2", "pwm_3", "pwm_4"]


def required_columns(vehicle: Vehicle) -> list[str]:
    """The SI columns :func:`quadcore.physics.dynamics.flight_state` needs for this vehicle and thrust map."""
    need = [c for c in NOMINAL_COLUMNS if not c.startswith("pwm_")]
    need += [f"pwm_{i}" for i in range(1, vehicle.n_rotors + 1)]
    if vehicle.thrust_map_kind == "motor_speed":
        need += [f"motor_{i}_radps" for i in range(1, vehicle.n_rotors + 1)]
    return need


MIN_ROWS = 250  # 0.5 s at 500 Hz: less cannot fill the smoothing window and a 0.1 s rollout
QUATERNION_NORM_TOL = 0.05  # the estimator keeps |q| = 1 to float32 precision; 5 % is a broken log
VBAT_MIN_V = 2.5  # a 1S LiPo is flat at 3.0 V; below 2.5 V the logged voltage is wrong, not low
MAX_ABS_VALUE = 1e4  # no SI value of a small quadrotor comes near this (PWM <= 1, rates <= 35 rad/s)
# The state estimate's own consistency (see state_estimate_problem): thresholds over any window of
# CONSISTENCY_WINDOW_S, in what they mean physically.
CONSISTENCY_WINDOW_S = 0.1
MAX_POSITION_DRIFT_M = 0.25  # 2.5 m/s of motion the velocity does not carry; real flights: <= 0.021 m
MAX_VELOCITY_DRIFT_MPS = 1.0  # 10 m/s^2 (1 g) the accelerometer does not see; real flights: <= 0.066 m/s
MAX_INTEGRATION_GAP_S = 0.2  # no integration across a longer gap between samples (the logs' longest: ~0.12 s)
STATE_COLUMNS = ("p_w_x_m", "p_w_y_m", "p_w_z_m", "v_w_x_mps", "v_w_y_mps", "v_w_z_mps", "q_x", "q_y", "q_z", "q_w",
                 "sf_b_x_mps2", "sf_b_y_mps2", "sf_b_z_mps2")


@dataclass(frozen=True)
class PhysicsFacts:
    """What the physics gate (:func:`physics_problem`) finds in one decoded table, for any
    columns the physics may read (another vehicle reads other PWM or motor columns): recorded in
    the decoded main table's footer (:func:`quadcore.physics.decoded_store.write_decoded`), so that a fleet
    stage decides which flights it can use without reading their rows."""

    columns: tuple[str, ...]  # every column of the table
    early: str | None  # too few samples, or time not increasing: refused whatever the columns
    bad_values: dict[str, int] = field(default_factory=dict)  # per column checked: non-finite or absurd values
    quaternion: str | None = None
    vbat_low: int = 0  # samples below VBAT_MIN_V
    flight_phase: str | None = None  # why there is no flight phase, or None
    state_estimate: str | None = None  # how the state estimate contradicts itself, or None

    def covers(self, columns: list[str]) -> bool:
        """Whether these facts decide :meth:`problem` for ``columns`` (each value column checked)."""
        return self.early is not None or all(c in self.bad_values for c in columns if c != "t_s")

    def problem(self, columns: list[str]) -> str | None:
        """:func:`physics_problem` of the table for ``columns`` (which :meth:`covers` them)."""
        if self.early is not None:
            return self.early
        worst = ", ".join(f"{c} ({self.bad_values[c]} rows)" for c in columns if c != "t_s" and self.bad_values[c])
        if worst:
            return f"non-finite or absurd (|x| > {MAX_ABS_VALUE:g}) values in {worst}"
        if self.quaternion is not None:
            return self.quaternion
        if self.state_estimate is not None:
            return self.state_estimate
        if "vbat_V" in columns and self.vbat_low:
            return f"battery voltage below {VBAT_MIN_V} V in {self.vbat_low} rows: the thrust map cannot use it"
        return self.flight_phase

    def to_dict(self) -> dict:
        """The footer's document, with the digest of the code that found the facts (:func:`facts_digest`)."""
        return {"columns": list(self.columns), "early": self.early, "bad_values": self.bad_values,
                "quaternion": self.quaternion, "vbat_low": self.vbat_low, "flight_phase": self.flight_phase,
                "state_estimate": self.state_estimate, "code": facts_digest()}

    @classmethod
    def from_dict(cls, d) -> PhysicsFacts | None:
        """The facts of a footer's document, or None when it holds none (or not readable ones, or
        ones found by other code than this, :func:`facts_digest`, such as before the state
        estimate's consistency was checked: the table is then read)."""
        try:
            if d["code"] != facts_digest():
                return None
            return cls(tuple(d["columns"]), d["early"], {str(k): int(v) for k, v in d["bad_values"].items()},
                       d["quaternion"], int(d["vbat_low"]), d["flight_phase"], d["state_estimate"])
        except (KeyError, TypeError, ValueError, AttributeError):
            return None


# The code the facts recorded in a decoded table's footer come from: this module's checks, the log's
# checks (its flight phase) and the quaternion helpers. Facts recorded by other code are not used.
FACTS_MODULES = ("quadcore.physics.gate", "quadcore.logs.checks", "quadcore.physics.rotations")


@functools.lru_cache(maxsize=1)
def facts_digest() -> str:
    """The digest of :data:`FACTS_MODULES`' source (once per process)."""
    return codedigest.modules_digest(FACTS_MODULES)


def physics_facts(df: pl.DataFrame, columns: list[str] | None = None) -> PhysicsFacts:
    """The :class:`PhysicsFacts` of a table, its values checked on ``columns`` (default: every
    numeric one)."""
    if columns is None:
        columns = [c for c, dt in df.schema.items() if dt.is_numeric()]
    if df.height < MIN_ROWS:
        return PhysicsFacts(tuple(df.columns), f"{df.height} samples; the physics needs at least {MIN_ROWS}")
    t = df["t_s"].to_numpy()
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        return PhysicsFacts(tuple(df.columns),
                            f"time does not increase at {len(back)} samples (first at t = {t[back[0]]:.3f} s)")
    value_columns = [c for c in columns if c != "t_s"]
    values = df.select(value_columns).to_numpy().astype(np.float64)
    bad = (~np.isfinite(values) | (np.abs(values) > MAX_ABS_VALUE)).sum(axis=0)
    quaternion = None
    if {"q_x", "q_y", "q_z", "q_w"} <= set(df.columns):
        norm = np.linalg.norm(df.select("q_x", "q_y", "q_z", "q_w").to_numpy().astype(np.float64), axis=1)
        off = int(np.count_nonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOL))
        if off:
            quaternion = (f"{off} attitude quaternions are not unit length "
                          f"(|q| from {norm.min():.3g} to {norm.max():.3g})")
    low = int((df["vbat_V"] < VBAT_MIN_V).sum()) if "vbat_V" in df.columns else 0
    flew, desc, _ = has_flight_phase(df)
    finite_state = all(n == 0 for c, n in zip(value_columns, bad) if c in STATE_COLUMNS)
    state = state_estimate_problem(df) if quaternion is None and finite_state else None
    return PhysicsFacts(tuple(df.columns), None, {c: int(n) for c, n in zip(value_columns, bad)}, quaternion, low,
                        None if flew else desc, state)


def _window_drift(t_s: np.ndarray, y: np.ndarray, dydt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(for each sample i, |(y(j) - y(i)) - integral of dydt from t_i to t_j|, with t_j the first
    sample at least CONSISTENCY_WINDOW_S later; the index i), the integral by the trapezoid rule
    over each interval no longer than MAX_INTEGRATION_GAP_S (a longer gap restarts it)."""
    dt = np.diff(t_s)
    step = np.diff(y, axis=0) - 0.5 * (dydt[1:] + dydt[:-1]) * dt[:, None]
    step[dt > MAX_INTEGRATION_GAP_S] = 0.0
    drift = np.vstack([np.zeros((1, y.shape[1])), np.cumsum(step, axis=0)])
    j = np.searchsorted(t_s, t_s + CONSISTENCY_WINDOW_S)
    i = np.flatnonzero(j < len(t_s))
    return np.linalg.norm(drift[j[i]] - drift[i], axis=1), i


def state_estimate_problem(df: pl.DataFrame) -> str | None:
    """How the state estimate contradicts itself, or None (also when it lacks a column).

    Over every window of ``CONSISTENCY_WINDOW_S`` (0.1 s), in the world frame:

    - position against integrated velocity: ``|p_w(t+T) - p_w(t) - int v_w dt| <=
      MAX_POSITION_DRIFT_M`` (0.25 m: an unlogged 2.5 m/s, half the Crazyflie's top speed; the
      estimator moves its position by mocap corrections of millimetres to centimetres);
    - velocity against integrated acceleration ``a_w = R(q) sf_b + g_w`` (the accelerometer's
      specific force rotated into the world frame, plus gravity): ``|v_w(t+T) - v_w(t) -
      int a_w dt| <= MAX_VELOCITY_DRIFT_MPS`` (1 m/s: an unlogged 1 g; a calibrated MEMS
      accelerometer's bias of < 0.5 m/s^2 makes 0.05 m/s).

    On the 19 real flights the largest drifts are 0.021 m and 0.066 m/s (12x and 15x below the
    limits); a position jump of 100 m, or a velocity spike of a few m/s that the accelerometer
    does not see, fails. Integration restarts after a gap longer than MAX_INTEGRATION_GAP_S."""
    if not set(STATE_COLUMNS) <= set(df.columns) or df.height < 2:
        return None
    t = df["t_s"].to_numpy().astype(np.float64)
    p = df.select("p_w_x_m", "p_w_y_m", "p_w_z_m").to_numpy().astype(np.float64)
    v = df.select("v_w_x_mps", "v_w_y_mps", "v_w_z_mps").to_numpy().astype(np.float64)
    q = df.select("q_x", "q_y", "q_z", "q_w").to_numpy().astype(np.float64)
    sf = df.select("sf_b_x_mps2", "sf_b_y_mps2", "sf_b_z_mps2").to_numpy().astype(np.float64)
    a = rotations.body_to_world(rotations.rotation_matrix(q), sf) + rotations.GRAVITY_W_MPS2
    for what, y, dydt, limit, unit in (("position", p, v, MAX_POSITION_DRIFT_M, "m"),
                                        ("velocity", v, a, MAX_VELOCITY_DRIFT_MPS, "m/s")):
        drift, i = _window_drift(t, y, dydt)
        over = np.flatnonzero(drift > limit)
        if len(over):
            worst = over[np.argmax(drift[over])]
            source = "the velocity" if what == "position" else "the accelerometer"
            return (f"the state estimate contradicts itself: its {what} moves up to {drift[worst]:.3g} {unit} more "
                    f"than {source} explains within {CONSISTENCY_WINDOW_S:g} s (at most {limit:g} {unit}; "
                    f"{len(over)} windows, the worst at t = {t[i[worst]]:.3f} s)")
    return None


def physics_problem(df: pl.DataFrame, columns: list[str]) -> str | None:
    """Why the physics cannot use this flight (``columns``: the ones it reads), or None: in
    order, too few samples, time not increasing, non-finite or absurd values, quaternions off
    unit length, a state estimate that contradicts itself (:func:`state_estimate_problem`), a
    battery voltage below :data:`VBAT_MIN_V`, no flight phase."""
    return physics_facts(df, columns).problem(columns)


def usable_for_physics(df: pl.DataFrame) -> tuple[bool, str, dict]:
    """The physics gate as a check, on the columns the nominal quadrotor model reads."""
    missing = [c for c in NOMINAL_COLUMNS if c not in df.columns]
    problem = f"missing columns: {logged_as(missing)}" if missing else physics_problem(df, NOMINAL_COLUMNS)
    return problem is None, problem or "usable for the physics", {}


def usable_flights(tables: Mapping[str, pl.DataFrame], vehicle: Vehicle,
                   facts: Callable[[str], PhysicsFacts | None] | None = None) -> tuple[list[str], dict[str, str]]:
    """(ids of the flights the physics can use with ``vehicle``, skipped: flight -> reason),
    looking at one table at a time (``tables`` may read each as it is looked up). ``facts``
    (flight -> its recorded :class:`PhysicsFacts`, or None) decides without reading a table
    wherever they cover the columns ``vehicle`` needs."""
    need = required_columns(vehicle)
    usable, skipped = [], {}
    for fid in tables:
        known = facts(fid) if facts is not None else None
        missing = [c for c in need if c not in (known.columns if known is not None else tables[fid].columns)]
        problem: str | None
        if missing:
            problem = f"missing columns: {logged_as(missing)}"
        elif known is not None and known.covers(need):
            problem = known.problem(need)
        else:
            problem = physics_problem(tables[fid], need)
        if problem:
            skipped[fid] = problem
        else:
            usable.append(fid)
    return usable, skipped


# Every check of a decoded flight, for the UI: the log's own and the physics gate.
ALL_CHECKS = {**LOG_CHECKS, "usable_for_physics": usable_for_physics}
DESCRIPTIONS = {
    **LOG_CHECK_DESCRIPTIONS,
    "usable_for_physics": "The physics can use the flight: the columns it needs, enough samples, finite "
                          "values, unit quaternions, a plausible battery voltage and a flight phase.",
}
