"""A decoded flight: every event type as an SI table, with provenance.

The flight id is the log file's name. Time ``t_s`` starts at the first timestamp of
any event type in the file, so all tables of a flight share one clock.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from quadcore import logformat, names, units


@dataclass
class Flight:
    """One flight. ``tables[event]`` is SI; ``columns[event]`` documents each column."""

    flight_id: str
    tables: dict[str, pl.DataFrame]
    columns: dict[str, dict[str, dict[str, str]]]
    provenance: dict[str, object] = field(default_factory=dict)

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
    t0_us = int(min(starts)) if starts else 0
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
    return Flight(flight_id, tables, columns, provenance)


def decode_flight(path: str | Path) -> Flight:
    """Decode a raw uSD log file into SI tables. Raises ``LogFormatError`` if unrecoverable."""
    path = Path(path)
    buf = path.read_bytes()
    log = logformat.decode_bytes(buf)
    provenance = {
        "source_file": str(path.resolve()),
        "source_sha256": hashlib.sha256(buf).hexdigest(),
    }
    return from_decoded(flight_id_of(path), log, provenance)


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
