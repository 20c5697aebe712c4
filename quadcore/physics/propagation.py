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
    n_steps: int | np.ndarray,
    extra_wrench: ExtraWrench | None = None,
) -> dict[str, np.ndarray]:
    """Integrate from each start index for ``n_steps`` (one count for all, or one per start);
    errors (n_starts, max steps + 1), NaN past a start's own count.

    Returns position error norm (m), velocity error norm (m/s), attitude error angle (rad),
    angular-rate error norm (rad/s), and the elapsed time (s) of each step. The windows are
    integrated together, longest first, so that at each step the ones still going are the
    first rows: a window's result does not depend on the others.
    """
    starts = np.asarray(starts, dtype=np.int64)
    steps = np.broadcast_to(np.asarray(n_steps, dtype=np.int64), starts.shape)
    order = np.argsort(-steps, kind="stable")
    starts, steps = starts[order], steps[order]
    longest = int(steps.max(initial=0))
    going = np.searchsorted(-steps, -np.arange(longest), side="left")  # at step k: the rows with steps > k
    p, v = state.p_w_m[starts].copy(), state.v_w_mps[starts].copy()
    q, w = state.q_xyzw[starts].copy(), state.omega_b_radps[starts].copy()
    shape = (len(starts), longest + 1)
    err = {k: np.full(shape, np.nan) for k in ("pos_m", "vel_mps", "att_rad", "rate_radps", "elapsed_s")}
    for e in err.values():
        e[:, 0] = 0.0
    T_all, tau_all = dynamics.wrench_from_thrusts(vehicle, state.f_rotor_N)
    for k, m in enumerate(going):
        p, v, q, w = p[:m], v[:m], q[:m], w[:m]
        i = starts[:m] + k
        dt = state.t_s[i + 1] - state.t_s[i]
        f_b = np.zeros((m, 3))
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
        err["pos_m"][:m, k + 1] = np.linalg.norm(p - state.p_w_m[j], axis=1)
        err["vel_mps"][:m, k + 1] = np.linalg.norm(v - state.v_w_mps[j], axis=1)
        err["att_rad"][:m, k + 1] = rotations.angle_between_rad(q, state.q_xyzw[j])
        err["rate_radps"][:m, k + 1] = np.linalg.norm(w - state.omega_b_radps[j], axis=1)
        err["elapsed_s"][:m, k + 1] = state.t_s[j] - state.t_s[starts[:m]]
    back = np.argsort(order, kind="stable")  # rows in the order the starts were given
    return {k: e[back] for k, e in err.items()}


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
    windows = []  # (horizon, steps, starts) of each horizon that has windows
    for horizon in (0.0, *horizons_s):
        n_steps = max(1, int(round(horizon / dt))) if dt > 0 else 0
        if n_steps == 0 or n_steps >= state.n:
            continue
        stride = max(1, int(round(stride_s / dt)))
        starts = np.arange(0, state.n - n_steps - 1, stride)
        starts = starts[gaps_before[starts + n_steps] == gaps_before[starts]]
        if len(starts):
            windows.append((horizon if horizon > 0 else dt, n_steps, starts))
    if not windows:
        return pl.DataFrame(schema=GROWTH_SCHEMA)
    # One rollout from every start, as far as the longest horizon that starts there: a shorter
    # horizon's window is the first steps of the longer one from the same sample.
    every = np.unique(np.concatenate([starts for _, _, starts in windows]))
    reach = np.zeros(len(every), np.int64)
    for _, n_steps, starts in windows:
        rows = np.searchsorted(every, starts)
        reach[rows] = np.maximum(reach[rows], n_steps)
    e = rollout(state, vehicle, every, reach, extra_wrench)
    frames = []
    for horizon, n_steps, starts in windows:
        sub = {k: v[np.searchsorted(every, starts), 1:n_steps + 1] for k, v in e.items()}
        frames.append(pl.DataFrame({
            "horizon_s": np.full(n_steps, horizon),
            "step": np.arange(1, n_steps + 1),
            "t_ahead_s": sub["elapsed_s"].mean(axis=0),
            "pos_err_m": np.sqrt((sub["pos_m"] ** 2).mean(axis=0)),
            "vel_err_mps": np.sqrt((sub["vel_mps"] ** 2).mean(axis=0)),
            "att_err_deg": np.degrees(np.sqrt((sub["att_rad"] ** 2).mean(axis=0))),
            "rate_err_radps": np.sqrt((sub["rate_radps"] ** 2).mean(axis=0)),
            "windows": np.full(n_steps, len(starts)),
        }))
    return pl.concat(frames).cast(GROWTH_SCHEMA)


def horizon_summary(growth: pl.DataFrame) -> pl.DataFrame:
    """The error at the end of each horizon (one row per horizon)."""
    return growth.group_by("horizon_s").agg(pl.all().sort_by("step").last()).sort("horizon_s").drop("step")
