"""Rigid-body dynamics of a multirotor, vectorised over whole flights.

Frames: world ``w`` (z up, gravity ``g_w = (0, 0, -g0)``), body ``b`` (x forward, y left,
z up). ``R`` maps body to world. With rotor thrusts ``f`` (N) and allocation ``A``
(see :mod:`quadcore.physics.vehicle`), the nominal model is::

    [T, tau_b] = A f                                   (collective thrust, body torque)
    m a_w      = m g_w + R (0, 0, T) + R f_extra_b       (Newton)
    J dω_b/dt  = tau_b + tau_extra_b - ω_b × J ω_b       (Euler, with the gyroscopic term)

``f_extra_b`` and ``tau_extra_b`` are the contributions of any effects added to the model
(:mod:`quadcore.effects`); the nominal model has none.

An accelerometer measures the specific force ``sf_b = R^T (a_w - g_w)``, i.e. every
non-gravitational force divided by mass, in the body frame. So the measured force is
``m sf_b`` and the modelled force ``(0, 0, T) + f_extra_b``, both in the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from quadcore.logs.units import SI_COLUMNS
from quadcore.physics import rotations
from quadcore.physics.gate import (
    XYZ as XYZ,  # re-exported for identify.regimes (its re-layout, issue 23)
    cols,
    physics_problem,
    required_columns,
)
from quadcore.physics.rotations import GRAVITY_W_MPS2 as GRAVITY_W_MPS2  # re-exported, as XYZ
from quadcore.physics.vehicle import Vehicle


@dataclass
class FlightState:
    """A flight's logged state and inputs as arrays (n samples), SI, plus derived frames."""

    t_s: np.ndarray
    p_w_m: np.ndarray  # (n, 3)
    v_w_mps: np.ndarray  # (n, 3)
    q_xyzw: np.ndarray  # (n, 4) body->world
    omega_b_radps: np.ndarray  # (n, 3)
    sf_b_mps2: np.ndarray  # (n, 3) accelerometer specific force
    pwm: np.ndarray  # (n, rotors) 0..1
    vbat_V: np.ndarray  # (n,)
    motor_radps: np.ndarray | None  # (n, rotors) or None when not logged
    R_wb: np.ndarray  # (n, 3, 3)
    v_b_mps: np.ndarray  # (n, 3) velocity in the body frame
    f_rotor_N: np.ndarray  # (n, rotors) nominal rotor thrusts from the thrust map
    thrust_hold_s: float = 0.0  # how long a sample of the thrust map's input holds (Vehicle.thrust_hold_s)

    @property
    def n(self) -> int:
        return len(self.t_s)


class UnusableFlightError(ValueError):
    """A flight the physics cannot use (see :func:`quadcore.physics.gate.physics_problem`): the
    fleet stages skip it with this reason and go on."""


class MissingColumnsError(UnusableFlightError):
    """A flight table lacks what the dynamics need (a variable not logged, or a vehicle file
    with more rotors than the log has motors)."""


def flight_state(df: pl.DataFrame, vehicle: Vehicle) -> FlightState:
    """Arrays for the dynamics from a decoded ``fixedFrequency`` SI table.

    Raises :class:`MissingColumnsError` naming the logged variables that are missing, and
    :class:`UnusableFlightError` for a flight :func:`quadcore.physics.gate.physics_problem` refuses."""
    missing = [c for c in required_columns(vehicle) if c not in df.columns]
    if missing:
        logged = {si: var for var, (si, *_rest) in SI_COLUMNS.items()}
        names = ", ".join(f"{c} (log variable {logged[c]})" if c in logged else c for c in missing)
        raise MissingColumnsError(
            f"the flight lacks {names}, needed by vehicle {vehicle.name!r} ({vehicle.n_rotors} rotors, "
            f"thrust map {vehicle.thrust_map_kind})")
    problem = physics_problem(df, required_columns(vehicle))
    if problem:
        raise UnusableFlightError(problem)

    def block(names):
        return df.select(names).to_numpy().astype(np.float64)

    n_rot = vehicle.n_rotors
    motor_cols = [f"motor_{i}_radps" for i in range(1, n_rot + 1)]
    motor = block(motor_cols) if all(c in df.columns for c in motor_cols) else None
    q = block(["q_x", "q_y", "q_z", "q_w"])
    R = rotations.rotation_matrix(q)
    v_w = block(cols("v_w", "mps"))
    pwm = block([f"pwm_{i}" for i in range(1, n_rot + 1)])
    vbat = df["vbat_V"].to_numpy().astype(np.float64)
    return FlightState(
        t_s=df["t_s"].to_numpy().astype(np.float64),
        p_w_m=block(cols("p_w", "m")),
        v_w_mps=v_w,
        q_xyzw=q,
        omega_b_radps=block(cols("omega_b", "radps")),
        sf_b_mps2=block(cols("sf_b", "mps2")),
        pwm=pwm,
        vbat_V=vbat,
        motor_radps=motor,
        R_wb=R,
        v_b_mps=rotations.world_to_body(R, v_w),
        f_rotor_N=vehicle.rotor_thrusts_N(pwm, vbat, motor),
        thrust_hold_s=vehicle.thrust_hold_s,
    )


def wrench_from_thrusts(vehicle: Vehicle, f_rotor_N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Collective thrust T (n,) and body torque tau_b (n, 3) from rotor thrusts (n, rotors)."""
    w = f_rotor_N @ vehicle.allocation.T
    return w[:, 0], w[:, 1:]


def linear_acceleration_w(vehicle: Vehicle, R_wb: np.ndarray, f_b_N: np.ndarray) -> np.ndarray:
    """Newton: ``a_w = g_w + R f_b / m`` where ``f_b`` is every non-gravitational force."""
    return GRAVITY_W_MPS2 + rotations.body_to_world(R_wb, f_b_N) / vehicle.mass_kg


def angular_acceleration_b(vehicle: Vehicle, omega_b: np.ndarray, tau_b: np.ndarray) -> np.ndarray:
    """Euler: ``dω/dt = J^-1 (tau_b - ω × J ω)``."""
    J = vehicle.inertia_kgm2
    gyro = np.cross(omega_b, omega_b @ J.T)
    return np.linalg.solve(J, (tau_b - gyro).T).T


def torque_for_angular_acceleration(vehicle: Vehicle, omega_b: np.ndarray, omega_dot_b: np.ndarray) -> np.ndarray:
    """Inverse Euler: the body torque that produces ``dω/dt``: ``J dω/dt + ω × J ω``."""
    J = vehicle.inertia_kgm2
    return omega_dot_b @ J.T + np.cross(omega_b, omega_b @ J.T)
