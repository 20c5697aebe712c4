"""Assemble the header and source: vehicle constants, the input, memory and output structs,
the effects' blocks, the learned part, and the one function that ties them together."""

from __future__ import annotations

from dataclasses import dataclass

from quadcore.effects import UnknownEffectError, c_inputs as inputs, get as get_effect
from quadcore.effects.c_inputs import Derived, ExportError, Field
from quadcore.export.c.learned import learned_c
from quadcore.identify.model import PhysicsModel
from quadcore.learn.artefacts import LearnedModel
from quadcore.logs.units import G0_MPS2

HEADER = "quadcore_model.h"
SOURCE = "quadcore_model.c"
OUTPUTS = ("f_b_N", "tau_b_Nm", "f_effects_b_N", "tau_effects_b_Nm", "f_learned_b_N", "tau_learned_b_Nm")


class NoCFormError(ExportError):
    """An effect in the model whose module gives no C form (``c_code`` returns ``None``)."""

    def __init__(self, effect: str):
        super().__init__(f"effect {effect!r} has no C form: its c_code(vehicle, params) gives none (a method "
                         "returning quadcore.effects.ccode.CCode; see docs/adding-an-effect.md, section 6)")
        self.effect = effect


@dataclass(frozen=True)
class Generated:
    """The two files' text and what the caller needs to feed and describe them."""

    header: str
    source: str
    fields: tuple[Field, ...]  # the input struct, in order
    memory: tuple[tuple[str, int], ...]  # (member, length) beyond `started`
    feature_columns: tuple[str, ...]
    learned: dict  # figures of the learned part ({} without one)
    label: str
    left_out: tuple[tuple[str, str], ...] = ()  # (effect, why) of the effects the C code does not hold


def comment(text: str) -> str:
    """Text safe inside a C comment (a user's parameter doc or path could hold its end)."""
    return text.replace("*/", "* /").replace("/*", "/ *")


def r(value: float) -> str:
    """A vehicle constant at full precision, in the derived quantities' type."""
    return f"((qc_real){float(value)!r})"


def _vehicle_constants(physics: PhysicsModel, with_allocation: bool) -> str:
    v = physics.vehicle
    pv = v.pwm_vbat
    a = v.allocation
    rows = ",\n    ".join("{" + ", ".join(r(x) for x in row) + "}" for row in a)
    lines = [
        f"#define QC_MASS_KG {r(v.mass_kg)}  /* vehicle mass, kg */",
        f"#define QC_ROTOR_RADIUS_M {r(v.rotor_radius_m)}  /* rotor radius, m */",
        f"#define QC_N_PER_GRAM {r(G0_MPS2 / 1000.0)}  /* g0 / 1000, N per gram */",
        f"#define QC_VBAT_REF_V {r(pv.vbat_ref_V)}  /* thrust map: reference battery voltage, V */",
        *(f"#define QC_{k.upper()} {r(getattr(pv, k))}  /* thrust map coefficient {k}, grams */"
          for k in ("c0", "cp", "cb", "cpp", "cpb")),
        f"#define QC_K_F {r(v.motor_speed.k_F_N_per_radps2)}  /* motor-speed thrust map, N/(rad/s)^2 */",
    ]
    if with_allocation:
        lines += ["", "/* [T, tau_x, tau_y, tau_z] = A f: column i = [1, y_i, -x_i, t2t * yaw_sign_i] for rotor i */",
                  f"static const qc_real QC_ALLOCATION[4][QC_N_ROTORS] = {{\n    {rows}\n}};"]
    return "\n".join(lines)


ROTOR_WRENCH = """/* f_b_N[2] += scale * sum f; tau_b_Nm += scale * A[1..3] f */
static void qc_add_rotor_wrench(const qc_real f[QC_N_ROTORS], qc_real scale, qc_real f_b_N[3], qc_real tau_b_Nm[3])
{
    int i, k;
    for (i = 0; i < QC_N_ROTORS; ++i) {
        f_b_N[2] += scale * QC_ALLOCATION[0][i] * f[i];
        for (k = 0; k < 3; ++k) tau_b_Nm[k] += scale * QC_ALLOCATION[k + 1][i] * f[i];
    }
}
"""


def _indent(code: str, spaces: int = 4) -> str:
    pad = " " * spaces
    return "\n".join(pad + line if line.strip() else "" for line in code.splitlines())


def _effect_block(term, physics: PhysicsModel) -> tuple[str, tuple[tuple[str, int], ...]]:
    try:
        effect = get_effect(term.name)
    except UnknownEffectError as exc:  # a plugin effect: a fitted model's JSON does not say where its module is
        raise ExportError(f"{exc}. A plugin effect is exported only where its module is loaded "
                          "(quadcore.effects.load_plugin, or the pipeline with the model file naming it)") from None
    form = effect.c_code(physics.vehicle, term.params)
    if form is None:
        raise NoCFormError(term.name)
    lines = [f"/* effect {term.name} (fitted parameters as constants) */", "{"]
    for p in effect.parameters:
        value = float(term.params[p.name])
        how = "fixed" if term.fixed else (f"fitted, std {term.std[p.name]:.3g}" if p.name in term.std else "fitted")
        lines.append(f"    const qc_real {p.name} = {r(value)};  /* {comment(f'{p.doc} [{p.unit}], {how}')} */")
        lines.append(f"    (void){p.name};")
    for name, _length in form.memory:
        lines.append(f"    qc_real *const {name} = mem->{term.name}__{name};")
    lines += [_indent(form.statements), "}"]
    return "\n".join(lines), tuple((f"{term.name}__{n}", length) for n, length in form.memory)


def _locals(fields: list[Field], derived: list[Derived], first_call: bool) -> str:
    out = []
    for f in fields:
        if f.length:
            out.append(f"const float *const {f.name} = in->{f.name};")
        else:
            out.append(f"const float {f.name} = in->{f.name};")
        out.append(f"(void){f.name};")
    if first_call:
        out += ["const int first_call = !mem->started;", "(void)first_call;"]
    for d in derived:
        out += [d.code, f"(void){d.name};"]
    return "\n".join(out)


def generate(physics: PhysicsModel, learned: LearnedModel | None, provenance: str, footprint: str = "",
             leave_out: bool = False) -> Generated:
    """The header and source of ``physics`` (+ ``learned``). ``footprint``: a comment block to
    put in both files (measured by compiling a first version). An effect with no C form raises
    :class:`NoCFormError`, or with ``leave_out`` is left out and named, with why, at the top of
    both files and in :attr:`Generated.left_out`."""
    veh = physics.vehicle
    blocks: list[str] = []
    memory: list[tuple[str, int]] = []
    left_out: list[tuple[str, str]] = []
    for term in physics.terms:
        try:
            block, mem = _effect_block(term, physics)
        except NoCFormError as exc:
            if not leave_out:
                raise
            left_out.append((term.name, str(exc)))
            continue
        blocks.append(block)
        memory += mem
    learned_code, figures, feature_cols = "", {}, ()  # type: tuple[str, dict, tuple[str, ...]]
    if learned is not None:
        learned_code, figures = learned_c(learned)
        feature_cols = tuple(learned.features)
    x_exprs = [inputs.feature_expression(c, veh) for c in feature_cols]
    reads = inputs.mentioned("\n".join(blocks + x_exprs), veh)
    fields, derived = inputs.closure(reads, veh)
    uses_rotor_wrench = "qc_add_rotor_wrench" in "\n".join(blocks + [d.code for d in derived])
    label = physics.label + (f" + {learned.kind}({learned.feature_set.name})" if learned is not None else "")
    comment = _top_comment(label, provenance, fields, feature_cols, footprint, left_out)
    header = _header(comment, veh.n_rotors, fields, memory, len(feature_cols))
    body = _body(fields, derived, "first_call" in reads, blocks, x_exprs)
    source = "\n".join(filter(None, [
        comment, f'#include "{HEADER}"', "#include <math.h>", "", PRECISION,
        "#define QC_N_ROTORS QUADCORE_N_ROTORS", "#define QC_N_FEATURES QUADCORE_N_FEATURES" if feature_cols else "",
        _vehicle_constants(physics, uses_rotor_wrench), "",
        ROTOR_WRENCH if uses_rotor_wrench else "", learned_code, body, _reset(memory),
        _features_entry() if learned is not None else "",
    ]))
    return Generated(header, source, tuple(fields), tuple(memory), feature_cols, figures, label, tuple(left_out))


PRECISION = """/* Derived quantities (rotation, body velocity, rotor thrusts) are float, as on the Cortex-M4's FPU.
   -DQUADCORE_DOUBLE_INPUTS computes them in double, as the Python model does: then the trees branch
   exactly as in Python even for an input that lands within float rounding of a split. */
#ifdef QUADCORE_DOUBLE_INPUTS
typedef double qc_real;
#define qc_sqrt sqrt
#define qc_exp exp
#define qc_fabs fabs
#else
typedef float qc_real;
#define qc_sqrt sqrtf
#define qc_exp expf
#define qc_fabs fabsf
#endif
"""


def _top_comment(label: str, provenance: str, fields: list[Field], features: tuple[str, ...], footprint: str,
                 left_out: list[tuple[str, str]] | None = None) -> str:
    lines = [f"/* Generated by `quadcore export-c` from {comment(provenance)}. Do not edit: export again.",
             f"   Model: {comment(label)}.",
             "   quadcore_residual() returns what the nominal model (thrust map, rigid body) misses: the fitted",
             "   effects' wrench plus the learned residual, body frame (x forward, y left, z up), SI units.",
             "   Single precision, no heap, no library but math.h."]
    if features:
        lines.append(f"   Learned model inputs, in order: {', '.join(features)}.")
    for _effect, why in left_out or []:
        lines.append(f"   LEFT OUT: {comment(why)}; this code does not add its wrench.")
    if footprint:
        lines += ["", *("   " + line for line in footprint.splitlines())]
    return "\n".join(lines) + " */\n"


def _header(comment: str, n_rotors: int, fields: list[Field], memory, n_features: int) -> str:
    members = "\n".join(f"    float {f.name}{f'[{f.length}]' if f.length else ''};  /* {f.doc}; log: {f.logged_as()} */"
                        for f in fields) or "    float unused;  /* the model reads no input */"
    mem = "\n".join(f"    QUADCORE_MEMORY_REAL {name}[{length}];" for name, length in memory)
    outputs = "\n".join(f"    float {o}[3];" for o in OUTPUTS)
    features = (f"\n#define QUADCORE_N_FEATURES {n_features}\n/* The learned part alone, on a feature vector "
                "(the columns listed above, SI): residual force (N) and torque (N m), body frame. */\n"
                "void quadcore_learned_from_features(const float x[QUADCORE_N_FEATURES], float f_b_N[3], "
                "float tau_b_Nm[3]);\n") if n_features else ""
    return f"""{comment}
#ifndef QUADCORE_MODEL_H
#define QUADCORE_MODEL_H

#define QUADCORE_N_ROTORS {n_rotors}
#ifdef QUADCORE_DOUBLE_INPUTS
#define QUADCORE_MEMORY_REAL double
#else
#define QUADCORE_MEMORY_REAL float
#endif

/* What the model reads, SI. Motors in firmware order (1 front-right, 2 back-right, 3 back-left, 4 front-left). */
typedef struct {{
{members}
}} quadcore_input_t;

/* What the model keeps between calls (filters); set by quadcore_reset(). */
typedef struct {{
    int started;
{mem}
}} quadcore_memory_t;

/* Body frame, N and N m: total = effects + learned. */
typedef struct {{
{outputs}
}} quadcore_wrench_t;

/* Call once before the first quadcore_residual (and after a gap in the inputs). */
void quadcore_reset(quadcore_memory_t *mem);
/* One sample: the residual wrench the nominal model misses. */
void quadcore_residual(const quadcore_input_t *in, quadcore_memory_t *mem, quadcore_wrench_t *out);
{features}
#endif /* QUADCORE_MODEL_H */
"""


def _body(fields, derived, first_call: bool, blocks: list[str], x_exprs: list[str]) -> str:
    learned = ""
    if x_exprs:
        x_init = ",\n        ".join(x_exprs)
        learned = f"""    {{
        const float x[QC_N_FEATURES] = {{
        {x_init}
        }};
        float y[6];
        qc_learned(x, y);
        for (qc_i = 0; qc_i < 3; ++qc_i) {{
            out->f_learned_b_N[qc_i] = y[qc_i];
            out->tau_learned_b_Nm[qc_i] = y[3 + qc_i];
        }}
    }}"""
    else:
        learned = "    for (qc_i = 0; qc_i < 3; ++qc_i) out->f_learned_b_N[qc_i] = out->tau_learned_b_Nm[qc_i] = 0.0f;"
    effects = "\n".join(_indent(b) for b in blocks) or "    /* no effects in the model */"
    return f"""void quadcore_residual(const quadcore_input_t *in, quadcore_memory_t *mem, quadcore_wrench_t *out)
{{
    int qc_i;  /* the generated loops' index: effects' blocks may use i, j, k */
    qc_real f_b_N[3] = {{0, 0, 0}}, tau_b_Nm[3] = {{0, 0, 0}};
{_indent(_locals(fields, derived, first_call))}
    (void)in;
{effects}
    for (qc_i = 0; qc_i < 3; ++qc_i) {{
        out->f_effects_b_N[qc_i] = (float)f_b_N[qc_i];
        out->tau_effects_b_Nm[qc_i] = (float)tau_b_Nm[qc_i];
    }}
{learned}
    for (qc_i = 0; qc_i < 3; ++qc_i) {{
        out->f_b_N[qc_i] = out->f_effects_b_N[qc_i] + out->f_learned_b_N[qc_i];
        out->tau_b_Nm[qc_i] = out->tau_effects_b_Nm[qc_i] + out->tau_learned_b_Nm[qc_i];
    }}
    mem->started = 1;
}}
"""


def _reset(memory) -> str:
    clear = "\n".join(f"    for (i = 0; i < {length}; ++i) mem->{name}[i] = 0;" for name, length in memory)
    return f"""void quadcore_reset(quadcore_memory_t *mem)
{{
    int i;
    (void)i;
    mem->started = 0;
{clear}
}}
"""


def _features_entry() -> str:
    return """void quadcore_learned_from_features(const float x[QUADCORE_N_FEATURES], float f_b_N[3], float tau_b_Nm[3])
{
    float y[6];
    int i;
    qc_learned(x, y);
    for (i = 0; i < 3; ++i) {
        f_b_N[i] = y[i];
        tau_b_Nm[i] = y[3 + i];
    }
}
"""
