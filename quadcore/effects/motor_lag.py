"""Motor lag: each rotor's thrust follows its command through a first-order lag::

    τ_m df/dt = f_cmd - f        (per rotor; f_cmd from the thrust map)

The extra wrench is what the lag takes away: ``A (f - f_cmd)``, force along body z and
torque about all three axes. Nonlinear in the time constant τ_m (s); evaluated with an
exact discretisation at the median sample period. The force is the lag's value at each
sample (what the accelerometer sees); the torque its mean over the interval that follows,
``f_cmd + (f - f_cmd)(1 - a) τ_m / dt`` (what the gyro's derivative integrates, with the
command held over the interval: docs/timing.md). It starts at steady state on the first
command. A log that starts in a manoeuvre starts with the rotors' true lag state unknown: the
identification leaves out the first five time constants at the longest lag searched
(:meth:`MotorLag.memory_s`, 1 s), where that start would bias the fit.
"""

import math

import numpy as np
from scipy.signal import lfilter, lfilter_zi

from quadcore.effects.base import Effect, Parameter, SimHook, rotor_wrench
from quadcore.effects.ccode import CCode


def first_order_lag(x: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Filter columns of ``x`` through ``1 / (tau s + 1)``, starting at steady state.

    Causal, zero-order hold: a command logged at sample k acts from sample k + 1,
    ``y[k+1] = a y[k] + (1 - a) x[k]`` with ``a = exp(-dt / tau)``.
    """
    if tau_s <= 0 or len(x) < 2:
        return x.copy()
    dt = float(np.median(np.diff(t_s)))
    a = np.exp(-dt / tau_s)
    b, den = [0.0, 1.0 - a], [1.0, -a]
    y, _ = lfilter(b, den, x, axis=0, zi=lfilter_zi(b, den)[:, None] * x[:1])
    return y


def interval_mean_share(t_s: np.ndarray, tau_s: float) -> float:
    """``(1 - a) τ / dt``: the mean over a sample interval of a lag's distance to a held input,
    per its distance at the interval's start (1 without a lag)."""
    if tau_s <= 0 or len(t_s) < 2:
        return 1.0
    dt = float(np.median(np.diff(t_s)))
    return float(-np.expm1(-dt / tau_s) * tau_s / dt)


class LagHook(SimHook):
    """Each rotor's thrust relaxes toward its input, integrated exactly per physics step
    (the input ``x`` is held over the step); starts at ``start_N`` (the rotors' thrust before
    the flight, the nominal hover thrust: a first command that asks for more or less is a step
    they follow with the lag), or at steady state on the first input when None.

    From ``y_0`` at the step's start, ``y(h) = x + (y_0 - x) a`` with ``a = exp(-h / τ)``; the
    body integrates the step's mean ``x + (y_0 - x) (1 - a) τ / h``, and the sensors see
    ``y_0`` at the log instant. (Holding ``y_0`` over the step instead would delay the thrust
    the body feels by ``h / 2`` behind the logged rotor speed.)"""

    def __init__(self, tau_s: float, h_s: float, start_N: list[float] | None = None):
        self.a = math.exp(-h_s / tau_s) if tau_s > 0 else 0.0
        self.mean = (1.0 - self.a) * tau_s / h_s if tau_s > 0 else 0.0
        self.f_N: list[float] | None = start_N

    def thrusts_now(self, f_N):
        return list(self.f_N) if self.f_N is not None else list(f_N)

    def rotor_thrusts(self, f_N, k, j):
        start = self.f_N if self.f_N is not None else list(f_N)
        self.f_N = [x + (y - x) * self.a for y, x in zip(start, f_N)]
        return [x + (y - x) * self.mean for y, x in zip(start, f_N)]


class MotorLag(Effect):
    name = "motor_lag"
    target = "both"
    linear = False
    retimes_thrust = True
    parameters = (Parameter("tau_s", "s", 0.0, 0.0, 0.2, "first-order time constant of rotor thrust"),)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        missing = first_order_lag(state.f_rotor_N, state.t_s, params["tau_s"]) - state.f_rotor_N
        f, _ = rotor_wrench(vehicle, missing)
        _, tau = rotor_wrench(vehicle, missing * interval_mean_share(state.t_s, params["tau_s"]))
        return f, tau

    def check(self, params):
        if params["tau_s"] < 0:
            raise ValueError("tau_s must be >= 0")

    def memory_s(self):
        """Five time constants at the longest lag searched: an initial thrust error decays to
        e^-5 (0.7 %) of itself at that lag, and to far less at shorter ones."""
        return 5.0 * self.parameters[0].upper

    def simulator(self, params, context):
        if params["tau_s"] <= 0:
            return SimHook()  # no lag: nothing to fly
        n = context.vehicle.n_rotors  # the vehicle hovered before the flight
        return LagHook(params["tau_s"], context.h_s, [context.vehicle.weight_N / n] * n)

    def c_code(self, vehicle, params):
        if params["tau_s"] <= 0:  # as in first_order_lag: no lag, no wrench
            return CCode("/* tau_s <= 0: no lag */")
        # y[k+1] = a y[k] + (1 - a) x[k], a = exp(-dt / tau), steady state at the first call;
        # the wrench of this call uses y[k] (force) and its interval mean (torque), then y advances
        return CCode(
            "int r;\n"
            "qc_real missing[QC_N_ROTORS];\n"
            "const qc_real a = qc_exp(-dt_s / tau_s);\n"
            "const qc_real share = (1.0f - a) * tau_s / dt_s;\n"
            "for (r = 0; r < QC_N_ROTORS; ++r) {\n"
            "    if (first_call) lagged_f_rotor_N[r] = f_rotor_N[r];\n"
            "    missing[r] = lagged_f_rotor_N[r] - f_rotor_N[r];\n"
            "    lagged_f_rotor_N[r] = a * lagged_f_rotor_N[r] + (1.0f - a) * f_rotor_N[r];\n"
            "}\n"
            "qc_add_rotor_wrench(missing, share, f_b_N, tau_b_Nm);\n"
            "for (r = 0; r < QC_N_ROTORS; ++r) f_b_N[2] += (1.0f - share) * missing[r];  /* force: y[k] itself */",
            memory=(("lagged_f_rotor_N", vehicle.n_rotors),))


EFFECT = MotorLag()
