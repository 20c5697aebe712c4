"""Discovery of terms the effect library lacks: sparse regression of the residual on a
library of candidate terms, cross-validated over flights.

Starting point: the residual the current model leaves (its effects fitted on the training
flights), force and torque in the body frame (:mod:`quadcore.physics.residuals`).

**The candidate library** is built from the flight's state and inputs, named with the
residual table's columns, every term with its unit (:func:`library`):

* each variable alone (body velocity, body rate, position, collective and per-rotor thrust,
  motor speeds, battery voltage, a constant);
* products of pairs and squares of the core variables (``v_b``, ``omega_b``, ``T_N``,
  ``p_w_z_m``; ``vbat_V`` only with ``T_N``: the voltage barely changes, so ``x vbat`` would
  duplicate ``x``), signed squares ``x|x|`` of velocity and rate, and the airspeed-norm
  quadratic drag ``|v_b| v_b,a``;
* physically motivated combinations: per-rotor thrust differences, time derivatives of motor
  speed, rotor thrust and rotor torque (a delay or lag ``Δ`` turns ``f(t-Δ)`` into
  ``f - Δ df/dt``), the net rotor
  speed ``Σ s_i Ω_i`` and its gyroscopic products with the body rate (rotor inertia), the
  ground-effect term ``(R/4h)² T`` (Cheeseman & Bennett), ``T |v_h|²`` (translational lift).

**The tautology guard.** A residual is measured minus modelled. A term built from either
side of the *same* residual reconstructs it without any physics (the gyro derivative
``omega_dot_b`` rebuilds the torque residual exactly; the accelerometer the force
residual). So the torque library never holds ``omega_dot_b``, the force library never holds
``sf_b``, and neither holds the modelled side of its own axis: ``T_N`` and the per-rotor
map thrusts for ``f_z``, the per-rotor map thrusts and their differences for the torques
(the rotor torque is a combination of them). This matters more than it seems: in closed
loop the attitude controller holds off any slow disturbance torque with rotor-thrust
differences, so the modelled rotor torque *is* minus the disturbance at low frequency, and
a library holding it "explains" every disturbance as "the model's torque does not act"
(on the 19 real flights: -0.9 × the modelled torque, hiding a flapping moment ``∝ T v``).
As a second line, when the terms kept for an axis still rebuild a multiple of its modelled
force or torque, the result says so: the model's own term is mis-scaled or cancelled by
something, which is not a new mechanism by itself. Per-rotor thrusts stay in the
horizontal force library, motor speeds (a separate measurement) and time derivatives of
the map thrusts (timing) in every library.

**Every term goes through the residual's own filter** (force: the smoother; torque: the
gyro derivative's filter, :func:`quadcore.identify.fitting.smoothed_wrench`), so a coefficient found
here is exactly the parameter of a linear effect with that term as its basis
(:func:`write_effect`).

**Selection** per residual axis, from Gram matrices accumulated flight by flight (every
``stride``-th usable sample): orthogonal matching pursuit (``sklearn.linear_model.
orthogonal_mp_gram``, the greedy member of the LARS family) on each fold of a
cross-validation grouped by flight, scored on the fold's flights. The number of terms is
where one more term adds less than ``MIN_GAIN`` of the held-out variance. A term is kept
when it is selected in most folds (stability selection) and, refitted with the other kept
terms, still adds ``MIN_GAIN`` of the held-out variance. **Competing forms**: the forms of a
velocity term (``v``, ``T v``, ``v|v|``, ``|v_b| v``: :data:`VELOCITY_FORMS`) share one slot's
votes in the stability selection, and the slot keeps the form with the best mean rank of
held-out error over the folds, beside the other kept terms (:func:`_prefer_forms`; chosen on the
folds, never on a holdout); every rival is reported with its held-out share, and the mechanism
is named only when the kept form beats each rival in most folds (else "form undecided").
An axis whose residual is within
``evidence.NOISE_MARGIN`` (RMS) of the sensor-noise floor gets no terms, the same
margin the diagnosis uses.

**Reported** per term: the formula with its SI coefficient and grouped-jackknife standard
error, the held-out variance it explains (in the order of selection, so the shares add up),
its stability, the library effects whose basis it matches, the mechanism's name in the
literature where there is one, and the candidates it is collinear with (which the data
cannot separate from it).
"""

from __future__ import annotations

import functools
import re
import textwrap
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl
from sklearn.linear_model import orthogonal_mp_gram

from quadcore import effects as effectlib
from quadcore.effects.base import Effect, Parameter
from quadcore.identify import evidence, fitting, library_stats, sessions as sessionlib, sufficient
from quadcore.identify.model import ModelSpec
from quadcore.physics import dynamics, signals
from quadcore.physics.dynamics import XYZ, FlightState
from quadcore.physics.vehicle import Vehicle
from quadcore.store import store

TARGETS = tuple([f"f_res_b_{a}_N" for a in XYZ] + [f"tau_res_b_{a}_Nm" for a in XYZ])
MIN_GAIN = 0.02  # a term must add this share of the held-out variance of its axis
MIN_STABILITY = 0.6  # selected in at least this share of the folds ("most folds")
MAX_TERMS = 8  # per axis
COLLINEAR = 0.95  # |cosine| between two terms above which the data cannot separate them
MATCH = 0.9  # share of a term's energy in an effect's basis above which the term "is" that effect
MIN_HEIGHT_M = 0.02  # the ground-effect term is evaluated at no less than this height

# --- units, as exponents of (kg, m, s, rad, V) ------------------------------------------

_BASE = ("kg", "m", "s", "rad", "V")
UNIT = {
    "1": (0, 0, 0, 0, 0), "N": (1, 1, -2, 0, 0), "N m": (1, 2, -2, 0, 0), "m": (0, 1, 0, 0, 0),
    "m/s": (0, 1, -1, 0, 0), "m/s^2": (0, 1, -2, 0, 0), "rad/s": (0, 0, -1, 1, 0), "rad/s^2": (0, 0, -2, 1, 0),
    "V": (0, 0, 0, 0, 1), "N/s": (1, 1, -3, 0, 0),
}


def _mul(a, b, sign=1):
    return tuple(x + sign * y for x, y in zip(a, b))


def unit_text(exps) -> str:
    """``(1, 1, -2, 0, 0)`` -> ``"N"``; other combinations as ``kg m^2/(s rad)``."""
    for name, e in UNIT.items():
        if tuple(exps) == e and name != "1":
            return name
    num = [f"{b}^{e}" if e > 1 else b for b, e in zip(_BASE, exps) if e > 0]
    den = [f"{b}^{-e}" if e < -1 else b for b, e in zip(_BASE, exps) if e < 0]
    if not num and not den:
        return "1"
    top = " ".join(num) or "1"
    return top if not den else f"{top}/{den[0]}" if len(den) == 1 else f"{top}/({' '.join(den)})"


# --- the candidate library ----------------------------------------------------------------

@dataclass(frozen=True)
class Term:
    """One candidate: its expression (factors joined by ``*``; ``|x|`` is an absolute value),
    the residual-table columns it is built from, its unit, and where it may be used
    (``force``, ``torque`` or ``both``)."""

    expression: str
    variables: tuple[str, ...]
    unit: tuple[int, ...]
    channel: str = "both"


@dataclass(frozen=True)
class Variable:
    """A signal a term is built from: values over the flight, unit, source columns."""

    values: np.ndarray
    unit: tuple[int, ...]
    sources: tuple[str, ...]
    channel: str = "both"


CORE = ("v_b_x_mps", "v_b_y_mps", "v_b_z_mps", "omega_b_x_radps", "omega_b_y_radps", "omega_b_z_radps",
        "T_N", "p_w_z_m", "vbat_V")
SIGNED_SQUARES = CORE[:6]


def variables(state: FlightState, vehicle: Vehicle) -> dict[str, Variable]:
    """Every signal terms are built from, by name. Derived ones name their source columns."""
    out: dict[str, Variable] = {"1": Variable(np.ones(state.n), UNIT["1"], ())}

    def put(name, values, unit, sources=None, channel="both"):
        out[name] = Variable(np.asarray(values, dtype=float), UNIT[unit], tuple(sources or (name,)), channel)

    for j, a in enumerate(XYZ):
        put(f"v_b_{a}_mps", state.v_b_mps[:, j], "m/s")
        put(f"omega_b_{a}_radps", state.omega_b_radps[:, j], "rad/s")
        put(f"p_w_{a}_m", state.p_w_m[:, j], "m")
    T = state.f_rotor_N.sum(axis=1)
    put("T_N", T, "N")
    put("vbat_V", state.vbat_V, "V")
    # the measured side of one residual is a fair variable for the other one only
    omega_dot = signals.derivative(state.omega_b_radps, state.t_s)
    for j, a in enumerate(XYZ):
        put(f"omega_dot_b_{a}_radps2", omega_dot[:, j], "rad/s^2", channel="force")
        put(f"sf_b_{a}_mps2", state.sf_b_mps2[:, j], "m/s^2", channel="torque")
    n_rot = state.f_rotor_N.shape[1]
    for i in range(n_rot):
        put(f"f_rotor_{i + 1}_N", state.f_rotor_N[:, i], "N")
    for i in range(n_rot):
        for k in range(i + 1, n_rot):
            put(f"(f_rotor_{i + 1}_N-f_rotor_{k + 1}_N)", state.f_rotor_N[:, i] - state.f_rotor_N[:, k], "N",
                (f"f_rotor_{i + 1}_N", f"f_rotor_{k + 1}_N"))
    f_dot = signals.derivative(state.f_rotor_N, state.t_s)
    for i in range(n_rot):
        put(f"d(f_rotor_{i + 1}_N)/dt", f_dot[:, i], "N/s", (f"f_rotor_{i + 1}_N",))
    put("d(T_N)/dt", f_dot.sum(axis=1), "N/s", ("T_N",))
    _, tau_dot = dynamics.wrench_from_thrusts(vehicle, f_dot)  # the modelled rotor torque's rate: timing
    rotors = tuple(f"f_rotor_{i + 1}_N" for i in range(n_rot))
    for j, a in enumerate(XYZ):
        out[f"d(tau_rotor_{a}_Nm)/dt"] = Variable(tau_dot[:, j], _mul(UNIT["N m"], (0, 0, -1, 0, 0)), rotors, "torque")
    h = np.maximum(state.p_w_m[:, 2], MIN_HEIGHT_M)
    put("(R/4h)^2*T_N", (vehicle.rotor_radius_m / (4 * h)) ** 2 * T, "N", ("p_w_z_m", "T_N"))
    put("T_N*|v_h|^2", T * (state.v_b_mps[:, 0] ** 2 + state.v_b_mps[:, 1] ** 2), "N",
        ("T_N", "v_b_x_mps", "v_b_y_mps"))
    out["T_N*|v_h|^2"] = Variable(out["T_N*|v_h|^2"].values, _mul(UNIT["N"], _mul(UNIT["m/s"], UNIT["m/s"])),
                                   out["T_N*|v_h|^2"].sources)
    speed = np.linalg.norm(state.v_b_mps, axis=1)  # quadratic drag grows with the airspeed times each component
    velocity = tuple(f"v_b_{a}_mps" for a in XYZ)
    for j, a in enumerate(XYZ):
        out[f"|v_b|*v_b_{a}_mps"] = Variable(speed * state.v_b_mps[:, j], _mul(UNIT["m/s"], UNIT["m/s"]), velocity)
    if state.motor_radps is not None:
        motors = tuple(f"motor_{i + 1}_radps" for i in range(n_rot))
        for i, name in enumerate(motors):
            put(name, state.motor_radps[:, i], "rad/s")
        m_dot = signals.derivative(state.motor_radps, state.t_s)
        for i, name in enumerate(motors):
            put(f"d({name})/dt", m_dot[:, i], "rad/s^2", (name,))
        sign = np.asarray(vehicle.yaw_sign, dtype=float)
        put("Omega_net_radps", state.motor_radps @ sign, "rad/s", motors)
        put("d(Omega_net_radps)/dt", m_dot @ sign, "rad/s^2", motors)
    return out


def _literature(expr: str, channel: str = "force") -> str:
    """The mechanism's name in the multirotor literature, where a term has an obvious one
    (``channel``: where the term acts, force or torque)."""
    torque_rules = [
        (r"^(T_N\*)?v_b_[xy]_mps$", ("a moment growing with the horizontal velocity: the blade-flapping hub moment "
                                     "(Mahony, Kumar & Corke 2012), or rotor drag acting above the centre of mass "
                                     "(r × F); the two have the same form")),
        (r"^(1|T_N|T_N\*T_N)$", ("a trim torque growing with thrust: centre-of-mass offset (r × thrust) in roll and "
                                "pitch; in yaw, rotors whose torque-to-thrust ratios differ, or tilted motors")),
    ]
    rules = (torque_rules if channel == "torque" else []) + [
        (r"^T_N\*v_b_[xy]_mps$", ("rotor drag / blade flapping (Mahony, Kumar & Corke 2012; Faessler et al. 2018): "
                                 "in force a drag -kTv, in torque the flapping hub moment")),
        (r"^v_b_[xyz]_mps$", "linear airframe drag (or rotor drag at constant thrust)"),
        (r"^v_b_([xyz])_mps\*\|v_b_\1_mps\|$|^\|v_b\|\*v_b_[xyz]_mps$", "parasitic (quadratic) airframe drag"),
        (r"^\(R/4h\)\^2\*T_N$", "ground effect (Cheeseman & Bennett 1955)"),
        (r"^T_N\*\|v_h\|\^2$", "translational lift (momentum theory)"),
        (r"^v_b_([xy])_mps\*v_b_\1_mps$", "a force growing with the horizontal speed squared: translational lift "
                                          "along z (momentum theory), quadratic drag in the horizontal"),
        (r"^(T_N\*)?v_b_z_mps$|^T_N\*v_b_z_mps$", "axial inflow: thrust changes with climb speed (momentum theory)"),
        (r"^d\(motor_\d_radps\)/dt$|^d\(Omega_net_radps\)/dt$",
         "rotor inertia: reaction torque of accelerating rotors"),
        (r"^omega_b_[xyz]_radps\*Omega_net_radps$", "gyroscopic torque of the spinning rotors"),
        (r"^d\((f_rotor_\d_N|T_N|tau_rotor_[xyz]_Nm)\)/dt$",
         "timing: a delay or lag between the logged command and the thrust (f(t-Δ) ≈ f - Δ df/dt)"),
        (r"^f_rotor_\d_N$|^\(f_rotor_\d_N-f_rotor_\d_N\)$", "per-rotor thrust-map error (rotor imbalance)"),
        (r"^omega_b_([xyz])_radps$", "rotor / aerodynamic damping of the body rate"),
        (r"^omega_b_[xyz]_radps\*omega_b_[xyz]_radps$", "inertia-tensor error (Euler's ω × Jω term)"),
        (r"^T_N$", "centre-of-mass offset (r × thrust) in torque; thrust-map scale or payload in force"),
        (r"^omega_dot_b_[xyz]_radps2$", "centre-of-mass offset (tangential acceleration α × r)"),
        (r"vbat_V", "battery-voltage dependence of the thrust map"),
        (r"^1$", "a constant bias: sensor bias, or a fixed disturbance"),
    ]
    forms = {expr, "*".join(reversed(expr.split("*")))}  # products match in either order
    for pattern, name in rules:
        if any(re.search(pattern, f) for f in forms):
            return name
    return ""


def library(vars_: dict[str, Variable]) -> list[Term]:
    """The candidate terms over the given variables (see the module docstring)."""
    terms = [Term(name, v.sources, v.unit, v.channel) for name, v in vars_.items()]
    core = [c for c in CORE if c in vars_]
    for i, a in enumerate(core):
        for b in core[i:]:
            if "vbat_V" in (a, b) and "T_N" not in (a, b):
                continue  # a nearly constant voltage times x duplicates x; T vbat is the map's voltage error
            expr = f"{a}*{b}"
            terms.append(Term(expr, tuple(dict.fromkeys((a, b))), _mul(vars_[a].unit, vars_[b].unit)))
    for a in SIGNED_SQUARES:
        expr = f"{a}*|{a}|"
        terms.append(Term(expr, (a,), _mul(vars_[a].unit, vars_[a].unit)))
    if "Omega_net_radps" in vars_:
        for a in ("x", "y"):
            expr = f"omega_b_{a}_radps*Omega_net_radps"
            terms.append(Term(expr, (f"omega_b_{a}_radps", *vars_["Omega_net_radps"].sources),
                              _mul(UNIT["rad/s"], UNIT["rad/s"]), "torque"))
    return terms


def _factor(vars_: dict[str, Variable], text: str) -> np.ndarray:
    if text.startswith("|") and text.endswith("|"):
        return np.abs(vars_[text[1:-1]].values)
    return vars_[text].values


def evaluate(expressions: list[str], state: FlightState, vehicle: Vehicle) -> np.ndarray:
    """(n, k) raw values of the given term expressions over a flight."""
    vars_ = variables(state, vehicle)
    out = np.empty((state.n, len(expressions)))
    for k, expr in enumerate(expressions):
        if expr in vars_:
            out[:, k] = vars_[expr].values
            continue
        factors = expr.split("*")
        if any(f.strip("|") not in vars_ for f in factors):
            raise KeyError(f"unknown term {expr!r}: its variables are not in this flight")
        out[:, k] = np.prod([_factor(vars_, f) for f in factors], axis=0)
    return out


def excluded(term: Term, target: str) -> bool:
    """True when ``term`` holds an ingredient of ``target``'s own residual (see the module
    docstring): the measured side, or the modelled side of the same axis."""
    channel = "force" if target.startswith("f_") else "torque"
    if term.channel not in ("both", channel):
        return True
    per_rotor = re.fullmatch(r"f_rotor_\d+_N", term.expression) is not None
    if channel == "torque":  # the rotor torque is a combination of the map's rotor thrusts
        return per_rotor or re.fullmatch(r"\(f_rotor_\d+_N-f_rotor_\d+_N\)", term.expression) is not None
    return target == "f_res_b_z_N" and (term.expression == "T_N" or per_rotor)


# --- results --------------------------------------------------------------------------------

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

    def to_dict(self) -> dict:
        return {
            "terms": [t.to_dict() for t in self.terms],
            "axes": [{"target": a.target, "explained_variance": a.explained_variance,
                      "at_noise_level": a.at_noise_level, "notes": list(a.notes)} for a in self.axes],
            "baseline": self.baseline, "after": self.after, "noise_floor": self.noise_floor,
            "evaluation": self.evaluation, "effects_in_model": list(self.effects_in_model),
            "library_size": self.library_size,
        }

    @property
    def summary(self) -> str:
        """A paragraph a person reads first."""
        if not self.terms:
            return ("No term of the candidate library explains a stable share of the held-out residual "
                    f"(at least {MIN_GAIN:.0%} of an axis' variance, in most folds).")
        lines = ["Terms the model lacks (held-out variance explained, stability over folds):"]
        lines += [f"  {t.formula}" + (f" [{t.literature}]" if t.literature else "") for t in self.terms]
        return "\n".join(lines)


# --- the computation -----------------------------------------------------------------------

@dataclass
class _Columns:
    """The columns accumulated in the Gram matrices and where each block starts."""

    terms: list[Term]
    force: list[int]  # indices into terms usable for force targets
    torque: list[int]
    effect_cols: dict[tuple[str, int], list[int]]  # (effect, axis) -> Gram columns
    n_total: int

    def term_col(self, k: int, axis: int) -> int:
        """Gram column of term ``k`` filtered for ``axis`` (0-2 force, 3-5 torque)."""
        return self.force.index(k) if axis < 3 else len(self.force) + self.torque.index(k)

    @property
    def target0(self) -> int:
        return len(self.force) + len(self.torque)

    @property
    def model0(self) -> int:
        return self.target0 + 6

    def labels(self) -> tuple[str, ...]:
        """A name per Gram column: ``force:<term>``, ``torque:<term>``, ``y:<axis>`` (the
        residual), ``model:<axis>``, ``<effect>:<axis>:<parameter>``."""
        out = [f"force:{self.terms[k].expression}" for k in self.force]
        out += [f"torque:{self.terms[k].expression}" for k in self.torque]
        out += [f"y:{a}" for a in range(6)] + [f"model:{a}" for a in range(6)]
        out += [f"{name}:{axis}:{p}" for (name, axis), cs in self.effect_cols.items() for p in range(len(cs))]
        return tuple(out)


def _effect_basis(effect: Effect, state: FlightState, vehicle: Vehicle) -> list[tuple[np.ndarray, np.ndarray]]:
    """Its basis (linear effects) or its linearisation about 'no effect' (others)."""
    if effect.linear:
        return effect.basis(state, vehicle)
    out = []
    for p in effect.parameters:
        params = effect.defaults()
        h = 0.01 * (p.upper - p.lower) if np.isfinite(p.upper - p.lower) else 1e-3
        params[p.name] += h if p.default + h <= p.upper else -h
        f, tau = effect.wrench(state, vehicle, params)
        out.append((f / h, tau / h))
    return out


def _flight_blocks(fd: fitting.FlightData, resid: np.ndarray, cols: _Columns, fx_effects, vehicle) -> list:
    """The Gram columns of one flight on all its samples, in blocks: filtered terms (force,
    torque), residual targets, modelled sides, the effects' bases per axis."""
    s = fd.state
    raw = evaluate([t.expression for t in cols.terms], s, vehicle)
    F = signals.smooth(raw[:, cols.force])
    Tq = signals.matched_to_derivative(raw[:, cols.torque], s.t_s, s.thrust_hold_s)
    T_N, tau_rotor = dynamics.wrench_from_thrusts(vehicle, s.f_rotor_N)
    f_model = np.zeros((s.n, 3))
    f_model[:, 2] = T_N
    model = fitting.smoothed_wrench(f_model, tau_rotor, s)
    blocks = [F, Tq, resid, model]
    for e in fx_effects:
        cached = fd.basis_if_cached(e) if e.linear else None  # the same columns: smoothed_wrench of e.basis
        if cached is not None:
            blocks += [cached[:, axis, :] for axis in range(6)]
            continue
        try:
            basis = [fitting.smoothed_wrench(f, t, s) for f, t in _effect_basis(e, s, vehicle)]
        # a user's effect failing here: not matched
        except (ValueError, TypeError, KeyError, IndexError, ArithmeticError):
            basis = [np.zeros((s.n, 6)) for _ in e.parameters]
        blocks += [np.stack([b[:, axis] for b in basis], axis=1) for axis in range(6)]
    return blocks


def _gram(blocks: list, rows: np.ndarray) -> np.ndarray:
    Z = np.concatenate([b[rows] for b in blocks], axis=1)
    with sufficient.one_blas_thread():
        return Z.T @ Z


def _flight_gram(fd: fitting.FlightData, resid: np.ndarray, cols: _Columns, fx_effects, vehicle, stride: int):
    """Gram matrix of one flight's filtered terms, residual targets, modelled sides and the
    effects' bases, on every ``stride``-th usable sample."""
    return _gram(_flight_blocks(fd, resid, cols, fx_effects, vehicle), np.flatnonzero(fd.mask)[::stride])


def flight_grams(fd: fitting.FlightData, resid: np.ndarray, cols: _Columns, fx_effects, vehicle,
                 stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(the Gram matrix the selection uses: every ``stride``-th usable sample, the same matrix
    on every usable sample: the held-out RMSE's) of one flight (see :mod:`quadcore.identify.library_stats`).
    The second holds only the products within the force columns and within the torque columns
    (:func:`channel_groups`; zero between them): a force axis' RMSE never takes a torque term."""
    blocks = _flight_blocks(fd, resid, cols, fx_effects, vehicle)
    rows = np.flatnonzero(fd.mask)
    Z = np.concatenate([b[rows] for b in blocks], axis=1)
    H = np.zeros((cols.n_total, cols.n_total))
    for group in channel_groups(cols.labels()):
        Zg = Z[:, group]
        with sufficient.one_blas_thread():
            H[np.ix_(group, group)] = Zg.T @ Zg
    return _gram(blocks, rows[::stride]), H


def channel_groups(labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the columns of the force axes (force terms, residual, modelled side and
    effects' bases on x, y, z of the force) and of the torque axes, from their names
    (:meth:`_Columns.labels`)."""
    def axis(label: str) -> int:
        kind, _, rest = label.partition(":")
        if kind in ("force", "torque"):
            return 0 if kind == "force" else 3
        return int(rest if kind in ("y", "model") else rest.split(":")[0])

    axes = np.array([axis(label) for label in labels])
    return np.flatnonzero(axes < 3), np.flatnonzero(axes >= 3)


def _sse(G: np.ndarray, cols: list[int], y: int, beta: np.ndarray) -> float:
    """Residual sum of squares of ``y - X[:, cols] beta`` from a Gram matrix."""
    if not cols:
        return float(G[y, y])
    return float(G[y, y] - 2 * beta @ G[cols, y] + beta @ G[np.ix_(cols, cols)] @ beta)


def _ols(G: np.ndarray, cols: list[int], y: int) -> np.ndarray:
    if not cols:
        return np.zeros(0)
    return np.linalg.lstsq(G[np.ix_(cols, cols)], G[cols, y], rcond=1e-12)[0]


def _omp_path(G: np.ndarray, cols: list[int], y: int, n_max: int) -> list[list[int]]:
    """Supports of the greedy path (1, 2, ... terms), columns normalised for the selection."""
    sub = G[np.ix_(cols, cols)]
    d = np.sqrt(np.maximum(np.diag(sub), 1e-300))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "ended prematurely": fewer independent columns than asked
        path = orthogonal_mp_gram(sub / np.outer(d, d), G[cols, y] / d, n_nonzero_coefs=n_max, return_path=True)
    path = path.reshape(len(cols), -1)
    supports, seen = [], []
    for s in range(path.shape[1]):
        new = [cols[i] for i in np.flatnonzero(path[:, s]) if cols[i] not in seen]
        seen += new
        supports.append(list(seen))
    return supports


def _cv_ev(grams: list[tuple[np.ndarray, np.ndarray]], cols: list[int], y: int) -> float:
    """Held-out share of variance over folds: fit on each (train, test) Gram pair's train."""
    sse = sum(_sse(te, cols, y, _ols(tr, cols, y)) for tr, te in grams)
    tot = sum(te[y, y] for _, te in grams)
    return 1.0 - sse / tot if tot > 0 else 0.0


def _select(fold_grams, G_train, candidates: list[int], y: int, slot_of: Mapping[int, object] | None = None
            ) -> tuple[list[int], dict[int, int]]:
    """Stable terms of one axis and how many folds selected each. Rival forms of one term
    (``slot_of`` maps a column to its slot: :func:`form_family`) share their folds' votes: a
    slot is stable when most folds select one of its forms, and stands for them with its most
    selected form (which :func:`_prefer_forms` then weighs against the others)."""
    paths = [_omp_path(tr, candidates, y, MAX_TERMS) for tr, _ in fold_grams]
    n_steps = min(len(p) for p in paths)
    ev = [0.0]
    for s in range(n_steps):  # held-out variance with s+1 terms, each fold its own path
        sse = sum(_sse(te, p[s], y, _ols(tr, p[s], y)) for (tr, te), p in zip(fold_grams, paths))
        tot = sum(te[y, y] for _, te in fold_grams)
        ev.append(1.0 - sse / tot)
    k = 0
    while k < n_steps and ev[k + 1] - ev[k] >= MIN_GAIN:
        k += 1
    counts: dict[int, int] = {}
    slots: dict[object, set[int]] = {}  # slot -> the folds that selected one of its forms
    slot = slot_of or {}
    for f, p in enumerate(paths):
        for c in (p[k - 1] if k else []):
            counts[c] = counts.get(c, 0) + 1
            slots.setdefault(slot.get(c, c), set()).add(f)
    stable = []
    for key, folds in slots.items():
        if len(folds) >= MIN_STABILITY * len(fold_grams):
            members = [c for c in counts if slot.get(c, c) == key]
            lead = max(members, key=lambda c: (counts[c], -c))
            counts[lead] = len(folds)
            stable.append(lead)
    return _order_and_prune(fold_grams, stable, y), counts


def _order_and_prune(fold_grams, stable: list[int], y: int) -> list[int]:
    """Greedy order of the stable terms by held-out gain; drop those adding < MIN_GAIN."""
    chosen: list[int] = []
    left = list(stable)
    base = 0.0
    while left:
        gains = [(_cv_ev(fold_grams, chosen + [c], y) - base, c) for c in left]
        gain, best = max(gains)
        if gain < MIN_GAIN:
            break
        chosen.append(best)
        left.remove(best)
        base += gain
    return chosen


# The forms a velocity term takes on one slot of an axis: linear drag, rotor drag (-k T v),
# per-axis and airspeed-norm quadratic drag. They are nearly collinear on most flights, so the
# greedy path's first pick need not be the form the held-out flights prefer.
VELOCITY_FORMS = ("v_b_{a}_mps", "v_b_{a}_mps*T_N", "v_b_{a}_mps*|v_b_{a}_mps|", "|v_b|*v_b_{a}_mps")


def form_family(expression: str) -> tuple[str, ...]:
    """The rival forms of a term (itself among them), or () for a term without rivals."""
    for a in XYZ:
        family = tuple(f.format(a=a) for f in VELOCITY_FORMS)
        if expression in family:
            return family
    return ()


def _set_sse(pairs, cols: list[int], y: int) -> np.ndarray:
    """Held-out sum of squares per (training sum, held-out sum) pair."""
    return np.array([_sse(te, cols, y, _ols(tr, cols, y)) for tr, te in pairs])


def _prefer_forms(fold_grams, scored_on, chosen: list[int], y: int, col_term: dict[int, Term]
                  ) -> tuple[list[int], dict[int, tuple[Form, ...]]]:
    """Each kept term with rival forms (:func:`form_family`) replaced by the form the
    cross-validation folds prefer: with the axis' other kept terms beside it, the best mean rank
    of its held-out error among the rivals over the folds (each fold one vote, so one fold's
    large variance does not decide), then the least error summed over them. Chosen where the
    terms are selected, so a holdout stays unseen; every rival scored on ``scored_on``, the
    sets the kept terms' shares are scored on."""
    column_of = {t.expression: c for c, t in col_term.items()}
    tot = sum(te[y, y] for _, te in scored_on)
    out, forms = list(chosen), {}
    for i, c in enumerate(chosen):
        rivals = [column_of[e] for e in form_family(col_term[c].expression)
                  if e in column_of and (column_of[e] == c or column_of[e] not in out)]
        if len(rivals) < 2:
            continue
        sse = {r: _set_sse(fold_grams, out[:i] + [r] + out[i + 1:], y) for r in rivals}
        ranks = np.argsort(np.argsort(np.array([sse[r] for r in rivals]), axis=0), axis=0).mean(axis=1)
        best = min(rivals, key=lambda r: (float(ranks[rivals.index(r)]), float(sse[r].sum()), r != c))
        out[i] = best
        held = {r: float(_set_sse(scored_on, out[:i] + [r] + out[i + 1:], y).sum()) for r in rivals}
        scored = [Form(col_term[r].expression, 1.0 - held[r] / tot if tot > 0 else 0.0,
                       int(np.sum(sse[r] < sse[best])), len(fold_grams)) for r in rivals]
        forms[best] = tuple(sorted(scored, key=lambda f: (f.expression != col_term[best].expression,
                                                          -f.explained_variance)))
    return out, forms


def _form_label(expression: str, forms: tuple[Form, ...], channel: str) -> str:
    """The mechanism's name when the kept form (listed first) beats each rival in most folds
    (``MIN_STABILITY``, as a term must be kept in most folds); else the rival forms with their
    held-out scores."""
    scores = ", ".join(f"{f.expression} {f.explained_variance:.1%}" for f in forms)
    decided = all(f.sets - f.better_in >= MIN_STABILITY * f.sets for f in forms if f.expression != expression)
    if not forms or decided:
        name = _literature(expression, channel)
        return f"{name}; forms held out: {scores}" if forms and name else name
    return (f"form undecided: held out {scores} of the variance; the kept form is not the better one in most "
            "folds, so no mechanism is named")


@dataclass(frozen=True)
class _Library:
    """The candidate library (its terms and their Gram columns) and the flights' Gram matrices
    accumulated flight by flight, with each flight's usable samples and sensor noise."""

    terms: list[Term]
    cols: _Columns
    sums: _GramSums
    samples: dict[str, int]
    noise_of: dict[str, np.ndarray]
    full: _GramSums | None = None  # from statistics: the same sums on every usable sample
    y0_squares: dict[str, np.ndarray] | None = None  # from statistics, a model without effects: Σ y0² per flight


def _accumulate(ids: list[str], flight, decoded: Mapping[str, pl.DataFrame], spec: ModelSpec,
                fx_effects: list[Effect], folds: list[list[str]], holdout: list[str], stride: int, log) -> _Library:
    """Each flight's rows (``flight(f)``: its rows and residual) turned into its Gram matrix and
    dropped; the library is built from the first flight's variables."""
    vehicle = spec.vehicle
    # motor terms only when every flight has them (read off the columns, before any Gram matrix)
    motors = all(_logs_motors(decoded[f], spec.vehicle_for(f)) for f in ids)
    sums = _GramSums(folds, holdout)
    samples: dict[str, int] = {}
    noise_of: dict[str, np.ndarray] = {}
    for f in ids:
        fd, r = flight(f)
        if f == ids[0]:
            terms = _library_of(variables(fd.state, vehicle), motors)
            cols = library_columns(terms, fx_effects)
            log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; "
                f"accumulating on {len(ids)} flights")
        sums.add(f, _flight_gram(fd, r, cols, fx_effects, vehicle, stride))
        samples[f], noise_of[f] = int(fd.mask.sum()), fd.noise
    return _Library(terms, cols, sums, samples, noise_of)


def _library_of(vars_: dict[str, Variable], motors: bool) -> list[Term]:
    """The candidate library of a flight's variables; without those read off the motors unless
    every flight logs them (``motors``)."""
    if not motors:
        vars_ = {k: v for k, v in vars_.items() if not any(s.startswith("motor_") for s in v.sources)}
    return library(vars_)


def _library_terms(first: library_stats.FlightLibrary, motors: bool) -> list[Term]:
    """The candidate library from a flight's recorded variables (as :func:`_accumulate` builds it
    from its rows)."""
    return _library_of({name: Variable(np.empty(0), unit, sources, channel)
                        for name, unit, sources, channel in first.variables}, motors)


def _residual_transform(cols: _Columns, model, vehicle: Vehicle) -> np.ndarray:
    """``T`` with ``z T`` the design whose residual columns are ``y0 - Σ θ B`` (the fitted
    model's linear effects ``model`` subtracted; see :mod:`quadcore.identify.library_stats`)."""
    T = np.eye(cols.n_total)
    for term in model.terms:
        e = effectlib.get(term.name)
        theta = np.asarray(e.to_linear({**e.defaults(), **term.params}, vehicle), dtype=float)
        for axis in range(6):
            T[cols.effect_cols[(e.name, axis)], cols.target0 + axis] -= theta
    return T


def _combined(ids: list[str], decoded: Mapping[str, pl.DataFrame], spec: ModelSpec, fx_effects: list[Effect],
              folds: list[list[str]], holdout: list[str], train: list[str], stored, stats, sessions, log) -> _Library:
    """:func:`_accumulate` from the flights' discovery statistics (:mod:`quadcore.identify.library_stats`):
    the stored ones, else computed from the flight's rows; a model's linear effects fitted from
    the sufficient statistics (``stats``) and subtracted from the sums (:func:`_residual_transform`)."""
    found = {f: stored(f) for f in ids}
    motors = all(found[f].logs_motors if found[f] is not None else _logs_motors(decoded[f], spec.vehicle_for(f))
                 for f in ids)
    first = found[ids[0]] or library_stats.compute(spec, ids[0], decoded[ids[0]])
    terms = _library_terms(first, motors)
    cols = library_columns(terms, fx_effects)
    labels = cols.labels()
    missing = [f for f in ids if found[f] is None]
    log(f"candidate library: {len(cols.force)} force terms, {len(cols.torque)} torque terms; combining "
        f"{len(ids) - len(missing)} flights' stored statistics" + (f", computing {len(missing)}" if missing else ""))
    sums, full = _GramSums(folds, holdout), _GramSums(folds, holdout, scored_only=True)
    samples: dict[str, int] = {}
    noise_of: dict[str, np.ndarray] = {}
    y0_squares: dict[str, np.ndarray] = {}
    for f in ids:
        G, H, lib = _flight_statistics(f, found[f] if f != ids[0] else first, labels, spec, decoded, cols, fx_effects)
        sums.add(f, G)
        full.add(f, H)
        samples[f], noise_of[f], y0_squares[f] = lib.samples, lib.noise, lib.y0_squares
    if spec.effects:
        model = fitting.fit_model(spec, decoded, train, sessions, log, stats)
        T = _residual_transform(cols, model, spec.vehicle)
        sums.transformed(T)
        full.transformed(T)
    return _Library(terms, cols, sums, samples, noise_of, full, None if spec.effects else y0_squares)


def _flight_statistics(f: str, lib, labels: tuple[str, ...], spec: ModelSpec, decoded, cols: _Columns,
                       fx_effects) -> tuple[np.ndarray, np.ndarray, library_stats.FlightLibrary]:
    """(G, H, the statistics) of one flight in the columns ``labels``: the stored ones (``lib``),
    else computed from its rows; from its rows with ``cols`` when they lack a column (an effect
    loaded since)."""
    if lib is not None and set(labels) <= set(lib.labels):
        try:
            return *(_picked(M, lib.labels, labels) for M in lib.grams()), lib
        except sufficient.StatsError:  # cut short since its header was read
            lib = None
    if lib is None:
        lib = library_stats.compute(spec, f, decoded[f])
        if set(labels) <= set(lib.labels):
            return *(_picked(M, lib.labels, labels) for M in lib.grams()), lib
    fd = fitting.flight_data(f, decoded[f], spec.vehicle_for(f))
    G, H = flight_grams(fd, fitting.targets_of([fd])[0], cols, fx_effects, spec.vehicle, library_stats.STRIDE)
    return G, H, lib


def _picked(M: np.ndarray, have: tuple[str, ...], want: tuple[str, ...]) -> np.ndarray:
    """The rows and columns ``want`` of a matrix over the columns ``have`` (by name)."""
    if have == want:
        return M
    at = {name: i for i, name in enumerate(have)}
    idx = np.array([at[name] for name in want])
    return M[np.ix_(idx, idx)]


def _rmse_from_sums(lib: _Library, coefs: dict, pairs: list[tuple[np.ndarray, np.ndarray]],
                    eval_ids: list[str]) -> tuple[dict, dict]:
    """:func:`_held_out_rmse` from statistics: per pair (the Gram matrix the terms are fitted on,
    the sum of ``H`` of the flights scored with them), the residual's sum of squares after the
    terms, ``Σ r² - 2 βᵀXᵀr + βᵀXᵀXβ`` (:func:`_sse`); before them, ``Σ r²`` (a model without
    effects: the flights' own sums of ``y0²``, as the rows give them)."""
    cols = lib.cols
    if lib.y0_squares is not None:
        before = np.zeros(6)
        for f in eval_ids:
            before += lib.y0_squares[f]
    else:
        before = np.array([sum(float(H[y, y]) for _, H in pairs) for y in range(cols.target0, cols.target0 + 6)])
    after = before.copy()
    for axis, (chosen, _) in coefs.items():
        if chosen:
            y = cols.target0 + axis
            after[axis] = max(sum(_sse(H, chosen, y, _ols(G, chosen, y)) for G, H in pairs), 0.0)
    n = sum(lib.samples[f] for f in eval_ids)
    return _rmse(before, n), _rmse(after, n)


def _rmse(ss: np.ndarray, n: int) -> dict:
    """The RMSE per axis of the sums of squares ``ss`` (6,) over ``n`` samples (:func:`_by_axis`)."""
    return _by_axis(np.sqrt(ss / max(n, 1)))


def _by_axis(rms: np.ndarray) -> dict:
    """(6,) RMS values (force x, y, z in N, torque x, y, z in N m, body frame) as the JSON document lists them."""
    return {"force_rmse_N": [float(v) for v in rms[:3]], "torque_rmse_Nm": [float(v) for v in rms[3:]]}


def _discover_axis(axis: int, target: str, lib: _Library, fold_grams, G_train: np.ndarray, noise: np.ndarray,
                   holdout: bool, model_effects, fx_effects: list[Effect]
                   ) -> tuple[AxisResult, list[DiscoveredTerm], tuple[list[int], np.ndarray] | None]:
    """One residual axis: nothing when its residual is at the sensor-noise floor; else the
    stable terms (:func:`_select`) fitted on all training flights, with their jackknife
    standard errors over the folds and held-out shares, and their coefficients."""
    cols, terms = lib.cols, lib.terms
    y = cols.target0 + axis
    rms = np.sqrt(G_train[y, y] / _rows(G_train))
    if rms <= (1 + evidence.NOISE_MARGIN) * noise[axis]:
        why = (f"residual RMS {rms:.3g} within {evidence.NOISE_MARGIN:.0%} of the "
               f"sensor-noise floor {noise[axis]:.3g}: nothing to discover")
        return AxisResult(target, 0.0, True, (why,)), [], None
    candidates = [cols.term_col(k, axis) for k, t in enumerate(terms)
                  if not excluded(t, target) and (k in cols.force if axis < 3 else k in cols.torque)]
    col_term = {cols.term_col(k, axis): t for k, t in enumerate(terms) if t in _usable(cols, axis, terms)}
    chosen, counts = _select(fold_grams, G_train, candidates, y,
                             {c: form_family(col_term[c].expression) or c for c in candidates})
    scored_on = [(G_train, lib.sums.held_out())] if holdout else fold_grams
    picked, forms = _prefer_forms(fold_grams, scored_on, chosen, y, {c: col_term[c] for c in candidates})
    for old, new in zip(chosen, picked):  # a form's stability is its slot's: the folds that kept a form there
        counts[new] = max(counts.get(new, 0), counts.get(old, 0))
    chosen = picked
    beta = _ols(G_train, chosen, y)
    jack = [_ols(tr, chosen, y) for tr, _ in fold_grams]
    k_f = len(fold_grams)
    std = np.sqrt((k_f - 1) / k_f * np.sum((np.array(jack) - np.mean(jack, axis=0)) ** 2, axis=0)) if chosen \
        else np.zeros(0)
    shares = _sequential_shares(scored_on, chosen, y)
    kept = []
    for i, c in enumerate(chosen):
        t = col_term[c]
        coef_unit = _mul(UNIT["N"] if axis < 3 else UNIT["N m"], t.unit, -1)
        kept.append(DiscoveredTerm(
            target, t.expression, t.variables, float(beta[i]), float(std[i]), unit_text(coef_unit),
            unit_text(t.unit), shares[i], counts.get(c, 0) / k_f, counts.get(c, 0), k_f,
            _matches(G_train, cols, c, axis, fx_effects, model_effects),
            _form_label(t.expression, forms.get(c, ()), "force" if axis < 3 else "torque"),
            _collinear(G_train, c, [d for d in candidates if d != c], col_term), forms.get(c, ())))
    result = AxisResult(target, float(sum(shares)), False,
                        _modelled_side_note(G_train, cols, chosen, beta, axis, target))
    return result, kept, (chosen, beta)


def discover(
    decoded: Mapping[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    n_folds: int = 5,
    stride: int = library_stats.STRIDE,
    log=lambda msg: None,
    sessions: dict[str, list[str]] | None = None,
    stored: Callable[[str], library_stats.FlightLibrary | None] | None = None,
    stats: Callable[[str], sufficient.FlightStats | None] | None = None,
) -> Discovery:
    """Find the terms the model lacks (see the module docstring). ``sessions`` (name ->
    flights, from a sessions file) group the flights of per-session effects, as in
    :func:`quadcore.identify.diagnosis.diagnose`; None: the model file's, else the groups the data show.

    From rows, flight by flight: each flight's rows become its Gram matrix (the statistics the
    selection, the folds and the coefficients combine) and are dropped; the evaluated flights are
    read again for the held-out RMSE. ``decoded`` may read each table as it is looked up
    (:class:`quadcore.store.store.FlightTables`). Fitting the model's own effects reads the training
    flights' rows together (and every flight's for per-session effects).

    From statistics, with ``stored`` (flight -> its stored discovery statistics or None:
    :func:`quadcore.identify.library_stats.stored`) for a model without effects or of linear effects
    fitted fleet-wide, at the default ``stride``: no flight with stored statistics is read; the
    model's effects are fitted from the sufficient statistics (``stats``:
    :func:`quadcore.identify.sufficient.stored`). The same sums in the same order as from rows, so
    the same terms and coefficients; the held-out RMSE after the terms is a quadratic form of the
    flights' Gram matrices (equal to the rows' to rounding)."""
    vehicle = spec.vehicle
    ids = sorted(decoded)
    holdout = [h for h in (holdout or []) if h in decoded]
    train = [f for f in ids if f not in holdout]
    if len(train) < 2:
        raise ValueError("discovery needs at least two training flights (folds are grouped by flight)")
    fx_effects = library_stats.fx_effects(spec)  # the effects the stored statistics hold
    folds = fitting.folds(train, n_folds)
    combinable = (stored is not None and stride == library_stats.STRIDE and not spec.per_session
                  and all(effectlib.get(n).linear for n in spec.effects))
    if combinable:
        lib = _combined(ids, decoded, spec, fx_effects, folds, holdout, train, stored, stats, sessions, log)
    else:
        predict = _model_fit(spec, decoded, ids, train, sessions, log)

        def flight(f: str, quiet: bool = False) -> tuple[fitting.FlightData, np.ndarray]:
            """One flight's rows and its residual under the model."""
            fd = fitting.flight_data(f, decoded[f], spec.vehicle_for(f))  # a session's map
            target = fitting.targets_of([fd])[0]
            return fd, target if predict is None else target - predict(fd, (lambda msg: None) if quiet else log)

        lib = _accumulate(ids, flight, decoded, spec, fx_effects, folds, holdout, stride, log)
    fold_grams, G_train = lib.sums.fold_grams(), lib.sums.training_total()
    noise = _noise_floor([lib.samples[f] for f in train], [lib.noise_of[f] for f in train])

    kept: list[DiscoveredTerm] = []
    axes: list[AxisResult] = []
    coefs: dict[int, tuple[list[int], np.ndarray]] = {}
    for axis, target in enumerate(TARGETS):
        result, terms, coef = _discover_axis(axis, target, lib, fold_grams, G_train, noise, bool(holdout),
                                             spec.effects, fx_effects)
        axes.append(result)
        kept += terms
        if coef is not None:
            coefs[axis] = coef
    eval_ids = holdout or ids
    if lib.full is not None:  # each flight scored with its fold's training sum (the holdout: all training flights')
        pairs = [(G_train, lib.full.held_out())] if holdout else [
            (tr, inside) for (tr, _), inside in zip(fold_grams, lib.full.own_sums())]
        base, after = _rmse_from_sums(lib, coefs, pairs, eval_ids)
    else:
        train_gram = {f: G_train for f in eval_ids} if holdout else {
            f: fold_grams[i][0] for i, fold in enumerate(folds) for f in fold}  # the G each flight is scored with
        base, after = _held_out_rmse(lambda f: flight(f, quiet=True), eval_ids, train_gram, lib.cols, lib.terms,
                                     coefs, vehicle)
    return Discovery(
        tuple(kept), tuple(axes), base, after,
        _by_axis(noise),
        {"mode": "holdout" if holdout else "cross-validation", "train_flights": train, "eval_flights": eval_ids,
         "folds": len(folds), "stride": stride,
         # with a holdout the model's effects never see it; without one they are fitted on all flights
         "model_effects_fitted_on": train},
        tuple(spec.effects), {"force": len(lib.cols.force), "torque": len(lib.cols.torque)})


def _usable(cols: _Columns, axis: int, terms: list[Term]) -> list[Term]:
    idx = cols.force if axis < 3 else cols.torque
    return [terms[k] for k in idx]


def library_columns(terms: list[Term], fx_effects: list[Effect]) -> _Columns:
    """Where each of the Gram matrices' columns is: the terms usable in force, in torque, the
    six residual axes, the six modelled sides, then each effect's basis per axis."""
    force = [k for k, t in enumerate(terms) if t.channel in ("both", "force")]
    torque = [k for k, t in enumerate(terms) if t.channel in ("both", "torque")]
    i = len(force) + len(torque) + 12
    effect_cols = {}
    for e in fx_effects:
        for axis in range(6):
            effect_cols[(e.name, axis)] = list(range(i, i + len(e.parameters)))
            i += len(e.parameters)
    return _Columns(terms, force, torque, effect_cols, i)


def _rows(G: np.ndarray) -> float:
    """Samples behind a Gram matrix: the constant term "1" is the first force column."""
    return float(G[0, 0])


def _noise_floor(samples: list[int], noises: list[np.ndarray]) -> np.ndarray:
    """(6,) the flights' sensor-noise floors pooled by their usable samples."""
    n = np.array(samples, dtype=float)
    return np.sqrt(np.sum(n[:, None] * np.array(noises) ** 2, axis=0) / n.sum())


def _logs_motors(df: pl.DataFrame, vehicle: Vehicle) -> bool:
    """Whether a decoded table has every rotor's speed (``FlightState.motor_radps`` is set)."""
    return all(f"motor_{i}_radps" in df.columns for i in range(1, vehicle.n_rotors + 1))


def _model_fit(spec: ModelSpec, decoded: Mapping[str, pl.DataFrame], ids: list[str], train: list[str],
               sessions: dict[str, list[str]] | None, log) -> Callable | None:
    """``predict(flight data, log) -> (n, 6)``: the model's effects fitted on the training
    flights (per session for per-session effects), or None for a model without effects."""
    model_effects = [effectlib.get(n) for n in spec.effects]
    if spec.per_session:  # some effects fitted per session: each flight's residual under its session's values
        fds = {f: fitting.flight_data(f, decoded[f], spec.vehicle_for(f)) for f in ids}
        targets = dict(zip(ids, fitting.targets_of([fds[f] for f in ids])))
        pm = sessionlib.fit_per_session(spec, fds, targets, train, sessions, log)
        return lambda fd, say: sessionlib.model_prediction(pm, fd, say)
    if not model_effects:
        return None
    log(f"fitting the model's effects {spec.effects} on {len(train)} flights")
    fds_train = [fitting.flight_data(f, decoded[f], spec.vehicle_for(f)) for f in train]
    fit = fitting.fit_effects(model_effects, fds_train, fitting.targets_of(fds_train), spec.vehicle, spec.fixed)
    return lambda fd, say: fit.predict(model_effects, fd, spec.vehicle)


class _GramSums:
    """The sums of the flights' Gram matrices discovery combines, added up flight by flight as
    each flight's matrix is made (in the training flights' order: the same additions in the same
    order as summing every flight's matrix at the end, so the same numbers), so that memory holds
    a few sums, not one matrix per flight: the training total; per fold, the training flights
    outside it and the flights in it; and the held-out flights' own matrices (a few)."""

    def __init__(self, folds: list[list[str]], holdout: list[str], scored_only: bool = False):
        """``scored_only``: only each fold's own flights' sums and the held-out flights' (the
        matrices a flight is scored with, not fitted on)."""
        self.fold_of = {f: i for i, fold in enumerate(folds) for f in fold}
        self.holdout = holdout
        self.scored_only = scored_only
        self.train: np.ndarray | None = None
        self.outside: list[np.ndarray | None] = [None] * len(folds)
        self.inside: list[np.ndarray | None] = [None] * len(folds)
        self.held: dict[str, np.ndarray] = {}

    @staticmethod
    def _plus(total: np.ndarray | None, G: np.ndarray) -> np.ndarray:
        return G.copy() if total is None else np.add(total, G, out=total)

    def add(self, flight: str, G: np.ndarray) -> None:
        if flight in self.holdout:
            self.held[flight] = G
            return
        k = self.fold_of[flight]
        if self.scored_only:
            self.inside[k] = self._plus(self.inside[k], G)
            return
        self.train = self._plus(self.train, G)
        for i in range(len(self.outside)):
            if i == k:
                self.inside[i] = self._plus(self.inside[i], G)
            else:
                self.outside[i] = self._plus(self.outside[i], G)

    def training_total(self) -> np.ndarray:
        """The training flights' sum (discovery checks there are at least two of them)."""
        if self.train is None:
            raise ValueError("no training flight was added")
        return self.train

    def fold_grams(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per fold (its training flights' sum, its own flights' sum)."""
        return list(zip(self.outside, self.inside))  # type: ignore[arg-type]

    def own_sums(self) -> list[np.ndarray]:
        """Per fold, its own flights' sum (every fold holds a flight)."""
        if any(G is None for G in self.inside):
            raise ValueError("a fold without flights")
        return [G for G in self.inside if G is not None]

    def held_out(self) -> np.ndarray:
        return sum(self.held[f] for f in self.holdout)  # type: ignore[return-value]

    def transformed(self, T: np.ndarray) -> None:
        """Every sum ``G`` becomes ``Tᵀ G T`` (the Gram matrix of the columns ``Z T``)."""
        def tr(G):
            return None if G is None else T.T @ G @ T

        self.train = tr(self.train)
        self.outside = [tr(G) for G in self.outside]
        self.inside = [tr(G) for G in self.inside]
        self.held = {f: tr(G) for f, G in self.held.items()}


def _sequential_shares(pairs, chosen, y) -> list[float]:
    """Held-out variance each term adds, in the order of selection (they sum to the total):
    ``pairs`` (training sum, held-out sum) per fold, or the one of the holdout."""
    evs = [_cv_ev(pairs, chosen[:i], y) for i in range(len(chosen) + 1)]
    return [float(evs[i + 1] - evs[i]) for i in range(len(chosen))]


def _matches(G, cols: _Columns, c: int, axis: int, fx_effects, in_model) -> tuple[str, ...]:
    """Library effects whose basis (on this axis) holds at least MATCH of the term's energy."""
    out = []
    gcc = G[c, c]
    for e in fx_effects:
        b = cols.effect_cols[(e.name, axis)]
        if not b or gcc <= 0 or np.allclose(G[np.ix_(b, b)], 0):
            continue
        coef = np.linalg.lstsq(G[np.ix_(b, b)], G[b, c], rcond=1e-12)[0]
        r2 = float(G[c, b] @ coef / gcc)
        if r2 >= MATCH:
            out.append(f"{e.name}{' (in the model)' if e.name in in_model else ''}")
    return tuple(out)


def _collinear(G, c: int, others: list[int], col_term: dict[int, Term]) -> tuple[str, ...]:
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    return tuple(col_term[o].expression for o in others if abs(G[c, o] / (d[c] * d[o])) >= COLLINEAR)


def _modelled_side_note(G, cols: _Columns, chosen, beta, axis: int, target: str) -> tuple[str, ...]:
    """Say so when the kept terms rebuild a multiple of the axis' own modelled side."""
    m = cols.model0 + axis
    if not chosen or G[m, m] <= 0:
        return ()
    # prediction p = X beta; its projection on the modelled side: k = <p, m> / <m, m>
    pm = float(beta @ G[chosen, m])
    pp = float(beta @ G[np.ix_(chosen, chosen)] @ beta)
    if pp <= 0:
        return ()
    r2 = pm**2 / (pp * G[m, m])
    if r2 < 0.5:
        return ()
    k = pm / G[m, m]
    side = "thrust T" if axis < 3 else "rotor torque the thrust map gives"
    return ((f"{r2:.0%} of what the kept terms predict on {target} is {k:+.2f} × the modelled {side}: the model's own "
            f"term is mis-scaled or cancelled by something it does not model (a thrust-map error, or a disturbance "
            f"the controller holds off), not a new mechanism by itself"),)


def _held_out_rmse(flight, eval_ids, train_gram, cols, terms, coefs, vehicle):
    """RMSE per axis on the evaluated flights (every usable sample) before and after the
    discovered terms (fitted on training flights: ``train_gram[f]``, the Gram matrix flight
    ``f`` is scored with, of its fold's training flights without a holdout). ``flight(f)``
    gives a flight's rows and residual, read one flight at a time."""
    before = np.zeros(6)
    after = np.zeros(6)
    n = 0
    for f in eval_ids:
        fd, r = flight(f)
        pred = np.zeros_like(r)
        G = train_gram[f]
        for axis, (chosen, _) in coefs.items():
            if not chosen:
                continue
            beta = _ols(G, chosen, cols.target0 + axis)
            col_term = {cols.term_col(k, axis): t.expression for k, t in enumerate(terms)
                        if k in (cols.force if axis < 3 else cols.torque)}
            raw = evaluate([col_term[c] for c in chosen], fd.state, vehicle)
            filt = signals.smooth(raw) if axis < 3 else \
                signals.matched_to_derivative(raw, fd.state.t_s, fd.state.thrust_hold_s)
            pred[:, axis] = filt @ beta
        m = fd.mask
        before += (r[m] ** 2).sum(axis=0)
        after += ((r - pred)[m] ** 2).sum(axis=0)
        n += int(m.sum())

    return _rmse(before, n), _rmse(after, n)


# --- the generated effect ---------------------------------------------------------------------

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
        from quadcore.export.ccode import CCode

        lines = []
        for p, (axis, expr) in zip(self.parameters, self._terms):
            value = c_term(expr, vehicle)
            if value is None:
                return None
            out = f"f_b_N[{axis}]" if axis < 3 else f"tau_b_Nm[{axis - 3}]"
            lines.append(f"{out} += {p.name} * ({value});")
        return CCode("\n".join(lines))


def c_term(expression: str, vehicle: Vehicle) -> str | None:
    """A term of :func:`variables` as a C expression (names of :mod:`quadcore.export.ccode`), or None."""
    from quadcore.export.c.inputs import ExportError, feature_expression

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
    from quadcore.physics import vehicle as vehicles

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
    text = f'''"""{name}: terms found by ``quadcore discover``, as a linear effect. List this file under
``plugins`` in the model file and ``{name}`` under ``effects``: the fit refits the coefficients.

{evaluation.strip()}

{formulas}
{("" if not literature else chr(10) + "Literature:" + chr(10) + literature + chr(10))}
{left_note}Each parameter is the coefficient of one term on one residual axis (SI; default 0 = no effect).
The terms are evaluated by quadcore.identify.discovery.evaluate; every one has a C form (quadcore export-c).
"""

from quadcore.identify.discovery import DiscoveredEffect

# (target axis, term, parameter, unit of the parameter, bound on |parameter|)
TERMS = [
{terms_src}
]

EFFECT = DiscoveredEffect({name!r}, TERMS, __doc__)
'''
    return WrittenEffect(store.write_text(text, path), left_out)
