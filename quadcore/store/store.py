"""Where things live under the data root, and atomic Parquet with metadata.

Layout (hive-style, so ``polars.scan_parquet`` and DuckDB read all flights at once)::

    <root>/raw/<flight>                                raw uSD logs (the input)
    <root>/decoded/<event>/flight=<flight>/data.parquet
    <root>/residuals/flight=<flight>/data.parquet
    <root>/quarantine/<flight>.json                    why a file was refused

The flight id lives in the path, not in the file, so that hive partitioning adds it
as a column without a clash (pass ``hive_schema={"flight": pl.String}`` to polars so that
an all-digit flight id stays a string). Every name that becomes a path component (event,
flight, stage) is checked by :func:`quadcore.store.names.check_component`: nothing built from a log's
content or a file's name can leave the data root. Each file's Parquet key-value metadata holds,
under the key ``quadcore``, a JSON document with column units and provenance.

The root may be an object-store URL (``s3://bucket/prefix``): :func:`as_root` makes it a
``UPath`` (fsspec), and every function here reads and writes through it. Credentials and the
endpoint come from the usual environment (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``,
``AWS_ENDPOINT_URL`` for an S3-compatible server). There, a write is one PUT of the finished
file (an object appears whole or not at all), in place of the local temp file + rename.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import polars as pl

from quadcore.store.names import (
    MAIN_EVENT as MAIN_EVENT,  # re-exported: store.MAIN_EVENT
    check_component,
    column_units,
)
from quadcore.store.safewrite import temp_prefix

METADATA_KEY = b"quadcore"
PHYSICS_FACTS = "physics_facts"  # the key of the physics gate's facts in a decoded main table's metadata


def as_root(root: Any) -> Any:
    """A data root as a path: a local ``Path``, or a ``UPath`` for a URL such as ``s3://bucket/prefix``."""
    if is_remote(root):
        return root
    text = str(root)
    if "://" in text:
        from upath import UPath

        return UPath(text)
    return Path(text)


def is_remote(path: Any) -> bool:
    """Whether ``path`` lives in an object store (a ``UPath`` with a protocol), not on this disk."""
    return bool(getattr(path, "protocol", "")) and not isinstance(path, Path)


def _file_mode() -> int:
    """The mode ``open()`` gives a new file here: 0666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


FILE_MODE = _file_mode()


def decoded_path(root: Path, event: str, flight: str) -> Path:
    event, flight = check_component(event, "event name"), check_component(flight, "flight id")
    return as_root(root) / "decoded" / event / f"flight={flight}" / "data.parquet"


def table_path(root: Path, stage: str, flight: str) -> Path:
    stage, flight = check_component(stage, "stage"), check_component(flight, "flight id")
    return as_root(root) / stage / f"flight={flight}" / "data.parquet"


def physics_model_path(root: Path) -> Path:
    """The fitted physics model (``physics_model`` asset, read by the per-flight stages and learning)."""
    return as_root(root) / "models" / "physics_model.json"


DIAGNOSIS_FILE, DISCOVERY_FILE, LEARNING_FILE = "diagnosis.json", "discovery.json", "learning.json"


def reports_dir(root: Path) -> Path:
    """The reports (``model_diagnosis``, ``term_discovery``, ``learning_report``)."""
    return as_root(root) / "reports"


def diagnosis_path(root: Path) -> Path:
    return reports_dir(root) / DIAGNOSIS_FILE


def discovery_path(root: Path) -> Path:
    return reports_dir(root) / DISCOVERY_FILE


def learning_report_path(root: Path) -> Path:
    return reports_dir(root) / LEARNING_FILE


def features_dir(root: Path) -> Path:
    """The feature tables (``features/<set>/flight=<id>/data.parquet``)."""
    return as_root(root) / "features"


def mcap_dir(root: Path) -> Path:
    return as_root(root) / "mcap"


def mcap_path(root: Path, flight: str) -> Path:
    """A flight as MCAP for Foxglove."""
    return mcap_dir(root) / f"{check_component(flight, 'flight id')}.mcap"


def checks_dir(root: Path) -> Path:
    """Every flight's latest plausibility-check outcomes (``decoded_flight``'s checks, kept per flight)."""
    return as_root(root) / "checks"


def check_outcomes_path(root: Path, flight: str) -> Path:
    return checks_dir(root) / f"{check_component(flight, 'flight id')}.json"


def own_model_file(root: Path) -> Path:
    """The data root's own model file (the demo writes one; it is the default model file there)."""
    return as_root(root) / "model.toml"


def learned_dir(root: Path) -> Path:
    """The learned models (``learned/<run>/``) and their ``index.json``."""
    return as_root(root) / "learned"


def export_c_dir(root: Path) -> Path:
    return as_root(root) / "export_c"


def quarantine_path(root: Path, flight: str) -> Path:
    return as_root(root) / "quarantine" / f"{check_component(flight, 'flight id')}.json"


def atomic_write(path: Any, write) -> Path:
    """Run ``write(tmp)`` on a temp file beside ``path`` and rename it into place; in an object
    store, on a local temp file then uploaded in one PUT."""
    path = as_root(path)
    if is_remote(path):
        with tempfile.TemporaryDirectory(prefix="quadcore-upload-") as local:
            tmp = os.path.join(local, path.name)
            write(tmp)
            remote: Any = path
            remote.fs.put_file(tmp, remote.path)
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(path.name), suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, FILE_MODE)  # mkstemp makes it 0600: every output gets the same mode as a plain file
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_parquet(df: pl.DataFrame, path: Path, metadata: dict, physics_facts: dict | None = None) -> Path:
    """Write ``df`` to ``path`` atomically (temp file + rename) with JSON file metadata, which
    always holds ``units`` (column -> unit): the given ones, else those of a ``columns``
    description, else read off the column names (:func:`quadcore.store.names.column_units`).
    Physics facts in ``metadata`` are dropped: they were found in other rows (metadata copied
    from another file); ``physics_facts`` (those of these very rows, which only
    :func:`quadcore.physics.decoded_store.write_decoded` knows) are recorded under :data:`PHYSICS_FACTS`."""
    metadata = {k: v for k, v in metadata.items() if k != PHYSICS_FACTS}
    if physics_facts is not None:
        metadata[PHYSICS_FACTS] = physics_facts
    metadata = {"units": _units(df, metadata), **metadata}
    meta = {METADATA_KEY.decode(): json.dumps(metadata, default=str)}
    return atomic_write(path, lambda tmp: df.write_parquet(tmp, compression="zstd", metadata=meta))


def _units(df: pl.DataFrame, metadata: dict) -> dict[str, str]:
    if "units" in metadata:
        return metadata["units"]
    described = metadata.get("columns") or {}
    by_name = column_units(df.columns)
    return {c: described[c]["unit"] if isinstance(described.get(c), dict) and "unit" in described[c] else by_name[c]
            for c in df.columns}


def read_metadata(path: Path) -> dict:
    """The ``quadcore`` document from a file's key-value metadata (also readable with DuckDB's
    ``parquet_kv_metadata`` or pyarrow's ``ParquetFile(path).metadata.metadata``)."""
    if is_remote(path):
        with path.open("rb") as fh:
            return json.loads(pl.read_parquet_metadata(fh).get(METADATA_KEY.decode(), "{}"))
    return json.loads(pl.read_parquet_metadata(path).get(METADATA_KEY.decode(), "{}"))


def read_parquet(path: Path) -> pl.DataFrame:
    """One Parquet file, local or in an object store."""
    if is_remote(path):
        with path.open("rb") as fh:
            return pl.read_parquet(fh)
    return pl.read_parquet(path)


def upload_folder(local: Path, remote: Any, last: str) -> Any:
    """Put every file of the local folder ``local`` under the object-store folder ``remote``,
    the file named ``last`` (the one readers check, such as a manifest) after all others."""
    files = sorted((p for p in Path(local).rglob("*") if p.is_file()), key=lambda p: (p.name == last, str(p)))
    for p in files:
        remote.fs.put_file(str(p), (remote / p.relative_to(local).as_posix()).path)
    return remote


def download_folder(remote: Any, local: Path) -> Path:
    """Copy the object-store folder ``remote`` into the local folder ``local``."""
    for p in remote.rglob("*"):
        if p.is_file():
            dest = Path(local) / p.relative_to(remote).as_posix()
            dest.parent.mkdir(parents=True, exist_ok=True)
            p.fs.get_file(p.path, str(dest))
    return Path(local)


def remove_tree(path: Any) -> None:
    """Remove a folder and everything in it, here or in an object store."""
    path = as_root(path)
    if is_remote(path):
        if path.exists():
            path.fs.rm(path.path, recursive=True)
    else:
        shutil.rmtree(path, ignore_errors=True)


def write_text(text: str, path: Path) -> Path:
    """Write ``text`` to ``path`` atomically (temp file + rename)."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def write_bytes(data: bytes, path: Path) -> Path:
    """Write ``data`` to ``path`` atomically (temp file + rename)."""
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def write_json(obj: dict, path: Path) -> Path:
    return atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(obj, indent=2, default=str)))


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_decoded(root: Path, event: str, flight: str) -> pl.DataFrame:
    return read_parquet(decoded_path(root, event, flight))


def read_table(root: Path, stage: str, flight: str) -> pl.DataFrame:
    return read_parquet(table_path(root, stage, flight))


def decoded_flights(root: Path, event: str) -> list[str]:
    """Flight ids that have a decoded table of ``event`` under ``root``, sorted."""
    folder = as_root(root) / "decoded" / event
    return sorted(p.parent.name.split("=", 1)[1] for p in folder.glob("flight=*/data.parquet"))


# What a :class:`FlightTables` keeps of the tables it has read (estimated in-memory size): the
# whole fleet for a lab's tens of flights (each read once, as when everything was held), a
# bounded part of it at thousands (a flight read again costs milliseconds).
TABLE_CACHE_BYTES = 256 << 20


class FlightTables(Mapping[str, pl.DataFrame]):
    """Per-flight Parquet tables by flight id, each read when it is looked up: a fleet stage
    walks the flights one at a time and never needs every flight's rows in memory at once.

    The most recently read tables are kept up to ``cache_bytes`` (their estimated size), so
    that a stage that looks at a flight twice (fit, then score) reads it once on a small fleet.
    Iteration order is the order of ``paths``. A plain ``dict`` of tables works wherever this
    does; this only loads later."""

    def __init__(self, paths: Mapping[str, Any], cache_bytes: int = TABLE_CACHE_BYTES):
        self._paths = dict(paths)
        self._cache: OrderedDict[str, pl.DataFrame] = OrderedDict()
        self._cache_bytes = cache_bytes
        self._held = 0  # estimated bytes in the cache

    def __getitem__(self, flight: str) -> pl.DataFrame:
        if flight in self._cache:
            self._cache.move_to_end(flight)
            return self._cache[flight]
        df = read_parquet(self._paths[flight])
        self._cache[flight] = df
        self._held += _nbytes(df)
        while len(self._cache) > 1 and self._held > self._cache_bytes:
            self._held -= _nbytes(self._cache.popitem(last=False)[1])
        return df

    def __iter__(self) -> Iterator[str]:
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)

    def __contains__(self, flight: object) -> bool:
        return flight in self._paths  # Mapping's own would read the table

    def path(self, flight: str) -> Any:
        return self._paths[flight]

    def subset(self, flights: Iterable[str]) -> FlightTables:
        """The named flights only, with the tables already read of them."""
        out = FlightTables({f: self._paths[f] for f in flights}, self._cache_bytes)
        for f, df in self._cache.items():
            if f in out._paths:
                out._cache[f] = df
                out._held += _nbytes(df)
        return out


def _nbytes(df: pl.DataFrame) -> int:
    """Polars' estimate of the frame's size in bytes (typed ``int | float`` for other units)."""
    return int(df.estimated_size())


def flight_tables(folder: Any, cache_bytes: int = TABLE_CACHE_BYTES) -> FlightTables:
    """Every ``<folder>/flight=<id>/data.parquet`` as :class:`FlightTables`, by flight id, sorted."""
    files = sorted(as_root(folder).glob("flight=*/data.parquet"))
    return FlightTables({check_component(p.parent.name.split("=", 1)[1], "flight id"): p for p in files}, cache_bytes)


def read_all_decoded(root: Path, event: str, flights: list[str] | None = None) -> FlightTables:
    """Decoded tables of ``event`` by flight (all of them, or the ones named), read as each is
    looked up (:class:`FlightTables`)."""
    ids = decoded_flights(root, event) if flights is None else flights
    return FlightTables({f: decoded_path(root, event, f) for f in ids})


def write_quarantine(root: Path, flight: str, source: str, reason: str, error_type: str) -> Path:
    record = {"flight": flight, "source_file": source, "reason": reason, "error_type": error_type}
    return write_json(record, quarantine_path(root, flight))


def quarantined(root: Path) -> list[dict]:
    """Every quarantine record under ``root``, by flight id."""
    return [json.loads(p.read_text()) for p in sorted((as_root(root) / "quarantine").glob("*.json"))]


def clear_quarantine(root: Path, flight: str) -> None:
    quarantine_path(root, flight).unlink(missing_ok=True)


def read_json(path: Path) -> dict:
    return json.loads(as_root(path).read_text())
