"""The two kinds of learned model, each a module that imports its library at module level:
:mod:`quadcore.learn.backends.xgb` (XGBoost) and :mod:`quadcore.learn.backends.mlp` (PyTorch). Both offer
``train(spec, data, seed, threads) -> (impl, info)``, ``predict(impl, Z)``, ``save(impl, folder)`` and
``load(folder, spec, n_in, n_out, threads)``.

:func:`backend` is the one place they are imported: by kind, when a model of that kind is trained, read or
run (each library takes ~1.7 s of CPU to import, and torch is installed on its own, outside the
package's dependencies), so that the rest of ``quadcore.learn`` stays cheap to import."""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["backend", "MODULES"]

# learner kind -> its module in this package
MODULES = {"xgboost": "xgb", "mlp": "mlp"}


def backend(kind: str) -> ModuleType:
    """The module of the learner kind ``kind`` (``xgboost`` or ``mlp``), imported now."""
    return importlib.import_module(f"quadcore.learn.backends.{MODULES[kind]}")
