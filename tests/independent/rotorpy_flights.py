"""Flights from an independent simulator (rotorpy), written as uSD logs by this project's writer.

Why: the project's own simulator shares the project's conventions (how the modelled wrench is
timed against the measured one, which forms the effects take, how a flight starts), so errors
common to both are invisible on its flights. rotorpy (Folk et al., on the package index) has its
own Crazyflie, its own rotor-drag model with a vertical part, its own first-order motor lag, its
own SE3 controller and trajectories. Nothing of rotorpy is imported by ``quadcore``.

**What is simulated.** rotorpy's ``Multirotor._s_dot_fn`` (its state derivative: rigid body,
rotor thrust ``k_eta w_i^2``, yaw moment ``k_m w_i^2``, rotor drag ``H_i = -w_i diag(k_d, k_d,
k_z) v_i`` at each hub's local air velocity ``v_i = v_b + Omega x r_i``, parasitic drag
``D = -|v_b| diag(c_Dx, c_Dy, c_Dz) v_b``, rotor speeds ``tau_m dw_i/dt = w_cmd,i - w_i``)
integrated with a fixed-step RK4 at ``RATE_HZ * SUBSTEPS`` (its own ``step`` calls
``solve_ivp`` per step, far slower), with the rotor-speed command held over a control period.
rotorpy's ``SE3Control`` runs at ``RATE_HZ`` (500 Hz, the Crazyflie's stabiliser rate) on the
true state, as in rotorpy's own ``simulate``. "No lag" (``Physics.tau_m = None``) sets the
rotor speeds to the command at every control step. Trajectories: rotorpy's circle (with a
vertical component), Lissajous and min-snap through random waypoints (re-drawn until the plan's
peak thrust stays below ``THRUST_MARGIN`` of the rotors' maximum).

**Where a log starts.** ``Flight.warmup_s`` of flight is simulated before the log's first
sample: with a warm-up the log begins mid-manoeuvre (the rotors lag a changing command); the
min-snap flights begin at rest, in hover (the rotors at their steady state).

**What is logged** at each log sample ``t_k`` (every control step at 500 Hz, every fifth at
100 Hz), through :func:`quadcore.sim.usdlog.encode` (the real logs' format, gaps, motion capture)
with the sensor noise measured on the real logs (:class:`quadcore.sim.simulation.SensorNoise`):
the state at ``t_k`` (position, velocity, attitude, body rates), the accelerometer = rotorpy's
body force at ``t_k`` over its mass (after the command of ``t_k`` is applied: the same instant
as the rotor speeds), the actual rotor speeds (for the motor-speed map, in firmware order m1
front-right, m2 back-right, m3 back-left, m4 front-left = rotorpy's r2, r3, r4, r1), the
commanded ones as PWM through the PWM/voltage map's inverse at the logged battery voltage (for
the PWM map), and the battery voltage.

**Cache.** The logs of a fleet go to ``cache_root() / <fleet name>-<digest>``, the digest of
the fleet's specification, the generating code's source (``GENERATING``), the project's log
writer, encoder and noise model (``LOG_SETTINGS``), the vehicle file and rotorpy's version. Every file is written whole
(a temporary name, then renamed) and a fleet is complete once its ``done`` marker exists, so
an interrupted run resumes where it stopped. Deterministic: every random draw comes from the
flight's seed.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import io
import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
VEHICLE_FILE = REPO / "quadcore" / "vehicles" / "rotorpy_crazyflie.toml"
RATE_HZ = 500.0  # the controller's rate and the fast log rate
SUBSTEPS = 2  # RK4 steps per control period: 1 kHz
LOG_RATES_HZ = (500, 100)
THRUST_MARGIN = 0.8  # a min-snap plan's peak thrust, at most this share of the rotors' maximum
MAX_ACCEL_MPS2 = 5.0  # a min-snap plan's peak acceleration (steeper plans saturate the rotors in attitude)
MAX_YAW_RATE_RADPS = 3.0  # a min-snap plan's peak yaw rate (its yaw polynomials can overshoot)
MAX_BODY_RATE_RADPS = 8.0  # a simulated flight beyond this (or saturating its rotors) has lost control
FIRMWARE_FROM_ROTORPY = np.array([1, 2, 3, 0])  # m1..m4 = rotorpy's r2, r3, r4, r1
G_ROTORPY_MPS2 = 9.81  # rotorpy's gravity (this project's is 9.80665; only hover speed depends on it)


def base_params() -> dict:
    """rotorpy's Crazyflie parameters (a copy)."""
    from rotorpy.vehicles.crazyflie_params import quad_params

    return {k: (dict(v) if isinstance(v, dict) else v) for k, v in quad_params.items()}


@dataclass(frozen=True)
class Physics:
    """Which of rotorpy's effects are on: rotor drag per rotor ``k_d`` (horizontal) and ``k_z``
    (vertical) in kg/rad, parasitic drag ``c_D_xy`` (= c_Dx = c_Dy) and ``c_D_z`` in kg/m, the
    motor time constant ``tau_m`` in s (None: no lag). Defaults: everything off."""

    k_d: float = 0.0
    k_z: float = 0.0
    c_D_xy: float = 0.0
    c_D_z: float = 0.0
    tau_m: float | None = None

    @classmethod
    def rotorpy_default(cls) -> Physics:
        """rotorpy's Crazyflie as it comes: rotor drag with its vertical part, its motor lag."""
        p = base_params()
        return cls(k_d=p["k_d"], k_z=p["k_z"], c_D_xy=p["c_Dx"], c_D_z=p["c_Dz"], tau_m=p["tau_m"])

    def params(self) -> dict:
        p = base_params()
        p.update(k_d=self.k_d, k_z=self.k_z, c_Dx=self.c_D_xy, c_Dy=self.c_D_xy, c_Dz=self.c_D_z,
                 tau_m=self.tau_m if self.tau_m is not None else 1.0)
        return p


@dataclass(frozen=True)
class Flight:
    """One flight: a rotorpy trajectory ``kind`` (circle, lissajous, minsnap) drawn from
    ``seed``, ``duration_s`` of log after ``warmup_s`` of unlogged flight."""

    name: str
    kind: str
    seed: int
    duration_s: float
    warmup_s: float = 0.0


@dataclass(frozen=True)
class Fleet:
    name: str
    physics: Physics
    flights: tuple[Flight, ...]

    def digest(self) -> str:
        return _digest(self)[:12]


FLIGHT_S = 8.0


def standard_flights(prefix: str = "f", seed: int = 0) -> tuple[Flight, ...]:
    """Six varied flights of ``FLIGHT_S`` each: two circles and a Lissajous figure that start
    mid-manoeuvre (1.5 s of unlogged flight first; ``f0``, ``f1``, ``f3``), three min-snap plans
    that start at rest in hover (``f2``, ``f4``, ``f5``)."""
    kinds = [("circle", 1.5), ("lissajous", 1.5), ("minsnap", 0.0), ("circle", 1.5), ("minsnap", 0.0),
             ("minsnap", 0.0)]
    return tuple(Flight(f"{prefix}{i}", kind, seed + i, FLIGHT_S, warm) for i, (kind, warm) in enumerate(kinds))


def fleets() -> dict[str, Fleet]:
    """The fleets of the independent-physics suite, each the same six flights
    (:func:`standard_flights`) with some of rotorpy's effects on: nothing (``clean``); the motor
    lag alone (``lag``); rotorpy's Crazyflie as it comes (``rotor_drag``: rotor drag with its
    vertical part, and the lag); rotor drag without its vertical part (``rotor_drag_xy``, and the
    lag); parasitic drag alone (``parasitic``, and the lag: invisible to the motor-speed map)."""
    p, flights = base_params(), standard_flights()
    tau = p["tau_m"]
    return {f.name: f for f in (
        Fleet("clean", Physics(), flights),
        Fleet("lag", Physics(tau_m=tau), flights),
        Fleet("rotor_drag", Physics.rotorpy_default(), flights),
        Fleet("rotor_drag_xy", Physics(k_d=p["k_d"], tau_m=tau), flights),
        Fleet("parasitic", Physics(c_D_xy=0.008, c_D_z=0.012, tau_m=tau), flights),
    )}


# ---------------------------------------------------------------------------------------
# Trajectories
# ---------------------------------------------------------------------------------------

def trajectory(flight: Flight):
    """The rotorpy trajectory object of ``flight`` (random within limits from its seed)."""
    rng = np.random.default_rng([flight.seed, 7])
    if flight.kind == "circle":
        from rotorpy.trajectories.circular_traj import ThreeDCircularTraj

        radius = rng.uniform(0.4, 0.8)
        speed = rng.uniform(0.8, 1.6)
        f_xy = min(speed / radius, math.sqrt(4.0 / radius)) / (2 * np.pi)  # centripetal <= 4 m/s^2
        r_z, f_z = rng.uniform(0.1, 0.25), rng.uniform(0.3, 0.6)  # vertical motion: the rotors' vertical drag
        return ThreeDCircularTraj(center=np.array([0.0, 0.0, 1.0]), radius=np.array([radius, radius, r_z]),
                                  freq=np.array([f_xy, f_xy, f_z]), yaw_bool=bool(rng.random() < 0.5))
    if flight.kind == "lissajous":
        from rotorpy.trajectories.lissajous_traj import TwoDLissajous

        A, B = rng.uniform(0.5, 1.0, 2)
        a = rng.uniform(1.0, 1.8)
        b = a * rng.choice([0.5, 2.0])
        scale = min(1.0, math.sqrt(4.0 / max(A * a**2, B * b**2)))  # peak acceleration <= 4 m/s^2
        return TwoDLissajous(A=A, B=B, a=a * scale, b=b * scale, delta=rng.uniform(0, np.pi), height=1.0,
                             yaw_bool=bool(rng.random() < 0.5))
    if flight.kind == "minsnap":
        return _minsnap(rng, flight.duration_s)
    raise ValueError(f"unknown trajectory kind {flight.kind!r}: circle, lissajous or minsnap")


def _minsnap(rng: np.random.Generator, duration_s: float):
    """rotorpy's MinSnap through random waypoints in a 2 x 2 x 1 m box (varying height, yaw),
    at a random average speed; re-drawn until the peak thrust the plan needs stays within
    ``THRUST_MARGIN`` of the rotors' maximum and the plan lasts ``duration_s``."""
    from rotorpy.trajectories.minsnap import MinSnap

    p = base_params()
    t_max_N = 4 * p["k_eta"] * p["rotor_speed_max"] ** 2
    for _ in range(50):
        n = int(rng.integers(10, 14))
        points = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0.6, 1.6, n)])
        if np.linalg.norm(np.diff(points, axis=0), axis=1).min() < 0.3:
            continue  # MinSnap drops waypoints closer than 0.1 m but not their yaw angles
        yaw = rng.uniform(-0.6, 0.6, n)
        yaw[0] = 0.0
        try:
            traj = MinSnap(points, yaw_angles=yaw, v_avg=float(rng.uniform(0.8, 1.3)), verbose=False)
        except (TypeError, ValueError, ArithmeticError):  # its QP found no solution: draw again
            continue
        if getattr(traj, "null", False) or traj.t_keyframes[-1] < duration_s:
            continue
        flat = [traj.update(ti) for ti in np.arange(0.0, duration_s + 1.0, 0.01)]
        acc = np.array([f["x_ddot"] for f in flat])
        thrust = p["mass"] * np.linalg.norm(acc + [0.0, 0.0, G_ROTORPY_MPS2], axis=1)
        yaw_rate = np.abs([float(f["yaw_dot"]) for f in flat])
        if (thrust.max() <= THRUST_MARGIN * t_max_N and np.linalg.norm(acc, axis=1).max() <= MAX_ACCEL_MPS2
                and yaw_rate.max() <= MAX_YAW_RATE_RADPS):
            return traj
    raise RuntimeError("no min-snap plan within the thrust, acceleration and yaw-rate limits in 50 draws")


# ---------------------------------------------------------------------------------------
# Simulation
# ---------------------------------------------------------------------------------------

@dataclass
class Trace:
    """One simulated flight at the control rate, from the first logged sample: time s, world
    position m and velocity m/s, attitude (x, y, z, w), body rates rad/s, body specific force
    m/s^2, actual and commanded rotor speeds rad/s (firmware order m1..m4), and the parts of
    rotorpy's body wrench that its aerodynamic effects make (rotor drag force N and torque N m,
    parasitic drag force N; rotorpy's wrench with the effect minus without it)."""

    t_s: np.ndarray
    p_w_m: np.ndarray
    v_w_mps: np.ndarray
    q_xyzw: np.ndarray
    omega_b_radps: np.ndarray
    sf_b_mps2: np.ndarray
    rotor_radps: np.ndarray
    cmd_radps: np.ndarray
    f_rotor_drag_b_N: np.ndarray
    tau_rotor_drag_b_Nm: np.ndarray
    f_parasitic_b_N: np.ndarray

    def save(self, file) -> None:
        np.savez(file, **{f.name: getattr(self, f.name) for f in fields(self)})

    @classmethod
    def load(cls, path: Path) -> Trace:
        with np.load(path) as z:
            return cls(**{f.name: z[f.name] for f in fields(cls)})

    def every(self, step: int) -> Trace:
        """Every ``step``-th sample (the samples a slower log holds)."""
        return Trace(**{f.name: getattr(self, f.name)[::step] for f in fields(self)})

    @property
    def v_b_mps(self) -> np.ndarray:
        """Body-frame velocity (no wind)."""
        return np.einsum("nji,nj->ni", _rotations(self.q_xyzw), self.v_w_mps)


def _initial_state(traj, params: dict) -> dict:
    flat = traj.update(0.0)
    yaw = float(flat["yaw"])
    hover = math.sqrt(params["mass"] * G_ROTORPY_MPS2 / (4 * params["k_eta"]))
    return {"x": np.asarray(flat["x"], float), "v": np.asarray(flat["x_dot"], float),
            "q": np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]), "w": np.zeros(3),
            "wind": np.zeros(3), "rotor_speeds": np.full(4, hover)}


def simulate(flight: Flight, physics: Physics) -> Trace:
    """Fly ``flight`` with rotorpy's dynamics and SE3 controller (see the module docstring)."""
    from rotorpy.controllers.quadrotor_control import SE3Control
    from rotorpy.vehicles.multirotor import Multirotor

    params = physics.params()
    traj = trajectory(flight)
    vehicle = Multirotor(params, initial_state=None, control_abstraction="cmd_motor_speeds", aero=True)
    without_rotor_drag = Multirotor({**params, "k_d": 0.0, "k_z": 0.0}, initial_state=None, aero=True)
    without_parasitic = Multirotor({**params, "c_Dx": 0.0, "c_Dy": 0.0, "c_Dz": 0.0}, initial_state=None, aero=True)
    controller = SE3Control(params)
    dt = 1.0 / RATE_HZ
    h = dt / SUBSTEPS
    warm = int(round(flight.warmup_s * RATE_HZ))
    n = warm + int(round(flight.duration_s * RATE_HZ))
    s = Multirotor._pack_state(_initial_state(traj, params))
    lagged = physics.tau_m is not None
    out = np.zeros((n, 13 + 3 + 4 + 4 + 9))
    for k in range(n):
        t = k * dt
        state = Multirotor._unpack_state(s)
        cmd = controller.update(t, state, traj.update(t))["cmd_motor_speeds"]
        cmd = np.clip(cmd, params["rotor_speed_min"], params["rotor_speed_max"])
        if not lagged:
            s[16:] = cmd
        if k >= warm:
            args = (s[10:13], s[16:20], _rotation(s[6:10]).T @ s[3:6])
            force_b, torque_b = vehicle.compute_body_wrench(*args)
            f_nrd, t_nrd = without_rotor_drag.compute_body_wrench(*args)
            f_npd, _ = without_parasitic.compute_body_wrench(*args)
            out[k] = np.concatenate([s[0:13], force_b / params["mass"], s[16:20], cmd,
                                     force_b - f_nrd, torque_b - t_nrd, force_b - f_npd])
        for _ in range(SUBSTEPS):
            s = _rk4_step(vehicle, s, cmd, h, lagged)
    out = out[warm:]
    _check_in_control(flight, out[:, 10:13], out[:, 20:24], params)
    fw = FIRMWARE_FROM_ROTORPY
    return Trace(t_s=np.arange(len(out)) * dt, p_w_m=out[:, 0:3], v_w_mps=out[:, 3:6], q_xyzw=out[:, 6:10],
                 omega_b_radps=out[:, 10:13], sf_b_mps2=out[:, 13:16], rotor_radps=out[:, 16:20][:, fw],
                 cmd_radps=out[:, 20:24][:, fw], f_rotor_drag_b_N=out[:, 24:27], tau_rotor_drag_b_Nm=out[:, 27:30],
                 f_parasitic_b_N=out[:, 30:33])


def _check_in_control(flight: Flight, omega_b_radps: np.ndarray, cmd_radps: np.ndarray, params: dict) -> None:
    """A flight that lost control (body rates past ``MAX_BODY_RATE_RADPS``, rotors commanded to
    their limits) is no test flight: say so rather than log it."""
    saturated = np.mean((cmd_radps >= params["rotor_speed_max"]) | (cmd_radps <= params["rotor_speed_min"]))
    rate = float(np.abs(omega_b_radps).max())
    if rate > MAX_BODY_RATE_RADPS or saturated > 0.001:
        raise RuntimeError(f"flight {flight.name} ({flight.kind}, seed {flight.seed}) lost control: body rate up to "
                           f"{rate:.1f} rad/s, rotor commands at their limits {saturated:.1%} of the time")


def _rk4_step(vehicle, s: np.ndarray, cmd: np.ndarray, h: float, lagged: bool) -> np.ndarray:
    """One RK4 step of rotorpy's state derivative with the rotor command held (the rotor speeds
    held too without lag); the attitude quaternion renormalised after it, as rotorpy's ``step``
    does."""

    def deriv(si: np.ndarray) -> np.ndarray:
        d = vehicle._s_dot_fn(0.0, si, cmd)
        if not lagged:
            d[16:] = 0.0
        return d

    k1 = deriv(s)
    k2 = deriv(s + 0.5 * h * k1)
    k3 = deriv(s + 0.5 * h * k2)
    k4 = deriv(s + h * k3)
    s = s + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    s[6:10] /= np.linalg.norm(s[6:10])
    return s


def _rotations(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) R_wb of unit quaternions (n, 4) (x, y, z, w)."""
    return np.stack([_rotation(qi) for qi in q])


def _rotation(q: np.ndarray) -> np.ndarray:
    """R_wb of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


# ---------------------------------------------------------------------------------------
# Logging through the project's writer
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Battery:
    """Logged battery voltage: ``ocv_V + rate t - sag * T`` in whole mV (T the total thrust, N);
    the PWM map's inverse uses the same voltage, so the logged PWM and voltage give back the
    commanded thrust."""

    ocv_V: float = 3.9
    rate_V_per_s: float = -0.003
    sag_V_per_N: float = 1.05


def log_bytes(trace: Trace, rate_hz: int, seed: int, battery: Battery | None = None) -> bytes:
    """``trace`` sampled at ``rate_hz`` as a uSD log (see the module docstring)."""
    from quadcore.logs.units import PWM_FULL_SCALE
    from quadcore.physics import vehicle as vehicle_mod
    from quadcore.sim import usdlog
    from quadcore.sim.simulation import SimConfig, _draw_noise

    battery = battery or Battery()
    veh = vehicle_mod.load(VEHICLE_FILE)
    step = int(round(RATE_HZ / rate_hz))
    idx = np.arange(0, len(trace.t_s), step)
    t = trace.t_s[idx]
    k_F = veh.motor_speed.k_F_N_per_radps2
    f_act, f_cmd = k_F * trace.rotor_radps[idx] ** 2, k_F * trace.cmd_radps[idx] ** 2
    rng_noise, rng_drop, rng_mocap, rng_clock, rng_vbat = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, rate_hz]).spawn(5))
    config = SimConfig(log_rate_hz=float(rate_hz), seed=seed)
    noise = _draw_noise(rng_noise, config.noise, len(t), float(rate_hz))  # white: no low-pass asked
    vbat_V = battery.ocv_V + battery.rate_V_per_s * t - battery.sag_V_per_N * f_act.sum(axis=1) \
        + rng_vbat.normal(0.0, config.noise.vbat_V, len(t))
    vbat_mV = np.rint(vbat_V * 1000.0).astype(np.int64)
    pwm = np.rint(veh.pwm_vbat.pwm_for_thrust(f_cmd, (vbat_mV * 1e-3)[:, None]) * PWM_FULL_SCALE).astype(np.int64)
    data, _ = usdlog.encode(config, t, trace.p_w_m[idx], trace.v_w_mps[idx], trace.q_xyzw[idx],
                            trace.omega_b_radps[idx], trace.sf_b_mps2[idx], f_act, pwm, vbat_mV, veh.motor_speed,
                            noise.pos, noise.vel, noise.att, noise.gyro, noise.acc, noise.rpm,
                            rng_drop, rng_mocap, rng_clock)
    return data


# ---------------------------------------------------------------------------------------
# Fleets on disk, cached
# ---------------------------------------------------------------------------------------

# The settings of the project's simulator that the log writer reads (noise, gaps, motion capture).
LOG_SETTINGS = ("noise", "drop_prob", "drop_max_samples", "mocap_rate_hz", "mocap_drop_prob", "mocap_jitter_s")

# The code whose change changes the logs (the cache key holds its source, with the project's
# writer, encoder and noise model).
GENERATING = (base_params, Physics, trajectory, _minsnap, _initial_state, simulate, _check_in_control, _rk4_step,
              log_bytes, Battery)


def cache_root() -> Path:
    """``$QUADCORE_TEST_CACHE`` or ``tests/.cache`` (gitignored)."""
    return Path(os.environ.get("QUADCORE_TEST_CACHE") or REPO / "tests" / ".cache") / "independent"


def _digest(fleet: Fleet) -> str:
    from importlib.metadata import version

    from quadcore.logs import logformat
    from quadcore.sim import simulation, usdlog

    h = hashlib.sha256()
    h.update(json.dumps(asdict(fleet), sort_keys=True).encode())
    h.update(version("rotorpy").encode())
    for code in (*GENERATING, usdlog, logformat.encode, simulation.SensorNoise, simulation._draw_noise):
        h.update(inspect.getsource(code).encode())
    config = simulation.SimConfig().to_dict()
    h.update(json.dumps({k: config[k] for k in LOG_SETTINGS}, sort_keys=True).encode())
    h.update(VEHICLE_FILE.read_bytes())
    return h.hexdigest()


def _root(fleet: Fleet) -> Path:
    return cache_root() / f"{fleet.name}-{fleet.digest()}"


def folder(fleet: Fleet, rate_hz: int) -> Path:
    """The folder of ``fleet``'s logs at ``rate_hz`` (``<cache>/<name>-<digest>/<rate>hz``),
    simulated and written on first use."""
    prepare([fleet])
    return _root(fleet) / f"{rate_hz}hz"


def traces(fleet: Fleet, rate_hz: int = int(RATE_HZ)) -> list[Trace]:
    """The fleet's simulated flights, at the samples its ``rate_hz`` logs hold."""
    prepare([fleet])
    step = int(round(RATE_HZ / rate_hz))
    return [Trace.load(_root(fleet) / "traces" / f"{f.name}.npz").every(step) for f in fleet.flights]


def prepare(fleets: list[Fleet], workers: int | None = None) -> None:
    """Simulate and write every flight of ``fleets`` not in the cache yet, shared among
    ``workers`` processes (default: up to two, the CI machine's cores). Each flight's files are
    written whole (a temporary name, then renamed); a fleet is complete once its ``done`` marker
    is written, so an interrupted run resumes with the flights it lacks. Under the cache's lock: a
    second process (another pytest-xdist worker) waits and then finds the flights written."""
    with _cache_lock():
        _prepare(fleets, workers)


@contextlib.contextmanager
def _cache_lock():
    """The cache's lock file, held while flights are written (released by the system if killed)."""
    import fcntl

    cache_root().mkdir(parents=True, exist_ok=True)
    with open(cache_root() / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _prepare(fleets: list[Fleet], workers: int | None) -> None:
    todo = [(fleet, flight) for fleet in fleets if not (_root(fleet) / "done").is_file()
            for flight in fleet.flights if not _flight_done(fleet, flight)]
    workers = workers or min(2, os.cpu_count() or 1, len(todo))
    if workers > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            list(pool.map(_fly_and_write, *zip(*todo)))
    else:
        for job in todo:
            _fly_and_write(*job)
    for fleet in fleets:
        root = _root(fleet)
        if not (root / "done").is_file():
            _write(root / "fleet.json", json.dumps({**asdict(fleet), "truth": truth(fleet.physics)}, indent=2).encode())
            _write(root / "done", b"")


def _paths(fleet: Fleet, flight: Flight) -> list[Path]:
    root = _root(fleet)
    return [root / "traces" / f"{flight.name}.npz", *(root / f"{rate}hz" / flight.name for rate in LOG_RATES_HZ)]


def _flight_done(fleet: Fleet, flight: Flight) -> bool:
    return all(p.is_file() for p in _paths(fleet, flight))


def _write(path: Path, data: bytes) -> None:
    """``data`` at ``path`` whole or not at all (a temporary file in the same folder, renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _fly_and_write(fleet: Fleet, flight: Flight) -> None:
    trace = simulate(flight, fleet.physics)
    trace_path, *log_paths = _paths(fleet, flight)
    for rate, path in zip(LOG_RATES_HZ, log_paths):
        _write(path, log_bytes(trace, rate, flight.seed))
    buffer = io.BytesIO()
    trace.save(buffer)
    _write(trace_path, buffer.getvalue())  # last: it marks the flight done


# ---------------------------------------------------------------------------------------
# rotorpy's parameters in this project's terms
# ---------------------------------------------------------------------------------------

def hover_speed_radps() -> float:
    """Each rotor's speed in hover: ``k_eta w_h^2 = m g / 4``."""
    p = base_params()
    return math.sqrt(p["mass"] * G_ROTORPY_MPS2 / (4 * p["k_eta"]))


def truth(physics: Physics) -> dict[str, float]:
    """rotorpy's effects as this project's parameters (see the tests' docstrings for the
    derivations): ``rotor_drag.k`` = k_d / (k_eta w_h) s/m (its axial ``k_z`` likewise,
    k_z / (k_eta w_h)); vertical drag 4 k_z w_h kg/s;
    yaw rate damping 4 k_d w_h d^2 and roll/pitch rate damping 2 k_z w_h d^2 N m s;
    parasitic c = c_D kg/m; motor lag tau_m s."""
    p = base_params()
    w_h = hover_speed_radps()
    d = float(np.linalg.norm(p["rotor_pos"]["r1"]))
    return {
        "rotor_drag.k_x_s_per_m": physics.k_d / (p["k_eta"] * w_h),
        "rotor_drag.k_y_s_per_m": physics.k_d / (p["k_eta"] * w_h),
        "rotor_drag.k_z_s_per_m": physics.k_z / (p["k_eta"] * w_h),
        "vertical_drag_kg_per_s": 4 * physics.k_z * w_h,
        "yaw_rate_damping_Nms": 4 * physics.k_d * w_h * d**2,
        "roll_rate_damping_Nms": 2 * physics.k_z * w_h * d**2,
        "pitch_rate_damping_Nms": 2 * physics.k_z * w_h * d**2,
        "parasitic_drag.c_xy_kg_per_m": physics.c_D_xy,
        "parasitic_drag.c_z_kg_per_m": physics.c_D_z,
        "motor_lag.tau_s": physics.tau_m or 0.0,
    }


def with_physics(fleet: Fleet, **changes) -> Fleet:
    return replace(fleet, physics=replace(fleet.physics, **changes))


def projected_truth(fleet: Fleet, rate_hz: int) -> dict[str, float]:
    """rotorpy's effects on the fleet's flights in this project's parameters: :func:`truth`, with
    the rotor drag's ``k`` the value a fit of ``-k T v`` converges to on these flights (rotorpy's
    rotor drag goes with the rotor speed, this project's with the thrust; see :func:`projection`)
    and the terms outside the library (vertical drag, rate damping) likewise, on ``v_z`` and
    ``Omega``."""
    out = dict(truth(fleet.physics))
    for key, target, expression in (("rotor_drag.k_x_s_per_m", "f_res_b_x_N", "T_N*v_b_x_mps"),
                                    ("rotor_drag.k_y_s_per_m", "f_res_b_y_N", "T_N*v_b_y_mps"),
                                    ("rotor_drag.k_z_s_per_m", "f_res_b_z_N", "T_N*v_b_z_mps"),
                                    ("vertical_drag_kg_per_s", "f_res_b_z_N", "v_b_z_mps"),
                                    ("roll_rate_damping_Nms", "tau_res_b_x_Nm", "omega_b_x_radps"),
                                    ("pitch_rate_damping_Nms", "tau_res_b_y_Nm", "omega_b_y_radps"),
                                    ("yaw_rate_damping_Nms", "tau_res_b_z_Nm", "omega_b_z_radps")):
        out[key] = -projection(fleet, rate_hz, target, expression, rotor_drag_only=True)
    return out


def projection(fleet: Fleet, rate_hz: int, target: str, expression: str, rotor_drag_only: bool = False) -> float:
    """The least-squares coefficient ``c`` of ``target ~ c * expression`` over the fleet's flights
    at the samples its ``rate_hz`` logs hold, with rotorpy's true aerodynamic wrench as the
    target (``f_res_b_<axis>_N``: rotor drag plus parasitic drag force; ``tau_res_b_<axis>_Nm``:
    rotor drag torque; only the rotor drag with ``rotor_drag_only``) and ``expression`` a product
    of ``v_b_<axis>_mps``, ``omega_b_<axis>_radps`` and ``T_N`` (= k_eta sum w_i^2) on the true
    state: ``c = sum(x y) / sum(x x)``."""
    trs = traces(fleet, rate_hz)
    k_eta = base_params()["k_eta"]
    axis = "xyz".index(target.split("_")[3])
    variables = {"T_N": np.concatenate([k_eta * np.sum(t.rotor_radps**2, axis=1) for t in trs])}
    for j, a in enumerate("xyz"):
        variables[f"v_b_{a}_mps"] = np.concatenate([t.v_b_mps[:, j] for t in trs])
        variables[f"omega_b_{a}_radps"] = np.concatenate([t.omega_b_radps[:, j] for t in trs])
    x = np.prod([variables[f] for f in expression.split("*")], axis=0)
    if target.startswith("f_"):
        y = np.concatenate([t.f_rotor_drag_b_N[:, axis] + (0.0 if rotor_drag_only else t.f_parasitic_b_N[:, axis])
                            for t in trs])
    else:
        y = np.concatenate([t.tau_rotor_drag_b_Nm[:, axis] for t in trs])
    return float(np.dot(x, y) / np.dot(x, x))


# ---------------------------------------------------------------------------------------
# The project's public paths on a fleet (what `quadcore diagnose/discover DATA` calls)
# ---------------------------------------------------------------------------------------

def decoded(fleet: Fleet, rate_hz: int, thrust_map: str):
    """The fleet's logs at ``rate_hz`` decoded as the CLI decodes them (a workflows Fleet)."""
    from quadcore import workflows
    from quadcore.workflows import fleet as fleetmod

    spec = workflows.resolve_model(None, str(VEHICLE_FILE), thrust_map, [], None)
    return fleetmod.fleet_from_logs([str(folder(fleet, rate_hz))], spec.vehicle)


def model_spec(thrust_map: str, effects: tuple[str, ...] = ()):
    """``--vehicle rotorpy_crazyflie.toml --thrust-map MAP --effects ...``."""
    from quadcore import workflows

    return workflows.resolve_model(None, str(VEHICLE_FILE), thrust_map, list(effects), None)


def diagnose(flights, thrust_map: str, effects: tuple[str, ...] = ()):
    """``quadcore diagnose`` (no holdout: cross-validation over the given flights)."""
    from quadcore.workflows import identify

    return identify.diagnose(flights, model_spec(thrust_map, effects), [])


def discover(flights, thrust_map: str, effects: tuple[str, ...] = ()):
    """``quadcore discover``: cross-validation over the given flights (no holdout)."""
    from quadcore.workflows import identify

    return identify.discover(flights, model_spec(thrust_map, effects), [])
