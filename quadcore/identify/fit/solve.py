"""What every fit shares, whatever it is fitted from: the fit's result (:class:`Fit`), the channel
weights, the linear solve from normal equations (free, and within the parameters' physical bounds),
the parameters and standard errors it gives, the one-parameter search (:func:`scalar_minimum`), the
folds over flights and the grouped jackknife.

Targets are the residual force (N) and torque (N m) of each flight, body frame, on samples away
from logging gaps. Force and torque are weighted by the inverse of their mean square on the
training flights, so that both count alike::

    J(θ) = Σ_flights  |r_f - p_f(θ)|² / σ_f²  +  |r_τ - p_τ(θ)|² / σ_τ²

Linear effects are solved in closed form from the normal equations ``A θ = b``
(:func:`solved_linear`); standard errors come from the curvature of ``J`` at the optimum (``J`` is
quadratic in them), and for one nonlinear parameter from the profile of ``J`` itself (where it has
risen by one standard error's worth, :func:`scalar_minimum`: right when ``J`` is not quadratic),
inflated by the smoother's window length because neighbouring samples of a smoothed residual are
not independent (about one independent sample per window).

The fits themselves, from the flights' statistics: :mod:`quadcore.identify.fit` (linear,
profiled, search).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq, lsq_linear, minimize, minimize_scalar

from quadcore.effects import Effect
from quadcore.identify.flightdata import SAMPLES_PER_INDEPENDENT, Predicting
from quadcore.identify.model import EffectTerm, HeldBound
from quadcore.identify.settings import DEFAULT
from quadcore.identify.stats.profiles import search_grid
from quadcore.physics.vehicle import Vehicle

# a free fit beyond a physical bound by more than this many standard errors is unphysical (the settings' default)
BOUND_SIGMA = DEFAULT.bound_sigma


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

    def predict(self, effects: list[Effect], fd: Predicting, vehicle: Vehicle) -> np.ndarray:
        """The effects' summed prediction on a flight (:meth:`Flight.predict`: (n, 6) on its
        rows, a signal vector on its statistics)."""
        return fd.predict(effects, self.params, vehicle)


def weights_from_sums(ss: np.ndarray, n: int) -> np.ndarray:
    """1/σ² for force and torque channels from the (6,) sums of squares of ``n`` samples."""
    ms_f = float(np.sum(ss[:3]) / (3 * n)) if n else 0.0
    ms_t = float(np.sum(ss[3:]) / (3 * n)) if n else 0.0
    return np.array([1 / (ms_f or 1.0)] * 3 + [1 / (ms_t or 1.0)] * 3)


def weighted_values(w: np.ndarray, samples: int) -> int:
    """How many values a fit with channel weights ``w`` sums over ``samples`` samples: the
    channels it weighs (a channel of weight 0, left out of the fit, counts none)."""
    return int(np.count_nonzero(w)) * samples


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


def unpack(nonlin: list[Effect], x: np.ndarray) -> dict[str, dict[str, float]]:
    """The nonlinear effects' parameters (by effect) from their stacked values ``x``."""
    out, i = {}, 0
    for e in nonlin:
        out[e.name] = {p.name: float(x[i + j]) for j, p in enumerate(e.parameters)}
        i += len(e.parameters)
    return out


def scalar_minimum(J: Callable[[float], float], n: int, lower: float, upper: float,
                   samples_per_independent: int = SAMPLES_PER_INDEPENDENT) -> tuple[float, float]:
    """The minimum of ``J`` (a weighted sum of squares over ``n`` values) over ``[lower, upper]``
    and the variance of its position: ``J`` on the geometric grid
    (:func:`search_grid`), then Brent's method between the grid
    neighbours of the best point (``xatol`` 5e-4 of the span); the variance from the profile of
    ``J`` itself, not its curvature: the standard error is the larger distance from the optimum
    at which ``J`` has risen by ``s² W`` (``s² = J/(n - 1)``, ``W = samples_per_independent``: the
    smoother's window for a smoothed residual, 1 for a white one) --
    the likelihood-ratio interval, which for a quadratic ``J`` is the curvature's
    ``2 s² W / J''`` and stays right where ``J`` is not quadratic (a lag's kink at the first
    sample, a delay's ripple, a minimum on a bound). No rise within the bounds on either side:
    infinite."""
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
    if edge == best or J(edge) < level:
        return None
    return float(brentq(lambda v: J(v) - level, best, edge, xtol=1e-5 * span))


def jackknife_std(fold_params: list[dict[str, float]]) -> dict[str, float]:
    """Grouped-jackknife standard error of each parameter from fits that each leave out one
    group of flights: ``sqrt((K-1)/K Σ_k (θ_k - θ̄)²)``; empty with fewer than two groups."""
    if len(fold_params) < 2:
        return {}
    k = len(fold_params)
    out = {}
    for name in fold_params[0]:
        vals = np.array([p[name] for p in fold_params])
        out[name] = float(np.sqrt((k - 1) / k * np.sum((vals - vals.mean()) ** 2)))
    return out


def folds(flight_ids: list[str], k: int = 5) -> list[list[str]]:
    """Deterministic folds over flights (round robin over the sorted ids)."""
    ids = sorted(flight_ids)
    k = max(1, min(k, len(ids)))
    return [ids[i::k] for i in range(k)]


def model_terms(effects: list[Effect], fit: Fit, fixed: Mapping[str, dict[str, float]]) -> list[EffectTerm]:
    """The model's terms from its effects' fit (within their bounds): values, standard errors,
    whether fixed, and the parameters held at a bound (:func:`held_bounds`)."""
    return [EffectTerm(e.name, fit.params[e.name], fit.std[e.name], e.name in fixed, held=held_bounds(fit, e))
            for e in effects]
