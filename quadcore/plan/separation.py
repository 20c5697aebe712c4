"""The measured separation of two explanations on flights: the diagnosis's held-out comparison.

Cross-validation over flights (:func:`quadcore.identify.fit.solve.folds`, as the diagnosis),
from the flights' statistics (:func:`quadcore.identify.diagnosis.held_out_of_model`: each
flight's rows become statistics once, with the model's effects and the two candidates): in each
fold both candidates are fitted on the training flights' residual of the model and predict the
test flights' (signal vectors; a one-parameter nonlinear candidate from its profiles); then
:func:`quadcore.identify.evidence.compare` tests, over all held-out 1 s blocks (its variance
widened where the flights disagree in sign), which of the two fits the residual better, in the
channels above the sensor-noise floor (and one at it on the flights where either adds error
there: :func:`quadcore.identify.evidence.compared_weights`). Its ``t`` is the
separation in standard errors (positive: the first fits better).

As the diagnosis, it compares the two on the same samples: each flight's first ``skip`` blocks
(:func:`skipped_blocks`: those within the longest memory of the diagnosis's effects) are left
out.

Between two timing candidates (both :attr:`~quadcore.effects.Effect.retimes_thrust`) the
diagnosis decides at the angular-rate level (:mod:`quadcore.identify.rates`), not by this
comparison: :func:`rate_compare` is its held-out comparison there, run with the rate level's own
functions on the same folds.

Two simplifications against the diagnosis: the model's own effects are not refitted in each
fold; its residual is taken against the model fitted on all flights (``model``, from the
diagnosis), so the model's parameters have seen the test flights (a few parameters over
thousands of samples; the comparison of the two candidates is what matters here). And the
candidates are fitted free, not within their physical bounds (the separation of the data's own
best fits).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
from scipy import stats

from quadcore import effects as effectlib
from quadcore.identify import diagnosis as diagnosislib, evidence, flightdata, rates
from quadcore.identify.diagnosis.results import Diagnosis
from quadcore.identify.model import PhysicsModel
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.spec.model import ModelSpec

N_FOLDS = 5


@dataclass(frozen=True)
class ByFlight:
    """The same comparison with each flight as one cluster (its blocks' scores summed): how many
    flights ``a`` fits better, of how many, and the cluster-robust t of the mean block score with
    the flights as clusters (``t = ḡ / se``, ``se² = F/(F-1) Σ_f (S_f - n_f ḡ)² / N²``: ``S_f`` a
    flight's summed score over its ``n_f`` blocks, ``N`` blocks of ``F`` flights; Student's t with
    ``F - 1`` degrees of freedom). The comparison itself takes its 1 s blocks as independent
    where the flights agree and widens its variance by theirs where they disagree
    in sign (:func:`quadcore.identify.evidence.slope_test`); this is the plainer count beside it:
    on the 19 real flights com_offset against rotor_imbalance is 5.0 σ with blocks as independent,
    2.2 σ in the comparison (the flights disagree in sign), 1.6 σ by flights (11 of 19 prefer
    com_offset)."""

    flights: int
    for_first: int
    t: float
    p_value: float

    @classmethod
    def of(cls, sums: Sequence[float], blocks: Sequence[int]) -> ByFlight:
        s, n = np.asarray(sums, dtype=float), np.asarray(blocks, dtype=float)
        k, total = len(s), float(n.sum())
        if k < 2 or total <= 0:
            return cls(k, int((s > 0).sum()), 0.0, 1.0)
        mean = float(s.sum() / total)
        se = float(np.sqrt(k / (k - 1) * np.sum((s - n * mean) ** 2)) / total)
        t = mean / se if se > 0 else 0.0
        return cls(k, int((s > 0).sum()), t, float(2 * stats.t.sf(abs(t), k - 1)))

    def to_dict(self) -> dict[str, float]:
        return {"flights": self.flights, "preferring_the_first": self.for_first,
                "separation_sigma": abs(self.t), "p_value": self.p_value}


@dataclass(frozen=True)
class Comparison:
    """The held-out comparison of ``a`` and ``b``: ``t`` (> 0: ``a`` fits better), its p-value,
    the blocks it was summed over; ``undecided``: why the diagnosis prefers neither whatever ``t``
    says (empty: it goes by ``t``), and ``undecided_by`` what decides it in its place, in a few
    words: at the rate level, ``the noise model`` (the comparison with the whitening filter, ``t``,
    and the one without, ``unwhitened_t``, both significant and opposite:
    :func:`quadcore.identify.rates.noise_model_decides`) or ``the closed loop`` (the comparison with
    the timing direction one sample back as the instrument contradicts ``t``:
    :func:`quadcore.identify.rates.closed_loop_decides`); ``by_flight``: the same by flight
    (:class:`ByFlight`; None at the rate level); ``available_blocks``: the held-out blocks there
    were to compare on (None at the rate level), fewer than ``evidence.MIN_BLOCKS`` being no test."""

    a: str
    b: str
    t: float
    p_value: float
    blocks: int
    undecided: str = ""
    unwhitened_t: float | None = None
    undecided_by: str = ""
    by_flight: ByFlight | None = None
    available_blocks: int | None = None

    def sigma_for(self, truth: str) -> float:
        """The separation in favour of ``truth`` (negative when the data prefer the other), as the
        diagnosis decides the pair: 0 where it prefers neither (:attr:`undecided`)."""
        if self.undecided:
            return 0.0
        return self.t if truth == self.a else -self.t


def flights_of(tables: Mapping, spec: ModelSpec) -> dict[str, flightdata.FlightData]:
    """Each decoded table as the fits take it (its session's thrust map)."""
    return {f: flightdata.flight_data(f, tables[f], spec.vehicle_for(f)) for f in sorted(tables)}


def skipped_blocks(diag: Diagnosis) -> int:
    """The first blocks of each flight the diagnosis left out of its comparison of candidates
    (:func:`quadcore.identify.evidence.memory_blocks` of its model's effects and candidates)."""
    names = [*diag.effects_in_model, *(c.effect for c in diag.candidates)]
    return evidence.memory_blocks([effectlib.get(n) for n in names])


def compare(tables: Mapping[str, pl.DataFrame], spec: ModelSpec, model: PhysicsModel, a: str, b: str,
            n_folds: int = N_FOLDS, skip: int = 0, stats=None) -> Comparison:
    """The held-out comparison of candidates ``a`` and ``b`` on the decoded ``tables`` (their
    statistics for ``spec``; ``stats``: stored ones, as the diagnosis takes them), each flight
    without its first ``skip`` blocks (see the module)."""
    held = diagnosislib.held_out_of_model(tables, spec, model, [a, b], n_folds, skip, bounded=False, stats=stats)
    w = evidence.compared_weights(held.flights, held.resid, held.cand_pred[a], held.cand_pred[b], held.w, held.at_noise)
    test = evidence.compare(held.flights, held.resid, held.cand_pred[a], held.cand_pred[b], w)
    available = test.blocks or len(evidence.block_sums(held.flights, held.resid, held.resid, held.w))
    return Comparison(a, b, float(test.t), float(test.p_value), int(test.blocks),
                      by_flight=_by_flight(held, a, b, w) if test.blocks else None, available_blocks=available)


def _by_flight(held, a: str, b: str, w: np.ndarray) -> ByFlight:
    """The comparison's block scores (:func:`quadcore.identify.evidence.compare`, ``w`` its
    weights per flight and channel) summed per evaluated flight (:class:`ByFlight`)."""
    sums, blocks = [], []
    for f, fd, w_f in zip(held.ids, held.flights, w):
        pa, pb = held.cand_pred[a][f], held.cand_pred[b][f]
        g = evidence.block_sums([fd], {f: pa - pb}, {f: held.resid[f] - 0.5 * (pa + pb)}, w_f)
        sums.append(float(g.sum()))
        blocks.append(len(g))
    return ByFlight.of(sums, blocks)


def timing_pair(a: str, b: str) -> bool:
    """Both candidates re-time the rotors' thrust: the diagnosis compares them at the rate level."""
    return all(effectlib.get(n).retimes_thrust and len(effectlib.get(n).parameters) == 1 for n in (a, b))


def rate_compare(tables: Mapping[str, pl.DataFrame], spec: ModelSpec, model: PhysicsModel, a: str, b: str,
                 timing: Sequence[str] = (), settings: DiagnosisSettings = DEFAULT) -> Comparison:
    """The diagnosis's comparison of two timing candidates at the angular-rate level
    (:func:`quadcore.identify.rates.judge`'s, for one pair, with its ``settings``: folds and
    ``alpha``): each flight's rate sums with the model's torque removed and the first blocks of the
    longest memory among the diagnosis's ``timing`` candidates left out (``a`` and ``b`` at least),
    :func:`quadcore.identify.rates.timing_comparison` on the diagnosis's folds (both candidates
    fitted on all the training flights, every flight scored; held-out flights given: those)
    (``t > 0``: ``a``): undecided where the diagnosis prefers neither because the noise model or the
    closed loop decides it."""
    ea, eb = effectlib.get(a), effectlib.get(b)
    skip = evidence.memory_blocks([effectlib.get(n) for n in {a, b, *timing}])
    fds = flights_of(tables, spec)
    sums = {f: rates.flight_sums(fd, model, f, [ea, eb], skip) for f, fd in fds.items()}
    splits, _, _ = diagnosislib.fold_splits(sorted(sums), None, settings.n_folds)
    pair = rates.timing_comparison(sums, splits, ea, eb, settings.alpha)
    test = pair.test
    return Comparison(a, b, float(test.t), float(test.p_value), int(test.blocks), pair.note() if pair.undecided else "",
                      None if pair.unwhitened is None else float(pair.unwhitened.t), pair.undecided_by)


def timing_candidates(diag: Diagnosis) -> list[str]:
    """The diagnosis's candidates its rate level compares (one parameter, re-timing the thrust)."""
    return [c.effect for c in diag.candidates if timing_pair(c.effect, c.effect)]


def measured(tables: Mapping[str, pl.DataFrame], spec: ModelSpec, diag: Diagnosis, a: str, b: str,
             stats=None) -> Comparison:
    """The separation of ``a`` and ``b`` in the statistic the diagnosis ``diag`` decides them by:
    :func:`rate_compare` for two timing candidates, else :func:`compare` (its model, its skipped
    blocks; ``stats`` as there)."""
    if timing_pair(a, b):
        return rate_compare(tables, spec, diag.model, a, b, timing_candidates(diag), diag.settings)
    return compare(tables, spec, diag.model, a, b, skip=skipped_blocks(diag), stats=stats)
