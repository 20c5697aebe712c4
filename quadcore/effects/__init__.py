"""The effect library: physical effects the nominal model may be missing.

Each built-in effect lives in its own module of this package with an ``EFFECT`` instance
(see :mod:`quadcore.effects.base` for the contract); every module here is picked up, so
:func:`builtin_names` is whatever the package holds. User modules elsewhere are loaded with
:func:`load_plugin` (the model file's ``plugins`` list does this; a module that cannot be
used raises :class:`PluginError`) and forgotten with :func:`unregister`. A worked example:
``docs/adding-an-effect.md`` and ``examples/effects/linear_drag.py``.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
from pathlib import Path

from quadcore.effects.base import (
    TARGETS,
    Effect,
    Parameter,
    SimContext,
    SimHook,
    Target,
)

__all__ = [
    "Effect",
    "Parameter",
    "PluginError",
    "SimContext",
    "SimHook",
    "Target",
    "UnknownEffectError",
    "builtin_names",
    "get",
    "load_plugin",
    "registry",
    "unregister",
]

_NOT_EFFECTS = ("base",)  # modules of this package that define no effect
_REGISTRY: dict[str, Effect] = {}
_BUILTIN: list[str] = []  # names of the effects found in this package, in module order


class UnknownEffectError(KeyError):
    """An effect name that no module defines."""

    def __str__(self) -> str:
        return str(self.args[0])


def _register(module) -> Effect:
    effect = getattr(module, "EFFECT", None)
    if not isinstance(effect, Effect) or not effect.name:
        raise TypeError(f"module {module.__name__} has no EFFECT (an Effect instance with a name)")
    if effect.target not in TARGETS:
        raise TypeError(f"effect {effect.name!r} has target {effect.target!r}; one of {', '.join(TARGETS)}")
    _REGISTRY[effect.name] = effect
    return effect


def _discover() -> None:
    if _BUILTIN:
        return
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name not in _NOT_EFFECTS:
            _BUILTIN.append(_register(importlib.import_module(f"{__name__}.{info.name}")).name)


def builtin_names() -> tuple[str, ...]:
    """The effects this package defines (one per module, alphabetical by module)."""
    _discover()
    return tuple(_BUILTIN)


def registry() -> dict[str, Effect]:
    """All known effects by name (built in, then plugins), in a stable order."""
    builtin = builtin_names()
    order = [*builtin, *sorted(n for n in _REGISTRY if n not in builtin)]
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
    if spec is None or spec.loader is None:
        raise PluginError(f"effect module {path} cannot be imported (not a Python file?)")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except (Exception, SystemExit) as exc:  # a user's module: report, do not crash (nor exit)
        raise PluginError(f"cannot import effect module {path}: {type(exc).__name__}: {exc}") from exc
    effect = getattr(module, "EFFECT", None)
    if isinstance(effect, Effect) and effect.name in builtin_names():
        raise PluginError(f"effect module {path} names its effect {effect.name!r}, a built-in effect; "
                          "choose another name")
    try:
        return _register(module)
    except TypeError as exc:
        raise PluginError(str(exc)) from None


def unregister(name: str) -> None:
    """Forget a plugin effect (built-in effects stay)."""
    if name in builtin_names():
        raise ValueError(f"{name!r} is built in and cannot be unregistered")
    _REGISTRY.pop(name, None)
