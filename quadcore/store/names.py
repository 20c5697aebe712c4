"""Names that become path components under the data root (event types, flight ids, run names), and
the unit a column's name carries (:func:`column_units`, recorded in every Parquet file's metadata).

Such a name comes from a log's header or from a file name, so it is untrusted: it could hold a
separator, ``..``, a ``=`` (which breaks hive-partitioned paths such as ``flight=<id>``), or be
too long for the file system once a temp-file prefix is added. Two functions:

- :func:`safe_component` maps any text to a safe component (a name that is already safe is kept
  as it is; any other gets its unsafe characters replaced and a short hash of the original
  appended, so two different names never map to the same component);
- :func:`check_component` is the guard at the point where a path is built: it raises
  :class:`UnsafeNameError` for anything but a safe component.
"""

from __future__ import annotations

import hashlib
import re

MAIN_EVENT = "fixedFrequency"  # the event whose decoded table the physics reads
MAX_COMPONENT_CHARS = 100  # leaves room for ".<name>.<random>.tmp" within the usual 255-byte limit
SAFE_COMPONENT = re.compile(rf"[A-Za-z0-9_+-][A-Za-z0-9_.+-]{{0,{MAX_COMPONENT_CHARS - 1}}}")
_HASH_CHARS = 8


class UnsafeNameError(ValueError):
    """A name that cannot be a single path component under the data root."""


def is_safe(name: str) -> bool:
    """Letters, digits, ``_ . + -``; not starting with a dot; at most ``MAX_COMPONENT_CHARS``."""
    return isinstance(name, str) and SAFE_COMPONENT.fullmatch(name) is not None


def safe_component(name: str) -> str:
    """``name`` itself when safe, else a safe, deterministic stand-in ``<cleaned>-<hash>``."""
    if is_safe(name):
        return name
    digest = hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:_HASH_CHARS]
    cleaned = re.sub(r"[^A-Za-z0-9_.+-]+", "_", name).lstrip(".")
    return f"{cleaned[:MAX_COMPONENT_CHARS - _HASH_CHARS - 1]}-{digest}"


def check_component(name: str, what: str) -> str:
    """``name`` if it is a safe path component, else :class:`UnsafeNameError` naming ``what``."""
    if not is_safe(name):
        raise UnsafeNameError(
            f"{what} {name!r:.120} is not a safe path component (letters, digits, '_.+-', not starting "
            f"with '.', at most {MAX_COMPONENT_CHARS} characters)"
        )
    return name


def unique_safe_names(names: list[str]) -> tuple[list[str], list[str]]:
    """Safe, pairwise distinct components for ``names`` (in order), and a warning per change.

    A repeated name keeps its first occurrence and gets ``_dup2``, ``_dup3``, ... on the later ones:
    both tables survive, and the warning says which is which.
    """
    out, warnings, taken = [], [], set()
    for name in names:
        safe = safe_component(name)
        if safe != name:
            warnings.append(f"name {name!r:.120} is not a safe path component: stored as {safe!r}")
        candidate, k = safe, 2
        while candidate in taken:
            candidate, k = f"{safe[:MAX_COMPONENT_CHARS - 10]}_dup{k}", k + 1
        if candidate != safe:
            warnings.append(f"name {name!r:.120} is declared more than once: this one is stored as {candidate!r}")
        taken.add(candidate)
        out.append(candidate)
    return out, warnings


# The unit of a column, from the last part of its name (the project's naming convention:
# ``f_res_b_x_N``, ``v_w_x_mps``, ``timestamp_us``); a name without one is dimensionless ("1").
SUFFIX_UNITS = {"N": "N", "Nm": "N m", "mps": "m/s", "mps2": "m/s^2", "radps": "rad/s", "radps2": "rad/s^2",
                "m": "m", "V": "V", "s": "s", "us": "us", "deg": "deg", "rad": "rad", "kg": "kg", "Hz": "Hz"}


def column_units(columns) -> dict[str, str]:
    """Unit of each column name, read off its suffix (see ``SUFFIX_UNITS``)."""
    return {c: SUFFIX_UNITS.get(c.rsplit("_", 1)[-1], "1") for c in columns}
