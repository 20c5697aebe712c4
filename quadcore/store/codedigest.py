"""The code a kept result was made by, as one digest: a file kept under the data root (a decoded
table, a flight's statistics, its rate-level sums) records the digest of the modules whose
functions made its numbers, so that after a change of that code the file is stale: computed
again, never read as if the new code had made it.

What is digested is a module's code, not its text: the syntax tree of its source without
docstrings (:func:`code_of`), so an edit of a comment, a docstring or the layout keeps every
kept file current, and any other edit (a number, a name, an error message) makes them stale.

The one way the project digests its own code; each cache names its modules beside the code that
keys it (``quadcore.logs.flight.DECODER_MODULES``, ``quadcore.identify.stats.sufficient.CODE_MODULES``, ...).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
from collections.abc import Iterable
from pathlib import Path

_DOCUMENTED = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)


def modules_digest(names: Iterable[str]) -> str:
    """The first 16 hex digits of the SHA-256 of each module's name and code (:func:`code_of` of
    its source file), in the order given (a module that cannot be found counts as the bytes
    ``missing``). Not cached here: each caller keeps its digest once per process (a release is a
    new process), so that a test can clear it to stand for one."""
    digest = hashlib.sha256()
    for name in names:
        found = importlib.util.find_spec(name)
        origin = found.origin if found is not None else None
        digest.update(name.encode() + (code_of(Path(origin).read_bytes()) if origin else b"missing"))
    return digest.hexdigest()[:16]


@functools.lru_cache(maxsize=64)
def code_of(source: bytes) -> bytes:
    """What of a module's source makes its behaviour: its syntax tree (``ast.dump``, without line
    numbers) with each module's, class's and function's docstring taken out; comments and layout
    are not in the tree. A file that is not Python source (an extension module) counts whole.
    Kept per source text: the caches' digests share modules, and a parse takes 5-25 ms."""
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return source
    for node in ast.walk(tree):
        if isinstance(node, _DOCUMENTED) and node.body and _is_docstring(node.body[0]):
            node.body = node.body[1:]
    return ast.dump(tree, include_attributes=False).encode()


def _is_docstring(statement: ast.stmt) -> bool:
    return (isinstance(statement, ast.Expr) and isinstance(statement.value, ast.Constant)
            and isinstance(statement.value.value, str))
