"""Rotor drag (blade flapping and induced drag, and its axial part): a force against the
body-frame velocity, proportional to thrust -- the linear rotor-drag matrix
``D = diag(d_x, d_y, d_z)`` of Faessler, Franchi & Scaramuzza (2018) scaled by the thrust
(Kai et al. 2017), and the per-rotor drag ``-ω_i diag(k_d, k_d, k_z) v`` of rotorpy's
multirotor model (Folk et al. 2023, ``ω_i`` the rotor speed)::

    f_b,x = -k_x T v_b,x,    f_b,y = -k_y T v_b,y,    f_b,z = -k_z T v_b,z      [k] = s/m

``T`` is the collective thrust (N). Linear in (k_x, k_y, k_z). At constant thrust it looks
exactly like a linear drag; near hover ``k T`` is the linear drag in kg/s. The horizontal
entries are the flapping of the blades and their induced drag; the vertical one, ``k_z``, is
the same rotors' axial inflow: climbing lowers their thrust, descending raises it (Svacha et
al. 2017 model it through the induced velocity). It shows only when the vehicle climbs or
descends, has its own size (rotorpy's Crazyflie: ``k_z / k_d = 0.74``) and is bounded at 0
like the others (a fit that puts it below 0 by less than its noise holds it there).
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, collective_thrust_N
from quadcore.effects.ccode import CCode


class RotorDrag(Effect):
    name = "rotor_drag"
    target = "force"
    linear = True
    parameters = (
        Parameter("k_x_s_per_m", "s/m", 0.0, 0.0, 5.0, "drag per newton of thrust per m/s, body x"),
        Parameter("k_y_s_per_m", "s/m", 0.0, 0.0, 5.0, "drag per newton of thrust per m/s, body y"),
        Parameter("k_z_s_per_m", "s/m", 0.0, 0.0, 5.0, "drag per newton of thrust per m/s, body z (axial)"),
    )
    doc = __doc__

    def wrench(self, state, vehicle, params):
        T = collective_thrust_N(state)
        k = np.array([params["k_x_s_per_m"], params["k_y_s_per_m"], params["k_z_s_per_m"]])
        return -k * T[:, None] * state.v_b_mps, np.zeros((state.n, 3))

    def c_code(self, vehicle, params):
        return CCode("f_b_N[0] -= k_x_s_per_m * T_N * v_b_mps[0];\n"
                     "f_b_N[1] -= k_y_s_per_m * T_N * v_b_mps[1];\n"
                     "f_b_N[2] -= k_z_s_per_m * T_N * v_b_mps[2];")


EFFECT = RotorDrag()
