"""Stage 4, learned residual models (``docs/learning.md``): feature sets (``features``), what to train
(``learners``), which flights (``splits``), the trainers (``trainers``; ``backends``, XGBoost and the MLP,
each loaded when used; ``trees`` for the compiled forest), a trained model's folder (``artefacts``;
``quadcore.learn.artefacts.load``), experiments (``experiments``) and how good they are (``evaluation``,
``metrics``, ``tables``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["artefacts", "backends", "evaluation", "experiments", "features", "learners", "metrics", "splits", "tables",
           "trees"]
