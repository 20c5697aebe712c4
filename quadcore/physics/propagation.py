"""Forward propagation: how far the model drifts from the real vehicle.

From the logged state at a start sample, integrate the model open loop with the logged
inputs (rotor thrusts from the thrust map) over a horizon, and compare with the logged
state at every step. Many start samples are integrated at once (vectorised over
windows; the only loop is over the steps of the horizon)::

    v   <- v + a_w dt,        a_w = g_w + R (f_model_b) / m
    p   <- p + v dt                                   (semi-implicit Euler)
    ω   <- ω + dω/dt dt,      dω/dt = J^-1 (tau_model_b - ω × J ω)
    q   <- q ⊗ exp(ω dt / 2)                          (exponential map)

``dt`` is the logged sample spacing. A window that contains a step longer than
``MAX_STEP_S`` (a gap in the log) is not integrated: gaps split the rollouts.
A horizon of one step is the one-step prediction.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import polars as pl

from quadcore.logs import checks
from quadcore.physics import dynamics, rotations
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle

HORIZONS_S = (0.1, 0.5, 1.0)
MAX_STEP_S = checks.GAP_WARN_S  # a step longer than the checks' gap threshold is a gap

# sample indices -> (extra force, extra torque) of the model's effects, body frame, evaluated on
# the logged state at those samples (the rollout's own state is not fed back to the effects)
ExtraWrench = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def rollout(
    state: FlightState,
    vehicle: Vehicle,
    starts: np.ndarray,
    n_steps: int,
    extra_wrench: ExtraWrench | None = None,
) -> dict[str, np.ndarray]:
    """Integrate from each start index for ``n_steps``; errors (n_starts, n_steps + 1).

    Returns position error norm (m), velocity error norm (m/s), attitude error angle (rad),
    angular-rate error norm (rad/s), and the elapsed time (s) of each step.
    """
    starts = np.asarray(starts, dtype=np.int64)
    p, v = state.p_w_m[starts].copy(), state.v_w_mps[starts].copy()
    q, w = state.q_xyzw[starts].copy(), state.omega_b_radps[starts].copy()
    shape = (len(starts), n_steps + 1)
    err = {k: np.zeros(shape) for k in ("pos_m", "vel_mps", "att_rad", "rate_radps", "elapsed_s")}
    T_all, tau_all = dynamics.wrench_from_thrusts(vehicle, state.f_rotor_N)
    for k in range(n_steps):
        i = starts + k
        dt = state.t_s[i + 1] - state.t_s[i]
        f_b = np.zeros((len(i), 3))
        f_b[:, 2] = T_all[i]
        tau_b = tau_all[i].copy()
        if extra_wrench is not None:
            ef, et = extra_wrench(i)
            f_b += ef
            tau_b += et
        a_w = dynamics.linear_acceleration_w(vehicle, rotations.rotation_matrix(q), f_b)
        w_dot = dynamics.angular_acceleration_b(vehicle, w, tau_b)
        v = v + a_w * dt[:, None]
        p = p + v * dt[:, None]
        q = rotations.integrate_body_rate(q, w, dt)
        w = w + w_dot * dt[:, None]
        j = i + 1
        err["pos_m"][:, k + 1] = np.linalg.norm(p - state.p_w_m[j], axis=1)
        err["vel_mps"][:, k + 1] = np.linalg.norm(v - state.v_w_mps[j], axis=1)
        err["att_rad"][:, k + 1] = rotations.angle_between_rad(q, state.q_xyzw[j])
        err["rate_radps"][:, k + 1] = np.linalg.norm(w - state.omega_b_radps[j], axis=1)
        err["elapsed_s"][:, k + 1] = state.t_s[j] - state.t_s[starts]
    return err


# The columns of :func:`error_growth`, also where the flight is too short for any window.
GROWTH_SCHEMA = pl.Schema({
    "horizon_s": pl.Float64, "step": pl.Int64, "t_ahead_s": pl.Float64, "pos_err_m": pl.Float64,
    "vel_err_mps": pl.Float64, "att_err_deg": pl.Float64, "rate_err_radps": pl.Float64, "windows": pl.Int64,
})


def error_growth(
    state: FlightState,
    vehicle: Vehicle,
    horizons_s: tuple[float, ...] = HORIZONS_S,
    stride_s: float = 0.2,
    extra_wrench: ExtraWrench | None = None,
) -> pl.DataFrame:
    """RMS error over windows at each step of each horizon (plus the one-step prediction).

    Columns: ``horizon_s, t_ahead_s, pos_err_m, vel_err_mps, att_err_deg, rate_err_radps,
    windows``. Windows start every ``stride_s``, skipping those that span a gap; a horizon
    longer than the flight is skipped (a flight too short for any window gives no rows, with
    these columns).
    """
    dt = float(np.median(np.diff(state.t_s))) if state.n > 1 else 0.0
    gaps_before = np.concatenate([[0], np.cumsum(np.diff(state.t_s) > MAX_STEP_S)])  # per sample
    frames = []
    for horizon in (0.0, *horizons_s):
        n_steps = max(1, int(round(horizon / dt))) if dt > 0 else 0
        if n_steps == 0 or n_steps >= state.n:
            continue
        stride = max(1, int(round(stride_s / dt)))
        starts = np.arange(0, state.n - n_steps - 1, stride)
        starts = starts[gaps_before[starts + n_steps] == gaps_before[starts]]
        if len(starts) == 0:
            continue
        e = rollout(state, vehicle, starts, n_steps, extra_wrench)
        frames.append(
            pl.DataFrame(
                {
                    "horizon_s": np.full(n_steps, horizon if horizon > 0 else dt),
                    "step": np.arange(1, n_steps + 1),
                    "t_ahead_s": e["elapsed_s"][:, 1:].mean(axis=0),
                    "pos_err_m": np.sqrt((e["pos_m"][:, 1:] ** 2).mean(axis=0)),
                    "vel_err_mps": np.sqrt((e["vel_mps"][:, 1:] ** 2).mean(axis=0)),
                    "att_err_deg": np.degrees(np.sqrt((e["att_rad"][:, 1:] ** 2).mean(axis=0))),
                    "rate_err_radps": np.sqrt((e["rate_radps"][:, 1:] ** 2).mean(axis=0)),
                    "windows": np.full(n_steps, len(starts)),
                }
            )
        )
    return pl.concat(frames).cast(GROWTH_SCHEMA) if frames else pl.DataFrame(schema=GROWTH_SCHEMA)


def horizon_summary(growth: pl.DataFrame) -> pl.DataFrame:
    """The error at the end of each horizon (one row per horizon)."""
    return growth.group_by("horizon_s").agg(pl.all().sort_by("step").last()).sort("horizon_s").drop("step")
