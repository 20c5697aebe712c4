"""Added mass: an unmodelled payload ``m_p`` (kg). The vehicle really weighs ``m + m_p``, so
the accelerometer reads ``T / (m + m_p)`` and the force the model infers from it,
``m sf``, falls short of the thrust::

    f_b = -(m_p / (m + m_p)) (0, 0, T)

In force it is indistinguishable from a weaker thrust map (``thrust_scale``). Fitted
linearly in ``c = m_p / (m + m_p)``, then ``m_p = c m / (1 - c)``.
"""

import numpy as np

from quadcore.effects.base import (
    Effect,
    Parameter,
    SimHook,
    body_z,
    collective_thrust_N,
)
from quadcore.effects.ccode import CCode


class PayloadHook(SimHook):
    """The body carries ``m_p`` more than the vehicle file says (at the CoM; inertia unchanged)."""

    def __init__(self, m_p_kg: float):
        self.m_p_kg = m_p_kg

    def true_mass_kg(self, mass_kg):
        if mass_kg + self.m_p_kg <= 0:
            raise ValueError("m + m_p must be positive")
        return mass_kg + self.m_p_kg


class AddedMass(Effect):
    name = "added_mass"
    target = "force"
    linear = True
    parameters = (Parameter("m_p_kg", "kg", 0.0, 0.0, 0.1, "unmodelled payload mass"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        m_p = params["m_p_kg"]
        c = m_p / (vehicle.mass_kg + m_p)
        return body_z(-c * collective_thrust_N(state)), np.zeros((state.n, 3))

    def basis(self, state, vehicle):
        # per unit of c = m_p / (m + m_p); see from_linear
        return [(body_z(-collective_thrust_N(state)), np.zeros((state.n, 3)))]

    def from_linear(self, coefficients, vehicle):
        c = float(np.clip(coefficients[0], -0.5, 0.9))
        return {"m_p_kg": c * vehicle.mass_kg / (1.0 - c)}

    def to_linear(self, params, vehicle):
        m_p = params["m_p_kg"]
        return [m_p / (vehicle.mass_kg + m_p)]

    def simulator(self, params, context):
        return PayloadHook(params["m_p_kg"])

    def c_code(self, vehicle, params):
        return CCode("const qc_real c = m_p_kg / (QC_MASS_KG + m_p_kg);\n"
                     "f_b_N[2] -= c * T_N;")


EFFECT = AddedMass()
