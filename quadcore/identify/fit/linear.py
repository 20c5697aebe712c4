"""The linear effects fitted from the flights' statistics (:mod:`quadcore.identify.stats.sufficient`):
normal equations summed over flights, then the solve every fit shares
(:func:`quadcore.identify.fit.solve.solved_linear`).

For a target ``y_f = z·v_f`` per flight (a signal vector over the flight's augmented design ``z``)
and the fitted effects' coordinates ``K``::

    A = Σ_f Σ_c w_c G_fc[K, K],   b = Σ_f Σ_c w_c G_fc[K, :] v_f,   yy = Σ_f Σ_c w_c v_fᵀ G_fc v_f

and ``θ = A⁻¹ b`` (least squares), the residual sum of squares ``yy - 2 θᵀb + θᵀAθ``. A fit costs
a sum over flights of small matrices: it does not grow with the rows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from quadcore.effects import Effect
from quadcore.identify.fit.solve import Fit, fixed_values, solved_linear, weighted_values, weights_from_sums
from quadcore.identify.stats.sufficient import FlightStats, Layout, normal_equations, sum_of_squares
from quadcore.physics.vehicle import Vehicle


def channel_weights(stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
                    channels: np.ndarray | None = None) -> np.ndarray:
    """1/σ² for the force and the torque channels from the mean squares of the targets ``z·v_f``
    (:func:`quadcore.identify.fit.solve.weights_from_sums`); ``channels``: (6,) 1 on the channels
    the fit takes, 0 on those it leaves out (None: every channel)."""
    # per flight: stacking the totals (a copy of ~23 MB at 1,000 flights) costs 5x these products
    ss = sum((sum_of_squares(s, v) for s, v in zip(stats, targets)), np.zeros(6))
    w = weights_from_sums(ss, sum(s.n for s in stats))
    return w if channels is None else w * channels


def subtract_fixed(effects: list[Effect], fixed: dict[str, dict[str, float]], stats: Sequence[FlightStats],
                   targets: Sequence[np.ndarray], vehicle: Vehicle) -> tuple[list[np.ndarray], dict, dict]:
    """The targets minus the predictions of the effects named in ``fixed`` (at their given values:
    a linear one's coordinates, a profiled one's column ``pred:<effect>`` the statistics were grown
    by, :func:`quadcore.identify.stats.sufficient.predicted`), and the fixed effects' (parameters,
    standard errors) (:func:`fixed_values`)."""
    params, std = fixed_values(effects, fixed)
    vs = [np.asarray(v, dtype=float) for v in targets]
    for e in effects:
        if e.name in fixed:
            vs = [v - (s.layout.coefficients(e, params[e.name], vehicle) if e.linear
                       else s.layout.unit(s.layout.extra(f"pred:{e.name}"))) for s, v in zip(stats, vs)]
    return vs, params, std


def linear_columns(layout: Layout, lin: Sequence[Effect]) -> np.ndarray:
    """The columns of the linear effects ``lin`` in a flight's layout (stacked, in order)."""
    return np.concatenate([layout.cols(e.name) for e in lin]) if lin else np.zeros(0, dtype=int)


def projected_rss(A: np.ndarray, b: np.ndarray, yy: float) -> float:
    """The weighted residual sum of squares left when the linear coordinates are solved for
    (variable projection): ``yy - 2 θ·b + θᵀ A θ`` at ``θ = A⁺ b`` (least squares), never below 0."""
    if not len(b):
        return max(yy, 0.0)
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    return max(yy - 2 * float(theta @ b) + float(theta @ A @ theta), 0.0)


def fit_linear(effects: list[Effect], stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
               vehicle: Vehicle, fixed: dict[str, dict[str, float]] | None = None, bounded: bool = False,
               channels: np.ndarray | None = None) -> Fit:
    """Jointly fit the linear ``effects`` to the targets ``z·v_f`` (normal equations, see the
    module); those named in ``fixed`` keep their values and are subtracted first; ``bounded``:
    within the parameters' physical bounds (:func:`quadcore.identify.fit.solve.solved_linear`);
    ``channels``: the channels fitted (:func:`channel_weights`)."""
    fixed = fixed or {}
    w = channel_weights(stats, [np.asarray(v, dtype=float) for v in targets], channels)
    vs, params, std = subtract_fixed(effects, fixed, stats, targets, vehicle)
    lin = [e for e in effects if e.name not in fixed]
    if lin:
        A, b, yy = normal_equations(stats, vs, w, lambda lay: linear_columns(lay, lin))
        n = weighted_values(w, sum(s.n for s in stats))
        return solved_linear(lin, A, b, yy, n, vehicle, params, std, w, bounded)
    return Fit(params, std, w)
