"""Nonlinear effects the profiles cannot carry, fitted from the flights' statistics: several
nonlinear parameters (a plugin's, two nonlinear effects), a nonlinear effect fixed at given values,
or one whose profile the statistics do not hold.

At each trial value ``x`` of the nonlinear parameters their effects' summed prediction ``e_f(x)``
((n, 6), smoothed force and torque, body frame) is made on each flight's rows and enters the flight's
statistics as an extra column, where rows become statistics
(:func:`quadcore.identify.stats.sufficient.extra_column`): its row of the augmented Gram matrix on the
columns the fit reads (the fitted linear effects' ``K`` and the target's), ``c_fc(x) = Σ_i z_ic
e_ic``, and ``q_fc(x) = Σ_i e_ic²``. The residual is the target ``u_f`` (a signal vector) minus
``e``; with the linear effects solved inside (variable projection, weights ``w_c``)::

    A = Σ_f Σ_c w_c G_fc[K, K]                                  (from the statistics, once)
    b(x) = Σ_f Σ_c w_c (G_fc[K, :] u_f - c_fc(x)[K])
    yy(x) = Σ_f Σ_c w_c (u_fᵀ G_fc u_f - 2 c_fc(x)·u_f + q_fc(x))
    J(x) = yy(x) - θᵀ b(x),   θ = A⁺ b(x)

then the linear effects on what ``e(x*)`` leaves, as every fit solves them
(:func:`quadcore.identify.fit.solve.solved_linear`, within their bounds when asked).

**The optimiser.** One parameter: :func:`quadcore.identify.fit.solve.scalar_minimum` on ``J``, as
every one-parameter fit (the grid, Brent's refinement, the profile-likelihood interval). Several:
the fit on rows ran bounded nonlinear least squares on the residual vector (trust region
reflective, ``scipy.optimize.least_squares``), which needs that vector: the statistics give
``J`` and its sums, not the residual sample by sample. Here a bounded quasi-Newton minimiser of ``J``
itself (L-BFGS-B in coordinates scaled to the box, from the row search's start, a tenth into the
box, central-difference gradients), and at the optimum the row search's Gauss-Newton covariance:
the derivatives ``d_a`` of ``e`` by each parameter (central differences) enter as extra columns, and
the projected Jacobian's ``JᵀJ`` (what ``least_squares`` gives with the linear effects solved
inside) is::

    M_ab = Σ_f Σ_c w_c (d_a·d_b - (d_a·X_K) A⁺ (X_K·d_b)),   cov = M⁻¹ J(x*) / (N - k) × W

(``N`` the values fitted, ``k`` the nonlinear parameters, ``W`` = ``SAMPLES_PER_INDEPENDENT``;
``d_a·d_b`` by polarisation from the extra column's sums of ``d_a``, ``d_b`` and ``d_a + d_b``).
Chosen over a minimiser without derivatives because ``J`` is smooth wherever the effects'
predictions are, and a gradient method stops where the gradient vanishes as the trust region does;
both take the same covariance. Where ``J`` has one minimum in the box both land on it; how close,
on the plugin effects of the tests: ``tests/test_search.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy.optimize import minimize

from quadcore import effects as effectlib
from quadcore.effects import Effect
from quadcore.identify.binfile import StatsError
from quadcore.identify.fit.linear import channel_weights, linear_columns, projected_rss, subtract_fixed
from quadcore.identify.fit.solve import Fit, scalar_minimum, solved_linear, unpack, weighted_values
from quadcore.identify.flightdata import SAMPLES_PER_INDEPENDENT, FlightData, prediction
from quadcore.identify.stats import sufficient
from quadcore.identify.stats.sufficient import FlightStats, normal_equations
from quadcore.physics.vehicle import Vehicle

Rows = Callable[[str], FlightData]  # a flight's rows by its id (the statistics' ``flight``)
Extras = Callable[[str], Mapping[str, np.ndarray]]  # by flight id: (n, 6) rows of extra columns a target reads

START = 0.1  # where in the box the search starts (the row search's start)
DIFF_STEP = 1e-3  # the Jacobian's step, relative to max(1, |x|) (least_squares' diff_step of the row search)


class _Search:
    """The sums of the module for one fit: ``A``, ``b0``, ``yy0`` from the statistics, and per
    flight the extra column's sums of a prediction on its rows."""

    def __init__(self, nonlin: list[Effect], lin: list[Effect], held: dict[str, dict[str, float]],
                 stats: Sequence[FlightStats], us: list[np.ndarray], w: np.ndarray, rows: Rows, vehicle: Vehicle,
                 extras: Extras | None = None):
        self.nonlin, self.vehicle, self.w = nonlin, vehicle, w
        self.A, self.b0, self.yy0 = normal_equations(stats, us, w, lambda lay: linear_columns(lay, lin))
        self.n = weighted_values(w, sum(s.n for s in stats))
        self.flights: list[tuple[FlightData, Callable[[np.ndarray], np.ndarray], np.ndarray, np.ndarray,
                                 np.ndarray]] = []
        for s, u in zip(stats, us):
            fd = rows(s.flight)
            if fd.n != s.n:
                raise StatsError(f"{s.flight}: its rows have {fd.n} usable samples, its statistics {s.n}")
            K = linear_columns(s.layout, lin)
            cols = np.array(sorted({*K.tolist(), *np.flatnonzero(u).tolist()}), dtype=int)
            at_K = np.searchsorted(cols, K)
            base = sum((prediction(effectlib.get(n), v, fd, vehicle) for n, v in held.items()),
                       np.zeros((fd.state.n, 6)))  # the nonlinear effects held at given values
            more = extras(s.flight) if extras is not None and np.any(u[s.layout.y0 + 1:]) else None
            self.flights.append((fd, sufficient.extra_column(fd, vehicle, s.layout, cols, more), u[cols], at_K, base))

    def column(self, nl: dict[str, dict[str, float]], fd: FlightData, base: np.ndarray) -> np.ndarray:
        """(n, 6) the extra column: the nonlinear effects' summed prediction at ``nl``."""
        return base + sum((prediction(e, nl[e.name], fd, self.vehicle) for e in self.nonlin), np.zeros_like(base))

    def normal(self, nl: dict[str, dict[str, float]]) -> tuple[np.ndarray, float]:
        """``(b, yy)`` of the linear effects on what the nonlinear ones leave at ``nl``."""
        b, yy = self.b0.copy(), self.yy0
        for fd, sums, u, at_K, base in self.flights:
            S = self.w @ sums(self.column(nl, fd, base))  # Σ_c w_c [c_fc | q_fc]
            b -= S[at_K]
            yy += -2.0 * float(S[:-1] @ u) + float(S[-1])
        return b, yy

    def rss(self, nl: dict[str, dict[str, float]]) -> float:
        return projected_rss(self.A, *self.normal(nl))

    def gauss_newton(self, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """``M`` of the module at ``x`` (the derivatives by central differences within the box)."""
        k = len(x)
        steps = DIFF_STEP * np.maximum(1.0, np.abs(x))
        M = np.zeros((k, k))
        C = np.zeros((k, len(self.b0)))
        for fd, sums, _, at_K, base in self.flights:
            D = []
            for a in range(k):
                up, down = min(x[a] + steps[a], hi[a]), max(x[a] - steps[a], lo[a])
                xu, xd = x.copy(), x.copy()
                xu[a], xd[a] = up, down
                D.append((self.column(self.values(xu), fd, base) - self.column(self.values(xd), fd, base))
                         / (up - down))
            S = [self.w @ sums(d) for d in D]  # Σ_c w_c [d_a·z | d_a·d_a]
            for a in range(k):
                C[a] += S[a][at_K]
                M[a, a] += S[a][-1]
                for b in range(a + 1, k):
                    both = self.w @ sums(D[a] + D[b])
                    M[a, b] += 0.5 * (both[-1] - S[a][-1] - S[b][-1])
                    M[b, a] = M[a, b]
        if len(self.b0):
            M -= C @ np.linalg.pinv(self.A) @ C.T
        return M

    def values(self, x: np.ndarray) -> dict[str, dict[str, float]]:
        """The nonlinear effects' parameters at the stacked values ``x``."""
        return unpack(self.nonlin, x)


def search_fit(effects: list[Effect], stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
               vehicle: Vehicle, rows: Rows, fixed: dict[str, dict[str, float]] | None = None,
               bounded: bool = False, extras: Extras | None = None, channels: np.ndarray | None = None) -> Fit:
    """Jointly fit ``effects`` (nonlinear ones among them) to the targets ``z·u_f`` from the
    flights' statistics, the nonlinear effects' predictions made on their rows (``rows(flight)``)
    and entering as an extra column (see the module); those named in ``fixed`` keep their values
    (linear ones subtracted as vectors, nonlinear ones part of the column); ``bounded``: the linear
    effects within their physical bounds; ``extras(flight)``: the rows of the extra columns of the
    flight's statistics a target reads (a model's profiled prediction, say); ``channels``: the
    channels fitted (:func:`quadcore.identify.fit.linear.channel_weights`)."""
    fixed = fixed or {}
    w = channel_weights(stats, [np.asarray(u, dtype=float) for u in targets], channels)
    us, params, std = subtract_fixed(effects, {e.name: fixed[e.name] for e in effects if e.linear and e.name in fixed},
                                     stats, targets, vehicle)
    held = {e.name: {**e.defaults(), **fixed[e.name]} for e in effects if not e.linear and e.name in fixed}
    for e in effects:
        if e.name in held:
            params[e.name], std[e.name] = held[e.name], {p.name: 0.0 for p in e.parameters}
    lin = [e for e in effects if e.linear and e.name not in fixed]
    nonlin = [e for e in effects if not e.linear and e.name not in fixed]
    search = _Search(nonlin, lin, held, stats, us, w, rows, vehicle, extras)
    ps = [p for e in nonlin for p in e.parameters]
    lo, hi = np.array([p.lower for p in ps]), np.array([p.upper for p in ps])
    if len(ps) == 1:
        memo: dict[float, float] = {}

        def J(v: float) -> float:
            v = float(min(max(v, lo[0]), hi[0]))
            if v not in memo:
                memo[v] = search.rss(search.values(np.array([v])))
            return memo[v]

        best, var = scalar_minimum(J, search.n, float(lo[0]), float(hi[0]))
        x, cov = np.array([best]), np.array([[var]])
    elif ps:
        x, cov = _vector_minimum(search, lo, hi)
    else:
        x, cov = np.zeros(0), np.zeros((0, 0))
    nl = search.values(x)
    i = 0
    for e in nonlin:
        params[e.name] = nl[e.name]
        std[e.name] = {p.name: float(np.sqrt(max(cov[i + j, i + j], 0.0))) for j, p in enumerate(e.parameters)}
        i += len(e.parameters)
    if not lin:
        return Fit(params, std, w)
    b, yy = search.normal(nl)
    return solved_linear(lin, search.A, b, yy, search.n, vehicle, params, std, w, bounded)


def _vector_minimum(search: _Search, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Several nonlinear parameters: the bounded minimum of ``J`` and its Gauss-Newton covariance
    (see the module)."""
    span = hi - lo
    scale = search.rss(search.values(lo + START * span)) or 1.0  # J of order one for the minimiser's tolerances

    def J(z: np.ndarray) -> float:
        return search.rss(search.values(lo + np.clip(z, 0.0, 1.0) * span)) / scale

    sol = minimize(J, np.full(len(lo), START), method="L-BFGS-B", jac="3-point", bounds=[(0.0, 1.0)] * len(lo),
                   options={"ftol": 1e-12, "gtol": 1e-9, "maxiter": 500, "finite_diff_rel_step": 1e-4})
    x = lo + np.clip(sol.x, 0.0, 1.0) * span
    j = search.rss(search.values(x))
    s2 = j / max(search.n - len(lo), 1)
    try:
        cov = np.linalg.inv(search.gauss_newton(x, lo, hi)) * s2 * SAMPLES_PER_INDEPENDENT
    except np.linalg.LinAlgError:
        cov = np.full((len(lo), len(lo)), np.inf)
    return x, cov
