"""The vehicle: mass, inertia, rotor layout and thrust map, read from a TOML file.

Body frame: x forward, y left, z up, origin at the centre of mass. Rotor ``i`` sits at
``r_i = arm_i (cos a_i, sin a_i, 0)`` and pushes ``f_i`` along body +z. The actuation
(allocation) matrix ``A`` maps rotor thrusts to collective thrust and body torques::

    [T, tau_x, tau_y, tau_z]^T = A f,   A[:, i] = [1, y_i, -x_i, t2t * yaw_sign_i]

For the Crazyflie (X layout, a = arm / sqrt 2) this is the inverse of the firmware's
mixer: ``tau_x = a(-f1 - f2 + f3 + f4)``, ``tau_y = a(-f1 + f2 + f3 - f4)``,
``tau_z = t2t(-f1 + f2 - f3 + f4)``.

The built-in default is ``vehicles/crazyflie21.toml``; every constant lives there.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from quadcore.units import G0_MPS2

DEFAULT_VEHICLE = "crazyflie21"
THRUST_MAP_KINDS = ("pwm_vbat", "motor_speed")


class VehicleFileError(ValueError):
    """A vehicle file that is missing, unreadable or incomplete."""


@dataclass(frozen=True)
class PwmVbatThrustMap:
    """Per-rotor thrust in grams from normalised PWM p and battery ratio b = vbat/vbat_ref:
    ``f_g = c0 + cp p + cb b + cpp p^2 + cpb p b`` (clipped at zero)."""

    c0: float
    cp: float
    cb: float
    cpp: float
    cpb: float
    vbat_ref_V: float

    def thrust_N(self, pwm: np.ndarray, vbat_V: np.ndarray | float) -> np.ndarray:
        """``pwm`` in 0..1 (any shape, rotors last), ``vbat_V`` broadcastable to it."""
        p, b = pwm, vbat_V / self.vbat_ref_V
        grams = self.c0 + self.cp * p + self.cb * b + self.cpp * p**2 + self.cpb * p * b
        return np.maximum(grams, 0.0) * (G0_MPS2 / 1000.0)

    def pwm_for_thrust(self, thrust_N: np.ndarray, vbat_V: np.ndarray | float) -> np.ndarray:
        """Inverse map: the PWM (0..1) giving ``thrust_N`` at ``vbat_V`` (larger root, clipped)."""
        b = vbat_V / self.vbat_ref_V
        grams = np.asarray(thrust_N) * (1000.0 / G0_MPS2)
        qa, qb, qc = self.cpp, self.cp + self.cpb * b, self.c0 + self.cb * b - grams
        disc = np.maximum(qb**2 - 4 * qa * qc, 0.0)
        return np.clip((-qb + np.sqrt(disc)) / (2 * qa), 0.0, 1.0)


@dataclass(frozen=True)
class MotorSpeedThrustMap:
    """Per-rotor thrust from measured motor speed: ``f = k_F omega^2`` (omega in rad/s)."""

    k_F_N_per_radps2: float

    def thrust_N(self, omega_radps: np.ndarray) -> np.ndarray:
        return self.k_F_N_per_radps2 * np.square(omega_radps)

    def speed_for_thrust(self, thrust_N: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(thrust_N, 0.0) / self.k_F_N_per_radps2)


@dataclass(frozen=True)
class Vehicle:
    """Rigid-body parameters and rotor layout (see module docstring for frames)."""

    name: str
    mass_kg: float
    inertia_kgm2: np.ndarray  # (3, 3), body frame, about the centre of mass
    rotor_xy_m: np.ndarray  # (n_rotors, 2) rotor positions in the body x-y plane
    yaw_sign: np.ndarray  # (n_rotors,) +1 / -1
    torque_to_thrust_m: float
    rotor_radius_m: float
    thrust_map_kind: str
    pwm_vbat: PwmVbatThrustMap
    motor_speed: MotorSpeedThrustMap
    source: str = field(default="", compare=False)

    @property
    def n_rotors(self) -> int:
        return len(self.yaw_sign)

    @property
    def weight_N(self) -> float:
        return self.mass_kg * G0_MPS2

    @property
    def allocation(self) -> np.ndarray:
        """(4, n_rotors): rotor thrusts -> [T, tau_x, tau_y, tau_z]."""
        x, y = self.rotor_xy_m[:, 0], self.rotor_xy_m[:, 1]
        return np.vstack([np.ones_like(x), y, -x, self.torque_to_thrust_m * self.yaw_sign])

    def rotor_thrusts_N(self, pwm: np.ndarray, vbat_V: np.ndarray, motor_radps: np.ndarray | None) -> np.ndarray:
        """(n, n_rotors) thrusts from the selected map. ``pwm`` 0..1 (n, rotors), ``vbat_V`` (n,)."""
        if self.thrust_map_kind == "motor_speed":
            if motor_radps is None:
                raise VehicleFileError("thrust map 'motor_speed' needs motor speed columns in the log")
            if self.motor_speed.k_F_N_per_radps2 <= 0:
                raise VehicleFileError(
                    f"vehicle {self.name!r}: motor_speed thrust map has no k_F; run `quadcore fit-thrust`"
                )
            return self.motor_speed.thrust_N(motor_radps)
        return self.pwm_vbat.thrust_N(pwm, np.asarray(vbat_V)[..., None])

    def with_thrust_map(self, kind: str) -> Vehicle:
        if kind not in THRUST_MAP_KINDS:
            raise VehicleFileError(f"unknown thrust map {kind!r}; choose one of {', '.join(THRUST_MAP_KINDS)}")
        return replace(self, thrust_map_kind=kind)


def _require(d: dict, key: str, where: str):
    if key not in d:
        raise VehicleFileError(f"{where}: missing key {key!r}")
    return d[key]


def from_dict(d: dict, source: str = "") -> Vehicle:
    where = source or "vehicle"
    try:
        return _from_dict(d, source, where)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, VehicleFileError):
            raise
        raise VehicleFileError(f"{where}: a value is not a number or has the wrong shape: {exc}") from None


def _from_dict(d: dict, source: str, where: str) -> Vehicle:
    inertia = np.asarray(_require(d, "inertia_kgm2", where), dtype=float)
    if inertia.shape != (3, 3) or not np.allclose(inertia, inertia.T):
        raise VehicleFileError(f"{where}: inertia_kgm2 must be a symmetric 3x3 matrix")
    if np.any(np.linalg.eigvalsh(inertia) <= 0):
        raise VehicleFileError(f"{where}: inertia_kgm2 must be positive definite")
    rotors = _require(d, "rotors", where)
    angles = np.radians([float(_require(r, "angle_deg", where)) for r in rotors])
    arms = np.array([float(_require(r, "arm_m", where)) for r in rotors])
    tm = _require(d, "thrust_map", where)
    pv = _require(tm, "pwm_vbat", f"{where} [thrust_map]")
    ms = tm.get("motor_speed", {})
    mass = float(_require(d, "mass_kg", where))
    if mass <= 0:
        raise VehicleFileError(f"{where}: mass_kg must be positive")
    kind = tm.get("kind", "pwm_vbat")
    if kind not in THRUST_MAP_KINDS:
        raise VehicleFileError(f"{where}: thrust_map.kind {kind!r} is not one of {THRUST_MAP_KINDS}")
    return Vehicle(
        name=str(d.get("name", Path(source).stem if source else "vehicle")),
        mass_kg=mass,
        inertia_kgm2=inertia,
        rotor_xy_m=np.column_stack([arms * np.cos(angles), arms * np.sin(angles)]),
        yaw_sign=np.array([float(_require(r, "yaw_sign", where)) for r in rotors]),
        torque_to_thrust_m=float(_require(d, "torque_to_thrust_m", where)),
        rotor_radius_m=float(_require(d, "rotor_radius_m", where)),
        thrust_map_kind=kind,
        pwm_vbat=PwmVbatThrustMap(**{k: float(pv[k]) for k in ("c0", "cp", "cb", "cpp", "cpb", "vbat_ref_V")}),
        motor_speed=MotorSpeedThrustMap(float(ms.get("k_F_N_per_radps2", 0.0))),
        source=source,
    )


def load(path_or_name: str | Path | None = None) -> Vehicle:
    """Load a vehicle file (a path), or a built-in by name (default: the Crazyflie 2.1)."""
    if path_or_name is None or str(path_or_name) == DEFAULT_VEHICLE:
        text = resources.files("quadcore").joinpath(f"vehicles/{DEFAULT_VEHICLE}.toml").read_text()
        return from_dict(tomllib.loads(text), source=f"builtin:{DEFAULT_VEHICLE}")
    path = Path(path_or_name)
    return from_dict(read_toml(path, VehicleFileError, "vehicle file"), source=str(path))


def read_toml(path: Path, error: type[Exception], what: str) -> dict:
    """A TOML file as a dict; a missing or malformed file raises ``error`` saying which."""
    if not path.is_file():
        raise error(f"{what} not found: {path}")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None

