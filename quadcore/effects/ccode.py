"""The C form of an effect: what an effect's ``c_code`` hook returns for ``quadcore export-c``.

An effect that can run on a flight controller returns :class:`CCode` from
``Effect.c_code(vehicle, params)``: C99 statements that **add** its body-frame wrench to
``f_b_N[3]`` (N) and ``tau_b_Nm[3]`` (N m), in single precision, with no heap and nothing
but ``math.h``. The exporter wraps them in a block of their own and, before them, declares
every parameter of the effect as a commented constant under its own name
(``const float k_x_s_per_m = 0.31f;``), so the statements use the parameter names as they are.
Local names are free (the generated code's own loop index is ``qc_i``); the check compiles with
``-Wshadow`` and ``-Wdouble-promotion`` too, so use ``float`` literals (``1.0f``).

Names the statements may read (the exporter declares exactly the ones they mention, and the
input struct carries exactly what those need):

=====================  =====================================================================
``p_w_m[3]``           position, world frame (z up), m
``v_w_mps[3]``         velocity, world frame, m/s
``q_xyzw[4]``          attitude quaternion body->world, scalar last, as logged
``omega_b_radps[3]``   body angular rate, rad/s
``pwm[N]``             motor PWM duty, 0..1
``vbat_V``             battery voltage, V
``motor_radps[N]``     motor speeds, rad/s
``dt_s``               time since the previous call, s (the Python model: the flight's
                       median sample period)
``R_wb[3][3]``         rotation body->world from the normalised quaternion
``v_b_mps[3]``         velocity in the body frame, ``R^T v_w``, m/s
``f_rotor_N[N]``       rotor thrusts of the vehicle's thrust map, N
``T_N``                collective thrust ``sum f_rotor_N``, N
``tau_rotors_b_Nm[3]`` torque of the rotor thrusts, ``A[1:4] f``, N m
``first_call``         1 on the first call after ``quadcore_reset``, else 0
=====================  =====================================================================

Vehicle constants: ``QC_N_ROTORS``, ``QC_MASS_KG``, ``QC_ROTOR_RADIUS_M``, and
``qc_add_rotor_wrench(const qc_real f[QC_N_ROTORS], qc_real scale, f_b_N, tau_b_Nm)``,
which adds ``scale * A f`` (A: the allocation matrix). ``qc_real`` is the type of the derived
quantities (``float``; ``double`` when compiled with ``-DQUADCORE_DOUBLE_INPUTS``), with
``qc_sqrt``, ``qc_exp`` and ``qc_fabs`` the matching ``math.h`` functions.

An effect with memory (a filter, a delay) lists ``qc_real`` arrays in ``memory`` as ``(name,
length)``; its statements see each as a ``qc_real *`` of that
name that keeps its values between calls (zero after ``quadcore_reset``; ``first_call`` says
when to initialise them).

This module imports nothing from quadcore, so that effect modules can import it freely. It lives in
``effects`` (below ``export``) because effects return it; ``quadcore.export.ccode`` re-exports it for
plugins written against the earlier path.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CCode:
    """C99 statements adding an effect's wrench to ``f_b_N`` / ``tau_b_Nm`` (see the module
    docstring for the names they may read), and the persistent arrays they keep."""

    statements: str
    memory: tuple[tuple[str, int], ...] = ()
