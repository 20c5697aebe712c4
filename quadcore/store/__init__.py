"""The data root: where everything lives and Parquet with metadata (``store``), writes that survive a
kill (``safewrite``) and the names allowed to become path components (``names``, the jail)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["names", "ownership", "safewrite", "store"]
