"""What the diagnosis says: why each candidate is ranked where it is, the verdict sentence (what is
missing, what the data cannot tell apart, what would go unnoticed), and the candidate and
sensitivity rows of the reports (``docs/diagnosis.md``, parts 3 to 5).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from quadcore import effects as effectlib
from quadcore.effects import Parameter
from quadcore.identify.diagnosis.results import CandidateScore
from quadcore.identify.diagnosis.rows import CandidateRow
from quadcore.identify.rates import RATE_LEVEL
from quadcore.identify.settings import DEFAULT, DiagnosisSettings


def _why_not(r: CandidateRow, at_noise: dict[str, bool], settings: DiagnosisSettings) -> tuple[str, str]:
    """(status, reason) of a candidate that is not found."""
    ch = r.target
    if not r.physical:
        return "unphysical", "unphysical fit: " + "; ".join(n for n in r.notes if "outside" in n)
    if r.rate_level is not None:
        return "not_significant", _why_not_at_rate_level(r)
    if at_noise[ch]:
        return "noise_level", (f"no evidence: the held-out {ch} residual is within {settings.noise_margin:.0%} "
                               "of the sensor-noise floor")
    if r.explained_variance <= 0:
        return "no_gain", f"removes nothing from the held-out {ch} residual"
    if r.significance_sigma >= settings.min_sigma:
        return "not_significant", (f"indistinguishable from noise on held-out flights "
                                   f"(p = {r.held_out_p_value:.2g}, needs p < {r.held_out_alpha:.2g})")
    return "not_significant", f"its fit is within noise of 'no effect' ({r.significance_sigma:.1f} σ)"


def _why_not_at_rate_level(r: CandidateRow) -> str:
    """Why a timing candidate decided at the angular-rate level (``r.rate_level``) is not found."""
    if not r.significant:
        return f"its fit is within noise of 'no effect' at the angular-rate level ({r.significance_sigma:.1f} σ)"
    if r.rate_level is not None and r.rate_level.undecided:
        return f"not confirmed against no timing effect at the angular-rate level: {r.rate_level.undecided}"
    return (f"indistinguishable from no timing effect on held-out flights at the angular-rate level "
            f"(p = {r.held_out_p_value:.2g}, needs p < {r.held_out_alpha:.2g})")


def _size(r: CandidateRow) -> str:
    """How large a found candidate is and what it removes, at the level it was decided at."""
    if r.rate_level is not None:
        return (f"{r.grade}: removes {_pct(r.rate_level.explained)} of the held-out {RATE_LEVEL} residual "
                f"against no timing effect, p = {r.held_out_p_value:.2g} (found at the angular-rate level, where "
                "the closed loop biases a timing fit less than in the torque channels: docs/timing.md)")
    return (f"{r.grade}: removes {_pct(r.explained_variance)} of the held-out {r.target} residual "
            f"({_pct(r.explained_above_noise)} of what lies above the noise floor), p = {r.held_out_p_value:.2g}")


def rank_reasons(rows: list[CandidateRow], at_noise: dict[str, bool], settings: DiagnosisSettings = DEFAULT) -> None:
    """Give every candidate (best first) a ``status`` and a ``reason``: why it is ranked where
    it is (found and how large; tied with; an alternative to the best one; unphysical; not
    significant; at the noise level)."""
    top = rows[0] if rows and rows[0].found else None
    for i, r in enumerate(rows):
        if not r.found:
            r.status, r.reason = _why_not(r, at_noise, settings)
            above = [o.effect for o in rows[:i] if o.effect in r.indistinguishable_from]
            if above and r.physical:
                r.reason += f"; indistinguishable from {', '.join(above)}"
            continue
        size = _size(r)
        assert top is not None  # rows are ranked: a found candidate never follows one not found
        if r is top:
            r.status, r.reason = "found", size
        elif top.effect in r.tied_with:
            r.status = "tied"
            r.reason = (f"tied with {top.effect} (held-out flights prefer neither), which has fewer or as "
                        f"many parameters; {size}")
        elif r.explained_after_top >= settings.min_explained:
            r.status, r.reason = "found", f"also missing beyond {top.effect}; {size}"
        else:
            r.status = "alternative"
            r.reason = f"an alternative to {top.effect} (explains the same residual, less well); {size}"


def _below(p: Parameter, v: float | None) -> str:
    """``k_x_s_per_m < 0.003 s/m`` or ``|scale - 1| < 0.006``: a deviation below ``v``."""
    if v is None:
        return f"{p.name} not detectable in its range"
    name = p.name if p.default == 0 else f"|{p.name} - {p.default:g}|"
    return f"{name} < {v:.2g} {p.unit if p.unit != '1' else ''}".rstrip()


def sensitivity_text(sensitivity: Mapping[str, Mapping[str, float | None]], effects: list[str] | None = None) -> str:
    """``rotor_drag k_x_s_per_m < 0.003 s/m, ...`` for the named effects (all by default)."""
    parts = []
    for name in effects or list(sensitivity):
        if name not in effectlib.registry():
            continue
        params = {p.name: p for p in effectlib.get(name).parameters}
        vals = ", ".join(_below(params[k], v) for k, v in sensitivity.get(name, {}).items() if k in params)
        parts.append(f"{name} ({vals})")
    return "; ".join(parts)


def _other(channel: str) -> str:
    return "torque" if channel == "force" else "force"


def _one_per_tie(rows: list[CandidateRow]) -> list[CandidateRow]:
    """The first of each group of candidates the data cannot tell apart (rows best first)."""
    out: list[CandidateRow] = []
    seen: set[str] = set()
    for r in rows:
        if r.effect not in seen:
            out.append(r)
        seen |= {r.effect, *r.tied_with}
    return out


def _pct(x: float) -> str:
    return f"{max(x, 0.0):.0%}"


def _search_with(outside: Mapping[str, Any] | None) -> str:
    return (f" Search for its form with `{outside['command']}` (sparse regression over a library of terms, "
            "held out)." if outside else "")


def _outside_library(rows: list[CandidateRow], part: dict, headline: bool) -> str:
    """What the library finds in a channel is a small part of what is left there (see
    :func:`quadcore.identify.diagnosis.run._outside_library`), or nothing in the library is
    confirmed in a channel above its noise floor (``best`` None)."""
    ch, left = part["channel"], part.get("residual_to_noise_after")
    if part["best"] is None:
        return (f" Nothing in the library is confirmed in the {ch} channel on held-out flights, and the {ch} residual "
                f"stands {left:.1f} times the sensor-noise floor (RMS): what is left there is a physical effect "
                "outside the library, or one below what these flights can detect.")
    best = next(r for r in rows if r.effect == part["best"])
    return (("Mostly outside the library: the best candidate, " if headline
             else f" The {ch} residual is mostly outside the library: its best candidate, ")
            + f"{best.effect} (confirmed on held-out flights, p = {best.held_out_p_value:.2g}; {_params(best)}), "
            f"removes only {best.explained_above_noise:.0%} of what lies above the sensor-noise floor of the "
            f"held-out {ch} residual"
            + (f" ({part['explained_above_noise']:.0%} with the library's other findings)"
               if part["explained_above_noise"] > best.explained_above_noise + 0.005 else "")
            + (f", and the {ch} residual stays {left:.1f} times the noise floor (RMS) after it" if left else "")
            + ": what is missing there is mostly a physical effect the library does not have"
            + (", and a candidate that explains a small part of it is not called missing." if headline else "."))


def _params(r: CandidateRow) -> str:
    std = r.parameter_std
    return ", ".join(f"{k} = {v:.4g} ± {std.get(k, float('nan')):.2g}" for k, v in r.parameters.items())


def _nothing_found(rows: list[CandidateRow], at_noise: dict[str, bool] | None, missed: str, outside: dict | None,
                   settings: DiagnosisSettings) -> str:
    if at_noise and all(at_noise.values()):
        return ("No effect of the library explains the residual on held-out flights: none improves it "
                f"significantly, and it is within {settings.noise_margin:.0%} (RMS) of the sensor-noise floor in "
                "force and in torque; there is nothing left to explain at what these flights can resolve." + missed)
    best = rows[0] if rows else None
    tail = f" (best: {best.effect}, {best.reason})" if best else ""
    return ("No effect of the library explains the residual on held-out flights" + tail +
            ": what is left is a physical effect outside the library, or one below what these flights can "
            "detect." + _search_with(outside) + missed)


def _most_likely(top: CandidateRow, settings: DiagnosisSettings) -> str:
    """The best candidate found: how large, how sure, what it removes, its parameters."""
    grade = top.grade
    size = {"small but certain": "small but certain (weaker than the sensor noise, confirmed on held-out flights"}.get(
        grade, grade + " (confirmed on held-out flights") + f", p = {top.held_out_p_value:.2g})"
    params = _params(top)
    ch, other = top.target, _other(top.target)
    if top.rate_level is not None:
        text = (f"Most likely missing: {top.effect}: {size}: it removes {_pct(top.rate_level.explained)} of the "
                f"held-out {RATE_LEVEL} residual against no timing effect (found at the angular-rate level, where "
                f"the closed loop biases a timing fit less than in the torque channels; "
                f"{_pct(top.explained_in(ch))} of the held-out {ch} residual)")
    else:
        text = (f"Most likely missing: {top.effect}: {size}: it removes {top.explained_variance:.0%} of the held-out "
                f"{ch} residual ({_pct(top.explained_above_noise)} of what lies above the sensor-noise floor)")
    if top.acts_on == "both" and top.explained_in(other) >= settings.min_explained:
        text += f" and {top.explained_in(other):.0%} of the {other} residual"
    text += f" ({params})."
    if top.notes:
        text += " Note: " + "; ".join(top.notes) + "."
    return text


def _alike(top: CandidateRow, by_name: dict[str, CandidateRow], settings: DiagnosisSettings) -> str:
    """What the data cannot tell apart from the best candidate, and what separates the others."""
    text = ""
    ch = top.target
    tied = top.tied_with
    if tied:
        fewer = all(by_name[o].n_parameters > top.n_parameters for o in tied if o in by_name)
        text += (f" This data cannot tell it apart from {', '.join(tied)}: they explain the held-out residual equally "
                 f"well, with nearly the same predictions wherever the residual is above the sensor noise; it is "
                 f"ranked first "
                 + ("because it needs fewer parameters" if fewer else "by a margin within noise")
                 + ". Flights that separate them are needed (or knowledge of the vehicle) before choosing.")
    for o, by in top.separated_by.items():
        r = by_name.get(o)
        if r is None:
            continue
        if by == RATE_LEVEL:
            text += (f" In {ch} alone it is indistinguishable from {o}; on the held-out flights' angular rates, "
                     f"where the closed loop biases a timing fit less (docs/timing.md), {top.effect} fits "
                     f"better.")
            continue
        if by == ch:
            text += (f" Its {ch} signature resembles that of {o}, which explains less of it "
                     f"({_pct(r.explained_in(ch))} against {_pct(top.explained_in(ch))}).")
            continue
        text += f" In {ch} alone it is indistinguishable from {o}; the {by} residual tells them apart: "
        if (top.explained_in(by) >= settings.min_explained
                and top.explained_in(by) - r.explained_in(by) >= settings.tie_margin):
            text += (f"{top.effect} also removes {_pct(top.explained_in(by))} of the held-out {by} residual, "
                     f"{o} {_pct(r.explained_in(by))}.")
        else:
            text += (f"{o} cannot explain the {ch} residual without an error in {by} that is not there "
                     f"(fitted to both, it removes only {_pct(r.explained_in(ch))} of the {ch} residual).")
    return text


def _beyond_the_best(top: CandidateRow, found: list[CandidateRow], settings: DiagnosisSettings) -> str:
    """The other found candidates: also missing (they explain more once the best is in), or alternatives."""
    text = ""
    alike = set(top.indistinguishable_from) | set(top.tied_with)
    others = [r for r in found[1:] if r.effect not in alike]
    independent = _one_per_tie([r for r in others if r.explained_after_top >= settings.min_explained])
    overlapping = [r for r in others if r.explained_after_top < settings.min_explained]
    if independent:  # both shares from the same screen (least squares on the evaluated flights), not held-out
        text += (" Also missing, beyond it: "
                 + ", ".join(f"{r.effect} (removes {r.explained_after_top:.0%} of the {r.target} residual "
                             f"on top of {top.effect}, {r.explained_alone_screen:.0%} alone"
                             + (f"; indistinguishable from {', '.join(r.tied_with)}" if r.tied_with else "")
                             + ")" for r in independent[:3]) + " (both shares by one least-squares screen on the "
                 "evaluated flights).")
    if overlapping:
        text += (f" Explaining the same residual as {top.effect} (alternatives, nothing left for them once it is "
                 "in the model): "
                 + ", ".join(f"{r.effect} ({r.explained_variance:.0%})" for r in overlapping[:3])
                 + ".")
    return text


def verdict(rows: list[CandidateRow], at_noise: dict[str, bool] | None = None, sensitivity: dict | None = None,
            outside: dict | None = None, settings: DiagnosisSettings = DEFAULT) -> str:
    """One paragraph a person reads first: what is missing and how sure, or why nothing is (or
    why what the library finds is not what is missing: ``outside``, with the command that
    searches outside the library), and how small an effect these flights could have missed."""
    found = [r for r in rows if r.found]
    unseen = [r.effect for r in rows if r not in found[:1]]
    missed = (f" Smaller effects would go unnoticed on these flights ({settings.power:.0%} detection, "
              f"{settings.alpha:.0%} false alarms): " + sensitivity_text(sensitivity, unseen) + "."
              if sensitivity else "")
    parts = outside["channels"] if outside else []
    outside_text = "".join(_outside_library(rows, part, i == 0 and not found) for i, part in enumerate(parts))
    if parts:
        outside_text += _search_with(outside)
    if not found:
        return outside_text.lstrip() + missed if parts else _nothing_found(rows, at_noise, missed, outside, settings)
    top = found[0]
    by_name = {r.effect: r for r in rows}
    return (_most_likely(top, settings) + _alike(top, by_name, settings) + _beyond_the_best(top, found, settings)
            + outside_text + missed)


def candidate_summary(candidates: Iterable[CandidateScore]) -> list[dict]:
    """One row per candidate, best first, for people: its status and why it is ranked there
    (the console, the reports and the UI show the same)."""
    return [{
        "rank": i,
        "effect": c.effect,
        "status": c.status,
        "target": c.target,
        "explained": round(c.explained_variance, 3),
        "above_noise": round(c.explained_above_noise, 3),
        "held_out_p": float(f"{c.held_out_p_value:.2g}"),
        "held_out_level": c.held_out_level,  # where held_out_p was measured: target channel or angular rate
        "parameters": ", ".join(f"{k}={v:.4g}±{c.parameter_std.get(k, float('nan')):.2g}"
                                for k, v in c.parameters.items()),
        "why": c.reason,
    } for i, c in enumerate(candidates, 1)]


def sensitivity_rows(sensitivity: Mapping[str, Mapping[str, float | None]],
                     basis: Mapping[str, Any]) -> list[dict]:
    """One row per effect and parameter: the smallest deviation these flights would detect
    (``sensitivity`` and ``sensitivity_basis`` of a :class:`Diagnosis`)."""
    rows = []
    for name, params in sensitivity.items():
        known = {p.name: p for p in effectlib.get(name).parameters} if name in effectlib.registry() else {}
        cond = basis.get("conditions", {}).get(name, {})
        for k, v in params.items():
            p = known.get(k)
            rows.append({
                "effect": name, "parameter": k,
                "undetected_below": None if v is None else float(f"{v:.2g}"),
                "unit": p.unit if p and p.unit != "1" else "",
                "of": (f"|{k} - {p.default:g}|" if p and p.default != 0 else k)
                + (", at " + ", ".join(f"{c}={x:g}" for c, x in cond.items()) if cond and k not in cond else ""),
            })
    return rows
