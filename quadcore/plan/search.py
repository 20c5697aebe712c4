"""The search over the manoeuvre family (:mod:`quadcore.plan.family`): a grid, then local
refinement of the best few, with the limits as constraints.

Every candidate is scaled to the largest excursion the limits allow
(:func:`quadcore.plan.limits.largest_scale`: the excitation grows with the excursion, so the
best flight of a shape and frequency uses all the room and all the speed it may), turned into
the lab's polynomial pieces, flown in prediction (:mod:`quadcore.plan.flatness`) and scored by
the objective (:mod:`quadcore.plan.objective`) on those pieces: what is scored is what is
written and flown. The grid spans the shapes, base frequencies 0.15 and 0.5 Hz, chirp ratios 1 and 3 (the path's
frequencies below what the pieces carry, :func:`quadcore.plan.family.max_hz`), vertical bob or
none, and no yaw wobble or one at that frequency, over the
whole flight time or a shorter manoeuvre followed by hover; refinement moves one coordinate at a
time (frequency and chirp by
factors, the bob by steps) while it improves, from the best ``REFINE_FROM`` grid points and the
best of each flight-time share (a short manoeuvre and one over the whole flight are different
basins: on the 19 real flights the short one's grid point scored highest, the whole flight's
refined to twice its value).
Deterministic: same inputs, same plan.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from quadcore.physics.vehicle import Vehicle
from quadcore.plan import family, limits as limitlib
from quadcore.plan.limits import Limits
from quadcore.sim.trajectories import PolyTrajectory

GRID_F0_HZ = (0.15, 0.5)
GRID_CHIRP = (1.0, 3.0)
GRID_BOB = (0.0, 0.6)  # vertical half-amplitude as a share of the arena's half height
# the manoeuvre's share of the flight time (the rest hovers): a shorter one carries higher
# frequencies in the same 31 pieces (base frequencies scale with what the pieces carry)
GRID_ACTIVE = (1.0, 0.4)
MIN_ACTIVE_S = 3.0
BASE_TOP_HZ = 3.1  # what the pieces carry over 10 s: the grid's frequencies are for this
# yaw wobble: amplitude (rad, before the scale) and frequency as a share of what the pieces carry
GRID_YAW = ((0.0, 0.5), (0.15, 1.0))
REFINE_FROM = 2
REFINE_ROUNDS = 2
F0_MIN_HZ = 0.05
CHIRP_RANGE = (1.0, 6.0)
YAW_MAX_RAD = 1.0
YAW_MIN_HZ = 0.5
SHRINK = 0.97  # scale step when the 1 kHz check finds what the search's 200 Hz check missed


@dataclass(frozen=True)
class Candidate:
    """A scored member of the family: the manoeuvre (at its largest allowed scale), its
    pieces, and the objective's value."""

    manoeuvre: family.Manoeuvre
    trajectory: PolyTrajectory
    value: float


def _fitted(m: family.Manoeuvre, vehicle: Vehicle, limits: Limits) -> tuple[family.Manoeuvre, PolyTrajectory] | None:
    """The manoeuvre at the largest scale the limits allow, as pieces; None if none passes."""
    unit = family.trajectory(m.scaled(1.0))
    s = limitlib.largest_scale(unit, m.centre_m, vehicle, limits)
    if s <= 0.02:
        return None
    return m.scaled(s), family.scaled_trajectory(unit, m.centre_m, s)


def _score(m: family.Manoeuvre, vehicle: Vehicle, limits: Limits, value: Callable[[PolyTrajectory], float],
           seen: dict) -> Candidate | None:
    key = (m.shape, round(m.f0_hz, 6), round(m.chirp, 6), round(m.amp_z_m, 6), round(m.yaw_amp_rad, 6), m.yaw_hz)
    if key not in seen:
        fitted = _fitted(m, vehicle, limits)
        seen[key] = None if fitted is None else Candidate(
            fitted[0], fitted[1], float(value(fitted[1])))
    return seen[key]


def _neighbours(m: family.Manoeuvre, half_z: float, top_hz: float) -> list[family.Manoeuvre]:
    """One coordinate moved each way; the path's frequencies (twice θ's for the bob and the
    figure-eight) stay below ``top_hz``."""
    out = []
    path_hz = top_hz / 2
    for f in (1 / 1.3, 1.3):
        out.append(replace(m, f0_hz=float(np.clip(m.f0_hz * f, F0_MIN_HZ, path_hz / m.chirp))))
        chirp = np.clip(m.chirp * f, CHIRP_RANGE[0], min(CHIRP_RANGE[1], path_hz / m.f0_hz))
        out.append(replace(m, chirp=float(chirp)))
    for dz in (-0.2, 0.2):
        out.append(replace(m, amp_z_m=float(np.clip(m.amp_z_m + dz * half_z, 0.0, half_z))))
    for f in (1 / 1.5, 1.5):
        out.append(replace(m, yaw_amp_rad=float(np.clip(m.yaw_amp_rad * f, 0.0, YAW_MAX_RAD))))
        out.append(replace(m, yaw_hz=float(np.clip(m.yaw_hz * f, YAW_MIN_HZ, top_hz))))
    return out


def search(value: Callable[[PolyTrajectory], float], vehicle: Vehicle, limits: Limits, duration_s: float,
           log: Callable[[str], None] = lambda m: None) -> Candidate:
    """The best member of the family for ``value`` (pieces -> number, larger is better) within
    ``limits`` and ``duration_s``. Raises :class:`quadcore.plan.limits.LimitsError`
    when no member passes the limits."""
    half = limits.half_extent_m
    amp_xy = float(min(half[0], half[1]))
    seen: dict = {}
    grid = []
    for share in GRID_ACTIVE:
        active = max(share * duration_s, MIN_ACTIVE_S) if share < 1 else None
        if active is not None and active >= duration_s:
            continue
        top = family.max_hz(duration_s, active)
        grid += [family.Manoeuvre(shape, f0 * top / BASE_TOP_HZ, chirp, amp_xy, bob * half[2], limits.centre_m,
                                  duration_s, yaw_amp_rad=yaw[0], yaw_hz=yaw[1] * top, active_s=active)
                 for shape, f0, chirp, bob, yaw in itertools.product(family.SHAPES, GRID_F0_HZ, GRID_CHIRP, GRID_BOB,
                                                                      GRID_YAW)
                 if f0 * chirp <= BASE_TOP_HZ / 2]
    scored = [c for c in (_score(m, vehicle, limits, value, seen) for m in grid) if c is not None]
    if not scored:
        raise limitlib.LimitsError("no manoeuvre of the family fits these limits (arena, speed, tilt, thrust)")
    log(f"plan: {len(scored)} grid manoeuvres scored; refining the best {REFINE_FROM} and the best of each flight-time "
        "share")
    ranked = sorted(scored, key=lambda c: -c.value)
    best = ranked[:REFINE_FROM]
    firsts: dict = {}
    for c in ranked:  # and from the best of each flight-time share: a basin of its own
        firsts.setdefault(c.manoeuvre.active_s, c)
    best += [c for c in firsts.values() if c not in best]
    for start in list(best):
        here = start
        for _ in range(REFINE_ROUNDS):
            trial = [c for c in (_score(n, vehicle, limits, value, seen)
                                 for n in _neighbours(here.manoeuvre, half[2],
                                                      family.max_hz(duration_s, here.manoeuvre.active_s)))
                     if c is not None]
            step = max(trial, key=lambda c: c.value, default=here)
            if step.value <= here.value:
                break
            here = step
        best.append(here)
    winner = max(best, key=lambda c: c.value)
    return _verified(winner, vehicle, limits, value)


def _verified(c: Candidate, vehicle: Vehicle, limits: Limits, value: Callable[[PolyTrajectory], float]) -> Candidate:
    """Shrink the winner until the 1 kHz check of its pieces passes (the search checks at 200 Hz)."""
    m, traj = c.manoeuvre, c.trajectory
    unit = family.trajectory(m.scaled(1.0))
    changed = False
    while not limitlib.check(traj, vehicle, limits).ok:
        if m.scale < 0.02:
            raise limitlib.LimitsError("the planned manoeuvre cannot be made to fit the limits")
        m = m.scaled(m.scale * SHRINK)
        traj = family.scaled_trajectory(unit, m.centre_m, m.scale)
        changed = True
    if not changed:
        return c
    return Candidate(m, traj, float(value(traj)))
