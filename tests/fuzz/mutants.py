"""Mutants of a good log and what the decoder must do with each.

Every mutant carries the byte range it corrupted (``corrupt_from``, ``corrupt_to``, in the
mutated file) when that range is in the record body, so that the harness can check that
every whole record before it was kept and how much after it was recovered.

Kinds: truncations, bit flips, overwritten / inserted / deleted runs of bytes, a record whose
event id is replaced by an undeclared one, and crafted headers (huge counts, long names,
duplicated, reserved, empty and hostile names, flipped header bytes).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from quadcore.logs import logformat

ESCAPE_MARK = "quadcore-fuzz-escape"  # a hostile event name tries to create a file with this name


@dataclass(frozen=True)
class Mutant:
    kind: str
    data: bytes
    corrupt_from: int | None = None  # first corrupted byte of the body, in the mutated file
    corrupt_to: int | None = None  # first byte after it


@dataclass(frozen=True)
class Layout:
    """Where the header ends and where each record starts (a plain walk of the clean log)."""

    data_start: int
    record_starts: np.ndarray
    record_sizes: np.ndarray
    declared_ids: frozenset[int]


def layout(buf: bytes) -> Layout:
    log = logformat.decode_bytes(buf)
    _, types, start = logformat.parse_header(buf)
    ts_size = logformat.TIMESTAMP_DTYPE[log.version].itemsize
    sizes = {eid: 2 + ts_size + et.payload_dtype().itemsize for eid, et in types.items()}
    starts, lens, pos, end = [], [], start, len(buf) - logformat.CRC_SIZE
    while pos + 2 <= end:
        (eid,) = struct.unpack_from("<H", buf, pos)
        if eid not in sizes or pos + sizes[eid] > end:
            break
        starts.append(pos)
        lens.append(sizes[eid])
        pos += sizes[eid]
    return Layout(start, np.array(starts), np.array(lens), frozenset(sizes))


def _with_crc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def _body_offset(rng: np.random.Generator, lay: Layout, n: int) -> int:
    return int(rng.integers(lay.data_start, n - logformat.CRC_SIZE))


def _truncate(buf, lay, rng):
    cut = int(rng.integers(0, len(buf)))
    return Mutant("truncate", buf[:cut])


def _flips(buf, lay, rng):
    data = bytearray(buf)
    at = _body_offset(rng, lay, len(buf))
    for _ in range(int(rng.integers(1, 4))):
        pos = min(at + int(rng.integers(0, 16)), len(buf) - 1)
        data[pos] ^= 1 << int(rng.integers(0, 8))
    return Mutant("flip", bytes(data), at, at + 16)


def _overwrite(buf, lay, rng):
    at, width = _body_offset(rng, lay, len(buf)), int(rng.integers(1, 200))
    junk = rng.integers(0, 256, width, dtype=np.uint8).tobytes()
    return Mutant("overwrite", buf[:at] + junk + buf[at + width:], at, at + width)


def _insert(buf, lay, rng):
    at, width = _body_offset(rng, lay, len(buf)), int(rng.integers(1, 100))
    junk = rng.integers(0, 256, width, dtype=np.uint8).tobytes()
    return Mutant("insert", buf[:at] + junk + buf[at:], at, at + width)


def _delete(buf, lay, rng):
    at, width = _body_offset(rng, lay, len(buf)), int(rng.integers(1, 100))
    return Mutant("delete", buf[:at] + buf[at + width:], at, at + 1)


def _unknown_id(buf, lay, rng):
    i = int(rng.integers(0, len(lay.record_starts)))
    at = int(lay.record_starts[i])
    free = next(e for e in range(1, 65535) if e not in lay.declared_ids)
    data = bytearray(buf)
    data[at:at + 2] = struct.pack("<H", free)
    return Mutant("unknown_id", bytes(data), at, at + int(lay.record_sizes[i]))


def _header_flip(buf, lay, rng):
    data = bytearray(buf)
    pos = int(rng.integers(0, lay.data_start))
    data[pos] ^= 1 << int(rng.integers(0, 8))
    return Mutant("header_flip", bytes(data))


def _rewrite_header(buf: bytes, lay: Layout, edit) -> bytes:
    """The log with its header re-serialised after ``edit(list of EventType)``."""
    version, types, start = logformat.parse_header(buf)
    ets = edit(list(types.values()))
    header = bytearray(struct.pack("<BHH", logformat.MAGIC, version, len(ets) & 0xFFFF))
    for et in ets:
        header += struct.pack("<H", et.event_id) + et.name.encode("latin-1") + b"\x00"
        header += struct.pack("<H", len(et.variables))
        for var, t in zip(et.variables, et.type_chars):
            header += f"{var}({t})".encode("latin-1") + b"\x00"
    return _with_crc(bytes(header) + buf[start:len(buf) - logformat.CRC_SIZE])


HOSTILE_NAMES = ["../../" + ESCAPE_MARK, "/tmp/" + ESCAPE_MARK, "a=b", "x" * 250, "", ".", "..", "fixedFrequency",
                 "con", "a\\b", "name with spaces", "\x7f\x01"]


def _hostile_name(buf, lay, rng):
    name = HOSTILE_NAMES[int(rng.integers(0, len(HOSTILE_NAMES)))]
    which = int(rng.integers(0, 2))

    def edit(ets):
        ets[which] = logformat.EventType(ets[which].event_id, name, ets[which].variables, ets[which].type_chars)
        return ets
    return Mutant("hostile_event_name", _rewrite_header(buf, lay, edit))


def _bad_variable(buf, lay, rng):
    how = ["duplicate", "reserved", "empty", "timestamp", "long"][int(rng.integers(0, 5))]

    def edit(ets):
        et = ets[0]
        names = list(et.variables)
        names[1] = {"duplicate": names[0], "reserved": "event_id", "empty": "", "timestamp": "timestamp",
                    "long": "v" * 300}[how]
        ets[0] = logformat.EventType(et.event_id, et.name, tuple(names), et.type_chars)
        return ets
    return Mutant(f"variable_{how}", _rewrite_header(buf, lay, edit))


def _huge_counts(buf, lay, rng):
    data = bytearray(buf)
    how = int(rng.integers(0, 3))
    if how == 0:  # the header declares more event types than it holds
        data[3:5] = struct.pack("<H", int(rng.integers(3, 65536)))
    elif how == 1:  # the first event declares a huge number of variables
        name_end = buf.index(b"\x00", 7)
        data[name_end + 1:name_end + 3] = struct.pack("<H", int(rng.integers(1000, 65536)))
    else:  # many declared event types, each tiny, ahead of the real ones
        version, types, start = logformat.parse_header(buf)
        extra = min(int(rng.integers(10, 2000)), 65535 - len(types))
        ids = [e for e in range(1, 65535) if e not in types][:extra]
        filler = b"".join(struct.pack("<H", e) + b"e%d\x00" % e + struct.pack("<H", 1) + b"v(B)\x00" for e in ids)
        head = struct.pack("<BHH", logformat.MAGIC, version, len(types) + extra) + filler + buf[5:start]
        return Mutant("huge_counts", _with_crc(head + buf[start:len(buf) - logformat.CRC_SIZE]))
    return Mutant("huge_counts", bytes(data))


GENERATORS = [_truncate, _flips, _overwrite, _insert, _delete, _unknown_id, _header_flip, _hostile_name,
              _bad_variable, _huge_counts]


def mutants(buf: bytes, n: int, seed: int = 0) -> Iterator[Mutant]:
    """``n`` mutants of the good log ``buf``, cycling over the kinds."""
    rng = np.random.default_rng(seed)
    lay = layout(buf)
    for i in range(n):
        yield GENERATORS[i % len(GENERATORS)](buf, lay, rng)
