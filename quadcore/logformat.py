"""The Crazyflie uSD-card binary log format: decoder and encoder.

Layout of a file (all integers little-endian)::

    u8   magic           0xBC
    u16  version         1: u32 timestamps in ms, 2: u64 timestamps in us
    u16  n_event_types
    n_event_types times:
        u16  event_id        (differs between firmware builds: always map through the header)
        str  event_name      NUL-terminated ASCII
        u16  n_variables
        n_variables times:
            str  "name(t)"   NUL-terminated; t is a struct character: B b H h I i f e
    records, until the trailer:
        u16  event_id
        u32 | u64 timestamp
        packed values of that event's variables, in header order, no padding
    u32  CRC32 of everything before it

Decoding is vectorised. Records of different event types have different sizes, so
record boundaries form a chain ``next = start + size(id at start)``.  We read the
u16 at *every* byte offset, keep the offsets that hold a known event id (the
candidates), and enumerate the chain from the first record by pointer doubling:
``O(n log n)`` numpy gathers, no Python loop per record.  Records are then
gathered into one ``(rows, record_size)`` byte matrix per event type and viewed
through a structured dtype.

Bad input never raises for something that can be recovered: a CRC mismatch,
a missing CRC, a partial last record or bytes that break the record chain are
reported in ``DecodedLog.warnings`` together with what was kept and dropped.
Only a file with nothing to recover (empty, wrong magic byte, unknown version,
unreadable header) raises a :class:`LogFormatError`.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAGIC = 0xBC
CRC_SIZE = 4
TIMESTAMP_DTYPE = {1: np.dtype("<u4"), 2: np.dtype("<u8")}
TIMESTAMP_TO_US = {1: 1000, 2: 1}
TYPE_CHARS = {
    "B": "<u1",
    "b": "<i1",
    "H": "<u2",
    "h": "<i2",
    "I": "<u4",
    "i": "<i4",
    "f": "<f4",
    "e": "<f2",
}


class LogFormatError(ValueError):
    """A file that holds no recoverable log. Subclasses say why."""


class EmptyLogError(LogFormatError):
    """The file has no bytes (or too few for a header)."""


class BadMagicError(LogFormatError):
    """The first byte is not 0xBC: not a Crazyflie uSD log."""


class UnsupportedVersionError(LogFormatError):
    """A format version this decoder does not know."""


class CorruptHeaderError(LogFormatError):
    """The header cannot be parsed (truncated, bad type character, duplicate ids)."""


@dataclass(frozen=True)
class EventType:
    """One event type declared in the header."""

    event_id: int
    name: str
    variables: tuple[str, ...]
    type_chars: tuple[str, ...]

    def payload_dtype(self) -> np.dtype:
        return np.dtype([(v, TYPE_CHARS[t]) for v, t in zip(self.variables, self.type_chars)])

    def record_dtype(self, version: int) -> np.dtype:
        fields = [("event_id", "<u2"), ("timestamp", TIMESTAMP_DTYPE[version])]
        fields += [(v, TYPE_CHARS[t]) for v, t in zip(self.variables, self.type_chars)]
        return np.dtype(fields)  # packed: numpy adds no padding without align=True


@dataclass
class DecodedLog:
    """What a log holds: one structured array per event type, plus what went wrong.

    ``timestamps_us`` per event type are the raw timestamps converted to integer
    microseconds; ``tables`` hold the raw logged values (firmware units).
    """

    version: int
    event_types: dict[str, EventType]
    tables: dict[str, np.ndarray]
    timestamps_us: dict[str, np.ndarray]
    warnings: list[str] = field(default_factory=list)
    bytes_total: int = 0
    bytes_dropped: int = 0
    crc_ok: bool | None = None  # None: no CRC present

    def rows(self) -> dict[str, int]:
        return {name: len(table) for name, table in self.tables.items()}


def _read_cstring(buf: bytes, pos: int) -> tuple[str, int]:
    end = buf.find(b"\x00", pos)
    if end < 0:
        raise CorruptHeaderError(f"header is truncated: unterminated name at byte {pos}")
    try:
        return buf[pos:end].decode("ascii"), end + 1
    except UnicodeDecodeError as exc:
        raise CorruptHeaderError(f"non-ASCII name in header at byte {pos}") from exc


def parse_header(buf: bytes) -> tuple[int, dict[int, EventType], int]:
    """Parse the header. Returns (version, event types by id, offset of first record)."""
    if len(buf) == 0:
        raise EmptyLogError("file is empty")
    if buf[0] != MAGIC:
        raise BadMagicError(f"first byte is 0x{buf[0]:02X}, expected 0xBC: not a Crazyflie uSD log")
    if len(buf) < 5:
        raise EmptyLogError(f"file has {len(buf)} bytes, too short for a header")
    version, n_types = struct.unpack_from("<HH", buf, 1)
    if version not in TIMESTAMP_DTYPE:
        raise UnsupportedVersionError(f"format version {version} is not supported (known: 1, 2)")
    pos = 5
    types: dict[int, EventType] = {}
    try:
        for _ in range(n_types):
            (event_id,) = struct.unpack_from("<H", buf, pos)
            name, pos = _read_cstring(buf, pos + 2)
            (n_vars,) = struct.unpack_from("<H", buf, pos)
            pos += 2
            names, chars = [], []
            for _ in range(n_vars):
                spec, pos = _read_cstring(buf, pos)
                if not (spec.endswith(")") and "(" in spec):
                    raise CorruptHeaderError(f"variable spec {spec!r} is not 'name(t)'")
                var, t = spec[:-1].split("(", 1)
                if t not in TYPE_CHARS:
                    raise CorruptHeaderError(f"variable {var!r} has unknown type {t!r}")
                names.append(var)
                chars.append(t)
            if event_id in types:
                raise CorruptHeaderError(f"event id {event_id} declared twice")
            types[event_id] = EventType(event_id, name, tuple(names), tuple(chars))
    except struct.error as exc:
        raise CorruptHeaderError(f"header is truncated at byte {pos}") from exc
    return version, types, pos


def _chain(starts: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    """Indices of the nodes reached from node 0 by following ``nxt``, in order.

    ``nxt`` maps node -> node; sink nodes map to themselves. Pointer doubling:
    after step k the list holds the first 2**k nodes of the chain.
    """
    order = np.zeros(1, dtype=np.int64)
    jump = nxt
    while True:
        last = order[-1]
        if nxt[last] == last:  # reached a sink
            break
        order = np.concatenate([order, jump[order]])
        jump = jump[jump]
    is_sink = nxt[order] == order
    first_sink = int(np.argmax(is_sink))
    return order[: first_sink + 1]


def decode_bytes(buf: bytes) -> DecodedLog:
    """Decode a whole uSD log held in memory. See the module docstring."""
    version, types_by_id, data_start = parse_header(buf)
    warnings: list[str] = []
    n_total = len(buf)

    crc_ok: bool | None = None
    data_end = n_total - CRC_SIZE
    if data_end >= data_start:
        (crc_stored,) = struct.unpack_from("<I", buf, data_end)
        crc_ok = (zlib.crc32(buf[:data_end]) & 0xFFFFFFFF) == crc_stored

    ts_dtype = TIMESTAMP_DTYPE[version]
    sizes = {eid: 2 + ts_dtype.itemsize + et.payload_dtype().itemsize for eid, et in types_by_id.items()}

    def walk(end: int):
        """Follow the record chain over buf[data_start:end]. Returns (starts, ids, stop_reason, stop_at)."""
        region = np.frombuffer(buf, dtype=np.uint8, count=end - data_start, offset=data_start)
        n = len(region)
        if n < 2 or not types_by_id:
            return np.empty(0, np.int64), np.empty(0, np.uint16), ("end" if n == 0 else "garbage"), 0
        # Candidate record starts: offsets holding a declared event id (two byte compares per id).
        per_id = [np.flatnonzero((region[:-1] == (eid & 0xFF)) & (region[1:] == (eid >> 8))) for eid in sizes]
        cand = np.sort(np.concatenate(per_id)) if len(per_id) > 1 else per_id[0]
        if len(cand) == 0 or cand[0] != 0:
            return np.empty(0, np.int64), np.empty(0, np.uint16), "garbage", 0
        cand_ids = region[cand].astype(np.uint16) | (region[cand + 1].astype(np.uint16) << 8)
        size_lut = np.zeros(65536, dtype=np.int64)
        for eid, size in sizes.items():
            size_lut[eid] = size
        m = len(cand)
        # Two sinks: END (chain hits exactly the end) and BREAK (anything else).
        END, BREAK = m, m + 1
        nxt_offset = cand + size_lut[cand_ids]
        j = np.minimum(np.searchsorted(cand, nxt_offset), m - 1)
        nxt = np.where(cand[j] == nxt_offset, j, np.where(nxt_offset == n, END, BREAK))
        nxt = np.concatenate([nxt, [END, BREAK]])
        order = _chain(cand, nxt)
        sink = order[-1]
        nodes = order[:-1]
        starts, ids = cand[nodes], cand_ids[nodes]
        if sink == END:
            return starts, ids, "end", n
        if len(nodes) and nxt_offset[nodes[-1]] > n:
            # the final record runs past the end: a partial last record
            return starts[:-1], ids[:-1], "partial", int(starts[-1])
        # the chain hit bytes that are no record: keep what came before
        stop = int(nxt_offset[nodes[-1]]) if len(nodes) else 0
        return starts, ids, "garbage", stop

    if crc_ok is None:
        warnings.append("no CRC trailer: file is truncated; decoded what was there")
        starts, ids, reason, stop = walk(n_total)
        end_used = n_total
    else:
        starts, ids, reason, stop = walk(data_end)
        end_used = data_end
        if reason != "end":
            # Either the trailer is missing (a truncated file) or the data is damaged. A file
            # whose records end cleanly or mid-record at its very end, read without a trailer,
            # was truncated; otherwise keep whichever reading recovers more.
            starts2, ids2, reason2, stop2 = walk(n_total)
            if reason2 in ("end", "partial") or len(starts2) > len(starts):
                starts, ids, reason, stop, end_used = starts2, ids2, reason2, stop2, n_total
                crc_ok = None
                warnings.append("no valid CRC trailer: file looks truncated; decoded what was there")
        if crc_ok is False:
            warnings.append("CRC mismatch: the file is damaged; values may be wrong")

    region_len = end_used - data_start
    bytes_dropped = region_len - stop if reason != "end" else 0
    if reason == "partial":
        warnings.append(f"partial last record: dropped {bytes_dropped} bytes at the end")
    elif reason == "garbage":
        warnings.append(
            f"record chain broken at byte {data_start + stop}: kept {len(starts)} records, "
            f"dropped {bytes_dropped} bytes"
        )

    tables: dict[str, np.ndarray] = {}
    timestamps: dict[str, np.ndarray] = {}
    region = np.frombuffer(buf, dtype=np.uint8, count=region_len, offset=data_start)
    for eid, et in types_by_id.items():
        rec_starts = starts[ids == eid]
        dtype = et.record_dtype(version)
        size = dtype.itemsize
        if len(rec_starts) and len(region) >= size:
            # every record start as a row of a strided byte matrix: one row gather, no index arrays
            rows = np.lib.stride_tricks.as_strided(region, shape=(len(region) - size + 1, size), strides=(1, 1))
            records = rows[rec_starts].reshape(-1).view(dtype)
        else:
            records = np.empty(0, dtype)
        # the variables only: a view of the same records that skips id and timestamp
        tables[et.name] = records.view(np.dtype({
            "names": list(et.variables),
            "formats": [dtype.fields[v][0] for v in et.variables],
            "offsets": [dtype.fields[v][1] for v in et.variables],
            "itemsize": size,
        }))
        timestamps[et.name] = records["timestamp"].astype(np.int64) * TIMESTAMP_TO_US[version]

    return DecodedLog(
        version=version,
        event_types={et.name: et for et in types_by_id.values()},
        tables=tables,
        timestamps_us=timestamps,
        warnings=warnings,
        bytes_total=n_total,
        bytes_dropped=int(bytes_dropped),
        crc_ok=crc_ok,
    )


def decode_file(path: str | Path) -> DecodedLog:
    """Decode a uSD log file. Raises :class:`LogFormatError` when nothing is recoverable."""
    return decode_bytes(Path(path).read_bytes())


def encode(
    event_types: list[EventType],
    records: list[tuple[str, np.ndarray, np.ndarray]],
    version: int = 2,
    with_crc: bool = True,
) -> bytes:
    """Write a uSD log.

    ``records`` is a list of ``(event name, timestamps, values)`` where ``timestamps`` are
    in the file's native unit (ms for version 1, us for version 2) and ``values`` is a
    structured array with the event's variables (or a 2-D array in header order).
    Records of all event types are interleaved in timestamp order (stable), as the
    deck writes them.
    """
    if version not in TIMESTAMP_DTYPE:
        raise UnsupportedVersionError(f"format version {version} is not supported (known: 1, 2)")
    by_name = {et.name: et for et in event_types}
    header = bytearray(struct.pack("<BHH", MAGIC, version, len(event_types)))
    for et in event_types:
        header += struct.pack("<H", et.event_id) + et.name.encode("ascii") + b"\x00"
        header += struct.pack("<H", len(et.variables))
        for var, t in zip(et.variables, et.type_chars):
            header += f"{var}({t})".encode("ascii") + b"\x00"

    chunks, keys = [], []
    for name, ts, values in records:
        et = by_name[name]
        dtype = et.record_dtype(version)
        rec = np.empty(len(ts), dtype=dtype)
        rec["event_id"] = et.event_id
        rec["timestamp"] = ts
        for i, var in enumerate(et.variables):
            rec[var] = values[var] if values.dtype.names else values[:, i]
        chunks.append(rec.view(np.uint8).reshape(len(ts), dtype.itemsize))
        keys.append(np.asarray(ts, dtype=np.int64))
    body = b""
    if chunks:
        owner = np.concatenate([np.full(len(k), i) for i, k in enumerate(keys)])
        row = np.concatenate([np.arange(len(k)) for k in keys])
        order = np.lexsort((owner, np.concatenate(keys)))
        owner, row = owner[order], row[order]
        sizes = np.array([c.shape[1] for c in chunks])[owner]
        offsets = np.cumsum(sizes) - sizes
        out = np.empty(int(sizes.sum()), dtype=np.uint8)
        for i, chunk in enumerate(chunks):  # one scatter per event type
            mine = owner == i
            out[offsets[mine][:, None] + np.arange(chunk.shape[1])] = chunk[row[mine]]
        body = out.tobytes()
    data = bytes(header) + body
    if with_crc:
        data += struct.pack("<I", zlib.crc32(data) & 0xFFFFFFFF)
    return data
