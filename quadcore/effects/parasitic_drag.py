"""Parasitic (airframe) drag, quadratic in airspeed::

    f_b = -|v| (c_xy v_b,x, c_xy v_b,y, c_z v_b,z),     c = ½ ρ C_d A   [kg/m]

Linear in (c_xy, c_z). The velocity is the ground velocity (no wind in the model); in a
simulated wind the simulator applies it to the airspeed.
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter
from quadcore.effects.ccode import CCode


class ParasiticDrag(Effect):
    name = "parasitic_drag"
    target = "force"
    linear = True
    acts_on_airspeed = True
    parameters = (
        Parameter("c_xy_kg_per_m", "kg/m", 0.0, 0.0, 1.0, "½ρC_dA in the body x-y plane"),
        Parameter("c_z_kg_per_m", "kg/m", 0.0, 0.0, 1.0, "½ρC_dA along body z"),
    )
    doc = __doc__

    def wrench(self, state, vehicle, params):
        v = state.v_b_mps
        speed = np.linalg.norm(v, axis=1)
        c = np.array([params["c_xy_kg_per_m"], params["c_xy_kg_per_m"], params["c_z_kg_per_m"]])
        return -speed[:, None] * v * c, np.zeros((state.n, 3))

    def c_code(self, vehicle, params):
        return CCode("const qc_real speed = qc_sqrt(v_b_mps[0] * v_b_mps[0] + v_b_mps[1] * v_b_mps[1]"
                     " + v_b_mps[2] * v_b_mps[2]);\n"
                     "f_b_N[0] -= c_xy_kg_per_m * speed * v_b_mps[0];\n"
                     "f_b_N[1] -= c_xy_kg_per_m * speed * v_b_mps[1];\n"
                     "f_b_N[2] -= c_z_kg_per_m * speed * v_b_mps[2];")

EFFECT = ParasiticDrag()
