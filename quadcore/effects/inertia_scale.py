"""Inertia scale: the body's true inertia differs from the vehicle file's on the diagonal,
``J_true = J + ΔJ`` with ``ΔJ = diag((s_x - 1) J_xx, (s_y - 1) J_yy, (s_z - 1) J_zz)`` (a
battery or deck placed differently, an inertia computed from CAD). The measured torque
``J dω/dt + ω × J ω`` uses the file's ``J``, so the model lacks::

    tau_b = -(ΔJ dω/dt + ω × ΔJ ω)                                               [s] = 1

``dω/dt`` is the forward difference of the logged rate, so that through the residuals'
derivative filter it is exactly the measured ``dω/dt``. In torque it resembles a thrust
scale of ``1/s`` (the rotors' torque is ``J dω/dt + ω × Jω``); only the force, which the
inertia does not touch, tells them apart. Linear in (s_x - 1, s_y - 1, s_z - 1). No C form:
the forward difference needs the next sample (on board, use a causal rate derivative).
"""

import numpy as np

from quadcore.effects.base import Effect, Parameter, SimHook

AXES = ("x", "y", "z")


def inertia_change_kgm2(vehicle, params: dict[str, float]) -> np.ndarray:
    """(3, 3) ΔJ: the diagonal scaled by ``s - 1``, off-diagonal products unchanged."""
    J = np.asarray(vehicle.inertia_kgm2, float)
    return np.diag([(params[f"s_{a}"] - 1.0) * J[i, i] for i, a in enumerate(AXES)])


def forward_rate_change(omega_b: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """(n, 3) ``(ω[k+1] - ω[k]) / (t[k+1] - t[k])``, zero at the last sample."""
    out = np.zeros_like(omega_b)
    out[:-1] = np.diff(omega_b, axis=0) / np.maximum(np.diff(t_s), 1e-9)[:, None]
    return out


class TrueInertia(SimHook):
    def __init__(self, delta_kgm2: np.ndarray):
        self.delta_kgm2 = delta_kgm2

    def true_inertia_kgm2(self, inertia_kgm2):
        J = inertia_kgm2 + self.delta_kgm2
        if np.any(np.linalg.eigvalsh(J) <= 0):
            raise ValueError("the true inertia must be positive definite")
        return J


class InertiaScale(Effect):
    name = "inertia_scale"
    target = "torque"
    linear = True
    parameters = tuple(Parameter(f"s_{a}", "1", 1.0, 0.5, 2.0, f"true / file inertia about body {a}") for a in AXES)
    doc = __doc__

    def wrench(self, state, vehicle, params):
        dJ = inertia_change_kgm2(vehicle, params)
        w = state.omega_b_radps
        tau = -(forward_rate_change(w, state.t_s) @ dJ.T + np.cross(w, w @ dJ.T))
        return np.zeros((state.n, 3)), tau

    def check(self, params):
        if any(params[f"s_{a}"] <= 0 for a in AXES):
            raise ValueError("every s must be > 0")

    def simulator(self, params, context):
        return TrueInertia(inertia_change_kgm2(context.vehicle, params))


EFFECT = InertiaScale()
