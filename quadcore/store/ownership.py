"""What the project owns on disk: the folders it made carry a marker, and only those are swept.

A data root (``QUADCORE_DATA_ROOT``, ``quadcore decode|train --out DIR``) gets a marker file
``<root>/.quadcore`` (JSON: ``{"quadcore": "data root", "format": 1, "flights": ...}``) when the
project creates it or takes it over. :func:`claim` is called before anything is written there:

- a folder that does not exist yet, or is empty, is created and marked;
- a marked folder is used (a marker of a newer format is refused: another version's root);
- a folder without a marker whose every entry is the project's own layout (``decoded/``,
  ``residuals/``, ``model.toml``, ... as earlier versions left it; :data:`LAYOUT`) is adopted:
  marked, and said so;
- any other folder (``~``, a project checkout, a folder of documents) is refused with
  :class:`ForeignFolderError`, naming a few of its entries: nothing is written or deleted there.

:func:`quadcore.store.safewrite.sweep_stale` sweeps marked folders only, and there only the
names the project's writers produce. The marker also records what kind of flights the root
holds (``"real"`` or ``"simulated"``, :func:`flights_kind`): the main job never fits simulated
and real flights in one root unless asked to (``QUADCORE_ALLOW_SIMULATED=1``).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path

MARKER = ".quadcore"
FORMAT = 1
LOCK_FILE = ".quadcore.lock"
# Entries a data root of this project holds (what its writers create; README.md is the default
# root's own, committed with the repository): a root made of these alone may be adopted.
OUTPUT_FOLDERS = frozenset({"decoded", "residuals", "rollouts", "stats", "checks", "history", "models", "reports",
                            "features", "learned", "export_c", "mcap", "quarantine", "plots"})
LAYOUT = OUTPUT_FOLDERS | {"raw", "model.toml", ".dagster", LOCK_FILE, MARKER, "README.md", "demo"}
# Temp files, staging and old folders of the project's writers (safewrite.temp_prefix):
# ``.<name>.<pid>.<random>.tmp|staging|old`` with <name> a safe path component.
LEFTOVER = re.compile(r"^\.(?P<name>[A-Za-z0-9_+-][A-Za-z0-9_.+-]*)\.(?P<pid>\d+)\.(?P<tag>[A-Za-z0-9_]+)"
                      r"\.(?P<kind>tmp|staging|old)$")
# What versions before the marker left at a root's top level while replacing the feature tables.
LEGACY_LEFTOVER = re.compile(r"^\.features-(old-\.features-)?[a-z0-9_]+$")
FLIGHT_KINDS = ("real", "simulated", "mixed")


class ForeignFolderError(ValueError):
    """A folder the project did not create (no marker, not its layout): never written to, never swept."""


def _is_url(root) -> bool:
    """An object-store root (``s3://...`` or a ``UPath`` with a protocol): never swept, no marker."""
    return "://" in str(root) or (bool(getattr(root, "protocol", "")) and not isinstance(root, Path))


def read_marker(root) -> dict | None:
    """The marker of ``root`` (None: no marker, or not readable as one, or an object store)."""
    if _is_url(root):
        return None
    try:
        text = (Path(root) / MARKER).read_text(encoding="utf-8")
        marker = json.loads(text)
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and marker.get("quadcore") == "data root" else None


def is_marked(root) -> bool:
    """Whether ``root`` is a folder the project made or took over (it holds a readable marker)."""
    return not _is_url(root) and read_marker(root) is not None


def _write_marker(root: Path, marker: dict) -> None:
    fd, tmp = tempfile.mkstemp(dir=root, prefix=f"{MARKER}.{os.getpid()}.", suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump(marker, fh)
    os.replace(tmp, root / MARKER)


def is_leftover_name(name: str) -> bool:
    """A name one of the project's writers gives a temp file or staging/old folder."""
    return LEFTOVER.match(name) is not None or LEGACY_LEFTOVER.match(name) is not None


def _own_layout(root: Path) -> bool:
    """Every entry of ``root`` is one of the project's (its layout, a leftover of its writers,
    or a nested data root of its own)."""
    return all(p.name in LAYOUT or is_leftover_name(p.name) or is_marked(p) for p in root.iterdir())


def claim(root, what: str = "data root") -> str:
    """Make ``root`` a marked data root, or refuse it (:class:`ForeignFolderError`). Returns a
    note for the user when an unmarked root of the project's layout was adopted, else ''.
    An object-store root (``s3://...``) is never swept and needs no marker."""
    if _is_url(root):
        return ""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise ForeignFolderError(f"{what} {root} is a file, not a folder")
    if root.is_dir():
        marker = read_marker(root)
        if marker is not None:
            if not isinstance(marker.get("format"), int) or marker["format"] > FORMAT:
                raise ForeignFolderError(f"{what} {root} was made by a newer quadcore (marker format "
                                         f"{marker.get('format')!r}; this one reads {FORMAT}): use that version")
            return ""
        entries = sorted(p.name for p in root.iterdir())
        if entries and not _own_layout(root):
            shown = ", ".join(entries[:4]) + (f", ... ({len(entries)} entries)" if len(entries) > 4 else "")
            raise ForeignFolderError(
                f"{what} {root} is a folder quadcore did not create and it is not empty ({shown}): quadcore "
                f"writes (and clears its own leftovers) only in folders it made; give a new or empty folder, "
                f"e.g. {root / 'quadcore'}")
        note = f"adopted {root} as a data root (an earlier version's layout; marked with {MARKER})" if entries else ""
    else:
        note = ""
    root.mkdir(parents=True, exist_ok=True)
    _write_marker(root, {"quadcore": "data root", "format": FORMAT})
    return note


def flights_kind(root) -> str:
    """The kind of flights a marked root holds (``real``, ``simulated``, ``mixed``; '' unknown yet)."""
    marker = read_marker(root) or {}
    kind = marker.get("flights", "")
    return kind if kind in FLIGHT_KINDS else ""


def record_flights_kind(root, kind: str) -> None:
    """Record in the marker what kind of flights ``root`` holds."""
    if kind not in FLIGHT_KINDS:
        raise ValueError(f"flight kind {kind!r}: expected one of {FLIGHT_KINDS}")
    marker = read_marker(root)
    if marker is None or _is_url(root):
        return
    if marker.get("flights") != kind:
        _write_marker(Path(root), {**marker, "flights": kind})
