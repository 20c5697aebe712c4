"""Fitting effect parameters to residuals, and scoring them on flights they never saw.

Targets are the residual force (N) and torque (N m) of each flight, body frame, on
samples away from logging gaps. Force and torque are weighted by the inverse of their
mean square on the training flights, so that both count alike::

    J(θ) = Σ_flights  |r_f - p_f(θ)|² / σ_f²  +  |r_τ - p_τ(θ)|² / σ_τ²

Linear effects (all built-ins but ``motor_lag``) are solved in closed form from normal
equations accumulated flight by flight; nonlinear parameters are found by bounded
least squares (``scipy.optimize.least_squares``) with the linear ones solved inside
(variable projection). Several effects are fitted jointly.

Standard errors come from the curvature of ``J`` at the optimum (linear parameters: ``J`` is
quadratic in them), and for one nonlinear parameter from the profile of ``J`` itself (where it
has risen by one standard error's worth, :func:`scalar_minimum`: right when ``J`` is not
quadratic), inflated by the smoother's window length because neighbouring samples of a smoothed
residual are not independent (about one independent sample per window). An effect with memory
(a lag, a delay) predicts nothing within its ``memory_s`` of a flight's start
(:func:`prediction`): a log that starts in a manoeuvre starts from a state the filter cannot know.

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

import hashlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from quadcore.effects import Effect
from quadcore.identify.settings import DEFAULT
from quadcore.physics import dynamics, residuals, signals
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle

if TYPE_CHECKING:
    from quadcore.identify.model import EffectTerm, HeldBound
    from quadcore.identify.sufficient import Flights, FlightStats

SAMPLES_PER_INDEPENDENT = signals.WINDOW
# a free fit beyond a physical bound by more than this many standard errors is unphysical (the settings' default)
BOUND_SIGMA = DEFAULT.bound_sigma


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
    _predictions: dict = field(default_factory=dict, repr=False)
    _sums: dict = field(default_factory=dict, repr=False)
    _designs: dict = field(default_factory=dict, repr=False)

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

    def design(self, lin: list[Effect], vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray]:
        """Masked stacked basis (m, 6, k) of linear effects and its Gram matrix per channel
        (6, k, k), cached: the weights change between fits, the basis does not."""
        key = tuple(e.name for e in lin)
        if key not in self._designs:
            X = np.concatenate([self.basis(e, vehicle) for e in lin], axis=2)[self.mask]
            self._designs[key] = (X, np.einsum("nci,ncj->cij", X, X))
        return self._designs[key]

    def cached_prediction(self, effect: Effect, params: dict, vehicle: Vehicle) -> np.ndarray:
        """(n, 6) smoothed prediction of a nonlinear effect, cached for repeated parameter values
        (the grid search evaluates the same values in every fold)."""
        key = (effect.name, tuple(sorted(params.items())))
        if key not in self._predictions:
            if len(self._predictions) > 64:
                self._predictions.clear()
            self._predictions[key] = prediction(effect, params, self, vehicle)
        return self._predictions[key]


    def forget_bases(self) -> None:
        """Drop the cached bases and designs (a flight's statistics hold what they gave)."""
        self._basis.clear()
        self._designs.clear()

    def cached_sums(self, nonlin: list[Effect], params: dict, y: np.ndarray, target_key: str,
                    vehicle: Vehicle) -> np.ndarray:
        """(6,) ``Σ (y - Σ_e p_e)²`` per channel over the usable samples, for nonlinear effects at
        ``params`` and the target ``y`` (``target_key``: its digest), cached: a search keeps six
        numbers per value and flight instead of a prediction, and a value met again (the grid's,
        in every fold on the same target) costs nothing."""
        key = (target_key, tuple((e.name, tuple(sorted(params[e.name].items()))) for e in nonlin))
        if key not in self._sums:
            p = np.zeros_like(y)
            for e in nonlin:
                p += prediction(e, params[e.name], self, vehicle)
            self._sums[key] = ((y - p)[self.mask] ** 2).sum(axis=0)
        return self._sums[key]


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


@dataclass
class Fit:
    """Fitted parameters per effect (SI), standard errors, and the weights used. A fit kept
    within the parameters' physical bounds (``fit_effects(..., bounded=True)``) whose free fit
    left them has ``active``: per effect, the parameters held at a bound and that bound, and
    ``free``: the fit without bounds (what the data ask for)."""

    params: dict[str, dict[str, float]]
    std: dict[str, dict[str, float]]
    weights: np.ndarray  # (6,) per channel: 1/σ_f² ×3, 1/σ_τ² ×3
    active: dict[str, dict[str, float]] = field(default_factory=dict)
    free: Fit | None = None

    def predict(self, effects: list[Effect], fd, vehicle: Vehicle) -> np.ndarray:
        """(n, 6) the effects' summed prediction on a :class:`FlightData`; on a flight's
        :class:`quadcore.identify.sufficient.FlightStats`, the same as a signal vector."""
        if not isinstance(fd, FlightData):
            from quadcore.identify import sufficient

            return sufficient.prediction(effects, self.params, fd, vehicle)
        out = np.zeros((fd.state.n, 6))
        for e in effects:
            out += prediction(e, self.params[e.name], fd, vehicle)
        return out


def channel_weights(targets: list[np.ndarray]) -> np.ndarray:
    """1/σ² for force and torque channels from (n, 6) targets (one array per flight)."""
    ss = sum(np.einsum("nc,nc->c", y, y) for y in targets)
    return weights_from_sums(ss, sum(len(y) for y in targets))


def weights_from_sums(ss: np.ndarray, n: int) -> np.ndarray:
    """1/σ² for force and torque channels from the (6,) sums of squares of ``n`` samples."""
    ms_f = float(np.sum(ss[:3]) / (3 * n)) if n else 0.0
    ms_t = float(np.sum(ss[3:]) / (3 * n)) if n else 0.0
    return np.array([1 / (ms_f or 1.0)] * 3 + [1 / (ms_t or 1.0)] * 3)


def _row_normal_equations(lin: list[Effect], flights: Sequence[FlightData], ys: list[np.ndarray], w: np.ndarray,
                          vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(A, b, yy, n_rows)`` of the weighted least squares for the stacked linear coordinates."""
    k = sum(len(e.parameters) for e in lin)
    A, b, yy, n = np.zeros((k, k)), np.zeros(k), 0.0, 0
    for fd, y in zip(flights, ys):
        ym = y[fd.mask]
        yy += float((ym**2).sum(axis=0) @ w)
        n += ym.size
        if lin:
            X, gram = fd.design(lin, vehicle)
            A += np.tensordot(w, gram, axes=1)
            b += np.einsum("nck,nc->k", X, ym * w)
    return A, b, yy, n


def _linear_solve(lin: list[Effect], flights: Sequence[FlightData], ys: list[np.ndarray], w: np.ndarray,
                  vehicle: Vehicle):
    """Weighted least squares for the stacked linear coordinates: (θ, A, rss, n_rows)."""
    A, b, yy, n = _row_normal_equations(lin, flights, ys, w, vehicle)
    theta = np.linalg.lstsq(A, b, rcond=None)[0] if len(b) else np.zeros(0)
    rss = yy - 2 * theta @ b + theta @ A @ theta
    return theta, A, max(rss, 0.0), n


def _linear_prediction(lin: list[Effect], theta: np.ndarray, fd: FlightData, vehicle: Vehicle) -> np.ndarray:
    if not lin:
        return np.zeros((fd.state.n, 6))
    X = np.concatenate([fd.basis(e, vehicle) for e in lin], axis=2)
    return X @ theta


def _params_with_std(effect: Effect, coeffs: np.ndarray, cov: np.ndarray, vehicle: Vehicle):
    """SI parameters from linear coordinates, standard errors by the delta method."""
    params = effect.from_linear(coeffs, vehicle)
    names = [p.name for p in effect.parameters]
    base = np.array([params[n] for n in names])
    jac = np.zeros((len(names), len(coeffs)))
    for j in range(len(coeffs)):
        h = 1e-6 * max(1.0, abs(coeffs[j]))
        c2 = coeffs.copy()
        c2[j] += h
        p2 = effect.from_linear(c2, vehicle)
        jac[:, j] = (np.array([p2[n] for n in names]) - base) / h
    var = np.diag(jac @ cov @ jac.T)
    return params, {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(names, var)}


def fit_effects(
    effects: list[Effect],
    flights: Flights,
    targets: Sequence[np.ndarray],
    vehicle: Vehicle,
    fixed: dict[str, dict[str, float]] | None = None,
    bounded: bool = False,
) -> Fit:
    """Jointly fit ``effects`` to ``targets`` ((n, 6) residual per flight) on ``flights``.

    Effects named in ``fixed`` keep the given parameters and are subtracted first. On
    :class:`quadcore.identify.sufficient.FlightStats` with signal-vector targets (linear effects only),
    the same fit from the flights' statistics (:func:`quadcore.identify.sufficient.fit_effects`).
    ``bounded``: the linear effects' parameters are kept within their physical bounds
    (:func:`bounded_linear_parameters`; nonlinear ones are searched within them anyway).
    """
    from quadcore.identify import sufficient

    if sufficient.are_stats(flights):
        return sufficient.fit_effects(effects, flights, targets, vehicle, fixed, bounded)
    fixed = fixed or {}
    w = channel_weights([y[fd.mask] for fd, y in zip(flights, targets)])
    ys = [y.copy() for y in targets]
    params, std = fixed_values(effects, fixed)
    for e in effects:
        if e.name in fixed:
            ys = [y - prediction(e, params[e.name], fd, vehicle) for fd, y in zip(flights, ys)]
    free = [e for e in effects if e.name not in fixed]
    lin = [e for e in free if e.linear]
    nonlin = [e for e in free if not e.linear]
    if nonlin:
        n_nonlin = sum(len(e.parameters) for e in nonlin)
        search = _scalar_search if n_nonlin == 1 else _vector_search
        x, cov = search(nonlin, lin, flights, ys, w, vehicle)
        nl = _unpack(nonlin, x)
        i = 0
        for e in nonlin:
            params[e.name] = nl[e.name]
            std[e.name] = {p.name: float(np.sqrt(max(cov[i + j, i + j], 0.0))) for j, p in enumerate(e.parameters)}
            i += len(e.parameters)
        if lin:  # the linear effects are solved on what the nonlinear ones leave
            ys = _after(nonlin, nl, flights, ys, vehicle)

    if not lin:
        return Fit(params, std, w)
    A, b, yy, n = _row_normal_equations(lin, flights, ys, w, vehicle)
    return solved_linear(lin, A, b, yy, n, vehicle, params, std, w, bounded)


def solved_linear(lin: list[Effect], A: np.ndarray, b: np.ndarray, yy: float, n: int, vehicle: Vehicle,
                  params: dict, std: dict, w: np.ndarray, bounded: bool = False) -> Fit:
    """The fit of the linear effects ``lin`` from their normal equations ``A θ = b`` (``yy`` the
    target's weighted sum of squares over ``n`` values), beside ``params``/``std`` of the others:
    least squares, and with ``bounded`` and parameters outside their bounds, the least squares
    within them (:func:`bounded_linear_parameters`, the free fit kept as ``free``)."""
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    rss = max(float(yy - 2 * theta @ b + theta @ A @ theta), 0.0)
    free_params, free_std = dict(params), dict(std)
    linear_parameters(lin, theta, A, rss, n, vehicle, free_params, free_std)
    free = Fit(free_params, free_std, w)
    if not bounded or not any(outside_bounds(e, free_params[e.name]) for e in lin):
        return free
    params, std = dict(params), dict(std)
    start = np.array([free_params[e.name][p.name] for e in lin for p in e.parameters])
    active = bounded_linear_parameters(lin, A, b, yy, n, vehicle, start, params, std)
    for e in lin:  # a parameter held at a bound: how well the data pin it is its free fit's error
        std[e.name] = {k: free_std[e.name][k] if k in active.get(e.name, {}) else v for k, v in std[e.name].items()}
    return Fit(params, std, w, active, free)


def held_bounds(fit: Fit, effect: Effect) -> dict[str, HeldBound]:
    """The parameters of ``effect`` a bounded ``fit`` holds at a physical bound, each with its free
    value and how many standard errors that lies beyond the bound. Beyond by more than
    ``BOUND_SIGMA``: the effect's form does not fit the data (the free fit absorbs something the
    effect cannot be), which is said rather than hidden behind the bound."""
    from quadcore.identify.model import HeldBound

    free = fit.free or fit
    out = {}
    for k, bound in fit.active.get(effect.name, {}).items():
        v, s = float(free.params[effect.name][k]), float(free.std[effect.name].get(k, 0.0))
        z = abs(v - bound) / s if s > 0 else float(np.inf)
        where = f"{k} held at its bound {bound:g} (free fit {v:.3g} ± {s:.2g}, {z:.1f} σ beyond it)"
        note = (f"{where}: {effect.name}'s form does not fit the data; the fit absorbs something else "
                "(a missing effect, or this one's form is wrong)" if z > BOUND_SIGMA
                else f"{where}: within noise of it")
        out[k] = HeldBound(float(bound), v, s, float(z), note)
    return out


def outside_bounds(effect: Effect, params: dict[str, float]) -> list[str]:
    """The parameters of ``effect`` outside their physical bounds."""
    return [p.name for p in effect.parameters if not p.lower <= params[p.name] <= p.upper]


def _coordinates_at(lin: list[Effect], x: np.ndarray, vehicle: Vehicle) -> np.ndarray:
    """The stacked linear coordinates of the effects at parameter values ``x`` (stacked)."""
    out, i = [], 0
    for e in lin:
        k = len(e.parameters)
        out += e.to_linear({p.name: float(v) for p, v in zip(e.parameters, x[i: i + k])}, vehicle)
        i += k
    return np.asarray(out, dtype=float)


def bounded_linear_parameters(lin: list[Effect], A: np.ndarray, b: np.ndarray, yy: float, n: int, vehicle: Vehicle,
                              start: np.ndarray, params: dict, std: dict) -> dict[str, dict[str, float]]:
    """The least squares ``J = yy - 2 θ·b + θᵀAθ`` with every parameter within its bounds (into
    ``params``, ``std``), and the parameters it holds at a bound (returned, per effect).

    Effects linear in their parameters (``p = default + θ``, the base class's mapping): the
    bounds are a box on ``θ``, solved exactly (bounded-variable least squares on ``A = MᵀM``,
    ``b = Mᵀy``). Effects with another mapping (``added_mass``, ``inertia_scale``, ``wind``): the
    parameters themselves, bounded quasi-Newton (L-BFGS-B) from ``start`` (the free fit's
    parameters, stacked) clipped to the bounds. Standard errors of the others as
    :func:`linear_parameters`, with the held ones fixed: ``cov = A_ff⁻¹ rss / (n - k_f) ×
    SAMPLES_PER_INDEPENDENT``."""
    from scipy.optimize import lsq_linear, minimize

    ps = [p for e in lin for p in e.parameters]
    lo, hi = np.array([p.lower for p in ps]), np.array([p.upper for p in ps])
    if all(type(e).from_linear is Effect.from_linear for e in lin):
        # in coordinates scaled to unit diagonal (u = d θ): parameters of very different sizes (a
        # discovered term's 1e-7 beside a drag's 0.04) would otherwise leave the small eigenvalues
        # of A, dropped below 1e-12 of the largest, carrying whole parameters
        default = np.array([p.default for p in ps])
        d = np.sqrt(np.diag(A))
        d = np.where(d > 0, d, 1.0)
        lam, V = np.linalg.eigh(A / np.outer(d, d))
        keep = lam > lam.max(initial=0.0) * 1e-12
        M = np.sqrt(lam[keep])[:, None] * V[:, keep].T
        y = (V[:, keep].T @ (b / d)) / np.sqrt(lam[keep])
        x = default + lsq_linear(M, y, bounds=((lo - default) * d, (hi - default) * d), method="bvls").x / d
    else:
        span = hi - lo

        def J(z: np.ndarray) -> float:
            c = _coordinates_at(lin, lo + z * span, vehicle)
            return float(yy - 2 * c @ b + c @ A @ c)

        z = minimize(J, np.clip((start - lo) / span, 0.0, 1.0), method="L-BFGS-B", bounds=[(0.0, 1.0)] * len(ps),
                     options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 500}).x
        x = lo + z * span
    x = np.clip(x, lo, hi)
    held = (x <= lo) | (x >= hi)
    c = _coordinates_at(lin, x, vehicle)
    rss = max(float(yy - 2 * c @ b + c @ A @ c), 0.0)
    cov = np.zeros((len(c), len(c)))
    f = ~held  # coordinates of a held parameter are fixed (each effect maps its parameters one to one)
    if f.any():
        try:
            cov[np.ix_(f, f)] = (np.linalg.inv(A[np.ix_(f, f)]) * rss / max(n - int(f.sum()), 1)
                                 * SAMPLES_PER_INDEPENDENT)
        except np.linalg.LinAlgError:
            cov[np.ix_(f, f)] = np.inf
    active: dict[str, dict[str, float]] = {}
    for i, e in _offsets(lin):
        k = len(e.parameters)
        params[e.name], std[e.name] = _params_with_std(e, c[i: i + k], cov[i: i + k, i: i + k], vehicle)
        params[e.name] = {p.name: float(v) for p, v in zip(e.parameters, x[i: i + k])}
        if held[i: i + k].any():
            active[e.name] = {p.name: float(v) for p, v, h in zip(e.parameters, x[i: i + k], held[i: i + k]) if h}
    return active


def _offsets(lin: list[Effect]) -> list[tuple[int, Effect]]:
    """(first stacked index, effect) of each linear effect."""
    out, i = [], 0
    for e in lin:
        out.append((i, e))
        i += len(e.parameters)
    return out


def fixed_values(effects: list[Effect], fixed: dict[str, dict[str, float]]) -> tuple[dict, dict]:
    """(parameters, standard errors) of the effects named in ``fixed``: their given values over
    the defaults, with no uncertainty."""
    named = [e for e in effects if e.name in fixed]
    return ({e.name: {**e.defaults(), **fixed[e.name]} for e in named},
            {e.name: {p.name: 0.0 for p in e.parameters} for e in named})


def linear_parameters(lin: list[Effect], theta: np.ndarray, A: np.ndarray, rss: float, n: int, vehicle: Vehicle,
                      params: dict, std: dict) -> None:
    """Each linear effect's parameters and standard errors (into ``params``, ``std``) from the
    stacked solution ``θ`` of the normal equations ``A θ = b`` with residual sum of squares
    ``rss`` over ``n`` values: ``cov = A⁻¹ rss / (n - k) × SAMPLES_PER_INDEPENDENT``."""
    s2 = rss / max(n - len(theta), 1)
    try:
        cov_all = np.linalg.inv(A) * s2 * SAMPLES_PER_INDEPENDENT
    except np.linalg.LinAlgError:
        cov_all = np.full((len(theta), len(theta)), np.inf)
    i = 0
    for e in lin:
        k = len(e.parameters)
        params[e.name], std[e.name] = _params_with_std(e, theta[i: i + k], cov_all[i: i + k, i: i + k], vehicle)
        i += k


def _unpack(nonlin: list[Effect], x: np.ndarray) -> dict[str, dict[str, float]]:
    out, i = {}, 0
    for e in nonlin:
        out[e.name] = {p.name: float(x[i + j]) for j, p in enumerate(e.parameters)}
        i += len(e.parameters)
    return out


def _after(nonlin, nl, flights, ys, vehicle) -> list[np.ndarray]:
    """Targets minus the nonlinear effects' predictions (cached per flight and value)."""
    out = []
    for fd, y in zip(flights, ys):
        p = np.zeros_like(y)
        for e in nonlin:
            p += fd.cached_prediction(e, nl[e.name], vehicle)
        out.append(y - p)
    return out


def _objective(nonlin, lin, flights, ys, w, vehicle, x, keys=None) -> tuple[float, int]:
    """Weighted residual sum of squares with the linear effects solved for (variable projection).
    Without linear effects, from each flight's cached sums of squares (:meth:`FlightData.cached_sums`,
    ``keys`` the targets' digests): the same sums, added in the same order."""
    if not lin and keys is not None:
        nl, yy, n = _unpack(nonlin, x), 0.0, 0
        for fd, y, key in zip(flights, ys, keys):
            yy += float(fd.cached_sums(nonlin, nl, y, key, vehicle) @ w)
            n += int(fd.mask.sum()) * y.shape[1]
        return max(yy, 0.0), n
    ys2 = _after(nonlin, _unpack(nonlin, x), flights, ys, vehicle)
    _, _, rss, n = _linear_solve(lin, flights, ys2, w, vehicle)
    return rss, n


def _scalar_search(nonlin, lin, flights, ys, w, vehicle):
    """One nonlinear parameter, from rows: :func:`scalar_minimum` of the objective on every
    flight's rows (a flight's statistics with a profile of the effect give the same search
    without them: :func:`quadcore.identify.profiles.fit_effects`)."""
    (p,) = [q for e in nonlin for q in e.parameters]
    memo: dict[float, tuple[float, int]] = {}
    keys = None if lin else [hashlib.blake2b(np.ascontiguousarray(y).tobytes(), digest_size=16).hexdigest()
                             for y in ys]

    def J(v: float) -> float:
        v = float(min(max(v, p.lower), p.upper))
        if v not in memo:
            memo[v] = _objective(nonlin, lin, flights, ys, w, vehicle, np.array([v]), keys)
        return memo[v][0]

    J(p.lower)  # the grid's first point; n is the same at every value
    n = memo[float(p.lower)][1]
    best, var = scalar_minimum(J, n, p.lower, p.upper)
    return np.array([best]), np.array([[var]])


def scalar_minimum(J: Callable[[float], float], n: int, lower: float, upper: float,
                   samples_per_independent: int = SAMPLES_PER_INDEPENDENT) -> tuple[float, float]:
    """The minimum of ``J`` (a weighted sum of squares over ``n`` values) over ``[lower, upper]``
    and the variance of its position: ``J`` on the geometric grid
    (:func:`quadcore.identify.profiles.search_grid`), then Brent's method between the grid
    neighbours of the best point (``xatol`` 5e-4 of the span); the variance from the profile of
    ``J`` itself, not its curvature: the standard error is the larger distance from the optimum
    at which ``J`` has risen by ``s² W`` (``s² = J/(n - 1)``, ``W = samples_per_independent``: the
    smoother's window for a smoothed residual, 1 for a white one) --
    the likelihood-ratio interval, which for a quadratic ``J`` is the curvature's
    ``2 s² W / J''`` and stays right where ``J`` is not quadratic (a lag's kink at the first
    sample, a delay's ripple, a minimum on a bound). No rise within the bounds on either side:
    infinite."""
    from quadcore.identify.profiles import search_grid

    span = upper - lower
    grid = search_grid(lower, upper)
    costs = [J(g) for g in grid]
    i = int(np.argmin(costs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best = float(grid[i])
    if hi > lo:
        res = minimize_scalar(J, bounds=(lo, hi), method="bounded", options={"xatol": 5e-4 * span})
        if res.fun <= costs[i]:
            best = float(res.x)
    j0 = J(best)
    level = j0 + j0 / max(n - 1, 1) * samples_per_independent
    sides = [_rise(J, best, edge, level, span) for edge in (lower, upper)]
    widths = [abs(v - best) for v in sides if v is not None]
    return best, float(max(widths) ** 2) if widths else float(np.inf)


def _rise(J: Callable[[float], float], best: float, edge: float, level: float, span: float) -> float | None:
    """Where ``J`` reaches ``level`` between ``best`` and ``edge`` (a root of ``J - level``, to
    1e-5 of the span), or None when it does not there."""
    from scipy.optimize import brentq

    if edge == best or J(edge) < level:
        return None
    return float(brentq(lambda v: J(v) - level, best, edge, xtol=1e-5 * span))


def _vector_search(nonlin, lin, flights, ys, w, vehicle):
    """Several nonlinear parameters: bounded least squares (trust region reflective)."""
    sw = np.sqrt(w)

    def resid(x):
        ys2 = _after(nonlin, _unpack(nonlin, x), flights, ys, vehicle)
        theta = _linear_solve(lin, flights, ys2, w, vehicle)[0]
        return np.concatenate([((y - _linear_prediction(lin, theta, fd, vehicle))[fd.mask] * sw).reshape(-1)
                               for fd, y in zip(flights, ys2)])

    lo = np.array([p.lower for e in nonlin for p in e.parameters])
    hi = np.array([p.upper for e in nonlin for p in e.parameters])
    sol = least_squares(resid, lo + 0.1 * (hi - lo), bounds=(lo, hi), x_scale=hi - lo, diff_step=1e-3)
    s2 = 2 * sol.cost / max(sol.fun.size - len(lo), 1)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2 * SAMPLES_PER_INDEPENDENT
    except np.linalg.LinAlgError:
        cov = np.full((len(lo), len(lo)), np.inf)
    return sol.x, cov


def targets_of(flights: Sequence[FlightData]) -> list[np.ndarray]:
    """(n, 6) nominal residual per flight."""
    return [np.concatenate([fd.r_f, fd.r_tau], axis=1) for fd in flights]


def folds(flight_ids: list[str], k: int = 5) -> list[list[str]]:
    """Deterministic folds over flights (round robin over the sorted ids)."""
    ids = sorted(flight_ids)
    k = max(1, min(k, len(ids)))
    return [ids[i::k] for i in range(k)]


def model_terms(effects: list[Effect], fit: Fit, fixed: Mapping[str, dict[str, float]]) -> list[EffectTerm]:
    """The model's terms from its effects' fit (within their bounds): values, standard errors,
    whether fixed, and the parameters held at a bound (:func:`held_bounds`)."""
    from quadcore.identify.model import EffectTerm

    return [EffectTerm(e.name, fit.params[e.name], fit.std[e.name], e.name in fixed, held=held_bounds(fit, e))
            for e in effects]


def _from_statistics(spec, effects: list[Effect]) -> bool:
    """Whether :func:`fit_model` fits ``effects`` from the flights' statistics."""
    from quadcore.identify import profiles

    nonlinear = [e for e in effects if not e.linear]
    return not nonlinear or (len(nonlinear) == 1 and profiles.profiled(nonlinear[0]) and not spec.per_session
                             and nonlinear[0].name not in spec.fixed)


def fit_model(spec, decoded: Mapping, train: list[str], sessions: dict[str, list[str]] | None = None, log=None,
              stats=None):
    """Fit the effects a :class:`quadcore.identify.model.ModelSpec` names on the ``train`` flights (its
    ``per_session`` effects per session: :func:`quadcore.identify.sessions.fit_per_session`), within
    their parameters' physical bounds; a parameter held at a bound says so in its term
    (:func:`held_bounds`: its free value, and whether that is within noise of the bound).

    A model of linear effects, and one effect with a single nonlinear parameter (not fixed) beside
    them, is fitted from the flights' sufficient statistics (:mod:`quadcore.identify.sufficient`, the
    nonlinear one from its profiles: :func:`quadcore.identify.profiles.fit_effects`): ``stats(flight)``
    gives a flight's stored ones (None: computed from its decoded table); any other model (per-session
    effects beside a nonlinear one included) reads every training flight's rows."""
    from quadcore.effects import get
    from quadcore.identify import sufficient
    from quadcore.identify.model import PhysicsModel

    effect_list = [get(n) for n in spec.effects]
    maps = ((spec.sessions_of(sorted(decoded)), spec.session_maps, spec.session_patterns) if spec.session_maps
            else ({}, {}, {}))
    if not effect_list:
        return PhysicsModel(spec.vehicle, [], *maps)
    by_id: Mapping[str, FlightData] | Mapping[str, FlightStats]
    flights: Flights
    if _from_statistics(spec, effect_list):
        by_id = sufficient.for_flights(spec, decoded, train, sufficient.layout_of(effect_list), stats)
        flights = [by_id[f] for f in train]
        targets = {f: s.layout.target() for f, s in by_id.items()}
    else:
        by_id = {f: flight_data(f, decoded[f], spec.vehicle_for(f)) for f in train}
        flights = [by_id[f] for f in train]
        targets = dict(zip(train, targets_of(flights)))
    if spec.per_session:
        from quadcore.identify import sessions as sessionlib

        return sessionlib.fit_per_session(spec, by_id, targets, train, sessions, log or (lambda msg: None))
    fit = fit_effects(effect_list, flights, [targets[f] for f in train], spec.vehicle, spec.fixed, bounded=True)
    terms = model_terms(effect_list, fit, spec.fixed)
    return PhysicsModel(spec.vehicle, terms, *maps)
