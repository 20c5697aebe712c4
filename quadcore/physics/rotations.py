"""Frames and attitude: quaternions (x, y, z, w, scalar last, as logged) and rotation matrices.

``R = rotation_matrix(q)`` maps body-frame vectors to the world frame: ``v_w = R v_b``; the world
frame has z up, so gravity is ``g_w = (0, 0, -g0)``.
Built on ``scipy.spatial.transform.Rotation``, which uses the same scalar-last order.
All functions take whole flights: quaternions ``(n, 4)``, vectors ``(n, 3)``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from quadcore.logs.units import G0_MPS2

GRAVITY_W_MPS2 = np.array([0.0, 0.0, -G0_MPS2])


def rotation_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """(n, 3, 3) body->world rotation matrices from (n, 4) quaternions (normalised here)."""
    return Rotation.from_quat(q_xyzw).as_matrix()


def body_to_world(R: np.ndarray, v_b: np.ndarray) -> np.ndarray:
    """``v_w = R v_b`` row by row."""
    return np.einsum("nij,nj->ni", R, v_b)


def world_to_body(R: np.ndarray, v_w: np.ndarray) -> np.ndarray:
    """``v_b = R^T v_w`` row by row."""
    return np.einsum("nji,nj->ni", R, v_w)


def integrate_body_rate(q_xyzw: np.ndarray, omega_b_radps: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """One step of the exponential map: ``q_next = q ⊗ exp(omega_b dt / 2)``.

    ``omega_b`` is the body-frame angular rate, held constant over ``dt``; exact for
    constant rate, and the result stays a unit quaternion.
    """
    step = Rotation.from_rotvec(omega_b_radps * np.asarray(dt_s)[..., None])
    return (Rotation.from_quat(q_xyzw) * step).as_quat()


def angle_between_rad(q1_xyzw: np.ndarray, q2_xyzw: np.ndarray) -> np.ndarray:
    """Angle (rad, 0..pi) of the rotation taking attitude q1 to attitude q2."""
    return (Rotation.from_quat(q1_xyzw).inv() * Rotation.from_quat(q2_xyzw)).magnitude()

