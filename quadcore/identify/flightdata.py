"""A flight's rows (:class:`FlightData`): its state, the nominal residual, the usable samples and
the sensor-noise floor, what a flight's statistics are made from
(:func:`quadcore.identify.stats.sufficient.flight_stats`), and what every fit, test and description
asks of a flight (the :class:`Flight` protocol, which the statistics,
:class:`quadcore.identify.stats.sufficient.FlightStats`, answer from their Gram matrices; the same
answered on rows, sample by sample, is the tests' reference, ``tests/reference/flight.py``). Rows
answer only a prediction (:class:`Predicting`): what enters the statistics as an extra column
where they cannot carry an effect.

The bottom of the identification: the smoothed prediction of one effect on rows
(:func:`prediction`), its unit wrench (:func:`unit_wrench`), the blocks of the held-out test
(:data:`BLOCK_S`, :func:`block_index`) and the samples per independent one
(:data:`SAMPLES_PER_INDEPENDENT`). Nothing here imports anything above it in
``quadcore.identify``.

**Torque through the measurement's own filter.** The measured torque is
``J dω/dt + ω × J ω`` with ``dω/dt`` from the Savitzky-Golay *derivative*
(:func:`quadcore.physics.signals.derivative`). That derivative is the slope of a local line fit,
a stronger low-pass than the quadratic smoother (:func:`quadcore.physics.signals.smooth`): at
5 Hz it passes 91 % where the smoother passes 99.7 %, at 10 Hz 67 % against 96 %.
Comparing it with a *smoothed* model torque therefore leaves a residual of a few per cent
of the rotor torque in every flight (on simulated flights without any effect it is six
times the gyro noise) -- a signature a thrust scale or a motor lag would happily "explain".
Here every model torque (the rotors' and each effect's) goes through exactly the
measurement's filter instead: integrated in time (each sample held as the flight's thrust
source holds it: a PWM command for the command period, a measured motor speed for no time)
and then differentiated with the same derivative as the gyro
(:func:`quadcore.physics.signals.matched_to_derivative`; docs/timing.md). The force side needs
nothing of the kind: measured and modelled force go through the same smoother.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, Self

import numpy as np
from threadpoolctl import ThreadpoolController

from quadcore.effects import Effect, Parameter
from quadcore.identify.settings import STATISTICS
from quadcore.physics import dynamics, residuals, signals
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle

SAMPLES_PER_INDEPENDENT = signals.WINDOW
# the fixed settings of the statistics (quadcore.identify.settings.STATISTICS) under the names the code reads
BLOCK_S = STATISTICS.block_s  # length of the blocks (clusters) of the held-out test, s
SECANT = STATISTICS.secant  # share of a parameter's range over which its unit wrench is taken
GRAM_STRIDE = STATISTICS.gram_stride  # every 4th usable sample for the signature Gram (identify.diagnosis.span)

Signals = Mapping[str, np.ndarray]  # flight -> its signal: (n, 6) on rows, a (W,) vector on statistics


class Predicting(Protocol):
    """A flight an effect's prediction is made on: its rows (:class:`FlightData`, an (n, 6)
    array) or its statistics (:class:`quadcore.identify.stats.sufficient.FlightStats`, a signal
    vector over its columns)."""

    @property
    def flight(self) -> str: ...

    def predict(self, effects: Sequence[Effect], params: Mapping[str, dict], vehicle: Vehicle) -> np.ndarray: ...


class Flight(Predicting, Protocol):
    """What the fits, held-out tests and descriptions ask of one flight's statistics
    (:class:`quadcore.identify.stats.sufficient.FlightStats`: signals are vectors over its columns);
    ``tests/reference/flight.py`` answers the same on rows, the reference it is tested against."""

    @property
    def noise(self) -> np.ndarray: ...

    @property
    def n(self) -> int: ...

    def sum_of_squares(self, signal: np.ndarray) -> np.ndarray: ...

    def unit_signal(self, effect: Effect, param: Parameter, vehicle: Vehicle) -> np.ndarray: ...

    def reference_ss(self, effect: Effect, vehicle: Vehicle) -> float: ...

    def after_blocks(self, k: int) -> Self: ...

    def block_channel_sums(self, pairs: Sequence[tuple[Signals, Signals]]) -> list[np.ndarray]: ...

    def basis_columns(self, effect: Effect, vehicle: Vehicle) -> list[np.ndarray]: ...

    def strided_grams(self, columns: Sequence[np.ndarray], w: np.ndarray,
                      groups: Mapping[str, slice]) -> dict[str, np.ndarray]: ...


def smoothed_wrench(f: np.ndarray, tau: np.ndarray, state: FlightState) -> np.ndarray:
    """(n, 6) force through the smoother and torque through the gyro's filter (its samples
    held as the flight's thrust source holds), side by side: the way a wrench appears in the
    residuals."""
    t_s = state.t_s
    return np.concatenate([signals.smooth(f, t_s=t_s),
                           signals.matched_to_derivative(tau, t_s, state.thrust_hold_s)], axis=1)


@dataclass
class FlightData:
    """One flight ready for fitting: its state, the nominal residual and the usable samples."""

    flight: str
    state: FlightState
    r_f: np.ndarray  # (n, 3) nominal residual force, N
    r_tau: np.ndarray  # (n, 3) nominal residual torque, N m
    mask: np.ndarray  # (n,) the usable samples (usable_samples: away from gaps and the filters' edges)
    noise: np.ndarray = field(default_factory=lambda: np.zeros(6))  # (6,) sensor-noise RMS of r_f, r_tau
    _basis: dict = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        """Usable samples."""
        return int(self.mask.sum())

    @property
    def vbat_std_V(self) -> float:
        """Spread of the logged battery voltage in flight (a stuck log shows none)."""
        return float(np.std(self.state.vbat_V[self.mask])) if self.mask.any() else 0.0

    @property
    def vbat_median_V(self) -> float:
        return float(np.median(self.state.vbat_V)) if self.state.n else 0.0

    def basis(self, effect: Effect, vehicle: Vehicle) -> np.ndarray:
        """(n, 6, k) smoothed basis of a linear effect (cached per flight)."""
        if effect.name not in self._basis:
            cols = [smoothed_wrench(f, t, self.state) for f, t in effect.basis(self.state, vehicle)]
            self._basis[effect.name] = np.stack(cols, axis=2)
        return self._basis[effect.name]

    def basis_if_cached(self, effect: Effect) -> np.ndarray | None:
        """The effect's smoothed basis if :meth:`basis` computed it for this flight, else None
        (without caching one: a caller over many flights holds no bases it did not ask for)."""
        return self._basis.get(effect.name)

    def blocks(self) -> np.ndarray:
        """Block of each usable sample (:func:`block_index`)."""
        return block_index(self.state.t_s[self.mask])

    # --- a prediction on the rows (the Predicting protocol below): what becomes an extra column of
    # a flight's statistics where they cannot carry an effect (a model the profiles cannot, the search)

    def predict(self, effects: Sequence[Effect], params: Mapping[str, dict], vehicle: Vehicle) -> np.ndarray:
        """(n, 6) the effects' summed smoothed prediction at ``params`` (by effect name)."""
        out = np.zeros((self.state.n, 6))
        for e in effects:
            out += prediction(e, params[e.name], self, vehicle)
        return out

    def forget_bases(self) -> None:
        """Drop the cached bases (a flight's statistics hold what they gave)."""
        self._basis.clear()


def flight_data(flight: str, decoded, vehicle: Vehicle) -> FlightData:
    """Nominal residuals of a decoded ``fixedFrequency`` table.

    Both are :func:`quadcore.physics.residuals.residual_arrays`' (the model torque there passes
    through the gyro derivative's filter; see :func:`quadcore.physics.signals.matched_to_derivative`).
    """
    state = dynamics.flight_state(decoded, vehicle)
    r = residuals.residual_arrays(state, vehicle)
    mask = usable_samples(state.t_s)
    return FlightData(flight, state, r["f_res_b"], r["tau_res_b"], mask, sensor_noise_floor(state, vehicle, mask))


def usable_samples(t_s: np.ndarray) -> np.ndarray:
    """(n,) the samples every residual statistic counts (fits, scores, the sensor-noise floor):
    those whose filter window spans no gap (:func:`quadcore.physics.signals.near_gap`) and is
    not an edge fit (:func:`quadcore.physics.signals.near_edge`), where the filters pass more
    noise than the floor's interior gains count."""
    return ~(signals.near_gap(t_s) | signals.near_edge(t_s))


def _noise_gains(dt: float, hold_s: float = 0.0) -> tuple[float, float, float]:
    """RMS gain for white noise of the smoother, of the derivative (per second) and of the
    modelled torque's filter (:func:`quadcore.physics.signals.matched_to_derivative` with
    samples held ``hold_s``) at sample period ``dt``: the norms of their impulse responses."""
    n = 8 * signals.WINDOW + 1
    x = np.zeros(n)
    x[n // 2] = 1.0
    t = np.arange(n) * dt
    return (float(np.sqrt(np.sum(signals.smooth(x) ** 2))),
            float(np.sqrt(np.sum(signals.derivative(x, t) ** 2))),
            float(np.sqrt(np.sum(signals.matched_to_derivative(x, t, hold_s) ** 2))))


def _white_noise(x: np.ndarray, mask: np.ndarray, g_s: float) -> np.ndarray:
    """Per column, the white-noise standard deviation of a logged signal: what the smoother
    removes (``x - smooth(x)``; robust spread, so short manoeuvres do not count), scaled by
    ``1 / sqrt(1 - h0)`` for the share of white noise the smoother keeps (``h0`` = its centre
    coefficient = ``g_s²``, the squared norm of its impulse response)."""
    d = (x - signals.smooth(x))[mask]
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(max(1.0 - g_s**2, 1e-6))


def sensor_noise_floor(state: FlightState, vehicle: Vehicle, mask: np.ndarray | None = None) -> np.ndarray:
    """(6,) RMS that white measurement noise alone leaves in the residual force (N) and
    torque (N m), body frame, per axis, over the samples ``mask`` (default: :func:`usable_samples`,
    where the filters' interior gains hold): the floor below which no effect can be seen.

    **Measured side.** The white-noise level σ of each accelerometer and gyro axis is read off
    the flight itself (:func:`_white_noise`). It then passes the residual's filters:
    ``m smooth(sf_b)`` for force (``m σ_sf g_s``), ``J d/dt ω_b`` for torque
    (``g_d sqrt((J∘J) σ_ω²)``, ``g_d`` the derivative's gain per second).

    **Modelled side.** PWM commands are set, not measured: they carry no noise. With the
    ``motor_speed`` map the modelled wrench is a function of logged, noisy rotor speeds
    ``ω_i = ω̄_i + ε_i`` (white, σ_i per rotor, read off the flight the same way). To first
    order (``k_F ε²`` is ``ε / 2ω`` smaller) the rotor thrusts move by ``δf_i = 2 k_F ω_i ε_i``
    and the body wrench ``[T, τ_x, τ_y, τ_z] = A f`` (``A``: ``Vehicle.allocation``) by
    ``δw_c = Σ_i A_ci 2 k_F ω_i ε_i``, whose variance averaged over the usable samples is::

        σ_c² = Σ_i A_ci² (2 k_F)² ⟨ω_i²⟩ σ_i²

    The thrust ``T`` (body z force) passes ``smooth`` (gain ``g_s``) and the torques pass
    :func:`quadcore.physics.signals.matched_to_derivative` (gain ``g_m``, the held-for-no-time
    trapezoid for measured speeds). Measured and modelled noise are independent: the floor
    per channel is their root sum of squares. Anything above ~17 Hz that is not noise
    (vibration, fast motor-speed ripple) counts as noise here, which is what it is for a
    rigid-body model.
    """
    mask = usable_samples(state.t_s) if mask is None else mask
    if state.n < 4 * signals.WINDOW or mask.sum() < signals.WINDOW:
        return np.zeros(6)
    g_s, g_d, g_m = _noise_gains(float(np.median(np.diff(state.t_s))), state.thrust_hold_s)
    s_acc, s_gyro = _white_noise(state.sf_b_mps2, mask, g_s), _white_noise(state.omega_b_radps, mask, g_s)
    J = np.asarray(vehicle.inertia_kgm2)
    floor = np.concatenate([vehicle.mass_kg * s_acc * g_s, g_d * np.sqrt((J**2) @ (s_gyro**2))])
    if vehicle.thrust_map_kind == "motor_speed" and state.motor_radps is not None:
        gains = np.array([0.0, 0.0, g_s, g_m, g_m, g_m])
        floor = np.sqrt(floor**2 + gains**2 * _thrust_input_variance(state, vehicle, mask, g_s))
    return floor


def _thrust_input_variance(state: FlightState, vehicle: Vehicle, mask: np.ndarray, g_s: float) -> np.ndarray:
    """(6,) ``σ_c²`` of the body wrench [F_x, F_y, F_z, τ_x, τ_y, τ_z] before the residual's
    filters, from the white noise of the logged rotor speeds through the motor-speed map
    (see :func:`sensor_noise_floor`; no thrust on the body x and y axes)."""
    omega = np.asarray(state.motor_radps)
    s_omega = _white_noise(omega, mask, g_s)
    slope_sq = np.mean(vehicle.motor_speed.thrust_slope_N_per_radps(omega[mask]) ** 2, axis=0)
    var_w = (vehicle.allocation**2) @ (slope_sq * s_omega**2)  # [T, τ_x, τ_y, τ_z]
    return np.concatenate([[0.0, 0.0], var_w])


def prediction(effect: Effect, params: dict, fd: FlightData, vehicle: Vehicle) -> np.ndarray:
    """(n, 6) smoothed force and torque of an effect on a flight; zero within the effect's
    :meth:`~quadcore.effects.Effect.memory_s` of the flight's first sample (a lag's settling
    from the unknown state the log starts in), for the fits, tests and model predictions alike."""
    f, t = effect.wrench(fd.state, vehicle, params)
    out = smoothed_wrench(f, t, fd.state)
    memory = effect.memory_s()
    if memory > 0 and len(out):
        out[fd.state.t_s - fd.state.t_s[0] < memory] = 0.0
    return out


def unit_wrench(effect, param, fd: FlightData, vehicle) -> np.ndarray:
    """(n, 6) smoothed wrench per unit of ``param`` away from 'no effect' (a secant)."""
    step = SECANT * (param.upper - param.lower)
    params = {**effect.defaults(), **effect.sensitivity_reference}
    if param.name in effect.sensitivity_reference:
        params[param.name] = param.default
    base = prediction(effect, params, fd, vehicle)
    params[param.name] += step if param.default + step <= param.upper else -step
    return (prediction(effect, params, fd, vehicle) - base) / step


def targets_of(flights: Sequence[FlightData]) -> list[np.ndarray]:
    """(n, 6) nominal residual per flight."""
    return [np.concatenate([fd.r_f, fd.r_tau], axis=1) for fd in flights]


def block_index(t_s: np.ndarray) -> np.ndarray:
    """Block of each usable sample (times ``t_s`` of the usable samples), numbered over the
    blocks that hold samples (of :data:`BLOCK_S` seconds): a gap in the log makes no empty
    cluster (which would count as a block with a zero score in the test's degrees of freedom
    and spread)."""
    if not len(t_s):
        return np.zeros(0, dtype=int)
    return np.unique(((t_s - t_s[0]) // BLOCK_S).astype(int), return_inverse=True)[1].reshape(-1)


def one_blas_thread():
    """One BLAS thread for the per-flight products: the same numbers (each product is one
    thread's sum either way), and with the two cores shared by other work, OpenBLAS's second
    thread waiting for a core made a 6,000-sample Gram product ten times slower (0.38 s against
    0.03 s at load average 5), and the held-out sums of the detection limits (a product with
    a column per parameter) 6.6 s against 0.4 s at 1,000 flights."""
    return _blas_controller().limit(limits=1, user_api="blas")


@functools.lru_cache(maxsize=1)
def _blas_controller():
    """The process's thread pools, found once (finding them costs about 10 ms a time)."""
    return ThreadpoolController()
