"""The physics model a flight is compared against: a vehicle plus a list of effects.

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
"""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from quadcore import effects
from quadcore.physics import dynamics, residuals, vehicle as vehiclemod
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle


class ModelFileError(ValueError):
    """A model file that is missing, unreadable or names unknown things."""


@dataclass
class EffectTerm:
    """An effect in the model with its parameter values (SI) and their standard errors."""

    name: str
    params: dict[str, float]
    std: dict[str, float] = field(default_factory=dict)
    fixed: bool = False
    # fitted per session: session -> parameters (and their std); ``params`` is then the fleet value
    per_session: dict[str, dict[str, float]] = field(default_factory=dict)
    per_session_std: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def effect(self) -> effects.Effect:
        return effects.get(self.name)

    def to_dict(self) -> dict:
        out = {"name": self.name, "params": self.params, "std": self.std, "fixed": self.fixed}
        if self.per_session:
            out |= {"per_session": self.per_session, "per_session_std": self.per_session_std}
        return out


VEHICLE_DIGEST = "vehicle_digest"


def vehicle_digest(vehicle: Vehicle) -> str:
    """A hash of a vehicle's content (mass, inertia, geometry, thrust map...), not of where it was
    read from: part of a model's identity (its version, what per-flight tables were computed with)."""
    content = {k: v for k, v in dataclasses.asdict(vehicle).items() if k != "source"}
    text = json.dumps(content, sort_keys=True, default=lambda a: np.asarray(a).tolist())
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class PhysicsModel:
    """Nominal vehicle + effects. ``label`` reads like ``nominal+rotor_drag``."""

    vehicle: Vehicle
    terms: list[EffectTerm] = field(default_factory=list)
    sessions: dict[str, list[str]] = field(default_factory=dict)  # session -> flights
    session_maps: dict[str, str] = field(default_factory=dict)  # session -> thrust map kind
    session_patterns: dict[str, list[str]] = field(default_factory=dict)  # session -> flight patterns

    def session_of(self, flight: str) -> str | None:
        """``flight``'s session: one it was fitted in, or one whose patterns name it (a new flight)."""
        return next((s for s, members in self.sessions.items() if flight in members), None) or next(
            (s for s, patterns in self.session_patterns.items()
             if s in self.sessions and any(fnmatch.fnmatchcase(flight, p) for p in patterns)), None)

    def for_flight(self, flight: str) -> PhysicsModel:
        """The model with the thrust map and the per-session parameters of ``flight``'s session
        (a new flight joins the session whose patterns name it); a flight of no known session
        keeps the fleet values, with a warning."""
        session = self.session_of(flight)
        kind = self.session_maps.get(session or "")
        vehicle = self.vehicle.with_thrust_map(kind) if kind else self.vehicle
        split = [t for t in self.terms if t.per_session]
        if split and (session is None or any(session not in t.per_session for t in split)):
            warnings.warn(f"flight {flight!r} is in no fitted session: {', '.join(t.name for t in split)} "
                          "at the fleet value", stacklevel=2)
            return PhysicsModel(vehicle, self.terms, self.sessions, self.session_maps, self.session_patterns)
        terms = [EffectTerm(t.name, t.per_session[session], t.per_session_std.get(session, {}), t.fixed)
                 if t.per_session and session else t for t in self.terms]
        return PhysicsModel(vehicle, terms, self.sessions, self.session_maps, self.session_patterns)

    @property
    def effect_names(self) -> list[str]:
        return [t.name for t in self.terms]

    @property
    def label(self) -> str:
        return "+".join(["nominal", *self.effect_names])

    def extra_wrench(self, state: FlightState) -> tuple[np.ndarray, np.ndarray]:
        """Sum of the effects' body-frame force and torque over a flight."""
        f, tau = np.zeros((state.n, 3)), np.zeros((state.n, 3))
        for t in self.terms:
            df, dtau = t.effect.wrench(state, self.vehicle, t.params)
            f, tau = f + df, tau + dtau
        return f, tau

    def rollout_wrench(self, state: FlightState):
        """The effects' wrench for :func:`quadcore.physics.propagation.rollout`, evaluated on the logged
        state along each window (a simplification: the rollout's own state is not fed back)."""
        f, tau = self.extra_wrench(state)
        return lambda i: (f[i], tau[i])

    def residual_table(self, decoded: pl.DataFrame) -> pl.DataFrame:
        state = dynamics.flight_state(decoded, self.vehicle)
        f, tau = self.extra_wrench(state) if self.terms else (None, None)
        return residuals.residual_table(decoded, self.vehicle, f, tau)

    def to_dict(self) -> dict:
        return {
            "label": self.label,
            "vehicle": self.vehicle.name,
            "vehicle_source": self.vehicle.source,
            "thrust_map": self.vehicle.thrust_map_kind,
            VEHICLE_DIGEST: vehicle_digest(self.vehicle),  # a vehicle file edited in place is another model
            "effects": [t.to_dict() for t in self.terms],
            **({"sessions": self.sessions} if self.sessions else {}),
            **({"session_thrust_map": self.session_maps} if self.session_maps else {}),
            **({"session_patterns": self.session_patterns} if self.session_patterns else {}),
        }

    @classmethod
    def from_dict(cls, d: dict, vehicle: Vehicle) -> PhysicsModel:
        terms = [EffectTerm(e["name"], dict(e["params"]), dict(e.get("std", {})), e.get("fixed", False),
                            dict(e.get("per_session", {})), dict(e.get("per_session_std", {})))
                 for e in d.get("effects", [])]
        return cls(vehicle, terms, {k: list(v) for k, v in d.get("sessions", {}).items()},
                   dict(d.get("session_thrust_map", {})),
                   {k: list(v) for k, v in d.get("session_patterns", {}).items()})


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
    from quadcore.store import store

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


SPEC_DIGEST = "spec_digest"
PLUGINS = "plugins"


@dataclass(frozen=True)
class FittedModel:
    """A physics model fitted for a spec, as ``physics_model`` and the CLI write it: the model,
    the flights its effects were fitted on and those held out, the digest of the spec it was
    fitted for (:func:`fitted_for`), and the plugin modules its effects come from, by effect
    name, file name and SHA-256 (never a path to load: a reader, such as ``quadcore export-c``,
    takes the plugins from the model file its user gives and checks them, :func:`check_plugins`)."""

    model: PhysicsModel
    trained_on: tuple[str, ...]
    held_out: tuple[str, ...]
    spec_digest: str
    plugins: tuple[dict, ...] = ()

    @classmethod
    def of(cls, model: PhysicsModel, spec: ModelSpec, trained_on: list[str],
           held_out: tuple[str, ...] | list[str] = ()) -> FittedModel:
        plugins = tuple(src.to_dict() for src in effects.plugins_from(spec.plugins))
        return cls(model, tuple(trained_on), tuple(held_out), spec.digest(), plugins)

    def to_dict(self) -> dict:
        """The JSON of the fitted model file (``held_out`` is not part of it: it is every other flight)."""
        return {**self.model.to_dict(), "trained_on": list(self.trained_on), SPEC_DIGEST: self.spec_digest,
                **({PLUGINS: list(self.plugins)} if self.plugins else {})}

    def parameter_rows(self) -> list[dict]:
        """One row per fitted parameter: the fleet value, then each session's."""
        rows = [{"effect": t.name, "session": "fleet", "parameter": k, "value": v, "std": t.std.get(k, 0.0)}
                for t in self.model.terms for k, v in t.params.items()]
        return rows + [{"effect": t.name, "session": s, "parameter": k, "value": v,
                        "std": t.per_session_std[s].get(k, 0.0)}
                       for t in self.model.terms for s, values in t.per_session.items() for k, v in values.items()]


def save(model: PhysicsModel, path: Path, trained_on: list[str], spec: ModelSpec) -> Path:
    """Write a fitted model with the digest of the ``spec`` it was fitted for (see :func:`fitted_for`)
    and its plugin modules."""
    from quadcore.store import store

    return store.write_json(FittedModel.of(model, spec, trained_on).to_dict(), path)


def fitted_for(saved: dict, spec: ModelSpec) -> bool:
    """Whether a saved fit (the JSON of :func:`save`) was made for ``spec`` as it is now. The spec
    is compared, not the fit's outcome: a per-session fit whose sessions had no training flight
    saves no per-session values yet is current. A fit saved without a digest is stale."""
    return saved.get(SPEC_DIGEST) == spec.digest()


def check_plugins(saved: dict, where: str = "the fitted model") -> None:
    """Check that the plugin effects a saved model uses (a fitted model's JSON, a learned model's
    manifest) are loaded in this process, from the model file its user gave, with the content
    they were fitted with. Nothing an output names is ever imported: a saved model that names a
    plugin not loaded, or another version of it, or names it by path (as versions before this
    check did), or uses an effect no loaded module defines, raises :class:`ModelFileError` with
    the reason and the fix."""
    fix = "give the model file that names its plugin (--model, QUADCORE_MODEL)"
    recorded = saved.get(PLUGINS, []) or []
    if not isinstance(recorded, list):
        raise ModelFileError(f"{where}: plugins = {recorded!r:.80}: not a list of plugin records; refit with this "
                             "version")
    for entry in recorded:
        if not isinstance(entry, dict) or not {"effect", "sha256"} <= set(entry):
            name = entry if isinstance(entry, str) else repr(entry)[:80]
            loaded_paths = {src.path for src in map(effects.plugin_source, effects.registry()) if src is not None}
            if isinstance(entry, str) and entry in loaded_paths:
                continue  # an earlier version's record: the module the user's model file loaded, not imported here
            raise ModelFileError(f"{where} names the plugin module {name!r}: outputs never name code to run, so it "
                                 f"is not imported; {fix}, or refit with this version")
        loaded = effects.plugin_source(str(entry["effect"]))
        if loaded is None:
            raise ModelFileError(f"{where} uses the plugin effect {entry['effect']!r} (module "
                                 f"{str(entry.get('module', '?'))!r:.80}), which is not loaded: {fix}")
        if loaded.sha256 != entry["sha256"]:
            raise ModelFileError(f"{where} was fitted with another version of plugin effect {entry['effect']!r} "
                                 f"(sha256 {str(entry['sha256'])[:12]}...; loaded from {loaded.path}: "
                                 f"{loaded.sha256[:12]}...): refit, or give the model file with that version")
    known = effects.registry()
    for term in saved.get("effects", []) or []:
        used = term.get("name") if isinstance(term, dict) else None
        if used not in known:
            raise ModelFileError(f"{where} uses the effect {used!r:.80}, which no built-in or loaded plugin module "
                                 f"defines: {fix}")


def load_fitted(path: Path, vehicle: Vehicle) -> PhysicsModel:
    """A fitted model saved by :func:`save`, on the given vehicle (its plugins checked, never
    loaded from it: :func:`check_plugins`)."""
    import json

    saved = json.loads(Path(path).read_text())
    check_plugins(saved, str(path))
    return PhysicsModel.from_dict(saved, vehicle)
