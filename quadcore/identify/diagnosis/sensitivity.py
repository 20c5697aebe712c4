"""How small an effect could hide in what is left: each candidate parameter's detection limit on
the evaluated flights (:func:`detection_limits`) and what those values mean (:func:`sensitivity_basis`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from quadcore.identify import evidence
from quadcore.identify.flightdata import Flight
from quadcore.identify.settings import DEFAULT, DiagnosisSettings


def detection_limits(cands, flights: Sequence[Flight], resid: dict[str, np.ndarray], noise_ss: np.ndarray,
                     vehicle, n_candidates: int, settings: DiagnosisSettings = DEFAULT, all_at_once: bool = False
                     ) -> dict[str, dict[str, float | None]]:
    """Per candidate and parameter: the smallest |deviation from 'no effect'| these flights
    would detect (:func:`quadcore.identify.evidence.detection_limits`); None when no value within the
    parameter's range would be. A parameter stated at a reference point of the others (a
    wind, at a rotor drag) must also lift the score by ``2 tie_margin`` above the simpler
    effect it then resembles (a wind above rotor drag), or the two are a tie. ``all_at_once``:
    every parameter's sums in one pass over the flights (statistics: one read of their Gram
    matrices), else one unit wrench at a time (rows: one signal per flight in memory)."""
    jobs = [(c, p) for c in cands for p in c.parameters]
    base_ss = {c.name: sum(fd.reference_ss(c, vehicle) for fd in flights) for c in cands if c.sensitivity_reference}
    batch = max(len(jobs), 1) if all_at_once else 1
    out: dict[str, dict[str, float | None]] = {c.name: {} for c in cands}
    for start in range(0, len(jobs), batch):
        part = jobs[start: start + batch]
        asks = [_limit_ask(c, p, flights, vehicle, base_ss.get(c.name, 0.0), settings.tie_margin) for c, p in part]
        limits = evidence.detection_limits(flights, resid, asks, noise_ss, n_candidates, settings)
        for (c, p), v in zip(part, limits):
            if not c.linear:  # the unit wrench is a secant: nothing is known below its step
                v = max(v, evidence.SECANT * (p.upper - p.lower))
            out[c.name][p.name] = float(v) if v <= max(p.upper - p.default, p.default - p.lower) else None
    return out


def _limit_ask(c, p, flights: Sequence[Flight], vehicle, base_ss: float, tie_margin: float) -> evidence.LimitAsk:
    """A parameter's detection limit to find: stated at a reference point of the others (a wind,
    at a rotor drag), it must also lift the score by ``2 tie_margin`` above the effect it then
    resembles."""
    unit = {fd.flight: fd.unit_signal(c, p, vehicle) for fd in flights}
    if c.sensitivity_reference and p.name not in c.sensitivity_reference:
        return evidence.LimitAsk(unit, 2 * tie_margin, base_ss)
    return evidence.LimitAsk(unit)


def sensitivity_basis(cands, settings: DiagnosisSettings = DEFAULT) -> dict:
    """What the sensitivity values mean (for the JSON and the reports)."""
    return {
        "meaning": "smallest |parameter - its 'no effect' value| these flights would detect, each parameter alone",
        "detection_probability": settings.power,
        "false_alarm_probability": settings.alpha,
        "noise_margin": settings.noise_margin,
        "conditions": {c.name: dict(c.sensitivity_reference) for c in cands if c.sensitivity_reference},
    }
