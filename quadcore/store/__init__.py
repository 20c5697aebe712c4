"""The data root: where everything lives and Parquet with metadata (``store``), writes that survive a
kill (``safewrite``), the names allowed to become path components (``names``, the jail) and the
digest of the code a kept file was made by (``codedigest``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["codedigest", "names", "ownership", "safewrite", "store"]
