"""A plugin effect with two nonlinear parameters (a share of the thrust lagging by a first-order
lag): what the profiles cannot carry, so the search fits it (tests/test_search.py, test_sufficient.py)."""

from quadcore.effects.base import Effect, Parameter, rotor_wrench
from quadcore.effects.motor_lag import first_order_lag


class ScaledLag(Effect):
    name = "scaled_lag"
    target = "both"
    parameters = (Parameter("tau_s", "s", 0.0, 0.0, 0.2, "time constant"),
                  Parameter("share", "1", 0.0, 0.0, 2.0, "share of the thrust that lags"))

    def wrench(self, state, vehicle, params):
        lagged = first_order_lag(state.f_rotor_N, state.t_s, params["tau_s"])
        return rotor_wrench(vehicle, params["share"] * (lagged - state.f_rotor_N))


EFFECT = ScaledLag()
