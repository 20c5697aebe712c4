"""A sessions file: which flights form a session of flights (TOML, ``[sessions] NAME = ["jana00",
"jana1*", ...]``, shell patterns allowed; ``--sessions``, ``QUADCORE_SESSIONS``). What the sessions
change in a fit is :mod:`quadcore.identify.fit.sessions`.
"""

from __future__ import annotations

import fnmatch
from pathlib import Path

from quadcore.physics import vehicle as vehiclemod


class SessionsFileError(ValueError):
    """A sessions file that is missing, unreadable or malformed."""


def read_sessions_file(path: str | Path, flights: list[str]) -> dict[str, list[str]]:
    """Sessions -> flights (among ``flights``) from a TOML sessions file. A flight matched by
    two sessions is an error; flights matched by none are left out."""
    d = vehiclemod.read_toml(Path(path), SessionsFileError, "sessions file")
    table = d.get("sessions")
    if not isinstance(table, dict) or not table:
        raise SessionsFileError(f"{path}: needs a [sessions] table: NAME = [\"flight\", \"pattern*\", ...]")
    out: dict[str, list[str]] = {}
    owner: dict[str, str] = {}
    for name, patterns in table.items():
        if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
            raise SessionsFileError(f"{path}: session {name!r} must be a list of flight names or patterns")
        members = sorted({f for f in flights for p in patterns if fnmatch.fnmatchcase(f, p)})
        for f in members:
            if f in owner:
                raise SessionsFileError(f"{path}: flight {f!r} is in sessions {owner[f]!r} and {name!r}")
            owner[f] = name
        out[name] = members
    return out
