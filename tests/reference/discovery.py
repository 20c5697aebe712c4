"""The reference term discovery's held-out RMSE is tested against: the kept terms evaluated on each
evaluated flight's rows, filtered as the residual is, and the squares of the residual before and after
them summed sample by sample. Nothing in quadcore uses it; discovery scores from the flights'
statistics (:func:`quadcore.identify.discovery.select._held_out_errors`, a quadratic form of the Gram
matrices on every usable sample), and tests/test_discovery_statistics.py compares the two."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from quadcore.identify import flightdata
from quadcore.identify.discovery.grams import Columns
from quadcore.identify.discovery.terms import Term, evaluate
from quadcore.physics import signals
from quadcore.physics.vehicle import Vehicle
from reference.flight import as_rows


def _ols(G: np.ndarray, cols: list[int], y: int) -> np.ndarray:
    """Least squares of column ``y`` on ``cols`` from a Gram matrix."""
    return np.linalg.lstsq(G[np.ix_(cols, cols)], G[cols, y], rcond=1e-12)[0]


def held_out_rmse(flight: Callable[[str], tuple[flightdata.FlightData, np.ndarray]], eval_ids: list[str],
                  train_gram: Mapping[str, np.ndarray], cols: Columns, terms: list[Term],
                  coefs: Mapping[int, tuple[list[int], np.ndarray]], vehicle: Vehicle, skip: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(before, after) the RMSE per axis (6,) (force N, torque N m, body frame) on the evaluated
    flights before and after the kept terms (``coefs``: per axis the kept Gram columns), each fitted on
    ``train_gram[f]``, the Gram matrix flight ``f`` is scored with; on the usable samples after each
    flight's first ``skip`` blocks (on every usable sample when no evaluated flight keeps one there).
    ``flight(f)``: a flight's rows and its residual under the model, (n, 6)."""
    ss = np.zeros((2, 2, 6))  # (after the first blocks, every usable sample) x (before, after the terms)
    n = np.zeros(2, dtype=int)
    for f in eval_ids:
        fd, r = flight(f)
        pred = np.zeros_like(r)
        for axis, (chosen, _) in coefs.items():
            if not chosen:
                continue
            beta = _ols(train_gram[f], chosen, cols.target0 + axis)
            col_term = {cols.term_col(k, axis): t.expression for k, t in enumerate(terms)
                        if k in (cols.force if axis < 3 else cols.torque)}
            raw = evaluate([col_term[c] for c in chosen], fd.state, vehicle)
            filt = signals.smooth(raw) if axis < 3 else \
                signals.matched_to_derivative(raw, fd.state.t_s, fd.state.thrust_hold_s)
            pred[:, axis] = filt @ beta
        for i, m in enumerate((as_rows(fd).after_blocks(skip).mask, fd.mask)):
            ss[i, 0] += (r[m] ** 2).sum(axis=0)
            ss[i, 1] += ((r - pred)[m] ** 2).sum(axis=0)
            n[i] += int(m.sum())
    i = 0 if n[0] > 0 else 1
    return np.sqrt(ss[i, 0] / max(n[i], 1)), np.sqrt(ss[i, 1] / max(n[i], 1))
