"""Per-flight profiles of the one-parameter nonlinear effects: their search and held-out test
from a flight's statistics, without its rows.

A nonlinear effect ``e`` with one parameter ``v`` (``motor_lag``'s τ, ``thrust_delay``'s t_d, a
plugin's) predicts ``p_ic(v)`` (smoothed force and torque, body frame, as
:func:`quadcore.identify.flightdata.prediction`). Every sum its fit and its held-out test take of
``p`` against a signal ``s = z·u`` of the flight's statistics (:mod:`quadcore.identify.stats.sufficient`)
is ``Σ_i p_ic(v) z_ic·u`` or ``Σ_i p_ic(v)²``. So, per flight, on a fixed grid ``v_g`` of the
parameter (:func:`profile_grid`: the search's 17 points, :func:`search_grid`, and
``GRID_DENSITY - 1`` geometric points between each two), the profile holds per channel ``c``

    P_gc = [Σ_i p_ic(v_g) z_ic  |  Σ_i p_ic(v_g)²]          (W + 1 numbers)

per 1 s block (float32: the held-out test's clusters), over the flight (float64: the fits), and
over every ``GRAM_STRIDE``-th sample (the signature comparison); and between two profiled
effects ``a``, ``b`` the cross sums ``Σ_i p_a(v_g)·p_b(v_h)`` per channel over those strided
samples (float32), all the signature comparison asks of two predictions, and over every usable
sample (float64, ``cross_total``, with each effect against itself, ``a = b``): what a residual
that holds a model's profiled prediction asks of it and of a profiled candidate. The columns ``z``
include, per profiled effect, its unit wrench (:func:`quadcore.identify.flightdata.unit_wrench`,
``unit:<effect>:<parameter>``) and its prediction at the sensitivity reference (``ref:<effect>``)
when it has one: fixed signals, so the detection limits take them as any other column.

**Between grid points** a sum is interpolated linearly in its grid values (:func:`weights`): a
not-a-knot cubic spline in ``log(v - lower)`` over the grid's points above the lower bound,
linear in ``v`` between the lower bound and the first point above it (``motor_lag`` jumps there:
any τ > 0 delays the thrust by a whole sample). So, with weights ``ω(v)``, the fit's objective
(:func:`quadcore.identify.fit.fit_effects`, weights ``w_c``, residual ``r_f = z·u_f``) is

    J(v) = Σ_f Σ_c w_c [u_fᵀ G_fc u_f - 2 ω(v)·(P_f·c[:W] u_f) + ω(v)·P_f·c[W]],

exact on the grid (the search's grid stage finds the row search's grid point), a smooth
interpolant between (the bounded Brent refinement and the profile interval of the standard
error run on it); beside linear effects, these are solved inside it
(:func:`quadcore.identify.fit.profiled.profiled_fit`). A held-out
prediction at the fitted ``v`` is an extra column whose sums with every other column are
``ω(v)·P`` per block: exact on a grid point (to float32 rounding per block), interpolated between
as the search's objective is; the unit wrench and the reference are exact (stored columns).
A cross between two profiled effects' predictions over the flight is ``ω_a·C_ab·ω_b`` of the
whole-flight cross sums, per block shared out in proportion to ``sqrt(aa_b bb_b)`` (per-block
cross sums are not held: the comparison of two candidates' predictions cancels their cross
exactly, and a candidate against a model's prediction reads it only summed over the blocks).

**A model's prediction** (a model of linear effects and one profiled effect, diagnosed from
statistics) is such a column too, subtracted in its residual; its own energy is then that of the
interpolated signal ``p̃ = Σ_g ω_g p(v_g)``, ``ω·C_aa·ω`` (``signals`` of :func:`with_predictions`),
not the interpolated energy ``ω·P[W]``: the residual ``y - p̃`` is small beside ``y`` and ``p̃``, and
the interpolated energy's error (~1e-5 of ``Σ p²``) would be 1-2 % of the residual's energy on a
simulated lag at the noise floor, the signal's ~1e-4 (the residual's Gram matrix stays one).
The fits' objective keeps the interpolated energy (:func:`quadcore.identify.fit.profiled.profiled_fit`).
Where such a residual is wanted on rows (its regime tables, the search's extra columns beside it),
its column's rows are ``p̃`` itself (:func:`interpolated_prediction`), not ``p(v)``: the residual on
rows is then the one its statistics hold (docs/diagnosis.md figures the difference).

**Accuracy** (``benchmarks/bench_profiles.py``, all flights fitted at once): for ``motor_lag``
the profile search lands within 0.02 of the row search's own tolerance (``xatol``, 5e-4 of the
span) of where it does, its standard error within 4 %. A delay's row objective ripples with the
sample period (``thrust_delay`` is linear between samples, so it smooths the thrust most
half-way between them; on the 19 real flights the ripple is a third of the objective's rise
over ±5 ms): the grid does not resolve it, and the profile search finds the minimum of the
smooth curve through the exact grid values, up to 0.6 sample from the row search's trough
(0.05 sample on simulated flights), with the smooth curve's larger standard error.

**Size:** per effect, ``G (6 (W + 1))`` numbers per block (float32) and twice that over the
flight and strided (float64); with the library's 2 profiled effects and 22 columns, 0.35 MB per
10 s of flight and 0.17 MB a flight beside the Gram matrices; the whole-flight cross sums
(``cross_total``: each of the 2 effects with itself and the pair, (32, 32, 6) float64) add 147 kB a
flight (measured: a 5 s simulated flight's ``stats.bin`` 620 kB with them).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache, partial
from typing import TYPE_CHECKING

import numpy as np

from quadcore import effects as effectlib
from quadcore.effects import Effect, Parameter
from quadcore.identify.binfile import StatsError
from quadcore.identify.flightdata import FlightData, prediction, unit_wrench
from quadcore.physics.vehicle import Vehicle

if TYPE_CHECKING:
    from quadcore.identify.stats.sufficient import FlightStats, Layout

GRID_DENSITY = 2  # intervals of the profile's grid per interval of the search's grid


def search_grid(lower: float, upper: float) -> np.ndarray:
    """The one-parameter search's grid (:func:`quadcore.identify.fit.solve.scalar_minimum`): the lower
    bound and 16 geometric points up to the upper one; the profiles hold every flight's sums on it."""
    span = upper - lower
    return np.unique(np.concatenate([[lower], lower + span * np.geomspace(1e-3, 1.0, 16)]))


def profiled(effect: Effect) -> bool:
    """Whether an effect's fit and held-out test can come from profiles: nonlinear, one parameter."""
    return not effect.linear and len(effect.parameters) == 1


@lru_cache(maxsize=64)
def profile_grid(lower: float, upper: float) -> np.ndarray:
    """The search's grid with ``GRID_DENSITY - 1`` geometric points between each two above the
    lower bound (the search's points kept bit for bit)."""
    base = search_grid(lower, upper)
    between = [lower + (a - lower) * ((b - lower) / (a - lower)) ** (np.arange(1, GRID_DENSITY) / GRID_DENSITY)
               for a, b in zip(base[1:-1], base[2:])]
    return np.unique(np.concatenate([base, *between]))


@lru_cache(maxsize=64)
def _spline(lower: float, upper: float):
    """The not-a-knot cubic spline of each grid point's unit vector in ``log(v - lower)``."""
    from scipy.interpolate import CubicSpline  # imported when first needed: 0.4 s at start-up otherwise

    grid = profile_grid(lower, upper)
    return CubicSpline(np.log(grid[1:] - lower), np.eye(len(grid) - 1), axis=0)


def weights(lower: float, upper: float, v: float) -> np.ndarray:
    """(G,) interpolation weights of the profile's grid at ``v`` (see the module): any sum at
    ``v`` is ``weights · (its grid values)``; on a grid point, that point's unit vector."""
    grid = profile_grid(lower, upper)
    v = float(min(max(v, lower), upper))
    out = np.zeros(len(grid))
    hit = np.flatnonzero(grid == v)
    if len(hit):
        out[hit[0]] = 1.0
    elif v < grid[1]:
        t = (v - grid[0]) / (grid[1] - grid[0])
        out[0], out[1] = 1.0 - t, t
    else:
        out[1:] = _spline(lower, upper)(np.log(v - lower))
    return out


def fixed_columns(effect: Effect) -> list[str]:
    """The extra columns a profiled effect adds to its flights' statistics."""
    names = [f"unit:{effect.name}:{p.name}" for p in effect.parameters]
    return names + ([f"ref:{effect.name}"] if effect.sensitivity_reference else [])


def fixed_signals(names: Sequence[str], fd: FlightData, vehicle: Vehicle) -> dict[str, np.ndarray]:
    """(n, 6) the fixed columns of the profiled effects ``names`` on a flight."""
    out = {}
    for name in names:
        e = effectlib.get(name)
        out.update({f"unit:{name}:{p.name}": unit_wrench(e, p, fd, vehicle) for p in e.parameters})
        if e.sensitivity_reference:
            out[f"ref:{name}"] = prediction(e, {**e.defaults(), **e.sensitivity_reference}, fd, vehicle)
    return out


def interpolated_prediction(effect: Effect, v: float, fd: FlightData, vehicle: Vehicle) -> np.ndarray:
    """(n, 6) on a flight's rows, the column ``pred:<effect>`` that :func:`with_predictions` adds
    to its statistics at ``v``: the interpolated signal ``p̃ = Σ_g ω_g(v) p(v_g)`` over the
    profile's grid (see the module), whose sums with every column, and own energy as a model's
    signal, are those the statistics hold; the exact prediction ``p(v)`` only on a grid point."""
    (p,) = effect.parameters
    w = weights(p.lower, p.upper, v)
    out = np.zeros((fd.state.n, 6))
    for g in np.flatnonzero(w):
        out += w[g] * prediction(effect, {**effect.defaults(), p.name: float(profile_grid(p.lower, p.upper)[g])},
                                 fd, vehicle)
    return out


@dataclass(frozen=True)
class Profile:
    """One effect's profile on one flight (see the module): ``total`` and ``strided``
    (G, 6, W + 1), the per-block ones (B, G, 6, W + 1) :attr:`blocks` read when first asked for."""

    effect: str
    total: np.ndarray
    strided: np.ndarray
    blocks_source: Callable[[], np.ndarray]

    @cached_property
    def blocks(self) -> np.ndarray:
        return self.blocks_source()

    @property
    def parameter(self) -> Parameter:
        """The effect's one parameter (the profile's grid spans its bounds)."""
        return effectlib.get(self.effect).parameters[0]

    def at(self, v: float) -> np.ndarray:
        """(G,) the interpolation weights at ``v``."""
        p = self.parameter
        return weights(p.lower, p.upper, v)


@dataclass(frozen=True)
class Profiles:
    """A flight's profiles, by effect, and the cross sums of each pair of them, by ``(a, b)`` in
    the layout's order, (Ga, Gb, 6): ``cross`` over the strided samples (float32), ``cross_total``
    over every usable sample (float64: a residual that holds one profiled effect's prediction,
    a model's, against another's profile); ``thinning``: the usable samples over the strided ones."""

    by_effect: Mapping[str, Profile]
    cross: Mapping[tuple[str, str], np.ndarray]
    thinning: float
    cross_total: Mapping[tuple[str, str], np.ndarray]


def compute(names: Sequence[str], fd: FlightData, vehicle: Vehicle, Z: np.ndarray, starts: np.ndarray,
            stride: int) -> Profiles:
    """The profiles of ``names`` on a flight: ``Z`` (m, 6, W) its augmented design on the usable
    samples, ``starts`` (B + 1,) where each block starts in them."""
    preds, by_effect = {}, {}
    for name in names:
        e = effectlib.get(name)
        (p,) = e.parameters
        P = np.stack([prediction(e, {**e.defaults(), p.name: float(v)}, fd, vehicle)[fd.mask]
                      for v in profile_grid(p.lower, p.upper)], axis=2)  # (m, 6, G)
        preds[name] = P
        blocks = np.stack([sums(P[a:b], Z[a:b]) for a, b in zip(starts[:-1], starts[1:])]) if len(starts) > 1 \
            else np.zeros((0, P.shape[2], 6, Z.shape[2] + 1))
        stored = blocks.astype(np.float32)  # as the file holds them
        by_effect[name] = Profile(name, blocks.sum(axis=0), sums(P[::stride], Z[::stride]), _given(stored))
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    cross = {(a, b): _cross_sums(preds[a][::stride], preds[b][::stride]).astype(np.float32) for a, b in pairs}
    cross_total = {(a, b): _cross_sums(preds[a], preds[b]) for a, b in [*((n, n) for n in names), *pairs]}
    return Profiles(by_effect, cross, len(Z) / max(len(Z[::stride]), 1), cross_total)


def _cross_sums(Pa: np.ndarray, Pb: np.ndarray) -> np.ndarray:
    """(Ga, Gb, 6) ``Σ_i p_a(v_g)·p_b(v_h)`` per channel of two effects' predictions (m, 6, G)."""
    return np.stack([Pa[:, c, :].T @ Pb[:, c, :] for c in range(Pa.shape[1])], axis=2)


def _given(a: np.ndarray) -> Callable[[], np.ndarray]:
    """A source of blocks that are already in memory."""
    return lambda: a


def sums(P: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """(G, 6, W + 1): ``Σ p·z`` per column and ``Σ p·p``, per grid point and channel."""
    return np.concatenate([np.einsum("ncg,ncw->gcw", P, Z), np.einsum("ncg,ncg->gc", P, P)[:, :, None]], axis=2)


# ---------------------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------------------

def of_flight(s: FlightStats) -> Profiles:
    """A flight's profiles; a :class:`quadcore.identify.stats.sufficient.StatsError` if its statistics hold none
    (:func:`covers` says whether they do)."""
    if s.profiles is None:
        raise StatsError("these statistics hold no profiles (their layout profiles no effect)")
    return s.profiles


def covers(effect: Effect, stats: Sequence[FlightStats]) -> bool:
    """Whether every flight's statistics hold a profile of ``effect``."""
    return profiled(effect) and all(s.profiles is not None and effect.name in s.profiles.by_effect for s in stats)


# ---------------------------------------------------------------------------------------
# Held-out predictions as extra columns
# ---------------------------------------------------------------------------------------

def with_predictions(s: FlightStats, values: Mapping[str, float], signals: Collection[str] = ()) -> FlightStats:
    """A flight's statistics with, per profiled effect in ``values`` (name -> its parameter's
    value), its prediction there as an extra column ``pred:<effect>`` (see the module), and the
    profiles of its other profiled effects grown by those columns (their whole-flight and strided
    sums against them from the cross sums: a candidate fitted to a residual that holds a model's
    profiled prediction; not per block). ``signals``: the effects whose column's own energy is that
    of the interpolated signal (a model's, which a residual subtracts; see the module), not the
    interpolated energy."""
    names = list(values)
    base = s.layout.width
    layout = s.layout.with_extras([f"pred:{n}" for n in names])
    prof = of_flight(s)
    om = {n: prof.by_effect[n].at(values[n]) for n in names}
    pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))]

    def grown(G: np.ndarray, part: Callable[[str], np.ndarray], cross: Mapping | None) -> np.ndarray:
        """``G`` with the predictions' rows and columns (their crosses from ``cross``, None: zero)."""
        out = np.zeros((*G.shape[:-2], layout.width, layout.width))
        out[..., :base, :base] = G
        for i, n in enumerate(names):
            row = np.einsum("g,...gcw->...cw", om[n], part(n))
            out[..., base + i, :base] = out[..., :base, base + i] = row[..., :base]
            out[..., base + i, base + i] = row[..., base]
        for i, j in pairs:
            if cross is not None:
                c = _cross(cross, names[i], names[j], om)
                out[..., base + i, base + j] = out[..., base + j, base + i] = c
        return out

    total = grown(s.total, lambda n: prof.by_effect[n].total, prof.cross_total)
    mine = [i for i, n in enumerate(names) if n in signals]
    for i in mine:  # the energy of the interpolated signal itself (see the module)
        total[:, base + i, base + i] = _cross(prof.cross_total, names[i], names[i], om)
    strided = grown(s.strided, lambda n: prof.by_effect[n].strided, prof.cross)

    def gram() -> np.ndarray:
        blocks = grown(s.gram, lambda n: prof.by_effect[n].blocks.astype(float), None)
        for i in mine:  # each block's energy in proportion to its interpolated one
            k = base + i
            held = blocks[:, :, k, k].sum(axis=0)
            blocks[:, :, k, k] *= np.where(held > 0, total[:, k, k] / np.where(held > 0, held, 1.0), 1.0)
        for i, j in pairs:  # the flight's cross shared out over its blocks
            a, b = base + i, base + j
            share = np.sqrt(np.abs(blocks[:, :, a, a] * blocks[:, :, b, b]))
            share = share / np.where(share.sum(axis=0) > 0, share.sum(axis=0), 1.0)
            blocks[:, :, a, b] = blocks[:, :, b, a] = share * total[:, a, b]
        return blocks

    return replace(s, layout=layout, total=total, strided=strided, blocks_source=gram,
                   profiles=_others_grown(prof, om))


def _others_grown(prof: Profiles, om: Mapping[str, np.ndarray]) -> Profiles | None:
    """The profiles of the effects not predicted (not in ``om``), each grown by the predictions'
    columns (before its ``Σ p²``): ``Σ p_e(v_g) p_n(v_n)`` from the cross sums, over the flight
    and the strided samples; their per-block sums are not held (a held-out test takes the
    predictions, not the profiles)."""
    kept = [n for n in prof.by_effect if n not in om]
    if not kept:
        return None

    def with_columns(P: np.ndarray, e: str, cross: Mapping) -> np.ndarray:
        cols = [np.einsum("ghc,h->gc", _pair(cross, e, n).astype(float), w)[:, :, None] for n, w in om.items()]
        return np.concatenate([P[:, :, :-1], *cols, P[:, :, -1:]], axis=2)

    def no_blocks() -> np.ndarray:
        raise StatsError("a grown profile holds no per-block sums")

    by_effect = {e: Profile(e, with_columns(prof.by_effect[e].total, e, prof.cross_total),
                            with_columns(prof.by_effect[e].strided, e, prof.cross), no_blocks) for e in kept}
    return Profiles(by_effect, {k: C for k, C in prof.cross.items() if k[0] in kept and k[1] in kept},
                    prof.thinning, {k: C for k, C in prof.cross_total.items() if k[0] in kept and k[1] in kept})


def _pair(cross: Mapping, a: str, b: str) -> np.ndarray:
    """(Ga, Gb, 6) the cross sums of ``a`` and ``b`` (stored once per pair, in the layout's order)."""
    return cross[a, b] if (a, b) in cross else np.swapaxes(cross[b, a], 0, 1)


def _cross(cross: Mapping, a: str, b: str, om: Mapping) -> np.ndarray:
    """(6,) ``Σ p_a(v_a)·p_b(v_b)`` per channel, from the cross sums ``cross`` (whole flight or strided)."""
    return np.einsum("g,ghc,h->c", om[a], _pair(cross, a, b).astype(float), om[b])


# ---------------------------------------------------------------------------------------
# Storage (in the flight's statistics file)
# ---------------------------------------------------------------------------------------

def arrays(profiles: Profiles | None) -> dict[str, np.ndarray]:
    """The arrays a flight's statistics file holds for its profiles."""
    if profiles is None:
        return {}
    out = {}
    for name, prof in profiles.by_effect.items():
        out[f"profile:{name}:total"] = prof.total
        out[f"profile:{name}:strided"] = prof.strided
        out[f"profile:{name}:blocks"] = prof.blocks
    for (a, b), C in profiles.cross.items():
        out[f"cross:{a}:{b}"] = C
    for (a, b), C in profiles.cross_total.items():
        out[f"cross_total:{a}:{b}"] = C
    out["profile_thinning"] = np.array([profiles.thinning])
    return out


def from_arrays(layout: Layout, array: Callable[[str], np.ndarray]) -> Profiles | None:
    """The profiles of a statistics file (``array(name)`` reads one of its arrays)."""
    names = list(layout.profiled)
    if not names:
        return None
    by_effect = {n: Profile(n, array(f"profile:{n}:total"), array(f"profile:{n}:strided"),
                            partial(array, f"profile:{n}:blocks")) for n in names}
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    return Profiles(by_effect, {k: array(f"cross:{k[0]}:{k[1]}") for k in pairs},
                    float(array("profile_thinning")[0]),
                    {k: array(f"cross_total:{k[0]}:{k[1]}") for k in [*((n, n) for n in names), *pairs]})
