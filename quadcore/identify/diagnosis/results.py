"""The diagnosis as types: one :class:`CandidateScore` per candidate effect and the
:class:`Diagnosis` around them (:func:`quadcore.identify.diagnosis.diagnose`). Serialised only at
the JSON boundary (:meth:`Diagnosis.to_dict`), in the key order of the ``quadcore diagnose
--json`` contract (``tests/test_json_contracts.py`` pins it byte for byte)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import FrozenInstanceError, dataclass, field, replace
from typing import TYPE_CHECKING, Any

from quadcore.identify.model import VEHICLE_DIGEST
from quadcore.identify.rates import TIE
from quadcore.identify.settings import DEFAULT, DiagnosisSettings

if TYPE_CHECKING:
    import polars as pl

    from quadcore.identify.fit.sessions import Disagreement
    from quadcore.identify.model import PhysicsModel


@dataclass(eq=False)
class CandidateFields:
    """Every field of a candidate's row, once, in the key order of its JSON object: the result's
    :class:`CandidateScore` and the row the diagnosis builds it as
    (:class:`~quadcore.identify.diagnosis.rows.CandidateRow`) both take them from here. The
    fields the later steps set start at "not yet decided" values."""

    # scored (diagnosis.scoring._score)
    effect: str
    target: str  # the channel it explains: "force" or "torque"
    acts_on: str  # the channel(s) the effect acts in: "force", "torque" or "both"
    explained_variance: float
    explained_variance_force: float
    explained_variance_torque: float
    explained_variance_raw: Mapping[str, float]
    score: float
    force_rmse_N: tuple[float, ...]
    torque_rmse_Nm: tuple[float, ...]
    parameters: Mapping[str, float]
    parameter_spread_between_flights: Mapping[str, float]
    parameter_std: Mapping[str, float]
    n_parameters: int
    explained_variance_per_axis: Mapping[str, float]
    physical: bool
    active_bounds: Mapping[str, float]  # parameters held at a physical bound (their free fit within noise of it)
    significance_sigma: float
    significant: bool
    notes: tuple[str, ...]
    # the held-out test (evidence.held_out_test_of), the share of the residual above the noise floor
    # it removes, and the size of what it removes in noise floors (RMS), in its target channel; a
    # timing candidate's test and signal_to_noise are the angular-rate level's (rates.judgement).
    # held_out_level names the level of held_out_* and signal_to_noise: the target ("force",
    # "torque") or rates.RATE_LEVEL ("angular rate"); explained_* stay the target channel's
    held_out_level: str
    held_out_slope: float
    held_out_t: float
    held_out_p_value: float
    held_out_blocks: int
    explained_above_noise: float
    signal_to_noise: float
    # decided (_decide; _outside_library may make a found one partial)
    held_out_alpha: float = 0.0
    found: bool = False
    grade: str = ""
    # compared (_mark_alike)
    indistinguishable_from: tuple[str, ...] = ()
    tied_with: tuple[str, ...] = ()
    separated_by: Mapping[str, str] = field(default_factory=dict)
    # ranked (_beyond_the_best, verdict.rank_reasons)
    explained_after_top: float = 0.0
    status: str = ""
    reason: str = ""
    sensitivity: Mapping[str, float | None] = field(default_factory=dict)


@dataclass
class CandidateScore(CandidateFields):
    """A candidate effect fitted on the training flights and scored on held-out ones: how much
    of the residual it removes (raw, per channel and axis, above the noise floor), its fitted
    parameters with their uncertainty, the held-out test, the decision (``found``, ``grade``,
    ``status``, ``reason``), the candidates the data cannot tell it from, and the smallest
    value of each parameter these flights would detect (fields: :class:`CandidateFields`).
    Compared by value. Read-only: a field is set once, when it is made (a frozen dataclass cannot
    share its fields with the mutable :class:`~quadcore.identify.diagnosis.rows.CandidateRow`,
    so the guard is :meth:`__setattr__`'s)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self.__dict__:
            raise FrozenInstanceError(f"cannot assign to field {name!r} of a CandidateScore")
        super().__setattr__(name, value)

    @property
    def useful(self) -> bool:
        """The JSON's older name of ``found``."""
        return self.found

    @classmethod
    def from_dict(cls, row: Mapping[str, Any]) -> CandidateScore:
        """From its JSON object (a document as `quadcore diagnose --json` writes it)."""
        absent = {"active_bounds": {}, "held_out_level": row["target"]}  # from documents written before them
        values = {name: row.get(name, absent[name]) if name in absent else row[name]
                  for name in cls.__dataclass_fields__}
        for name in ("force_rmse_N", "torque_rmse_Nm", "notes", "indistinguishable_from", "tied_with"):
            values[name] = tuple(values[name])
        return cls(**values)

    def to_dict(self) -> dict:
        """The candidate's JSON object; ``useful`` (the older name of ``found``) follows ``found``."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, tuple | Mapping):  # JSON lists and objects, copied
                value = list(value) if isinstance(value, tuple) else dict(value)
            out[name] = value
            if name == "found":
                out["useful"] = self.found
        return out


@dataclass(frozen=True)
class Evaluation:
    """How the diagnosis was scored: ``mode`` (holdout, cross-validation, in-sample), the folds,
    the flights fitted on and scored on, and the samples scored."""

    mode: str
    folds: int
    train_flights: tuple[str, ...]
    eval_flights: tuple[str, ...]
    samples: int

    @property
    def protocol(self) -> str:
        """The protocol in words, as the verdict, the report and the JSON state it."""
        if self.mode == "holdout":
            return (f"holdout on {', '.join(self.eval_flights)} (held out: every number fitted on the other "
                    f"{len(self.train_flights)} flights)")
        if self.mode == "cross-validation":
            return (f"{self.folds}-fold cross-validation over {len(self.eval_flights)} flights (folds grouped by "
                    "flight: each flight scored by fits that never saw it; nothing held out)")
        return f"{self.mode}: scored on the flight it was fitted on"

    def to_dict(self) -> dict:
        return {"mode": self.mode, "protocol": self.protocol, "folds": self.folds,
                "train_flights": list(self.train_flights), "eval_flights": list(self.eval_flights),
                "samples": self.samples}


NOTHING = "nothing"  # a fold's (or the diagnosis's) answer when no candidate of the library is found
# A fold's answer when its flights' residual is at their own sensor-noise floor on every channel
# (a hover that shows no drag): they hold no evidence for any effect, so the fold abstains.
NO_EVIDENCE = "no evidence"


@dataclass(frozen=True)
class Stability:
    """How stable the top answer is: the answer of each fold (``unit``: the cross-validation's
    folds, or each held-out flight), the candidate that removes the largest share of the residual
    of its flights (or :data:`NOTHING`), counted against the diagnosis's answer and the
    candidates the data cannot tell from it (``group``). ``undecided_between`` lists the answers
    when another one comes first in some fold: the top answer flips with the flights held out. A
    fold of :data:`NO_EVIDENCE` (its flights at their noise floor) abstains: it neither agrees
    nor flips the answer, and the sentence says how many did."""

    answer: str
    group: tuple[str, ...]
    unit: str  # "fold" or "held-out flight"
    votes: Mapping[str, int]  # answer -> in how many units it comes first, most first
    total: int

    def _in_group(self, answer: str) -> bool:
        """Whether a unit's answer is the top answer or one the data cannot tell from it; a tie
        between timing candidates (:data:`quadcore.identify.rates.TIE`) when each of them is."""
        return all(a in self.group for a in answer.split(TIE))

    @property
    def agree(self) -> int:
        return sum(n for a, n in self.votes.items() if self._in_group(a))

    @property
    def undecided_between(self) -> tuple[str, ...]:
        """The answers when another one than the top comes first in some unit (none with a single
        unit: one answer cannot flip)."""
        others = [a for a in self.votes if not self._in_group(a) and a != NO_EVIDENCE]
        return (self.answer, *others) if others and self.total > 1 else ()

    def sentence(self) -> str:
        """``Stable: ... first in 5 of 5 folds`` or ``Undecided between A and B: ...``."""
        def name(a: str) -> str:
            return {NOTHING: "no effect of the library",
                    NO_EVIDENCE: "none (flights at the sensor-noise floor: no evidence)"}.get(
                        a, a if TIE not in a else f"a tie ({a}, at the angular-rate level)")

        units = f"{self.unit}{'s' if self.total != 1 else ''}"
        if self.total < 2:
            return (f"Stability not measured: a single {self.unit} (cross-validation, the default without a holdout, "
                    "measures it).")
        counts = ", ".join(f"{name(a)} in {n}" for a, n in self.votes.items())
        if self.undecided_between:
            return (f"Undecided between {' and '.join(name(a) for a in self.undecided_between)}: the answer "
                    f"depends on which flights are held out (first in each of {self.total} {units}: {counts}).")
        abstained = self.votes.get(NO_EVIDENCE, 0)
        if abstained == self.total:
            return (f"Stability not measured: the flights of every {self.unit} are at their sensor-noise floor "
                    "(no evidence for any effect).")
        alike = [a for a in self.group if a != self.answer]
        return (f"Stable: {name(self.answer)}" + (f" (or {', '.join(alike)}, which the data cannot tell from it)"
                                                   if alike else "")
                + f" comes first in {self.agree} of {self.total} {units}" + (f" ({counts})." if len(self.votes) > 1
                                                                              else "."))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> Stability:
        """From its JSON object (a document written before it existed: not measured)."""
        if not d:
            return cls(NOTHING, (NOTHING,), "fold", {}, 0)
        return cls(d["answer"], tuple(d["group"]), d["unit"], dict(d["votes"]), d["total"])

    def to_dict(self) -> dict:
        return {"answer": self.answer, "group": list(self.group), "unit": self.unit, "votes": dict(self.votes),
                "agree": self.agree, "total": self.total, "undecided_between": list(self.undecided_between),
                "sentence": self.sentence()}


@dataclass(frozen=True)
class ResidualRmse:
    """Residual RMSE per body axis: force in N, torque in N m."""

    force_rmse_N: tuple[float, ...]  # x, y, z
    torque_rmse_Nm: tuple[float, ...]

    def to_dict(self) -> dict:
        return {"force_rmse_N": list(self.force_rmse_N), "torque_rmse_Nm": list(self.torque_rmse_Nm)}


@dataclass(frozen=True)
class Diagnosis:
    """Where the model fails and what is missing (see :mod:`quadcore.identify.diagnosis`)."""

    effects_in_model: tuple[str, ...]
    model: PhysicsModel  # the model's effects fitted on the training flights
    evaluation: Evaluation
    baseline: ResidualRmse  # the model's held-out residual
    noise_floor: ResidualRmse  # the sensor-noise floor on the same samples
    at_noise_level: Mapping[str, bool]
    residual_to_noise: Mapping[str, float | None]
    candidates: tuple[CandidateScore, ...]  # best first
    sensitivity: Mapping[str, Mapping[str, float | None]]
    sensitivity_basis: Mapping[str, Any]
    verdict: str
    stability: Stability
    disagreements: tuple[Disagreement, ...]
    regimes: pl.DataFrame
    flights: pl.DataFrame
    worst_segments: pl.DataFrame
    frequency: Mapping[str, Any]
    skipped_flights: Mapping[str, str] | None = None  # flight -> why, where the caller skipped some
    # when what the library finds removes less than evidence.LIBRARY_SHARE of the above-noise
    # residual: the channel, that share, the residual left in noise floors (RMS), the command to run
    outside_library: Mapping[str, Any] | None = None
    settings: DiagnosisSettings = DEFAULT  # the thresholds and folds it was made with

    def with_skipped(self, skipped: Mapping[str, str]) -> Diagnosis:
        return replace(self, skipped_flights=dict(skipped))

    def suggestion(self) -> str | None:
        """The top candidate if it is found."""
        return next((c.effect for c in self.candidates if c.found), None)

    def to_dict(self) -> dict:
        """The JSON document (``quadcore diagnose --json``, ``reports/diagnosis.json``)."""
        return {
            "effects_in_model": list(self.effects_in_model),
            "model": {k: v for k, v in self.model.to_dict().items() if k != VEHICLE_DIGEST},  # the pinned contract
            "evaluation": self.evaluation.to_dict(),
            "settings": self.settings.to_dict(),
            "baseline": self.baseline.to_dict(),
            "noise_floor": self.noise_floor.to_dict(),
            "at_noise_level": dict(self.at_noise_level),
            "residual_to_noise": dict(self.residual_to_noise),
            "candidates": [c.to_dict() for c in self.candidates],
            "sensitivity": {k: dict(v) for k, v in self.sensitivity.items()},
            "sensitivity_basis": dict(self.sensitivity_basis),
            "verdict": self.verdict,
            "outside_library": dict(self.outside_library) if self.outside_library is not None else None,
            "stability": self.stability.to_dict(),
            "disagreements": [d.to_dict() for d in self.disagreements],
            "regimes": self.regimes.to_dicts(),
            "flights": self.flights.to_dicts(),
            "worst_segments": self.worst_segments.to_dicts(),
            "frequency": self.frequency,
            **({"skipped_flights": dict(self.skipped_flights)} if self.skipped_flights is not None else {}),
        }
