"""Which question the next flight should answer, from a diagnosis or as asked.

* ``separate`` two explanations: asked with ``--between A,B``; by default the diagnosis's top
  candidate and the first candidate it is tied with (``tied_with``), else the first it cannot
  tell apart from in its channel (``indistinguishable_from``) -- the verdict's "This data cannot
  tell it apart from ...".
* ``parameter``: asked with ``--parameter EFFECT.NAME`` (a candidate's or the model's own
  effect); by default, when nothing is tied, the found top candidate's parameter with the
  largest relative standard error, if that exceeds ``RELATIVE_STD``.
* nothing: no tie and no parameter worth a flight. The planner then plans nothing and says why.
"""

from __future__ import annotations

from dataclasses import dataclass

from quadcore import effects as effectlib
from quadcore.identify.diagnosis.results import CandidateScore, Diagnosis
from quadcore.plan.signatures import Explanation

RELATIVE_STD = 0.10  # a found parameter known to better than this needs no flight of its own


class QuestionError(ValueError):
    """A question that cannot be asked of this diagnosis (an unknown effect or parameter...)."""


@dataclass(frozen=True)
class Question:
    """``kind`` "separate" (``candidates``) or "parameter" (``parameter`` as EFFECT.NAME), or
    "none" with ``why`` nothing needs a flight; ``why`` says where the question came from."""

    kind: str
    candidates: tuple[str, ...] = ()
    parameter: str = ""
    why: str = ""
    alternatives: tuple[str, ...] = ()  # default question: every rival of the top candidate, in order

    def with_rival(self, rival: str, why: str) -> Question:
        return Question("separate", (self.candidates[0], rival), why=why, alternatives=self.alternatives)

    def to_dict(self) -> dict:
        if self.kind == "separate":
            return {"kind": "separate", "candidates": list(self.candidates)}
        if self.kind == "parameter":
            return {"kind": "parameter", "parameter": self.parameter}
        return {"kind": "none"}


def _candidate(diag: Diagnosis, name: str) -> CandidateScore:
    for c in diag.candidates:
        if c.effect == name:
            return c
    known = [c.effect for c in diag.candidates]
    raise QuestionError(f"{name!r} is not a candidate of this diagnosis (candidates: {', '.join(known)}); "
                        "an effect already in the model cannot be one side of a separation")


def explanation(diag: Diagnosis, name: str) -> Explanation:
    """A candidate, or one of the model's effects, with its fitted parameters."""
    for t in diag.model.terms:
        if t.name == name:
            return Explanation(t.effect, dict(t.params), dict(t.std))
    c = _candidate(diag, name)
    return Explanation(effectlib.get(name), dict(c.parameters), dict(c.parameter_std))


def ask(diag: Diagnosis, between: tuple[str, str] | None = None, parameter: str | None = None) -> Question:
    """The question (see the module)."""
    if between is not None:
        a, b = between
        if a == b:
            raise QuestionError("--between needs two different effects")
        _candidate(diag, a), _candidate(diag, b)
        return Question("separate", (a, b), why=f"asked: separate {a} from {b}")
    if parameter is not None:
        effect, _, name = parameter.partition(".")
        expl = explanation(diag, effect)
        if name not in expl.params:
            raise QuestionError(f"{effect} has no parameter {name!r}; its parameters: {', '.join(expl.params)}")
        return Question("parameter", parameter=parameter, why=f"asked: pin down {parameter}")
    return _default(diag)


def _default(diag: Diagnosis) -> Question:
    if not diag.candidates:
        return Question("none", why="the diagnosis has no candidates")
    top = diag.candidates[0]
    rivals = list(top.tied_with) or list(top.indistinguishable_from)
    if rivals:
        how = "tied with" if top.tied_with else "cannot be told apart from"
        return Question("separate", (top.effect, rivals[0]),
                        why=f"the diagnosis's top candidate {top.effect} {how} {rivals[0]}",
                        alternatives=tuple(rivals))
    if top.found:
        effect = effectlib.get(top.effect)
        rel = {p.name: top.parameter_std.get(p.name, 0.0) / abs(top.parameters[p.name] - p.default)
               for p in effect.parameters if top.parameters[p.name] != p.default}
        if rel:
            name = max(rel, key=lambda k: rel[k])
            if rel[name] > RELATIVE_STD:
                return Question("parameter", parameter=f"{top.effect}.{name}",
                                why=f"{top.effect} is found and told apart, but {name} is known only to "
                                    f"{rel[name]:.0%}")
        return Question("none", why=f"the top candidate {top.effect} is found, told apart from every other, and "
                                    f"its parameters known to better than {RELATIVE_STD:.0%}: nothing needs separating")
    return Question("none", why="no candidate is found and none is tied with another: nothing needs separating "
                                "(ask --parameter EFFECT.NAME to plan a flight that would detect a smaller effect)")
