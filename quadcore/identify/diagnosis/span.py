"""Candidates' signatures compared on the evaluated flights (:class:`_SpanOverlap`): which candidate
can reproduce another's held-out prediction, and what one still removes once another is in the model."""

from __future__ import annotations

import numpy as np

from quadcore.identify.diagnosis.problem import (
    TARGET_CHANNELS,
)


class _SpanOverlap:
    """Signatures compared on the evaluated flights, accumulated flight by flight as Gram
    matrices of ``[residual | held-out predictions | bases]`` per channel (no big arrays).

    * :meth:`mimic`: how well one candidate's held-out prediction can be reproduced by another
      candidate with *any* parameter values: the share of the prediction's energy in the span
      of the other's basis (linear effects) or along its prediction (nonlinear ones).
      Independent of how large either fit is, so a fit that the other channel pulled to zero
      still shows its shape.
    * :meth:`left_after`: the share of the baseline residual a candidate can still remove
      once another one's held-out prediction is subtracted (least squares on its basis over
      the evaluated flights: in-sample, so it is a screening number; a few parameters on
      thousands of samples barely overfit).
    """

    def __init__(self, cands, cand_pred, flights, resid, w, vehicle):
        self.names = [c.name for c in cands]
        self.cols: dict[str, list[int]] = {}
        k = 1 + len(cands)
        for c in cands:
            n_basis = len(c.parameters) if c.linear else 1
            self.cols[c.name] = list(range(k, k + n_basis))
            k += n_basis
        self.gram = {"force": np.zeros((k, k)), "torque": np.zeros((k, k))}
        for fd in flights:  # rows or statistics alike (Flight.strided_grams)
            cols = [resid[fd.flight]] + [cand_pred[c.name][fd.flight] for c in cands]
            for c in cands:
                cols += fd.basis_columns(c, vehicle) if c.linear else [cand_pred[c.name][fd.flight]]
            for ch, G in fd.strided_grams(cols, w, TARGET_CHANNELS).items():
                self.gram[ch] += G

    def _G(self, channel: str | None) -> np.ndarray:
        return self.gram[channel] if channel else self.gram["force"] + self.gram["torque"]

    def _fit(self, G: np.ndarray, y: np.ndarray, b: str) -> tuple[float, np.ndarray]:
        """Least-squares fit of the combination ``y`` of columns on ``b``'s basis: the
        energy it reproduces and the coefficients."""
        cols = self.cols[b]
        A, c = G[np.ix_(cols, cols)], G[cols] @ y
        beta = np.linalg.lstsq(A, c, rcond=1e-10)[0]
        return float(c @ beta), beta

    def _gain(self, G: np.ndarray, y: np.ndarray, b: str) -> float:
        return self._fit(G, y, b)[0]

    def mimic(self, a: str, b: str, channel: str | None) -> tuple[float, np.ndarray]:
        """Share of ``a``'s prediction (in ``channel``, or both channels when None) that
        ``b`` can reproduce, and the coefficients of ``b`` that do it (its linear
        coordinates for a linear effect; a factor on its own prediction otherwise)."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[1 + self.names.index(a)] = 1.0
        yy = float(y @ G @ y)
        if yy <= 0:
            return 0.0, np.zeros(len(self.cols[b]))
        gain, beta = self._fit(G, y, b)
        return float(np.clip(gain / yy, 0.0, 1.0)), beta

    def left_after(self, b: str, top: str | None, channel: str) -> float:
        """Share of the baseline ``channel`` residual that ``b`` removes from what ``top``
        leaves (from the whole residual: ``top`` None; the same screen, to compare with)."""
        G = self._G(channel)
        y = np.zeros(len(G))
        y[0] = 1.0
        if top is not None:
            y[1 + self.names.index(top)] = -1.0
        base = G[0, 0]
        return float(np.clip(self._gain(G, y, b) / base, 0.0, 1.0)) if base > 0 else 0.0
