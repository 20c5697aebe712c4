"""A smooth path as the lab's polynomial trajectory: 7th-order pieces, one CSV row per piece.

The Crazyflie's high-level commander flies a trajectory of pieces, each a ``duration`` and one
polynomial of degree 7 per coordinate x, y, z, yaw (8 coefficients, lowest order first, time
local to the piece). Its trajectory memory holds 4 KiB, i.e. at most ``MAX_PIECES`` = 31
uncompressed pieces (132 bytes each), so a plan never has more.

A piece on ``[0, h]`` is the unique degree-7 polynomial that matches the path's position,
velocity, acceleration and jerk at both ends (Hermite interpolation): neighbouring pieces then
join with continuous jerk, so the commanded thrust and attitude rate are continuous too. With
coefficients ``c_k``, ``p(s) = Σ_k c_k s^k``; the first four follow from the start values
(``c_k = p^(k)(0) / k!``), the last four solve the 4x4 system of the end values.

The CSV has the header line of the lab's ``figure8.csv`` and loads in
:func:`quadcore.sim.trajectories.parse_plan`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from quadcore.sim.trajectories import PolyTrajectory
from quadcore.store import store

MAX_PIECES = 31  # 4 KiB of trajectory memory / 132 bytes per uncompressed poly4d piece
DEGREE = 7
HEADER = "duration," + ",".join(f"{c}^{k}" for c in ("x", "y", "z", "yaw") for k in range(DEGREE + 1))


def _end_matrix(h: float) -> np.ndarray:
    """(4, 4) the k-th derivative (rows, k = 0..3) at ``s = h`` of ``s^j`` for j = 4..7 (columns)."""
    m = np.zeros((4, 4))
    for k in range(4):
        for col, j in enumerate(range(4, 8)):
            m[k, col] = math.factorial(j) / math.factorial(j - k) * h ** (j - k)
    return m


def hermite_piece(start: np.ndarray, end: np.ndarray, h: float) -> np.ndarray:
    """(8,) coefficients of the degree-7 polynomial on ``[0, h]`` with derivatives 0..3 equal to
    ``start`` (4,) at 0 and ``end`` (4,) at ``h``."""
    low = np.array([start[k] / math.factorial(k) for k in range(4)])
    # the low part's derivatives at h, subtracted from the end values
    low_at_end = np.array([sum(math.factorial(j) / math.factorial(j - k) * low[j] * h ** (j - k)
                               for j in range(k, 4)) for k in range(4)])
    high = np.linalg.solve(_end_matrix(h), np.asarray(end, float) - low_at_end)
    return np.concatenate([low, high])


def from_derivatives(knots_s: np.ndarray, derivs: np.ndarray, name: str = "plan") -> PolyTrajectory:
    """The trajectory through ``knots_s`` (m+1,) with ``derivs`` (m+1, 4 coordinates, 4 orders):
    position, velocity, acceleration and jerk of x, y, z, yaw at each knot."""
    if len(knots_s) - 1 > MAX_PIECES:
        raise ValueError(f"{len(knots_s) - 1} pieces: the Crazyflie holds at most {MAX_PIECES}")
    durations = np.diff(knots_s)
    coeffs = np.zeros((len(durations), 4, DEGREE + 1))
    for i, h in enumerate(durations):
        for c in range(4):
            coeffs[i, c] = hermite_piece(derivs[i, c], derivs[i + 1, c], float(h))
    return PolyTrajectory(name, durations, coeffs)


def to_csv(traj: PolyTrajectory) -> str:
    """The lab's CSV text: the header, then ``duration`` and 32 coefficients per piece."""
    rows = [HEADER]
    for d, c in zip(traj.durations, traj.coeffs):
        rows.append(",".join(f"{v:.9g}" for v in [d, *c.reshape(-1)]))
    return "\n".join(rows) + "\n"


def write_csv(traj: PolyTrajectory, path: str | Path) -> Path:
    """Write the CSV atomically (``quadcore.store.store.write_text``)."""
    return store.write_text(to_csv(traj), store.as_root(path))
