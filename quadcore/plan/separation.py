"""The measured separation of two explanations on flights: the diagnosis's held-out comparison.

Cross-validation over flights (:func:`quadcore.identify.fit.solve.folds`, as the diagnosis): in
each fold both candidates are fitted (:func:`quadcore.identify.fit.fit_rows`) on the
training flights' residual of the model and predict the test flights; then
:func:`quadcore.identify.evidence.compare` tests, over all held-out 1 s blocks, which of the two
fits the residual better, in the channels above the sensor-noise floor. Its ``t`` is the
separation in standard errors (positive: the first fits better).

As the diagnosis, it compares the two on the same samples: each flight's first ``skip`` blocks
(:func:`compared_blocks`: those within the longest memory of the diagnosis's effects) are left
out.

One simplification against the diagnosis: the model's own effects are not refitted in each
fold; its residual is taken against the model fitted on all flights (``model``, from the
diagnosis), so the model's parameters have seen the test flights (a few parameters over
thousands of samples; the comparison of the two candidates is what matters here).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import evidence, fit as fitlib, flightdata
from quadcore.identify.diagnosis.results import Diagnosis
from quadcore.identify.fit import sessions, solve
from quadcore.identify.model import PhysicsModel
from quadcore.spec.model import ModelSpec

N_FOLDS = 5


@dataclass(frozen=True)
class Comparison:
    """The held-out comparison of ``a`` and ``b``: ``t`` (> 0: ``a`` fits better), its p-value,
    the blocks it was summed over."""

    a: str
    b: str
    t: float
    p_value: float
    blocks: int

    def sigma_for(self, truth: str) -> float:
        """The separation in favour of ``truth`` (negative when the data prefer the other)."""
        return self.t if truth == self.a else -self.t


def flights_of(tables: Mapping, spec: ModelSpec) -> dict[str, flightdata.FlightData]:
    """Each decoded table as the fits take it (its session's thrust map)."""
    return {f: flightdata.flight_data(f, tables[f], spec.vehicle_for(f)) for f in sorted(tables)}


def compared_blocks(diag: Diagnosis) -> int:
    """The first blocks of each flight the diagnosis left out of its comparison of candidates
    (:func:`quadcore.identify.evidence.memory_blocks` of its model's effects and candidates)."""
    names = [*diag.effects_in_model, *(c.effect for c in diag.candidates)]
    return evidence.memory_blocks([effectlib.get(n) for n in names])


def compare(fds: Mapping[str, flightdata.FlightData], model: PhysicsModel, a: str, b: str,
            n_folds: int = N_FOLDS, skip: int = 0) -> Comparison:
    """The held-out comparison of candidates ``a`` and ``b`` on ``fds``, each flight without its
    first ``skip`` blocks (see the module)."""
    ids = sorted(fds)
    vehicle = model.vehicle
    resid = {}
    for f in ids:
        fd = fds[f]
        target = np.concatenate([fd.r_f, fd.r_tau], axis=1)
        resid[f] = target - sessions.model_prediction(model, fd) if model.terms else target
    ea, eb = effectlib.get(a), effectlib.get(b)
    pred_a: dict[str, np.ndarray] = {}
    pred_b: dict[str, np.ndarray] = {}
    for held in solve.folds(ids, n_folds):
        train = [f for f in ids if f not in held] or ids
        for e, out in ((ea, pred_a), (eb, pred_b)):
            fit = fitlib.fit_rows([e], [fds[f] for f in train], [resid[f] for f in train], vehicle)
            for f in held:
                out[f] = fit.predict([e], fds[f], vehicle)
    flights = [fds[f].after_blocks(skip) for f in ids]
    before = sum((resid[fd.flight][fd.mask] ** 2).sum(axis=0) for fd in flights)
    floor = sum((fd.noise ** 2 * fd.n for fd in flights), np.zeros(6))
    quiet = evidence.at_noise_level(before, floor)
    w = fitlib.row_weights(flights, [resid[fd.flight] for fd in flights])
    w = w * evidence.channel_mask([ch for ch, q in quiet.items() if not q])
    test = evidence.compare(flights, resid, pred_a, pred_b, w)
    return Comparison(a, b, float(test.t), float(test.p_value), int(test.blocks))
