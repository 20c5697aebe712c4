"""Snapshot files under ``tests/snapshots/``: a test compares what the code gives now with a
committed list of lines, and fails with the diff and the command that updates the file."""

from __future__ import annotations

import difflib
import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FOLDER = REPO / "tests" / "snapshots"
UPDATE_ENV = "QUADCORE_UPDATE_SNAPSHOT"


def assert_matches(lines: list[str], name: str, what: str, test_file: str) -> None:
    """``lines`` equal the snapshot ``name``; with ``QUADCORE_UPDATE_SNAPSHOT=1`` the snapshot is
    rewritten first (then commit it with the change that made it necessary)."""
    path = FOLDER / name
    if os.environ.get(UPDATE_ENV):
        path.write_text("\n".join(lines) + "\n")
    expected = path.read_text().splitlines()
    diff = "\n".join(difflib.unified_diff(expected, lines, "snapshot", "now", lineterm=""))
    assert lines == expected, (
        f"{what} changed:\n{diff}\n\nIf the change is intended, update the snapshot with "
        f"`{UPDATE_ENV}=1 python -m pytest {test_file}` and commit {path.relative_to(REPO)}")


def json_shape(value, path: str = "", data_maps: tuple[str, ...] = ()) -> list[str]:
    """The key structure of a JSON document, one sorted line per path: ``.a.b[].c: number``.
    List items are merged (``[]``); a map whose keys are data, not names (e.g. parameter values
    by parameter name), is listed in ``data_maps`` and shown as ``{name}``."""
    out: set[str] = set()

    def walk(v, p: str) -> None:
        if isinstance(v, dict):
            if p.rsplit(".", 1)[-1] in data_maps:
                out.add(f"{p}{{name}}")
                return
            for k, x in v.items():
                walk(x, f"{p}.{k}")
        elif isinstance(v, list):
            out.add(f"{p}[]")
            for x in v:
                if isinstance(x, dict | list):
                    walk(x, f"{p}[]")
        else:
            kind = ("null" if v is None else "bool" if isinstance(v, bool)
                    else "number" if isinstance(v, int | float) else type(v).__name__)
            out.add(f"{p}: {kind}")

    walk(value, path)
    return sorted(out)
