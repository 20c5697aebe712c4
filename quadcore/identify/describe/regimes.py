"""Where the model fails, by flight regime (speed, height, thrust-to-weight, angular rate,
battery voltage, acceleration, flight phase): each sample's regime variables, their bins and
labels, and the windows of the worst segments in time (``docs/diagnosis.md``, part 1). The
tables themselves come from each flight's stored sums (:mod:`quadcore.identify.describe.summaries`); the
same tables on rows, the reference they are tested against: tests/reference/tables.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadcore.identify.flightdata import FlightData
from quadcore.identify.settings import STATISTICS
from quadcore.physics import rotations, signals
from quadcore.physics.dynamics import GRAVITY_W_MPS2, XYZ

# the bins' edges (quadcore.identify.settings.STATISTICS)
SPEED_BINS = list(STATISTICS.speed_bins_mps)
HEIGHT_BINS = list(STATISTICS.height_bins_m)
THRUST_BINS = list(STATISTICS.thrust_to_weight_bins)
RATE_BINS = list(STATISTICS.angular_rate_bins_radps)
VBAT_BINS = list(STATISTICS.battery_bins_V)
ACCEL_BINS = list(STATISTICS.acceleration_bins_mps2)


@dataclass
class RegimeColumns:
    """Per-sample regime variables of one flight."""

    speed_mps: np.ndarray
    height_m: np.ndarray
    thrust_to_weight: np.ndarray
    angular_rate_radps: np.ndarray
    vbat_V: np.ndarray
    acceleration_mps2: np.ndarray
    phase: np.ndarray


def regime_columns(fd: FlightData, vehicle) -> RegimeColumns:
    s = fd.state
    sf_w = rotations.body_to_world(s.R_wb, signals.smooth(s.sf_b_mps2))
    a_w = GRAVITY_W_MPS2 + sf_w  # kinematic acceleration, from the smoothed accelerometer
    speed = np.linalg.norm(s.v_w_mps, axis=1)
    vz = s.v_w_mps[:, 2]
    tw = s.f_rotor_N.sum(axis=1) / vehicle.weight_N
    phase = np.where(
        tw < 0.5, "ground",
        np.where(vz > 0.2, "climb", np.where(vz < -0.2, "descent", np.where(speed < 0.1, "hover", "cruise"))),
    )
    return RegimeColumns(speed, s.p_w_m[:, 2], tw, np.linalg.norm(s.omega_b_radps, axis=1), s.vbat_V,
                         np.linalg.norm(a_w, axis=1), phase)


def bin_labels(edges: list[float], unit: str = "") -> list[str]:
    """The label of each bin: ``<e1``, ``e1-e2``, ..., ``ek+`` (edges ascending, first may be -inf)."""
    labels = []
    for i, lo in enumerate(edges):
        if i + 1 == len(edges):
            labels.append(f"{lo:g}+ {unit}")
        elif np.isinf(lo):
            labels.append(f"<{edges[i + 1]:g} {unit}")
        else:
            labels.append(f"{lo:g}-{edges[i + 1]:g} {unit}")
    return [label.strip() for label in labels]


def bin_codes(x: np.ndarray, edges: list[float]) -> np.ndarray:
    """Each value's bin, as its index in :func:`bin_labels`."""
    return np.searchsorted(np.asarray(edges[1:]), x, side="right")


def regime_codes(rc: RegimeColumns) -> dict[str, np.ndarray]:
    """Each sample's bin of every regime in :data:`REGIMES`, as its index in that regime's
    :data:`LABELS` (the row reference tests/reference/tables.py labels its rows with these)."""
    names, inverse = np.unique(rc.phase, return_inverse=True)
    codes = {"speed": bin_codes(rc.speed_mps, SPEED_BINS), "height": bin_codes(rc.height_m, HEIGHT_BINS),
             "thrust_to_weight": bin_codes(rc.thrust_to_weight, THRUST_BINS),
             "angular_rate": bin_codes(rc.angular_rate_radps, RATE_BINS), "battery": bin_codes(rc.vbat_V, VBAT_BINS),
             "acceleration": bin_codes(rc.acceleration_mps2, ACCEL_BINS),
             "phase": np.array([PHASES.index(str(n)) for n in names], dtype=int)[inverse.reshape(-1)]}
    return {r: codes[r] for r in REGIMES}


REGIMES = ("speed", "height", "thrust_to_weight", "angular_rate", "battery", "acceleration", "phase")
PHASES = ("ground", "climb", "descent", "hover", "cruise")
LABELS = {"speed": bin_labels(SPEED_BINS, "m/s"), "height": bin_labels(HEIGHT_BINS, "m"),
          "thrust_to_weight": bin_labels(THRUST_BINS, ""), "angular_rate": bin_labels(RATE_BINS, "rad/s"),
          "battery": bin_labels(VBAT_BINS, "V"), "acceleration": bin_labels(ACCEL_BINS, "m/s^2"), "phase": list(PHASES)}


RMSE_COLUMNS = [f"force_rmse_{a}_N" for a in XYZ] + [f"torque_rmse_{a}_Nm" for a in XYZ]
WINDOW_S = 0.5  # the worst segments' windows
TOP_SEGMENTS = 10  # the worst segments the diagnosis lists
