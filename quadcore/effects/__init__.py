"""The effect library: physical effects the nominal model may be missing.

Each built-in effect lives in its own module of this package with an ``EFFECT`` instance
(see :mod:`quadcore.effects.base` for the contract); every module here is picked up, so
:func:`builtin_names` is whatever the package holds. User modules elsewhere are loaded with
:func:`load_plugin` (the model file's ``plugins`` list does this; a module that cannot be
used raises :class:`PluginError`) and forgotten with :func:`unregister`. A worked example:
``docs/adding-an-effect.md`` and ``examples/effects/linear_drag.py``.
"""

from __future__ import annotations

import hashlib
import importlib
import pkgutil
import types
from dataclasses import dataclass
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
    "PluginSource",
    "SimContext",
    "SimHook",
    "Target",
    "UnknownEffectError",
    "builtin_names",
    "get",
    "load_plugin",
    "plugin_source",
    "plugins_from",
    "registry",
    "unregister",
]

_NOT_EFFECTS = ("base", "c_inputs", "ccode")  # modules of this package that define no effect
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


@dataclass(frozen=True)
class PluginSource:
    """Where a plugin effect was loaded from: the module file and the SHA-256 of the bytes that ran."""

    effect: str
    path: str
    sha256: str

    def to_dict(self) -> dict:
        """As a fitted model records it: the effect, the module's file name (not a path to load:
        outputs never name code to run) and its digest."""
        return {"effect": self.effect, "module": Path(self.path).name, "sha256": self.sha256}


_PLUGIN_SOURCES: dict[str, PluginSource] = {}  # plugin effect name -> its module, as loaded


def plugin_source(name: str) -> PluginSource | None:
    """The module a plugin effect was loaded from in this process (None: not a loaded plugin)."""
    return _PLUGIN_SOURCES.get(name)


def plugins_from(paths) -> list[PluginSource]:
    """The plugin effects this process loaded from the module files ``paths`` (a model file's
    resolved ``plugins``), in the registry's order: that model's own plugins, not every plugin
    a long-lived process has loaded for other models."""
    paths = {str(Path(p)) for p in paths}
    return [src for name in registry() if (src := _PLUGIN_SOURCES.get(name)) is not None and src.path in paths]


def load_plugin(path: str | Path) -> Effect:
    """Load a user's effect module from a file and register its ``EFFECT``.

    The file is read once; the bytes that run are those whose SHA-256 is recorded
    (:func:`plugin_source`). Raises ``FileNotFoundError`` for a missing file and
    :class:`PluginError` for a module that fails to import, has no ``EFFECT`` or would replace
    a built-in effect.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"effect module not found: {path}")
    data = path.read_bytes()
    module = types.ModuleType(f"quadcore_plugin_{path.stem}")
    module.__file__ = str(path)
    try:
        exec(compile(data, str(path), "exec"), module.__dict__)  # noqa: S102 (a module the user's model file names)
    except (Exception, SystemExit) as exc:  # a user's module: report, do not crash (nor exit)
        raise PluginError(f"cannot import effect module {path}: {type(exc).__name__}: {exc}") from exc
    effect = getattr(module, "EFFECT", None)
    if isinstance(effect, Effect) and effect.name in builtin_names():
        raise PluginError(f"effect module {path} names its effect {effect.name!r}, a built-in effect; "
                          "choose another name")
    try:
        registered = _register(module)
    except TypeError as exc:
        raise PluginError(str(exc)) from None
    _PLUGIN_SOURCES[registered.name] = PluginSource(registered.name, str(path), hashlib.sha256(data).hexdigest())
    return registered


def unregister(name: str) -> None:
    """Forget a plugin effect (built-in effects stay)."""
    if name in builtin_names():
        raise ValueError(f"{name!r} is built in and cannot be unregistered")
    _REGISTRY.pop(name, None)
    _PLUGIN_SOURCES.pop(name, None)
