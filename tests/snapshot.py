"""Snapshot files under ``tests/snapshots/``: a test compares what the code gives now with a
committed list of lines, and fails with the diff and the command that updates the file."""

from __future__ import annotations

import difflib
import json
import math
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


# How close a number in a pinned JSON document must be to the pinned one: relative, with an absolute
# floor for values near zero (an explained variance that cancels to ~1e-15, a coherence of 0).
# Another machine, another BLAS thread count or another summation order moves the last digits
# (measured: up to ~1e-10 relative on near-cancelling sums); a change of method moves far more.
REL = 1e-7
ABS = 1e-12


def json_differences(got, expected, path: str = "", rel: float = REL, abs_: float = ABS) -> list[str]:
    """Where two JSON values differ: structure, keys (in order), strings, booleans and nulls
    exactly; integers exactly; other numbers within ``rel`` (relative) or ``abs_``."""
    def number(v) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool)

    if isinstance(expected, dict) and isinstance(got, dict):
        keys = [] if list(got) == list(expected) else [f"{path or '.'}: keys {list(got)} != {list(expected)}"]
        return keys + [d for k in expected if k in got
                       for d in json_differences(got[k], expected[k], f"{path}.{k}", rel, abs_)]
    if isinstance(expected, list) and isinstance(got, list):
        if len(got) != len(expected):
            return [f"{path}: {len(got)} items != {len(expected)}"]
        return [d for i, (a, b) in enumerate(zip(got, expected)) for d in json_differences(a, b, f"{path}[{i}]", rel,
                                                                                           abs_)]
    if number(got) and number(expected) and (isinstance(got, float) or isinstance(expected, float)):
        a, b = float(got), float(expected)
        if (math.isnan(a) and math.isnan(b)) or a == b or abs(a - b) <= max(rel * max(abs(a), abs(b)), abs_):
            return []
        return [f"{path}: {got!r} != {expected!r}"]
    return [] if type(got) is type(expected) and got == expected else [f"{path}: {got!r} != {expected!r}"]


def assert_json_matches(text: str, name: str, what: str, test_file: str) -> None:
    """The JSON document ``text`` equals the snapshot ``name`` in structure and text, numbers to
    :data:`REL` / :data:`ABS` (:func:`json_differences`), never byte for byte; with
    ``QUADCORE_UPDATE_SNAPSHOT=1`` a snapshot that differs is rewritten (one that matches is left
    alone: its last digits are another machine's, as good as this one's)."""
    path = FOLDER / name
    diffs = json_differences(json.loads(text), json.loads(path.read_text())) if path.exists() else ["(no snapshot)"]
    if diffs and os.environ.get(UPDATE_ENV):  # rewritten only when it differs beyond the tolerance
        path.write_text(text if text.endswith("\n") else text + "\n")
        diffs = json_differences(json.loads(text), json.loads(path.read_text()))
    shown = "\n".join(diffs[:40]) + (f"\n... and {len(diffs) - 40} more" if len(diffs) > 40 else "")
    assert not diffs, (
        f"{what} changed ({len(diffs)} values; numbers compared to {REL:g} relative or {ABS:g}):\n{shown}\n\n"
        f"If the change is intended, update the snapshot with `{UPDATE_ENV}=1 python -m pytest {test_file}` and "
        f"commit {path.relative_to(REPO)}")


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
