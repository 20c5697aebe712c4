"""Wind: a constant horizontal air velocity ``w`` (world frame) that the rotors feel through
rotor drag on the airspeed instead of the ground speed::

    v_air,b = R^T (v_w - w),     f_b,xy = -k T v_air,b,xy,     f_b,z = -k_z T v_b,z
                                                               [k] = [k_z] = s/m, [w] = m/s

With ``w = 0`` and ``k_x = k_y = k`` this is ``rotor_drag``, its axial part ``k_z`` included
(so the two compare like for like, and a still-air wind has one parameter more); a wind shows
as a drag force that depends on heading and attitude. The axial part acts on the ground
velocity along body z: the horizontal wind's share of the air velocity along body z
(``w`` times the tilt) is left out, which keeps the effect linear. Fitted linearly in
(k, k w_x, k w_y, k_z), then ``w = (k w) / k``.

Simulated as a real wind: ``w`` plus a horizontal gust (Ornstein-Uhlenbeck with the
``SimConfig``'s ``wind_gust_std_mps`` and ``wind_gust_tau_s``), felt by this effect and by
every effect that ``acts_on_airspeed``.
"""

import math
from typing import ClassVar

import numpy as np
from scipy.signal import lfilter

from quadcore.effects.base import Effect, Parameter, SimHook, collective_thrust_N
from quadcore.effects.ccode import CCode
from quadcore.physics import rotations


class WindHook(SimHook):
    """The air velocity of one flight (mean + gust, drawn once) and its rotor-drag wrench."""

    def __init__(self, effect: "Wind", params: dict[str, float], context):
        n, dt, cfg = len(context.t_s), context.dt_s, context.config
        air = np.zeros((n, 3))
        air[:, 0], air[:, 1] = params["w_x_mps"], params["w_y_mps"]
        if cfg.wind_gust_std_mps > 0:
            a = math.exp(-dt / max(cfg.wind_gust_tau_s, 1e-6))
            drive = context.rng.normal(0.0, cfg.wind_gust_std_mps * math.sqrt(1 - a * a), size=(n, 2))
            zi = (context.rng.normal(0.0, cfg.wind_gust_std_mps, size=2) * a)[None, :]
            air[:, :2] += lfilter([1.0], [1.0, -a], drive, axis=0, zi=zi)[0]
        self.air, self.effect, self.params, self.vehicle = air, effect, params, context.vehicle

    def air_velocity_w_mps(self):
        return self.air

    def wrench(self, state, k, j):
        params = {**self.params, "w_x_mps": self.air[k, 0], "w_y_mps": self.air[k, 1]}
        f, _ = self.effect.wrench(state, self.vehicle, params)
        return f[0].tolist(), [0.0, 0.0, 0.0]


class Wind(Effect):
    name = "wind"
    target = "force"
    linear = True
    parameters = (
        Parameter("k_s_per_m", "s/m", 0.0, 0.0, 5.0, "rotor-drag coefficient acting on airspeed"),
        Parameter("w_x_mps", "m/s", 0.0, -10.0, 10.0, "air velocity, world x"),
        Parameter("w_y_mps", "m/s", 0.0, -10.0, 10.0, "air velocity, world y"),
        Parameter("k_z_s_per_m", "s/m", 0.0, 0.0, 5.0, "axial rotor-drag coefficient, body z"),
    )
    doc = __doc__
    # a wind shows only through a drag: how small a wind is noticed is stated at the rotor
    # drag of a Crazyflie 2.1 (0.036-0.04 s/m on the real logs)
    sensitivity_reference: ClassVar[dict[str, float]] = {"k_s_per_m": 0.04}

    def wrench(self, state, vehicle, params):
        k = params["k_s_per_m"]
        w = np.array([params["w_x_mps"], params["w_y_mps"], 0.0])
        v_air_b = rotations.world_to_body(state.R_wb, state.v_w_mps - w)
        f = np.zeros((state.n, 3))
        T = collective_thrust_N(state)
        f[:, :2] = -k * T[:, None] * v_air_b[:, :2]
        f[:, 2] = -params["k_z_s_per_m"] * T * state.v_b_mps[:, 2]
        return f, np.zeros((state.n, 3))

    def basis(self, state, vehicle):
        T = collective_thrust_N(state)[:, None]
        zero = np.zeros((state.n, 3))
        out = []
        for col in range(4):  # coefficients of k, k w_x, k w_y, k_z
            f = np.zeros((state.n, 3))
            if col == 0:
                f[:, :2] = -T * state.v_b_mps[:, :2]
            elif col == 3:
                f[:, 2] = -T[:, 0] * state.v_b_mps[:, 2]
            else:
                e = np.zeros(3)
                e[col - 1] = 1.0
                f[:, :2] = T * rotations.world_to_body(state.R_wb, np.broadcast_to(e, (state.n, 3)))[:, :2]
            out.append((f, zero))
        return out

    def from_linear(self, coefficients, vehicle):
        k, k_z = float(coefficients[0]), float(coefficients[3])
        if k <= 1e-9:
            return {"k_s_per_m": max(k, 0.0), "w_x_mps": 0.0, "w_y_mps": 0.0, "k_z_s_per_m": k_z}
        return {"k_s_per_m": k, "w_x_mps": float(coefficients[1]) / k, "w_y_mps": float(coefficients[2]) / k,
                "k_z_s_per_m": k_z}

    def to_linear(self, params, vehicle):
        k = params["k_s_per_m"]
        return [k, k * params["w_x_mps"], k * params["w_y_mps"], params["k_z_s_per_m"]]

    def simulator(self, params, context):
        return WindHook(self, params, context)

    def c_code(self, vehicle, params):
        # v_air,b = R^T (v_w - w), x and y components only
        return CCode("const qc_real dv[3] = {v_w_mps[0] - w_x_mps, v_w_mps[1] - w_y_mps, v_w_mps[2]};\n"
                     "int j;\n"
                     "for (j = 0; j < 2; ++j) {\n"
                     "    const qc_real v_air = R_wb[0][j] * dv[0] + R_wb[1][j] * dv[1] + R_wb[2][j] * dv[2];\n"
                     "    f_b_N[j] -= k_s_per_m * T_N * v_air;\n"
                     "}\n"
                     "f_b_N[2] -= k_z_s_per_m * T_N * v_b_mps[2];")


EFFECT = Wind()
