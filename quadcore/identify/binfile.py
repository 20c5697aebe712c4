"""The one file format of the per-flight records (``stats.bin`` of :mod:`quadcore.identify.stats.sufficient`,
``library.bin`` of :mod:`quadcore.identify.discovery.library_stats`, ``summary.bin`` of
:mod:`quadcore.identify.describe.summaries`), where they are stored, and the error a record that cannot
serve a request raises (:class:`StatsError`). Below every module that reads or writes one."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from quadcore.store import store
from quadcore.store.names import check_component

Record = TypeVar("Record")  # what a per-flight record file is read as


class StatsError(ValueError):
    """Statistics that cannot serve a request (an effect missing from their layout, a nonlinear
    effect asked of them, a file that is not a statistics file)."""


def stats_path(root: Any, flight: str) -> Any:
    return store.as_root(root) / "stats" / f"flight={check_component(flight, 'flight id')}" / "stats.bin"


@functools.lru_cache(maxsize=64)
def upper_indices(width: int) -> tuple[np.ndarray, np.ndarray]:
    """The upper triangle's indices of a width × width matrix (cached: every flight asks for the
    same few; read only)."""
    return np.triu_indices(width)


def packed(G: np.ndarray) -> np.ndarray:
    """The upper triangles of symmetric (..., W, W) matrices, (..., W (W + 1) / 2)."""
    return G[(..., *upper_indices(G.shape[-1]))]


def unpacked(P: np.ndarray, width: int) -> np.ndarray:
    i, j = upper_indices(width)
    G = np.zeros((*P.shape[:-1], width, width))
    G[..., i, j] = P
    G[..., j, i] = P
    return G


MAGIC = b"QCSTATS\n"
_HEAD = len(MAGIC) + 8  # the magic, then the JSON header's length


# The one file format of the per-flight records (stats.bin here, library.bin of
# :mod:`quadcore.identify.discovery.library_stats`, summary.bin of :mod:`quadcore.identify.describe.summaries`).

def encode(header: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """``MAGIC``, the JSON header's length (8 bytes, little endian), the header (with each
    array's dtype, shape and offset), then the arrays' bytes: read back without a parser."""
    offset, parts, index = 0, [], {}
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        index[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset}
        parts.append(a.tobytes())
        offset += a.nbytes
    text = json.dumps({**header, "arrays": index}).encode()
    return MAGIC + len(text).to_bytes(8, "little") + text + b"".join(parts)


def decode_header(raw: bytes) -> tuple[dict, int]:
    """The header of an :func:`encode` file and the byte where its arrays start (``raw``: the
    file, or its first bytes up to the arrays, :func:`read_file`'s ``header_only``)."""
    if not raw.startswith(MAGIC):
        raise ValueError("no statistics header")
    start = _HEAD + int.from_bytes(raw[len(MAGIC): _HEAD], "little")
    return json.loads(raw[_HEAD: start]), start


def read_array(raw: bytes, start: int, name: str, spec: dict) -> np.ndarray:
    """The array ``name`` of an :func:`encode` file (``spec``: its header entry, ``start``: where
    the arrays start), a view of ``raw``; a ValueError when the file is cut short of it."""
    count = int(np.prod(spec["shape"]))
    end = start + spec["offset"] + count * np.dtype(spec["dtype"]).itemsize
    if end > len(raw):
        raise ValueError(f"cut short: array {name!r} ends at byte {end}, the file has {len(raw)}")
    return np.frombuffer(raw, np.dtype(spec["dtype"]), count, start + spec["offset"]).reshape(spec["shape"])


def decode(raw: bytes) -> tuple[dict, Callable[[str], np.ndarray]]:
    """The header of an :func:`encode` file and ``array(name)``, after checking every array is
    whole (before any is read lazily)."""
    header, start = decode_header(raw)
    for name, spec in header["arrays"].items():
        read_array(raw, start, name, spec)

    def array(name: str) -> np.ndarray:
        return read_array(raw, start, name, header["arrays"][name])

    return header, array


def require_format(header: dict, fmt: int) -> None:
    """A ValueError unless the header is of the format ``fmt`` this code reads."""
    if header.get("format") != fmt:
        raise ValueError(f"format {header.get('format')}, this code reads {fmt}")


def write_file(path: Any, header: dict, arrays: dict[str, np.ndarray]) -> Any:
    """:func:`encode` written to ``path`` atomically (an object store too)."""
    data = encode(header, arrays)
    return store.atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def read_file(path: Any, header_only: bool = False) -> bytes:
    """An :func:`encode` file's bytes (an object store's too); ``header_only``: up to its arrays."""
    if not header_only:
        return path.read_bytes() if store.is_remote(path) else Path(path).read_bytes()
    with path.open("rb") as fh:
        head = fh.read(_HEAD)
        return head + fh.read(int.from_bytes(head[len(MAGIC):], "little"))


def read_if_present(path: Any, read: Callable[[], Record]) -> Record | None:
    """``read()`` of the record file at ``path``, or None when it is missing or not one
    (:class:`StatsError`)."""
    if not path.exists():
        return None
    try:
        return read()
    except StatsError:
        return None
