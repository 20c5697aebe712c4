"""The fits, from the flights' statistics (:mod:`quadcore.identify.sufficient`), laid out by
concept and importing only downward: what every fit shares (:mod:`.solve`: the result, the
weights, the linear solve free and within bounds, the one-parameter search, the folds), the
linear effects (:mod:`.linear`), one nonlinear effect with one parameter from its profiles
(:mod:`.profiled`).

:func:`fit_effects` chooses among them by the effects' kinds, never by the type of what it is
given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from quadcore.effects import Effect
from quadcore.identify import profiles, sufficient
from quadcore.identify.binfile import StatsError
from quadcore.identify.fit.linear import channel_weights, fit_linear
from quadcore.identify.fit.profiled import profiled_fit
from quadcore.identify.fit.solve import Fit, fixed_values
from quadcore.identify.sufficient import FlightStats
from quadcore.physics.vehicle import Vehicle

__all__ = ["Fit", "channel_weights", "fit_effects", "fit_linear", "profiled_fit"]


def fit_effects(effects: list[Effect], stats: Sequence[FlightStats], targets: Sequence[np.ndarray],
                vehicle: Vehicle, fixed: dict[str, dict[str, float]] | None = None, bounded: bool = False) -> Fit:
    """Jointly fit ``effects`` to the targets ``z·v_f`` (a signal vector per flight) from the
    flights' statistics; those named in ``fixed`` keep their values and are subtracted first;
    ``bounded``: the linear effects within their physical bounds. Linear effects:
    :func:`fit_linear`; one nonlinear effect with one parameter (not fixed) beside them, profiled in
    every flight's statistics: :func:`profiled_fit`. A fixed profiled effect (a per-session fit
    beside a shared lag) is subtracted as its prediction's column at its value
    (:func:`quadcore.identify.sufficient.predicted`), the weights still of the targets as given."""
    fixed = fixed or {}
    held = [e for e in effects if not e.linear and e.name in fixed and profiles.covers(e, stats)]
    if held:
        grown = [sufficient.predicted(held, fixed_values(held, fixed)[0], s, vehicle)[0] for s in stats]
        stats, targets = grown, [s.layout.pad(np.asarray(v, dtype=float)) for s, v in zip(grown, targets)]
    nonlinear = [e for e in effects if not e.linear and e not in held]
    if len(nonlinear) == 1 and nonlinear[0].name not in fixed and profiles.covers(nonlinear[0], stats):
        return profiled_fit(effects, stats, targets, vehicle, fixed, bounded)
    if nonlinear:
        raise StatsError(f"nonlinear effect(s) {', '.join(e.name for e in nonlinear)}: fitted from rows, not "
                         "statistics (but one with a profile in every flight's statistics)")
    return fit_linear(effects, stats, targets, vehicle, fixed, bounded)
