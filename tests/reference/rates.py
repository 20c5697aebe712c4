"""The reference the rate level's sums (:class:`quadcore.identify.rates.RateSums`) are tested
against: every cost evaluated on the flight's rows, recomputing the candidate's torque
(``R_k − C_k(v)`` less its mean per segment, summed per block, docs/timing.md), with the sums' interface (``cost``,
``costs``, ``differences``, ``n``, ``dt_s``), so that :func:`~quadcore.identify.rates.block_differences`
runs on either, and :func:`fit`, the rows' :func:`quadcore.identify.rates.fit` (the same search,
:func:`quadcore.identify.rates.fit_cost`, on the rows' costs). Nothing in quadcore uses it."""

from __future__ import annotations

import numpy as np

from quadcore.identify import rates
from quadcore.physics import signals


class RowRates:
    """One flight's rate level evaluated on its rows (the module)."""

    def __init__(self, rf: rates.RateFlight):
        self.rf, self.n = rf, rf.n
        self.dt_s = float(np.median(np.diff(rf.fd.state.t_s)))

    def _deviations(self, effect, value: float) -> tuple[np.ndarray, np.ndarray]:
        st, (p,) = self.rf.fd.state, effect.parameters
        c = signals.interval_integrals(effect.wrench(st, self.rf.vehicle, {p.name: value})[1], st.t_s,
                                       st.thrust_hold_s)
        use = self.rf.block >= 0
        R, seg = np.cumsum(self.rf.increments - c, axis=0)[use], self.rf.segment[use]
        mean = np.stack([np.bincount(seg, R[:, a]) for a in range(3)], axis=1) / np.bincount(seg)[:, None]
        return R - mean[seg], np.unique(self.rf.block[use], return_inverse=True)[1].reshape(-1)

    @staticmethod
    def _per_block(x: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(b, x[:, a]) for a in range(3)], axis=1)

    def costs(self, effect, value: float) -> np.ndarray:
        dev, b = self._deviations(effect, value)
        return self._per_block(dev**2, b)

    def cost(self, effect, value: float, w: np.ndarray) -> float:
        return float(self.costs(effect, value).sum(axis=0) @ w)

    def differences(self, a, va: float, b, vb: float, unwhitened: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The rows have no whitening filter: ``unwhitened`` changes nothing."""
        (dev_a, blocks), (dev_b, _) = self._deviations(a, va), self._deviations(b, vb)
        return self._per_block(dev_b**2 - dev_a**2, blocks), self._per_block((dev_b - dev_a) ** 2, blocks)


def fit(effect, flights: list[RowRates], w: np.ndarray) -> rates.RateFit:
    """:func:`quadcore.identify.rates.fit` on the rows: the same search and standard errors
    (:func:`quadcore.identify.rates.fit_cost`), each cost from the rows."""
    def J(v: float) -> float:
        return sum(f.cost(effect, v, w) for f in flights)

    def per_block(v: float) -> np.ndarray:
        return np.concatenate([f.costs(effect, v) @ w for f in flights])

    knots = np.unique(np.concatenate([rates.rate_grid(effect, f.dt_s) for f in flights]))
    return rates.fit_cost(effect, J, per_block, sum(f.n for f in flights) * 3, min(f.dt_s for f in flights), knots)


def instrumented(rows: RowRates, a, va: float, b, vb: float, ar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`quadcore.identify.rates.RateSums.instrumented` on the rows: per segment the deviations
    whitened with ``ar`` (3, p) and demeaned again, the direction ``Δ = C_a − C_b`` one interval
    back times the residual about the middle and times ``Δ``, summed per block."""
    (dev_a, blocks), (dev_b, _) = rows._deviations(a, va), rows._deviations(b, vb)
    seg = rows.rf.segment[rows.rf.block >= 0]
    g, D = np.zeros((blocks.max() + 1, 3)), np.zeros((blocks.max() + 1, 3))
    for s in np.unique(seg):
        at = np.flatnonzero(seg == s)
        d = rates.whitened(dev_b[at] - dev_a[at], ar)
        e = rates.whitened(0.5 * (dev_a[at] + dev_b[at]), ar)
        d, e = d - d.mean(axis=0), e - e.mean(axis=0)
        g[blocks[at[0]]] += 2.0 * (d[:-1] * e[1:]).sum(axis=0)
        D[blocks[at[0]]] += (d[:-1] * d[1:]).sum(axis=0)
    return g, D
