"""Thrust scale: the rotors give ``s`` times what the thrust map says (a worn or different
propeller, a map fitted on another vehicle)::

    f_b = (s - 1) (0, 0, T),     tau_b = (s - 1) tau_rotors

Linear in (s - 1). In force it is indistinguishable from an unmodelled payload
(``added_mass``); only the torque part can tell them apart.
"""

from quadcore.effects.base import Effect, Parameter, ScaleRotorThrusts, body_z
from quadcore.effects.ccode import CCode
from quadcore.physics import dynamics


class ThrustScale(Effect):
    name = "thrust_scale"
    target = "both"
    linear = True
    parameters = (Parameter("scale", "1", 1.0, 0.3, 2.0, "true thrust / mapped thrust"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        T, tau = dynamics.wrench_from_thrusts(vehicle, state.f_rotor_N)
        k = params["scale"] - 1.0
        return body_z(k * T), k * tau

    def check(self, params):
        if params["scale"] <= 0:
            raise ValueError("scale must be > 0")

    def simulator(self, params, context):
        return ScaleRotorThrusts([params["scale"]] * context.vehicle.n_rotors)

    def c_code(self, vehicle, params):
        return CCode("qc_add_rotor_wrench(f_rotor_N, scale - 1.0f, f_b_N, tau_b_Nm);")


EFFECT = ThrustScale()
