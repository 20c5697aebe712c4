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

import re
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from quadcore.logs.units import G0_MPS2
from quadcore.store import store

DEFAULT_VEHICLE = "crazyflie21"
THRUST_MAP_KINDS = ("pwm_vbat", "motor_speed")


class VehicleFileError(ValueError):
    """A vehicle file that is missing, unreadable or incomplete."""


@dataclass(frozen=True)
class PwmVbatThrustMap:
    """Per-rotor thrust in grams from normalised PWM p and battery ratio b = vbat/vbat_ref:
    ``f_g = c0 + cp p + cb b + cpp p^2 + cpb p b`` (clipped at zero).

    ``command_period_s``: the firmware sets the motor PWM every ``command_period_s`` and holds
    it in between (the Crazyflie's rate controller runs at 500 Hz: 0.002 s, whatever the log
    rate). How the residuals time a held command: :mod:`quadcore.physics.signals`."""

    c0: float
    cp: float
    cb: float
    cpp: float
    cpb: float
    vbat_ref_V: float
    command_period_s: float = 0.002

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

    def thrust_slope_N_per_radps(self, omega_radps: np.ndarray) -> np.ndarray:
        """The map's Jacobian per rotor: ``df/domega = 2 k_F omega`` (N per rad/s)."""
        return 2.0 * self.k_F_N_per_radps2 * np.asarray(omega_radps)


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

    @property
    def thrust_hold_s(self) -> float:
        """How long a logged sample of the thrust map's input holds (s): a PWM command holds
        for the command period; a measured motor speed is a sample of a continuous state (the
        rotor's inertia), held for no time. See :func:`quadcore.physics.signals.matched_to_derivative`."""
        return 0.0 if self.thrust_map_kind == "motor_speed" else self.pwm_vbat.command_period_s

    def with_thrust_map(self, kind: str) -> Vehicle:
        if kind not in THRUST_MAP_KINDS:
            raise VehicleFileError(f"unknown thrust map {kind!r}; choose one of {', '.join(THRUST_MAP_KINDS)}")
        return replace(self, thrust_map_kind=kind)


KNOWN_KEYS = {
    "": {"name", "mass_kg", "inertia_kgm2", "torque_to_thrust_m", "rotor_radius_m", "rotors", "thrust_map",
         "allow_unusual"},
    "rotors": {"arm_m", "angle_deg", "yaw_sign"},
    "thrust_map": {"kind", "pwm_vbat", "motor_speed"},
    "thrust_map.pwm_vbat": {"c0", "cp", "cb", "cpp", "cpb", "vbat_ref_V", "command_period_s"},
    "thrust_map.motor_speed": {"k_F_N_per_radps2"},
}


def _table(d, key: str, where: str) -> dict:
    value = d.get(key) if isinstance(d, dict) else None
    if not isinstance(value, dict):
        raise VehicleFileError(f"{where}: [{key}]: expected a table, got {_shown(value)}")
    return value


def _shown(value) -> str:
    return "nothing (missing)" if value is None else f"{value!r:.60}"


def _check_keys(d: dict, section: str, where: str) -> None:
    unknown = sorted(set(d) - KNOWN_KEYS[section])
    if unknown:
        label = f"[{section}] " if section else ""
        raise VehicleFileError(f"{where}: {label}unknown key {unknown[0]!r}: expected one of "
                               f"{', '.join(sorted(KNOWN_KEYS[section]))}")


def _number(d: dict, key: str, where: str, lo: float | None = None, strict: bool = True, default=None) -> float:
    """``d[key]`` as a finite float (not a bool), ``> lo`` (``>= lo`` when not ``strict``)."""
    value = d.get(key, default)
    bound = "" if lo is None else f" {'>' if strict else '>='} {lo:g}"
    ok = is_finite_number(value)
    if ok and lo is not None:
        ok = value > lo if strict else value >= lo
    if not ok:
        raise VehicleFileError(f"{where}: {key} = {_shown(value)}: expected a finite number{bound}")
    return float(value)


def is_finite_number(value) -> bool:
    """An int or float (not a bool) that is finite as a float (an integer too large for one is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return bool(np.isfinite(float(value)))
    except OverflowError:
        return False


def from_dict(d: dict, source: str = "") -> Vehicle:
    """A vehicle from a parsed file. Every value is checked (type, finiteness, range, rotor
    layout); an error names the file, the key and what was expected."""
    where = source or "vehicle"
    _check_keys(d, "", where)
    inertia = _inertia(d, where)
    rotors = d.get("rotors")
    if not isinstance(rotors, list) or not all(isinstance(r, dict) for r in rotors):
        raise VehicleFileError(f"{where}: rotors = {_shown(rotors)}: expected [[rotors]] tables")
    for i, r in enumerate(rotors, 1):
        _check_keys(r, "rotors", f"{where}: rotor {i}")
    arms = np.array([_number(r, "arm_m", f"{where}: rotor {i}", 0.0) for i, r in enumerate(rotors, 1)])
    angles = np.radians([_number(r, "angle_deg", f"{where}: rotor {i}") for i, r in enumerate(rotors, 1)])
    yaw = np.array([_number(r, "yaw_sign", f"{where}: rotor {i}") for i, r in enumerate(rotors, 1)])
    if not np.all(np.isin(yaw, (-1.0, 1.0))):
        raise VehicleFileError(f"{where}: yaw_sign = {yaw.tolist()}: expected -1 or +1 for every rotor")
    tm = _table(d, "thrust_map", where)
    _check_keys(tm, "thrust_map", where)
    kind = tm.get("kind", "pwm_vbat")
    if kind not in THRUST_MAP_KINDS:
        raise VehicleFileError(f"{where}: [thrust_map] kind = {_shown(kind)}: expected one of {THRUST_MAP_KINDS}")
    pv = _table(tm, "pwm_vbat", f"{where}: [thrust_map]")
    _check_keys(pv, "thrust_map.pwm_vbat", where)
    pv_where = f"{where}: [thrust_map.pwm_vbat]"
    coeffs = {k: _number(pv, k, pv_where) for k in ("c0", "cp", "cb", "cpp", "cpb")}
    ms = tm.get("motor_speed", {})
    if not isinstance(ms, dict):
        raise VehicleFileError(f"{where}: [thrust_map.motor_speed]: expected a table, got {_shown(ms)}")
    _check_keys(ms, "thrust_map.motor_speed", where)
    name = d.get("name", Path(source).stem if source else "vehicle")
    if not isinstance(name, str):
        raise VehicleFileError(f"{where}: name = {_shown(name)}: expected a string")
    vehicle = Vehicle(
        name=name,
        mass_kg=_number(d, "mass_kg", where, 0.0),
        inertia_kgm2=inertia,
        rotor_xy_m=np.column_stack([arms * np.cos(angles), arms * np.sin(angles)]),
        yaw_sign=yaw,
        torque_to_thrust_m=_number(d, "torque_to_thrust_m", where, 0.0),
        rotor_radius_m=_number(d, "rotor_radius_m", where, 0.0),
        thrust_map_kind=kind,
        pwm_vbat=PwmVbatThrustMap(**coeffs, vbat_ref_V=_number(pv, "vbat_ref_V", pv_where, 0.0),
                                  command_period_s=_number(pv, "command_period_s", pv_where, 0.0,
                                                           default=PwmVbatThrustMap.command_period_s)),
        motor_speed=MotorSpeedThrustMap(_number(ms, "k_F_N_per_radps2", f"{where}: [thrust_map.motor_speed]",
                                                0.0, strict=False, default=0.0)),
        source=source,
    )
    _check_layout(vehicle, where)
    _check_plausible(vehicle, arms, d, where)
    return vehicle


# The plausible range of each vehicle quantity (SI), from a ~10 g micro quadrotor to a ~200 kg
# heavy-lift multirotor. A value outside is refused with its range unless the file names the key in
# ``allow_unusual = ["mass_kg", ...]`` (the override for an unusual vehicle, docs/reliability.md).
PLAUSIBLE: dict[str, tuple[float, float, str]] = {
    "mass_kg": (0.005, 200.0, "kg"),
    "inertia_kgm2": (1e-8, 100.0, "kg m^2 (each principal moment)"),
    "inertia_condition": (1.0, 100.0, "(largest / smallest principal moment)"),
    "rotors": (4, 16, "rotors"),
    "arm_m": (0.01, 5.0, "m"),
    "rotor_radius_m": (0.005, 1.5, "m"),
    "torque_to_thrust_m": (1e-4, 0.1, "m"),
    "thrust_to_weight": (1.0, 20.0, "(all rotors at full PWM and the reference voltage, over the weight)"),
    "vbat_ref_V": (1.0, 100.0, "V"),
    "k_F_N_per_radps2": (1e-11, 1e-2, "N/(rad/s)^2"),
}
# allow_unusual names these keys; each covers the quantities listed
UNUSUAL_KEYS = {"mass_kg": ("mass_kg",), "inertia_kgm2": ("inertia_kgm2", "inertia_condition"),
                "rotors": ("rotors", "arm_m"), "rotor_radius_m": ("rotor_radius_m",),
                "torque_to_thrust_m": ("torque_to_thrust_m",), "thrust_map": ("thrust_to_weight", "vbat_ref_V",
                                                                              "k_F_N_per_radps2")}


def _allowed(d: dict, where: str) -> set[str]:
    keys = d.get("allow_unusual", [])
    if not isinstance(keys, list) or not all(isinstance(k, str) and k in UNUSUAL_KEYS for k in keys):
        raise VehicleFileError(f"{where}: allow_unusual = {_shown(keys)}: expected a list of keys among "
                               f"{', '.join(UNUSUAL_KEYS)}")
    return {q for k in keys for q in UNUSUAL_KEYS[k]}


def _plausible(name: str, values, where: str, allowed: set[str]) -> None:
    lo, hi, unit = PLAUSIBLE[name]
    vals = np.atleast_1d(np.asarray(values, dtype=float))
    if name in allowed or np.all((vals >= lo) & (vals <= hi)):
        return
    bad = vals[(vals < lo) | (vals > hi)][0]
    key = next(k for k, qs in UNUSUAL_KEYS.items() if name in qs)
    raise VehicleFileError(f"{where}: {name} = {bad:.4g}: outside the plausible range {lo:g} to {hi:g} {unit}; "
                           f"if the vehicle really is so, add allow_unusual = [\"{key}\"] to the file")


def _check_plausible(v: Vehicle, arms: np.ndarray, d: dict, where: str) -> None:
    """Refuse a vehicle no multirotor is (``PLAUSIBLE``) unless ``allow_unusual`` names the key;
    a thrust map must also grow with PWM over the flying range (p 0.3 to 1)."""
    allowed = _allowed(d, where)
    moments = np.linalg.eigvalsh(v.inertia_kgm2)
    for name, value in (("mass_kg", v.mass_kg), ("inertia_kgm2", moments),
                        ("inertia_condition", moments[-1] / moments[0]), ("rotors", v.n_rotors), ("arm_m", arms),
                        ("rotor_radius_m", v.rotor_radius_m), ("torque_to_thrust_m", v.torque_to_thrust_m),
                        ("vbat_ref_V", v.pwm_vbat.vbat_ref_V)):
        _plausible(name, value, where, allowed)
    if v.motor_speed.k_F_N_per_radps2 > 0:
        _plausible("k_F_N_per_radps2", v.motor_speed.k_F_N_per_radps2, where, allowed)
    if v.thrust_map_kind == "pwm_vbat":
        full = float(v.pwm_vbat.thrust_N(np.ones(1), v.pwm_vbat.vbat_ref_V)[0])
        _plausible("thrust_to_weight", v.n_rotors * full / v.weight_N, f"{where}: [thrust_map.pwm_vbat]", allowed)
        m = v.pwm_vbat
        slope = m.cp + 2 * m.cpp * np.linspace(0.3, 1.0, 8) + m.cpb
        if np.any(slope < 0) and "thrust_to_weight" not in allowed:
            raise VehicleFileError(f"{where}: [thrust_map.pwm_vbat]: thrust falls as PWM rises between 0.3 and 1 "
                                   "(cp + 2 cpp p + cpb < 0): not a thrust map; if it really is so, add "
                                   "allow_unusual = [\"thrust_map\"] to the file")


def _inertia(d: dict, where: str) -> np.ndarray:
    raw = d.get("inertia_kgm2")
    try:
        inertia = np.asarray(raw, dtype=float)
    except (TypeError, ValueError, OverflowError):
        inertia = np.zeros(0)
    numbers = isinstance(raw, list) and all(isinstance(r, list) and all(map(is_finite_number, r)) for r in raw)
    if not numbers or inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)) \
            or not np.allclose(inertia, inertia.T) or np.any(np.linalg.eigvalsh(inertia) <= 0):
        raise VehicleFileError(f"{where}: inertia_kgm2 = {_shown(raw)}: expected a symmetric, positive "
                               "definite 3x3 matrix of finite numbers (kg m^2)")
    return inertia


def _check_layout(vehicle: Vehicle, where: str) -> None:
    """The rotors must be able to produce thrust and all three torques: the allocation matrix
    ``A`` (4 x rotors) has rank 4. Three rotors, or all on one line, cannot."""
    if vehicle.n_rotors < 4 or np.linalg.matrix_rank(vehicle.allocation, tol=1e-12) < 4:
        raise VehicleFileError(
            f"{where}: rotors: {vehicle.n_rotors} rotors whose layout cannot produce thrust and roll, pitch "
            "and yaw torque independently: expected at least 4 rotors around the centre of mass with both "
            "yaw_sign values")


def load(path_or_name: str | Path | None = None) -> Vehicle:
    """Load a vehicle file (a path), or a built-in by name (default: the Crazyflie 2.1)."""
    if path_or_name is None or str(path_or_name) == DEFAULT_VEHICLE:
        text = resources.files("quadcore").joinpath(f"vehicles/{DEFAULT_VEHICLE}.toml").read_text()
        return from_dict(tomllib.loads(text), source=f"builtin:{DEFAULT_VEHICLE}")
    path = Path(path_or_name)
    return from_dict(read_toml(path, VehicleFileError, "vehicle file"), source=str(path))


def write_template(name: str, path: str | Path) -> Vehicle:
    """``quadcore vehicle new``: a vehicle file for ``name`` at ``path`` from the commented
    template (``vehicles/template.toml``: every number with its meaning and unit, starting at the
    Crazyflie 2.1's values), checked by :func:`load` before it is written. Refuses to overwrite
    a file; a name that is not a plain identifier is a :class:`VehicleFileError`."""
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
        raise VehicleFileError(f"vehicle name {name!r}: use letters, digits, '_' or '-' (starting with a letter)")
    path = Path(path)
    if path.exists():
        raise VehicleFileError(f"{path} exists already: choose another --out (nothing was written)")
    text = resources.files("quadcore").joinpath("vehicles/template.toml").read_text().replace("NAME", name)
    vehicle = from_dict(tomllib.loads(text), source=str(path))  # the template is a valid vehicle
    store.write_text(text, path)
    return vehicle


MAX_CONFIG_BYTES = 1 << 20  # a vehicle or model file is a few hundred bytes; anything near this is not one


def read_toml(path: Path, error: type[Exception], what: str) -> dict:
    """A TOML file as a dict; a missing, oversized, non-UTF-8 (UTF-16, binary), malformed or
    absurdly nested file raises ``error`` naming the file and what is wrong, in one line."""
    if not path.is_file():
        raise error(f"{what} not found: {path}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise error(f"{path}: {len(data):,} bytes: not a {what} (at most {MAX_CONFIG_BYTES:,} bytes)")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise error(f"{path}: UTF-16 text: TOML files are UTF-8; save the {what} as UTF-8")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}): a {what} is "
                    "UTF-8 TOML") from None
    if "\x00" in text:
        raise error(f"{path}: holds NUL bytes: a binary file, not a {what}")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{path}: nested too deeply to be a {what}") from None

