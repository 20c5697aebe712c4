"""What a model file asks for, before fitting (:class:`ModelSpec`): a vehicle plus a list of effects.

A model file (TOML) names them; a user "adds an effect" by adding its name::

    vehicle = "crazyflie21"          # built-in name or a path to a vehicle file
    thrust_map = "pwm_vbat"          # optional: override the vehicle file's map
    effects = ["rotor_drag"]         # fitted on training flights
    plugins = ["my_effects/prop_wash.py"]   # optional: user effect modules

    [parameters.rotor_drag]          # optional: fixed values instead of fitting
    k_x_s_per_m = 0.01

    [per_session]                    # optional: fitted per session of flights, not fleet-wide
    thrust_scale = ["scale"]         # (every free parameter of the effect)

    [sessions]                       # optional: which flights form a session (shell patterns);
    early = ["jana0*", "jana1*"]     # without it, sessions are the groups the data show
    late = ["jana2*", "jana3*"]

    [session_thrust_map]             # optional: another thrust map for a named session (e.g.
    late = "motor_speed"             # where the logged battery voltage is stuck)

Relative paths are relative to the model file. A flight of no session gets the fleet value of
a per-session parameter, with a warning.

The fitted model (values, standard errors, per-session values) is
:mod:`quadcore.identify.model`.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadcore import effects
from quadcore.physics import vehicle as vehiclemod
from quadcore.physics.vehicle import Vehicle
from quadcore.store import store


class ModelFileError(ValueError):
    """A model file that is missing, unreadable or names unknown things."""


@dataclass
class ModelSpec:
    """What a model file asks for, before fitting."""

    vehicle: Vehicle
    effects: list[str]
    fixed: dict[str, dict[str, float]] = field(default_factory=dict)
    source: str = ""
    per_session: list[str] = field(default_factory=list)  # effects fitted per session
    session_patterns: dict[str, list[str]] = field(default_factory=dict)  # session -> flight patterns
    session_maps: dict[str, str] = field(default_factory=dict)  # session -> thrust map kind
    plugins: list[str] = field(default_factory=list)  # resolved paths of the plugin modules
    sessions_file: str = ""  # a sessions file (--sessions, QUADCORE_SESSIONS): its groups change a fit

    def digest(self) -> str:
        """A hash of everything here that changes a fit: effects, fixed values, per-session
        effects, session patterns and thrust maps, the vehicle's content (not where it was read
        from), the plugins' source and the sessions file's content. Equal specs give equal
        digests across processes."""
        vehicle = {k: v for k, v in dataclasses.asdict(self.vehicle).items() if k != "source"}
        content = {"effects": self.effects, "fixed": self.fixed, "per_session": self.per_session,
                   "sessions": self.session_patterns, "session_thrust_map": self.session_maps,
                   "vehicle": vehicle, "plugins": [_file_digest(p) for p in self.plugins]}
        if self.sessions_file:  # only then: a fit made without one keeps its digest
            content["sessions_file"] = _file_digest(self.sessions_file)
        text = json.dumps(content, sort_keys=True, default=lambda a: np.asarray(a).tolist())
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def session_of(self, flight: str) -> str | None:
        return next((name for name, patterns in self.session_patterns.items()
                     if any(fnmatch.fnmatchcase(flight, p) for p in patterns)), None)

    def vehicle_for(self, flight: str) -> Vehicle:
        """The vehicle with the thrust map of ``flight``'s session (the spec's own otherwise)."""
        kind = self.session_maps.get(self.session_of(flight) or "")
        return self.vehicle.with_thrust_map(kind) if kind else self.vehicle

    def sessions_of(self, flights: list[str]) -> dict[str, list[str]]:
        """The model file's sessions resolved against ``flights`` (empty without a [sessions] table)."""
        return {name: sorted(f for f in flights if any(fnmatch.fnmatchcase(f, p) for p in patterns))
                for name, patterns in self.session_patterns.items()}

    def with_effects(self, names: list[str]) -> ModelSpec:
        """The same vehicle and source with ``names`` as the effect list (what ``--effects`` and
        ``QUADCORE_EFFECTS`` do to a model file); fixed values are kept for the effects still named."""
        spec = spec_from(self.vehicle, names, {k: v for k, v in self.fixed.items() if k in names})
        spec.source = self.source
        spec.per_session = [n for n in self.per_session if n in names]
        spec.session_patterns, spec.session_maps = self.session_patterns, self.session_maps
        spec.plugins, spec.sessions_file = self.plugins, self.sessions_file
        return spec


def _file_digest(path: str) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:  # gone since it was loaded: differs from any saved digest, so the fit is redone
        return f"unreadable:{path}"


def spec_from(vehicle: Vehicle, effect_names: list[str], fixed: dict | None = None) -> ModelSpec:
    for name in effect_names:
        effects.get(name)  # raises UnknownEffectError with the known names
    if len(set(effect_names)) != len(effect_names):
        raise ModelFileError(f"an effect is listed twice: {effect_names}")
    return ModelSpec(vehicle, list(effect_names), dict(fixed or {}))


MODEL_FILE_KEYS = ("vehicle", "thrust_map", "effects", "plugins", "parameters", "per_session", "sessions",
                   "session_thrust_map", "allow_unusual")


def _string_list(d: dict, key: str, path: Path) -> list[str]:
    value = d.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ModelFileError(f"{path}: {key} = {value!r:.60}: expected a list of strings")
    return value


def _fixed_parameters(d: dict, names: list[str], path: Path) -> dict[str, dict[str, float]]:
    """The ``[parameters.<effect>]`` values: finite numbers within the effect's fitting bounds (the
    plausible range), unless ``allow_unusual = ["<effect>.<parameter>"]`` names them."""
    allowed = _string_list(d, "allow_unusual", path)
    fixed = d.get("parameters", {})
    if not isinstance(fixed, dict) or not all(isinstance(v, dict) for v in fixed.values()):
        raise ModelFileError(f"{path}: parameters = {fixed!r:.60}: expected [parameters.<effect>] tables")
    for name, params in fixed.items():
        if name not in names:
            raise ModelFileError(f"{path}: [parameters.{name}] given but {name!r} is not in effects")
        known = {p.name: p for p in effects.get(name).parameters}
        unknown = set(params) - set(known)
        if unknown:
            raise ModelFileError(f"{path}: unknown parameters for {name}: {sorted(unknown)}; known: {sorted(known)}")
        for key, value in params.items():
            if not vehiclemod.is_finite_number(value):
                raise ModelFileError(f"{path}: [parameters.{name}] {key} = {value!r:.60}: expected a finite number")
            par = known[key]
            if not par.lower <= value <= par.upper and f"{name}.{key}" not in allowed:
                raise ModelFileError(f"{path}: [parameters.{name}] {key} = {value:.4g}: outside the plausible range "
                                     f"{par.lower:g} to {par.upper:g} {par.unit}; if it really is so, add "
                                     f"allow_unusual = [\"{name}.{key}\"] to the file")
    return fixed


def _per_session(d: dict, names: list[str], fixed: dict, path: Path) -> list[str]:
    """Effects whose parameters ``[per_session]`` asks to fit per session (all of their parameters)."""
    table = d.get("per_session", {})
    if not isinstance(table, dict):
        raise ModelFileError(f"{path}: per_session = {table!r:.60}: expected a [per_session] table")
    for name, params in table.items():
        if name not in names or name in fixed:
            raise ModelFileError(f"{path}: [per_session] {name}: {name!r} must be in effects and not fixed")
        known = [p.name for p in effects.get(name).parameters]
        names_ok = isinstance(params, list) and all(isinstance(x, str) for x in params)
        if not names_ok or sorted(params) != sorted(known):
            raise ModelFileError(f"{path}: [per_session] {name} = {params!r:.60}: a session gets all of "
                                 f"{name}'s parameters: {known}")
    return list(table)


def _session_maps(d: dict, sessions: dict, path: Path) -> dict[str, str]:
    table = d.get("session_thrust_map", {})
    if not isinstance(table, dict):
        raise ModelFileError(f"{path}: session_thrust_map = {table!r:.60}: expected a [session_thrust_map] table")
    for name, kind in table.items():
        if name not in sessions:
            raise ModelFileError(f"{path}: [session_thrust_map] {name}: no session {name!r} in [sessions]")
        if kind not in vehiclemod.THRUST_MAP_KINDS:
            raise ModelFileError(f"{path}: [session_thrust_map] {name} = {kind!r:.60}: expected one of "
                                 f"{', '.join(vehiclemod.THRUST_MAP_KINDS)}")
    return table


def _session_patterns(d: dict, path: Path) -> dict[str, list[str]]:
    table = d.get("sessions", {})
    if not isinstance(table, dict) or not all(isinstance(v, list) and all(isinstance(x, str) for x in v)
                                              for v in table.values()):
        raise ModelFileError(f"{path}: sessions = {table!r:.60}: expected NAME = [\"flight\", \"pattern*\"]")
    return table


def load_model_file(model_file: str | Path, vehicle_override: str | None = None) -> ModelSpec:
    """Read a model file (see module docstring). Every key is checked; an error names the file,
    the key and what was expected. Plugins are Python modules that run when loaded: a model
    file must be trusted like code."""
    path: Path = store.as_root(model_file)  # a data root's own model file may sit in an object store
    d = vehiclemod.read_toml(path, ModelFileError, "model file")
    unknown = sorted(set(d) - set(MODEL_FILE_KEYS))
    if unknown:
        raise ModelFileError(f"{path}: unknown key {unknown[0]!r}: expected one of {', '.join(MODEL_FILE_KEYS)}")
    base = path.parent

    def resolve(p: str) -> str:
        if Path(p).is_absolute():
            return p
        if store.is_remote(base):  # plugins and vehicle files are read from this machine's disk
            raise ModelFileError(f"{path}: {p!r}: a model file in an object store names local files by "
                                 "absolute path only")
        return str((base / p).resolve())

    plugins = _string_list(d, "plugins", path)
    twice = sorted({p for p in plugins if [resolve(q) for q in plugins].count(resolve(p)) > 1})
    if twice:
        raise ModelFileError(f"{path}: plugins: {twice[0]!r} is listed twice: list each module once")
    for plugin in plugins:
        try:
            effects.load_plugin(resolve(plugin))
        except (FileNotFoundError, TypeError) as exc:
            raise ModelFileError(f"{path}: plugin {plugin!r}: {exc}") from None
    veh_name = vehicle_override or d.get("vehicle", vehiclemod.DEFAULT_VEHICLE)
    if not isinstance(veh_name, str) or not veh_name:
        raise ModelFileError(f"{path}: vehicle = {veh_name!r:.60}: expected a built-in vehicle name or a path")
    if veh_name != vehiclemod.DEFAULT_VEHICLE and not vehicle_override:
        veh_name = resolve(veh_name)
    try:
        veh = vehiclemod.load(veh_name)
    except vehiclemod.VehicleFileError as exc:  # one line naming both files
        raise ModelFileError(f"{path}: vehicle {veh_name!r:.200}: {exc}") from None
    if "thrust_map" in d:
        if d["thrust_map"] not in vehiclemod.THRUST_MAP_KINDS:
            raise ModelFileError(f"{path}: thrust_map = {d['thrust_map']!r:.60}: expected one of "
                                 f"{', '.join(vehiclemod.THRUST_MAP_KINDS)}")
        veh = veh.with_thrust_map(d["thrust_map"])
    names = _string_list(d, "effects", path)
    try:
        spec = spec_from(veh, names, _fixed_parameters(d, names, path))
    except (effects.UnknownEffectError, ModelFileError) as exc:
        raise ModelFileError(exc.args[0] if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    spec.source, spec.plugins = str(path), [resolve(p) for p in plugins]
    spec.per_session = _per_session(d, names, spec.fixed, path)
    spec.session_patterns = _session_patterns(d, path)
    spec.session_maps = _session_maps(d, spec.session_patterns, path)
    return spec
