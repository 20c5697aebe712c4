"""The candidate library of term discovery: the signals terms are built from, the terms, their
units, their values over a flight, which terms a residual axis may not use, and the name of the
mechanism a term stands for in the multirotor literature.

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

**The tautology guard** (:func:`excluded`). A residual is measured minus modelled. A term built
from either side of the *same* residual reconstructs it without any physics (the gyro derivative
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
force or torque, the result says so (:mod:`quadcore.identify.discovery.select`): the model's own
term is mis-scaled or cancelled by something, which is not a new mechanism by itself. Per-rotor
thrusts stay in the horizontal force library, motor speeds (a separate measurement) and time
derivatives of the map thrusts (timing) in every library.

**Competing forms** (:func:`form_family`): the forms of a velocity term (``v``, ``T v``,
``v|v|``, ``|v_b| v``: :data:`VELOCITY_FORMS`) are rivals for one slot of an axis.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from quadcore.physics import dynamics, signals
from quadcore.physics.dynamics import XYZ, FlightState
from quadcore.physics.vehicle import Vehicle

# the residual axes discovery explains: force (N) and torque (N m), body frame
TARGETS = tuple([f"f_res_b_{a}_N" for a in XYZ] + [f"tau_res_b_{a}_Nm" for a in XYZ])
MIN_HEIGHT_M = 0.02  # the ground-effect term is evaluated at no less than this height

# --- units, as exponents of (kg, m, s, rad, V) ------------------------------------------

_BASE = ("kg", "m", "s", "rad", "V")
UNIT = {
    "1": (0, 0, 0, 0, 0), "N": (1, 1, -2, 0, 0), "N m": (1, 2, -2, 0, 0), "m": (0, 1, 0, 0, 0),
    "m/s": (0, 1, -1, 0, 0), "m/s^2": (0, 1, -2, 0, 0), "rad/s": (0, 0, -1, 1, 0), "rad/s^2": (0, 0, -2, 1, 0),
    "V": (0, 0, 0, 0, 1), "N/s": (1, 1, -3, 0, 0),
}


def mul_units(a, b, sign=1):
    """The unit of a product of quantities of units ``a`` and ``b`` (exponents; ``sign=-1``: of ``a / b``)."""
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
        out[f"d(tau_rotor_{a}_Nm)/dt"] = Variable(tau_dot[:, j], mul_units(UNIT["N m"], (0, 0, -1, 0, 0)), rotors,
                                                  "torque")
    h = np.maximum(state.p_w_m[:, 2], MIN_HEIGHT_M)
    put("(R/4h)^2*T_N", (vehicle.rotor_radius_m / (4 * h)) ** 2 * T, "N", ("p_w_z_m", "T_N"))
    put("T_N*|v_h|^2", T * (state.v_b_mps[:, 0] ** 2 + state.v_b_mps[:, 1] ** 2), "N",
        ("T_N", "v_b_x_mps", "v_b_y_mps"))
    out["T_N*|v_h|^2"] = Variable(out["T_N*|v_h|^2"].values,
                                  mul_units(UNIT["N"], mul_units(UNIT["m/s"], UNIT["m/s"])), out["T_N*|v_h|^2"].sources)
    speed = np.linalg.norm(state.v_b_mps, axis=1)  # quadratic drag grows with the airspeed times each component
    velocity = tuple(f"v_b_{a}_mps" for a in XYZ)
    for j, a in enumerate(XYZ):
        out[f"|v_b|*v_b_{a}_mps"] = Variable(speed * state.v_b_mps[:, j], mul_units(UNIT["m/s"], UNIT["m/s"]), velocity)
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


def literature(expr: str, channel: str = "force") -> str:
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
            terms.append(Term(expr, tuple(dict.fromkeys((a, b))), mul_units(vars_[a].unit, vars_[b].unit)))
    for a in SIGNED_SQUARES:
        expr = f"{a}*|{a}|"
        terms.append(Term(expr, (a,), mul_units(vars_[a].unit, vars_[a].unit)))
    if "Omega_net_radps" in vars_:
        for a in ("x", "y"):
            expr = f"omega_b_{a}_radps*Omega_net_radps"
            terms.append(Term(expr, (f"omega_b_{a}_radps", *vars_["Omega_net_radps"].sources),
                              mul_units(UNIT["rad/s"], UNIT["rad/s"]), "torque"))
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


def library_of(vars_: dict[str, Variable], motors: bool) -> list[Term]:
    """The candidate library of a flight's variables; without those read off the motors unless
    every flight logs them (``motors``)."""
    if not motors:
        vars_ = {k: v for k, v in vars_.items() if not any(s.startswith("motor_") for s in v.sources)}
    return library(vars_)

