"""The code a kept result was made by, as one digest: a file kept under the data root (a decoded
table, a flight's statistics, its rate-level sums) records the digest of the modules whose
functions made its numbers, so that after a change of that code the file is stale: computed
again, never read as if the new code had made it.

The one way the project digests its own code; each cache names its modules beside the code that
keys it (``quadcore.logs.flight.DECODER_MODULES``, ``quadcore.identify.stats.sufficient.CODE_MODULES``, ...).
"""

from __future__ import annotations

import hashlib
import importlib.util
from collections.abc import Iterable
from pathlib import Path


def modules_digest(names: Iterable[str]) -> str:
    """The first 16 hex digits of the SHA-256 of each module's name and source file bytes, in the
    order given (a module that cannot be found counts as the bytes ``missing``). Not cached here:
    each caller keeps its digest once per process (a release is a new process), so that a test can
    clear it to stand for one."""
    digest = hashlib.sha256()
    for name in names:
        found = importlib.util.find_spec(name)
        origin = found.origin if found is not None else None
        digest.update(name.encode() + (Path(origin).read_bytes() if origin else b"missing"))
    return digest.hexdigest()[:16]
