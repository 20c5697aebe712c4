"""Fit the motor-speed thrust map ``f = k_F omega^2`` from flight data.

The accelerometer gives the collective non-gravitational force along body z,
``m sf_z``; with the rotors the only large z force, ``m sf_z ≈ k_F Σ_i omega_i^2``.
Least squares over all airborne samples (collective thrust above half the weight) gives::

    k_F = Σ (m sf_z S) / Σ S^2,   S = Σ_i omega_i^2

Reported per flight too: a k_F that differs between groups of flights means the
speed-to-thrust relation changed (e.g. other propellers or RPM sensor settings).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.physics import signals
from quadcore.physics.vehicle import Vehicle
from quadcore.store import store


def speed_squared_sum(df: pl.DataFrame, n_rotors: int) -> np.ndarray:
    w = df.select([f"motor_{i}_radps" for i in range(1, n_rotors + 1)]).to_numpy()
    return np.square(w).sum(axis=1)


def fit_k_F(flights: dict[str, pl.DataFrame], vehicle: Vehicle) -> tuple[float, dict[str, float]]:
    """(k_F over all flights, k_F per flight) in N/(rad/s)^2."""
    num, den, per_flight = 0.0, 0.0, {}
    for fid, df in flights.items():
        S = speed_squared_sum(df, vehicle.n_rotors)
        fz = vehicle.mass_kg * signals.smooth(df["sf_b_z_mps2"].to_numpy())
        airborne = fz > 0.5 * vehicle.weight_N
        if airborne.sum() < 10:
            continue
        a, b = float(fz[airborne] @ S[airborne]), float(S[airborne] @ S[airborne])
        per_flight[fid] = a / b
        num, den = num + a, den + b
    if den == 0:
        raise ValueError("no airborne samples with motor speeds: cannot fit k_F")
    return num / den, per_flight


def write_k_F(vehicle_toml_text: str, k_F: float, out: Path) -> Path:
    """Write a copy of a vehicle file with ``k_F_N_per_radps2`` replaced."""
    new, n = re.subn(r"(?m)^(\s*k_F_N_per_radps2\s*=\s*)[^#\n]*", rf"\g<1>{k_F:.6e} ", vehicle_toml_text)
    if n != 1:
        raise ValueError("vehicle file has no single 'k_F_N_per_radps2 = ...' line under [thrust_map.motor_speed]")
    return store.write_text(new, out)  # atomic: a kill never leaves half a vehicle file
