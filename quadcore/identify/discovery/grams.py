"""The Gram matrices term discovery selects from: which column is which (:class:`Columns`), one
flight's matrices (:func:`flight_grams`), and their sums over the flights of the training set,
of each cross-validation fold and of the holdout (:class:`GramSums`).

**Every term goes through the residual's own filter** (force: the smoother; torque: the
gyro derivative's filter, :func:`quadcore.identify.flightdata.smoothed_wrench`), so a coefficient found
here is exactly the parameter of a linear effect with that term as its basis
(:func:`quadcore.identify.discovery.writer.write_effect`). On a flight's samples the design row is

    z_i = [F_i | Tq_i | y_i | m_i | B_i]

``F`` the candidate terms through the force smoother, ``Tq`` through the gyro derivative's
filter, ``y`` (6) the residual (force N, torque N m, body frame), ``m`` (6) the modelled thrust
and rotor torque, ``B`` every effect's basis per axis; a flight's Gram matrix is ``Σ z_i z_iᵀ``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadcore.effects.base import Effect
from quadcore.identify import flightdata
from quadcore.identify.discovery.terms import Term, evaluate
from quadcore.physics import dynamics, signals
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle

CHUNK_ROWS = 2048  # strided samples per chunk of a flight's design rows (a few MB: the rows are never all copied)


@dataclass
class Columns:
    """The columns accumulated in the Gram matrices and where each block starts."""

    terms: list[Term]
    force: list[int]  # indices into terms usable for force targets
    torque: list[int]
    effect_cols: dict[tuple[str, int], list[int]]  # (effect, axis) -> Gram columns
    n_total: int

    def term_col(self, k: int, axis: int) -> int:
        """Gram column of term ``k`` filtered for ``axis`` (0-2 force, 3-5 torque)."""
        return self.force.index(k) if axis < 3 else len(self.force) + self.torque.index(k)

    @property
    def target0(self) -> int:
        return len(self.force) + len(self.torque)

    @property
    def model0(self) -> int:
        return self.target0 + 6

    def labels(self) -> tuple[str, ...]:
        """A name per Gram column: ``force:<term>``, ``torque:<term>``, ``y:<axis>`` (the
        residual), ``model:<axis>``, ``<effect>:<axis>:<parameter>``."""
        out = [f"force:{self.terms[k].expression}" for k in self.force]
        out += [f"torque:{self.terms[k].expression}" for k in self.torque]
        out += [f"y:{a}" for a in range(6)] + [f"model:{a}" for a in range(6)]
        out += [f"{name}:{axis}:{p}" for (name, axis), cs in self.effect_cols.items() for p in range(len(cs))]
        return tuple(out)


def _effect_basis(effect: Effect, state: FlightState, vehicle: Vehicle) -> list[tuple[np.ndarray, np.ndarray]]:
    """Its basis (linear effects) or its linearisation about 'no effect' (others)."""
    if effect.linear:
        return effect.basis(state, vehicle)
    out = []
    for p in effect.parameters:
        params = effect.defaults()
        h = 0.01 * (p.upper - p.lower) if np.isfinite(p.upper - p.lower) else 1e-3
        params[p.name] += h if p.default + h <= p.upper else -h
        f, tau = effect.wrench(state, vehicle, params)
        out.append((f / h, tau / h))
    return out


def _flight_blocks(fd: flightdata.FlightData, resid: np.ndarray, cols: Columns, fx_effects, vehicle) -> list:
    """The Gram columns of one flight on all its samples, in blocks: filtered terms (force,
    torque), residual targets, modelled sides, the effects' bases per axis."""
    s = fd.state
    raw = evaluate([t.expression for t in cols.terms], s, vehicle)
    F = signals.smooth(raw[:, cols.force])
    Tq = signals.matched_to_derivative(raw[:, cols.torque], s.t_s, s.thrust_hold_s)
    T_N, tau_rotor = dynamics.wrench_from_thrusts(vehicle, s.f_rotor_N)
    f_model = np.zeros((s.n, 3))
    f_model[:, 2] = T_N
    model = flightdata.smoothed_wrench(f_model, tau_rotor, s)
    blocks = [F, Tq, resid, model]
    for e in fx_effects:
        cached = fd.basis_if_cached(e) if e.linear else None  # the same columns: smoothed_wrench of e.basis
        if cached is not None:
            blocks += [cached[:, axis, :] for axis in range(6)]
            continue
        try:
            basis = [flightdata.smoothed_wrench(f, t, s) for f, t in _effect_basis(e, s, vehicle)]
        # a user's effect failing here: not matched
        except (ValueError, TypeError, KeyError, IndexError, ArithmeticError):
            basis = [np.zeros((s.n, 6)) for _ in e.parameters]
        blocks += [np.stack([b[:, axis] for b in basis], axis=1) for axis in range(6)]
    return blocks


def flight_grams(fd: flightdata.FlightData, resid: np.ndarray, cols: Columns, fx_effects, vehicle,
                 stride: int, head_blocks: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(the Gram matrix the selection uses: every ``stride``-th usable sample, the same matrix
    on every usable sample: the held-out RMSE's, and that one on the usable samples after the first
    ``head_blocks`` blocks: the RMSE's of a score that leaves them out) of one flight (see
    :mod:`quadcore.identify.discovery.library_stats`). The last two hold only the products within the
    force columns and within the torque columns (:func:`channel_groups`; zero between them): a force
    axis' RMSE never takes a torque term. Summed over chunks of ``stride * CHUNK_ROWS`` usable samples,
    so no copy of the flight's whole design is made."""
    blocks = _flight_blocks(fd, resid, cols, fx_effects, vehicle)
    rows, keep = np.flatnonzero(fd.mask), fd.blocks() >= head_blocks
    groups = channel_groups(cols.labels())
    G, H, H_after = (np.zeros((cols.n_total, cols.n_total)) for _ in range(3))
    chunk = stride * CHUNK_ROWS  # a multiple of the stride: the chunks' strided rows are the flight's
    for start in range(0, len(rows), chunk):
        Z = np.concatenate([b[rows[start:start + chunk]] for b in blocks], axis=1)
        Za = Z[keep[start:start + chunk]]
        Zs = np.ascontiguousarray(Z[::stride])
        with flightdata.one_blas_thread():
            G += Zs.T @ Zs
            for g in groups:
                Zg, Zga = Z[:, g], Za[:, g]
                H[np.ix_(g, g)] += Zg.T @ Zg
                H_after[np.ix_(g, g)] += Zga.T @ Zga
    return G, H, H_after


def channel_groups(labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the columns of the force axes (force terms, residual, modelled side and
    effects' bases on x, y, z of the force) and of the torque axes, from their names
    (:meth:`Columns.labels`)."""
    def axis(label: str) -> int:
        kind, _, rest = label.partition(":")
        if kind in ("force", "torque"):
            return 0 if kind == "force" else 3
        return int(rest if kind in ("y", "model") else rest.split(":")[0])

    axes = np.array([axis(label) for label in labels])
    return np.flatnonzero(axes < 3), np.flatnonzero(axes >= 3)


def library_columns(terms: list[Term], fx_effects: list[Effect]) -> Columns:
    """Where each of the Gram matrices' columns is: the terms usable in force, in torque, the
    six residual axes, the six modelled sides, then each effect's basis per axis."""
    force = [k for k, t in enumerate(terms) if t.channel in ("both", "force")]
    torque = [k for k, t in enumerate(terms) if t.channel in ("both", "torque")]
    i = len(force) + len(torque) + 12
    effect_cols = {}
    for e in fx_effects:
        for axis in range(6):
            effect_cols[(e.name, axis)] = list(range(i, i + len(e.parameters)))
            i += len(e.parameters)
    return Columns(terms, force, torque, effect_cols, i)


class GramSums:
    """The sums of the flights' Gram matrices discovery combines, added up flight by flight as
    each flight's matrix is made (in the training flights' order: the same additions in the same
    order as summing every flight's matrix at the end, so the same numbers), so that memory holds
    a few sums, not one matrix per flight: the training total; per fold, the training flights
    outside it and the flights in it; and the held-out flights' own matrices (a few)."""

    def __init__(self, folds: list[list[str]], holdout: list[str], scored_only: bool = False):
        """``scored_only``: only each fold's own flights' sums and the held-out flights' (the
        matrices a flight is scored with, not fitted on)."""
        self.fold_of = {f: i for i, fold in enumerate(folds) for f in fold}
        self.holdout = holdout
        self.scored_only = scored_only
        self.train: np.ndarray | None = None
        self.outside: list[np.ndarray | None] = [None] * len(folds)
        self.inside: list[np.ndarray | None] = [None] * len(folds)
        self.held: dict[str, np.ndarray] = {}

    @staticmethod
    def _plus(total: np.ndarray | None, G: np.ndarray) -> np.ndarray:
        return G.copy() if total is None else np.add(total, G, out=total)

    def add(self, flight: str, G: np.ndarray) -> None:
        if flight in self.holdout:
            self.held[flight] = G
            return
        k = self.fold_of[flight]
        if self.scored_only:
            self.inside[k] = self._plus(self.inside[k], G)
            return
        self.train = self._plus(self.train, G)
        for i in range(len(self.outside)):
            if i == k:
                self.inside[i] = self._plus(self.inside[i], G)
            else:
                self.outside[i] = self._plus(self.outside[i], G)

    def training_total(self) -> np.ndarray:
        """The training flights' sum (discovery checks there are at least two of them)."""
        if self.train is None:
            raise ValueError("no training flight was added")
        return self.train

    def fold_grams(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per fold (its training flights' sum, its own flights' sum)."""
        return list(zip(self.outside, self.inside))  # type: ignore[arg-type]

    def own_sums(self) -> list[np.ndarray]:
        """Per fold, its own flights' sum (every fold holds a flight)."""
        if any(G is None for G in self.inside):
            raise ValueError("a fold without flights")
        return [G for G in self.inside if G is not None]

    def held_out(self) -> np.ndarray:
        return sum(self.held[f] for f in self.holdout)  # type: ignore[return-value]

    def transformed(self, T: np.ndarray) -> None:
        """Every sum ``G`` becomes ``Tᵀ G T`` (the Gram matrix of the columns ``Z T``)."""
        def tr(G):
            return None if G is None else T.T @ G @ T

        self.train = tr(self.train)
        self.outside = [tr(G) for G in self.outside]
        self.inside = [tr(G) for G in self.inside]
        self.held = {f: tr(G) for f, G in self.held.items()}

