"""The state a quadrotor flies along a planned path, by differential flatness.

Position ``p(t)`` and yaw ``ψ(t)`` determine everything (Mellinger and Kumar 2011), world z
up, body z along the thrust::

    F = m (a + g e_z),  T = |F|,  b3 = F / T                              collective thrust N
    b1c = (cos ψ, sin ψ, 0),  b2 = b3 × b1c / |b3 × b1c|,  b1 = b2 × b3,  R_wb = [b1 b2 b3]
    h = (m / T) (j - (b3·j) b3),  ω_b = (-h·b2, h·b1, ψ' e_z·b3)          body rate rad/s
    τ_b = J dω_b/dt + ω_b × J ω_b,   f = A⁻¹ [T, τ_b]                       rotor thrusts N

(``j`` the jerk, ``A`` the allocation of :class:`quadcore.physics.vehicle.Vehicle`). The result
is a noise-free :class:`quadcore.physics.dynamics.FlightState` at the log rate, with hover before
and after the manoeuvre, on which any effect's ``wrench`` predicts what that effect would add
(:mod:`quadcore.plan.signatures`): the rotor thrusts are the ones a perfect tracking controller
commands, the PWM those the vehicle's thrust map needs for them at ``vbat_V``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from quadcore.logs.units import G0_MPS2
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle
from quadcore.sim.trajectories import PolyTrajectory

LOG_RATE_HZ = 500.0  # the logs' rate: the effects' filters (lag, delay) see the same sampling
HOVER_PAD_S = 1.0  # hover before and after the manoeuvre, as flown
VBAT_V = 3.6  # battery voltage for the PWM of the predicted thrusts (in-flight 3.3-3.9 V)


@dataclass(frozen=True)
class FlatPath:
    """Sampled path and what flatness derives: times (n,), position, velocity, acceleration,
    jerk (n, 3, world), yaw (n,), thrust T (n,), rotation (n, 3, 3), body rate (n, 3), body
    angular acceleration (n, 3), rotor thrusts (n, rotors)."""

    t_s: np.ndarray
    p_w_m: np.ndarray
    v_w_mps: np.ndarray
    a_w_mps2: np.ndarray
    j_w_mps3: np.ndarray
    yaw_rad: np.ndarray
    thrust_N: np.ndarray
    R_wb: np.ndarray
    omega_b_radps: np.ndarray
    omega_dot_b_radps2: np.ndarray
    f_rotor_N: np.ndarray

    @property
    def tilt_rad(self) -> np.ndarray:
        """Angle between body z and world z."""
        return np.arccos(np.clip(self.R_wb[:, 2, 2], -1.0, 1.0))


def sample(traj: PolyTrajectory, rate_hz: float = LOG_RATE_HZ, pad_s: float = HOVER_PAD_S) -> np.ndarray:
    """Plan times: ``pad_s`` of hover, the plan, ``pad_s`` of hover (evaluation clamps)."""
    dt = 1.0 / rate_hz
    return np.arange(-pad_s, traj.duration_s + pad_s + 0.5 * dt, dt)


def flat_path(traj: PolyTrajectory, vehicle: Vehicle, rate_hz: float = LOG_RATE_HZ,
              pad_s: float = HOVER_PAD_S) -> FlatPath:
    """The flat outputs of ``traj`` sampled at ``rate_hz`` and the state they imply (see the
    module). Times start at 0 with the first hover sample."""
    tau = sample(traj, rate_hz, pad_s)
    inside = (tau >= 0) & (tau <= traj.duration_s)
    d = [traj.evaluate(np.clip(tau, 0.0, traj.duration_s), k) for k in range(4)]
    for k in (1, 2, 3):
        d[k][~inside] = 0.0  # hover outside the plan
    p, v, a, j = (x[:, :3] for x in d)
    yaw, yaw_rate = d[0][:, 3], d[1][:, 3]
    m = vehicle.mass_kg
    F = m * (a + np.array([0.0, 0.0, G0_MPS2]))
    T = np.linalg.norm(F, axis=1)
    b3 = F / T[:, None]
    b1c = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
    b2 = np.cross(b3, b1c)
    b2 /= np.linalg.norm(b2, axis=1)[:, None]
    b1 = np.cross(b2, b3)
    R = np.stack([b1, b2, b3], axis=2)
    h = (m / T)[:, None] * (j - np.einsum("ni,ni->n", b3, j)[:, None] * b3)
    omega = np.column_stack([-np.einsum("ni,ni->n", h, b2), np.einsum("ni,ni->n", h, b1), yaw_rate * b3[:, 2]])
    t = tau - tau[0]
    omega_dot = np.gradient(omega, t, axis=0)
    J = np.asarray(vehicle.inertia_kgm2, float)
    torque = omega_dot @ J.T + np.cross(omega, omega @ J.T)
    f = np.linalg.solve(vehicle.allocation, np.column_stack([T, torque]).T).T if vehicle.n_rotors == 4 else (
        np.linalg.lstsq(vehicle.allocation, np.column_stack([T, torque]).T, rcond=None)[0].T)
    return FlatPath(t, p, v, a, j, yaw, T, R, omega, omega_dot, f)


def flight_state(path: FlatPath, vehicle: Vehicle, vbat_V: float = VBAT_V) -> FlightState:
    """The noise-free :class:`~quadcore.physics.dynamics.FlightState` along the path: the
    accelerometer reads ``(0, 0, T / m)``, the rotors give ``f``, their PWM is the thrust map's
    inverse at ``vbat_V`` (motor speed ``sqrt(f / k_F)`` where the vehicle has a ``k_F``)."""
    n = len(path.t_s)
    f = np.maximum(path.f_rotor_N, 0.0)
    vbat = np.full(n, float(vbat_V))
    pwm = vehicle.pwm_vbat.pwm_for_thrust(f, vbat[:, None])
    k_F = vehicle.motor_speed.k_F_N_per_radps2
    motor = np.sqrt(f / k_F) if k_F > 0 else None
    sf = np.zeros((n, 3))
    sf[:, 2] = path.thrust_N / vehicle.mass_kg
    v_b = np.einsum("nji,nj->ni", path.R_wb, path.v_w_mps)
    return FlightState(
        t_s=path.t_s, p_w_m=path.p_w_m, v_w_mps=path.v_w_mps, q_xyzw=Rotation.from_matrix(path.R_wb).as_quat(),
        omega_b_radps=path.omega_b_radps, sf_b_mps2=sf, pwm=pwm, vbat_V=vbat, motor_radps=motor, R_wb=path.R_wb,
        v_b_mps=v_b, f_rotor_N=f,
    )
