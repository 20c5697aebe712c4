"""Rotor drag (blade flapping and induced drag): a horizontal force against the body-frame
velocity, proportional to thrust (Faessler et al. 2018, Kai et al. 2017)::

    f_b,x = -k_x T v_b,x,    f_b,y = -k_y T v_b,y          [k] = s/m

Linear in (k_x, k_y). At constant thrust it looks exactly like a linear drag.
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
    )
    doc = __doc__

    def wrench(self, state, vehicle, params):
        T = collective_thrust_N(state)
        f = np.zeros((state.n, 3))
        f[:, 0] = -params["k_x_s_per_m"] * T * state.v_b_mps[:, 0]
        f[:, 1] = -params["k_y_s_per_m"] * T * state.v_b_mps[:, 1]
        return f, np.zeros((state.n, 3))

    def c_code(self, vehicle, params):
        return CCode("f_b_N[0] -= k_x_s_per_m * T_N * v_b_mps[0];\n"
                     "f_b_N[1] -= k_y_s_per_m * T_N * v_b_mps[1];")

EFFECT = RotorDrag()
