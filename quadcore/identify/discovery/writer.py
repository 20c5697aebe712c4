"""The kept terms of a discovery as a linear effect plugin: the effect class the written modules
build (:class:`DiscoveredEffect`), its terms in C (:func:`c_term`), the parameters' names
(:func:`parameter_name`) and the module writer (:func:`write_effect`)."""

from __future__ import annotations

import functools
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadcore import effects as effectlib
from quadcore.effects.base import Effect, Parameter
from quadcore.effects.c_inputs import ExportError, feature_expression
from quadcore.effects.ccode import CCode
from quadcore.identify.discovery.results import DiscoveredTerm, Discovery
from quadcore.identify.discovery.terms import MIN_HEIGHT_M, TARGETS, evaluate
from quadcore.physics import vehicle as vehicles
from quadcore.physics.dynamics import XYZ
from quadcore.physics.vehicle import Vehicle
from quadcore.store import store


class DiscoveredEffect(Effect):
    """A linear effect whose basis is a list of discovered terms, each acting on one axis::

        f_b[a] = Σ_k c_k term_k(state)     (a force axis),   tau_b[a] likewise (a torque axis)

    Built by the modules :func:`write_effect` generates; parameters are the coefficients
    ``c_k`` (SI), default 0 (no effect)."""

    linear = True

    def __init__(self, name: str, terms: list[tuple[str, str, str, str, float]], doc: str = ""):
        """``terms``: (target, expression, parameter name, coefficient unit, bound) per term."""
        self.name = name
        self.doc = doc
        self._terms = [(TARGETS.index(t), e) for t, e, *_ in terms]
        channels = {"force" if t.startswith("f_") else "torque" for t, *_ in terms}
        self.target = "both" if len(channels) > 1 else "force" if channels == {"force"} else "torque"
        self.parameters = tuple(Parameter(p, u, 0.0, -b, b, f"{t} per unit of {e}") for t, e, p, u, b in terms)

    def basis(self, state, vehicle):
        values = evaluate([e for _, e in self._terms], state, vehicle) if state.n > 1 else \
            np.zeros((state.n, len(self._terms)))
        out = []
        for k, (axis, _) in enumerate(self._terms):
            w = np.zeros((state.n, 6))
            w[:, axis] = values[:, k]
            out.append((w[:, :3], w[:, 3:]))
        return out

    def wrench(self, state, vehicle, params):
        f, tau = np.zeros((state.n, 3)), np.zeros((state.n, 3))
        for p, (bf, bt) in zip(self.parameters, self.basis(state, vehicle)):
            f += params[p.name] * bf
            tau += params[p.name] * bt
        return f, tau

    def c_code(self, vehicle, params):
        """The terms in C for ``quadcore export-c`` when every one has an on-board form; ``None``
        when one needs a time derivative or a sensor the residual is measured with."""
        lines = []
        for p, (axis, expr) in zip(self.parameters, self._terms):
            value = c_term(expr, vehicle)
            if value is None:
                return None
            out = f"f_b_N[{axis}]" if axis < 3 else f"tau_b_Nm[{axis - 3}]"
            lines.append(f"{out} += {p.name} * ({value});")
        return CCode("\n".join(lines))


def c_term(expression: str, vehicle: Vehicle) -> str | None:
    """A term of :func:`quadcore.identify.discovery.terms.variables` as a C expression (names of
    :mod:`quadcore.export.ccode`), or None."""
    h = f"(p_w_m[2] > {MIN_HEIGHT_M!r}f ? p_w_m[2] : {MIN_HEIGHT_M!r}f)"
    special = {
        "1": "1.0f",
        "(R/4h)^2*T_N": f"QC_ROTOR_RADIUS_M * QC_ROTOR_RADIUS_M / (16 * {h} * {h}) * T_N",
        "T_N*|v_h|^2": "T_N * (v_b_mps[0] * v_b_mps[0] + v_b_mps[1] * v_b_mps[1])",
        **{f"|v_b|*v_b_{a}_mps": "qc_sqrt(v_b_mps[0] * v_b_mps[0] + v_b_mps[1] * v_b_mps[1] + v_b_mps[2] * v_b_mps[2])"
                                 f" * v_b_mps[{j}]" for j, a in enumerate(XYZ)},
        "Omega_net_radps": " + ".join(f"({float(s)!r}f * motor_radps[{i}])" for i, s in enumerate(vehicle.yaw_sign)),
    }

    def variable(name: str) -> str | None:
        pair = re.fullmatch(r"\(f_rotor_(\d+)_N-f_rotor_(\d+)_N\)", name)
        if name in special:
            return special[name]
        if pair:
            return f"(f_rotor_N[{int(pair[1]) - 1}] - f_rotor_N[{int(pair[2]) - 1}])"
        try:
            return feature_expression(name, vehicle)
        except ExportError:  # a time derivative, or the residual's own sensors
            return None

    if expression in special:
        return special[expression]
    factors = [(f.startswith("|"), variable(f.strip("|"))) for f in expression.split("*")]
    if any(c is None for _, c in factors):
        return None
    return " * ".join(f"qc_fabs({c})" if absolute else f"({c})" for absolute, c in factors)


def _slug(text: str) -> str:
    return re.sub(r"_+", "_", re.sub(r"[^0-9A-Za-z]+", "_", text)).strip("_")


def parameter_name(target: str, expression: str, unit: str) -> str:
    """``tau_res_b_x_Nm``, ``T_N*v_b_y_mps``, ``s`` -> ``tau_x__T_N_times_v_b_y_mps__s``
    (``s^2/m^2`` -> ``s2_per_m2``)."""
    axis = target.replace("_res_b_", "_").removesuffix("_Nm").removesuffix("_N")
    body = (expression.replace("*|", "_times_abs_").replace("*", "_times_").replace("(R/4h)^2", "ground_R_over_4h_sq")
            .replace("|v_h|^2", "vh_sq").replace("|v_b|", "speed_b").replace("d(", "d_").replace(")/dt", "_dt")
            .replace("-", "_minus_"))
    unit_slug = _slug(unit.replace("^", "").replace("/", " per ")) or "one"
    return f"{_slug(axis)}__{_slug(body)}__{unit_slug}"


NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class WrittenEffect:
    """What :func:`write_effect` wrote: the module, and the kept terms it left out (term ->
    why: a term with no on-board C form would make the effect impossible to export)."""

    path: Path
    left_out: dict[str, str]


def c_form_problem(expression: str, vehicle: Vehicle) -> str | None:
    """Why a term has no C form (:func:`c_term`), or None when it has one."""
    if c_term(expression, vehicle) is not None:
        return None
    if "dot" in expression or "/dt" in expression:
        return ("a zero-phase smoothed time derivative (it needs samples after the present one): "
                "a flight controller cannot compute it")
    return "built from a signal the exported model does not compute on board (the residual's own sensor)"


def write_effect(result: Discovery, path: str | Path, vehicle: Vehicle | None = None) -> WrittenEffect:
    """Write the kept terms as a linear effect plugin module named after the file's stem. Only
    terms with a C form (:func:`c_term`: built from logged variables, computable on board) go
    in, so the effect exports to C like the library's; the others are left out and named, with
    why, in the module's docstring and the result. ``vehicle``: the model's (default Crazyflie 2.1)."""
    path = Path(path)
    name = path.stem
    if path.suffix != ".py" or not NAME_RE.match(name):
        raise ValueError(f"--write-effect needs DIR/NAME.py with NAME a Python identifier, got {path}")
    if name in effectlib.builtin_names():
        raise ValueError(f"{name!r} is a built-in effect; choose another name")
    if not result.terms:
        raise ValueError("no term was kept: there is no effect to write")
    vehicle = vehicle or vehicles.load()
    left_out = {t.expression: why for t in result.terms if (why := c_form_problem(t.expression, vehicle))}
    terms = [t for t in result.terms if t.expression not in left_out]
    if not terms:
        raise ValueError("no kept term has a C form (" + "; ".join(f"{e}: {w}" for e, w in left_out.items())
                         + "): there is no exportable effect to write")
    return WrittenEffect(store.write_text(_module_text(name, result, terms, left_out), path), left_out)


def _module_text(name: str, result: Discovery, terms: list[DiscoveredTerm], left_out: dict[str, str]) -> str:
    """The source of the plugin module ``name`` holding ``terms`` (each with a C form), its docstring
    naming the kept terms ``left_out`` (term -> why)."""
    rows = []
    for t in terms:
        bound = max(100 * abs(t.coefficient), 100 * t.std, 1e-12)
        rows.append((t.target, t.expression, parameter_name(t.target, t.expression, t.unit), t.unit, bound))
    wrap = functools.partial(textwrap.fill, width=100, initial_indent="    ", subsequent_indent="        ")
    formulas = "\n".join(wrap(t.formula) for t in terms)
    literature = "\n".join(wrap(f"{t.expression}: {t.literature}") for t in terms if t.literature)
    dropped = "\n".join(wrap(f"{t.formula}: {left_out[t.expression]}") for t in result.terms
                         if t.expression in left_out)
    terms_src = "\n".join("    (\n" + "".join(f"        {v!r},\n" for v in row) + "    )," for row in rows)
    left_note = ("" if not dropped else "Kept by discover but left out here, as they have no C form for the flight "
                 f"controller:\n{dropped}\n\n")
    evaluation = textwrap.fill(f"Discovered on top of the model {'+'.join(['nominal', *result.effects_in_model])} "
                               f"({result.evaluation['mode']}; evaluated on "
                               f"{', '.join(result.evaluation['eval_flights'])}):", width=100)
    return f'''"""{name}: terms found by ``quadcore discover``, as a linear effect. List this file under
``plugins`` in the model file and ``{name}`` under ``effects``: the fit refits the coefficients.

{evaluation.strip()}

{formulas}
{("" if not literature else chr(10) + "Literature:" + chr(10) + literature + chr(10))}
{left_note}Each parameter is the coefficient of one term on one residual axis (SI; default 0 = no effect).
The terms are evaluated by quadcore.identify.discovery.terms.evaluate; every one has a C form (quadcore export-c).
"""

from quadcore.identify.discovery import DiscoveredEffect

# (target axis, term, parameter, unit of the parameter, bound on |parameter|)
TERMS = [
{terms_src}
]

EFFECT = DiscoveredEffect({name!r}, TERMS, __doc__)
'''
