"""Centre-of-mass offset: the CoM sits at ``r_c = (x_c, y_c, 0)`` from the rotor centre, so
the thrust acts with a lever arm about it::

    tau_b = -r_c × (0, 0, T) = (-y_c T, x_c T, 0)                  [x_c, y_c] = m

Linear in (x_c, y_c).
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, collective_thrust_N
from quadcore.effects.ccode import CCode


class ComOffset(Effect):
    name = "com_offset"
    target = "torque"
    linear = True
    parameters = (
        Parameter("x_c_m", "m", 0.0, -0.02, 0.02, "CoM offset along body x"),
        Parameter("y_c_m", "m", 0.0, -0.02, 0.02, "CoM offset along body y"),
    )
    doc = __doc__

    def wrench(self, state, vehicle, params):
        T = collective_thrust_N(state)
        tau = np.zeros((state.n, 3))
        tau[:, 0] = -params["y_c_m"] * T
        tau[:, 1] = params["x_c_m"] * T
        return np.zeros((state.n, 3)), tau

    def c_code(self, vehicle, params):
        return CCode("tau_b_Nm[0] -= y_c_m * T_N;\n"
                     "tau_b_Nm[1] += x_c_m * T_N;")

EFFECT = ComOffset()
