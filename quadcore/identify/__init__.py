"""Stage 3, system identification: the physics model and its spec file (``model``), a flight's rows
(``flightdata``), per-flight sufficient statistics (``sufficient``, their file format ``binfile``),
fitting effect parameters (``fit``, a package: the fits, per flight and per session ``fit.sessions``,
the model's fit ``fit.model_fit``),
what physics is missing (``diagnosis``, a package explained in ``docs/diagnosis.md``: problem, scoring,
verdict text, typed result) with its regime tables (``regimes``), evidence (``evidence``) and settings
(``settings``), sparse term discovery (``discovery``, a package: terms, Gram matrices, stored
statistics, selection, effect writer), residual spectra (``spectrum``) and the run history (``history``).

The public API is small (``__all__``): fit a model, diagnose it, discover what it lacks, and the
types they take and give. Each name is loaded on first use (PEP 562 ``__getattr__``): importing
one identify module must not load them all (discovery loads scikit-learn, ~0.7 s).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from quadcore.identify.diagnosis import CandidateScore, Diagnosis, diagnose
    from quadcore.identify.discovery import Discovery, discover
    from quadcore.identify.fit.model_fit import fit_model
    from quadcore.identify.model import PhysicsModel
    from quadcore.identify.settings import DiagnosisSettings
    from quadcore.spec.model import ModelSpec

__all__ = ["CandidateScore", "Diagnosis", "DiagnosisSettings", "Discovery", "ModelSpec", "PhysicsModel", "diagnose",
           "discover", "fit_model"]


# each public name and the identify module it is taken from (ModelSpec: quadcore.spec.model's, as the model imports it)
_WHERE = {"CandidateScore": "diagnosis", "Diagnosis": "diagnosis", "diagnose": "diagnosis", "Discovery": "discovery",
          "discover": "discovery", "fit_model": "fit.model_fit", "PhysicsModel": "model", "ModelSpec": "model",
          "DiagnosisSettings": "settings"}


def __getattr__(name: str) -> Any:
    """A public name, imported when first asked for."""
    if name not in _WHERE:
        raise AttributeError(f"module 'quadcore.identify' has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
