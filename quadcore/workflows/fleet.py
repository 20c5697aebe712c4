"""The decisions every workflow takes first, the same way for the command line and the assets:
which flights (decoded, usable by the physics), which model (file, effects override) and which
flights are held out (only those named: by default none, and the diagnosis cross-validates)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from quadcore.logs import flight as flightmod, logformat
from quadcore.physics import decoded_store, gate, vehicle as vehiclemod
from quadcore.spec.model import ModelSpec, load_model_file, spec_from
from quadcore.spec.sessions import SessionsFileError, read_sessions_file
from quadcore.store import store
from quadcore.store.names import MAIN_EVENT  # the decoded table the physics reads

if TYPE_CHECKING:
    import polars as pl

    from quadcore.physics.vehicle import Vehicle


class WorkflowError(ValueError):
    """A request a workflow cannot carry out (a user error): the CLI prints it in one line and
    exits 2, an asset fails with it."""


class HoldoutError(WorkflowError):
    """A named held-out flight that is not among the flights (mistyped, or quarantined because
    its log could not be read), or a holdout that leaves nothing to fit on."""


class NoFlightsError(WorkflowError):
    """No log, or no flight the physics can use."""


@dataclass(frozen=True)
class Fleet:
    """The flights a fleet-wide workflow works on: the main table of every usable flight, and
    the others with the reason each was skipped (quarantined, no main table, unusable)."""

    tables: Mapping[str, pl.DataFrame]  # a dict, or tables read as they are looked up (store.FlightTables)
    skipped: dict[str, str] = field(default_factory=dict)

    @property
    def ids(self) -> list[str]:
        return sorted(self.tables)

    def only(self, flights: Iterable[str]) -> Fleet:
        """The same fleet restricted to ``flights`` (the skipped ones kept, to report them)."""
        return Fleet(_subset(self.tables, flights), self.skipped)


def _subset(tables: Mapping[str, pl.DataFrame], flights: Iterable[str]) -> Mapping[str, pl.DataFrame]:
    return tables.subset(flights) if isinstance(tables, store.FlightTables) else {f: tables[f] for f in flights}


def parse_names(text: str | None) -> list[str]:
    """``"a, b,,c"`` -> ``["a", "b", "c"]``: a comma-separated list as given on the command line
    or in an environment variable."""
    return [n.strip() for n in (text or "").split(",") if n.strip()]


def quarantine_reason(exc: BaseException) -> str:
    """The one-line reason a file is quarantined for: the error's type and message (a decoder's
    own :class:`~quadcore.logs.logformat.LogFormatError` as it says; any other error marked as an
    unexpected one, so that it is reported as a defect, not as the file's fault alone)."""
    text = str(exc).splitlines()[0][:300] if str(exc) else ""
    if isinstance(exc, (logformat.LogFormatError, OSError)):
        return f"{type(exc).__name__}: {text}"
    return f"unexpected {type(exc).__name__} while decoding (a defect: please report it): {text}"


def decode_logs(paths: list[str], out: Path | None = None,
                log: Callable[[str], None] = lambda m: None) -> tuple[list[flightmod.Flight], dict[str, str]]:
    """Decode every log under ``paths``; with ``out``, write SI Parquet and quarantine records
    there. Returns (flights, quarantined: id -> reason); one unreadable log never stops the others."""
    try:
        logs = flightmod.discover_logs(*paths)
    except FileNotFoundError as exc:
        raise NoFlightsError(str(exc)) from None
    if not logs:
        raise NoFlightsError(f"no log files found in {', '.join(map(str, paths))}")
    ids, collisions = flightmod.flight_ids(logs)
    for note in collisions:
        log(f"flight id collision: {note}")
    flights, quarantined = [], {}
    for i, (fid, path) in enumerate(ids.items(), 1):
        try:  # any failure is this file's alone: it is quarantined with its reason, the others go on
            fl = flightmod.decode_flight(path, fid)
            if out is not None:
                decoded_store.write_decoded(out, fl)
        except Exception as exc:  # noqa: BLE001 (per-file isolation: the reason is recorded and reported)
            reason = quarantine_reason(exc)
            if out is not None:
                store.write_quarantine(out, fid, str(path), reason, type(exc).__name__)
            quarantined[fid] = reason
            log(f"[{i}/{len(logs)}] {fid}: QUARANTINED ({reason})")
            continue
        if out is not None:
            store.clear_quarantine(out, fid)
        flights.append(fl)
        warn = f"  warnings: {'; '.join(fl.warnings)}" if fl.warnings else ""
        log(f"[{i}/{len(logs)}] {fid}: {fl.provenance.rows}{warn}")
    digests = {f.flight_id: f.provenance.source_sha256 for f in flights}
    for fid, why in duplicates(digests, digests.get).items():
        log(f"{fid}: {why} (decoded; the fleet stages skip it)")
    return flights, quarantined


def duplicates(flights: Iterable[str], digest: Callable[[str], str | None]) -> dict[str, str]:
    """The flights that repeat another one's log bytes (same SHA-256, ``digest``; None or "":
    unknown, never a duplicate), each with the reason: of every group of copies the first id in
    sorted order is kept (whatever the listing order), so that a flight is fitted, trained on
    and scored once, and never trains a model scored on a copy of itself (a held-out jana02
    dropped in again as jana99)."""
    first: dict[str, str] = {}
    out = {}
    for fid in sorted(flights):
        sha = digest(fid)
        if not sha:
            continue
        if sha in first:
            out[fid] = f"duplicate of {first[sha]}: the same log bytes (SHA-256 {sha[:12]}...); a flight is used once"
        else:
            first[sha] = fid
    return out


def usable(tables: Mapping[str, pl.DataFrame], vehicle: Vehicle, skipped: dict[str, str] | None = None,
           warn: Callable[[str], None] = lambda m: None,
           digest: Callable[[str], str | None] | None = None) -> Fleet:
    """The flights the physics can use with ``vehicle``, each log once (:func:`duplicates` by
    ``digest``: flight -> the SHA-256 of its log); each other one is skipped with its reason,
    said through ``warn``. Tables decoded under a data root are judged from the physics facts and
    the digest their footers record (:func:`quadcore.physics.decoded_store.write_decoded`), without reading
    their rows; a table without facts (decoded by older code, or rewritten) is read."""
    facts = None
    if isinstance(tables, store.FlightTables):  # decoded under a data root: their footers say
        footers: dict[str, dict] = {}

        def footer(fid: str) -> dict:
            if fid not in footers:
                footers[fid] = store.read_metadata(tables.path(fid))
            return footers[fid]

        def facts(fid: str) -> gate.PhysicsFacts | None:
            return gate.PhysicsFacts.from_dict(footer(fid).get(store.PHYSICS_FACTS))

        digest = digest or (lambda fid: footer(fid).get("source_sha256"))

    copies = duplicates(tables, digest) if digest is not None else {}
    for fid, why in copies.items():
        warn(f"{fid} skipped: {why}")
    good, unusable = gate.usable_flights(_subset(tables, [f for f in tables if f not in copies]), vehicle, facts)
    skipped = {**(skipped or {}), **copies, **unusable}
    for fid, why in unusable.items():
        warn(f"{fid} skipped: {why}")
    return Fleet(_subset(tables, good), skipped)


def main_tables(flights: list[flightmod.Flight], vehicle: Vehicle, quarantined: dict[str, str] | None = None,
                warn: Callable[[str], None] = lambda m: None) -> Fleet:
    """The main table of every decoded flight the physics can use; the quarantined ones, those
    without a main table and the unusable ones are skipped, each with its reason said through
    ``warn``. Raises :class:`NoFlightsError` when none is left."""
    for fid, why in (quarantined or {}).items():
        warn(f"{fid} skipped: {why}")
    tables = {f.flight_id: f.tables[MAIN_EVENT] for f in flights if MAIN_EVENT in f.tables}
    no_main = {f.flight_id: f"no {MAIN_EVENT!r} records" for f in flights if MAIN_EVENT not in f.tables}
    for fid, why in no_main.items():
        warn(f"{fid} skipped: {why}")
    skipped = {**{f: f"quarantined: {w}" for f, w in (quarantined or {}).items()}, **no_main}
    digests = {f.flight_id: f.provenance.source_sha256 for f in flights}
    fleet = usable(tables, vehicle, skipped, warn, digests.get)
    if not fleet.tables:
        raise NoFlightsError(f"no flight the physics can use ({len(flights)} decoded; each needs usable "
                             f"{MAIN_EVENT!r} records)")
    return fleet


def fleet_from_logs(paths: list[str], vehicle: Vehicle, warn: Callable[[str], None] = lambda m: None) -> Fleet:
    """Decode the logs under ``paths`` (nothing written) and keep the flights the physics can use
    (:func:`main_tables`)."""
    flights, quarantined = decode_logs(paths)
    return main_tables(flights, vehicle, quarantined, warn)


def fleet_from_store(root, vehicle: Vehicle, warn: Callable[[str], None] = lambda m: None) -> Fleet:
    """Every decoded flight under the data root that the physics can use."""
    return usable(store.read_all_decoded(root, MAIN_EVENT), vehicle, warn=warn)


def named_holdout(requested: list[str], flights: Iterable[str], where: str = "the flights") -> list[str]:
    """The requested held-out flights, checked against ``flights``.

    Raises :class:`HoldoutError` if one is not among them (it is never silently dropped: the
    scores would then be on other flights than the user asked for) or if every flight is held
    out. An empty request is returned as is (the caller picks its default)."""
    flights = list(flights)
    unknown = [h for h in requested if h not in flights]
    if unknown:
        raise HoldoutError(f"holdout flight(s) not found in {where}: {', '.join(unknown)} "
                           f"(a misspelt id, or a log that could not be read); flights: {', '.join(sorted(flights))}")
    if requested and not set(flights) - set(requested):
        raise HoldoutError("every flight is held out: nothing left to fit on")
    return list(requested)


def held_out(requested: list[str], flights: list[str], where: str = "the decoded flights") -> list[str]:
    """The flights never fitted on: the named holdout (checked: :func:`named_holdout`), and
    nothing else. Nothing is held out unless asked for (``--holdout``, ``QUADCORE_HOLDOUT``): the
    physics model is fitted on every flight and the diagnosis cross-validates over all of them
    (:func:`quadcore.workflows.identify.diagnosis_flights`). The learned models, which need a flight
    they never saw to be scored, pick their own (:func:`quadcore.workflows.learn.learning_holdout`)."""
    return named_holdout(requested, flights, where)


def resolve_model(model_file: str | None, vehicle_name: str | None = None, thrust_map: str | None = None,
                  effects: list[str] | None = None, sessions_file: str | None = None) -> ModelSpec:
    """The physics model a run asks for: a model file (its vehicle, effects, fixed parameters
    and plugins), else just the vehicle (``vehicle_name``: built-in name or file, default the
    Crazyflie 2.1); non-empty ``effects`` replace the effect list (keeping the file as the
    source); ``thrust_map`` overrides the vehicle's; ``sessions_file`` (``--sessions``,
    ``QUADCORE_SESSIONS``) joins the spec, so that its digest, and hence the fit's freshness,
    follows the file's content.

    Raises :class:`quadcore.spec.model.ModelFileError`, :class:`quadcore.physics.vehicle.VehicleFileError`,
    :class:`quadcore.effects.UnknownEffectError` or, for a sessions file that is missing or
    malformed, :class:`WorkflowError`, with the reason."""
    if model_file:
        spec = load_model_file(model_file, vehicle_override=vehicle_name or None)
    else:
        spec = spec_from(vehiclemod.load(vehicle_name or None), [])
    if effects:
        spec = spec.with_effects(effects)
    if thrust_map:
        spec.vehicle = spec.vehicle.with_thrust_map(thrust_map)
    if sessions_file:
        try:  # read now, so a missing or malformed file stops a run before any work
            read_sessions_file(sessions_file, [])
        except SessionsFileError as exc:
            raise WorkflowError(str(exc)) from None
        spec.sessions_file = str(sessions_file)
    return spec


def sessions_of(spec: ModelSpec, flights: list[str]) -> dict[str, list[str]] | None:
    """The sessions file's groups among ``flights`` (session -> flights), or None without one
    (the workflows then use the model file's sessions, or the groups the data show).
    Raises :class:`quadcore.spec.sessions.SessionsFileError` (a :class:`WorkflowError`)."""

    if not spec.sessions_file:
        return None
    try:
        return read_sessions_file(spec.sessions_file, flights)
    except SessionsFileError as exc:
        raise WorkflowError(str(exc)) from None
