"""What term discovery reports: the kept terms (:class:`DiscoveredTerm`), their rival forms
(:class:`Form`), each residual axis' conclusion (:class:`AxisResult`) and the whole result
(:class:`Discovery`, the ``quadcore discover --json`` document through :meth:`Discovery.to_dict`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from quadcore.identify.settings import DEFAULT, DiagnosisSettings


@dataclass(frozen=True)
class Form:
    """One functional form of a term's slot on its axis, scored held out: the share of the
    held-out variance the axis' kept terms explain with this form in the slot (on the flights
    the terms are scored on: the holdout, or the folds), and in how many of the cross-validation
    folds (where forms are chosen, never on the holdout) it leaves less than the kept form."""

    expression: str
    explained_variance: float
    better_in: int  # folds where it beats the kept form (0 for the kept form itself)
    sets: int  # folds

    def to_dict(self) -> dict:
        return {"expression": self.expression, "explained_variance": self.explained_variance,
                "better_in": self.better_in, "sets": self.sets}


@dataclass(frozen=True)
class DiscoveredTerm:
    """A kept term: ``target ≈ coefficient · expression`` (SI)."""

    target: str
    expression: str
    variables: tuple[str, ...]
    coefficient: float
    std: float
    unit: str  # of the coefficient
    term_unit: str
    explained_variance: float  # held-out share of the target's variance it adds (selection order)
    stability: float  # share of folds selecting it
    folds_selected: int
    folds: int
    matches_effects: tuple[str, ...] = ()
    literature: str = ""
    collinear_with: tuple[str, ...] = ()
    competing_forms: tuple[Form, ...] = ()  # its form's rivals, scored held out (best first)

    @property
    def formula(self) -> str:
        unit = f" {self.unit}" if self.unit != "1" else ""
        return (f"{self.target} ≈ {self.coefficient:+.3g}{unit} · {self.expression} "
                f"(± {self.std:.2g}; explains {self.explained_variance:.0%} held out, kept in "
                f"{self.folds_selected}/{self.folds} folds)")

    def to_dict(self) -> dict:
        return {"target": self.target, "expression": self.expression, "variables": list(self.variables),
                "coefficient": self.coefficient, "std": self.std, "unit": self.unit, "term_unit": self.term_unit,
                "explained_variance": self.explained_variance, "stability": self.stability,
                "formula": self.formula, "matches_effects": list(self.matches_effects),
                "literature": self.literature, "collinear_with": list(self.collinear_with),
                "competing_forms": [f.to_dict() for f in self.competing_forms]}


@dataclass(frozen=True)
class AxisResult:
    """What discovery concluded on one residual axis."""

    target: str
    explained_variance: float  # of all kept terms together, held out
    at_noise_level: bool
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Discovery:
    terms: tuple[DiscoveredTerm, ...]
    axes: tuple[AxisResult, ...]
    baseline: dict
    after: dict
    noise_floor: dict
    evaluation: dict
    effects_in_model: tuple[str, ...]
    library_size: dict = field(default_factory=dict)
    settings: DiagnosisSettings = DEFAULT  # the folds, min_gain and noise_margin it selected by

    def to_dict(self) -> dict:
        return {
            "terms": [t.to_dict() for t in self.terms],
            "axes": [{"target": a.target, "explained_variance": a.explained_variance,
                      "at_noise_level": a.at_noise_level, "notes": list(a.notes)} for a in self.axes],
            "baseline": self.baseline, "after": self.after, "noise_floor": self.noise_floor,
            "evaluation": self.evaluation, "settings": self.settings.to_dict(),
            "effects_in_model": list(self.effects_in_model),
            "library_size": self.library_size,
        }

    @property
    def summary(self) -> str:
        """A paragraph a person reads first."""
        if not self.terms:
            return ("No term of the candidate library explains a stable share of the held-out residual "
                    f"(at least {self.settings.min_gain:.0%} of an axis' variance, in most folds).")
        lines = ["Terms the model lacks (held-out variance explained, stability over folds):"]
        lines += [f"  {t.formula}" + (f" [{t.literature}]" if t.literature else "") for t in self.terms]
        return "\n".join(lines)

