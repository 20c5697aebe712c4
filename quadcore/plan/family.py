"""The family of manoeuvres the planner searches: chirped Lissajous figures in an envelope.

A manoeuvre of duration ``T`` about the hover point ``c`` (world frame, metres)::

    x(t) = c_x + s e(t) A_x sin θ(t)
    y(t) = c_y + s e(t) A_y sin(k_y θ(t) + φ_y)        shape: line (A_y = 0), circle (k_y = 1,
    z(t) = c_z + s e(t) A_z sin(2 θ(t))                  φ_y = π/2), figure-eight (k_y = 2, φ_y = 0)
    ψ(t) = ψ_0 + s e(t) A_ψ sin(2π f_ψ t)                a yaw wobble
    θ(t) = 2π ∫ f(t') dt',   f(t) = f_0 r^(t / T)       an exponential chirp from f_0 to r f_0
    e(t) = S(t / t_r) S((T - t) / t_r),  S(u) = 35u⁴ - 84u⁵ + 70u⁶ - 20u⁷ (u clipped to [0, 1])

``S`` has zero first to third derivatives at 0 and 1, so the
manoeuvre starts and ends at rest at the hover point (zero velocity, acceleration and jerk):
the vehicle hovers before and after. ``s`` scales the whole excursion; the planner sets it to
the largest value the limits allow (:mod:`quadcore.plan.limits`).

Why this family. What separates the explanations the diagnosis confuses is a range of the
quantities their signatures depend on differently: speed for the two drags (rotor drag grows
as ``v``, parasitic drag as ``v |v|``), attitude rate and angular acceleration for a thrust
scale against a payload (only the thrust scale scales the rotors' torques), and the frequency
of thrust changes for a lag against a delay (a lag damps fast changes, a delay only shifts
them: the difference grows with ``ω τ`` and needs rotor-thrust changes at several hertz). A
chirp sweeps speed and frequency over the flight at a given amplitude, the shape sets
which axes move, the vertical bob changes the collective thrust, and the yaw wobble
changes the rotors' thrusts against each other at ``f_ψ`` (the yaw torque is the rotors'
drag torques, so a fast small wobble asks for large, fast rotor-thrust differences without
tilting or moving the vehicle: the lag/delay and thrust-scale/payload signatures at high
frequency, within the arena and speed limits); all are smooth, so a handful
of 7th-order pieces represent them (:mod:`quadcore.plan.pieces`). Eight numbers span it, few
enough to search on a grid and refine locally (:mod:`quadcore.plan.search`) with the limits
as constraints, rather than trusting a general optimiser over piece coefficients.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from quadcore.plan import pieces
from quadcore.sim.trajectories import PolyTrajectory

SHAPES = {"line": (0.0, 0.0, 0.0), "circle": (1.0, 1.0, math.pi / 2), "figure8": (0.5, 2.0, 0.0)}  # A_y/A_x, k_y, φ_y
PIECE_S = 0.25  # preferred piece length; longer when the flight needs more than MAX_PIECES
STEP_S = 1e-3  # finite-difference step for the knots' derivatives (errors ~1e-6 relative)


@dataclass(frozen=True)
class Manoeuvre:
    """One member of the family (see the module): shape, base frequency ``f0_hz``, chirp ratio
    ``chirp`` (end frequency / start), horizontal and vertical half-amplitudes (m, before the
    scale ``scale``), centre ``centre_m`` (the hover point), ``duration_s``, ramp ``ramp_s``."""

    shape: str
    f0_hz: float
    chirp: float
    amp_xy_m: float
    amp_z_m: float
    centre_m: tuple[float, float, float]
    duration_s: float
    ramp_s: float = 1.5
    scale: float = 1.0
    yaw_rad: float = 0.0
    yaw_amp_rad: float = 0.0
    yaw_hz: float = 4.0
    active_s: float | None = None  # manoeuvre for this long, then hover to the end (None: all of it)

    @property
    def active(self) -> float:
        return self.duration_s if self.active_s is None else min(self.active_s, self.duration_s)

    def scaled(self, scale: float) -> Manoeuvre:
        return replace(self, scale=float(scale))

    def to_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        text = (f"{self.shape}, {self.f0_hz:.2f} -> {self.f0_hz * self.chirp:.2f} Hz, "
                f"±{self.scale * self.amp_xy_m:.2f} m horizontally, ±{self.scale * self.amp_z_m:.2f} m vertically")
        if self.yaw_amp_rad:
            text += f", yaw ±{math.degrees(self.scale * self.yaw_amp_rad):.1f} deg at {self.yaw_hz:.1f} Hz"
        if self.active < self.duration_s:
            text += f", for {self.active:.1f} s then hover"
        return text


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**4 * (35 - 84 * u + 70 * u**2 - 20 * u**3)


def _phase(m: Manoeuvre, t: np.ndarray) -> np.ndarray:
    """θ(t) = 2π ∫ f0 r^(t'/T) dt' (r = 1: 2π f0 t)."""
    if abs(m.chirp - 1.0) < 1e-9:
        return 2 * math.pi * m.f0_hz * t
    k = math.log(m.chirp) / m.active
    return 2 * math.pi * m.f0_hz * np.expm1(k * t) / k


def position(m: Manoeuvre, t_s: np.ndarray) -> np.ndarray:
    """(n, 4) x, y, z, yaw of the analytic manoeuvre at ``t_s`` (clipped to the flight)."""
    t = np.clip(np.asarray(t_s, float), 0.0, m.active)
    ramp = min(m.ramp_s, 0.5 * m.active)
    e = _smoothstep(t / ramp) * _smoothstep((m.active - t) / ramp)
    th = _phase(m, t)
    ratio_y, k_y, phi_y = SHAPES[m.shape]
    a = m.scale * e
    out = np.empty((len(t), 4))
    out[:, 0] = m.centre_m[0] + a * m.amp_xy_m * np.sin(th)
    out[:, 1] = m.centre_m[1] + a * m.amp_xy_m * ratio_y * np.sin(k_y * th + phi_y)  # e(0) = 0: from the centre
    out[:, 2] = m.centre_m[2] + a * m.amp_z_m * np.sin(2 * th)
    out[:, 3] = m.yaw_rad + a * m.yaw_amp_rad * np.sin(2 * math.pi * m.yaw_hz * t)
    return out


def _derivatives(m: Manoeuvre, t: np.ndarray) -> np.ndarray:
    """(n, 4 coordinates, 4 orders) position and its first three derivatives, by central
    differences of the analytic path (the knots' values; the pieces are what is flown)."""
    h = STEP_S
    p = [position(m, t + k * h) for k in (-2, -1, 0, 1, 2)]
    d0 = p[2]
    d1 = (p[3] - p[1]) / (2 * h)
    d2 = (p[3] - 2 * p[2] + p[1]) / h**2
    d3 = (p[4] - 2 * p[3] + 2 * p[1] - p[0]) / (2 * h**3)
    out = np.stack([d0, d1, d2, d3], axis=2)
    # the ends are at rest exactly (the differences would read across the clip)
    out[(t <= 0.0) | (t >= m.active), :, 1:] = 0.0
    return out


def knots(duration_s: float, active_s: float | None = None) -> np.ndarray:
    """Equal pieces of about ``PIECE_S`` over the manoeuvre (``active_s``, default all of it), at
    most ``MAX_PIECES`` in all; a hover after it is one more piece."""
    active = duration_s if active_s is None else min(active_s, duration_s)
    tail = active < duration_s - 1e-9
    n = min(pieces.MAX_PIECES - int(tail), max(2, math.ceil(active / PIECE_S)))
    t = np.linspace(0.0, active, n + 1)
    return np.append(t, duration_s) if tail else t


def max_hz(duration_s: float, active_s: float | None = None) -> float:
    """The highest frequency the pieces carry: one period per piece (a degree-7 piece matching
    position to jerk at both ends follows one period of a sine within ~10 %, two not at all).
    The Crazyflie's 31 pieces thus cap a manoeuvre's frequencies at about ``31 / its length``."""
    return 1.0 / float(np.diff(knots(duration_s, active_s))[0])


def trajectory(m: Manoeuvre, name: str = "plan") -> PolyTrajectory:
    """The manoeuvre as the lab's piecewise polynomial (what is flown, checked and predicted)."""
    t = knots(m.duration_s, m.active_s)
    return pieces.from_derivatives(t, _derivatives(m, t), name)


def scaled_trajectory(unit: PolyTrajectory, centre_m: tuple[float, float, float], scale: float) -> PolyTrajectory:
    """``unit`` (a manoeuvre at scale 1) at another scale: the offsets from the centre (and from
    the first yaw) are linear in the scale, so its coefficients scale except the constant centre."""
    c = unit.coeffs.copy()
    centre = np.array([*centre_m, unit.coeffs[0, 3, 0]])
    c *= scale
    c[:, :, 0] += (1 - scale) * centre
    return PolyTrajectory(unit.name, unit.durations.copy(), c)
