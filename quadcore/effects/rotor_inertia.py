"""Rotor inertia: the spinning rotors (propeller and motor bell, inertia ``J_r`` each about
their axis) carry angular momentum ``h_b = -J_r S ẑ_b`` with ``S = Σ yaw_sign_i Ω_i`` (the
rotors spin against their reaction torque). Changing it, or turning it with the body,
takes a torque from the body::

    tau_b = -dh_b/dt - ω_b × h_b = J_r dS/dt ẑ_b + J_r S (ω_y, -ω_x, 0)          [J_r] = kg m²

the reaction torque of spinning a rotor up or down (about z) and the gyroscopic torque
(about x and y). ``Ω_i`` (rad/s) is the logged motor speed where the log has it, else the
thrust map's rotor speed for the mapped thrust (``MotorSpeedThrustMap.speed_for_thrust``).
``dS/dt`` is the change since the previous sample over the median sample period (as
``motor_lag``): a speed change logged at sample k acts over ``[t_k, t_k+1)`` like the
thrusts do. Linear in J_r. A Crazyflie-sized rotor (45 mm propeller, 7 mm motor) is a few
1e-8 kg m^2.
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, SimHook
from quadcore.effects.ccode import CCode


def rotor_speeds_radps(state, vehicle) -> np.ndarray:
    """(n, rotors) the logged motor speed, or the one the thrust map implies."""
    if state.motor_radps is not None:
        return state.motor_radps
    if vehicle.motor_speed.k_F_N_per_radps2 <= 0:
        return np.zeros_like(state.f_rotor_N)
    return vehicle.motor_speed.speed_for_thrust(state.f_rotor_N)


def rotor_inertia_torque(S: np.ndarray, dS_dt: np.ndarray, omega_b: np.ndarray, J_r: float) -> np.ndarray:
    """(n, 3) body torque of rotors with net spin ``S`` (rad/s, yaw_sign-weighted) changing at ``dS_dt``."""
    tau = np.zeros((len(S), 3))
    tau[:, 0] = J_r * S * omega_b[:, 1]
    tau[:, 1] = -J_r * S * omega_b[:, 0]
    tau[:, 2] = J_r * dS_dt
    return tau


class RotorSpinHook(SimHook):
    """The rotor torque per physics step from the true rotor speeds and their change since
    the previous step."""

    def __init__(self, J_r: float, context):
        self.J_r, self.h_s = J_r, context.h_s
        self.yaw_sign = [float(s) for s in context.vehicle.yaw_sign]
        self.S_prev: float | None = None

    def wrench(self, state, k, j):
        S = sum(s * w for s, w in zip(self.yaw_sign, state.motor_radps[0]))
        dS = 0.0 if self.S_prev is None else (S - self.S_prev) / self.h_s
        self.S_prev = S
        w = state.omega_b_radps[0]
        return [0.0, 0.0, 0.0], [self.J_r * S * w[1], -self.J_r * S * w[0], self.J_r * dS]


class RotorInertia(Effect):
    name = "rotor_inertia"
    target = "torque"
    linear = True
    parameters = (Parameter("J_r_kgm2", "kg m^2", 0.0, 0.0, 1e-7,
                            "inertia of one rotor (propeller + motor) about its axis"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        S = rotor_speeds_radps(state, vehicle) @ np.asarray(vehicle.yaw_sign, float)
        dS_dt = np.zeros_like(S)
        if state.n > 1:
            dS_dt[1:] = np.diff(S) / float(np.median(np.diff(state.t_s)))
        return np.zeros((state.n, 3)), rotor_inertia_torque(S, dS_dt, state.omega_b_radps, params["J_r_kgm2"])

    def check(self, params):
        if params["J_r_kgm2"] < 0:
            raise ValueError("J_r_kgm2 must be >= 0")

    def simulator(self, params, context):
        return RotorSpinHook(params["J_r_kgm2"], context)

    def c_code(self, vehicle, params):
        signs = ", ".join(f"{float(s):.1f}f" for s in vehicle.yaw_sign)
        # reads the logged motor speeds (the Python form falls back on the thrust map's when a log has none)
        return CCode(
            "int i;\n"
            f"const qc_real yaw_sign[QC_N_ROTORS] = {{{signs}}};\n"
            "qc_real S = 0.0f, dS_dt;\n"
            "for (i = 0; i < QC_N_ROTORS; ++i) S += yaw_sign[i] * (qc_real)motor_radps[i];\n"
            "if (first_call) net_spin_radps[0] = S;\n"
            "dS_dt = (S - net_spin_radps[0]) / dt_s;\n"
            "net_spin_radps[0] = S;\n"
            "tau_b_Nm[0] += J_r_kgm2 * S * omega_b_radps[1];\n"
            "tau_b_Nm[1] -= J_r_kgm2 * S * omega_b_radps[0];\n"
            "tau_b_Nm[2] += J_r_kgm2 * dS_dt;",
            memory=(("net_spin_radps", 1),))


EFFECT = RotorInertia()
