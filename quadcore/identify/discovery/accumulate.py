"""The flights' Gram sums term discovery selects from and scores with (:class:`LibrarySums`), combined
flight by flight from their discovery statistics (:mod:`quadcore.identify.discovery.library_stats`, one
accumulation: :func:`_combined`): computed from each flight's rows and its residual under the model
(:func:`from_rows`: a nonlinear or per-session model, predicted on the rows), or the flights' nominal
statistics, stored or computed from their rows (:func:`from_statistics`), with a model's linear effects
subtracted from the sums."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore.effects.base import Effect
from quadcore.identify import flightdata
from quadcore.identify.discovery import library_stats
from quadcore.identify.discovery.grams import Columns, GramSums, library_columns
from quadcore.identify.discovery.terms import Term, Variable, library_of, variables
from quadcore.identify.fit import sessions as sessionlib
from quadcore.identify.fit.model_fit import fit_model
from quadcore.identify.stats import sufficient
from quadcore.physics.vehicle import Vehicle
from quadcore.spec.model import ModelSpec


@dataclass(frozen=True)
class LibrarySums:
    """The candidate library (its terms and their Gram columns) and the flights' Gram matrices
    accumulated flight by flight, with each flight's usable samples and sensor noise; the same
    matrices on every usable sample (``full``) and after each flight's first blocks (``after``), the
    matrices the held-out RMSE is a quadratic form of."""

    terms: list[Term]
    cols: Columns
    sums: GramSums
    samples: dict[str, int]
    noise_of: dict[str, np.ndarray]
    full: GramSums  # the same sums on every usable sample (each fold's own flights' and the held-out ones')
    y_squares: dict[str, np.ndarray] | None  # Σ r² per flight as the rows give it; None: a model's linear fit
    after: GramSums  # ``full``'s sums after each flight's first blocks
    samples_after: dict[str, int]  # the usable samples there per flight
    y_squares_after: dict[str, np.ndarray] | None  # as ``y_squares``, there


# ``flight(f, quiet=False) -> (its rows, its residual under the model)``; quiet: without the model's progress
RowsOf = Callable[..., tuple[flightdata.FlightData, np.ndarray]]


def from_rows(ids: list[str], flight: RowsOf, decoded: Mapping[str, pl.DataFrame], spec: ModelSpec,
              fx_effects: list[Effect], folds: list[list[str]], holdout: list[str], stride: int, blocks: int,
              log) -> LibrarySums:
    """Each flight's rows and its residual under the model (``flight(f)``: :func:`residual_rows`) turned
    into its discovery statistics (:func:`quadcore.identify.discovery.library_stats.compute`, the residual
    in the ``y`` columns, every ``stride``-th sample, the "after" sums after the first ``blocks`` blocks)
    and dropped, then combined as stored ones are (:func:`_combined`); the library is built from the
    first flight's variables."""
    # motor terms only when every flight has them (read off the columns, before any Gram matrix)
    motors = all(_logs_motors(decoded[f], spec.vehicle_for(f)) for f in ids)
    fd, r = flight(ids[0])
    terms = library_of(variables(fd.state, spec.vehicle), motors)
    cols = library_columns(terms, fx_effects)
    log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; "
        f"accumulating on {len(ids)} flights")

    def statistics(f: str, rows: tuple[flightdata.FlightData, np.ndarray] | None = None) -> library_stats.FlightLibrary:
        fd, r = rows or flight(f)
        return library_stats.compute(spec, f, decoded[f], fd=fd, residual=r, terms=terms, stride=stride,
                                     blocks=blocks)

    first = statistics(ids[0], (fd, r))
    del fd, r
    return _combined(ids, lambda f: first if f == ids[0] else statistics(f), cols, folds, holdout)


def _combined(ids: list[str], statistics_of: Callable[[str], library_stats.FlightLibrary], cols: Columns,
              folds: list[list[str]], holdout: list[str]) -> LibrarySums:
    """The flights' statistics (``statistics_of(f)``, over at least the columns ``cols``), one flight at a
    time, added to the sums discovery selects and scores from."""
    labels = cols.labels()
    sums, full, after = (GramSums(folds, holdout), GramSums(folds, holdout, scored_only=True),
                         GramSums(folds, holdout, scored_only=True))
    samples: dict[str, int] = {}
    noise_of: dict[str, np.ndarray] = {}
    squares: dict[str, np.ndarray] = {}
    samples_after: dict[str, int] = {}
    squares_after: dict[str, np.ndarray] = {}
    for f in ids:
        lib = statistics_of(f)
        G, H, H_after = (_picked(M, lib.labels, labels) for M in lib.grams())
        sums.add(f, G)
        full.add(f, H)
        after.add(f, H_after)
        samples[f], noise_of[f], squares[f] = lib.samples, lib.noise, lib.y0_squares
        samples_after[f], squares_after[f] = lib.samples_after, lib.y0_squares_after
    return LibrarySums(cols.terms, cols, sums, samples, noise_of, full, squares, after, samples_after, squares_after)


def _library_terms(first: library_stats.FlightLibrary, motors: bool) -> list[Term]:
    """The candidate library from a flight's recorded variables (as :func:`from_rows` builds it
    from its rows)."""
    return library_of({name: Variable(np.empty(0), unit, sources, channel)
                       for name, unit, sources, channel in first.variables}, motors)


def _residual_transform(cols: Columns, model, vehicle: Vehicle) -> np.ndarray:
    """``T`` with ``z T`` the design whose residual columns are ``y0 - Σ θ B`` (the fitted
    model's linear effects ``model`` subtracted; see :mod:`quadcore.identify.discovery.library_stats`)."""
    T = np.eye(cols.n_total)
    for term in model.terms:
        e = effectlib.get(term.name)
        theta = np.asarray(e.to_linear({**e.defaults(), **term.params}, vehicle), dtype=float)
        for axis in range(6):
            T[cols.effect_cols[(e.name, axis)], cols.target0 + axis] -= theta
    return T


def from_statistics(ids: list[str], decoded: Mapping[str, pl.DataFrame], spec: ModelSpec, fx_effects: list[Effect],
                    folds: list[list[str]], holdout: list[str], train: list[str], stored, stats, sessions,
                    log) -> LibrarySums:
    """:func:`from_rows` from the flights' discovery statistics (:mod:`quadcore.identify.discovery.library_stats`):
    the stored ones, else computed from the flight's rows; a model's linear effects fitted from
    the sufficient statistics (``stats``) and subtracted from the sums (:func:`_residual_transform`)."""
    found = {f: stored(f) for f in ids}
    motors = all(found[f].logs_motors if found[f] is not None else _logs_motors(decoded[f], spec.vehicle_for(f))
                 for f in ids)
    first = found[ids[0]] or library_stats.compute(spec, ids[0], decoded[ids[0]])
    found[ids[0]] = first
    terms = _library_terms(first, motors)
    cols = library_columns(terms, fx_effects)
    missing = [f for f in ids if found[f] is None]
    log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; combining "
        f"{len(ids) - len(missing)} flights' stored statistics" + (f", computing {len(missing)}" if missing else ""))
    lib = _combined(ids, lambda f: _flight_statistics(f, found[f], cols, spec, decoded), cols, folds, holdout)
    if not spec.effects:  # a model without effects: the residual is y0, its squares summed as the rows sum them
        return lib
    model = fit_model(spec, decoded, train, sessions, log, stats)
    T = _residual_transform(cols, model, spec.vehicle)
    for g in (lib.sums, lib.full, lib.after):
        g.transformed(T)
    return dataclasses.replace(lib, y_squares=None, y_squares_after=None)


def _flight_statistics(f: str, lib: library_stats.FlightLibrary | None, cols: Columns, spec: ModelSpec,
                       decoded) -> library_stats.FlightLibrary:
    """One flight's statistics over at least the columns ``cols``: the stored ones (``lib``) with their
    matrices read now, else computed from its rows (over ``cols`` when the flight's own library lacks a
    column: an effect loaded since)."""
    labels = cols.labels()
    if lib is not None and set(labels) <= set(lib.labels):
        try:
            grams = lib.grams()
            return dataclasses.replace(lib, grams_source=lambda: grams)
        except sufficient.StatsError:  # cut short since its header was read
            lib = None
    if lib is None:
        lib = library_stats.compute(spec, f, decoded[f])
        if set(labels) <= set(lib.labels):
            return lib
    return library_stats.compute(spec, f, decoded[f], terms=cols.terms)


def _picked(M: np.ndarray, have: tuple[str, ...], want: tuple[str, ...]) -> np.ndarray:
    """The rows and columns ``want`` of a matrix over the columns ``have`` (by name)."""
    if have == want:
        return M
    at = {name: i for i, name in enumerate(have)}
    idx = np.array([at[name] for name in want])
    return M[np.ix_(idx, idx)]


def _logs_motors(df: pl.DataFrame, vehicle: Vehicle) -> bool:
    """Whether a decoded table has every rotor's speed (``FlightState.motor_radps`` is set)."""
    return all(f"motor_{i}_radps" in df.columns for i in range(1, vehicle.n_rotors + 1))


def residual_rows(spec: ModelSpec, decoded: Mapping[str, pl.DataFrame], ids: list[str], train: list[str],
                  sessions: dict[str, list[str]] | None, log) -> RowsOf:
    """``flight(f, quiet=False)``: one flight's rows and its residual (force N, torque N m, body frame)
    under the model's effects, fitted here on the training flights (:func:`model_fit`)."""
    predict = model_fit(spec, decoded, train, sessions, log)

    def flight(f: str, quiet: bool = False) -> tuple[flightdata.FlightData, np.ndarray]:
        fd = flightdata.flight_data(f, decoded[f], spec.vehicle_for(f))  # a session's map
        target = flightdata.targets_of([fd])[0]
        return fd, target if predict is None else target - predict(fd, (lambda msg: None) if quiet else log)

    return flight


def model_fit(spec: ModelSpec, decoded: Mapping[str, pl.DataFrame], train: list[str],
              sessions: dict[str, list[str]] | None, log) -> Callable | None:
    """``predict(flight data, log) -> (n, 6)``: the model's effects fitted on the training flights
    from their statistics (:func:`quadcore.identify.fit.model_fit.fit_model`; per session for per-session
    effects) and predicted on a flight's rows, or None for a model without effects."""
    if not spec.effects:
        return None
    if not spec.per_session:
        log(f"fitting the model's effects {spec.effects} on {len(train)} flights")
    pm = fit_model(spec, decoded, train, sessions, log)
    if spec.per_session:  # some effects fitted per session: each flight's residual under its session's values
        return lambda fd, say: sessionlib.model_prediction(pm, fd, say)
    effects, params = [t.effect for t in pm.terms], {t.name: t.params for t in pm.terms}
    return lambda fd, say: fd.predict(effects, params, spec.vehicle)
