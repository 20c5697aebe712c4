"""A flight's rows answering what the fits, held-out tests and descriptions ask of a flight (the
:class:`quadcore.identify.flightdata.Flight` protocol) sample by sample: the reference
:class:`quadcore.identify.stats.sufficient.FlightStats` is compared against, which answers the same
from its Gram matrices. Nothing in quadcore holds a flight this way any more (it holds statistics);
the row fits (:mod:`reference.rows`) and the equality tests do, through :func:`as_rows`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np

from quadcore.effects import Effect, Parameter
from quadcore.identify.flightdata import GRAM_STRIDE, FlightData, prediction, unit_wrench
from quadcore.physics.vehicle import Vehicle


@dataclass
class RowFlight(FlightData):
    """:class:`FlightData` with the Flight protocol on its rows (signals are (n, 6) arrays), and
    the caches a row search needs (designs, nonlinear predictions, sums of squares)."""

    _predictions: dict = field(default_factory=dict, repr=False)
    _sums: dict = field(default_factory=dict, repr=False)
    _designs: dict = field(default_factory=dict, repr=False)

    def sum_of_squares(self, signal: np.ndarray) -> np.ndarray:
        """(6,) per channel: the sum of squares of an (n, 6) signal over the usable samples."""
        return (signal[self.mask] ** 2).sum(axis=0)

    def unit_signal(self, effect: Effect, param: Parameter, vehicle: Vehicle) -> np.ndarray:
        return unit_wrench(effect, param, self, vehicle)

    def reference_ss(self, effect: Effect, vehicle: Vehicle) -> float:
        """Energy of the effect's prediction at its sensitivity reference over the usable samples."""
        ref = {**effect.defaults(), **effect.sensitivity_reference}
        return float((prediction(effect, ref, self, vehicle)[self.mask] ** 2).sum())

    def after_blocks(self, k: int) -> RowFlight:
        """The flight without its first ``k`` blocks; the cached sums and designs start afresh."""
        if k <= 0:
            return self
        keep = self.mask.copy()
        keep[np.flatnonzero(self.mask)[self.blocks() < k]] = False
        return replace(self, mask=keep, _sums={}, _designs={})

    def block_channel_sums(self, pairs: Sequence[tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]]]
                           ) -> list[np.ndarray]:
        """Per pair ``(a, b)`` of signals (flight -> (n, 6)): (blocks, 6) ``Σ_i a_ic b_ic`` per block."""
        blocks = self.blocks()
        out = []
        for a, b in pairs:
            prod = a[self.flight][self.mask] * b[self.flight][self.mask]
            out.append(np.stack([np.bincount(blocks, weights=prod[:, c], minlength=blocks.max(initial=-1) + 1)
                                 for c in range(6)], axis=1))
        return out

    def basis_columns(self, effect: Effect, vehicle: Vehicle) -> list[np.ndarray]:
        B = self.basis(effect, vehicle)
        return [B[:, :, j] for j in range(B.shape[2])]

    def strided_grams(self, columns: Sequence[np.ndarray], w: np.ndarray,
                      groups: Mapping[str, slice]) -> dict[str, np.ndarray]:
        """Per channel group: ``Zᵀ Z`` of the weighted columns on every ``GRAM_STRIDE``-th usable sample."""
        m = np.flatnonzero(self.mask)[::GRAM_STRIDE]
        Z = np.stack([c[m] for c in columns], axis=2) * np.sqrt(w)[None, :, None]
        return {ch: np.einsum("nci,ncj->ij", Z[:, sl, :], Z[:, sl, :]) for ch, sl in groups.items()}

    def design(self, lin: list[Effect], vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray]:
        """Masked stacked basis (m, 6, k) of linear effects and its Gram matrix per channel, cached."""
        key = tuple(e.name for e in lin)
        if key not in self._designs:
            X = np.concatenate([self.basis(e, vehicle) for e in lin], axis=2)[self.mask]
            self._designs[key] = (X, np.einsum("nci,ncj->cij", X, X))
        return self._designs[key]

    def cached_prediction(self, effect: Effect, params: dict, vehicle: Vehicle) -> np.ndarray:
        """(n, 6) a nonlinear effect's prediction, cached per parameter value (the grid search's)."""
        key = (effect.name, tuple(sorted(params.items())))
        if key not in self._predictions:
            if len(self._predictions) > 64:
                self._predictions.clear()
            self._predictions[key] = prediction(effect, params, self, vehicle)
        return self._predictions[key]

    def cached_sums(self, nonlin: list[Effect], params: dict, y: np.ndarray, target_key: str,
                    vehicle: Vehicle) -> np.ndarray:
        """(6,) ``Σ (y - Σ_e p_e)²`` per channel over the usable samples, cached per value and target."""
        key = (target_key, tuple((e.name, tuple(sorted(params[e.name].items()))) for e in nonlin))
        if key not in self._sums:
            p = np.zeros_like(y)
            for e in nonlin:
                p += prediction(e, params[e.name], self, vehicle)
            self._sums[key] = ((y - p)[self.mask] ** 2).sum(axis=0)
        return self._sums[key]


_BASE_FIELDS = [f.name for f in fields(FlightData)]


def as_rows(fd: FlightData) -> RowFlight:
    """``fd`` as a :class:`RowFlight` (itself when it is one); the cached bases are shared."""
    if isinstance(fd, RowFlight):
        return fd
    return RowFlight(**{name: getattr(fd, name) for name in _BASE_FIELDS})
