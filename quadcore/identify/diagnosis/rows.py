"""A candidate's row as the diagnosis builds it, step by step (:class:`CandidateRow`): scored
(:func:`~quadcore.identify.diagnosis.scoring._score`), decided (``_decide``), compared with the
others (``_mark_alike``), ranked and given its reason (``_rank``, ``_beyond_the_best``,
:func:`~quadcore.identify.diagnosis.verdict.rank_reasons`), perhaps made partial (what is left is
outside the library); then frozen into the result's
:class:`~quadcore.identify.diagnosis.results.CandidateScore` (:meth:`CandidateRow.frozen`).

The fields the later steps set start at "not yet decided" values; every step of
:func:`quadcore.identify.diagnosis.diagnose` runs on every row before it is frozen.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from quadcore.identify.diagnosis.results import CandidateScore


@dataclass(frozen=True)
class HeldOutEvidence:
    """A candidate's held-out test in its target channel (:func:`quadcore.identify.evidence.held_out_test_of`),
    the share of the residual *above the noise floor* it removes, and the size of what it
    removes in noise floors (RMS)."""

    held_out_slope: float
    held_out_t: float
    held_out_p_value: float
    held_out_blocks: int
    explained_above_noise: float
    signal_to_noise: float


@dataclass(eq=False)  # a row is itself: the steps compare rows by identity
class CandidateRow:
    """One candidate's scores and decisions (the fields of
    :class:`~quadcore.identify.diagnosis.results.CandidateScore`, with lists and dicts that the
    steps fill in, and ``explained_alone_screen``, which the verdict reads and the result does
    not keep)."""

    # scored (_score)
    effect: str
    target: str  # the channel it explains: "force" or "torque"
    acts_on: str  # "force", "torque" or "both"
    explained_variance: float
    explained_variance_force: float
    explained_variance_torque: float
    explained_variance_raw: dict[str, float]
    score: float
    force_rmse_N: list[float]
    torque_rmse_Nm: list[float]
    parameters: dict[str, float]
    parameter_spread_between_flights: dict[str, float]
    parameter_std: dict[str, float]
    n_parameters: int
    explained_variance_per_axis: dict[str, float]
    physical: bool
    active_bounds: dict[str, float]
    significance_sigma: float
    significant: bool
    notes: list[str]
    evidence: HeldOutEvidence
    # decided (_decide; _outside_library may make a found one partial)
    held_out_alpha: float = 0.0
    found: bool = False
    grade: str = ""
    # compared (_mark_alike)
    indistinguishable_from: list[str] = field(default_factory=list)
    tied_with: list[str] = field(default_factory=list)
    separated_by: dict[str, str] = field(default_factory=dict)
    # ranked (_beyond_the_best, rank_reasons)
    explained_after_top: float = 0.0
    explained_alone_screen: float = 0.0
    sensitivity: dict[str, float | None] = field(default_factory=dict)
    status: str = ""
    reason: str = ""

    @property
    def held_out_p_value(self) -> float:
        return self.evidence.held_out_p_value

    @property
    def held_out_slope(self) -> float:
        return self.evidence.held_out_slope

    @property
    def explained_above_noise(self) -> float:
        return self.evidence.explained_above_noise

    @property
    def signal_to_noise(self) -> float:
        return self.evidence.signal_to_noise

    def tier(self) -> int:
        """0: found (physical, significant, confirmed on held-out flights); 1: physical but not
        found; 2: unphysical (never an explanation, whatever it removes)."""
        return 0 if self.found else (1 if self.physical else 2)

    def explained_in(self, channel: str) -> float:
        """The share of the held-out ``channel`` residual it removes (clipped at the noise floor)."""
        return self.explained_variance_force if channel == "force" else self.explained_variance_torque

    def frozen(self) -> CandidateScore:
        """The result's typed row."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("evidence",
                                                                                       "explained_alone_screen")}
        values.update({f.name: getattr(self.evidence, f.name) for f in fields(self.evidence)})
        for name in ("force_rmse_N", "torque_rmse_Nm", "notes", "indistinguishable_from", "tied_with"):
            values[name] = tuple(values[name])
        return CandidateScore(**values)
