"""The effect library: physical effects the nominal model may be missing.

Built in: ``rotor_drag``, ``parasitic_drag``, ``ground_effect``, ``motor_lag``,
``com_offset``, ``thrust_scale``, ``added_mass``, ``wind``. Each lives in its own module
with an ``EFFECT`` instance (see :mod:`quadcore.effects.base` for the shape). Every
module in this package is picked up; user modules elsewhere are loaded with
:func:`load_plugin` (the model file's ``plugins`` list does this).
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
from pathlib import Path

from quadcore.effects.base import Effect, Parameter

__all__ = ["Effect", "Parameter", "registry", "get", "load_plugin", "UnknownEffectError", "BUILTIN"]

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


def load_plugin(path: str | Path) -> Effect:
    """Load a user's effect module from a file and register its ``EFFECT``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"effect module not found: {path}")
    spec = importlib.util.spec_from_file_location(f"quadcore_plugin_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    _discover()
    return _register(module)
