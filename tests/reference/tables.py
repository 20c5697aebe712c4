"""The reference the diagnosis's descriptive tables from stored summaries
(:func:`quadcore.identify.describe.summaries.regime_table`, :func:`~quadcore.identify.describe.summaries.flight_table`,
:func:`~quadcore.identify.describe.summaries.worst_segments`) are tested against: the same tables written on
the flights' rows, one polars row per usable sample (:func:`long_table`), grouped and aggregated
as readably as the definitions. Nothing in quadcore uses them; tests/test_summaries.py compares
against them. The bins, labels and regime codes both read: :mod:`quadcore.identify.describe.regimes`."""

from __future__ import annotations

import functools
import operator

import numpy as np
import polars as pl

from quadcore.identify.describe.regimes import (
    ACCEL_BINS,
    HEIGHT_BINS,
    LABELS,
    RATE_BINS,
    REGIMES,
    RMSE_COLUMNS,
    SPEED_BINS,
    THRUST_BINS,
    TOP_SEGMENTS,
    VBAT_BINS,
    WINDOW_S,
    bin_codes,
    bin_labels,
    regime_columns,
)
from quadcore.identify.flightdata import FlightData
from quadcore.physics.dynamics import XYZ

RESIDUAL_COLUMNS = [f"f_res_b_{a}_N" for a in XYZ] + [f"tau_res_b_{a}_Nm" for a in XYZ]
RMSE_EXPRS = [(pl.col(r) ** 2).mean().sqrt().alias(name) for r, name in zip(RESIDUAL_COLUMNS, RMSE_COLUMNS)]


def _bin_labels(x: np.ndarray, edges: list[float], unit: str) -> np.ndarray:
    """Label each value with its bin (see :func:`quadcore.identify.describe.regimes.bin_labels`)."""
    return np.asarray(bin_labels(edges, unit))[bin_codes(x, edges)]


def long_table(flights: list[FlightData], resid: dict[str, np.ndarray], vehicle) -> pl.DataFrame:
    """One row per usable sample of the evaluated flights: regime labels and the residual."""
    return pl.concat([long_frame(fd, resid[fd.flight], vehicle) for fd in flights])


def long_frame(fd: FlightData, r: np.ndarray, vehicle) -> pl.DataFrame:
    """One flight's part of :func:`long_table` (``r``: its (n, 6) residual); its labels' codes are
    :func:`quadcore.identify.describe.regimes.regime_codes`."""
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
    """Residual RMSE per axis of each flight, and its samples."""
    return long.group_by("flight").agg(pl.len().alias("samples"), *RMSE_EXPRS).sort("flight")


def worst_segments(long: pl.DataFrame, window_s: float = WINDOW_S, top: int = TOP_SEGMENTS) -> pl.DataFrame:
    """The ``top`` windows (non-overlapping, per flight) with the largest force-residual RMS."""
    force_sq = functools.reduce(operator.add, [pl.col(f"f_res_b_{a}_N") ** 2 for a in XYZ])
    return (
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

