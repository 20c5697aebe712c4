"""Stage 3, system identification: the physics model and its spec file (``model``), flight sessions
(``sessions``), per-flight sufficient statistics (``sufficient``), fitting effect parameters
(``fitting``), the evidence behind a verdict (``evidence``), what physics is missing (``diagnosis``),
sparse term discovery (``discovery``), residual spectra (``spectrum``) and the run history (``history``)."""
