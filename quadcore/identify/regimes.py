"""Where the model fails: the residual of the evaluated flights by flight regime (speed, height,
thrust-to-weight, angular rate, battery voltage, acceleration, flight phase), by flight, and its
worst segments in time (``docs/diagnosis.md``, part 1).
"""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass

import numpy as np
import polars as pl

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


def _bin_codes(x: np.ndarray, edges: list[float]) -> np.ndarray:
    """Each value's bin, as its index in :func:`bin_labels`."""
    return np.searchsorted(np.asarray(edges[1:]), x, side="right")


def _bin_labels(x: np.ndarray, edges: list[float], unit: str) -> np.ndarray:
    """Label each value with its bin (see :func:`bin_labels`)."""
    return np.asarray(bin_labels(edges, unit))[_bin_codes(x, edges)]


def regime_codes(rc: RegimeColumns) -> dict[str, np.ndarray]:
    """Each sample's bin of every regime in :data:`REGIMES`, as its index in that regime's
    :data:`LABELS` (the codes of :func:`long_frame`'s enums)."""
    names, inverse = np.unique(rc.phase, return_inverse=True)
    codes = {"speed": _bin_codes(rc.speed_mps, SPEED_BINS), "height": _bin_codes(rc.height_m, HEIGHT_BINS),
             "thrust_to_weight": _bin_codes(rc.thrust_to_weight, THRUST_BINS),
             "angular_rate": _bin_codes(rc.angular_rate_radps, RATE_BINS), "battery": _bin_codes(rc.vbat_V, VBAT_BINS),
             "acceleration": _bin_codes(rc.acceleration_mps2, ACCEL_BINS),
             "phase": np.array([PHASES.index(str(n)) for n in names], dtype=int)[inverse.reshape(-1)]}
    return {r: codes[r] for r in REGIMES}


def long_table(flights: list[FlightData], resid: dict[str, np.ndarray], vehicle) -> pl.DataFrame:
    """One row per usable sample of the evaluated flights: regime labels and the residual."""
    return pl.concat([long_frame(fd, resid[fd.flight], vehicle) for fd in flights])


def long_frame(fd: FlightData, r: np.ndarray, vehicle) -> pl.DataFrame:
    """One flight's part of :func:`long_table` (``r``: its (n, 6) residual)."""
    rc = regime_columns(fd, vehicle)
    m = fd.mask
    frame = {
        "flight": np.full(m.sum(), fd.flight),
        "t_s": fd.state.t_s[m],
        "speed": _bin_labels(rc.speed_mps[m], SPEED_BINS, "m/s"),
        "height": _bin_labels(rc.height_m[m], HEIGHT_BINS, "m"),
        "thrust_to_weight": _bin_labels(rc.thrust_to_weight[m], THRUST_BINS, ""),
        "angular_rate": _bin_labels(rc.angular_rate_radps[m], RATE_BINS, "rad/s"),
        "battery": _bin_labels(rc.vbat_V[m], VBAT_BINS, "V"),
        "acceleration": _bin_labels(rc.acceleration_mps2[m], ACCEL_BINS, "m/s^2"),
        "phase": rc.phase[m],
    }
    for j, a in enumerate(XYZ):
        frame[f"f_res_b_{a}_N"] = r[m, j]
        frame[f"tau_res_b_{a}_Nm"] = r[m, 3 + j]
    # labels as enums: a code per sample, not a string, so a thousand flights' table and the
    # group-bys over it stay small (the tables below turn them back into text)
    return pl.DataFrame(frame).with_columns(pl.col(k).cast(pl.Enum(v)) for k, v in LABELS.items())


REGIMES = ("speed", "height", "thrust_to_weight", "angular_rate", "battery", "acceleration", "phase")
PHASES = ("ground", "climb", "descent", "hover", "cruise")
LABELS = {"speed": bin_labels(SPEED_BINS, "m/s"), "height": bin_labels(HEIGHT_BINS, "m"),
          "thrust_to_weight": bin_labels(THRUST_BINS, ""), "angular_rate": bin_labels(RATE_BINS, "rad/s"),
          "battery": bin_labels(VBAT_BINS, "V"), "acceleration": bin_labels(ACCEL_BINS, "m/s^2"), "phase": list(PHASES)}


RESIDUAL_COLUMNS = [f"f_res_b_{a}_N" for a in XYZ] + [f"tau_res_b_{a}_Nm" for a in XYZ]
RMSE_COLUMNS = [f"force_rmse_{a}_N" for a in XYZ] + [f"torque_rmse_{a}_Nm" for a in XYZ]
RMSE_EXPRS = [(pl.col(r) ** 2).mean().sqrt().alias(name) for r, name in zip(RESIDUAL_COLUMNS, RMSE_COLUMNS)]
WINDOW_S = 0.5  # the worst segments' windows
TOP_SEGMENTS = 10


def regime_table(long: pl.DataFrame) -> pl.DataFrame:
    """Residual RMSE per axis in every bin of every regime variable, and the share of samples."""
    frames = []
    for regime in REGIMES:
        g = (long.group_by(regime).agg(pl.len().alias("samples"), *RMSE_EXPRS).rename({regime: "bin"})
             .with_columns(pl.col("bin").cast(pl.String)))
        frames.append(g.with_columns(pl.lit(regime).alias("regime")).sort("bin"))
    out = pl.concat(frames).select("regime", "bin", "samples", pl.exclude("regime", "bin", "samples"))
    return out.with_columns((pl.col("samples") / long.height).alias("share"))


def flight_table(long: pl.DataFrame) -> pl.DataFrame:
    return long.group_by("flight").agg(pl.len().alias("samples"), *RMSE_EXPRS).sort("flight")


def worst_segments(long: pl.DataFrame, window_s: float = WINDOW_S, top: int = TOP_SEGMENTS) -> pl.DataFrame:
    """The ``top`` windows (non-overlapping, per flight) with the largest force-residual RMS."""
    force_sq = functools.reduce(operator.add, [pl.col(f"f_res_b_{a}_N") ** 2 for a in XYZ])
    seg = (
        long.select("flight", "t_s", (pl.col("t_s") // window_s).alias("segment"), force_sq.alias("f2"),
                    pl.col("phase", "speed", "height").cast(pl.String))  # a tied mode picks as on text
        .group_by("flight", "segment")
        .agg(
            pl.col("t_s").min().alias("t_start_s"),
            pl.col("t_s").max().alias("t_end_s"),
            pl.col("f2").mean().sqrt().alias("force_rms_N"),
            pl.col("phase").mode().first().alias("phase"),
            pl.col("speed").mode().first().alias("speed"),
            pl.col("height").mode().first().alias("height"),
        )
        .sort("force_rms_N", descending=True)
        .head(top)
        .drop("segment")
    )
    return seg
