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
u16 at *every* byte offset once, keep the offsets that hold a declared event id (the
candidates: one table lookup, linear in the file size whatever the header declares), and
enumerate the chain from the first record by pointer doubling: ``O(n log n)`` numpy
gathers, no Python loop per record.  Records are then gathered into one
``(rows, record_size)`` byte matrix per event type and viewed through a structured dtype.

Bad input never raises for something that can be recovered: a CRC mismatch,
a missing CRC, a partial last record or bytes that break the record chain are
reported in ``DecodedLog.warnings`` together with what was kept and dropped.
After bytes that break the chain (a corrupt record), decoding resynchronises: it
resumes at the next offset from which ``RESYNC_RECORDS`` records chain without a
break, and reports each skipped stretch (bytes and time range) in ``DecodedLog.skipped``.
Only a file with nothing to recover (empty, wrong magic byte, unknown version,
unreadable header, a header beyond the limits below, a file above ``MAX_LOG_BYTES``)
raises a :class:`LogFormatError`.

A record is never invented: a record whose end starts no record is kept only when it can be
what its id says (its timestamp fits its own event stream, and the chain does not resume
exactly where a record of another declared type would end: an id corrupted into the other
valid id); an event type most of whose records break the chain has a header layout that does
not fit the body, and none of its records is kept; a CRC trailer that validates the bytes
before it ends the data even after a short last record; a second copy of the header (two files
joined) ends this log. The records the bytes allow are kept: the single intact record after a
corruption near the end is taken back when its timestamp fits its stream.

Event names become path components under the data root, so the decoder hands out
safe, unique names (:mod:`quadcore.store.names`); a renamed or repeated event is a warning.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from quadcore.store import names as namesmod

MAGIC = 0xBC
CRC_SIZE = 4
TIMESTAMP_DTYPE: dict[int, np.dtype] = {1: np.dtype("<u4"), 2: np.dtype("<u8")}
TIMESTAMP_TO_US = {1: 1000, 2: 1}
# Limits of the header: generous for real firmware (2 event types, 25 variables, names under 40
# characters), and they make a crafted header fail fast instead of costing time and folders.
MAX_EVENT_TYPES = 256
MAX_VARIABLES = 1024  # per event type
MAX_NAME_CHARS = 255
MAX_LOG_BYTES = 256 * 2**20
"""The largest file decoded (256 MiB): 95 minutes of the reference deck's 500 Hz records (47 kB/s),
more than ten times a Crazyflie's flight on one battery. Decoding a file into SI tables holds about
3.5 times its size at the peak (335 MB for a 102 MB log: docs/reliability.md), so one file never
needs more than ~1 GB; a larger file is refused with the reason (:class:`LogTooLargeError`)
before any of it is read."""
RESERVED_VARIABLES = ("event_id", "timestamp")  # the record's own fields
RESYNC_RECORDS = 8  # records that must chain without a break where decoding resumes
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


class LogTooLargeError(LogFormatError):
    """The file is larger than :data:`MAX_LOG_BYTES`: refused before it is read."""


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
    skipped: list = field(default_factory=list)  # SkippedStretch, where decoding resynchronised

    def rows(self) -> dict[str, int]:
        return {name: len(table) for name, table in self.tables.items()}


def _read_cstring(buf: bytes, pos: int) -> tuple[str, int]:
    end = buf.find(b"\x00", pos, pos + MAX_NAME_CHARS + 1)
    if end < 0:
        if buf.find(b"\x00", pos) < 0:
            raise CorruptHeaderError(f"header is truncated: unterminated name at byte {pos}")
        raise CorruptHeaderError(f"name at byte {pos} is longer than {MAX_NAME_CHARS} characters")
    try:
        return buf[pos:end].decode("ascii"), end + 1
    except UnicodeDecodeError as exc:
        raise CorruptHeaderError(f"non-ASCII name in header at byte {pos}") from exc


def _variable(spec: str, event: str) -> tuple[str, str]:
    """(name, type character) of a ``"name(t)"`` spec, or :class:`CorruptHeaderError`."""
    if not (spec.endswith(")") and "(" in spec):
        raise CorruptHeaderError(f"variable spec {spec!r:.60} is not 'name(t)'")
    var, t = spec[:-1].split("(", 1)
    if t not in TYPE_CHARS:
        raise CorruptHeaderError(f"variable {var!r:.60} has unknown type {t!r:.10}")
    if not var or var in RESERVED_VARIABLES:
        raise CorruptHeaderError(f"event {event!r:.60} has a variable named {var!r}: empty or reserved")
    return var, t


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
    if n_types > MAX_EVENT_TYPES:
        raise CorruptHeaderError(f"header declares {n_types} event types; at most {MAX_EVENT_TYPES} are supported")
    pos = 5
    types: dict[int, EventType] = {}
    try:
        for _ in range(n_types):
            (event_id,) = struct.unpack_from("<H", buf, pos)
            name, pos = _read_cstring(buf, pos + 2)
            (n_vars,) = struct.unpack_from("<H", buf, pos)
            pos += 2
            if n_vars > MAX_VARIABLES:
                raise CorruptHeaderError(f"event {name!r:.60} declares {n_vars} variables; at most {MAX_VARIABLES}")
            names, chars = [], []
            for _ in range(n_vars):
                spec, pos = _read_cstring(buf, pos)
                var, t = _variable(spec, name)
                if var in names:
                    raise CorruptHeaderError(f"event {name!r:.60} declares variable {var!r} twice")
                names.append(var)
                chars.append(t)
            if event_id in types:
                raise CorruptHeaderError(f"event id {event_id} declared twice")
            types[event_id] = EventType(event_id, name, tuple(names), tuple(chars))
    except struct.error as exc:
        raise CorruptHeaderError(f"header is truncated at byte {pos}") from exc
    return version, types, pos


def _chain(nxt: np.ndarray, start: int) -> np.ndarray:
    """Indices of the nodes reached from ``start`` by following ``nxt``, in order, ending
    with the sink reached.

    ``nxt`` maps node -> node; sink nodes map to themselves. Pointer doubling:
    after step k the list holds the first 2**k nodes of the chain.
    """
    order = np.array([start], dtype=np.int64)
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


@dataclass(frozen=True)
class SkippedStretch:
    """Bytes skipped to resynchronise after a corrupt record: ``[byte_start, byte_end)`` in the
    file, between the records kept at ``t_before_us`` and ``t_after_us`` (None: no such record)."""

    byte_start: int
    byte_end: int
    t_before_us: int | None
    t_after_us: int | None


@dataclass(frozen=True)
class _Walk:
    """The record chain over a region: kept record starts and ids (region offsets), why it
    stopped ("end", "partial", "garbage"), where, and the stretches skipped on the way."""

    starts: np.ndarray
    ids: np.ndarray
    reason: str
    stop: int
    skips: np.ndarray  # (k, 2) region byte ranges
    skip_neighbours: np.ndarray  # (k, 2) region offsets of the records kept before / after (-1: none)
    misfit: tuple[int, ...] = ()  # event ids whose declared layout does not fit the body (none kept)


def _empty_walk(reason: str) -> _Walk:
    none = np.empty((0, 2), np.int64)
    return _Walk(np.empty(0, np.int64), np.empty(0, np.uint16), reason, 0, none, none)


FEW_IDS = 4  # up to this many declared ids, two byte compares per id beat a table lookup


def _candidates(region: np.ndarray, size_lut: np.ndarray) -> np.ndarray:
    """Offsets whose u16 is a declared event id, sorted. Linear in the region's size: a
    compare per id for a few ids, else one lookup of the u16 at every offset."""
    ids = np.flatnonzero(size_lut).tolist()  # Python ints: a uint8 compare stays uint8
    if not ids or len(region) < 2:  # a header that declares no event type: no record can start
        return np.empty(0, np.int64)
    if len(ids) <= FEW_IDS:
        lo, hi = region[:-1], region[1:]
        hits = [np.flatnonzero((lo == (e & 0xFF)) & (hi == (e >> 8))) for e in ids]
        return np.sort(np.concatenate(hits)) if len(hits) > 1 else hits[0]
    n = len(region)
    words = np.empty(n - 1, np.uint16)  # the u16 at every offset: even offsets, then odd ones
    words[0::2] = region[: n - n % 2].view("<u2")
    words[1::2] = region[1 : 1 + 2 * ((n - 1) // 2)].view("<u2")
    return np.flatnonzero((size_lut > 0)[words])


def _walk(region: np.ndarray, size_lut: np.ndarray, ts_dtype: np.dtype = TIMESTAMP_DTYPE[2]) -> _Walk:
    """Follow the record chain over ``region``, resynchronising after bytes that break it.

    Candidates are offsets whose u16 is a declared event id; ``nxt`` links a candidate to the
    candidate where its record ends (or to the sinks END / BREAK). Where the chain breaks, it
    resumes at the first later candidate from which ``RESYNC_RECORDS`` records chain (or which
    starts at least two records that end the region exactly). A broken record (the bytes at its
    end start no record) is kept only when it can be the record its id says
    (:func:`_doubtful`): one that overlaps the resumed chain was no record, one whose resumed
    chain starts exactly where a record of another declared type would end had its id
    corrupted, and one whose timestamp does not fit its own event stream is not kept either.
    After a last break, a single record ending the region exactly is taken back when its
    timestamp fits its stream (:func:`_tail_record`).

    One function on purpose (issue #15): each step reads the arrays of the steps before
    (``cand``, ``nxt``, ``resumed``, ``dropped``, ``sync``), so parts would pass most of them.
    """
    n = len(region)
    if n < 2:
        return _empty_walk("end" if n == 0 else "garbage")
    cand = _candidates(region, size_lut)
    if len(cand) == 0:
        return _empty_walk("garbage")
    cand_ids = region[cand].astype(np.uint16) | (region[cand + 1].astype(np.uint16) << 8)
    m = len(cand)
    END, BREAK = m, m + 1
    nxt_offset = cand + size_lut[cand_ids]
    j = np.minimum(np.searchsorted(cand, nxt_offset), m - 1)
    nxt = np.where(cand[j] == nxt_offset, j, np.where(nxt_offset == n, END, BREAK))
    nxt = np.concatenate([nxt, [END, BREAK]])

    ahead = nxt
    for _ in range(RESYNC_RECORDS - 1):
        ahead = nxt[ahead]
    sync = np.flatnonzero((ahead[:m] != BREAK) & (nxt[:m] < m))
    breaks = np.flatnonzero(nxt[:m] == BREAK)
    k = np.searchsorted(sync, breaks, side="right")
    target = np.where(k < len(sync), sync[np.minimum(k, max(len(sync) - 1, 0))] if len(sync) else BREAK, BREAK)
    resumed = nxt.copy()
    resumed[breaks] = target
    dropped = np.zeros(m + 2, dtype=bool)
    dropped[breaks] = (target != BREAK) & (cand[np.minimum(target, m - 1)] < nxt_offset[breaks])

    first = 0 if cand[0] == 0 else (int(sync[0]) if len(sync) else -1)
    if first < 0:
        return _empty_walk("garbage")
    order = _chain(resumed, first)
    sink, nodes = order[-1], order[:-1]
    garbage_end = sink == BREAK and nxt_offset[nodes[-1]] <= n  # not a partial last record
    if garbage_end:  # a lone last record that ends the region may follow
        tail = _tail_record(region, cand, cand_ids, nxt, nodes, dropped, ts_dtype)
        if tail >= 0:
            x = nodes[-1]
            resumed[x], sink, garbage_end = tail, END, False
            dropped[x] = cand[tail] < nxt_offset[x]
            nodes = np.r_[nodes, tail]
    jumps = nodes[(nxt[nodes] == BREAK) & (resumed[nodes] != BREAK)]
    resume_at = np.r_[cand, n, -1]  # where the chain goes on after each node (END: the region's end)
    dropped[jumps] |= _doubtful(region, cand, cand_ids, size_lut, nodes, jumps, resume_at[resumed[jumps]], dropped,
                                ts_dtype)
    if garbage_end:
        last = nodes[-1:]
        dropped[last] |= _doubtful(region, cand, cand_ids, size_lut, nodes, last, np.array([n]), dropped, ts_dtype)
    misfit = _misfit_ids(cand_ids[nodes], nxt[nodes] == BREAK)
    if len(misfit):  # the header's layout of these types does not fit the body: none of them is kept
        dropped[nodes[np.isin(cand_ids[nodes], misfit)]] = True
        jumps = np.union1d(jumps, nodes[np.isin(cand_ids[nodes], misfit) & (resumed[nodes] < m)])
    kept = nodes[~dropped[nodes]]

    skip_from = np.where(dropped[jumps], cand[jumps], nxt_offset[jumps])
    skip_to = cand[resumed[jumps]]
    after = resumed[jumps]
    pos = np.searchsorted(kept, after)
    before = np.where(pos > 0, cand[kept[np.maximum(pos - 1, 0)]], -1)
    if first != 0:
        skip_from, skip_to = np.r_[0, skip_from], np.r_[cand[first], skip_to]
        before, after = np.r_[-1, before], np.r_[first, after]
    skips = np.stack([skip_from, skip_to], axis=1).astype(np.int64)
    neighbours = np.stack([before, cand[after]], axis=1).astype(np.int64)

    starts, ids, bad = cand[kept], cand_ids[kept], tuple(int(e) for e in misfit)
    if sink == END:
        return _Walk(starts, ids, "end", n, skips, neighbours, bad)
    last = nodes[-1]
    if nxt_offset[last] > n:  # the final record runs past the end: a partial last record
        keep = slice(None, -1) if not dropped[last] else slice(None)
        return _Walk(starts[keep], ids[keep], "partial", int(cand[last]), skips, neighbours, bad)
    stop = int(nxt_offset[last]) if not dropped[last] else int(cand[last])
    return _Walk(starts, ids, "garbage", stop, skips, neighbours, bad)


def _misfit_ids(ids: np.ndarray, broken: np.ndarray) -> np.ndarray:
    """The event ids most of whose records (more than half, at least two) end where no record
    starts: the header declares a record size the body does not have (a field list or type
    edited), so every record of that id would be read with the wrong layout."""
    if not broken.any():
        return np.zeros(0, ids.dtype)
    total = np.bincount(ids, minlength=65536)
    bad = np.bincount(ids[broken], minlength=65536)
    return np.flatnonzero((bad >= 2) & (2 * bad > total)).astype(ids.dtype)


RESYNC_MAX_GAP_US = 1_000_000
"""How far (us) a record taken back at a break may lie after the previous record of its own event
stream. The streams of a uSD log run at 10 to 1000 Hz, and the real logs' longest gap is ~0.12 s;
a random 8-byte (v2, us) or 4-byte (v1, ms) timestamp lands in a 1 s window with probability
5e-14 or 2e-7, on top of the 2**-16 of a random u16 being a declared id."""


def _stream_fits(ids: np.ndarray, at: np.ndarray, ts_of) -> np.ndarray:
    """Whether each record ``at`` (positions in ``ids``: the kept chain in file order;
    ``ts_of(positions)`` gives their raw timestamps) fits its own event stream: it has another
    record of its id to fit, is not before the previous one nor after the next one, and at most
    :data:`RESYNC_MAX_GAP_US` after the previous one (in the raw unit: a v1 timestamp in ms passes
    a wider window, which only makes it more lenient)."""
    ok = np.ones(len(at), dtype=bool)
    for eid in np.unique(ids[at]):
        sel = np.flatnonzero(ids[at] == eid)
        mine = np.flatnonzero(ids == eid)
        q = np.searchsorted(mine, at[sel])
        last = len(mine) - 1
        t, prev_t, next_t = (ts_of(mine[np.clip(q + d, 0, last)]) for d in (0, -1, 1))
        ok[sel] = (last > 0) & (t >= prev_t) & (t <= next_t) & ((q == 0) | (t - prev_t <= RESYNC_MAX_GAP_US))
    return ok


def _doubtful(region: np.ndarray, cand: np.ndarray, cand_ids: np.ndarray, size_lut: np.ndarray,
              nodes: np.ndarray, broken: np.ndarray, resume_at: np.ndarray, dropped: np.ndarray,
              ts_dtype: np.dtype) -> np.ndarray:
    """Which of the ``broken`` chain nodes (records whose end starts no record) cannot be kept as
    the record their id says: the chain resumes (``resume_at``: region offsets, the region's
    end for a last record) exactly where a record of another declared type starting there would
    end (the id was corrupted into a valid one: an estPose read from a fixedFrequency record's
    first floats), or the timestamp does not fit its own stream (:func:`_stream_fits`)."""
    if len(broken) == 0:
        return np.zeros(0, dtype=bool)
    gap = resume_at - cand[broken]
    own = size_lut[cand_ids[broken]]
    sizes = np.unique(size_lut[size_lut > 0])
    other = (gap != own) & np.isin(gap, sizes)
    live_mask = ~dropped[nodes]
    live_mask[np.searchsorted(nodes, broken)] = True  # the chain runs in file order: nodes ascend
    live = nodes[live_mask]
    fits = _stream_fits(cand_ids[live], np.searchsorted(live, broken),
                        lambda i: _timestamps_at(region, cand[live[i]], ts_dtype))
    return other | ~fits


def _tail_record(region: np.ndarray, cand: np.ndarray, cand_ids: np.ndarray, nxt: np.ndarray,
                 nodes: np.ndarray, dropped: np.ndarray, ts_dtype: np.dtype) -> int:
    """The candidate after the chain's last node whose record ends the region exactly and whose
    timestamp fits its stream (see :func:`_stream_fits`), or -1: the intact last record after
    a corruption too near the end for ``RESYNC_RECORDS`` records to follow it."""
    m = len(cand)
    if len(nodes) == 0:
        return -1
    ends = np.flatnonzero(nxt[:m] == m)
    ends = ends[cand[ends] > cand[nodes[-1]]]
    if len(ends) == 0:
        return -1
    live = nodes[~dropped[nodes]]
    for c in ends[::-1]:  # at most one per declared record size
        chain = np.r_[live, c]
        if _stream_fits(cand_ids[chain], np.array([len(chain) - 1]),
                        lambda i, chain=chain: _timestamps_at(region, cand[chain[i]], ts_dtype))[0]:
            return int(c)
    return -1


def _timestamps_at(region: np.ndarray, offsets: np.ndarray, ts_dtype: np.dtype) -> np.ndarray:
    """The raw timestamps of the records starting at ``offsets`` (region offsets)."""
    idx = offsets[:, None] + 2 + np.arange(ts_dtype.itemsize)
    return region[idx].copy().view(ts_dtype).reshape(-1).astype(np.int64)


def _skipped_stretches(walk: _Walk, region: np.ndarray, data_start: int, version: int) -> list[SkippedStretch]:
    ts_dtype = TIMESTAMP_DTYPE[version]
    nb = walk.skip_neighbours
    ts = _timestamps_at(region, np.maximum(nb, 0).reshape(-1), ts_dtype).reshape(-1, 2) * TIMESTAMP_TO_US[version]
    return [
        SkippedStretch(int(a) + data_start, int(b) + data_start,
                       int(t0) if i0 >= 0 else None, int(t1) if i1 >= 0 else None)
        for (a, b), (i0, i1), (t0, t1) in zip(walk.skips, nb, ts)
    ]


def _skip_warning(skipped: list[SkippedStretch], t0_us: int) -> str:
    total = sum(s.byte_end - s.byte_start for s in skipped)

    def at(t):
        return "start" if t is None else f"{(t - t0_us) * 1e-6:.3f} s"

    where = "; ".join(f"bytes {s.byte_start}..{s.byte_end} ({at(s.t_before_us)} to {at(s.t_after_us)})"
                      for s in skipped[:5])
    more = f"; and {len(skipped) - 5} more" if len(skipped) > 5 else ""
    return (f"resynchronised after {len(skipped)} corrupt stretch(es): skipped {total} bytes: {where}{more}")


def _safe_event_types(types_by_id: dict[int, EventType]) -> tuple[dict[int, EventType], list[str]]:
    """Event types renamed to safe, distinct names (they become folders), and what was renamed."""
    names, warnings = namesmod.unique_safe_names([et.name for et in types_by_id.values()])
    renamed = {eid: replace(et, name=name) for (eid, et), name in zip(types_by_id.items(), names)}
    return renamed, [f"event type: {w}" for w in warnings]


def _record_chain(buf: bytes | memoryview, version: int, types_by_id: dict[int, EventType], data_start: int,
                  warnings: list[str]) -> tuple[_Walk, int, bool | None]:
    """Walk the records from ``data_start`` to the CRC trailer (or to the end of a file without
    one, or whichever reading recovers more). Returns (the walk, where the data ends, CRC ok:
    True / False, None without a trailer); appends what it finds to ``warnings``."""
    n_total = len(buf)
    crc_ok: bool | None = None
    data_end = n_total - CRC_SIZE
    if data_end >= data_start:
        (crc_stored,) = struct.unpack_from("<I", buf, data_end)
        crc_ok = (zlib.crc32(buf[:data_end]) & 0xFFFFFFFF) == crc_stored

    ts_dtype = TIMESTAMP_DTYPE[version]
    size_lut = np.zeros(65536, dtype=np.int64)
    for eid, et in types_by_id.items():
        size_lut[eid] = 2 + ts_dtype.itemsize + et.payload_dtype().itemsize

    def walk(end: int) -> _Walk:
        region = np.frombuffer(buf, dtype=np.uint8, count=max(end - data_start, 0), offset=data_start)
        return _walk(region, size_lut, ts_dtype)

    if crc_ok is None:
        warnings.append("no CRC trailer: file is truncated; decoded what was there")
        w, end_used = walk(n_total), n_total
    else:
        w, end_used = walk(data_end), data_end
        # A trailer that validates the bytes before it is the file's end, whatever those bytes
        # end with (a short last record included): a random 4-byte tail matches with p = 2**-32.
        if not crc_ok and (w.reason != "end" or len(w.skips)):
            # Either the trailer is missing (a truncated file) or the data is damaged. A file
            # whose records end cleanly or mid-record at its very end, read without a trailer,
            # was truncated; otherwise keep whichever reading recovers more.
            w2 = walk(n_total)
            if (w2.reason in ("end", "partial") and not len(w2.skips)) or len(w2.starts) > len(w.starts):
                w, end_used, crc_ok = w2, n_total, None
                warnings.append("no valid CRC trailer: file looks truncated; decoded what was there")
        if crc_ok is False:
            warnings.append("CRC mismatch: the file is damaged; values may be wrong")
    return w, end_used, crc_ok


def _tables(region: np.ndarray, w: _Walk, types_by_id: dict[int, EventType],
            version: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Each event type's records as a structured array of its variables (a view, no copy of the
    values) and their timestamps in us."""
    tables: dict[str, np.ndarray] = {}
    timestamps: dict[str, np.ndarray] = {}
    for eid, et in types_by_id.items():
        rec_starts = w.starts[w.ids == eid]
        dtype = et.record_dtype(version)
        size = dtype.itemsize
        if len(rec_starts) and len(region) >= size:
            # every record start as a row of a strided byte matrix: one row gather, no index arrays
            rows = np.lib.stride_tricks.as_strided(region, shape=(len(region) - size + 1, size), strides=(1, 1))
            records = rows[rec_starts].reshape(-1).view(dtype)
        else:
            records = np.empty(0, dtype)
        # the variables only: a view of the same records that skips id and timestamp
        fields = dtype.fields
        assert fields is not None  # a record dtype always has fields
        tables[et.name] = records.view(np.dtype({
            "names": list(et.variables),
            "formats": [fields[v][0] for v in et.variables],
            "offsets": [fields[v][1] for v in et.variables],
            "itemsize": size,
        }))
        timestamps[et.name] = records["timestamp"].astype(np.int64) * TIMESTAMP_TO_US[version]
    return tables, timestamps


def _second_log_at(buf, data_start: int) -> int:
    """Where a second log begins (this log's header again, as when two files are joined), or
    the buffer's length. The header holds the magic byte, the version and every declared name:
    records do not repeat it by chance."""
    header = bytes(buf[:data_start])
    find = buf.find if hasattr(buf, "find") else bytes(buf).find
    at = find(header, data_start)
    return len(buf) if at < 0 else at


def decode_bytes(buf: bytes) -> DecodedLog:
    """Decode a whole uSD log held in memory. See the module docstring."""
    version, types_by_id, data_start = parse_header(buf)
    types_by_id, warnings = _safe_event_types(types_by_id)
    n_total = len(buf)
    own_end = _second_log_at(buf, data_start)
    if own_end < n_total:
        warnings.append(f"a second log starts at byte {own_end} (this log's header again: files joined): decoded "
                        f"the first only, dropped {n_total - own_end} bytes; split the file to decode the other")
    body = buf if own_end == n_total else memoryview(buf)[:own_end]
    w, end_used, crc_ok = _record_chain(body, version, types_by_id, data_start, warnings)

    region_len = end_used - data_start
    region = np.frombuffer(buf, dtype=np.uint8, count=region_len, offset=data_start)
    skipped = _skipped_stretches(w, region, data_start, version)
    bytes_skipped = int(sum(s.byte_end - s.byte_start for s in skipped))
    bytes_dropped = (region_len - w.stop if w.reason != "end" else 0) + bytes_skipped + n_total - own_end
    if w.reason == "partial":
        warnings.append(f"partial last record: dropped {region_len - w.stop} bytes at the end")
    elif w.reason == "garbage":
        warnings.append(
            f"record chain broken at byte {data_start + w.stop}: kept {len(w.starts)} records, "
            f"dropped {region_len - w.stop} bytes"
        )

    for eid in w.misfit:
        et = types_by_id[eid]
        warnings.append(f"event type {et.name!r}: its records do not fit the header's layout "
                        f"({et.record_dtype(version).itemsize} bytes a record): none kept")
    tables, timestamps = _tables(region, w, types_by_id, version)
    if skipped:
        firsts = [int(ts[0]) for ts in timestamps.values() if len(ts)]
        warnings.append(_skip_warning(skipped, min(firsts) if firsts else 0))
    return DecodedLog(
        version=version,
        event_types={et.name: et for et in types_by_id.values()},
        tables=tables,
        timestamps_us=timestamps,
        warnings=warnings,
        bytes_total=n_total,
        bytes_dropped=int(bytes_dropped),
        crc_ok=crc_ok,
        skipped=skipped,
    )


def read_log(path: str | Path) -> bytes:
    """A log file's bytes, at most :data:`MAX_LOG_BYTES` of them: a larger file (or one that grew
    past it while read) is a :class:`LogTooLargeError`, raised before it is read whole."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > MAX_LOG_BYTES:
            raise LogTooLargeError(f"file is {size / 2**20:.0f} MiB; logs above {MAX_LOG_BYTES // 2**20} MiB are "
                                   "refused (95 min of 500 Hz records): split it")
        data = fh.read(MAX_LOG_BYTES + 1)
    if len(data) > MAX_LOG_BYTES:
        raise LogTooLargeError(f"file grew past {MAX_LOG_BYTES // 2**20} MiB while it was read: refused")
    return data


def decode_file(path: str | Path) -> DecodedLog:
    """Decode a uSD log file (:func:`read_log`). Raises :class:`LogFormatError` when nothing is
    recoverable."""
    return decode_bytes(read_log(path))


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
