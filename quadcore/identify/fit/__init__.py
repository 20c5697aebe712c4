"""The fits, from the flights' statistics (:mod:`quadcore.identify.stats.sufficient`), laid out by
concept and importing only downward: what every fit shares (:mod:`.solve`: the result, the
weights, the linear solve free and within bounds, the one-parameter search, the folds), the
linear effects (:mod:`.linear`), one nonlinear effect with one parameter from its profiles
(:mod:`.profiled`), and the nonlinear effects the profiles cannot carry, their predictions made on
the flights' rows entering the statistics as an extra column (:mod:`.search`).

:func:`fit_effects` chooses among them by the effects' kinds, never by the type of what it is
given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from quadcore.effects import Effect
from quadcore.identify.binfile import StatsError
from quadcore.identify.fit.linear import channel_weights, fit_linear
from quadcore.identify.fit.profiled import profiled_fit
from quadcore.identify.fit.search import Extras, Rows, search_fit
from quadcore.identify.fit.solve import Fit, fixed_values
from quadcore.identify.flightdata import FlightData
from quadcore.identify.stats import profiles, sufficient
from quadcore.identify.stats.sufficient import FlightStats, flight_stats, layout_of
from quadcore.physics.vehicle import Vehicle

__all__ = ["Extras", "Fit", "Rows", "channel_weights", "fit_effects", "fit_linear", "fit_rows", "profiled_fit",
           "search_fit"]

TARGET = "target"  # the extra column a target given as rows becomes (fit_rows)


def fit_effects(effects: list[Effect], stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
                vehicle: Vehicle, fixed: dict[str, dict[str, float]] | None = None, bounded: bool = False,
                rows: Rows | None = None, extras: Extras | None = None, channels: np.ndarray | None = None) -> Fit:
    """Jointly fit ``effects`` to the targets ``z·v_f`` (a signal vector per flight) from the
    flights' statistics; those named in ``fixed`` keep their values and are subtracted first;
    ``bounded``: the linear effects within their physical bounds. Linear effects:
    :func:`fit_linear`; one nonlinear effect with one parameter (not fixed) beside them, profiled in
    every flight's statistics: :func:`profiled_fit`. A fixed profiled effect (a per-session fit
    beside a shared lag) is subtracted as its prediction's column at its value
    (:func:`quadcore.identify.stats.sufficient.predicted`), the weights still of the targets as given. Any
    other nonlinear effects (several parameters, several effects, one without a profile):
    :func:`search_fit`, their predictions made on the flights' rows (``rows(flight)``;
    ``extras(flight)``: the rows of the extra columns of its statistics a target reads).
    ``channels``: (6,) 1 on the channels fitted, 0 on those left out (None: all; the weights of
    :func:`channel_weights`)."""
    fixed = fixed or {}
    free = [e for e in effects if not e.linear and e.name not in fixed]
    held = [e for e in effects if not e.linear and e.name in fixed]
    if not (all(profiles.covers(e, stats) for e in held)
            and (not free or (len(free) == 1 and profiles.covers(free[0], stats)))):
        if rows is None:
            raise StatsError(f"nonlinear effect(s) {', '.join(e.name for e in free + held)}: their predictions "
                             "are made on the flights' rows, and none were given")
        return search_fit(effects, stats, targets, vehicle, rows, fixed, bounded, extras, channels)
    if held:
        grown = [sufficient.predicted(held, fixed_values(held, fixed)[0], s, vehicle)[0] for s in stats]
        stats, targets = grown, [s.layout.pad(np.asarray(v, dtype=float)) for s, v in zip(grown, targets)]
    if free:
        return profiled_fit(effects, stats, targets, vehicle, fixed, bounded, channels)
    return fit_linear(effects, stats, targets, vehicle, fixed, bounded, channels)


def fit_rows(effects: list[Effect], flights: Sequence[FlightData], targets: Sequence[np.ndarray], vehicle: Vehicle,
             fixed: dict[str, dict[str, float]] | None = None, bounded: bool = False) -> Fit:
    """:func:`fit_effects` of targets given as rows ((n, 6) per flight, on every sample): each flight's
    rows become statistics where rows become statistics (:func:`quadcore.identify.stats.sufficient.flight_stats`:
    the linear effects' columns, ``y0`` and the target as an extra column), then the fit from them,
    the nonlinear effects' predictions made on the same rows (:func:`search_fit`; a profile is no
    cheaper than the search's own predictions for one fit). For what holds rows, not statistics: a
    model fitted per session with a nonlinear per-session effect."""
    by_id = {fd.flight: fd for fd in flights}
    if len(by_id) != len(flights):  # the search finds a flight's rows by its id
        raise ValueError(f"fit_rows: two of the flights share an id ({', '.join(fd.flight for fd in flights)})")
    layout = layout_of([e for e in effects if e.linear]).with_extras([TARGET])
    columns = {fd.flight: {TARGET: np.asarray(y)} for fd, y in zip(flights, targets)}
    stats = [flight_stats(fd, vehicle, layout, extras=columns[fd.flight]) for fd in flights]
    return fit_effects(effects, stats, [layout.unit(layout.extra(TARGET)) for _ in stats], vehicle, fixed, bounded,
                       rows=lambda f: by_id[f], extras=lambda f: columns[f])

