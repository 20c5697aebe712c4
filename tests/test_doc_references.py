"""Every dotted name the README and docs/ mention (``quadcore.learn.artefacts.load``, ...) and
every ``:func:``/``:class:``/``:mod:``/``:meth:``/``:data:`` reference in a docstring resolves
to a module or attribute that exists: the package moves must not leave readers at names that
are gone."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOTTED = re.compile(r"(?<![\w/.])(?:quadcore|pipeline)(?:\.[A-Za-z_]\w*)+(?<!\.md)(?![\w/])")  # not pipeline.md
ROLE = re.compile(r":(?:func|class|mod|meth|data|attr):`~?((?:quadcore|pipeline)(?:\.[A-Za-z_]\w*)+)`")


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for attr in parts[k:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def _references() -> dict[str, str]:
    """name -> where it first appears (file:line)."""
    found: dict[str, str] = {}
    docs = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    sources = sorted([*(REPO / "quadcore").rglob("*.py"), *(REPO / "pipeline").rglob("*.py")])
    for path, pattern in [*((p, DOTTED) for p in docs), *((p, ROLE) for p in sources)]:
        for i, line in enumerate(path.read_text().splitlines(), 1):
            for m in pattern.finditer(line):
                name = m.group(1) if pattern is ROLE else m.group(0)
                found.setdefault(name, f"{path.relative_to(REPO)}:{i}")
    return found


def test_every_documented_name_exists():
    refs = _references()
    assert len(refs) > 50  # the scan found the references
    missing = [f"{where}: {name}" for name, where in sorted(refs.items()) if not _resolves(name)]
    assert not missing, "names that no longer exist:\n" + "\n".join(missing)


@pytest.mark.parametrize("name", ["quadcore.identify.stats.sufficient.nonexistent", "quadcore.nowhere.thing"])
def test_a_name_that_is_gone_is_caught(name):
    assert not _resolves(name)
