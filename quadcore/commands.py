"""The commands a hint names, spelled so that they run as printed from the working directory."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path


def shown_path(path: Path | str) -> str:
    """``path`` as a hint prints it: relative to the working directory when inside it
    (``mine/data``), else absolute."""
    resolved = Path(path).expanduser().resolve()
    try:
        return str(resolved.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(resolved)


def quadcore_command() -> str:
    """The ``quadcore`` command of this environment as a shell would run it here: ``quadcore``
    when the shell's ``PATH`` finds this environment's script (an activated venv), else its
    path (``.venv/bin/quadcore`` from the clone: the README's spelling)."""
    script = Path(sys.executable).parent / "quadcore"  # not resolved: the venv's bin, not the base Python's
    found = shutil.which("quadcore", path=os.environ.get("PATH", ""))
    if not script.is_file() or (found and Path(found).resolve() == script.resolve()):
        return "quadcore"
    return shown_path(script)
