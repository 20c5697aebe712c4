"""A decoded flight: every event type as an SI table, with provenance.

The flight id is the log file's name. Time ``t_s`` starts at the first timestamp of
any event type in the file, so all tables of a flight share one clock.
"""

from __future__ import annotations

import csv
import functools
import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from quadcore.logs import logformat, units
from quadcore.store import codedigest, names

# The code a decoded table's rows, columns and provenance come from: the uSD format's reader, the
# conversion to SI units and the assembly into a :class:`Flight` (the flight id's naming,
# ``quadcore.store.names``, names the table and makes none of its numbers). A decoded table records
# their digest (:func:`decoder_digest`, ``Provenance.decoder``): one decoded by other code is decoded
# again, and what was computed from it (statistics, rate-level sums) is stale
# (:meth:`Provenance.decoded_as`).
DECODER_MODULES = ("quadcore.logs.logformat", "quadcore.logs.units", "quadcore.logs.flight")


@functools.lru_cache(maxsize=1)
def decoder_digest() -> str:
    """The digest of :data:`DECODER_MODULES`' source (once per process)."""
    return codedigest.modules_digest(DECODER_MODULES)


@dataclass(frozen=True)
class Provenance:
    """Where a decoded flight came from and what decoding found. Written as JSON beside each of
    its decoded tables (:meth:`to_dict`); ``start_ns`` is the flight's absolute start (ns since
    the Unix epoch), None where it is not known; ``decoder`` the digest of the code that decoded
    it (:func:`decoder_digest`; "" when decoded before it was recorded)."""

    source_file: str = ""
    source_sha256: str = ""
    format_version: int = 0
    crc_ok: bool | None = None
    bytes_total: int = 0
    bytes_dropped: int = 0
    decode_warnings: tuple[str, ...] = ()
    rows: dict[str, int] = field(default_factory=dict)  # event -> records
    start_ns: int | None = None
    start_source: str = ""
    decoder: str = ""

    @property
    def decoded_as(self) -> str:
        """What the decoded table is a function of: the log's bytes (``source_sha256``) and the
        decoder's code (``decoder``). The one identity everything computed from the table and kept
        is keyed by (:func:`quadcore.identify.stats.sufficient.decoded_source`): a log decoded again
        from other bytes, or by another decoder, makes it stale."""
        return f"{self.source_sha256}+decoder:{self.decoder}"

    def current(self, source_sha256: str) -> bool:
        """Whether this decode is the one the current code makes of a log whose SHA-256 is
        ``source_sha256``: the same bytes, decoded by this decoder (:func:`decoder_digest`)."""
        return self.source_sha256 == source_sha256 and self.decoder == decoder_digest()

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (the keys the decoded Parquet files have always carried)."""
        d: dict[str, Any] = {
            "source_file": self.source_file, "source_sha256": self.source_sha256,
            "format_version": self.format_version, "crc_ok": self.crc_ok, "bytes_total": self.bytes_total,
            "bytes_dropped": self.bytes_dropped, "decode_warnings": list(self.decode_warnings), "rows": dict(self.rows),
            "decoder": self.decoder,
        }
        if self.start_ns is not None:
            d.update(start_ns=self.start_ns, start_source=self.start_source)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Provenance:
        """From the JSON form (e.g. :func:`quadcore.physics.decoded_store.recorded_provenance`); unknown keys
        ignored."""
        start = d.get("start_ns")
        return cls(str(d.get("source_file", "")), str(d.get("source_sha256", "")), int(d.get("format_version", 0)),
                   d.get("crc_ok"), int(d.get("bytes_total", 0)), int(d.get("bytes_dropped", 0)),
                   tuple(d.get("decode_warnings", ())), dict(d.get("rows", {})),
                   None if start is None else int(start), str(d.get("start_source", "")), str(d.get("decoder", "")))


@dataclass
class Flight:
    """One flight. ``tables[event]`` is SI; ``columns[event]`` documents each column."""

    flight_id: str
    tables: dict[str, pl.DataFrame]
    columns: dict[str, dict[str, dict[str, str]]]
    provenance: Provenance = field(default_factory=Provenance)

    @property
    def warnings(self) -> list[str]:
        return list(self.provenance.decode_warnings)


def flight_id_of(path: str | Path) -> str:
    """The flight id of a log: its file name, or a safe stand-in for a name that cannot be a
    path component (see :func:`quadcore.store.names.safe_component`)."""
    return names.safe_component(Path(path).name)


def flight_ids(paths: Iterable[str | Path]) -> tuple[dict[str, Path], list[str]]:
    """(flight id -> log, one line per collision resolved) for the logs ``paths``: unique ids,
    the same whatever order the paths are listed in.

    A file keeps :func:`flight_id_of` its name where no other file claims that id. Where two do
    (a file named exactly another file's safe stand-in, ``a b`` and ``a_b-c8687a08``; or two
    folders holding the same name), the files are taken in a fixed order: names that are their
    own id first, then by name and folder; the first keeps the id, each later one gets the id
    plus ``+`` and a digest of its name (of its folder and name if the name is the same), and
    the collision is reported."""
    order = sorted({Path(p) for p in paths}, key=lambda p: (not names.is_safe(p.name), p.name, str(p.parent)))
    out: dict[str, Path] = {}
    notes: list[str] = []
    for p in order:
        fid = flight_id_of(p)
        if fid in out:
            first, attempt = out[fid], 0
            while fid in out:
                key = p.name if attempt == 0 and first.name != p.name else f"{attempt}\0{p.parent}\0{p.name}"
                digest = hashlib.sha256(key.encode("utf-8", "surrogateescape")).hexdigest()[:12]
                fid, attempt = f"{flight_id_of(p)[:names.MAX_COMPONENT_CHARS - 13]}+{digest}", attempt + 1
            notes.append(f"{str(p)!r:.200} would have the flight id of {str(first)!r:.200} "
                         f"({flight_id_of(p)!r}): it is flight {fid!r}")
        out[fid] = p
    return dict(sorted(out.items())), notes


def find_log(folder: str | Path, flight_id: str) -> Path:
    """The log in ``folder`` whose flight id is ``flight_id`` (:func:`flight_ids`;
    ``FileNotFoundError`` if none)."""
    if names.is_safe(flight_id) and (Path(folder) / flight_id).is_file():
        return Path(folder) / flight_id  # a file named as its id always has it
    found = flight_ids(discover_logs(folder))[0].get(flight_id) if Path(folder).is_dir() else None
    if found is None:
        raise FileNotFoundError(f"no log with flight id {flight_id!r:.120} in {folder}")
    return found


def from_decoded(flight_id: str, log: logformat.DecodedLog, source_file: str = "", source_sha256: str = "",
                 source_mtime_ns: int | None = None) -> Flight:
    """The flight of a decoded log; its start time is estimated from ``source_mtime_ns`` (the
    log's modification time, taken as the end of the flight) where given."""
    starts = [ts[0] for ts in log.timestamps_us.values() if len(ts)]
    ends = [ts[-1] for ts in log.timestamps_us.values() if len(ts)]
    t0_us = int(min(starts)) if starts else 0
    duration_ns = (int(max(ends)) - t0_us) * 1000 if ends else 0
    tables, columns = {}, {}
    for event, values in log.tables.items():
        tables[event], columns[event] = units.to_si(values, log.timestamps_us[event], t0_us)
    estimated = source_mtime_ns is not None
    provenance = Provenance(
        source_file, source_sha256, log.version, log.crc_ok, log.bytes_total, log.bytes_dropped,
        tuple(log.warnings), log.rows(),
        start_ns=source_mtime_ns - duration_ns if source_mtime_ns is not None else None,
        start_source=START_FROM_MTIME if estimated else "", decoder=decoder_digest(),
    )
    return Flight(flight_id, tables, columns, provenance)


class OutsideFolderError(logformat.LogFormatError):
    """A log that is a symlink to a file outside its own folder (the raw folder): not followed."""


def check_inside_folder(path: str | Path) -> None:
    """Symlinks among the logs are followed only within the log's own folder (the raw folder):
    a link whose target resolves anywhere else raises :class:`OutsideFolderError` (the log is
    then quarantined with that reason), so a raw folder never reads files outside it."""
    path = Path(path)
    if path.is_symlink():
        target, folder = path.resolve(), path.parent.resolve()
        if not target.is_relative_to(folder):
            raise OutsideFolderError(f"{path.name} is a symlink to {target}, outside its folder {folder}: not "
                                     "followed; copy the log into the folder, or point QUADCORE_RAW_DIR at its own")


def decode_flight(path: str | Path, flight_id: str | None = None) -> Flight:
    """Decode a raw uSD log file (at most ``logformat.MAX_LOG_BYTES``) into SI tables, as flight
    ``flight_id`` (default: :func:`flight_id_of` the path). Any event types: whether the physics
    can use them is :func:`quadcore.logs.required.check`'s to say. Raises ``LogFormatError`` if
    unrecoverable (:class:`OutsideFolderError` for a symlink leaving its folder)."""
    path = Path(path)
    check_inside_folder(path)
    buf = logformat.read_log(path)
    log = logformat.decode_bytes(buf)
    return from_decoded(flight_id or flight_id_of(path), log, str(path.resolve()), hashlib.sha256(buf).hexdigest(),
                        path.stat().st_mtime_ns)


START_FROM_MTIME = "log file modification time at first decode, taken as the end of the flight"


def settle_start_time(fl: Flight, recorded: Provenance | None, override_ns: int | None = None) -> None:
    """Fix the flight's absolute start time (``provenance.start_ns``, ns since the Unix epoch;
    the logs count from power-on). In order: the user's ``override_ns`` (a flights file, a CLI
    option); else the time ``recorded`` at the first decode of the same log (same SHA-256), so
    that a copy of the log, with a new modification time, never moves it; else this decode's
    estimate from the file's modification time."""
    if override_ns is not None:
        fl.provenance = replace(fl.provenance, start_ns=int(override_ns), start_source="given by the user")
    elif (recorded and recorded.source_sha256 == fl.provenance.source_sha256 and recorded.start_ns is not None):
        fl.provenance = replace(fl.provenance, start_ns=recorded.start_ns,
                                start_source=recorded.start_source or START_FROM_MTIME)


def read_flight_starts(path: str | Path | None) -> dict[str, int]:
    """Start times given by the user: the ``start_utc`` column (ISO 8601) of a flights file
    (``flights.csv``: columns ``flight``, ..., ``start_utc``); {} when absent. A bad time is a
    ``ValueError`` naming the flight."""
    if not path or not Path(path).is_file():
        return {}
    out = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            text, fid = (row.get("start_utc") or "").strip(), (row.get("flight") or "").strip()
            if text and fid:
                try:
                    out[fid] = parse_start(text)
                except ValueError as exc:
                    raise ValueError(f"{path}: flight {fid}: {exc}") from None
    return out


def parse_start(text: str) -> int:
    """An ISO 8601 time (``2024-05-01T12:00:00Z``; no zone means UTC) as ns since the Unix epoch."""
    try:
        when = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"not an ISO 8601 time: {text!r} (e.g. 2024-05-01T12:00:00Z)") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return int(when.timestamp()) * 1_000_000_000 + when.microsecond * 1000


def sample_statistics(t_s: np.ndarray, gap_threshold_s: float = 0.02) -> dict[str, float]:
    """Duration, median rate and the gaps of a time column (seconds)."""
    if len(t_s) < 2:
        return {"duration_s": 0.0, "rate_hz_median": 0.0, "dt_max_s": 0.0, "gaps": 0}
    dt = np.diff(t_s)
    return {
        "duration_s": float(t_s[-1] - t_s[0]),
        "rate_hz_median": float(1.0 / np.median(dt)) if np.median(dt) > 0 else 0.0,
        "dt_max_s": float(dt.max()),
        "gaps": int(np.count_nonzero(dt > gap_threshold_s)),
    }


# The simulator's ground truth beside each log it writes (``<log>.truth.json``): marks a simulated flight.
TRUTH_SUFFIX = ".truth.json"
# Files beside the logs that are not logs (the simulator's ground-truth sidecars, notes).
SIDECAR_SUFFIXES = {".json", ".csv", ".txt", ".md", ".toml", ".yaml", ".yml"}


def discover_logs(*paths: str | Path) -> list[Path]:
    """Log files named by ``paths`` (files, or folders searched one level deep), sorted.

    Hidden files and sidecars (``SIDECAR_SUFFIXES``) are skipped; anything else is a
    candidate log and will be decoded or quarantined.
    """
    found: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found += [
                f for f in p.iterdir()
                if f.is_file() and not f.name.startswith(".") and f.suffix.lower() not in SIDECAR_SUFFIXES
            ]
        elif p.is_file():
            found.append(p)
        else:
            raise FileNotFoundError(f"no such file or folder: {p}")
    return sorted(set(found))
