"""Per-rotor thrust imbalance: rotor ``i`` gives ``(1 + d_i)`` times its mapped thrust
(a chipped or different propeller, a weaker motor), the imbalance summing to zero::

    Δf_i = d_i f_i,   d_4 = -(d_1 + d_2 + d_3),     [T, tau_b] = A Δf              [d] = 1

``A`` is the vehicle's allocation (:mod:`quadcore.physics.vehicle`). The common part of the four
factors is ``thrust_scale``; what is left here shows in yaw (``t2t Σ yaw_sign_i Δf_i``) and
in roll and pitch, where in hover it looks like a CoM offset (``a T d / 4``) and differs
from one when the rotors' thrusts part. Linear in (d_1, d_2, d_3). Four rotors only.
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, ScaleRotorThrusts, rotor_wrench
from quadcore.effects.ccode import CCode


def rotor_factors(params: dict[str, float]) -> np.ndarray:
    """(4,) the ``d_i`` of every rotor, the fourth closing the sum to zero."""
    d = [params["d_1"], params["d_2"], params["d_3"]]
    return np.array([*d, -sum(d)])


class RotorImbalance(Effect):
    name = "rotor_imbalance"
    target = "both"
    linear = True
    parameters = tuple(
        Parameter(f"d_{i}", "1", 0.0, -0.3, 0.3,
                  f"rotor {i}: true thrust / mapped thrust - 1 (d_4 closes the sum to 0)")
        for i in (1, 2, 3))
    doc = __doc__

    def wrench(self, state, vehicle, params):
        if vehicle.n_rotors != 4:
            raise ValueError(f"rotor_imbalance needs 4 rotors; vehicle {vehicle.name!r} has {vehicle.n_rotors}")
        return rotor_wrench(vehicle, state.f_rotor_N * rotor_factors(params))

    def check(self, params):
        if np.any(rotor_factors(params) <= -1.0):
            raise ValueError("every rotor needs 1 + d_i > 0")

    def simulator(self, params, context):
        return ScaleRotorThrusts(list(1.0 + rotor_factors(params)))

    def c_code(self, vehicle, params):
        if vehicle.n_rotors != 4:
            return None
        return CCode(
            "int i;\n"
            "const qc_real d[QC_N_ROTORS] = {d_1, d_2, d_3, -(d_1 + d_2 + d_3)};\n"
            "qc_real extra[QC_N_ROTORS];\n"
            "for (i = 0; i < QC_N_ROTORS; ++i) extra[i] = d[i] * f_rotor_N[i];\n"
            "qc_add_rotor_wrench(extra, 1.0f, f_b_N, tau_b_Nm);")


EFFECT = RotorImbalance()
