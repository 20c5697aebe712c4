"""Thrust delay: each rotor's thrust is its mapped thrust a fixed time ``t_d`` earlier (a
transport delay between the logged inputs and the thrust: ESC update, communication, the
log's timestamps), beside ``motor_lag``'s first-order lag::

    f_i(t) = f_map,i(t - t_d)         [T, tau_b] = A (f(t - t_d) - f(t))             [t_d] = s

At low frequency a delay and a lag of the same time constant shift the phase alike
(``-ω t_d`` against ``-atan(ω τ)``); only the lag also lowers the amplitude, so the data
tell them apart by the faster changes of thrust, or cannot. Nonlinear in t_d; the delayed
thrust is interpolated linearly between logged samples (the first sample held before it).
"""

import numpy as np

from quadcore import dynamics
from quadcore.effects.base import Effect, Parameter, SimHook, body_z


def delayed(x: np.ndarray, t_s: np.ndarray, delay_s: float) -> np.ndarray:
    """Columns of ``x`` (n, k) at ``t - delay_s``, linear between samples, held at the ends."""
    if delay_s <= 0:
        return x.copy()
    return np.column_stack([np.interp(t_s - delay_s, t_s, x[:, i]) for i in range(x.shape[1])])


class DelayHook(SimHook):
    """Each rotor's thrust is its input ``t_d`` earlier, from a history kept per physics step
    (linear between steps; the first input held before the flight)."""

    def __init__(self, delay_s: float, h_s: float):
        self.steps = delay_s / h_s
        self.whole = int(np.floor(self.steps))
        self.frac = self.steps - self.whole
        self.history: list[list[float]] = []

    def rotor_thrusts(self, f_N, k, j):
        self.history.append(list(f_N))
        m = len(self.history) - 1
        older = self.history[max(m - self.whole - 1, 0)]
        newer = self.history[max(m - self.whole, 0)]
        if len(self.history) > self.whole + 2:
            del self.history[0]
        return [b + (a - b) * self.frac for a, b in zip(older, newer)]


class ThrustDelay(Effect):
    name = "thrust_delay"
    target = "both"
    linear = False
    parameters = (Parameter("t_d_s", "s", 0.0, 0.0, 0.1, "transport delay from logged input to rotor thrust"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        late = delayed(state.f_rotor_N, state.t_s, params["t_d_s"])
        dT, dtau = dynamics.wrench_from_thrusts(vehicle, late - state.f_rotor_N)
        return body_z(dT), dtau

    def check(self, params):
        if params["t_d_s"] < 0:
            raise ValueError("t_d_s must be >= 0")

    def simulator(self, params, context):
        return DelayHook(params["t_d_s"], context.h_s) if params["t_d_s"] > 0 else SimHook()


EFFECT = ThrustDelay()
