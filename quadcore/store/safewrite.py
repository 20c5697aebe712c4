"""Writes that survive a kill and runs that do not collide.

- Temp files and staging folders carry the writer's pid in their name
  (``.<name>.<pid>.<random>.tmp``, ``.<name>.<pid>.<random>.staging``): two writers never share
  one, and a leftover whose writer is gone is recognisably stale.
- A folder of files that only make sense together (a learned model: weights, scaler, features,
  manifest) is written into a staging folder and put in place by :func:`replace_folder`.
- :func:`sweep_stale` removes what killed writers left behind; the main job calls it on start. It
  sweeps only data roots the project made (marked, :mod:`quadcore.store.ownership`), only its
  output folders there (never ``raw/`` or ``.dagster/``), and only the names its writers give.
- :func:`data_root_lock` serialises whole jobs on one data root: a second job waits.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from quadcore.store import ownership

LOCK_FILE = ownership.LOCK_FILE
STALE_AFTER_S = 3600.0  # a leftover of an earlier version (no pid in its name) is stale after this long


def temp_prefix(name: str) -> str:
    """Prefix of a temp file or staging folder for ``name`` (``tempfile`` adds the random part)."""
    return f".{name}.{os.getpid()}."


def staging_folder(final: Path) -> Path:
    """A new, empty staging folder beside ``final``."""
    final.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=temp_prefix(final.name), suffix=".staging", dir=final.parent))


def replace_folder(staging: Path, final: Path) -> Path:
    """Put the complete folder ``staging`` in the place of ``final`` (two renames: ``final``
    aside, ``staging`` in). A reader sees the old folder whole, or the new one whole, or,
    for the instant between the renames, none; never a mix."""
    old = None
    if final.exists():
        old = final.with_name(f"{temp_prefix(final.name)}{time.monotonic_ns()}.old")
        final.rename(old)
    staging.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _is_url(root) -> bool:
    """Whether a data root is an object-store URL (``s3://...``, a ``UPath``), not a folder here."""
    return "://" in str(root)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _is_stale(path: Path, now: float) -> bool:
    """A leftover of one of the project's writers whose writer is gone: its pid (in the name) is
    not running; a leftover of an earlier version (no pid) older than ``STALE_AFTER_S``."""
    match = ownership.LEFTOVER.match(path.name)
    if match:
        pid = int(match["pid"])
        return pid != os.getpid() and not _pid_alive(pid)
    if ownership.LEGACY_LEFTOVER.match(path.name):
        try:
            return now - path.lstat().st_mtime > STALE_AFTER_S
        except OSError:
            return False
    return False


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _walk_output_folder(folder: Path) -> Iterator[Path]:
    """Every entry under one of the root's output folders, parents first, never through a
    symlink nor into a nested data root."""
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        here = Path(dirpath)
        dirnames[:] = [d for d in dirnames if not ownership.is_marked(here / d)]
        for name in [*dirnames, *filenames]:
            yield here / name


def sweep_stale(root: Path) -> list[Path]:
    """Remove temp files and staging/old folders that killed writers left in the data root
    ``root`` (see :func:`_is_stale`). Only a root the project made or adopted (its marker,
    :func:`quadcore.store.ownership.claim`) is swept, and there only its top level and its output
    folders (:data:`quadcore.store.ownership.OUTPUT_FOLDERS`), never the raw logs, the Dagster
    instance or a nested data root. Returns what was removed."""
    removed: list[Path] = []
    if _is_url(root):  # an object store: every write is one whole PUT, no temp object is ever left
        return removed
    root, now = Path(root), time.time()
    if not root.is_dir() or not ownership.is_marked(root):
        return removed
    candidates = []
    for entry in sorted(root.iterdir()):
        candidates.append(entry)
        if entry.name in ownership.OUTPUT_FOLDERS and entry.is_dir() and not entry.is_symlink():
            candidates += _walk_output_folder(entry)
    for path in candidates:
        if ownership.is_leftover_name(path.name) and path.parent.exists() and _is_stale(path, now):
            _remove(path)
            removed.append(path)
    return removed


@contextlib.contextmanager
def data_root_lock(root: Path, on_wait=None) -> Iterator[None]:
    """Hold the data root's lock (``<root>/.quadcore.lock``) for the block. Another holder makes
    this wait (``on_wait(message)`` is called once first); the lock dies with its process.

    An object store has no such lock: for ``s3://...`` the lock is a local file named after the
    URL and the store's endpoint (``AWS_ENDPOINT_URL``; in the temp folder), which serialises the
    jobs of this machine on that root, not those of other machines. Two stores of one machine
    (two local clusters, each its own S3 server) hold the same URL and do not wait for each other."""
    if _is_url(root):
        endpoint = os.environ.get("AWS_ENDPOINT_URL", "").strip()
        digest = hashlib.sha256(f"{endpoint} {root}".strip().encode()).hexdigest()[:16]
        lock = Path(tempfile.gettempdir()) / f"quadcore-{digest}{LOCK_FILE}"
    else:
        Path(root).mkdir(parents=True, exist_ok=True)
        lock = Path(root) / LOCK_FILE
    with open(lock, "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait(f"another job holds {lock}: waiting for it to finish")
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
