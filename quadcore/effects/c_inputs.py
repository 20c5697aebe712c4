"""What the generated function reads: the input struct's fields, the quantities derived from
them in C, and the learned model's features as C expressions. The names an effect's C statements
(:mod:`quadcore.effects.ccode`) and a discovered effect's terms may use; here, below ``identify`` and
``export``, so that both the exporter (:mod:`quadcore.export.c`) and discovery's effect writer read them.

The input struct carries exactly what the model uses: the exporter collects the names the
effects' C statements and the feature set mention (:func:`needed`), closes them over their
dependencies, and emits only those fields and derived quantities, in a fixed order.
Derived quantities repeat the Python definitions:

* ``R_wb`` as :func:`quadcore.physics.rotations.rotation_matrix` (scipy: the quaternion normalised);
* ``v_b_mps = R^T v_w`` as :func:`quadcore.physics.rotations.world_to_body`;
* ``f_rotor_N`` as :meth:`quadcore.physics.vehicle.Vehicle.rotor_thrusts_N` for the vehicle's map;
* ``T_N`` and ``tau_rotors_b_Nm = A f`` as :func:`quadcore.physics.dynamics.wrench_from_thrusts`;
* ``qc_xyzw`` as :func:`quadcore.learn.features.with_derived` (sign fixed so that ``q_w >= 0``,
  not normalised).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from quadcore.logs.units import SI_COLUMNS
from quadcore.physics.dynamics import XYZ
from quadcore.physics.vehicle import Vehicle


class ExportError(ValueError):
    """A model that cannot be written as C (a feature with no on-board form, a bad source)."""


@dataclass(frozen=True)
class Field:
    """One member of the input struct: ``float name[length]`` (``length`` 0: a scalar)."""

    name: str
    length: int
    columns: tuple[str, ...]  # the residual-table columns it holds, in order
    doc: str

    @property
    def size(self) -> int:
        return max(self.length, 1)

    def logged_as(self) -> str:
        """The firmware log variables behind it, from :data:`quadcore.logs.units.SI_COLUMNS`."""
        source = {si: var for var, (si, *_rest) in SI_COLUMNS.items()}
        names = [source.get(c, "") for c in self.columns]
        return ", ".join(n for n in names if n) or "not logged"


def fields(vehicle: Vehicle) -> list[Field]:
    """Every field the struct may carry, in struct order."""
    n = vehicle.n_rotors
    return [
        Field("p_w_m", 3, tuple(f"p_w_{a}_m" for a in XYZ), "position, world frame (z up), m"),
        Field("v_w_mps", 3, tuple(f"v_w_{a}_mps" for a in XYZ), "velocity, world frame, m/s"),
        Field("q_xyzw", 4, ("q_x", "q_y", "q_z", "q_w"), "attitude quaternion body->world, scalar last"),
        Field("omega_b_radps", 3, tuple(f"omega_b_{a}_radps" for a in XYZ), "angular rate, body frame, rad/s"),
        Field("pwm", n, tuple(f"pwm_{i}" for i in range(1, n + 1)), "motor PWM duty 0..1 (firmware PWM / 65535)"),
        Field("vbat_V", 0, ("vbat_V",), "battery voltage, V"),
        Field("motor_radps", n, tuple(f"motor_{i}_radps" for i in range(1, n + 1)), "motor speeds, rad/s"),
        Field("dt_s", 0, (), "time since the previous call, s (the Python model uses the flight's median "
                             "sample period)"),
    ]


@dataclass(frozen=True)
class Derived:
    """A quantity computed in C from fields or other derived quantities."""

    name: str
    needs: tuple[str, ...]
    code: str  # C99 statements declaring and computing it


def derived(vehicle: Vehicle) -> list[Derived]:
    """Derived quantities, in dependency order."""
    if vehicle.thrust_map_kind == "motor_speed":
        thrust = Derived("f_rotor_N", ("motor_radps",), (
            "qc_real f_rotor_N[QC_N_ROTORS];  /* f = k_F omega^2 */\n"
            "for (qc_i = 0; qc_i < QC_N_ROTORS; ++qc_i) "
            "f_rotor_N[qc_i] = QC_K_F * ((qc_real)motor_radps[qc_i] * motor_radps[qc_i]);"))
    else:
        thrust = Derived("f_rotor_N", ("pwm", "vbat_V"), (
            "qc_real f_rotor_N[QC_N_ROTORS];  /* grams = c0 + cp p + cb b + cpp p^2 + cpb p b, b = vbat / vbat_ref */\n"
            "for (qc_i = 0; qc_i < QC_N_ROTORS; ++qc_i) {\n"
            "    const qc_real p = pwm[qc_i], b = vbat_V / QC_VBAT_REF_V;\n"
            "    const qc_real grams = QC_C0 + QC_CP * p + QC_CB * b + QC_CPP * p * p + QC_CPB * p * b;\n"
            "    f_rotor_N[qc_i] = (grams > 0 ? grams : 0) * QC_N_PER_GRAM;\n"
            "}"))
    return [
        Derived("R_wb", ("q_xyzw",), (
            "qc_real R_wb[3][3];  /* body->world from the normalised quaternion */\n"
            "{\n"
            "    const qc_real s = 1 / qc_sqrt((qc_real)q_xyzw[0] * q_xyzw[0] + (qc_real)q_xyzw[1] * q_xyzw[1]"
            " + (qc_real)q_xyzw[2] * q_xyzw[2] + (qc_real)q_xyzw[3] * q_xyzw[3]);\n"
            "    const qc_real x = q_xyzw[0] * s, y = q_xyzw[1] * s, z = q_xyzw[2] * s, w = q_xyzw[3] * s;\n"
            "    R_wb[0][0] = x * x - y * y - z * z + w * w;\n"
            "    R_wb[1][0] = 2 * (x * y + z * w);\n"
            "    R_wb[2][0] = 2 * (x * z - y * w);\n"
            "    R_wb[0][1] = 2 * (x * y - z * w);\n"
            "    R_wb[1][1] = -x * x + y * y - z * z + w * w;\n"
            "    R_wb[2][1] = 2 * (y * z + x * w);\n"
            "    R_wb[0][2] = 2 * (x * z + y * w);\n"
            "    R_wb[1][2] = 2 * (y * z - x * w);\n"
            "    R_wb[2][2] = -x * x - y * y + z * z + w * w;\n"
            "}")),
        Derived("v_b_mps", ("R_wb", "v_w_mps"), (
            "qc_real v_b_mps[3];  /* R^T v_w */\n"
            "for (qc_i = 0; qc_i < 3; ++qc_i) v_b_mps[qc_i] = R_wb[0][qc_i] * v_w_mps[0] + R_wb[1][qc_i] * v_w_mps[1]"
            " + R_wb[2][qc_i] * v_w_mps[2];")),
        Derived("qc_xyzw", ("q_xyzw",), (
            "float qc_xyzw[4];  /* the quaternion with q_w >= 0 (q and -q are one attitude) */\n"
            "for (qc_i = 0; qc_i < 4; ++qc_i) qc_xyzw[qc_i] = q_xyzw[3] < 0 ? -q_xyzw[qc_i] : q_xyzw[qc_i];")),
        thrust,
        Derived("T_N", ("f_rotor_N",), (
            "qc_real T_N = 0;  /* collective thrust */\n"
            "for (qc_i = 0; qc_i < QC_N_ROTORS; ++qc_i) T_N += f_rotor_N[qc_i];")),
        Derived("tau_rotors_b_Nm", ("f_rotor_N",), (
            "qc_real tau_rotors_b_Nm[3] = {0, 0, 0};\n"
            "{\n"
            "    qc_real no_force[3] = {0, 0, 0};\n"
            "    qc_add_rotor_wrench(f_rotor_N, 1, no_force, tau_rotors_b_Nm);\n"
            "}")),
    ]


MEMORY_NAMES = ("first_call",)


def all_names(vehicle: Vehicle) -> list[str]:
    return [f.name for f in fields(vehicle)] + [d.name for d in derived(vehicle)] + list(MEMORY_NAMES)


def mentioned(code: str, vehicle: Vehicle) -> set[str]:
    """The readable names (fields, derived quantities) that C code mentions."""
    return {n for n in all_names(vehicle) if re.search(rf"\b{re.escape(n)}\b", code)}


def closure(names: set[str], vehicle: Vehicle) -> tuple[list[Field], list[Derived]]:
    """The fields and derived quantities needed to compute ``names``, in emission order."""
    need = set(names)
    for d in reversed(derived(vehicle)):  # later ones depend on earlier ones only
        if d.name in need:
            need.update(d.needs)
    return [f for f in fields(vehicle) if f.name in need], [d for d in derived(vehicle) if d.name in need]


_AXIS = {a: i for i, a in enumerate(XYZ)}
_QUAT = {a: i for i, a in enumerate(("x", "y", "z", "w"))}
FEATURE_PATTERNS: list[tuple[str, str]] = [  # regex on the column -> C expression template
    (r"p_w_([xyz])_m", "p_w_m[{axis}]"),
    (r"v_w_([xyz])_mps", "v_w_mps[{axis}]"),
    (r"v_b_([xyz])_mps", "v_b_mps[{axis}]"),
    (r"omega_b_([xyz])_radps", "omega_b_radps[{axis}]"),
    (r"q_([xyzw])", "q_xyzw[{quat}]"),
    (r"qc_([xyzw])", "qc_xyzw[{quat}]"),
    (r"R_wb_([012])([012])", "R_wb[{i}][{j}]"),
    (r"T_N", "T_N"),
    (r"f_rotor_(\d+)_N", "f_rotor_N[{rotor}]"),
    (r"motor_(\d+)_radps", "motor_radps[{rotor}]"),
    (r"pwm_(\d+)", "pwm[{rotor}]"),
    (r"vbat_V", "vbat_V"),
]


def feature_expression(column: str, vehicle: Vehicle) -> str:
    """The C expression (float) of a feature column, or :class:`ExportError` when the column
    has no on-board form (the accelerometer, smoothed or differentiated signals, time)."""
    for pattern, template in FEATURE_PATTERNS:
        m = re.fullmatch(pattern, column)
        if not m:
            continue
        g = m.groups()
        rotor = int(g[0]) - 1 if g and g[0].isdigit() and template.startswith(("f_rotor", "motor", "pwm")) else 0
        if template.startswith(("f_rotor", "motor", "pwm")) and not 0 <= rotor < vehicle.n_rotors:
            break
        expr = template.format(axis=_AXIS.get(g[0], 0) if g else 0, quat=_QUAT.get(g[0], 0) if g else 0,
                               i=g[0] if g else 0, j=g[1] if len(g) > 1 else 0, rotor=rotor)
        return f"(float){expr}"
    raise ExportError(
        f"feature {column!r} has no on-board form: the exporter computes position, velocity (world and body), "
        "attitude, angular rate, rotor thrusts, PWM, motor speeds and battery voltage, not accelerometer, smoothed "
        "or differentiated signals")
