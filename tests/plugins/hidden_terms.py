"""Test plugin: physics that no effect of the library has, flown by the simulator so that
``quadcore discover`` can be checked against a known answer::

    f_z   = k_lift_s2_per_m2 · T |v_h|²         translational lift (thrust grows with horizontal speed)
    tau_x = +k_flap_s · T v_b,y                 blade-flapping hub moment
    tau_y = -k_flap_s · T v_b,x

``T`` is the collective map thrust, ``v_h`` the horizontal body velocity.
"""

import numpy as np

from quadcore.effects import Effect, Parameter


class HiddenTerms(Effect):
    name = "hidden_terms"
    target = "both"
    linear = True
    parameters = (
        Parameter("k_lift_s2_per_m2", "s^2/m^2", 0.0, -1.0, 1.0, "thrust gain per (m/s)^2 of horizontal speed"),
        Parameter("k_flap_s", "s", 0.0, -0.01, 0.01, "flapping moment per N m/s of thrust times speed"),
    )

    def wrench(self, state, vehicle, params):
        T = state.f_rotor_N.sum(axis=1)
        v = state.v_b_mps
        f = np.zeros((state.n, 3))
        tau = np.zeros((state.n, 3))
        f[:, 2] = params["k_lift_s2_per_m2"] * T * (v[:, 0] ** 2 + v[:, 1] ** 2)
        tau[:, 0] = params["k_flap_s"] * T * v[:, 1]
        tau[:, 1] = -params["k_flap_s"] * T * v[:, 0]
        return f, tau


EFFECT = HiddenTerms()
