"""The data root: where everything lives and Parquet with metadata (``store``), writes that survive a
kill (``safewrite``) and the names allowed to become path components (``names``, the jail)."""
