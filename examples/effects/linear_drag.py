"""Linear airframe drag: a force against the body-frame velocity, proportional to it::

    f_b = -(d_xy v_b,x, d_xy v_b,y, d_z v_b,z)           [d] = kg/s = N/(m/s)

A worked example of a user effect (see ``docs/adding-an-effect.md``): one module, one
:class:`~quadcore.effects.Effect` subclass, one ``EFFECT`` instance. List this file under
``plugins`` in ``model.toml`` and the diagnosis offers it as a candidate, the fitting fits
it, the simulator can fly it.

Physics note: in the body x-y plane it is what ``rotor_drag`` (``-k T v``) becomes at
constant thrust (``d_xy = k T``); only flights whose thrust varies a lot, or the ``z``
part, tell the two apart -- and the diagnosis will say so when they cannot.
"""

import numpy as np

from quadcore.effects import Effect, Parameter
from quadcore.effects.ccode import CCode


class LinearDrag(Effect):
    name = "linear_drag"
    target = "force"  # it only adds a force: the diagnosis scores it on the force residual
    linear = True  # the wrench is linear in (d_xy, d_z): fitted in closed form
    parameters = (
        Parameter("d_xy_kg_per_s", "kg/s", 0.0, 0.0, 1.0, "linear drag in the body x-y plane"),
        Parameter("d_z_kg_per_s", "kg/s", 0.0, 0.0, 1.0, "linear drag along body z"),
    )
    doc = __doc__

    def wrench(self, state, vehicle, params):
        d = np.array([params["d_xy_kg_per_s"], params["d_xy_kg_per_s"], params["d_z_kg_per_s"]])
        force = -state.v_b_mps * d  # (n, 3) N, body frame
        return force, np.zeros((state.n, 3))  # no torque

    def c_code(self, vehicle, params):
        # optional: the same force in C for `quadcore export-c` (parameters are declared by the exporter)
        return CCode("f_b_N[0] -= d_xy_kg_per_s * v_b_mps[0];\n"
                     "f_b_N[1] -= d_xy_kg_per_s * v_b_mps[1];\n"
                     "f_b_N[2] -= d_z_kg_per_s * v_b_mps[2];")


EFFECT = LinearDrag()
