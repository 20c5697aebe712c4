"""The flights' Gram sums term discovery selects from (:class:`LibrarySums`), made flight by
flight: from each flight's rows and its residual under the model (:func:`from_rows`), or from the
flights' stored statistics (:func:`from_statistics`, :mod:`quadcore.identify.discovery.library_stats`)
with a model's linear effects subtracted from the sums."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import polars as pl

from quadcore import effects as effectlib
from quadcore.effects.base import Effect
from quadcore.identify import flightdata
from quadcore.identify.discovery import library_stats
from quadcore.identify.discovery.grams import Columns, GramSums, flight_gram, flight_grams, library_columns
from quadcore.identify.discovery.terms import Term, Variable, library_of, variables
from quadcore.identify.fit import sessions as sessionlib
from quadcore.identify.fit.model_fit import fit_model
from quadcore.identify.stats import sufficient
from quadcore.physics.vehicle import Vehicle
from quadcore.spec.model import ModelSpec


@dataclass(frozen=True)
class LibrarySums:
    """The candidate library (its terms and their Gram columns) and the flights' Gram matrices
    accumulated flight by flight, with each flight's usable samples and sensor noise."""

    terms: list[Term]
    cols: Columns
    sums: GramSums
    samples: dict[str, int]
    noise_of: dict[str, np.ndarray]
    full: GramSums | None = None  # from statistics: the same sums on every usable sample
    y0_squares: dict[str, np.ndarray] | None = None  # from statistics, a model without effects: Σ y0² per flight
    after: GramSums | None = None  # from statistics: ``full``'s sums after each flight's first blocks
    samples_after: dict[str, int] | None = None  # from statistics: the usable samples there per flight
    y0_squares_after: dict[str, np.ndarray] | None = None  # as ``y0_squares``, there


# ``flight(f, quiet=False) -> (its rows, its residual under the model)``; quiet: without the model's progress
RowsOf = Callable[..., tuple[flightdata.FlightData, np.ndarray]]


def from_rows(ids: list[str], flight: RowsOf, decoded: Mapping[str, pl.DataFrame], spec: ModelSpec,
              fx_effects: list[Effect], folds: list[list[str]], holdout: list[str], stride: int, log) -> LibrarySums:
    """Each flight's rows (``flight(f)``: its rows and residual, :func:`residual_rows`) turned into its
    Gram matrix and dropped; the library is built from the first flight's variables."""
    vehicle = spec.vehicle
    # motor terms only when every flight has them (read off the columns, before any Gram matrix)
    motors = all(_logs_motors(decoded[f], spec.vehicle_for(f)) for f in ids)
    sums = GramSums(folds, holdout)
    samples: dict[str, int] = {}
    noise_of: dict[str, np.ndarray] = {}
    for f in ids:
        fd, r = flight(f)
        if f == ids[0]:
            terms = library_of(variables(fd.state, vehicle), motors)
            cols = library_columns(terms, fx_effects)
            log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; "
                f"accumulating on {len(ids)} flights")
        sums.add(f, flight_gram(fd, r, cols, fx_effects, vehicle, stride))
        samples[f], noise_of[f] = int(fd.mask.sum()), fd.noise
    return LibrarySums(terms, cols, sums, samples, noise_of)


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
    terms = _library_terms(first, motors)
    cols = library_columns(terms, fx_effects)
    labels = cols.labels()
    missing = [f for f in ids if found[f] is None]
    log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; combining "
        f"{len(ids) - len(missing)} flights' stored statistics" + (f", computing {len(missing)}" if missing else ""))
    sums, full, after = (GramSums(folds, holdout), GramSums(folds, holdout, scored_only=True),
                         GramSums(folds, holdout, scored_only=True))
    samples: dict[str, int] = {}
    noise_of: dict[str, np.ndarray] = {}
    y0_squares: dict[str, np.ndarray] = {}
    samples_after: dict[str, int] = {}
    y0_after: dict[str, np.ndarray] = {}
    for f in ids:
        G, H, H_after, lib = _flight_statistics(f, found[f] if f != ids[0] else first, labels, spec, decoded, cols,
                                               fx_effects)
        sums.add(f, G)
        full.add(f, H)
        after.add(f, H_after)
        samples[f], noise_of[f], y0_squares[f] = lib.samples, lib.noise, lib.y0_squares
        samples_after[f], y0_after[f] = lib.samples_after, lib.y0_squares_after
    if spec.effects:
        model = fit_model(spec, decoded, train, sessions, log, stats)
        T = _residual_transform(cols, model, spec.vehicle)
        for g in (sums, full, after):
            g.transformed(T)
    bare = not spec.effects  # a model without effects: the residual is y0, its squares summed as the rows sum them
    return LibrarySums(terms, cols, sums, samples, noise_of, full, y0_squares if bare else None, after,
                       samples_after, y0_after if bare else None)


def _flight_statistics(f: str, lib, labels: tuple[str, ...], spec: ModelSpec, decoded, cols: Columns,
                       fx_effects) -> tuple[np.ndarray, np.ndarray, np.ndarray, library_stats.FlightLibrary]:
    """(G, H, H_after, the statistics) of one flight in the columns ``labels``: the stored ones (``lib``),
    else computed from its rows; from its rows with ``cols`` when they lack a column (an effect
    loaded since)."""
    if lib is not None and set(labels) <= set(lib.labels):
        try:
            return *(_picked(M, lib.labels, labels) for M in lib.grams()), lib
        except sufficient.StatsError:  # cut short since its header was read
            lib = None
    if lib is None:
        lib = library_stats.compute(spec, f, decoded[f])
        if set(labels) <= set(lib.labels):
            return *(_picked(M, lib.labels, labels) for M in lib.grams()), lib
    fd = flightdata.flight_data(f, decoded[f], spec.vehicle_for(f))
    G, H, H_after = flight_grams(fd, flightdata.targets_of([fd])[0], cols, fx_effects, spec.vehicle,
                                library_stats.STRIDE, lib.head_blocks)
    return G, H, H_after, lib


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
    predict = model_fit(spec, decoded, ids, train, sessions, log)

    def flight(f: str, quiet: bool = False) -> tuple[flightdata.FlightData, np.ndarray]:
        fd = flightdata.flight_data(f, decoded[f], spec.vehicle_for(f))  # a session's map
        target = flightdata.targets_of([fd])[0]
        return fd, target if predict is None else target - predict(fd, (lambda msg: None) if quiet else log)

    return flight


def model_fit(spec: ModelSpec, decoded: Mapping[str, pl.DataFrame], ids: list[str], train: list[str],
              sessions: dict[str, list[str]] | None, log) -> Callable | None:
    """``predict(flight data, log) -> (n, 6)``: the model's effects fitted on the training flights
    from their statistics (:func:`quadcore.identify.fit.model_fit.fit_model`; per session for per-session
    effects) and predicted on a flight's rows, or None for a model without effects."""
    if not spec.effects:
        return None
    if spec.per_session:  # some effects fitted per session: each flight's residual under its session's values
        pm = fit_model(spec, decoded, train, sessions, log)
        return lambda fd, say: sessionlib.model_prediction(pm, fd, say)
    log(f"fitting the model's effects {spec.effects} on {len(train)} flights")
    pm = fit_model(spec, decoded, train, sessions, log)
    effects, params = [t.effect for t in pm.terms], {t.name: t.params for t in pm.terms}
    return lambda fd, say: fd.predict(effects, params, spec.vehicle)
