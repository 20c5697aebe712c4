"""Residual force and torque: what the measurements say minus what the model says.

For each sample of a flight (body frame ``b``, world frame ``w``; see :mod:`quadcore.physics.dynamics`)::

    f_meas_b   = m sf_b                                  accelerometer (specific force)
    f_model_b  = (0, 0, T) + f_extra_b                    thrust map + effects in the model
    f_res_b    = f_meas_b - f_model_b                     the residual force f_a,  N
    tau_meas_b = J dω/dt + ω × J ω                        gyro, filtered derivative (see below)
    tau_model_b= tau_rotors_b + tau_extra_b
    tau_res_b  = tau_meas_b - tau_model_b                 the residual torque tau_a, N m

and the same residuals rotated to the world frame (``f_res_w = R f_res_b``).

Measured and modelled forces pass through the same zero-phase smoother
(:mod:`quadcore.physics.signals`): the accelerometer samples the force at ``t_k``, the model is
its value there. ``dω/dt`` is the smoother's derivative, a weighting of the torque's integrals
over the sample intervals, so the modelled torque is integrated over the same intervals (each
sample held as its thrust source holds it: ``Vehicle.thrust_hold_s``, the command period for
PWM, none for measured motor speeds) and differentiated the same way
(:func:`quadcore.physics.signals.matched_to_derivative`); the gyroscopic term ``ω × J ω``,
part of the same integrals, goes through that filter too (:func:`measured_torque_b`). So each
pair has the same bandwidth and no relative delay (the derivation: docs/timing.md). Samples
whose filter window spans a logging gap are flagged in ``near_gap``.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from quadcore.physics import dynamics, rotations, signals
from quadcore.physics.dynamics import FlightState, cols
from quadcore.physics.vehicle import Vehicle
from quadcore.store import names

F_RES_B, F_RES_W = cols("f_res_b", "N"), cols("f_res_w", "N")
TAU_RES_B = cols("tau_res_b", "Nm")



def residual_arrays(
    state: FlightState,
    vehicle: Vehicle,
    extra_f_b_N: np.ndarray | None = None,
    extra_tau_b_Nm: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Measured, modelled and residual force and torque, (n, 3) each, body and world."""
    T_N, tau_rotors_b = dynamics.wrench_from_thrusts(vehicle, state.f_rotor_N)
    f_model_b = np.zeros((state.n, 3))
    f_model_b[:, 2] = T_N
    tau_model_b = tau_rotors_b.copy()
    if extra_f_b_N is not None:
        f_model_b += extra_f_b_N
    if extra_tau_b_Nm is not None:
        tau_model_b += extra_tau_b_Nm

    omega_dot = signals.derivative(state.omega_b_radps, state.t_s)
    f_meas_b, tau_meas_b = measured_wrench(state, vehicle, omega_dot)
    f_model_b = signals.smooth(f_model_b, t_s=state.t_s)
    tau_model_b = signals.matched_to_derivative(tau_model_b, state.t_s, state.thrust_hold_s)
    f_res_b = f_meas_b - f_model_b
    tau_res_b = tau_meas_b - tau_model_b
    R = state.R_wb
    return {
        "T_N": T_N,
        "omega_dot_b": omega_dot,
        "f_meas_b": f_meas_b,
        "f_model_b": f_model_b,
        "f_res_b": f_res_b,
        "f_res_w": rotations.body_to_world(R, f_res_b),
        "tau_meas_b": tau_meas_b,
        "tau_model_b": tau_model_b,
        "tau_res_b": tau_res_b,
        "tau_res_w": rotations.body_to_world(R, tau_res_b),
        "a_meas_w": dynamics.linear_acceleration_w(vehicle, R, f_meas_b),
        "a_model_w": dynamics.linear_acceleration_w(vehicle, R, f_model_b),
    }


def measured_wrench(state: FlightState, vehicle: Vehicle,
                    omega_dot_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The measured side of the residuals, (n, 3) each, body frame: force ``m · smooth(sf_b)`` (N)
    and torque (N m, :func:`measured_torque_b`) from the gyro and its filtered derivative
    ``omega_dot_b`` (computed here when not given)."""
    f_meas_b = vehicle.mass_kg * signals.smooth(state.sf_b_mps2, t_s=state.t_s)
    return f_meas_b, measured_torque_b(vehicle, state.omega_b_radps, state.t_s, omega_dot_b)


def measured_torque_b(vehicle: Vehicle, omega_b_radps: np.ndarray, t_s: np.ndarray,
                      omega_dot_b: np.ndarray | None = None) -> np.ndarray:
    """The torque (n, 3), N m, body frame, that turns the body as the gyro says, through the
    filter of the gyro's derivative ``D`` (:func:`quadcore.physics.signals.derivative`)::

        tau_meas_b = J D[ω] + M[ω × J ω]

    ``M`` is :func:`quadcore.physics.signals.matched_to_derivative` with the samples held for
    no time (``ω`` is a state, continuous). Why: ``D[ω]`` weighs the integrals of ``dω/dt`` over
    the sample intervals, and Euler's ``J dω/dt = tau - ω × J ω`` holds at every instant, so
    ``J D[ω] = M[tau] - M[ω × J ω]`` exactly (docs/timing.md): the gyroscopic term belongs
    beside the rotors' torque, through the same filter ``M``. Any other filter on it (the
    smoother, which passes 99.7 % at 1 Hz at a 100 Hz log where ``M`` passes 91 %) leaves the
    difference of the two filters on ``ω × J ω`` in the residual: a product of rates
    (``(J_xx - J_zz) ω_x ω_z`` in pitch) on flights with nothing hidden."""
    J = np.asarray(vehicle.inertia_kgm2, float)
    omega = np.asarray(omega_b_radps, float)
    omega_dot = signals.derivative(omega, t_s) if omega_dot_b is None else omega_dot_b
    gyroscopic = signals.matched_to_derivative(np.cross(omega, omega @ J.T), t_s, 0.0)
    return omega_dot @ J.T + gyroscopic


def residual_table(
    df: pl.DataFrame,
    vehicle: Vehicle,
    extra_f_b_N: np.ndarray | None = None,
    extra_tau_b_Nm: np.ndarray | None = None,
) -> pl.DataFrame:
    """The residual table of one flight: state, inputs, modelled, measured and residual.

    ``df`` is a decoded ``fixedFrequency`` SI table. Column names carry frame and unit.
    """
    state = dynamics.flight_state(df, vehicle)
    r = residual_arrays(state, vehicle, extra_f_b_N, extra_tau_b_Nm)
    keep = ["t_s", "timestamp_us", *cols("p_w", "m"), *cols("v_w", "mps"), "q_x", "q_y", "q_z", "q_w",
            *cols("omega_b", "radps"), *cols("sf_b", "mps2"), "vbat_V"]
    keep += [c for c in df.columns if c.startswith(("pwm_", "motor_"))]
    out: dict[str, pl.Series | np.ndarray] = {c: df[c] for c in keep if c in df.columns}

    def put(prefix: str, unit: str, arr: np.ndarray) -> None:
        for name, column in zip(cols(prefix, unit), arr.T):
            out[name] = column

    put("v_b", "mps", state.v_b_mps)
    for i, f in enumerate(state.f_rotor_N.T, 1):
        out[f"f_rotor_{i}_N"] = f
    out["T_N"] = r["T_N"]
    put("omega_dot_b", "radps2", r["omega_dot_b"])
    for key in ("f_meas_b", "f_model_b", "f_res_b", "f_res_w"):
        put(key, "N", r[key])
    for key in ("tau_meas_b", "tau_model_b", "tau_res_b", "tau_res_w"):
        put(key, "Nm", r[key])
    put("a_meas_w", "mps2", r["a_meas_w"])
    put("a_model_w", "mps2", r["a_model_w"])
    out["near_gap"] = signals.near_gap(state.t_s)
    return pl.DataFrame(out)


def column_units(df: pl.DataFrame) -> dict[str, str]:
    """Unit of every column, read off its name suffix (``_N``, ``_Nm``, ``_mps``, ...)."""
    return names.column_units(df.columns)


def rmse(df: pl.DataFrame, columns: list[str], where: pl.Expr | None = None) -> list[float]:
    """Root mean square of each column (optionally on rows where ``where`` holds)."""
    sel = df.filter(where) if where is not None else df
    return [float(np.sqrt(np.mean(sel[c].to_numpy() ** 2))) if sel.height else float("nan") for c in columns]


def summary(df: pl.DataFrame) -> dict[str, float]:
    """RMSE and mean per axis of the body-frame residuals, excluding samples near gaps."""
    ok = ~pl.col("near_gap")
    out: dict[str, float] = {}
    for name, columns in (("force", F_RES_B), ("torque", TAU_RES_B)):
        unit = "N" if name == "force" else "Nm"
        for axis, value in zip(dynamics.XYZ, rmse(df, columns, ok)):
            out[f"{name}_rmse_{axis}_{unit}"] = value
        means = df.filter(ok).select(columns).mean().row(0)
        for axis, value in zip(dynamics.XYZ, means):
            out[f"{name}_mean_{axis}_{unit}"] = float(value)
    return out
