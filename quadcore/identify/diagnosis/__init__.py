"""Where the model fails, and which physical effect is missing: :func:`diagnose` fits every effect
of the library that the model lacks on the training flights and scores it on flights it never saw.

How it decides (held-out significance, the noise floor, ties the data cannot break, what is
missing beside the best one) is in ``docs/diagnosis.md``; the thresholds in
:mod:`quadcore.identify.evidence`. The package, by step:

* :mod:`~quadcore.identify.diagnosis.problem`: the flights, the folds, the cross-fit;
* :mod:`~quadcore.identify.diagnosis.scoring`: each candidate's score and decision, the ties, the ranking;
* :mod:`~quadcore.identify.diagnosis.span`: the candidates' signatures compared;
* :mod:`~quadcore.identify.diagnosis.sensitivity`: the detection limits;
* :mod:`~quadcore.identify.diagnosis.verdict`: why each is ranked where it is, the verdict text and report rows;
* :mod:`~quadcore.identify.diagnosis.results`: the typed result (:class:`Diagnosis`, :class:`CandidateScore`);
* :mod:`~quadcore.identify.diagnosis.run`: :func:`diagnose`, the steps in order.
"""

from quadcore.identify.diagnosis.problem import HeldOut, default_candidates, fold_splits, held_out_of_model
from quadcore.identify.diagnosis.results import (
    NO_EVIDENCE,
    NOTHING,
    CandidateScore,
    Diagnosis,
    Evaluation,
    ResidualRmse,
    Stability,
)
from quadcore.identify.diagnosis.run import diagnose
from quadcore.identify.diagnosis.sensitivity import detection_limits, sensitivity_basis

__all__ = ["NOTHING", "NO_EVIDENCE", "CandidateScore", "Diagnosis", "Evaluation", "HeldOut", "ResidualRmse",
           "Stability", "default_candidates", "detection_limits", "diagnose", "fold_splits", "held_out_of_model",
           "sensitivity_basis"]
