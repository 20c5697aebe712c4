"""A closed-loop quadrotor simulator that writes real uSD logs with a known ground truth.

Why: the diagnosis stages must find effects we *know* are there. A simulated flight has the
same log format, header, rates and roughly the same noise as the real Crazyflie logs, and a
``<log>.truth.json`` sidecar with the effects and parameters it was flown with.

**What is simulated** (body frame x forward, y left, z up; world z up; SI throughout)

* Rigid body: mass, full inertia and X rotor layout of the :class:`~quadcore.physics.vehicle.Vehicle`.
  Newton-Euler as in :mod:`quadcore.physics.dynamics`.
* Closed loop at the vehicle's command rate (``[thrust_map.pwm_vbat] command_period_s``, 500 Hz
  for the Crazyflie, whatever the log rate; the log keeps every n-th step):
  :mod:`quadcore.sim.controller` (position PID with acceleration feed-forward, geometric
  attitude control on SO(3)), using the NOMINAL vehicle and the noisy sensor readings, -> rotor
  thrust commands ``A^-1 [T, tau]`` clipped to ``[0, f(pwm=1, vbat)]``.
* Actuation through the real chain: command -> PWM with ``pwm_vbat.pwm_for_thrust`` at the
  battery voltage *as logged* -> integer PWM (as logged) -> the map thrust
  ``pwm_vbat.thrust_N(pwm, vbat)``. So the logged PWM and vbat reproduce the rotor thrust
  exactly when no effect is on. Motor speed is logged as ``sqrt(f_actual / k_F)`` (rpm).
* Battery: open-circuit voltage falling linearly from ``ocv_start_V``, minus an internal
  resistance times a load current proportional to the total thrust (1.05 V per newton of
  thrust, fitted on jana00..jana11: ``vbat = a + b t - 1.05 T``), plus ADC noise, in whole mV.
* Effects (the vocabulary and parameter names of :mod:`quadcore.effects`), composed. The
  simulator names no effect: each effect either flies its own mechanism through a
  :class:`~quadcore.effects.base.SimHook` (true mass, true inertia, air velocity, the chain
  from map thrust to actual rotor thrust, an extra wrench with memory), or, by default, has
  its ``wrench(state, vehicle, params)`` evaluated on the TRUE state at every physics step (a
  one-sample FlightState whose ``f_rotor_N`` is the map thrust and ``motor_radps`` the true
  rotor speed) and added to the force and torque. Effects that ``acts_on_airspeed`` see
  the velocity relative to the air when a hook sets one (a wind). For example
  ``motor_lag`` lags each rotor's thrust (integrated exactly per physics step),
  ``thrust_scale`` scales it, ``added_mass`` changes the true mass (Newton and
  accelerometer), ``wind`` blows (mean + Ornstein-Uhlenbeck gust, ``SimConfig``'s
  ``wind_gust_std_mps`` and ``wind_gust_tau_s``).

  So the residual of :func:`quadcore.physics.residuals.residual_table` on the decoded log equals
  the sum of the effects' wrenches evaluated on the decoded flight, within noise (the tests
  check this effect by effect).
* Sensors: accelerometer = true specific force (non-gravitational force / TRUE mass) in g
  plus white noise; gyro = true body rate in deg/s plus white noise; state estimate = true
  position, velocity, attitude plus small noise; ``estPose`` (motion capture) at
  ``mocap_rate_hz`` with packet loss, timing jitter and noise. Noise levels are measured on
  the real logs (:class:`SensorNoise`). Random dropped log samples (gaps), as on the deck.

**Integration**: the controller, the PWM and the sensors run at the command rate (500 Hz,
zero-order hold of the rotor commands, as the firmware's 500 Hz rate loop), and the log keeps
every ``500 / log_rate_hz``-th step (every step at 500 Hz, every fifth at 100 Hz); the rigid
body is integrated with semi-implicit Euler (``v += a h; p += v h; w += dw/dt h;
q = q (x) exp(w h)``) at the command rate times ``physics_substeps`` = 1 kHz by default. A log
sample ``k`` holds the state at ``t_k`` and the accelerometer reading of the forces acting
just after the PWM of sample ``k`` is applied, so sample ``k``'s PWM and acceleration belong
together (the residual contract; docs/timing.md).

Deterministic given ``SimConfig.seed`` (``numpy.random.SeedSequence``, one child stream per
purpose). A 30 s flight takes about a second or two.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from scipy.signal import butter, lfilter

from quadcore import effects as effects_mod
from quadcore.logs.flight import TRUTH_SUFFIX
from quadcore.logs.units import DEG_TO_RAD, G0_MPS2, PWM_FULL_SCALE
from quadcore.physics import vehicle as vehicle_mod
from quadcore.physics.dynamics import FlightState
from quadcore.sim import trajectories, usdlog
from quadcore.sim.controller import Controller, Gains
from quadcore.store import store

KINDS = ("figure8", "circle0", "yaw0", "random", "hover", "low_pass", "plan")
TRUTH_FORMAT = "quadcore-sim-truth/1"

class SimulationError(ValueError):
    """A simulation request that cannot be met (unknown effect or parameter, bad config)."""


@dataclass(frozen=True)
class SensorNoise:
    """White-noise standard deviations, per axis where a tuple.

    Measured on the real logs in steady hover (|v| < 0.1 m/s, z > 0.2 m, 61-sample windows
    away from gaps; 15 of the 19 flights have enough hover): the signal minus its
    Savitzky-Golay trend (``quadcore.physics.signals.smooth``, 31 samples), scaled by
    ``1 / sqrt(1 - h0) = 1.038`` to undo the part of white noise the trend absorbs, median
    over flights. acc (0.0050, 0.0065, 0.0051) g; gyro (0.70, 0.74, 0.29) deg/s; position
    ~1e-4 m; velocity ~5e-4 m/s; quaternion components (6.4e-5, 7.6e-5, 2.0e-5), i.e.
    twice that in rotation angle; motor speed ~15 rpm; vbat ~1.2 mV (the ADC steps by
    ~5 mV). Motion capture (estPose): second differences in the hover-heavy flights
    jana04..06 give ~2.5e-4 m.

    ``lowpass_hz`` > 0: the noise of the readings the controller and the log see (position,
    velocity, attitude, gyro) passes a two-pole Butterworth low-pass at this cutoff, run at the
    command rate and scaled back to the standard deviations above: the Crazyflie's firmware
    filters its gyro at 80 Hz (two poles, at 1 kHz) before its controller and its log, and the
    real logs' gyro noise is coloured so (lag-one autocorrelation of the gyro minus its trend
    +0.69 to +0.78 on jana04-06 and jana20; the simulator's white noise -0.07, through this
    filter at 80 Hz +0.72 to +0.74). Only the noise is filtered: the filter's delay of the true
    rate (about 2.5 ms at low frequency) is not simulated. 0 (the default): white, as before.
    """

    acc_g: tuple[float, float, float] = (0.0050, 0.0065, 0.0051)
    gyro_dps: tuple[float, float, float] = (0.70, 0.74, 0.29)
    pos_m: float = 1.0e-4
    vel_mps: float = 5.0e-4
    att_rad: tuple[float, float, float] = (1.3e-4, 1.5e-4, 4.0e-5)
    rpm: float = 15.0
    vbat_V: float = 0.0012
    mocap_pos_m: float = 2.5e-4
    mocap_att_rad: float = 2.0e-4
    lowpass_hz: float = 0.0  # > 0: position, velocity, attitude and gyro noise through the firmware's low-pass


@dataclass(frozen=True)
class Battery:
    """Open-circuit voltage ``ocv_start_V + ocv_rate_V_per_s t`` (floored at ``ocv_min_V``)
    minus ``r_internal_ohm * current_per_thrust_A_per_N * T``. The product (1.05 V/N) is the
    sag per newton of total thrust fitted on the real logs jana00..jana11; their in-flight
    voltage is 3.27-3.58 V and falls by 2-5 mV/s."""

    ocv_start_V: float = 3.9
    ocv_rate_V_per_s: float = -0.003
    ocv_min_V: float = 3.3
    r_internal_ohm: float = 0.105
    current_per_thrust_A_per_N: float = 10.0

    def ocv(self, t_s: np.ndarray) -> np.ndarray:
        return np.maximum(self.ocv_start_V + self.ocv_rate_V_per_s * np.asarray(t_s), self.ocv_min_V)


@dataclass(frozen=True)
class SimConfig:
    """One simulated flight.

    ``kind``: figure8 / circle0 / yaw0 (the polynomial plans: take-off, hover, plan at
    ``timescale`` and ``height_m``, end hover), random (go-to flights to random points in
    ``box_min_m``..``box_max_m`` at peak speeds in ``speed_min_mps``..``speed_max_mps``), hover,
    low_pass (repeated passes at ``low_pass_height_m``, drawn in 0.03-0.08 m when None), plan (the
    lab-format trajectory CSV ``plan_file``, flown as the built-in plans are).
    ``duration_s``: None = the plan's natural length (plans) or 10 s; otherwise the flight is
    cut or its end hover extended to this length. ``log_start_s``: the log holds the flight from
    this time on (its clock starting there), so a flight can begin in a manoeuvre, with the
    vehicle moving, the controller busy and every mechanism with memory (a motor lag, a delay)
    in its state of that moment rather than at rest, as a log switched on in flight (or an
    independent simulator's flight starting on a moving trajectory) is. ``start_offset_m``: the
    vehicle starts this far (world frame) from where the reference starts, hovering: the
    controller's first commands are a hard correction while the rotors still give hover thrust
    (a flight that begins in a manoeuvre from its first logged sample).
    """

    kind: str = "figure8"
    duration_s: float | None = None
    height_m: float = 0.5
    timescale: float = 1.0
    speed_min_mps: float = 0.2
    speed_max_mps: float = 1.0
    box_min_m: tuple[float, float, float] = (-0.5, -0.5, 0.1)
    box_max_m: tuple[float, float, float] = (0.5, 0.5, 1.0)
    low_pass_height_m: float | None = None
    accel_max_mps2: float = 4.0  # peak acceleration of generated moves (random, low_pass)
    seed: int = 0
    battery: Battery = field(default_factory=Battery)
    noise: SensorNoise = field(default_factory=SensorNoise)
    drop_prob: float = 3.0e-4  # per sample: probability that a gap starts (~1.5 gaps per 10 s)
    drop_max_samples: int = 25  # gap length uniform in 1..this many samples (up to 50 ms)
    # Real estPose: median spacing 10.3-11.1 ms (90-97 Hz) but ~55 Hz on average (lost packets).
    mocap_rate_hz: float = 95.0
    mocap_drop_prob: float = 0.42
    mocap_jitter_s: float = 0.0015
    wind_gust_std_mps: float = 0.0
    wind_gust_tau_s: float = 1.0
    start_height_m: float = 0.1  # the flight starts airborne here (no ground contact model)
    log_start_s: float = 0.0  # the log begins this long into the flight (> 0: mid-manoeuvre, filters not settled)
    start_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # where the vehicle starts, from the reference's start
    takeoff_s: float = 2.0
    hover_s: float = 1.0
    end_hover_s: float = 1.0
    log_rate_hz: float = 500.0
    physics_substeps: int = 2
    gains: Gains = field(default_factory=Gains)
    name: str = ""
    plan_file: str = ""  # kind "plan": a trajectory CSV in the lab's format

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SimConfig:
        d = dict(d)
        nested = {"battery": Battery, "noise": SensorNoise, "gains": Gains}
        for key, typ in nested.items():
            if isinstance(d.get(key), dict):
                d[key] = typ(**{k: tuple(v) if isinstance(v, list) else v for k, v in d[key].items()})
        for key in ("box_min_m", "box_max_m", "start_offset_m"):
            if isinstance(d.get(key), list):
                d[key] = tuple(d[key])
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def validate(self) -> None:
        if self.kind not in KINDS:
            raise SimulationError(f"unknown kind {self.kind!r}; choose one of {', '.join(KINDS)}")
        if self.kind == "plan" and not self.plan_file:
            raise SimulationError("kind 'plan' needs a plan_file (a trajectory CSV)")
        if self.duration_s is not None and self.duration_s <= 0:
            raise SimulationError("duration_s must be positive")
        if self.timescale <= 0:
            raise SimulationError("timescale must be positive")
        if self.start_height_m <= 0 or self.height_m <= 0:
            raise SimulationError("start_height_m and height_m must be above the floor (> 0 m): the "
                                  "simulator has no ground contact, and a vehicle at the floor has lost control")
        if self.accel_max_mps2 <= 0:
            raise SimulationError("accel_max_mps2 must be positive")
        if not 0 < self.speed_min_mps <= self.speed_max_mps:
            raise SimulationError("need 0 < speed_min_mps <= speed_max_mps")
        if any(a >= b for a, b in zip(self.box_min_m, self.box_max_m)):
            raise SimulationError("box_min_m must be below box_max_m on every axis")
        if not 0 <= self.log_start_s < flight_duration(self) - 1.0 / max(self.log_rate_hz, 1e-9):
            raise SimulationError("log_start_s must be >= 0 and leave some of the flight to log")
        if self.noise.lowpass_hz < 0:
            raise SimulationError("noise.lowpass_hz must be >= 0 (0: white noise)")
        if self.physics_substeps < 1 or self.log_rate_hz <= 0:
            raise SimulationError("physics_substeps >= 1 and log_rate_hz > 0 required")
        if not 0 <= self.drop_prob < 1 or not 0 <= self.mocap_drop_prob < 1:
            raise SimulationError("drop probabilities must be in [0, 1)")


@dataclass
class SimFlight:
    """A simulated flight: the log bytes, what was logged (SI), and the ground truth.

    Arrays are at every control step ``t_s`` (n,); ``kept`` (n,) says which samples made it
    into the log (the others were dropped). ``*_true`` arrays are noise-free.
    """

    config: SimConfig
    vehicle_name: str
    effects: dict[str, dict[str, float]]
    true_mass_kg: float
    nominal_mass_kg: float
    data: bytes
    t_s: np.ndarray
    kept: np.ndarray
    p_true: np.ndarray
    v_true: np.ndarray
    q_true: np.ndarray
    omega_true: np.ndarray
    sf_true: np.ndarray
    f_map_N: np.ndarray
    f_actual_N: np.ndarray
    pwm_raw: np.ndarray
    vbat_V: np.ndarray
    wind_w_mps: np.ndarray
    reference: trajectories.Reference

    def truth(self) -> dict:
        kept_t = self.t_s[self.kept]
        gaps = np.diff(kept_t) > 1.5 / self.config.log_rate_hz
        return {
            "format": TRUTH_FORMAT,
            "name": self.config.name,
            "vehicle": self.vehicle_name,
            "nominal_mass_kg": self.nominal_mass_kg,
            "true_mass_kg": self.true_mass_kg,
            "effects": self.effects,
            "seed": self.config.seed,
            "config": self.config.to_dict(),
            "samples": int(self.kept.sum()),
            "samples_dropped": int((~self.kept).sum()),
            "gaps": int(gaps.sum()),
            "duration_s": float(self.t_s[-1] - self.t_s[0]) if len(self.t_s) else 0.0,
            "wind_mean_w_mps": [float(x) for x in self.wind_w_mps.mean(axis=0)] if len(self.t_s) else [0.0] * 3,
        }

    def write(self, path: str | Path) -> tuple[Path, Path]:
        return write_flight(self, path)


# ---------------------------------------------------------------------------------------
# Effects
# ---------------------------------------------------------------------------------------

def validate_effects(effects: dict[str, dict[str, float]] | None) -> dict[str, dict[str, float]]:
    """Check names and parameters against :mod:`quadcore.effects`; fill defaults; floats."""
    out: dict[str, dict[str, float]] = {}
    known = effects_mod.registry()
    for name, params in (effects or {}).items():
        if name not in known:
            raise SimulationError(f"unknown effect {name!r}; known: {', '.join(known)}")
        eff = known[name]
        allowed = {p.name: p for p in eff.parameters}
        params = dict(params or {})
        bad = [k for k in params if k not in allowed]
        if bad:
            raise SimulationError(
                f"effect {name!r} has no parameter {', '.join(map(repr, bad))}; its parameters: {', '.join(allowed)}")
        full = eff.defaults()
        for k, v in params.items():
            try:
                full[k] = float(v)
            except (TypeError, ValueError):
                raise SimulationError(f"effect {name!r}: parameter {k!r} must be a number, got {v!r}") from None
            if not math.isfinite(full[k]):
                raise SimulationError(f"effect {name!r}: parameter {k!r} must be finite")
        try:
            eff.check(full)
        except ValueError as exc:
            raise SimulationError(f"{name}: {exc}") from None
        out[name] = full
    return out


def _effect_hooks(eff: dict[str, dict[str, float]], context) -> tuple[list, list]:
    """The effects' simulator hooks, and the (effect, params) pairs simulated through their
    memoryless wrench (those without a hook)."""
    hooks, generic = [], []
    for name, params in eff.items():
        effect = effects_mod.get(name)
        try:
            hook = effect.simulator(params, context)
        except ValueError as exc:
            raise SimulationError(f"{name}: {exc}") from None
        if hook is not None:
            hooks.append(hook)
        else:
            generic.append((effect, params))
    return hooks, generic


def _overrides(hook, method: str) -> bool:
    return getattr(type(hook), method) is not getattr(effects_mod.SimHook, method)


def _one_sample_state(t, p, v, q, w, sf, pwm, vbat, motor, R, v_b, f_map) -> FlightState:
    return FlightState(
        t_s=np.array([t]), p_w_m=np.array([p]), v_w_mps=np.array([v]), q_xyzw=np.array([q]),
        omega_b_radps=np.array([w]), sf_b_mps2=np.array([sf]), pwm=np.array([pwm]), vbat_V=np.array([vbat]),
        motor_radps=np.array([motor]), R_wb=np.array([R]), v_b_mps=np.array([v_b]), f_rotor_N=np.array([f_map]),
    )


# ---------------------------------------------------------------------------------------
# Small float helpers for the inner loop
# ---------------------------------------------------------------------------------------

def _rot(q):
    x, y, z, w = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def _qmul_exp(q, wx, wy, wz, h):
    """q (x) exp(w h): rotate by the body-frame rotation vector w h, renormalised."""
    ax, ay, az = wx * h, wy * h, wz * h
    th = math.sqrt(ax * ax + ay * ay + az * az)
    if th < 1e-12:
        s, c = 0.5, 1.0
    else:
        s, c = math.sin(0.5 * th) / th, math.cos(0.5 * th)
    x2, y2, z2, w2 = ax * s, ay * s, az * s, c
    x1, y1, z1, w1 = q
    x = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    y = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    z = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    w = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return (x / n, y / n, z / n, w / n)


# ---------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------

def _plan_of(config: SimConfig) -> trajectories.PolyTrajectory:
    """A plan kind's polynomial plan: built in, or (kind "plan") from ``plan_file``."""
    try:
        return trajectories.load_plan(config.plan_file if config.kind == "plan" else config.kind)
    except (OSError, ValueError) as exc:
        raise SimulationError(f"plan {config.plan_file or config.kind}: {exc}") from None


def flight_duration(config: SimConfig) -> float:
    if config.duration_s is not None:
        return float(config.duration_s)
    if config.kind in (*trajectories.BUILTIN_PLANS, "plan"):
        plan = _plan_of(config)
        return trajectories.plan_flight_duration(plan, config.timescale, config.takeoff_s, config.hover_s,
                                                 config.end_hover_s)
    return 10.0


def build_reference(config: SimConfig, t_s: np.ndarray, rng: np.random.Generator) -> trajectories.Reference:
    c = config
    if c.kind in (*trajectories.BUILTIN_PLANS, "plan"):
        return trajectories.plan_reference(t_s, _plan_of(c), c.height_m, c.timescale,
                                           c.start_height_m, c.takeoff_s, c.hover_s)
    if c.kind == "hover":
        return trajectories.hover_reference(t_s, c.height_m, c.start_height_m, c.takeoff_s)
    if c.kind == "random":
        return trajectories.random_reference(t_s, rng, c.box_min_m, c.box_max_m, c.speed_min_mps, c.speed_max_mps,
                                             c.height_m, c.start_height_m, c.takeoff_s, c.accel_max_mps2)
    if c.kind == "low_pass":
        return trajectories.low_pass_reference(t_s, rng, c.box_min_m, c.box_max_m, c.speed_min_mps,
                                               c.speed_max_mps, c.height_m, c.low_pass_height_m,
                                               c.start_height_m, c.takeoff_s, c.accel_max_mps2)
    raise SimulationError(f"unknown kind {c.kind!r}")


# ---------------------------------------------------------------------------------------
# The simulator
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _TrueBody:
    """The vehicle as the effects make it fly: true mass and inertia, the air's velocity
    (world, m/s, per log sample), and the effects' hooks by what they do."""

    mass_kg: float
    inertia_kgm2: np.ndarray
    air_w_mps: np.ndarray
    chain: list  # hooks that change the rotor thrusts (map thrust -> actual)
    extra: list  # hooks that add a wrench (with memory)
    generic: list  # (effect, params) simulated through their memoryless wrench
    airspeed: bool  # some hook sets a wind: effects that act on airspeed see v - wind


def _true_body(veh: vehicle_mod.Vehicle, eff: dict[str, dict[str, float]], context, n: int) -> _TrueBody:
    """Apply the effects' hooks to the nominal vehicle (mass, inertia, air velocity)."""
    hooks, generic = _effect_hooks(eff, context)
    m_true, J, air = float(veh.mass_kg), np.asarray(veh.inertia_kgm2, float), np.zeros((n, 3))
    try:
        for hook in hooks:
            m_true = float(hook.true_mass_kg(m_true))
            J = np.asarray(hook.true_inertia_kgm2(J), float)
            hook_air = hook.air_velocity_w_mps()
            air = air + hook_air if hook_air is not None else air
    except ValueError as exc:
        raise SimulationError(f"effects {', '.join(eff)}: {exc}") from None
    if m_true <= 0:
        raise SimulationError(f"effects {', '.join(eff)}: the true mass must be positive")
    return _TrueBody(m_true, J, air, [hk for hk in hooks if _overrides(hk, "rotor_thrusts")],
                     [hk for hk in hooks if _overrides(hk, "wrench")], generic, bool(np.any(air)))


@dataclass(frozen=True)
class _Noise:
    """Sensor noise for every log sample, drawn up front (the controller sees the same noisy
    readings as the log): position m, velocity m/s, attitude rad, gyro rad/s, accelerometer g,
    motor rpm, battery V."""

    pos: np.ndarray
    vel: np.ndarray
    att: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    rpm: np.ndarray
    vbat: np.ndarray

    def sampled(self, rows: slice) -> _Noise:
        return _Noise(*(getattr(self, f.name)[rows] for f in fields(self)))


def _draw_noise(rng: np.random.Generator, noise: SensorNoise, n: int, rate_hz: float) -> _Noise:
    """White noise per command step (``rate_hz``); with ``noise.lowpass_hz`` the readings' noise
    low-passed (:class:`SensorNoise`)."""
    band = _lowpass(noise.lowpass_hz, rate_hz)
    return _Noise(
        pos=band(rng.normal(0.0, 1.0, (n, 3))) * noise.pos_m,
        vel=band(rng.normal(0.0, 1.0, (n, 3))) * noise.vel_mps,
        att=band(rng.normal(0.0, 1.0, (n, 3))) * np.asarray(noise.att_rad),
        gyro=band(rng.normal(0.0, 1.0, (n, 3))) * np.asarray(noise.gyro_dps) * DEG_TO_RAD,
        acc=rng.normal(0.0, 1.0, (n, 3)) * np.asarray(noise.acc_g),
        rpm=rng.normal(0.0, 1.0, (n, 4)) * noise.rpm,
        vbat=rng.normal(0.0, 1.0, n) * noise.vbat_V,
    )


def _lowpass(cutoff_hz: float, rate_hz: float):
    """Columns of unit white noise through a causal two-pole Butterworth low-pass at ``cutoff_hz``
    (sampled at ``rate_hz``), divided by its noise gain ``sqrt(Σ h²)`` (``h`` its impulse
    response) so that the standard deviation stays 1; the identity for ``cutoff_hz`` 0."""
    if cutoff_hz <= 0:
        return lambda x: x
    if not cutoff_hz < rate_hz / 2:
        raise SimulationError(f"noise.lowpass_hz {cutoff_hz:g} must be below half the command rate {rate_hz:g} Hz")
    b, a = butter(2, cutoff_hz, fs=rate_hz)
    h = lfilter(b, a, np.eye(1, int(rate_hz))[0])  # the impulse response, one second of it
    gain = float(np.sqrt(np.sum(h**2)))
    return lambda x: lfilter(b, a, x, axis=0) / gain


@dataclass
class _Record:
    """The true state at every log sample (world p, v; body w; body specific force sf) and
    the actuation: map and actual rotor thrust N, PWM as logged, battery mV as logged."""

    P: np.ndarray
    V: np.ndarray
    W: np.ndarray
    SF: np.ndarray
    Q: np.ndarray
    F_MAP: np.ndarray
    F_ACT: np.ndarray
    PWM: np.ndarray
    VBAT_MV: np.ndarray

    def sampled(self, rows: slice) -> _Record:
        return _Record(*(getattr(self, f.name)[rows] for f in fields(self)))

    @classmethod
    def empty(cls, n: int) -> _Record:
        P, V, W, SF = (np.zeros((n, 3)) for _ in range(4))
        return cls(P, V, W, SF, np.zeros((n, 4)), np.zeros((n, 4)), np.zeros((n, 4)),
                   np.zeros((n, 4), dtype=np.int64), np.zeros(n, dtype=np.int64))


def _command(ctrl: Controller, pv, dt: float, vbat: float, sensed, ref_k) -> tuple[np.ndarray, np.ndarray]:
    """The controller's rotor thrusts from the sensed state -> integer PWM at the battery
    voltage (as logged) -> the map's thrust for that PWM, N. Returns (pwm_raw, f_map_N)."""
    pe, ve, qe, we = sensed
    f_cmd, _, _ = ctrl.step(dt, pe, ve, _rot(qe), we, *ref_k)
    f_max = float(pv.thrust_N(np.array(1.0), np.array(vbat)))
    f_clip = np.clip(np.array(f_cmd), 0.0, f_max)
    pwm_raw = np.rint(pv.pwm_for_thrust(f_clip, vbat) * PWM_FULL_SCALE).astype(np.int64)
    return pwm_raw, pv.thrust_N(pwm_raw / PWM_FULL_SCALE, vbat)


def _body_wrench(body: _TrueBody, veh, k_F: float, A, fa, st_args, R, wk, k: int, j: int):
    """Thrust T (N), body force Fb (N) and torque tau (N m) on the true body for one physics
    step: the rotors' thrusts ``fa`` through the allocation, plus every effect's wrench
    evaluated on the true state (against the air where a hook sets a wind)."""
    T = fa[0] + fa[1] + fa[2] + fa[3]
    tau = [A[r][0] * fa[0] + A[r][1] * fa[1] + A[r][2] * fa[2] + A[r][3] * fa[3] for r in (1, 2, 3)]
    Fb = [0.0, 0.0, T]
    generic, extra = body.generic, body.extra
    if generic or extra:
        t, p, v, q, w, pwm_si, vbat, f_map = st_args
        vb = [R[0][i] * v[0] + R[1][i] * v[1] + R[2][i] * v[2] for i in range(3)]
        motor = [math.sqrt(max(x, 0.0) / k_F) if k_F > 0 else 0.0 for x in fa]
        st = _one_sample_state(t, p, v, q, w, [0.0, 0.0, 0.0], pwm_si, vbat, motor, R, vb, f_map)
        airspeed = body.airspeed
        if airspeed:
            va = [v[i] - wk[i] for i in range(3)]
            vab = [R[0][i] * va[0] + R[1][i] * va[1] + R[2][i] * va[2] for i in range(3)]
            st_air = replace(st, v_w_mps=np.array([va]), v_b_mps=np.array([vab]))
        for effect, params in generic:
            fe, te = effect.wrench(st_air if airspeed and effect.acts_on_airspeed else st, veh, params)
            Fb[0] += fe[0, 0]; Fb[1] += fe[0, 1]; Fb[2] += fe[0, 2]
            tau[0] += te[0, 0]; tau[1] += te[0, 1]; tau[2] += te[0, 2]
        for hook in extra:
            out = hook.wrench(st, k, j)
            if out is not None:
                (f0, f1, f2), (t0, t1, t2) = out
                Fb[0] += f0; Fb[1] += f1; Fb[2] += f2
                tau[0] += t0; tau[1] += t1; tau[2] += t2
    return T, Fb, tau


def _integrate(p, v, q, w, R, sf, tau, Jt, Ji, h: float):
    """One semi-implicit Euler step: Newton in the world frame (specific force ``sf`` in the
    body frame, rotated by R_wb, plus gravity), Euler's equation in the body frame
    (``J dw/dt = tau - w x J w``), then ``q = q (x) exp(w h)``. Returns (p, v, q, w)."""
    ax = R[0][0] * sf[0] + R[0][1] * sf[1] + R[0][2] * sf[2]
    ay = R[1][0] * sf[0] + R[1][1] * sf[1] + R[1][2] * sf[2]
    az = R[2][0] * sf[0] + R[2][1] * sf[1] + R[2][2] * sf[2] - G0_MPS2
    v = [v[0] + ax * h, v[1] + ay * h, v[2] + az * h]
    p = [p[0] + v[0] * h, p[1] + v[1] * h, p[2] + v[2] * h]
    if p[2] < 0.0:  # no ground contact model: keep out of the floor (the references never go there)
        p[2] = 0.0
        v[2] = max(v[2], 0.0)
    Jw = [Jt[r][0] * w[0] + Jt[r][1] * w[1] + Jt[r][2] * w[2] for r in range(3)]
    g0 = tau[0] - (w[1] * Jw[2] - w[2] * Jw[1])
    g1 = tau[1] - (w[2] * Jw[0] - w[0] * Jw[2])
    g2 = tau[2] - (w[0] * Jw[1] - w[1] * Jw[0])
    w = [w[r] + h * (Ji[r][0] * g0 + Ji[r][1] * g1 + Ji[r][2] * g2) for r in range(3)]
    return p, v, _qmul_exp(q, w[0], w[1], w[2], h), w


def _fly(config: SimConfig, veh: vehicle_mod.Vehicle, ref: trajectories.Reference, body: _TrueBody,
         noise: _Noise, t: np.ndarray) -> _Record:
    """The closed loop: at each log sample the battery, the sensors, the controller and the
    PWM; then ``physics_substeps`` physics steps with the rotor commands held."""
    n, dt, S = len(t), float(t[1] - t[0]), int(config.physics_substeps)
    h = dt / S
    sag_per_N = config.battery.r_internal_ohm * config.battery.current_per_thrust_A_per_N
    p = [float(x) + float(d) for x, d in zip(ref.p_w_m[0], config.start_offset_m)]
    v, w = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    yaw0 = float(ref.yaw_rad[0])
    q = (0.0, 0.0, math.sin(0.5 * yaw0), math.cos(0.5 * yaw0))
    Jt = tuple(tuple(float(x) for x in row) for row in body.inertia_kgm2)
    Ji = tuple(tuple(float(x) for x in row) for row in np.linalg.inv(body.inertia_kgm2))
    A = tuple(tuple(float(x) for x in row) for row in veh.allocation)
    T_prev = body.mass_kg * G0_MPS2
    ctrl, pv, k_F = Controller(veh, config.gains), veh.pwm_vbat, veh.motor_speed.k_F_N_per_radps2
    rec = _Record.empty(n)
    refs = list(zip(ref.p_w_m.tolist(), ref.v_w_mps.tolist(), ref.a_w_mps2.tolist(), ref.yaw_rad.tolist(),
                    ref.yaw_rate_radps.tolist(), ref.yaw_acc_radps2.tolist()))
    npos, nvel, ngyro, att_noise = noise.pos.tolist(), noise.vel.tolist(), noise.gyro.tolist(), noise.att.tolist()
    vbat_noisy = (config.battery.ocv(t) + noise.vbat).tolist()
    airl = body.air_w_mps.tolist()

    for k in range(n):
        tk = k * dt
        # battery: the voltage the ESCs see is the one logged (whole mV)
        vbat_mV = int(round((vbat_noisy[k] - sag_per_N * T_prev) * 1000.0))
        vbat_mV = min(max(vbat_mV, 0), 65535)
        vbat = vbat_mV * 1e-3
        rec.VBAT_MV[k] = vbat_mV
        # sensors as the controller sees them
        an = att_noise[k]
        sensed = ((p[0] + npos[k][0], p[1] + npos[k][1], p[2] + npos[k][2]),
                  (v[0] + nvel[k][0], v[1] + nvel[k][1], v[2] + nvel[k][2]),
                  _qmul_exp(q, an[0], an[1], an[2], 1.0),
                  (w[0] + ngyro[k][0], w[1] + ngyro[k][1], w[2] + ngyro[k][2]))
        pwm_raw, f_map_arr = _command(ctrl, pv, dt, vbat, sensed, refs[k])
        rec.PWM[k] = pwm_raw
        rec.F_MAP[k] = f_map_arr
        f_map = f_map_arr.tolist()
        pwm_si = (pwm_raw / PWM_FULL_SCALE).tolist()

        for j in range(S):
            fa = now = f_map
            for hook in body.chain:
                if j == 0:
                    now = hook.thrusts_now(now)
                fa = hook.rotor_thrusts(fa, k, j)
                now = fa if now is None else now
            R = _rot(q)
            T, Fb, tau = _body_wrench(body, veh, k_F, A, fa, (tk + j * h, p, v, q, w, pwm_si, vbat, f_map), R,
                                      airl[k], k, j)
            sf = (Fb[0] / body.mass_kg, Fb[1] / body.mass_kg, Fb[2] / body.mass_kg)
            if j == 0:  # the sensors: the state and the rotors' thrusts at t_k (the body integrates their mean)
                sf_now = sf[2] + (sum(now) - T) / body.mass_kg
                rec.P[k], rec.V[k], rec.Q[k], rec.W[k], rec.SF[k] = p, v, q, w, (sf[0], sf[1], sf_now)
                rec.F_ACT[k] = now
                T_prev = T
            p, v, q, w = _integrate(p, v, q, w, R, sf, tau, Jt, Ji, h)
    return rec


def simulate(config: SimConfig, vehicle: vehicle_mod.Vehicle | None = None,
             effects: dict[str, dict[str, float]] | None = None) -> SimFlight:
    """Fly one closed-loop flight and encode it as a uSD log. See the module docstring."""
    config.validate()
    veh = vehicle if vehicle is not None else vehicle_mod.load()
    if veh.n_rotors != 4:
        raise SimulationError(f"vehicle {veh.name!r} has {veh.n_rotors} rotors; the log format holds 4")
    eff = validate_effects(effects)
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(6)]
    ref_rng, noise_rng, drop_rng, gust_rng, mocap_rng, clock_rng = streams

    every = steps_per_log_sample(config, veh)
    rate = float(config.log_rate_hz) * every  # the controller's rate
    dt = 1.0 / rate
    n = max(int(round(flight_duration(config) * float(config.log_rate_hz))), 2) * every
    t = np.arange(n) * dt
    ref = build_reference(config, t, ref_rng)
    context = effects_mod.SimContext(t_s=t, dt_s=dt, h_s=dt / int(config.physics_substeps), vehicle=veh,
                                     config=config, rng=gust_rng)
    body = _true_body(veh, eff, context, n)
    noise = _draw_noise(noise_rng, config.noise, n, rate)
    rec = _fly(config, veh, ref, body, noise, t)
    lost = lost_control(t, rec.P, rec.Q)
    if lost is not None:
        flown = ", ".join(name + (" (" + ", ".join(f"{k}={v:.3g}" for k, v in params.items()) + ")"
                                  if len(params) <= 3 else f" ({len(params)} parameters)")
                          for name, params in eff.items()) or "no effects"
        raise SimulationError(f"the simulated vehicle lost control: {lost}. The simulator's controller "
                              f"(quadcore.sim.controller, tuned for the nominal vehicle) cannot fly it with "
                              f"{flown}; no log is written")
    # the log samples the controller's steps, from log_start_s on (its clock restarting there)
    skip = min(int(round(config.log_start_s * float(config.log_rate_hz))), n // every - 2) * every
    logged = slice(skip, None, every)
    t, rec, noise = t[logged] - t[skip], rec.sampled(logged), noise.sampled(logged)

    data, kept = usdlog.encode(config, t, rec.P, rec.V, rec.Q, rec.W, rec.SF, rec.F_ACT, rec.PWM, rec.VBAT_MV,
                         veh.motor_speed, noise.pos, noise.vel, noise.att, noise.gyro, noise.acc, noise.rpm,
                         drop_rng, mocap_rng, clock_rng)
    return SimFlight(
        config=config, vehicle_name=veh.name, effects=eff, true_mass_kg=body.mass_kg,
        nominal_mass_kg=float(veh.mass_kg), data=data, t_s=t, kept=kept, p_true=rec.P, v_true=rec.V,
        q_true=rec.Q, omega_true=rec.W, sf_true=rec.SF, f_map_N=rec.F_MAP, f_actual_N=rec.F_ACT,
        pwm_raw=rec.PWM, vbat_V=rec.VBAT_MV * 1e-3, wind_w_mps=body.air_w_mps[logged],
        reference=trajectories.Reference(*(np.asarray(getattr(ref, f.name))[logged] for f in fields(ref))),
    )


def lost_control(t_s: np.ndarray, p_w_m: np.ndarray, q_xyzw: np.ndarray) -> str | None:
    """Why a simulated flight is no longer a flight, or None: the vehicle turned upside down (its
    body z axis below the horizon: ``R_wb[2, 2] = 1 - 2 (q_x^2 + q_y^2) < 0``) or reached the
    floor (``p_w_z = 0``). The simulator has no ground contact: :func:`_integrate` holds the body
    out of the floor by setting its height and downward velocity to zero, a jump no force
    explains, so the log's velocity would contradict its accelerometer (the physics gate,
    :func:`quadcore.physics.gate.state_estimate_problem`, refuses such a log); the references never
    go there, so a vehicle that does has lost control (an unstable closed loop)."""
    up = 1.0 - 2.0 * (q_xyzw[:, 0] ** 2 + q_xyzw[:, 1] ** 2)
    flipped, floor = np.flatnonzero(up < 0.0), np.flatnonzero(p_w_m[:, 2] <= 0.0)
    first = [(t_s[i[0]], what) for i, what in ((flipped, "turned upside down"), (floor, "reached the floor")) if len(i)]
    if not first:
        return None
    at, what = min(first)
    return f"it {what} at t = {at:.2f} s"


def steps_per_log_sample(config: SimConfig, veh: vehicle_mod.Vehicle) -> int:
    """Controller steps per log sample: the controller runs at the vehicle's command rate
    (``[thrust_map.pwm_vbat] command_period_s``, as the firmware does) and the log keeps every
    this many of its steps. Raises :class:`SimulationError` when the log period is not a whole
    number of command periods."""
    ratio = veh.pwm_vbat.command_period_s * float(config.log_rate_hz)
    every = int(round(1.0 / ratio))
    if every < 1 or abs(every * ratio - 1.0) > 1e-9:
        raise SimulationError(
            f"log rate {config.log_rate_hz:g} Hz: the simulator logs every n-th step of the controller, which runs "
            f"at the vehicle's command rate {1.0 / veh.pwm_vbat.command_period_s:g} Hz; choose a log rate that "
            "divides it")
    return every


# ---------------------------------------------------------------------------------------
# Writing flights and sets
# ---------------------------------------------------------------------------------------

def truth_path(log_path: str | Path) -> Path:
    """``<log>.truth.json`` beside the log (a ``.json`` name: log discovery skips it)."""
    return Path(str(log_path) + TRUTH_SUFFIX)


def write_flight(sim: SimFlight, path: str | Path) -> tuple[Path, Path]:
    """Write the log and its ground-truth sidecar. Returns (log path, truth path)."""
    path = Path(path)
    store.write_bytes(sim.data, path)  # atomic: a watched raw folder never sees half a log
    truth = sim.truth()
    truth["log_file"] = path.name
    tp = store.write_text(json.dumps(truth, indent=2, sort_keys=False) + "\n", truth_path(path))
    return path, tp


def read_truth(log_path: str | Path) -> dict:
    return json.loads(truth_path(log_path).read_text())


def simulate_set(
    out_dir: str | Path,
    configs: list[SimConfig],
    effects: dict[str, dict[str, float]] | list[dict[str, dict[str, float]]] | None = None,
    vehicle: vehicle_mod.Vehicle | None = None,
    prefix: str = "sim",
) -> list[tuple[Path, Path]]:
    """Simulate and write several flights as ``<out_dir>/sim000``, ``sim001``, ... (+ truth).

    ``effects`` is one dict for every flight, or a list with one dict per flight. A flight the
    simulator cannot fly (its closed loop loses control, :func:`lost_control`) does not stop the
    others: they are written, and then one :class:`SimulationError` names every flight left out
    and why.
    """
    out = Path(out_dir)
    veh = vehicle if vehicle is not None else vehicle_mod.load()
    per_flight = effects if isinstance(effects, list) else [effects or {}] * len(configs)
    if len(per_flight) != len(configs):
        raise SimulationError(f"{len(per_flight)} effect sets for {len(configs)} flights")
    for e in per_flight:
        validate_effects(e)  # fail before simulating anything
    written, lost = [], []
    for i, (cfg, eff) in enumerate(zip(configs, per_flight)):
        name = f"{prefix}{i:03d}"
        cfg = cfg if cfg.name else replace(cfg, name=name)
        try:
            flown = simulate(cfg, veh, eff)
        except SimulationError as exc:
            lost.append(f"{name}: {exc}")
            continue
        written.append(write_flight(flown, out / name))
    if lost:
        raise SimulationError(f"{len(lost)} of {len(configs)} flights not written ({len(written)} written to {out}): "
                              + "; ".join(lost))
    return written


def default_flights(seed: int = 0) -> list[SimConfig]:
    """A small varied set (about 60 s of flight) that excites every effect: a fast figure 8
    (up to 1.2 m/s, 3 m/s^2), a circle, yawing (about 4 rad/s), two random go-to flights
    (slow and up to 1.5 m/s, heights 0.2-1.0 m) and low passes at 3-8 cm."""
    return [
        SimConfig(kind="figure8", timescale=1.0, height_m=0.5, seed=seed),
        SimConfig(kind="circle0", timescale=2.5, height_m=0.5, seed=seed + 1),
        SimConfig(kind="yaw0", timescale=3.0, height_m=0.5, duration_s=10.0, seed=seed + 2),
        SimConfig(kind="random", speed_min_mps=0.2, speed_max_mps=0.8, duration_s=10.0,
                  box_min_m=(-0.5, -0.5, 0.2), box_max_m=(0.5, 0.5, 1.0), seed=seed + 3),
        SimConfig(kind="random", speed_min_mps=0.8, speed_max_mps=1.5, duration_s=10.0,
                  box_min_m=(-0.7, -0.7, 0.2), box_max_m=(0.7, 0.7, 1.0), seed=seed + 4),
        SimConfig(kind="low_pass", speed_min_mps=0.3, speed_max_mps=0.8, duration_s=12.0,
                  box_min_m=(-0.6, -0.5, 0.1), box_max_m=(0.6, 0.5, 1.0), seed=seed + 5),
    ]


def parse_effect_spec(spec: str) -> tuple[str, dict[str, float]]:
    """``"rotor_drag:k_x_s_per_m=0.3,k_y_s_per_m=0.3"`` -> ``("rotor_drag", {...})``, checked
    against the effect library (raises :class:`SimulationError`)."""
    name, _, rest = spec.partition(":")
    name = name.strip()
    if not name:
        raise SimulationError(f"bad effect {spec!r}: expected NAME:param=value,param=value")
    params: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise SimulationError(f"bad effect parameter {item!r} in {spec!r}: expected param=value")
        try:
            params[key.strip()] = float(value)
        except ValueError:
            raise SimulationError(
                f"effect {name!r}: parameter {key.strip()!r} must be a number, got {value!r}") from None
    known = effects_mod.registry()
    if name not in known:
        raise SimulationError(f"unknown effect {name!r}; known: {', '.join(known)}")
    if not params:
        raise SimulationError(
            f"effect {name!r} needs parameters (its defaults mean 'no effect'), e.g. "
            f"{name}:{known[name].parameters[0].name}=VALUE; parameters: "
            f"{', '.join(p.name for p in known[name].parameters)}")
    validate_effects({name: params})
    return name, params
