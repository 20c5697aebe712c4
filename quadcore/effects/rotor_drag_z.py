"""Rotor drag along the rotor axis: a force along body z against the body-frame vertical
velocity, proportional to thrust -- the vertical entry ``d_z`` of the linear rotor-drag matrix
``D = diag(d_x, d_y, d_z)`` of Faessler et al. (2018), and the axial part ``k_z`` of a rotor's
drag ``-ω_i K v`` (``K = diag(k_d, k_d, k_z)``, ``ω_i`` the rotor speed) in rotorpy's
multirotor model (Folk et al. 2023): in axial flow the rotors' inflow changes with the climb
rate, so their thrust falls when climbing and rises when descending (Svacha et al. 2017 model
it through the induced velocity)::

    f_b,z = -k_z T v_b,z                     [k_z] = s/m,   T the collective thrust (N)

Linear in k_z. With ``rotor_drag`` (the horizontal entries, ``-k T v_b,x``, ``-k T v_b,y``) it
is Faessler's ``-T D v`` with ``D`` scaled by the thrust; near hover ``k_z T`` is the linear
vertical drag in kg/s. It is an effect of its own, not a third parameter of ``rotor_drag``:
the vertical coefficient is a different mechanism with its own size (rotorpy's Crazyflie:
``k_z / k_d = 0.74``), seen only when the vehicle climbs or descends, and a model with
horizontal rotor drag keeps its meaning (see ``docs/adding-an-effect.md``).
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, body_z, collective_thrust_N
from quadcore.effects.ccode import CCode


class RotorDragZ(Effect):
    name = "rotor_drag_z"
    target = "force"
    linear = True
    parameters = (Parameter("k_z_s_per_m", "s/m", 0.0, 0.0, 5.0, "drag per newton of thrust per m/s, body z"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        T = collective_thrust_N(state)
        return body_z(-params["k_z_s_per_m"] * T * state.v_b_mps[:, 2]), np.zeros((state.n, 3))

    def c_code(self, vehicle, params):
        return CCode("f_b_N[2] -= k_z_s_per_m * T_N * v_b_mps[2];")


EFFECT = RotorDragZ()
