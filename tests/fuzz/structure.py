"""Structure-aware mutants of a good log, each with what the decoder must give back.

Unlike :mod:`.mutants` (random damage), every case here is built from the log's own layout
(header fields, record boundaries, field boundaries, timestamps), and carries its own
reference: the records that are intact in the mutated file and that the bytes allow to
recover (``must_keep``), and how many damaged records of each event id may come back with
changed bytes (``damaged``). The harness (:func:`evaluate`) then counts, per case:

- a *phantom*: a decoded record whose bytes (timestamp and values) are not those of a record
  of that event id in the log, beyond the damaged records the case allows (an estPose row built
  from a fixedFrequency record, the CRC trailer read as a battery voltage, a record of a
  concatenated second log);
- an *intact record lost*: a record of ``must_keep`` missing from the output.

Families: ``cut`` (the file cut at every field boundary of the last records and of one in the
middle, without and with a CRC trailer that validates the bytes before it), ``header`` (counts
and field lists edited: event-type and variable counts, each variable's type, variables
removed or added), ``hostile_name``, ``timestamp`` (one record's timestamp jumped, the tail
shifted), ``other_id`` (a record whose id is the other valid id), ``late`` (a corruption among
the last records), ``concat`` (two logs back to back).
"""

from __future__ import annotations

import struct
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from quadcore.logs import logformat

from .mutants import HOSTILE_NAMES, Layout, layout

CRC = logformat.CRC_SIZE
Keys = dict[int, np.ndarray]  # event id -> a 64-bit hash of each record's bytes after its id (a multiset)
_WEIGHTS = np.random.default_rng(12345).integers(1, 2**63, 4096, dtype=np.uint64) | np.uint64(1)


def _hash_rows(rows: np.ndarray) -> np.ndarray:
    """One 64-bit hash per row of a (n, width) uint8 matrix (a weighted sum, wrapping)."""
    with np.errstate(over="ignore"):
        return (rows.astype(np.uint64) * _WEIGHTS[:rows.shape[1]]).sum(axis=1, dtype=np.uint64) \
            ^ np.uint64(rows.shape[1])


def _excess(a: np.ndarray, b: np.ndarray) -> int:
    """How many elements of the multiset ``a`` are not matched in the multiset ``b``."""
    if len(a) == 0:
        return 0
    ua, ca = np.unique(a, return_counts=True)
    if len(b) == 0:
        return len(a)
    ub, cb = np.unique(b, return_counts=True)
    idx = np.minimum(np.searchsorted(ub, ua), len(ub) - 1)
    have = np.where(ub[idx] == ua, cb[idx], 0)
    return int(np.maximum(ca - have, 0).sum())


@dataclass(frozen=True)
class Case:
    family: str
    data: bytes
    must_keep: Keys  # event id -> records (timestamp + value bytes) that must come back
    allowed: Keys  # event id -> every record that may come back unchanged
    damaged: dict[int, int] = field(default_factory=dict)  # event id -> records that may come back changed
    check_lost: bool = True  # False: the header is wrong, the bytes do not allow recovery


@dataclass(frozen=True)
class Source:
    """A good log and its records: offsets, sizes, ids and bytes after the id."""

    data: bytes
    lay: Layout
    ids: np.ndarray
    version: int
    types: dict[int, logformat.EventType]

    @classmethod
    def of(cls, data: bytes) -> Source:
        lay = layout(data)
        version, types, _ = logformat.parse_header(data)
        ids = np.array([int.from_bytes(data[s:s + 2], "little") for s in lay.record_starts])
        return cls(data, lay, ids, version, types)

    @property
    def ts_size(self) -> int:
        return logformat.TIMESTAMP_DTYPE[self.version].itemsize

    @property
    def hashes(self) -> np.ndarray:
        """Each record's hash (see :func:`_hash_rows`), in file order."""
        cached = self.__dict__.get("_hashes")
        if cached is None:
            buf = np.frombuffer(self.data, np.uint8)
            cached = np.zeros(len(self.ids), np.uint64)
            for eid in np.unique(self.ids):
                mine = np.flatnonzero(self.ids == eid)
                size = int(self.lay.record_sizes[mine[0]])
                rows = buf[self.lay.record_starts[mine][:, None] + np.arange(2, size)]
                cached[mine] = _hash_rows(rows)
            object.__setattr__(self, "_hashes", cached)
        return cached

    def keys(self, which) -> Keys:
        which = np.fromiter(which, dtype=np.int64)
        return {int(eid): self.hashes[which[self.ids[which] == eid]] for eid in np.unique(self.ids[which])}

    @property
    def body_end(self) -> int:
        return len(self.data) - CRC

    def body(self) -> bytes:
        return self.data[:self.body_end]


def with_crc(data: bytes) -> bytes:
    return data + struct.pack("<I", zlib.crc32(data) & 0xFFFFFFFF)


def _all(src: Source) -> range:
    return range(len(src.ids))


# --- families ---------------------------------------------------------------------------------

def _field_offsets(et: logformat.EventType, ts_size: int) -> list[int]:
    """Every field boundary inside a record: after the id, the timestamp, each variable."""
    offs, pos = [2, 2 + ts_size], 2 + ts_size
    for t in et.type_chars:
        pos += np.dtype(logformat.TYPE_CHARS[t]).itemsize
        offs.append(pos)
    return [0, 1, *offs[:-1]]  # 0: exactly at the record start; 1: inside the id


def cuts(src: Source) -> Iterator[Case]:
    """The file cut at every field boundary of the last two records of each event type and of
    one mid-file record of each, without a trailer and with a CRC trailer over the bytes kept."""
    picks: list[int] = []
    for eid in src.types:
        mine = np.flatnonzero(src.ids == eid)
        picks += [int(i) for i in (*mine[-2:], mine[len(mine) // 2])] if len(mine) else []
    for i in sorted(set(picks)):
        start = int(src.lay.record_starts[i])
        for off in _field_offsets(src.types[int(src.ids[i])], src.ts_size):
            cut = src.data[:start + off]
            whole = range(i)  # every record before the one cut
            keep = src.keys(whole)
            yield Case("cut", cut, keep, keep)
            yield Case("cut+crc", with_crc(cut), keep, keep)


def _header_bytes(version: int, ets: list[logformat.EventType], n_types: int | None = None,
                  n_vars: dict[int, int] | None = None) -> bytes:
    out = bytearray(struct.pack("<BHH", logformat.MAGIC, version, len(ets) if n_types is None else n_types))
    for et in ets:
        out += struct.pack("<H", et.event_id) + et.name.encode("latin-1") + b"\x00"
        out += struct.pack("<H", len(et.variables) if not n_vars or et.event_id not in n_vars else n_vars[et.event_id])
        for var, t in zip(et.variables, et.type_chars):
            out += f"{var}({t})".encode("latin-1") + b"\x00"
    return bytes(out)


def _with_header(src: Source, header: bytes) -> bytes:
    return with_crc(header + src.body()[src.lay.data_start:])


def _layout_kept(src: Source, ets: list[logformat.EventType]) -> Keys:
    """The records that may come back under an edited header: those of the event ids whose
    record layout (sizes of the id, timestamp and each variable) is unchanged."""
    same = {et.event_id for et in ets if et.event_id in src.types
            and et.payload_dtype().itemsize == src.types[et.event_id].payload_dtype().itemsize}
    return src.keys(i for i in _all(src) if int(src.ids[i]) in same)


def headers(src: Source, rng: np.random.Generator) -> Iterator[Case]:
    """Header counts and field lists edited. The bytes after the header are unchanged, so every
    record that comes back must be byte-identical to one of the log (the harness does not ask
    for records back: the header is wrong)."""
    ets = list(src.types.values())
    for n in (0, 1, len(ets) - 1, len(ets) + 1, len(ets) + 7, 255, 256, 65535):
        if n < 0:
            continue
        kept = ets[:n] if n <= len(ets) else ets
        yield Case("header_count", _with_header(src, _header_bytes(src.version, ets, n_types=n)),
                   {}, _layout_kept(src, kept), check_lost=False)
    for et in ets:
        for n in (0, 1, len(et.variables) - 1, len(et.variables) + 1, 1024, 1025, 65535):
            yield Case("header_nvars", _with_header(src, _header_bytes(src.version, ets, n_vars={et.event_id: n})),
                       {}, _layout_kept(src, [e for e in ets if e is not et]), check_lost=False)
        for v, t in enumerate(et.type_chars):  # each variable's type, changed to every other
            for new in logformat.TYPE_CHARS:
                if new == t:
                    continue
                chars = (*et.type_chars[:v], new, *et.type_chars[v + 1:])
                edited = [logformat.EventType(e.event_id, e.name, e.variables, chars) if e is et else e for e in ets]
                yield Case("header_type", _with_header(src, _header_bytes(src.version, edited)),
                           {}, _layout_kept(src, edited), check_lost=False)
        for v in range(len(et.variables)):  # a variable removed
            edited = [logformat.EventType(e.event_id, e.name, e.variables[:v] + e.variables[v + 1:],
                                          e.type_chars[:v] + e.type_chars[v + 1:]) if e is et else e for e in ets]
            yield Case("header_drop_var", _with_header(src, _header_bytes(src.version, edited)),
                       {}, _layout_kept(src, edited), check_lost=False)
        t = "BHIf"[int(rng.integers(0, 4))]
        edited = [logformat.EventType(e.event_id, e.name, (*e.variables, "extra"), (*e.type_chars, t))
                  if e is et else e for e in ets]
        yield Case("header_add_var", _with_header(src, _header_bytes(src.version, edited)),
                   {}, _layout_kept(src, edited), check_lost=False)


def hostile_names(src: Source) -> Iterator[Case]:
    """Each hostile name as each event's name: every record must come back."""
    ets = list(src.types.values())
    everything = src.keys(_all(src))
    for k in range(len(ets)):
        for name in HOSTILE_NAMES:
            edited = [logformat.EventType(e.event_id, name, e.variables, e.type_chars) if j == k else e
                      for j, e in enumerate(ets)]
            yield Case("hostile_name", _with_header(src, _header_bytes(src.version, edited)), everything, everything)


def _set_ts(buf: bytearray, src: Source, i: int, value: int) -> None:
    s = int(src.lay.record_starts[i]) + 2
    fmt = "<Q" if src.ts_size == 8 else "<I"
    buf[s:s + src.ts_size] = struct.pack(fmt, value % (1 << (8 * src.ts_size)))


def _ts(src: Source, i: int) -> int:
    fmt = "<Q" if src.ts_size == 8 else "<I"
    return struct.unpack_from(fmt, src.data, int(src.lay.record_starts[i]) + 2)[0]


def timestamps(src: Source, rng: np.random.Generator, n: int) -> Iterator[Case]:
    """One record's timestamp jumped (forward, back to zero, to the top of its range); or the
    tail from one record on shifted by a gap (a valid log with a gap: all of it must come back)."""
    per_s = 1_000_000 // logformat.TIMESTAMP_TO_US[src.version]
    for _ in range(n):
        i = int(rng.integers(0, len(src.ids)))
        how = int(rng.integers(0, 4))
        data = bytearray(src.body())
        if how < 3:
            value = [_ts(src, i) + 3600 * per_s, 0, (1 << (8 * src.ts_size)) - 1][how]
            _set_ts(data, src, i, value)
            others = [j for j in _all(src) if j != i]
            yield Case("timestamp_jump", with_crc(bytes(data)), src.keys(others), src.keys(others),
                       damaged={int(src.ids[i]): 1})
        else:
            gap = int(rng.integers(1, 600)) * per_s
            for j in range(i, len(src.ids)):
                _set_ts(data, src, j, _ts(src, j) + gap)
            shifted = Source(bytes(data) + b"\0" * CRC, src.lay, src.ids, src.version, src.types)
            keys = shifted.keys(_all(src))
            yield Case("timestamp_gap", with_crc(bytes(data)), keys, keys)


def other_ids(src: Source, rng: np.random.Generator, n: int) -> Iterator[Case]:
    """A record whose id is replaced by another declared id: every other record must come back,
    and nothing of that record (it is neither what its new id says nor, with its id lost, known
    to be what it was)."""
    ids = sorted(src.types)
    last = list(range(max(0, len(src.ids) - 12), len(src.ids)))
    picks = last + [int(i) for i in rng.integers(0, len(src.ids), max(0, n - len(last)))]
    for i in picks[:n]:
        new = ids[(ids.index(int(src.ids[i])) + 1) % len(ids)]
        if new == int(src.ids[i]):
            continue
        data = bytearray(src.data)
        s = int(src.lay.record_starts[i])
        data[s:s + 2] = struct.pack("<H", new)
        others = src.keys(j for j in _all(src) if j != i)
        yield Case("other_id", with_crc(bytes(data[:src.body_end])), others, others)


def late(src: Source, rng: np.random.Generator, n: int) -> Iterator[Case]:
    """Bytes overwritten among the last records (a few bytes to a whole record): every record
    after the damaged ones must come back (however few follow), and every one before."""
    for _ in range(n):
        k = int(rng.integers(1, min(9, len(src.ids))))
        i = len(src.ids) - k - 1  # the damage starts in record i; k records follow it
        s, size = int(src.lay.record_starts[i]), int(src.lay.record_sizes[i])
        at = s + int(rng.integers(0, size))
        width = int(rng.integers(1, size + 1))
        end = at + width
        data = bytearray(src.body())
        data[at:end] = bytes(rng.integers(0, 256, width, dtype=np.uint8))
        starts, sizes = src.lay.record_starts, src.lay.record_sizes
        hit = [j for j in _all(src) if starts[j] < end and starts[j] + sizes[j] > at]
        intact = [j for j in _all(src) if j not in hit]
        damaged = Counter(int(src.ids[j]) for j in hit)
        trailer = int(rng.integers(0, 2))  # with the (now wrong) CRC, or without a trailer
        body = bytes(data) + (src.data[src.body_end:] if trailer else b"")
        yield Case("late", body, src.keys(intact), src.keys(intact), damaged=dict(damaged))


def concatenated(a: Source, b: Source) -> Iterator[Case]:
    """Two log files back to back (the second whole or cut; the first with or without its
    trailer): the first log's records must come back, and none of the second's (they belong to
    another flight)."""
    keep = a.keys(_all(a))
    for second in (b.data, b.data[:len(b.data) // 2], b.data[:b.lay.data_start + 3]):
        yield Case("concat", a.data + second, keep, keep)
        yield Case("concat_no_crc", a.body() + second, keep, keep)
    yield Case("concat_self", a.data + a.data, keep, keep)
    yield Case("concat_self_no_crc", a.body() + a.data, keep, keep)


def cases(src: Source, others: list[Source], rng: np.random.Generator, per_family: int) -> Iterator[Case]:
    yield from cuts(src)
    yield from headers(src, rng)
    yield from hostile_names(src)
    yield from timestamps(src, rng, per_family)
    yield from other_ids(src, rng, per_family)
    yield from late(src, rng, per_family)
    for o in others:
        yield from concatenated(src, o)


# --- what the decoder gave back ---------------------------------------------------------------

def decoded_keys(log: logformat.DecodedLog) -> Keys:
    """Every decoded record's bytes after its id (timestamp in the file's unit, then values)."""
    out: Keys = {}
    to_native = logformat.TIMESTAMP_TO_US[log.version]
    for name, et in log.event_types.items():
        table = log.tables[name]
        rec = np.zeros(len(table), et.record_dtype(log.version))
        rec["timestamp"] = log.timestamps_us[name] // to_native
        for v in et.variables:
            rec[v] = table[v]
        raw = rec.view(np.uint8).reshape(len(table), rec.dtype.itemsize)[:, 2:]
        out[et.event_id] = np.r_[out.get(et.event_id, np.zeros(0, np.uint64)), _hash_rows(raw)]
    return out


@dataclass(frozen=True)
class Verdict:
    phantoms: int
    lost: int


def judge(case: Case, log: logformat.DecodedLog) -> Verdict:
    got = decoded_keys(log)
    none = np.zeros(0, np.uint64)
    phantoms = 0
    for eid, hashes in got.items():
        phantoms += max(0, _excess(hashes, case.allowed.get(eid, none)) - case.damaged.get(eid, 0))
    lost = 0
    if case.check_lost:
        for eid, hashes in case.must_keep.items():
            lost += _excess(hashes, got.get(eid, none))
    return Verdict(phantoms, lost)


# --- the run --------------------------------------------------------------------------------------

MAX_SECONDS = 5.0  # a decode taking longer is counted as a hang (and interrupted)


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


@dataclass
class Tally:
    cases: int = 0
    by_family: Counter = field(default_factory=Counter)
    typed: int = 0
    tracebacks: list[str] = field(default_factory=list)
    hangs: int = 0
    phantoms: int = 0
    phantom_cases: Counter = field(default_factory=Counter)
    lost: int = 0
    lost_cases: Counter = field(default_factory=Counter)
    slowest_s: float = 0.0

    def ok(self) -> bool:
        return not self.tracebacks and self.hangs == 0 and self.phantoms == 0 and self.lost == 0

    def lines(self) -> list[str]:
        def per(counts: Counter) -> str:
            return f" ({', '.join(f'{k} {n}' for k, n in sorted(counts.items()))})" if counts else ""

        return [f"structure-aware cases: {self.cases}{per(self.by_family)}",
                f"refused with a typed LogFormatError: {self.typed}",
                f"tracebacks (untyped exceptions): {len(self.tracebacks)}",
                f"hangs (a decode over {MAX_SECONDS:g} s): {self.hangs}; slowest decode {self.slowest_s * 1e3:.0f} ms",
                f"phantom records: {self.phantoms}{per(self.phantom_cases)}",
                f"intact records lost where the bytes allow recovery: {self.lost}{per(self.lost_cases)}"]


def run_case(case: Case, tally: Tally, write_root=None) -> None:
    """Decode one case (interrupted after :data:`MAX_SECONDS`), build its flight, and judge it."""
    import signal
    import time
    import traceback
    from pathlib import Path

    from quadcore.logs import flight
    from quadcore.physics import decoded_store

    tally.cases += 1
    tally.by_family[case.family] += 1
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, MAX_SECONDS)
    t0 = time.perf_counter()
    try:
        try:
            log = logformat.decode_bytes(case.data)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
            tally.slowest_s = max(tally.slowest_s, time.perf_counter() - t0)
        fl = flight.from_decoded(f"s{tally.cases:05d}", log, f"structure:{case.family}")
        if write_root is not None:
            decoded_store.write_decoded(write_root, fl)
    except _Hang:
        tally.hangs += 1
        return
    except logformat.LogFormatError:
        tally.typed += 1
        return
    except Exception as exc:  # noqa: BLE001 (what the harness counts)
        where = traceback.extract_tb(exc.__traceback__)[-1]
        tally.tracebacks.append(f"{case.family}: {type(exc).__name__}: {str(exc)[:100]} "
                                f"({Path(where.filename).name}:{where.lineno})")
        return
    v = judge(case, log)
    tally.phantoms += v.phantoms
    tally.lost += v.lost
    if v.phantoms:
        tally.phantom_cases[case.family] += 1
    if v.lost:
        tally.lost_cases[case.family] += 1


def run(logs: list[bytes], per_family: int, seed: int = 0, write_root=None, limit: int | None = None,
        log=print) -> Tally:
    """Every family over every log (``per_family`` random cases for the drawn families), the
    other logs as the second of a concatenation; ``limit``: stop after that many cases per log
    (a sample, drawn evenly over the families)."""
    tally = Tally()
    sources = [Source.of(d) for d in logs]
    for j, src in enumerate(sources):
        rng = np.random.default_rng(seed + j)
        every = list(cases(src, [o for o in sources if o is not src][:2] or [src], rng, per_family))
        if limit is not None and len(every) > limit:
            every = [every[int(i)] for i in np.linspace(0, len(every) - 1, limit).round()]
        for case in every:
            run_case(case, tally, write_root if case.family == "hostile_name" else None)
        log(f"  {tally.cases} structure-aware cases")
    return tally
