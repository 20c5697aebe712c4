"""The report modules, loaded when a report is written: ``reports.diagnosis`` is
:mod:`quadcore.report.diagnosis` (the diagnosis's page and plots) and ``reports.learning`` is
:mod:`quadcore.report.learning` (the learned models' report), each imported on first use (PEP 562
``__getattr__``; typed through the imports under ``TYPE_CHECKING``). They import matplotlib (~0.5 s of
CPU), which a diagnosis without ``--report``, a discovery and a plan's search never need, so the
workflows reach them through this module instead of importing them at module level
(``docs/benchmarks.md``, start-up of the CLI)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from quadcore.report import diagnosis, learning

__all__ = ["diagnosis", "learning"]  # a new report module: its name here and in the import above


def __getattr__(name: str) -> Any:
    """The report module ``name``, imported when first asked for."""
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return importlib.import_module(f"quadcore.report.{name}")
