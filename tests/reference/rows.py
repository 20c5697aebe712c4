"""The reference the fits from statistics (:mod:`quadcore.identify.fit`) are tested against: the
same fits written on the flights' rows, sample by sample, as readable as the mathematics. Nothing
in quadcore uses them; the equality tests (tests/test_sufficient.py, tests/test_search.py, ...)
compare against them, each with the tolerance it states.

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
(:func:`quadcore.identify.flightdata.prediction`): a log that starts in a manoeuvre starts from a
state the filter cannot know.

The flights' rows, the smoothed prediction of an effect and why the model torque goes through
the gyro derivative's own filter: :mod:`quadcore.identify.flightdata`. The same fits from the
flights' statistics: :mod:`quadcore.identify.fit`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares

from quadcore.effects import Effect
from quadcore.identify.fit.solve import (
    Fit,
    fixed_values,
    scalar_minimum,
    solved_linear,
    unpack,
    weights_from_sums,
)
from quadcore.identify.flightdata import SAMPLES_PER_INDEPENDENT, FlightData, prediction
from quadcore.physics.vehicle import Vehicle
from reference.flight import RowFlight, as_rows


def channel_weights(targets: list[np.ndarray]) -> np.ndarray:
    """1/σ² for force and torque channels from (n, 6) targets (one array per flight)."""
    ss = sum(np.einsum("nc,nc->c", y, y) for y in targets)
    return weights_from_sums(ss, sum(len(y) for y in targets))


def weights_of(flights: Sequence[FlightData], targets: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`channel_weights` of (n, 6) targets on the flights' usable samples."""
    return channel_weights([y[fd.mask] for fd, y in zip(flights, targets)])


def _row_normal_equations(lin: list[Effect], flights: Sequence[RowFlight], ys: list[np.ndarray], w: np.ndarray,
                          vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(A, b, yy, n_rows)`` of the weighted least squares for the stacked linear coordinates."""
    k = sum(len(e.parameters) for e in lin)
    A, b, yy, n = np.zeros((k, k)), np.zeros(k), 0.0, 0
    for fd, y in zip(flights, ys):
        ym = y[fd.mask]
        yy += float((ym**2).sum(axis=0) @ w)
        n += len(ym) * int(np.count_nonzero(w))  # the values of the channels fitted
        if lin:
            X, gram = fd.design(lin, vehicle)
            A += np.tensordot(w, gram, axes=1)
            b += np.einsum("nck,nc->k", X, ym * w)
    return A, b, yy, n


def _linear_solve(lin: list[Effect], flights: Sequence[RowFlight], ys: list[np.ndarray], w: np.ndarray,
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


def fit_effects(
    effects: list[Effect],
    flights: Sequence[FlightData],
    targets: Sequence[np.ndarray],
    vehicle: Vehicle,
    fixed: dict[str, dict[str, float]] | None = None,
    bounded: bool = False,
    channels: np.ndarray | None = None,
) -> Fit:
    """Jointly fit ``effects`` to ``targets`` ((n, 6) residual per flight) on the flights' rows.

    Effects named in ``fixed`` keep the given parameters and are subtracted first.
    ``bounded``: the linear effects' parameters are kept within their physical bounds
    (:func:`bounded_linear_parameters`; nonlinear ones are searched within them anyway). The
    same fit from the flights' statistics: :func:`quadcore.identify.fit.fit_effects`
    (chosen by who holds the flights, by the effects' kinds). ``channels``: (6,) 1 on the
    channels fitted, 0 on those left out (None: all).
    """
    fixed = fixed or {}
    rfs = [as_rows(fd) for fd in flights]  # the rows with the designs and caches a row fit keeps
    w = weights_of(rfs, targets) * (1.0 if channels is None else channels)
    ys = [y.copy() for y in targets]
    params, std = fixed_values(effects, fixed)
    for e in effects:
        if e.name in fixed:
            ys = [y - prediction(e, params[e.name], fd, vehicle) for fd, y in zip(rfs, ys)]
    free = [e for e in effects if e.name not in fixed]
    lin = [e for e in free if e.linear]
    nonlin = [e for e in free if not e.linear]
    if nonlin:
        n_nonlin = sum(len(e.parameters) for e in nonlin)
        search = _scalar_search if n_nonlin == 1 else _vector_search
        x, cov = search(nonlin, lin, rfs, ys, w, vehicle)
        nl = unpack(nonlin, x)
        i = 0
        for e in nonlin:
            params[e.name] = nl[e.name]
            std[e.name] = {p.name: float(np.sqrt(max(cov[i + j, i + j], 0.0))) for j, p in enumerate(e.parameters)}
            i += len(e.parameters)
        if lin:  # the linear effects are solved on what the nonlinear ones leave
            ys = _after(nonlin, nl, rfs, ys, vehicle)

    if not lin:
        return Fit(params, std, w)
    A, b, yy, n = _row_normal_equations(lin, rfs, ys, w, vehicle)
    return solved_linear(lin, A, b, yy, n, vehicle, params, std, w, bounded)


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
        nl, yy, n = unpack(nonlin, x), 0.0, 0
        for fd, y, key in zip(flights, ys, keys):
            yy += float(fd.cached_sums(nonlin, nl, y, key, vehicle) @ w)
            n += int(fd.mask.sum()) * int(np.count_nonzero(w))
        return max(yy, 0.0), n
    ys2 = _after(nonlin, unpack(nonlin, x), flights, ys, vehicle)
    _, _, rss, n = _linear_solve(lin, flights, ys2, w, vehicle)
    return rss, n


def _scalar_search(nonlin, lin, flights, ys, w, vehicle):
    """One nonlinear parameter, from rows: :func:`scalar_minimum` of the objective on every
    flight's rows (a flight's statistics with a profile of the effect give the same search
    without them: :func:`quadcore.identify.fit.profiled.profiled_fit`)."""
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


def _vector_search(nonlin, lin, flights, ys, w, vehicle):
    """Several nonlinear parameters: bounded least squares (trust region reflective)."""
    sw = np.sqrt(w)

    def resid(x):
        ys2 = _after(nonlin, unpack(nonlin, x), flights, ys, vehicle)
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
