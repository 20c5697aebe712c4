"""Per-flight sufficient statistics of the linear effects: what every linear fit, fold and
held-out test needs from a flight, without its rows.

**The augmented design.** On a flight's usable samples ``i`` (away from gaps) and channels
``c`` (force x, y, z in N; torque x, y, z in N m; body frame) the augmented row is

    z_ic = [X_ic1 … X_icK | y0_ic | e_ic1 …]

``X_ick`` the smoothed wrench per unit of linear coordinate ``k`` of every linear effect of
the :class:`Layout` (:meth:`quadcore.effects.Effect.basis`, as :meth:`FlightData.basis`),
``y0`` the nominal residual (measured minus the nominal model, with the flight's own thrust
map), and ``e`` extra signals: the unit wrench (and sensitivity reference) of each one-parameter
nonlinear effect of the layout, then any added for a held-out flight (a nonlinear effect's
prediction there). Those effects' fits and predictions come from their per-flight profiles
(:mod:`quadcore.identify.stats.profiles`), stored beside the Gram matrices.
Per block ``b`` of :data:`quadcore.identify.flightdata.BLOCK_S` seconds (the clusters of the held-out
test), per channel, the statistics are the Gram matrix and the sample count

    G_bc = Σ_{i∈b} z_ic z_icᵀ,        n_b = |b|,

with the flight's sensor-noise floor (:func:`quadcore.identify.flightdata.sensor_noise_floor`) and the
Gram matrix of every ``GRAM_STRIDE``-th usable sample (the diagnosis's signature comparison).

**Signals are vectors.** Any per-flight signal that is a combination of the columns is a
vector ``v`` with ``s_ic = z_ic·v``: the nominal residual is ``e_y0``, a linear effect's
prediction ``[θ; 0]``, a residual after a fit ``[-θ; 1]``. Then every sum the fits and tests
take is a quadratic form, summed over blocks and flights as needed:

    Σ_{i∈b} Σ_c w_c s_ic t_ic = Σ_c w_c uᵀ G_bc v            (s = z·u, t = z·v)

* the weighted normal equations of the coordinates ``k ∈ K_e`` of the fitted effects, for a
  target ``y_f = z·v_f`` per flight: ``A = Σ_f Σ_c w_c G_fc[K_e, K_e]``,
  ``b = Σ_f Σ_c w_c G_fc[K_e, :] v_f``, ``θ = A⁻¹ b`` (least squares), and the residual sum of
  squares ``Σ w yᵀy - 2 θᵀb + θᵀAθ``;
* the held-out test's per-block score of a prediction ``p = z·u`` against a residual
  ``r = z·v`` (:mod:`quadcore.identify.evidence`): ``Σ_c w_c uᵀ G_bc v`` and ``Σ_c w_c uᵀ G_bc u``; for a
  prediction ``Xθ`` the block's gain in squared error is ``2 θᵀX_bᵀr_b − θᵀX_bᵀX_bθ``.

So a fleet fit, a fold, a held-out test costs a sum over flights of small matrices: it does
not grow with the rows, and a new flight adds its own statistics only. Stored per flight under
``<root>/stats/flight=<id>/stats.bin`` with the :func:`stats_key` they were computed for.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np

from quadcore import effects as effectlib
from quadcore.effects import Effect, Parameter
from quadcore.identify.binfile import (  # noqa: F401  (the file format, read from here too)
    StatsError,
    decode,
    decode_header,
    encode,
    packed,
    read_array,
    read_file,
    read_if_present,
    require_format,
    stats_path,
    unpacked,
    upper_indices,
    write_file,
)
from quadcore.identify.describe import summaries
from quadcore.identify.describe.summaries import FlightSummary
from quadcore.identify.flightdata import GRAM_STRIDE, SECANT, FlightData, Signals, block_index, flight_data
from quadcore.identify.stats import profiles
from quadcore.physics import decoded_store
from quadcore.physics.vehicle import Vehicle
from quadcore.store import codedigest, store

FORMAT = 3  # bump when what the statistics mean changes: stored ones become stale
Y0 = "y0"


@dataclass(frozen=True)
class Layout:
    """Which column is which: the linear coordinates of each effect (in order), then ``y0``,
    then named extra signals; ``profiled``: the one-parameter nonlinear effects whose profiles
    the statistics hold (:mod:`quadcore.identify.stats.profiles`)."""

    effects: tuple[str, ...]
    sizes: tuple[int, ...]
    extras: tuple[str, ...] = ()
    profiled: tuple[str, ...] = ()

    @property
    def y0(self) -> int:
        return int(sum(self.sizes))

    @property
    def width(self) -> int:
        return self.y0 + 1 + len(self.extras)

    def cols(self, effect: str) -> np.ndarray:
        """Column indices of an effect's linear coordinates."""
        if effect not in self.effects:
            raise StatsError(f"effect {effect!r} is not in these statistics (they hold {', '.join(self.effects)})")
        i = self.effects.index(effect)
        start = int(sum(self.sizes[:i]))
        return np.arange(start, start + self.sizes[i])

    def extra(self, name: str) -> int:
        return self.y0 + 1 + self.extras.index(name)

    def with_extras(self, names: Sequence[str]) -> Layout:
        """This layout with more extra columns after its own."""
        return Layout(self.effects, self.sizes, self.extras + tuple(names), self.profiled)

    def unit(self, index: int) -> np.ndarray:
        v = np.zeros(self.width)
        v[index] = 1.0
        return v

    def target(self) -> np.ndarray:
        """The nominal residual ``y0`` as a signal vector."""
        return self.unit(self.y0)

    def coefficients(self, effect: Effect, params: dict, vehicle: Vehicle) -> np.ndarray:
        """The signal vector of a linear effect's prediction at ``params``: its linear coordinates
        (:meth:`Effect.to_linear`) in its columns."""
        if not effect.linear:
            raise StatsError(f"{effect.name} is nonlinear: its prediction is no combination of columns")
        v = np.zeros(self.width)
        v[self.cols(effect.name)] = effect.to_linear({**effect.defaults(), **params}, vehicle)
        return v

    def pad(self, v: np.ndarray) -> np.ndarray:
        """A vector of a layout with fewer extras, in this one (the extras it lacks are zero)."""
        out = np.zeros(self.width)
        out[: len(v)] = v
        return out


def layout_of(effects: Iterable[Effect]) -> Layout:
    """The layout of the linear ones of ``effects`` and of the one-parameter nonlinear ones
    (profiled, with their fixed extra columns), in the order given."""
    effects = list(effects)
    lin = [e for e in effects if e.linear]
    prof = [e for e in effects if profiles.profiled(e)]
    return Layout(tuple(e.name for e in lin), tuple(len(e.parameters) for e in lin),
                  tuple(c for e in prof for c in profiles.fixed_columns(e)), tuple(e.name for e in prof))


def library_layout() -> Layout:
    """Every linear and one-parameter nonlinear effect known in this process (built-in, then loaded plugins)."""
    return layout_of(effectlib.registry().values())


def spec_layout(spec) -> Layout:
    """What the per-flight asset stores for a :class:`quadcore.identify.model.ModelSpec`: every
    built-in linear effect, then the linear plugin effects the spec's model uses, and the
    profiles of the one-parameter nonlinear ones of both (:mod:`quadcore.identify.stats.profiles`). Decided by the
    spec alone, not by the plugins this process happens to have loaded (a long-lived process
    keeps every plugin it ever loaded); a plugin candidate outside the model is computed from
    rows where needed (:func:`for_flights`)."""
    builtin = effectlib.builtin_names()
    names = [*builtin, *(n for n in spec.effects if n not in builtin)]
    return layout_of(effectlib.get(n) for n in names)


@dataclass(frozen=True)
class FlightStats:
    """One flight's statistics (see the module): ``total`` (6, W, W) the flight's Gram matrix,
    ``rows`` (B,) per 1 s block, ``strided`` (6, W, W), ``noise`` (6,) the sensor-noise floor
    RMS, the logged battery voltage's spread and median (a stuck voltage log), and the per-block
    Gram matrices (B, 6, W, W) :attr:`gram`, given or read when first asked for (``blocks``: a
    function that returns them): a fit needs only the totals, a held-out test the blocks."""

    flight: str
    layout: Layout
    key: str
    total: np.ndarray
    rows: np.ndarray
    strided: np.ndarray
    noise: np.ndarray
    vbat_std_V: float
    vbat_median_V: float
    blocks_source: Callable[[], np.ndarray]
    source: str = ""  # the SHA-256 of the log the decoded table came from (stale once it is re-decoded)
    profiles: profiles.Profiles | None = None  # of the layout's profiled effects
    # the flight's FlightSummary (quadcore.identify.describe.summaries) when there is one to ask for: the
    # stored ones are read when asked (None when missing or stale), not held
    summary_source: Callable[[], FlightSummary | None] | None = None

    def summary(self) -> FlightSummary | None:
        """The flight's :class:`quadcore.identify.describe.summaries.FlightSummary`, or None."""
        return self.summary_source() if self.summary_source is not None else None

    @cached_property
    def gram(self) -> np.ndarray:
        """(B, 6, W, W) the Gram matrix of each block."""
        return self.blocks_source()

    @property
    def n(self) -> int:
        return int(self.rows.sum())

    @property
    def blocks(self) -> int:
        return len(self.rows)

    # --- the Flight protocol (quadcore.identify.flightdata.Flight): signals are vectors over the columns

    def predict(self, effects: Sequence[Effect], params: Mapping[str, dict], vehicle: Vehicle) -> np.ndarray:
        """The signal vector of the linear ``effects``' summed prediction at ``params``."""
        return prediction(list(effects), dict(params), self, vehicle)

    def sum_of_squares(self, v: np.ndarray) -> np.ndarray:
        """(6,) per channel: the sum of squares of the signal ``z·v`` over the flight."""
        return channel_sums(self.total, v, v)

    def unit_signal(self, effect: Effect, param: Parameter, vehicle: Vehicle) -> np.ndarray:
        """The unit wrench (:func:`quadcore.identify.flightdata.unit_wrench`) as a signal vector: of a
        linear effect from its coordinates, of a profiled one its stored column."""
        if effect.linear:
            return unit_vector(effect, param, self, vehicle, SECANT)
        return self.layout.unit(self.layout.extra(f"unit:{effect.name}:{param.name}"))

    def reference_ss(self, effect: Effect, vehicle: Vehicle) -> float:
        """Energy of the effect's prediction at its sensitivity reference over the flight."""
        ref = {**effect.defaults(), **effect.sensitivity_reference}
        v = (self.layout.coefficients(effect, ref, vehicle) if effect.linear
             else self.layout.unit(self.layout.extra(f"ref:{effect.name}")))
        return float(self.sum_of_squares(v).sum())

    def after_blocks(self, k: int) -> FlightStats:
        """The statistics without the first ``k`` blocks."""
        if k <= 0:
            return self
        gram = self.gram[k:]
        return replace(self, total=gram.sum(axis=0), rows=self.rows[k:], blocks_source=lambda: gram)

    def block_channel_sums(self, pairs: Sequence[tuple[Signals, Signals]]) -> list[np.ndarray]:
        """Per pair ``(a, b)`` of signals (flight -> vector): (blocks, 6) ``a_fᵀ G_bc b_f`` per block
        and channel. The Gram matrices are read once for all the pairs: ``G [b, b', ...]`` (one
        BLAS product with a column per distinct right-hand signal), then the dots with the
        left-hand ones. Reading ``G`` is what costs (a thousand flights' blocks are ~230 MB), so
        pairs sharing ``b`` cost one pass (run it under :func:`quadcore.identify.flightdata.one_blas_thread`)."""
        rights = list({id(b): b for _, b in pairs}.values())
        column = {id(b): k for k, b in enumerate(rights)}
        G = np.ascontiguousarray(self.gram)
        width = G.shape[-1]
        V = np.stack([b[self.flight] for b in rights], axis=1)
        GV = (G.reshape(-1, width) @ V).reshape(*G.shape[:-1], len(rights))
        return [GV[..., column[id(b)]] @ a[self.flight] for a, b in pairs]

    def basis_columns(self, effect: Effect, vehicle: Vehicle) -> list[np.ndarray]:
        """The unit vectors of a linear effect's coordinates."""
        return [self.layout.unit(i) for i in self.layout.cols(effect.name)]

    def strided_grams(self, columns: Sequence[np.ndarray], w: np.ndarray,
                      groups: Mapping[str, slice]) -> dict[str, np.ndarray]:
        """Per channel group: ``Tᵀ (Σ_c w_c G_c) T`` of the columns ``T`` (signal vectors), ``G`` the
        strided Gram matrix (every ``GRAM_STRIDE``-th usable sample)."""
        T = np.stack(columns, axis=1)
        return {ch: T.T @ np.tensordot(w[sl], self.strided[sl], axes=1) @ T for ch, sl in groups.items()}


def from_blocks(flight: str, layout: Layout, key: str, gram: np.ndarray, rows: np.ndarray, strided: np.ndarray,
                noise: np.ndarray, vbat_std_V: float, vbat_median_V: float) -> FlightStats:
    """Statistics from their per-block Gram matrices (``total`` their sum)."""
    return FlightStats(flight, layout, key, gram.sum(axis=0), rows, strided, noise, vbat_std_V, vbat_median_V,
                       lambda: gram)


def design_rows(fd, vehicle: Vehicle, layout: Layout, extras: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """(n, 6, W) the augmented design of a flight (all samples): bases, ``y0``, extras."""
    extras = extras or {}
    parts = [fd.basis(effectlib.get(name), vehicle) for name in layout.effects]
    y0 = np.concatenate([fd.r_f, fd.r_tau], axis=1)[:, :, None]
    parts += [y0] + [np.asarray(extras[name])[:, :, None] for name in layout.extras]
    return np.concatenate(parts, axis=2)


def extra_column(fd, vehicle: Vehicle, layout: Layout, columns: np.ndarray,
                 extras: Mapping[str, np.ndarray] | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """``sums(e)``: the row of the flight's augmented Gram matrix that an extra column ``e`` ((n, 6)
    on every sample: a nonlinear effect's prediction, say) adds, on the layout's ``columns`` (effects'
    coordinates, ``y0``, and extras whose rows ``extras`` gives by name): per channel ``c``,
    ``[Σ_i z_ic[columns] e_ic | Σ_i e_ic²]`` over the usable samples, (6, len(columns) + 1), the
    columns in increasing order. Those columns of the design (:func:`design_rows`) are made once,
    here, from the flight's rows and kept for every ``e`` asked for; the sums are the profiles'
    (:func:`quadcore.identify.stats.profiles.sums`)."""
    want = sorted({int(c) for c in columns})
    extras = extras or {}
    missing = [n for n in layout.extras if layout.extra(n) in want and n not in extras]
    if missing:
        raise StatsError(f"{fd.flight}: the extra column(s) {', '.join(missing)} of the statistics have no rows here")
    parts = []  # the design's columns in the layout's order (only the bases asked for are made)
    for name in layout.effects:
        cols = layout.cols(name)
        keep = [j for j, c in enumerate(cols) if c in want]
        if keep:
            parts.append(fd.basis(effectlib.get(name), vehicle)[:, :, keep])
    if layout.y0 in want:
        parts.append(np.concatenate([fd.r_f, fd.r_tau], axis=1)[:, :, None])
    parts += [np.asarray(extras[n])[:, :, None] for n in layout.extras if layout.extra(n) in want]
    Z = np.concatenate(parts, axis=2)[fd.mask] if parts else np.zeros((fd.n, 6, 0))
    return lambda e: profiles.sums(np.asarray(e)[fd.mask][:, :, None], Z)[0]


def flight_stats(fd, vehicle: Vehicle, layout: Layout, key: str = "",
                 extras: dict[str, np.ndarray] | None = None) -> FlightStats:
    """The statistics of a :class:`quadcore.identify.flightdata.FlightData` (its rows read once),
    with the profiles of the layout's profiled effects (their fixed columns computed here)."""
    extras = {**profiles.fixed_signals(layout.profiled, fd, vehicle), **(extras or {})}
    return _stats_of_rows(fd, vehicle, layout, key, design_rows(fd, vehicle, layout, extras))


def _stats_of_rows(fd, vehicle: Vehicle, layout: Layout, key: str, rows: np.ndarray) -> FlightStats:
    """:func:`flight_stats` from the flight's augmented design ``rows`` (n, 6, W) on every sample."""
    Z = rows[fd.mask]
    blocks = block_index(fd.state.t_s[fd.mask])
    B = int(blocks.max()) + 1 if len(blocks) else 0
    starts = np.searchsorted(blocks, np.arange(B + 1))  # blocks are runs of consecutive samples
    gram = np.stack([np.einsum("nci,ncj->cij", Z[a:b], Z[a:b]) for a, b in zip(starts[:-1], starts[1:])]) \
        if B else np.zeros((0, 6, layout.width, layout.width))
    thin = Z[::GRAM_STRIDE]
    s = from_blocks(fd.flight, layout, key, gram, np.diff(starts), np.einsum("nci,ncj->cij", thin, thin),
                    np.asarray(fd.noise, dtype=float), fd.vbat_std_V, fd.vbat_median_V)
    if not layout.profiled:
        return s
    return replace(s, profiles=profiles.compute(layout.profiled, fd, vehicle, Z, starts, GRAM_STRIDE))


# ---------------------------------------------------------------------------------------
# Quadratic forms
# ---------------------------------------------------------------------------------------

def channel_sums(G: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``uᵀ G_c v`` per channel (and per block, for a (B, 6, W, W) ``G``): ``G v`` as one
    matrix-vector product over all the matrices' rows (BLAS: 3x the speed of a three-operand
    einsum on a flight's blocks), then its dot with ``u``."""
    width = G.shape[-1]
    return (np.ascontiguousarray(G).reshape(-1, width) @ v).reshape(G.shape[:-1]) @ u


def sum_of_squares(s: FlightStats, v: np.ndarray) -> np.ndarray:
    """(6,) per channel: the sum of squares of the signal ``z·v`` over the flight."""
    return channel_sums(s.total, v, v)


def one_layout(stats: Sequence[FlightStats]) -> bool:
    """Whether the flights' statistics share one layout (their vectors then stack)."""
    return bool(stats) and all(s.layout == stats[0].layout for s in stats)


def stacked_totals(stats: Sequence[FlightStats]) -> np.ndarray:
    """(F, 6, W, W) the flights' whole-flight Gram matrices (one layout; ~23 MB at 1,000 flights)."""
    return np.stack([s.total for s in stats])


def normal_equations(stats: Sequence[FlightStats], targets: Sequence[np.ndarray], w: np.ndarray,
                     cols_of: Callable[[Layout], np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """``(A, b, yy)`` of the weighted least squares for the columns ``cols_of(layout)`` of each
    flight's design against its target ``z·v_f``: ``A = Σ_f (Σ_c w_c G_fc)[cols, cols]``,
    ``b = Σ_f (Σ_c w_c G_fc)[cols] v_f``, ``yy = Σ_f v_fᵀ (Σ_c w_c G_fc) v_f``. Flights sharing
    one layout in one pass over their stacked totals, others one at a time."""
    if one_layout(stats):
        cols, T, V = cols_of(stats[0].layout), stacked_totals(stats), np.stack(targets)
        TV = np.einsum("fcij,fj->fci", T, V)
        return (np.tensordot(w, T.sum(axis=0), axes=1)[np.ix_(cols, cols)], np.einsum("c,fci->i", w, TV)[cols],
                float(np.einsum("c,fci,fi->", w, TV, V)))
    k = len(cols_of(stats[0].layout)) if stats else 0
    A, b, yy = np.zeros((k, k)), np.zeros(k), 0.0
    for s, v in zip(stats, targets):  # each flight in its own layout
        cols = cols_of(s.layout)
        Gw = np.tensordot(w, s.total, axes=1)  # Σ_c w_c G_c
        A += Gw[np.ix_(cols, cols)]
        b += Gw[cols] @ v
        yy += float(v @ Gw @ v)
    return A, b, yy


def prediction(effects: list[Effect], params: dict[str, dict[str, float]], s: FlightStats,
               vehicle: Vehicle) -> np.ndarray:
    """The signal vector of the linear ``effects``' summed prediction at ``params``."""
    return sum((s.layout.coefficients(e, params[e.name], vehicle) for e in effects), np.zeros(s.layout.width))


def predicted(effects: list[Effect], params: Mapping[str, dict[str, float]], s: FlightStats,
              vehicle: Vehicle) -> tuple[FlightStats, np.ndarray]:
    """The summed prediction of ``effects`` at ``params`` on a flight's statistics: the linear
    effects' coordinates, and each profiled nonlinear effect's prediction at its value as an extra
    column ``pred:<effect>`` from its profile (:func:`quadcore.identify.stats.profiles.with_predictions`):
    the statistics grown by those columns (in the order of ``effects``) and the signal vector there."""
    values = {e.name: params[e.name][e.parameters[0].name] for e in effects if not e.linear}
    grown = profiles.with_predictions(s, values, signals=list(values)) if values else s
    v = prediction([e for e in effects if e.linear], dict(params), grown, vehicle)
    for name in values:
        v[grown.layout.extra(f"pred:{name}")] = 1.0
    return grown, v


def unit_vector(effect: Effect, param, s: FlightStats, vehicle: Vehicle, secant: float) -> np.ndarray:
    """:func:`quadcore.identify.flightdata.unit_wrench` of a linear effect as a signal vector: the secant
    of its prediction over ``secant`` of the parameter's range."""
    step = secant * (param.upper - param.lower)
    params = {**effect.defaults(), **effect.sensitivity_reference}
    if param.name in effect.sensitivity_reference:
        params[param.name] = param.default
    base = s.layout.coefficients(effect, params, vehicle)
    params[param.name] += step if param.default + step <= param.upper else -step
    return (s.layout.coefficients(effect, params, vehicle) - base) / step


def signal_rows(fd, vehicle: Vehicle, layout: Layout, v: np.ndarray,
                extras: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """(n, 6) the signal ``z·v`` on every sample of a flight (its rows read)."""
    used = [name for name in layout.effects if np.any(v[layout.cols(name)])]
    out = np.concatenate([fd.r_f, fd.r_tau], axis=1) * v[layout.y0]
    for name in used:
        out = out + fd.basis(effectlib.get(name), vehicle) @ v[layout.cols(name)]
    for name in layout.extras:
        if v[layout.extra(name)]:
            out = out + (extras or {})[name] * v[layout.extra(name)]
    return out


def compute(spec, flight: str, decoded, layout: Layout, source: str = "", summarize: bool = False,
            fd: FlightData | None = None) -> FlightStats:
    """A flight's statistics from its decoded table, for a :class:`quadcore.identify.model.ModelSpec`:
    the state and ``y0`` with the flight's own thrust map, the bases on the model's vehicle.
    ``source``: the SHA-256 of the log the table was decoded from (its provenance); ``summarize``:
    with the flight's :class:`quadcore.identify.describe.summaries.FlightSummary` (what the diagnosis
    describes the evaluated flights from); ``fd``: the table's
    :func:`quadcore.identify.flightdata.flight_data` when the caller has it (its bases are cached there)."""
    fd = fd if fd is not None else flight_data(flight, decoded, spec.vehicle_for(flight))
    extras = profiles.fixed_signals(layout.profiled, fd, spec.vehicle)
    rows = design_rows(fd, spec.vehicle, layout, extras)
    s = _stats_of_rows(fd, spec.vehicle, layout, stats_key(spec.vehicle, spec.vehicle_for(flight), layout), rows)
    if not summarize:
        return replace(s, source=source)
    # the columns of a linear model's residual: the effects' coordinates and y0, not the extras
    summary = summaries.summarize(fd, spec.vehicle, rows[:, :, : layout.y0 + 1])
    return replace(s, source=source, summary_source=lambda: summary)


def for_flights(spec, decoded, flights: Iterable[str], layout: Layout,
                stored: Callable[[str], FlightStats | None] | None = None) -> dict[str, FlightStats]:
    """Statistics of ``flights`` holding ``layout``'s effects and profiles: the stored ones
    (``stored(flight)``, None when missing or stale), else computed from the decoded table (its
    rows read once)."""
    out = {}
    for f in flights:
        s = stored(f) if stored else None
        if s is None or not (set(layout.effects) <= set(s.layout.effects)
                             and set(layout.profiled) <= set(s.layout.profiled)):
            s = compute(spec, f, decoded[f], layout)
        out[f] = s
    return out


# ---------------------------------------------------------------------------------------
# Identity and storage
# ---------------------------------------------------------------------------------------

# The code a flight's statistics come from besides the effects' own modules: the state and the
# nominal residual (dynamics, residuals, signals), the rotors' thrust from the vehicle's thrust map,
# its allocation and thrust hold (vehicle), the usable mask, noise floor and voltage
# (flightdata.flight_data), the blocks and strides (settings.STATISTICS), the bases' helpers, this module and the
# summaries' (their bins, windows and spectra: summaries, regimes, spectrum).
CODE_MODULES = ("quadcore.identify.settings", "quadcore.physics.dynamics", "quadcore.physics.residuals",
                "quadcore.physics.signals", "quadcore.physics.rotations", "quadcore.physics.vehicle",
                "quadcore.identify.flightdata",
                "quadcore.identify.binfile",
                "quadcore.identify.evidence",
                "quadcore.effects.base", "quadcore.identify.stats.sufficient", "quadcore.identify.stats.profiles",
                "quadcore.identify.describe.summaries", "quadcore.identify.describe.regimes",
                "quadcore.identify.describe.spectrum")


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """A digest of the source of :data:`CODE_MODULES` (once per process): statistics stored by
    other code are stale. The decoder's code is not in it: the statistics name the decoded table
    they were made from, decoder included (``source``, :func:`decoded_source`)."""
    return codedigest.modules_digest(CODE_MODULES)


@functools.cache
def source_digest(effect_class: type) -> str:
    """A digest of the code an effect class's predictions come from (once per class and process:
    reading the source costs milliseconds, and a key is asked for every flight): the whole module
    it is defined in, as its wrench calls the module's own functions (``motor_lag``'s
    ``first_order_lag``, ``thrust_delay``'s ``delayed``), its code without comments and docstrings
    (:func:`quadcore.store.codedigest.code_of`, as every digest of the project's code); for a plugin
    effect, the SHA-256 of the module file's bytes that ran (:func:`quadcore.effects.plugin_source`:
    its module is in no ``sys.modules``, where ``inspect`` finds none and every plugin had the digest
    ``unknown``, so an edited plugin left statistics made by the old one current)."""
    plugin = effectlib.plugin_source(str(getattr(effect_class, "name", "")))
    module = sys.modules.get(effect_class.__module__)
    try:
        if plugin is not None and module is None:
            code = plugin.sha256.encode()
        else:
            code = codedigest.code_of(inspect.getsource(module if module is not None else effect_class).encode())
        return hashlib.sha256(code).hexdigest()[:16]
    except (OSError, TypeError):
        return "unknown"


def _content(vehicle: Vehicle) -> dict:
    return {k: v for k, v in asdict(vehicle).items() if k != "source"}


def stats_key(vehicle: Vehicle, flight_vehicle: Vehicle, layout: Layout) -> str:
    """What the statistics were computed for: the model's vehicle (the bases), the flight's own
    (its session's thrust map: the state and ``y0``), the layout, the source of each effect
    in it and the code that computes them (:func:`code_digest`). Stored statistics with another
    key are stale."""
    content = {"format": FORMAT, "code": code_digest(), "layout": asdict(layout), "vehicle": _content(vehicle),
               "flight_vehicle": _content(flight_vehicle),
               "effects": {n: source_digest(type(effectlib.get(n))) for n in (*layout.effects, *layout.profiled)}}
    text = json.dumps(content, sort_keys=True, default=lambda a: np.asarray(a).tolist())
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save(s: FlightStats, root: Any) -> Any:
    """Write a flight's statistics under the data root (atomically; an object store too), its
    summary first (:func:`quadcore.identify.describe.summaries.save`, when it has one). The symmetric
    matrices are stored as their upper triangles."""
    summary = s.summary()
    if summary is not None:
        summaries.save(summary, root, s.key, s.source)
    header = {"flight": s.flight, "key": s.key, "layout": asdict(s.layout), "format": FORMAT,
              "vbat_std_V": s.vbat_std_V, "vbat_median_V": s.vbat_median_V, "source": s.source}
    return write_file(stats_path(root, s.flight), header,
                      {"total": packed(s.total), "rows": s.rows, "strided": packed(s.strided),
                       "noise": s.noise, "gram": packed(s.gram), **profiles.arrays(s.profiles)})


def load(root: Any, flight: str) -> FlightStats:
    """A flight's stored statistics (the per-block matrices unpacked when first asked for);
    :class:`StatsError` when the file is not one."""
    path = stats_path(root, flight)
    raw = read_file(path)
    try:
        header, array = decode(raw)
        require_format(header, FORMAT)
        lay = header["layout"]
        layout = Layout(tuple(lay["effects"]), tuple(lay["sizes"]), tuple(lay["extras"]), tuple(lay["profiled"]))
        width = layout.width
        key, source = header["key"], str(header.get("source", ""))
        return FlightStats(header["flight"], layout, key, unpacked(array("total"), width), array("rows"),
                           unpacked(array("strided"), width), array("noise"), float(header["vbat_std_V"]),
                           float(header["vbat_median_V"]), lambda: unpacked(array("gram"), width), source,
                           profiles.from_arrays(layout, array), lambda: summaries.load(root, flight, key, source))
    except (ValueError, KeyError, TypeError) as exc:
        raise StatsError(f"{path}: not a statistics file ({exc})") from None


def current_key(spec, flight: str) -> str:
    """The key a flight's stored statistics must carry for ``spec`` as it is now (the model's
    vehicle, the flight's session thrust map, the linear effects of :func:`spec_layout`)."""
    return stats_key(spec.vehicle, spec.vehicle_for(flight), spec_layout(spec))


def compute_current(spec, flight: str, decoded, source: str = "", fd: FlightData | None = None) -> FlightStats:
    """What the per-flight asset stores: the statistics of the linear effects of
    :func:`spec_layout`, with the flight's summary (``source`` and ``fd`` as for :func:`compute`)."""
    return compute(spec, flight, decoded, spec_layout(spec), source, summarize=True, fd=fd)


def decoded_source(root: Any, flight: str) -> str | None:
    """What the flight's main table under the data root was made from: the SHA-256 of its log and
    the digest of the decoder's code (:attr:`quadcore.logs.flight.Provenance.decoded_as`; None when
    it is not decoded). Everything kept from a decoded table is keyed by it (``stats.bin``,
    ``library.bin``, ``rates.bin``): a log decoded again, from other bytes or by another decoder,
    makes them stale."""
    provenance = decoded_store.recorded_provenance(root, store.MAIN_EVENT, flight)
    return provenance.decoded_as if provenance is not None else None


def stored(root: Any, spec) -> Callable[[str], FlightStats | None]:
    """``flight -> FlightStats | None``: a flight's statistics under the data root if they are
    current for ``spec`` (:func:`current_key`) and were made from the flight's decoded table as
    it is now (a log decoded again from other bytes makes them stale); None when missing or stale."""
    def current(flight: str) -> FlightStats | None:
        s = load_current(root, flight, current_key(spec, flight))
        return s if s is not None and s.source == decoded_source(root, flight) else None

    return current


def load_current(root: Any, flight: str, key: str) -> FlightStats | None:
    """A flight's stored statistics if they were computed for ``key``, else None."""
    s = read_if_present(stats_path(root, flight), lambda: load(root, flight))
    return s if s is not None and s.key == key else None
