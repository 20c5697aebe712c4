"""The limits a planned flight must respect, checked on the polynomials themselves.

Speed ``|v|``, acceleration ``|a|``, tilt (angle of the thrust from vertical,
``acos(b3·e_z)`` with ``b3 = (a + g e_z) / |a + g e_z|``), every rotor's thrust between
``MIN_ROTOR_SHARE`` and ``MAX_ROTOR_SHARE`` of the most the thrust map gives at
:data:`quadcore.plan.flatness.VBAT_V` (room for the controller to correct), and the arena box
with a ``ARENA_MARGIN_M`` margin. :func:`check` evaluates the pieces at 1 kHz through
:mod:`quadcore.plan.flatness`; :func:`largest_scale` finds the largest excursion of a
manoeuvre that passes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadcore.logs.units import G0_MPS2
from quadcore.physics.vehicle import Vehicle
from quadcore.plan import family, flatness
from quadcore.sim.trajectories import PolyTrajectory

MIN_ROTOR_SHARE = 0.10
MAX_ROTOR_SHARE = 0.85
ARENA_MARGIN_M = 0.05
CHECK_RATE_HZ = 1000.0
DEFAULT_ARENA = (-1.0, -1.0, 0.2, 1.0, 1.0, 1.5)
DEFAULT_MAX_SPEED_MPS = 1.5
DEFAULT_MAX_TILT_DEG = 25.0


class LimitsError(ValueError):
    """Limits that no flight can meet (an arena too small, a negative speed...)."""


@dataclass(frozen=True)
class Limits:
    """Vehicle and room limits: m/s, m/s², degrees, and the arena box
    ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres (world frame)."""

    max_speed_mps: float = DEFAULT_MAX_SPEED_MPS
    max_tilt_deg: float = DEFAULT_MAX_TILT_DEG
    max_acc_mps2: float | None = None  # None: what the tilt allows horizontally, g tan(tilt)
    arena: tuple[float, float, float, float, float, float] = DEFAULT_ARENA

    def __post_init__(self) -> None:
        if not self.max_speed_mps > 0:
            raise LimitsError("the maximum speed must be positive")
        if not 0 < self.max_tilt_deg < 80:
            raise LimitsError("the maximum tilt must be between 0 and 80 degrees")
        if self.max_acc_mps2 is not None and not self.max_acc_mps2 > 0:
            raise LimitsError("the maximum acceleration must be positive")
        if len(self.arena) != 6 or not all(math.isfinite(v) for v in self.arena):
            raise LimitsError("the arena needs six numbers: XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX")
        lo, hi = np.array(self.arena[:3]), np.array(self.arena[3:])
        if np.any(hi - lo <= 4 * ARENA_MARGIN_M):
            raise LimitsError(f"the arena {list(self.arena)} is too small: each side must exceed "
                              f"{4 * ARENA_MARGIN_M:.2f} m")

    @property
    def acc_mps2(self) -> float:
        if self.max_acc_mps2 is not None:
            return self.max_acc_mps2
        return G0_MPS2 * math.tan(math.radians(self.max_tilt_deg))

    @property
    def centre_m(self) -> tuple[float, float, float]:
        """The hover point: the middle of the arena's floor plan, at mid height."""
        a = self.arena
        return (0.5 * (a[0] + a[3]), 0.5 * (a[1] + a[4]), 0.5 * (a[2] + a[5]))

    @property
    def half_extent_m(self) -> np.ndarray:
        a = np.array(self.arena)
        return 0.5 * (a[3:] - a[:3]) - ARENA_MARGIN_M

    def to_dict(self) -> dict:
        return {"max_speed_mps": self.max_speed_mps, "max_acc_mps2": self.acc_mps2,
                "max_tilt_deg": self.max_tilt_deg, "arena": [float(v) for v in self.arena]}


@dataclass(frozen=True)
class LimitCheck:
    """The largest value of each limited quantity along a trajectory, and whether all pass."""

    max_speed_mps: float
    max_acc_mps2: float
    max_tilt_deg: float
    rotor_share: tuple[float, float]  # smallest and largest rotor thrust / the most it gives
    in_arena: bool
    ok: bool

    def to_dict(self) -> dict:
        return {"max_speed_mps": self.max_speed_mps, "max_acc_mps2": self.max_acc_mps2,
                "max_tilt_deg": self.max_tilt_deg, "rotor_share": list(self.rotor_share),
                "in_arena": self.in_arena, "ok": self.ok}


def max_rotor_thrust_N(vehicle: Vehicle) -> float:
    return float(vehicle.pwm_vbat.thrust_N(np.ones(1), flatness.VBAT_V)[0])


def check(traj: PolyTrajectory, vehicle: Vehicle, limits: Limits, rate_hz: float = CHECK_RATE_HZ) -> LimitCheck:
    """Every limit evaluated on the polynomials at ``rate_hz`` (and at the pieces' ends)."""
    path = flatness.flat_path(traj, vehicle, rate_hz, pad_s=0.0)
    return _check_path(path, vehicle, limits)


def _check_path(path: flatness.FlatPath, vehicle: Vehicle, limits: Limits) -> LimitCheck:
    speed = float(np.linalg.norm(path.v_w_mps, axis=1).max())
    acc = float(np.linalg.norm(path.a_w_mps2, axis=1).max())
    tilt = float(np.degrees(path.tilt_rad.max()))
    f_max = max_rotor_thrust_N(vehicle)
    share = (float(path.f_rotor_N.min() / f_max), float(path.f_rotor_N.max() / f_max))
    a = np.array(limits.arena)
    lo, hi = a[:3] + ARENA_MARGIN_M - 1e-9, a[3:] - ARENA_MARGIN_M + 1e-9
    inside = bool(np.all(path.p_w_m >= lo) and np.all(path.p_w_m <= hi))
    ok = (speed <= limits.max_speed_mps + 1e-9 and acc <= limits.acc_mps2 + 1e-9
          and tilt <= limits.max_tilt_deg + 1e-9 and share[0] >= MIN_ROTOR_SHARE and share[1] <= MAX_ROTOR_SHARE
          and inside)
    return LimitCheck(speed, acc, tilt, share, inside, bool(ok))


def largest_scale(unit: PolyTrajectory, centre_m: tuple[float, float, float], vehicle: Vehicle, limits: Limits,
                  rate_hz: float = 200.0) -> float:
    """The largest scale in (0, 1] of a manoeuvre (``unit``: at scale 1) that passes every limit
    at ``rate_hz``; 0 when none does. Speed and acceleration grow in proportion to the scale,
    the tilt and the rotor thrusts monotonically in practice: bisection after the linear bound."""
    path = flatness.flat_path(unit, vehicle, rate_hz, pad_s=0.0)
    speed = float(np.linalg.norm(path.v_w_mps, axis=1).max())
    acc = float(np.linalg.norm(path.a_w_mps2, axis=1).max())
    hi = min(1.0, limits.max_speed_mps / speed if speed > 0 else 1.0, limits.acc_mps2 / acc if acc > 0 else 1.0)

    def passes(s: float) -> bool:
        p = flatness.flat_path(family.scaled_trajectory(unit, centre_m, s), vehicle, rate_hz, pad_s=0.0)
        return _check_path(p, vehicle, limits).ok

    if passes(hi):
        return hi
    lo = 0.0
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if passes(mid) else (lo, mid)
    return lo
