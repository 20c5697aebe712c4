"""A decoded flight: every event type as an SI table, with provenance.

The flight id is the log file's name. Time ``t_s`` starts at the first timestamp of
any event type in the file, so all tables of a flight share one clock.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from datetime import UTC
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from quadcore import logformat, names, units


@dataclass
class Flight:
    """One flight. ``tables[event]`` is SI; ``columns[event]`` documents each column."""

    flight_id: str
    tables: dict[str, pl.DataFrame]
    columns: dict[str, dict[str, dict[str, str]]]
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def warnings(self) -> list[str]:
        return list(self.provenance.get("decode_warnings", []))


def flight_id_of(path: str | Path) -> str:
    """The flight id of a log: its file name, or a safe stand-in for a name that cannot be a
    path component (see :func:`quadcore.names.safe_component`)."""
    return names.safe_component(Path(path).name)


def find_log(folder: str | Path, flight_id: str) -> Path:
    """The log in ``folder`` whose flight id is ``flight_id`` (``FileNotFoundError`` if none)."""
    if names.is_safe(flight_id) and (Path(folder) / flight_id).is_file():
        return Path(folder) / flight_id
    for path in discover_logs(folder) if Path(folder).is_dir() else []:
        if flight_id_of(path) == flight_id:
            return path
    raise FileNotFoundError(f"no log with flight id {flight_id!r:.120} in {folder}")


def from_decoded(flight_id: str, log: logformat.DecodedLog, provenance: dict) -> Flight:
    starts = [ts[0] for ts in log.timestamps_us.values() if len(ts)]
    ends = [ts[-1] for ts in log.timestamps_us.values() if len(ts)]
    t0_us = int(min(starts)) if starts else 0
    duration_ns = (int(max(ends)) - t0_us) * 1000 if ends else 0
    tables, columns = {}, {}
    for event, values in log.tables.items():
        tables[event], columns[event] = units.to_si(values, log.timestamps_us[event], t0_us)
    provenance = {
        **provenance,
        "format_version": log.version,
        "crc_ok": log.crc_ok,
        "bytes_total": log.bytes_total,
        "bytes_dropped": log.bytes_dropped,
        "decode_warnings": list(log.warnings),
        "rows": log.rows(),
    }
    if "source_mtime_ns" in provenance:
        provenance.update(start_ns=provenance.pop("source_mtime_ns") - duration_ns, start_source=START_FROM_MTIME)
    return Flight(flight_id, tables, columns, provenance)


def decode_flight(path: str | Path) -> Flight:
    """Decode a raw uSD log file into SI tables. Raises ``LogFormatError`` if unrecoverable."""
    path = Path(path)
    buf = path.read_bytes()
    log = logformat.decode_bytes(buf)
    provenance = {
        "source_file": str(path.resolve()),
        "source_sha256": hashlib.sha256(buf).hexdigest(),
        "source_mtime_ns": path.stat().st_mtime_ns,
    }
    return from_decoded(flight_id_of(path), log, provenance)


START_FROM_MTIME = "log file modification time at first decode, taken as the end of the flight"


def settle_start_time(fl: Flight, recorded: dict | None, override_ns: int | None = None) -> None:
    """Fix the flight's absolute start time (``provenance["start_ns"]``, ns since the Unix epoch;
    the logs count from power-on). In order: the user's ``override_ns`` (a flights file, a CLI
    option); else the time ``recorded`` at the first decode of the same log (same SHA-256), so
    that a copy of the log, with a new modification time, never moves it; else this decode's
    estimate from the file's modification time."""
    if override_ns is not None:
        fl.provenance.update(start_ns=int(override_ns), start_source="given by the user")
    elif recorded and recorded.get("source_sha256") == fl.provenance.get("source_sha256") and "start_ns" in recorded:
        fl.provenance.update(start_ns=int(recorded["start_ns"]),
                             start_source=recorded.get("start_source", START_FROM_MTIME))


def read_flight_starts(path: str | Path | None) -> dict[str, int]:
    """Start times given by the user: the ``start_utc`` column (ISO 8601) of a flights file
    (``flights.csv``: columns ``flight``, ..., ``start_utc``); {} when absent. A bad time is a
    ``ValueError`` naming the flight."""
    import csv

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
    from datetime import datetime

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
