"""Stage 4, learned residual models: feature sets (``features``), trainers, artefacts and experiments
(``learning``; load a trained model with ``quadcore.learn.learning.load``) and their evaluation
(``evaluation``)."""
