"""Stage 3, system identification: the physics model and its spec file (``model``), flight sessions
(``sessions``), per-flight sufficient statistics (``sufficient``), fitting effect parameters
(``fitting``), what physics is missing (``diagnosis``, a package explained in ``docs/diagnosis.md``:
problem, scoring, verdict text, typed result) with its regime tables (``regimes``) and evidence
(``evidence``), sparse term discovery (``discovery``, a package: terms, Gram matrices,
stored statistics, selection, effect writer), residual spectra (``spectrum``) and the run
history (``history``)."""

# The modules other packages import today (the identify re-layout of issue 23 narrows this to the
# model, diagnosis and discovery; docs/architecture.md). Importing the package imports none of them.
__all__ = ["diagnosis", "discovery", "evidence", "fitting", "history", "model", "regimes", "sessions",
           "sufficient"]
