"""The physics model a flight is compared against, fitted: a vehicle plus effects with their
parameter values (:class:`PhysicsModel`), and a fitted model as it is saved and checked
(:class:`FittedModel`, :func:`save`, :func:`fitted_for`, :func:`check_plugins`, :func:`load_fitted`).

What a model file asks for, before fitting (:class:`quadcore.spec.model.ModelSpec`), and the model
file's parser live in :mod:`quadcore.spec.model`, below this package.
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
from quadcore.physics import dynamics, residuals
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle
from quadcore.spec.model import ModelFileError, ModelSpec
from quadcore.store import store


@dataclass(frozen=True)
class HeldBound:
    """A fitted parameter held at a physical bound: the bound, the free fit (without bounds) and
    its standard error, how many of them the free value lies beyond the bound, and ``note``: what
    that says (within noise of the bound, or a form that does not fit the data)."""

    bound: float
    free: float
    free_std: float
    beyond_sigma: float
    note: str

    def to_dict(self) -> dict:
        return {"bound": self.bound, "free": self.free, "free_std": self.free_std,
                "beyond_sigma": self.beyond_sigma, "note": self.note}

    @classmethod
    def from_dict(cls, d: dict) -> HeldBound:
        return cls(float(d["bound"]), float(d["free"]), float(d["free_std"]), float(d["beyond_sigma"]),
                   str(d.get("note", "")))


@dataclass
class EffectTerm:
    """An effect in the model with its parameter values (SI) and their standard errors;
    ``held``: the parameters the fit held at a physical bound (their free fit left it)."""

    name: str
    params: dict[str, float]
    std: dict[str, float] = field(default_factory=dict)
    fixed: bool = False
    # fitted per session: session -> parameters (and their std); ``params`` is then the fleet value
    per_session: dict[str, dict[str, float]] = field(default_factory=dict)
    per_session_std: dict[str, dict[str, float]] = field(default_factory=dict)
    held: dict[str, HeldBound] = field(default_factory=dict)
    per_session_held: dict[str, dict[str, HeldBound]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # a parameter not given is at its 'no effect' value (as the simulator takes it): a model
        # saved before its effect gained a parameter (rotor_drag's k_z) meant it there
        defaults = _defaults(self.name)
        self.params = {**defaults, **self.params}
        self.per_session = {s: {**defaults, **v} for s, v in self.per_session.items()}

    @property
    def effect(self) -> effects.Effect:
        return effects.get(self.name)

    def to_dict(self) -> dict:
        out = {"name": self.name, "params": self.params, "std": self.std, "fixed": self.fixed}
        if self.per_session:
            out |= {"per_session": self.per_session, "per_session_std": self.per_session_std}
        if self.held:
            out["held_at_bound"] = {k: h.to_dict() for k, h in self.held.items()}
        if self.per_session_held:
            out["per_session_held_at_bound"] = {s: {k: h.to_dict() for k, h in held.items()}
                                                for s, held in self.per_session_held.items()}
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
        terms = [EffectTerm(t.name, t.per_session[session], t.per_session_std.get(session, {}), t.fixed,
                            held=t.per_session_held.get(session, {}))
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
                            dict(e.get("per_session", {})), dict(e.get("per_session_std", {})),
                            _held(e.get("held_at_bound", {})),
                            {s: _held(h) for s, h in e.get("per_session_held_at_bound", {}).items()})
                 for e in d.get("effects", [])]
        return cls(vehicle, terms, {k: list(v) for k, v in d.get("sessions", {}).items()},
                   dict(d.get("session_thrust_map", {})),
                   {k: list(v) for k, v in d.get("session_patterns", {}).items()})


def _held(d: dict) -> dict[str, HeldBound]:
    return {k: HeldBound.from_dict(h) for k, h in d.items()}


def _defaults(name: str) -> dict[str, float]:
    """A known effect's 'no effect' values (none for an effect this process does not know)."""
    known = effects.registry()
    return known[name].defaults() if name in known else {}


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
    saved = json.loads(Path(path).read_text())
    check_plugins(saved, str(path))
    return PhysicsModel.from_dict(saved, vehicle)
