"""The effect library: physical effects the nominal model may be missing.

Built in: ``rotor_drag``, ``parasitic_drag``, ``ground_effect``, ``motor_lag``,
``com_offset``, ``thrust_scale``, ``added_mass``, ``wind``. Each lives in its own module
with an ``EFFECT`` instance (see :mod:`quadcore.effects.base` for the shape). Every
module in this package is picked up; user modules elsewhere are loaded with
:func:`load_plugin` (the model file's ``plugins`` list does this; a module that cannot be
used raises :class:`PluginError`) and forgotten with :func:`unregister`. A worked example:
``docs/adding-an-effect.md`` and ``examples/effects/linear_drag.py``.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
from pathlib import Path

from quadcore.effects.base import Effect, Parameter

__all__ = ["Effect", "Parameter", "registry", "get", "load_plugin", "unregister", "PluginError", "UnknownEffectError",
           "BUILTIN"]

BUILTIN = (
    "rotor_drag", "parasitic_drag", "ground_effect", "motor_lag",
    "com_offset", "thrust_scale", "added_mass", "wind",
)
_REGISTRY: dict[str, Effect] = {}


class UnknownEffectError(KeyError):
    """An effect name that no module defines."""

    def __str__(self) -> str:
        return str(self.args[0])


def _register(module) -> Effect:
    effect = getattr(module, "EFFECT", None)
    if not isinstance(effect, Effect) or not effect.name:
        raise TypeError(f"module {module.__name__} has no EFFECT (an Effect instance with a name)")
    _REGISTRY[effect.name] = effect
    return effect


def _discover() -> None:
    if _REGISTRY:
        return
    for info in pkgutil.iter_modules(__path__):
        if info.name != "base":
            _register(importlib.import_module(f"{__name__}.{info.name}"))


def registry() -> dict[str, Effect]:
    """All known effects by name (built in, then plugins), in a stable order."""
    _discover()
    order = [n for n in BUILTIN if n in _REGISTRY] + sorted(n for n in _REGISTRY if n not in BUILTIN)
    return {n: _REGISTRY[n] for n in order}


def get(name: str) -> Effect:
    effects = registry()
    if name not in effects:
        raise UnknownEffectError(f"unknown effect {name!r}; known: {', '.join(effects)}")
    return effects[name]


class PluginError(TypeError):
    """A user effect module that cannot be used (does not import, has no ``EFFECT``, or
    reuses a built-in name). A ``TypeError`` so that callers reporting bad plugins catch it."""


def load_plugin(path: str | Path) -> Effect:
    """Load a user's effect module from a file and register its ``EFFECT``.

    Raises ``FileNotFoundError`` for a missing file and :class:`PluginError` for a module
    that fails to import, has no ``EFFECT`` or would replace a built-in effect.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"effect module not found: {path}")
    spec = importlib.util.spec_from_file_location(f"quadcore_plugin_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)  # type: ignore[union-attr]
    except Exception as exc:  # a user's module: report, do not crash
        raise PluginError(f"cannot import effect module {path}: {type(exc).__name__}: {exc}") from exc
    _discover()
    effect = getattr(module, "EFFECT", None)
    if isinstance(effect, Effect) and effect.name in BUILTIN:
        raise PluginError(f"effect module {path} names its effect {effect.name!r}, a built-in effect; choose another name")
    try:
        return _register(module)
    except TypeError as exc:
        raise PluginError(str(exc)) from None


def unregister(name: str) -> None:
    """Forget a plugin effect (built-in effects stay)."""
    if name in BUILTIN:
        raise ValueError(f"{name!r} is built in and cannot be unregistered")
    _REGISTRY.pop(name, None)
