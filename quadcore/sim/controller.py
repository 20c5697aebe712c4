"""The simulator's flight controller: position PID + geometric attitude control on SO(3).

It knows only the NOMINAL vehicle (mass, inertia, allocation matrix): effects the vehicle
really has (drag, a payload, a CoM offset, ...) are disturbances it rejects through feedback
and integral action, so they show up in the residuals as on the real vehicle.

Position loop (world frame, z up)::

    e_p = p - p_ref,  e_v = v - v_ref,  i_p += e_p dt  (clamped)
    F   = m (a_ref - Kp e_p - Kd e_v - Ki i_p + g e_z)          desired thrust vector
    (horizontal part limited to tan(max_tilt) * F_z, F_z >= 0.2 m g)

Attitude loop (Lee, Leok, McClamroch 2010), body frame::

    b3d = F / |F|,  b1c = (cos yaw, sin yaw, 0),  b2d = b3d x b1c / |.|,  b1d = b2d x b3d
    e_R = vee(Rd^T R - R^T Rd) / 2,  e_w = w - yaw_rate R^T e_z,  i_R += e_R dt  (clamped)
    tau = -K_R e_R - K_w e_w - K_i i_R + w x J w + J yaw_acc R^T e_z
    T   = F . R e_z

Gains are set from natural frequencies and damping (diagonal ``K = J_ii w_n^2`` etc.), so they
scale with the vehicle. Then rotor thrusts ``f = A^-1 [T, tau]``, clipped to
``[0, f_max]`` by the caller (the simulator knows the battery voltage).

Written with plain Python floats: it runs once per control step inside the simulator's
closed loop, where numpy's per-call overhead on 3-vectors would dominate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadcore.logs.units import G0_MPS2
from quadcore.physics.vehicle import Vehicle


@dataclass(frozen=True)
class Gains:
    """Loop shapes: natural frequency (rad/s), damping, integral rate (1/s) per loop."""

    pos_wn_xy: float = 4.0
    pos_wn_z: float = 5.0
    pos_zeta: float = 0.9
    pos_ki_per_s: float = 1.5  # integral gain relative to Kp (1 / integral time)
    pos_i_limit_m_s: float = 0.5
    att_wn_rp: float = 30.0
    att_wn_yaw: float = 12.0
    att_zeta: float = 0.8
    att_ki_per_s: float = 2.0
    att_i_limit_rad_s: float = 0.3
    max_tilt_rad: float = math.radians(40.0)


class Controller:
    """State: the two integrators. ``step`` returns commanded rotor thrusts (N)."""

    def __init__(self, vehicle: Vehicle, gains: Gains | None = None):
        g = gains or Gains()
        self.gains = g
        self.m = float(vehicle.mass_kg)
        J = np.asarray(vehicle.inertia_kgm2, float)
        self.J = tuple(tuple(float(x) for x in row) for row in J)
        Jd = np.diag(J)
        self.kp = (g.pos_wn_xy**2, g.pos_wn_xy**2, g.pos_wn_z**2)
        self.kd = (2 * g.pos_zeta * g.pos_wn_xy, 2 * g.pos_zeta * g.pos_wn_xy, 2 * g.pos_zeta * g.pos_wn_z)
        self.ki = tuple(k * g.pos_ki_per_s for k in self.kp)
        wn = (g.att_wn_rp, g.att_wn_rp, g.att_wn_yaw)
        self.kR = tuple(float(Jd[i] * wn[i] ** 2) for i in range(3))
        self.kw = tuple(float(2 * g.att_zeta * Jd[i] * wn[i]) for i in range(3))
        self.kRi = tuple(k * g.att_ki_per_s for k in self.kR)
        self.tan_tilt = math.tan(g.max_tilt_rad)
        A_inv = np.linalg.inv(vehicle.allocation)
        self.A_inv = tuple(tuple(float(x) for x in row) for row in A_inv)
        self.i_p = [0.0, 0.0, 0.0]
        self.i_R = [0.0, 0.0, 0.0]

    def step(self, dt, p, v, R, w, p_ref, v_ref, a_ref, yaw, yaw_rate, yaw_acc):
        """One control step. ``R`` is row-major ((r00, r01, r02), ...), body->world; ``w`` the
        measured body rate. Returns ``(f_cmd tuple of rotor thrusts, T, tau)``."""
        m, kp, kd, ki = self.m, self.kp, self.kd, self.ki
        lim = self.gains.pos_i_limit_m_s
        acc = [0.0, 0.0, 0.0]
        for i in range(3):
            e_p = p[i] - p_ref[i]
            e_v = v[i] - v_ref[i]
            self.i_p[i] = min(max(self.i_p[i] + e_p * dt, -lim), lim)
            acc[i] = a_ref[i] - kp[i] * e_p - kd[i] * e_v - ki[i] * self.i_p[i]
        Fx, Fy, Fz = m * acc[0], m * acc[1], m * (acc[2] + G0_MPS2)
        Fz = max(Fz, 0.2 * m * G0_MPS2)
        h = math.hypot(Fx, Fy)
        hmax = self.tan_tilt * Fz
        if h > hmax:
            Fx, Fy = Fx * hmax / h, Fy * hmax / h
        nF = math.sqrt(Fx * Fx + Fy * Fy + Fz * Fz)
        b3 = (Fx / nF, Fy / nF, Fz / nF)
        c1 = (math.cos(yaw), math.sin(yaw), 0.0)
        b2 = _cross(b3, c1)
        n2 = math.sqrt(b2[0] ** 2 + b2[1] ** 2 + b2[2] ** 2)
        b2 = (b2[0] / n2, b2[1] / n2, b2[2] / n2)
        b1 = _cross(b2, b3)
        # Rd columns b1, b2, b3. M = Rd^T R: M_ij = b_i . R[:, j]
        Rc = ((R[0][0], R[1][0], R[2][0]), (R[0][1], R[1][1], R[2][1]), (R[0][2], R[1][2], R[2][2]))
        bd = (b1, b2, b3)
        M = [[_dot(bd[i], Rc[j]) for j in range(3)] for i in range(3)]
        # e_R = vee(M - M^T) / 2
        eR = (0.5 * (M[2][1] - M[1][2]), 0.5 * (M[0][2] - M[2][0]), 0.5 * (M[1][0] - M[0][1]))
        ez_b = (R[2][0], R[2][1], R[2][2])  # R^T e_z
        ew = (w[0] - yaw_rate * ez_b[0], w[1] - yaw_rate * ez_b[1], w[2] - yaw_rate * ez_b[2])
        J = self.J
        Jw = (_dot(J[0], w), _dot(J[1], w), _dot(J[2], w))
        gyro = _cross(w, Jw)
        alpha = (yaw_acc * ez_b[0], yaw_acc * ez_b[1], yaw_acc * ez_b[2])
        Ja = (_dot(J[0], alpha), _dot(J[1], alpha), _dot(J[2], alpha))
        ilim = self.gains.att_i_limit_rad_s
        tau = [0.0, 0.0, 0.0]
        for i in range(3):
            self.i_R[i] = min(max(self.i_R[i] + eR[i] * dt, -ilim), ilim)
            tau[i] = -self.kR[i] * eR[i] - self.kw[i] * ew[i] - self.kRi[i] * self.i_R[i] + gyro[i] + Ja[i]
        T = Fx * Rc[2][0] + Fy * Rc[2][1] + Fz * Rc[2][2]
        T = max(T, 0.0)
        u = (T, tau[0], tau[1], tau[2])
        f = tuple(_dot(row, u) for row in self.A_inv)
        return f, T, tau


def _dot(a, b) -> float:
    s = 0.0
    for x, y in zip(a, b):
        s += x * y
    return s


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
