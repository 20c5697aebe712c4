"""The reference the planner's measured separation (:func:`quadcore.plan.separation.compare`,
from the flights' statistics) is tested against: the same held-out comparison on the flights'
rows, sample by sample. Nothing in quadcore uses it; tests/test_plan_separation.py compares
against it.

Per fold over the flights (:func:`quadcore.identify.fit.solve.folds`), each candidate is fitted
(:func:`reference.rows.fit_effects`, free; a one-parameter candidate acting on force and torque
in the one of them above the sensor-noise floor on the training flights when the other is at it)
to the training flights' residual of the model and
predicts the test flights' (:func:`quadcore.identify.flightdata.prediction`). On the usable
samples ``i`` of each flight, numbered into blocks of ``BLOCK_S`` over the whole flight
(:func:`quadcore.identify.flightdata.block_index`) and without the first ``skip`` of them, the
score of a block ``b`` is

    g_b = Σ_{i∈b} Σ_c w_c 2 (a_ic - b_ic) (r_ic - (a_ic + b_ic)/2)     (= |r - b|² - |r - a|²)

``w_c`` the inverse mean square of the residual per force and torque, channels whose residual
is within the noise margin of the sensor-noise floor left out of a flight unless either prediction
adds error there on it (``Σ p·(p - 2 r) > 0`` over the flight); ``t`` the one-sample t statistic
of the ``g_b`` (> 0: ``a`` fits better), widened where the flights disagree about its sign: the library's
statistic (:func:`quadcore.identify.evidence.slope_test`, tested against its formulas in
tests/test_held_out_flights.py) on the block scores made here from the rows.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import evidence, flightdata
from quadcore.identify.fit import sessions, solve
from quadcore.identify.flightdata import FlightData
from quadcore.identify.model import PhysicsModel
from reference import rows


def _kept(fd: FlightData, skip: int) -> tuple[np.ndarray, np.ndarray]:
    """The usable samples after the first ``skip`` blocks (numbered over the whole flight), and their blocks."""
    idx = np.flatnonzero(fd.mask)
    block = flightdata.block_index(fd.state.t_s[idx])
    keep = block >= skip
    return idx[keep], block[keep] - skip


def _fitted_channels(e, train: list[FlightData], resid: list[np.ndarray], skip: int) -> np.ndarray | None:
    """A one-parameter candidate acting on force and torque is fitted in the one of the two above
    its sensor-noise floor on the training flights when the other is at it (the usable samples
    the scores count: after the first ``skip`` blocks, every one if none is left)."""
    if e.target != "both" or len(e.parameters) != 1:
        return None
    kept = [_kept(fd, skip)[0] for fd in train]
    if sum(len(k) for k in kept) == 0:
        kept = [np.flatnonzero(fd.mask) for fd in train]
    ss = sum((np.einsum("nc,nc->c", r[k], r[k]) for k, r in zip(kept, resid)), np.zeros(6))
    floor = sum((fd.noise ** 2 * len(k) for fd, k in zip(train, kept)), np.zeros(6))
    above = [ch for ch, quiet in evidence.at_noise_level(ss, floor).items() if not quiet]
    return evidence.channel_mask(above) if len(above) == 1 else None


def t_statistic(fds: Mapping[str, FlightData], model: PhysicsModel, a: str, b: str, n_folds: int = 5,
                skip: int = 0) -> tuple[float, int]:
    """The held-out comparison's ``t`` and its number of blocks (see the module)."""
    ids = sorted(fds)
    resid = {f: flightdata.targets_of([fds[f]])[0] - (sessions.model_prediction(model, fds[f]) if model.terms else 0)
             for f in ids}
    pred: dict[str, dict[str, np.ndarray]] = {a: {}, b: {}}
    for held in solve.folds(ids, n_folds):
        train = [f for f in ids if f not in held] or ids
        for name in (a, b):
            e = effectlib.get(name)
            fit = rows.fit_effects([e], [fds[f] for f in train], [resid[f] for f in train], model.vehicle,
                                   channels=_fitted_channels(e, [fds[f] for f in train], [resid[f] for f in train],
                                                                   skip))
            for f in held:
                pred[name][f] = flightdata.prediction(e, fit.params[name], fds[f], model.vehicle)
    kept = {f: _kept(fds[f], skip) for f in ids}
    r = {f: resid[f][kept[f][0]] for f in ids}
    ss = sum((np.einsum("nc,nc->c", r[f], r[f]) for f in ids), np.zeros(6))
    floor = sum((fds[f].noise ** 2 * len(kept[f][0]) for f in ids), np.zeros(6))
    quiet = evidence.at_noise_level(ss, floor)
    w_all = rows.channel_weights(list(r.values()))
    w = {}
    for f in ids:  # per flight: at the floor a channel is taken where either prediction adds error on it
        mask = evidence.channel_mask([ch for ch, q in quiet.items() if not q])
        for ch in (ch for ch, q in quiet.items() if q):
            sl = evidence.CHANNELS[ch]
            worse = [float(np.einsum("nc,nc->c", pred[n][f][kept[f][0]], pred[n][f][kept[f][0]] - 2 * r[f])[sl]
                           @ w_all[sl]) for n in (a, b)]
            mask[sl] = float(max(worse) > 0)
        w[f] = w_all * mask
    if _same_to_rounding([pred[a][f][kept[f][0]] for f in ids], [pred[b][f][kept[f][0]] for f in ids],
                         [w[f] for f in ids]):
        return 0.0, 0  # the same signal written two ways: no test (evidence.same_prediction)
    g = []
    for f in ids:
        pa, pb = pred[a][f][kept[f][0]], pred[b][f][kept[f][0]]
        per_sample = (2 * (pa - pb) * (r[f] - 0.5 * (pa + pb))) @ w[f]
        g.append(np.bincount(kept[f][1], weights=per_sample))
    scores = np.concatenate(g)
    flight = np.repeat(np.arange(len(g)), [len(x) for x in g])
    return evidence.slope_test(scores, np.ones(len(scores)), flight, two_sided=True).t, len(scores)


def _same_to_rounding(pa: list[np.ndarray], pb: list[np.ndarray], w: list[np.ndarray]) -> bool:
    """Whether the two candidates' held-out predictions differ by no more than rounding, their
    difference's weighted energy (``w`` per flight) against theirs on the rows (the library's threshold)."""
    diff = sum(float(np.einsum("nc,nc->c", x - y, x - y) @ wf) for x, y, wf in zip(pa, pb, w))
    total = sum(float(np.einsum("nc,nc->c", x, x) @ wf + np.einsum("nc,nc->c", y, y) @ wf)
                for x, y, wf in zip(pa, pb, w))
    return evidence.same_prediction(diff, total)
