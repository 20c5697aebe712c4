"""One nonlinear effect with one parameter (``motor_lag``'s τ, ``thrust_delay``'s t_d, a plugin's)
and linear effects beside it, fitted from the flights' statistics and the effect's profiles
(:mod:`quadcore.identify.stats.profiles`): variable projection, the nonlinear parameter searched with the
linear ones solved inside.

With the profile's interpolation weights ``ω = ω(v)`` (:func:`quadcore.identify.stats.profiles.weights`),
per flight the target's sums with the effect's prediction are ``ω·P_f`` and so, summed over
flights with the channel weights ``w_c``::

    A = Σ_f Σ_c w_c G_fc[K, K],   b(v) = Σ_f Σ_c w_c (G_fc[K, :] u_f - ω·P_f·c[K]),
    yy(v) = Σ_f Σ_c w_c (u_fᵀ G_fc u_f - 2 ω·P_f·c[:W] u_f + ω·P_f·c[W]),
    J(v) = yy(v) - b(v)ᵀ A⁻¹ b(v).

``J`` is searched as the rows search it (:func:`quadcore.identify.fit.solve.scalar_minimum`: the
grid, Brent's refinement, the profile-likelihood interval). Its accuracy against the row search:
:mod:`quadcore.identify.stats.profiles`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from quadcore.effects import Effect
from quadcore.identify.fit.linear import channel_weights, linear_columns, projected_rss, subtract_fixed
from quadcore.identify.fit.solve import Fit, scalar_minimum, solved_linear, weighted_values
from quadcore.identify.stats import profiles
from quadcore.identify.stats.sufficient import FlightStats
from quadcore.physics.vehicle import Vehicle


def profiled_fit(effects: list[Effect], stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
                vehicle: Vehicle, fixed: dict[str, dict[str, float]] | None = None, bounded: bool = False,
                channels: np.ndarray | None = None) -> Fit:
    """:func:`quadcore.identify.fit.fit_effects` of one profiled effect and linear ones to the
    targets ``z·u_f`` from the flights' statistics and profiles, as the rows do it: the profiled
    effect's parameter by the row search's grid, Brent refinement and profile interval
    (:func:`quadcore.identify.fit.solve.scalar_minimum`) on ``J(v)`` of the module with the linear
    effects solved inside (variable projection: with ``ω = ω(v)``, ``A = Σ_f Σ_c w_c G_fc[K, K]``,
    ``b(v) = Σ_f Σ_c w_c (G_fc[K, :] u_f - ω·P_f·c[K])``, ``J(v) = yy(v) - b(v)ᵀ A⁻¹ b(v)``), then
    the linear effects on what it leaves at the optimum (``bounded``: within their physical bounds,
    :func:`quadcore.identify.fit.solve.solved_linear`). Those named in ``fixed`` are subtracted
    first (a linear one by its coordinates, a profiled one by its column ``pred:<effect>``:
    :func:`quadcore.identify.fit.linear.subtract_fixed`); ``channels``: the channels fitted
    (:func:`quadcore.identify.fit.linear.channel_weights`)."""
    fixed = fixed or {}
    (nonlinear,) = [e for e in effects if not e.linear and e.name not in fixed]
    (p,) = nonlinear.parameters
    w = channel_weights(stats, [np.asarray(u, dtype=float) for u in targets], channels)
    us, params, std = subtract_fixed(effects, fixed, stats, targets, vehicle)
    lin = [e for e in effects if e.linear and e.name not in fixed]
    sums = _Sums.of(nonlinear.name, lin, stats, us, w)

    def J(v: float) -> float:
        return sums.rss(profiles.weights(p.lower, p.upper, v))

    best, var = scalar_minimum(J, sums.n, p.lower, p.upper)
    params[nonlinear.name] = {p.name: best}
    std[nonlinear.name] = {p.name: float(np.sqrt(max(var, 0.0)))}
    if lin:
        b, yy = sums.normal(profiles.weights(p.lower, p.upper, best))
        return solved_linear(lin, sums.A, b, yy, sums.n, vehicle, params, std, w, bounded)
    return Fit(params, std, w)


@dataclass(frozen=True)
class _Sums:
    """The combined sums of a variable-projection fit (see :func:`profiled_fit`): ``yy(v) = const
    - 2 ω·S + ω·Q``, ``b(v) = b0 - B ω``, over ``n`` values."""

    const: float
    S: np.ndarray
    Q: np.ndarray
    A: np.ndarray
    b0: np.ndarray
    B: np.ndarray
    n: int

    @classmethod
    def of(cls, name: str, lin: list[Effect], stats: Sequence[FlightStats], us: list[np.ndarray],
           w: np.ndarray) -> _Sums:
        k = sum(len(e.parameters) for e in lin)
        const, S, Q, A, b0, B, n = 0.0, 0.0, 0.0, np.zeros((k, k)), np.zeros(k), 0.0, 0
        for s, u in zip(stats, us):
            cols = linear_columns(s.layout, lin)
            Gw = np.tensordot(w, s.total, axes=1)  # Σ_c w_c G_c
            prof = profiles.of_flight(s).by_effect[name].total
            Pw = np.einsum("gcw,c->gw", prof[:, :, :len(u)], w)  # Σ_c w_c P_gc, per grid point
            const += float(u @ Gw @ u)
            S = S + Pw @ u
            Q = Q + prof[:, :, -1] @ w
            A += Gw[np.ix_(cols, cols)]
            b0 += Gw[cols] @ u
            B = B + Pw[:, cols].T
            n += weighted_values(w, s.n)
        return cls(const, np.asarray(S), np.asarray(Q), A, b0, np.asarray(B), n)

    def normal(self, om: np.ndarray) -> tuple[np.ndarray, float]:
        """``(b, yy)`` of the linear effects' normal equations (their ``A`` is :attr:`A`) on what
        the profiled effect leaves at weights ``om``."""
        return self.b0 - self.B @ om, self.const - 2 * float(om @ self.S) + float(om @ self.Q)

    def rss(self, om: np.ndarray) -> float:
        """The residual sum of squares at weights ``om``, the linear effects solved for."""
        return projected_rss(self.A, *self.normal(om))
