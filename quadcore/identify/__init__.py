"""Stage 3, system identification, laid out by concept (bottom to top, docs/architecture.md): the
diagnosis's settings (``settings``); a flight's rows (``flightdata``), the statistics' record format
(``binfile``), the physics model and its file (``model``), the range checks (``ranges``); what a residual
looks like (``describe``: regimes, spectrum, summaries); a flight's statistics, the one place its rows
become sums (``stats``: profiles, sufficient); the fits from statistics (``fit``: solve, linear, profiled,
search, sessions, model_fit); the held-out test and detection limits (``evidence``); rotor timing at the
angular-rate level (``rates``); what physics is missing (``diagnosis``, a package explained in
``docs/diagnosis.md``), sparse term discovery (``discovery``) and the run history (``history``).

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
