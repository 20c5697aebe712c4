"""A decoded flight in the data root: each event table with its columns' units and descriptions and the
flight's provenance, and in the main table's footer the physics gate's facts of its rows.

The writer sits above ``logs`` (it knows a :class:`~quadcore.logs.flight.Flight`, its
:class:`~quadcore.logs.flight.Provenance` and the gate's :class:`~quadcore.physics.gate.PhysicsFacts`);
the store below it knows paths and Parquet with metadata only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from quadcore.logs.flight import Flight, Provenance
from quadcore.physics import gate
from quadcore.store import store
from quadcore.store.names import MAIN_EVENT


def write_decoded(root: Path, flight: Flight) -> dict[str, Path]:
    """Write every event table of ``flight``; returns event -> path. The main table's footer also
    holds the physics gate's facts (the fleet stages decide usability from these, without the rows)."""
    paths = {}
    for event, df in flight.tables.items():
        meta = {"flight": flight.flight_id, "event": event, "columns": flight.columns[event],
                **flight.provenance.to_dict()}
        facts = gate.physics_facts(df).to_dict() if event == MAIN_EVENT else None
        paths[event] = store.write_parquet(df, store.decoded_path(root, event, flight.flight_id), meta, facts)
    return paths


def recorded_physics_facts(path: Any) -> dict | None:
    """The physics facts (:class:`quadcore.physics.gate.PhysicsFacts` as a dict) recorded in a
    decoded main table's footer by :func:`write_decoded`, or None (decoded by older code)."""
    return store.read_metadata(path).get(store.PHYSICS_FACTS)


def recorded_provenance(root: Path, event: str, flight: str) -> Provenance | None:
    """The :class:`quadcore.logs.flight.Provenance` written with a flight's decoded ``event`` table, or
    None if not decoded yet."""
    path = store.decoded_path(root, event, flight)
    return Provenance.from_dict(store.read_metadata(path)) if path.is_file() else None


def decoded_from(root: Path, event: str, flight: str, log_path: Path) -> bool:
    """Whether the flight's decoded ``event`` table was decoded from exactly these bytes (the
    SHA-256 in its provenance) by the decoder as it is now (:meth:`quadcore.logs.flight.Provenance.current`);
    False when it is missing, was decoded by other code, or the log cannot be read."""
    recorded = recorded_provenance(root, event, flight)
    try:
        return recorded is not None and recorded.current(store.file_sha256(log_path))
    except (OSError, ValueError):
        return False
