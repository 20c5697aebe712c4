"""A third timing plugin (it re-times the rotors' thrust, one parameter): each rotor's thrust
through two first-order lags of one time constant in series. With ``thrust_delay`` and
``motor_lag`` it makes three timing candidates, which the rate level compares pair by pair
(tests/test_rates.py)."""

from quadcore.effects.base import Effect, Parameter, rotor_wrench
from quadcore.effects.motor_lag import first_order_lag


class DoubleLag(Effect):
    name = "double_lag"
    target = "both"
    linear = False
    retimes_thrust = True
    parameters = (Parameter("tau_s", "s", 0.0, 0.0, 0.2, "time constant of each of the two lags"),)

    def wrench(self, state, vehicle, params):
        twice = first_order_lag(first_order_lag(state.f_rotor_N, state.t_s, params["tau_s"]), state.t_s,
                                params["tau_s"])
        return rotor_wrench(vehicle, twice - state.f_rotor_N)

    def memory_s(self):
        """Seven time constants at the longest lag searched: an initial thrust error through both
        lags, ``(1 + t/τ) e^(-t/τ)`` of itself, is 0.7 % of it there (``motor_lag``'s share)."""
        return 7.0 * self.parameters[0].upper


EFFECT = DoubleLag()
