"""What a residual looks like: by regime (:mod:`.regimes`), by frequency (:mod:`.spectrum`),
and the per-flight sums both are read from (:mod:`.summaries`)."""
