"""Stage 3, system identification: the physics model and its spec file (``model``), flight sessions
(``sessions``), per-flight sufficient statistics (``sufficient``), fitting effect parameters
(``fitting``), what physics is missing (``diagnosis``, explained in ``docs/diagnosis.md``) with its
regime tables (``regimes``), verdict text (``verdict``), typed result (``results``) and evidence
(``evidence``), sparse term discovery (``discovery``), residual spectra (``spectrum``) and the run
history (``history``)."""
