"""Reference trajectories for the simulator: polynomial flight plans and generated references.

**Polynomial plans** (``trajectories/*.csv``, the files the real flights flew): one row per
piece, ``duration`` then 8 coefficients each for x, y, z, yaw (lowest order first), time in
seconds of the plan, positions in metres, yaw in radians. Flown as the Crazyflie's high-level
commander flies an uploaded trajectory with ``relative=True`` and a ``timescale``:

* time is stretched: plan time ``tau = t / timescale`` (a larger timescale is slower), so
  velocities scale by ``1 / timescale`` and accelerations by ``1 / timescale^2``;
* position is relative: the plan is shifted so that its first point is where the vehicle
  hovers when the plan starts (``(0, 0, height_m)`` here). The real logs confirm this:
  ``circle0`` starts at (0.26, 0.13, 0.70) in the file but the real flights start at their
  hover point at 0.45-0.5 m;
* yaw is absolute (the real ``yaw0`` flight jana01 starts at yaw 72 deg = 1.26 rad, the
  plan's first yaw, and turns 97.5 rad in 50 s at timescale 5).

**Generated references** (all ``(p, v, a, yaw, yaw_rate, yaw_acc)`` sampled on a time grid):
minimum-jerk segments between rest points (``p(s) = p0 + (p1 - p0)(10 s^3 - 15 s^4 + 6 s^5)``,
peak speed ``1.875 d / T``), used for the take-off, random go-to flights and low passes.

Everything here is vectorised over the time grid: the reference is open loop, so the
simulator evaluates it once for the whole flight before the closed-loop integration.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import numpy.typing as npt

BUILTIN_PLANS = ("figure8", "circle0", "yaw0")
MIN_JERK_PEAK_SPEED = 1.875  # peak speed of a minimum-jerk segment, in units of d / T
MIN_JERK_PEAK_ACC = 5.7735  # peak acceleration, in units of d / T^2 (10 / sqrt(3))


@dataclass(frozen=True)
class Reference:
    """A sampled reference: (n,) times, (n, 3) position/velocity/acceleration (world), yaw (n,)."""

    t_s: np.ndarray
    p_w_m: np.ndarray
    v_w_mps: np.ndarray
    a_w_mps2: np.ndarray
    yaw_rad: np.ndarray
    yaw_rate_radps: np.ndarray
    yaw_acc_radps2: np.ndarray

    @property
    def n(self) -> int:
        return len(self.t_s)


@dataclass(frozen=True)
class PolyTrajectory:
    """Piecewise 7th-order polynomial plan: ``durations`` (pieces,), ``coeffs`` (pieces, 4, 8)
    for x, y, z, yaw, lowest order first."""

    name: str
    durations: np.ndarray
    coeffs: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.durations.sum())

    def evaluate(self, tau_s: np.ndarray, derivative: int = 0) -> np.ndarray:
        """(n, 4) x, y, z, yaw (or their ``derivative``-th time derivative) at plan times
        ``tau_s`` (clamped to the plan; the end point holds, with zero derivatives)."""
        tau = np.asarray(tau_s, dtype=float)
        ends = np.cumsum(self.durations)
        starts = ends - self.durations
        piece = np.clip(np.searchsorted(ends, tau, side="right"), 0, len(self.durations) - 1)
        local = np.clip(tau - starts[piece], 0.0, self.durations[piece])
        c = self.coeffs[piece]  # (n, 4, 8)
        for _ in range(derivative):  # differentiate the coefficients
            c = c[..., 1:] * np.arange(1, c.shape[-1])
        powers = local[:, None] ** np.arange(c.shape[-1])  # (n, k)
        out = np.einsum("nck,nk->nc", c, powers)
        if derivative:
            out[tau > ends[-1]] = 0.0
        return out


def parse_plan(text: str, name: str = "plan") -> PolyTrajectory:
    """Parse a plan CSV (a header line, or ``#`` comments; trailing commas allowed)."""
    rows = []
    for line in text.splitlines():
        line = line.strip().rstrip(",")
        if not line or line.startswith("#") or line[0].isalpha():
            continue
        values = [float(x) for x in line.split(",")]
        if len(values) != 33:
            raise ValueError(f"{name}: a plan row needs 33 values (duration + 4 x 8 coefficients), got {len(values)}")
        rows.append(values)
    if not rows:
        raise ValueError(f"{name}: no pieces in the plan")
    a = np.array(rows)
    if np.any(a[:, 0] <= 0):
        raise ValueError(f"{name}: piece durations must be positive")
    return PolyTrajectory(name, a[:, 0], a[:, 1:].reshape(-1, 4, 8))


def load_plan(name_or_path: str | Path) -> PolyTrajectory:
    """A built-in plan by name (``figure8``, ``circle0``, ``yaw0``) or a CSV file."""
    if str(name_or_path) in BUILTIN_PLANS:
        text = resources.files("quadcore").joinpath(f"trajectories/{name_or_path}.csv").read_text()
        return parse_plan(text, str(name_or_path))
    path = Path(name_or_path)
    if not path.is_file():
        raise FileNotFoundError(f"no trajectory {name_or_path!r}: not one of {', '.join(BUILTIN_PLANS)} nor a file")
    return parse_plan(path.read_text(), path.stem)


# ---------------------------------------------------------------------------------------
# Building blocks on a time grid
# ---------------------------------------------------------------------------------------

def min_jerk(t_s: np.ndarray, t0: float, T: float, p0: np.ndarray, p1: np.ndarray):
    """Minimum-jerk rest-to-rest move from ``p0`` to ``p1`` over ``[t0, t0 + T]``, clamped
    outside. Returns (p, v, a), each (n, d)."""
    s = np.clip((np.asarray(t_s) - t0) / T, 0.0, 1.0)[:, None]
    d = np.asarray(p1, float) - np.asarray(p0, float)
    shape = 10 * s**3 - 15 * s**4 + 6 * s**5
    dshape = (30 * s**2 - 60 * s**3 + 30 * s**4) / T
    ddshape = (60 * s - 180 * s**2 + 120 * s**3) / T**2
    inside = (s > 0) & (s < 1)
    return p0 + d * shape, d * dshape * inside, d * ddshape * inside


class _Builder:
    """Concatenates rest-to-rest segments into a reference sampled on ``t_s``."""

    def __init__(self, t_s: np.ndarray, p_start: npt.ArrayLike, yaw: float = 0.0):
        self.t = np.asarray(t_s, float)
        n = len(self.t)
        self.p = np.tile(np.asarray(p_start, float), (n, 1))
        self.v = np.zeros((n, 3))
        self.a = np.zeros((n, 3))
        self.yaw = np.full(n, float(yaw))
        self.yaw_rate = np.zeros(n)
        self.yaw_acc = np.zeros(n)
        self.now = 0.0
        self.here = np.asarray(p_start, float)

    def move(self, target, T: float) -> None:
        target = np.asarray(target, float)
        mask = self.t >= self.now
        p, v, a = min_jerk(self.t[mask], self.now, T, self.here, target)
        self.p[mask], self.v[mask], self.a[mask] = p, v, a
        self.now += T
        self.here = target

    def hold(self, T: float) -> None:
        self.now += T

    def reference(self) -> Reference:
        return Reference(self.t, self.p, self.v, self.a, self.yaw, self.yaw_rate, self.yaw_acc)


def segment_time(distance_m: float, peak_speed_mps: float, accel_max_mps2: float = 4.0, min_s: float = 0.4) -> float:
    """Duration of a minimum-jerk move whose peak speed is ``peak_speed_mps`` (or less, when
    the move is too short to reach it with peak acceleration ``accel_max_mps2``)."""
    return max(MIN_JERK_PEAK_SPEED * distance_m / max(peak_speed_mps, 1e-6),
               np.sqrt(MIN_JERK_PEAK_ACC * distance_m / max(accel_max_mps2, 1e-6)), min_s)


# ---------------------------------------------------------------------------------------
# The references the simulator flies
# ---------------------------------------------------------------------------------------

def plan_reference(
    t_s: np.ndarray, plan: PolyTrajectory, height_m: float, timescale: float,
    start_height_m: float, takeoff_s: float, hover_s: float,
) -> Reference:
    """Take off from ``(0, 0, start_height_m)`` to ``(0, 0, height_m)``, hover, fly the plan
    (relative position, absolute yaw, time stretched by ``timescale``), then hold its end."""
    if timescale <= 0:
        raise ValueError("timescale must be positive")
    first = plan.evaluate(np.zeros(1))[0]
    hover_point = np.array([0.0, 0.0, height_m])
    b = _Builder(t_s, [0.0, 0.0, start_height_m], yaw=first[3])
    b.move(hover_point, takeoff_s)
    b.hold(hover_s)
    t_plan = b.now
    mask = b.t >= t_plan
    tau = (b.t[mask] - t_plan) / timescale
    x = plan.evaluate(tau)
    dx = plan.evaluate(tau, 1) / timescale
    ddx = plan.evaluate(tau, 2) / timescale**2
    b.p[mask] = hover_point + x[:, :3] - first[:3]
    b.v[mask], b.a[mask] = dx[:, :3], ddx[:, :3]
    b.yaw[mask], b.yaw_rate[mask], b.yaw_acc[mask] = x[:, 3], dx[:, 3], ddx[:, 3]
    return b.reference()


def plan_flight_duration(plan: PolyTrajectory, timescale: float, takeoff_s: float, hover_s: float,
                         end_hover_s: float) -> float:
    return takeoff_s + hover_s + plan.duration_s * timescale + end_hover_s


def hover_reference(t_s: np.ndarray, height_m: float, start_height_m: float, takeoff_s: float) -> Reference:
    b = _Builder(t_s, [0.0, 0.0, start_height_m])
    b.move([0.0, 0.0, height_m], takeoff_s)
    return b.reference()


def random_reference(
    t_s: np.ndarray, rng: np.random.Generator, box_min, box_max, speed_min_mps: float, speed_max_mps: float,
    height_m: float, start_height_m: float, takeoff_s: float, accel_max_mps2: float = 4.0,
    min_hop_m: float = 0.4, max_pause_s: float = 0.3,
) -> Reference:
    """Take off, then minimum-jerk hops between random waypoints in the box, each hop with a
    peak speed drawn uniformly in ``[speed_min, speed_max]`` (reached when the hop is long
    enough for ``accel_max_mps2``) and a short random pause."""
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    b = _Builder(t_s, [0.0, 0.0, start_height_m])
    b.move([0.0, 0.0, float(np.clip(height_m, lo[2], hi[2]))], takeoff_s)
    end = float(t_s[-1]) if len(t_s) else 0.0
    while b.now < end:
        for _ in range(20):  # draw a waypoint far enough away to be a real move
            target = rng.uniform(lo, hi)
            if float(np.linalg.norm(target - b.here)) >= min(min_hop_m, 0.5 * float(np.linalg.norm(hi - lo))):
                break
        speed = rng.uniform(speed_min_mps, speed_max_mps)
        b.move(target, segment_time(float(np.linalg.norm(target - b.here)), speed, accel_max_mps2))
        b.hold(rng.uniform(0.0, max_pause_s))
    return b.reference()


def low_pass_reference(
    t_s: np.ndarray, rng: np.random.Generator, box_min, box_max, speed_min_mps: float, speed_max_mps: float,
    height_m: float, pass_height_m: float | None, start_height_m: float, takeoff_s: float,
    accel_max_mps2: float = 4.0,
) -> Reference:
    """Take off, then repeated low passes: descend to ``pass_height_m`` (drawn in 0.03-0.08 m
    when None) at one end of the box, cross it along x at a drawn speed, climb back to
    ``height_m``; alternate directions until the end."""
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    b = _Builder(t_s, [0.0, 0.0, start_height_m])
    y0 = 0.5 * (lo[1] + hi[1])
    b.move([lo[0], y0, height_m], max(takeoff_s, segment_time(float(np.hypot(lo[0], height_m - start_height_m)), 0.5)))
    end = float(t_s[-1]) if len(t_s) else 0.0
    x_from, x_to = lo[0], hi[0]
    while b.now < end:
        h = float(pass_height_m) if pass_height_m is not None else float(rng.uniform(0.03, 0.08))
        y = float(rng.uniform(lo[1], hi[1])) * 0.5 + 0.5 * y0
        dist_m = float(np.hypot(height_m - h, y - b.here[1]))
        b.move([x_from, y, h], segment_time(dist_m, 0.6, accel_max_mps2, min_s=1.2))
        b.hold(0.3)
        speed = rng.uniform(speed_min_mps, speed_max_mps)
        b.move([x_to, y, h], segment_time(abs(x_to - x_from), speed, accel_max_mps2))
        b.hold(0.3)
        b.move([x_to, y, height_m], segment_time(height_m - h, 0.6, accel_max_mps2, min_s=1.0))
        x_from, x_to = x_to, x_from
    return b.reference()
