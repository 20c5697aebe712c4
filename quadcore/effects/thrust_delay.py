"""Thrust delay: each rotor's thrust is its mapped thrust a fixed time ``t_d`` earlier (a
transport delay between the logged inputs and the thrust: ESC update, communication, the
log's timestamps), beside ``motor_lag``'s first-order lag::

    f_i(t) = f_map,i(t - t_d)         [T, tau_b] = A (f(t - t_d) - f(t))             [t_d] = s

At low frequency a delay and a lag of the same time constant shift the phase alike
(``-ω t_d`` against ``-atan(ω τ)``); only the lag also lowers the amplitude, so the data
tell them apart by the faster changes of thrust, or cannot. Nonlinear in t_d; evaluated at
the median sample period (as ``motor_lag``): the thrust ``t_d / dt`` samples earlier, linear
between samples, the first sample held before it.
"""

import math

import numpy as np

from quadcore.effects.base import Effect, Parameter, SimHook, rotor_wrench
from quadcore.effects.ccode import CCode

MIN_PERIOD_S = 0.001  # the C form keeps a history long enough for calls at up to 1 kHz


def delayed(x: np.ndarray, t_s: np.ndarray, delay_s: float) -> np.ndarray:
    """Columns of ``x`` (n, k) ``delay_s / dt`` samples earlier (``dt`` the median period),
    linear between samples, the first sample held before the start."""
    if delay_s <= 0 or len(x) < 2:
        return x.copy()
    steps = delay_s / float(np.median(np.diff(t_s)))
    k = np.arange(len(x), dtype=float)
    return np.column_stack([np.interp(k - steps, k, x[:, i]) for i in range(x.shape[1])])


class DelayHook(SimHook):
    """Each rotor's thrust is its input ``t_d`` earlier, from a history kept per physics step
    (linear between steps); before the flight, ``start_N`` (the nominal hover thrust: the
    vehicle hovered), or the first input held when None."""

    def __init__(self, delay_s: float, h_s: float, start_N: list[float] | None = None):
        self.steps = delay_s / h_s
        self.whole = int(np.floor(self.steps))
        self.frac = self.steps - self.whole
        self.history: list[list[float]] = [list(start_N)] if start_N is not None else []

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
    retimes_thrust = True
    linear_between_samples = True  # delayed(): linear in t_d between whole samples
    parameters = (Parameter("t_d_s", "s", 0.0, 0.0, 0.1, "transport delay from logged input to rotor thrust"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        return rotor_wrench(vehicle, delayed(state.f_rotor_N, state.t_s, params["t_d_s"]) - state.f_rotor_N)

    def memory_s(self):
        """The longest delay searched: before it the delayed thrust is the first sample's, held."""
        return self.parameters[0].upper

    def check(self, params):
        if params["t_d_s"] < 0:
            raise ValueError("t_d_s must be >= 0")

    def simulator(self, params, context):
        if params["t_d_s"] <= 0:
            return SimHook()
        n = context.vehicle.n_rotors  # the vehicle hovered before the flight
        return DelayHook(params["t_d_s"], context.h_s, [context.vehicle.weight_N / n] * n)

    def c_code(self, vehicle, params):
        if params["t_d_s"] <= 0:
            return CCode("/* t_d_s <= 0: no delay */")
        size = math.ceil(params["t_d_s"] / MIN_PERIOD_S) + 2
        # a ring of the last `size` thrusts; the delayed one t_d / dt_s calls back, linear between
        return CCode(
            "int i, r;\n"
            f"const int size = {size};\n"
            "qc_real steps = t_d_s / dt_s, frac, missing[QC_N_ROTORS];\n"
            "int whole, head, newer, older;\n"
            "if (first_call) {\n"
            "    for (r = 0; r < size; ++r)\n"
            "        for (i = 0; i < QC_N_ROTORS; ++i) thrust_history_N[r * QC_N_ROTORS + i] = f_rotor_N[i];\n"
            "    thrust_history_head[0] = 0.0f;\n"
            "}\n"
            "head = ((int)thrust_history_head[0] + 1) % size;\n"
            "thrust_history_head[0] = (qc_real)head;\n"
            "for (i = 0; i < QC_N_ROTORS; ++i) thrust_history_N[head * QC_N_ROTORS + i] = f_rotor_N[i];\n"
            "if (steps > (qc_real)(size - 2)) steps = (qc_real)(size - 2); /* calls faster than 1 kHz */\n"
            "whole = (int)steps;\n"
            "frac = steps - (qc_real)whole;\n"
            "newer = (head - whole + size) % size;\n"
            "older = (newer - 1 + size) % size;\n"
            "for (i = 0; i < QC_N_ROTORS; ++i)\n"
            "    missing[i] = thrust_history_N[newer * QC_N_ROTORS + i] * (1.0f - frac)\n"
            "        + thrust_history_N[older * QC_N_ROTORS + i] * frac - f_rotor_N[i];\n"
            "qc_add_rotor_wrench(missing, 1.0f, f_b_N, tau_b_Nm);",
            memory=(("thrust_history_N", size * vehicle.n_rotors), ("thrust_history_head", 1)))


EFFECT = ThrustDelay()
