"""A candidate's row as the diagnosis builds it, step by step (:class:`CandidateRow`): scored
(:func:`~quadcore.identify.diagnosis.scoring._score`), decided (``_decide``), compared with the
others (``_mark_alike``), ranked and given its reason (``_rank``, ``_beyond_the_best``,
:func:`~quadcore.identify.diagnosis.verdict.rank_reasons`), perhaps made partial (what is left is
outside the library); then copied into the result's
:class:`~quadcore.identify.diagnosis.results.CandidateScore` (:meth:`CandidateRow.result`). Both
take their fields from :class:`~quadcore.identify.diagnosis.results.CandidateFields`.

The fields the later steps set start at "not yet decided" values; every step of
:func:`quadcore.identify.diagnosis.diagnose` runs on every row before it is copied.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

from quadcore.identify.diagnosis.results import CandidateFields, CandidateScore

if TYPE_CHECKING:  # the rate level imports this module's type for its annotations
    from quadcore.identify.rates.judgement import RateEvidence


@dataclass(eq=False)  # a row is itself: the steps compare rows by identity
class CandidateRow(CandidateFields):
    """One candidate's scores and decisions as the steps fill them in: the result's fields and
    ``explained_alone_screen``, which the verdict reads and the result does not keep."""

    # ranked (_beyond_the_best): what it removes alone by the same screen as explained_after_top
    explained_alone_screen: float = 0.0
    # a timing candidate (rates.judge): its found-ness decided at the angular-rate level; None: at its target channel
    rate_level: RateEvidence | None = None

    def tier(self) -> int:
        """0: found (physical, significant, confirmed on held-out flights); 1: physical but not
        found; 2: unphysical (never an explanation, whatever it removes)."""
        return 0 if self.found else (1 if self.physical else 2)

    def explained_in(self, channel: str) -> float:
        """The share of the held-out ``channel`` residual it removes (clipped at the noise floor)."""
        return self.explained_variance_force if channel == "force" else self.explained_variance_torque

    def result(self) -> CandidateScore:
        """The result's row: a copy of the result's fields."""
        return CandidateScore(**{f.name: getattr(self, f.name) for f in fields(CandidateFields)})
