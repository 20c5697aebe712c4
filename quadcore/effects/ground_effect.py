"""Ground effect: more thrust near the ground, after Cheeseman and Bennett (1955)::

    ΔT = k_ge T (R / (4 h))^2,    h = max(z, R)                     along body z

``R`` is the rotor radius (vehicle file), ``h`` the height of the rotors over the ground
plane z = 0 (world frame), ``k_ge`` dimensionless: 1 for the classic single-rotor theory,
larger for multirotors whose rotors and frame interact. Linear in k_ge.
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, body_z, collective_thrust_N
from quadcore.effects.ccode import CCode


def proximity(state, vehicle) -> np.ndarray:
    """(R / 4h)^2 with the rotor height floored at one rotor radius."""
    R = vehicle.rotor_radius_m
    h = np.maximum(state.p_w_m[:, 2], R)
    return (R / (4.0 * h)) ** 2


class GroundEffect(Effect):
    name = "ground_effect"
    target = "force"
    linear = True
    parameters = (Parameter("k_ge", "1", 0.0, 0.0, 200.0, "thrust gain coefficient in ΔT = k T (R/4h)^2"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        dT = params["k_ge"] * collective_thrust_N(state) * proximity(state, vehicle)
        return body_z(dT), np.zeros((state.n, 3))

    def c_code(self, vehicle, params):
        return CCode("const qc_real h = p_w_m[2] > QC_ROTOR_RADIUS_M ? p_w_m[2] : QC_ROTOR_RADIUS_M;"
                     "  /* height floored at R */\n"
                     "const qc_real r = QC_ROTOR_RADIUS_M / (4.0f * h);\n"
                     "f_b_N[2] += k_ge * T_N * r * r;")

EFFECT = GroundEffect()
