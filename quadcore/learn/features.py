"""Feature sets for learning the residual: named column lists over residual tables.

A **residual table** (:mod:`quadcore.physics.residuals`) holds, per sample, the flight state, the
inputs and the residual force and torque left after the *current* physics model (nominal
vehicle + whatever effects the user added). The **targets** of every learned model are that
residual in the **body frame**, SI::

    f_res_b_{x,y,z}_N      residual force, N          (measured m·sf_b − modelled)
    tau_res_b_{x,y,z}_Nm   residual torque, N m

so a learned model sits on top of the physics model it was trained against.

**Feature sets** (``FEATURE_SETS``; define more with :func:`custom` or ``name=col+col`` in
:func:`parse`). Every column name carries its frame and unit:

=================  ==========================================================================
``vel_rate``       world velocity ``v_w_*_mps`` + body angular rate ``omega_b_*_radps``
                   (the study's "velocity + angular rate").
``acc_rate_rot``   measured acceleration ``a_meas_w_*_mps2`` + angular rate + the first two
                   columns of the rotation matrix body->world ``R_wb_{0,1,2}{0,1}`` (the
                   study's second set). **It sees the target**: the measured acceleration is
                   the accelerometer's specific force rotated to the world frame, the very
                   measurement the residual force is computed from (``f_res_b = m sf_b −
                   model``), and with the attitude columns a model can undo the rotation.
                   Its score is reported, flagged ``causal = False``, and never chosen as the
                   best model: a simulator or a controller does not know the acceleration it
                   is trying to predict.
``full_state``     everything logged but the accelerometer: position ``p_w_*``, velocity
                   ``v_w_*``, attitude quaternion ``qc_*`` (sign fixed to ``qc_w >= 0``),
                   angular rate, motor speeds, PWM and battery voltage.
``physics``        physics-informed: body-frame velocity ``v_b_*_mps`` (rotor drag acts in
                   the rotor plane), collective thrust ``T_N`` of the thrust map, motor speeds
                   ``motor_*_radps`` and height ``p_w_z_m`` (ground effect).
``physics_rate``   ``physics`` + body angular rate (gyroscopic and rate-dependent torques).
=================  ==========================================================================

**Rows.** Samples whose smoothing window spans a logging gap (``near_gap``) have unreliable
residuals: they are dropped from training and from scoring (:func:`usable`).

**Scaling** (:class:`Scaler`) is a per-column standardisation fitted on the training
flights' usable rows only, never on a held-out flight, for the inputs and the targets alike
(the study's torque scaling leaked test data into training; this one cannot: it is fitted
inside the training function from the training flights it is given).
"""

from __future__ import annotations

import csv
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.physics import residuals, rotations
from quadcore.physics.dynamics import XYZ, cols
from quadcore.store import safewrite, store

TARGET_FORCE = list(residuals.F_RES_B)  # f_res_b_{x,y,z}_N
TARGET_TORQUE = list(residuals.TAU_RES_B)  # tau_res_b_{x,y,z}_Nm
TARGETS = TARGET_FORCE + TARGET_TORQUE
TARGET_UNITS = ["N"] * 3 + ["N m"] * 3

# The first two columns of R_wb (body x and y axes expressed in the world frame): R_wb_ij is
# row i, column j.
ROTATION_COLUMNS = [f"R_wb_{i}{j}" for j in (0, 1) for i in (0, 1, 2)]
QUATERNION_COLUMNS = ["qc_x", "qc_y", "qc_z", "qc_w"]
MOTOR_SPEED = [f"motor_{i}_radps" for i in range(1, 5)]
PWM = [f"pwm_{i}" for i in range(1, 5)]


class FeatureError(ValueError):
    """A feature set that names unknown columns, or a table that lacks them."""


@dataclass(frozen=True)
class FeatureSet:
    """A named list of input columns (of a residual table, after :func:`with_derived`)."""

    name: str
    columns: tuple[str, ...]
    description: str = ""
    causal: bool = True  # False: some column is measured by the sensor the target comes from
    note: str = ""

    def to_dict(self) -> dict:
        return {"name": self.name, "columns": list(self.columns), "description": self.description,
                "causal": self.causal, "note": self.note}

    @classmethod
    def from_dict(cls, d: dict) -> FeatureSet:
        return cls(d["name"], tuple(d["columns"]), d.get("description", ""), bool(d.get("causal", True)),
                   d.get("note", ""))


LEAK_NOTE = ("uses the measured acceleration, i.e. the accelerometer the residual force is computed from: "
             "it sees the target (not usable in a simulator); reported for comparison with the study only")

FEATURE_SETS: dict[str, FeatureSet] = {
    fs.name: fs for fs in (
        FeatureSet("vel_rate", (*cols("v_w", "mps"), *cols("omega_b", "radps")),
                   "world velocity + body angular rate"),
        FeatureSet("acc_rate_rot", (*cols("a_meas_w", "mps2"), *cols("omega_b", "radps"), *ROTATION_COLUMNS),
                   "measured acceleration + angular rate + first two columns of R_wb", causal=False, note=LEAK_NOTE),
        FeatureSet("full_state", (*cols("p_w", "m"), *cols("v_w", "mps"), *QUATERNION_COLUMNS,
                                  *cols("omega_b", "radps"), *MOTOR_SPEED, *PWM, "vbat_V"),
                   "position, velocity, attitude, angular rate, motor speeds, PWM, battery voltage"),
        FeatureSet("physics", (*cols("v_b", "mps"), "T_N", *MOTOR_SPEED, "p_w_z_m"),
                   "body-frame velocity, thrust, motor speeds, height"),
        FeatureSet("physics_rate", (*cols("v_b", "mps"), "T_N", *MOTOR_SPEED, "p_w_z_m", *cols("omega_b", "radps")),
                   "physics + body angular rate"),
    )
}
DEFAULT_FEATURE_SETS = tuple(FEATURE_SETS)
PRIMARY_FEATURE_SET = "physics"  # the one the training-size, complexity and cross-validation comparisons use


def custom(name: str, columns: list[str] | tuple[str, ...], description: str = "") -> FeatureSet:
    """A user feature set. Columns: any numeric column of a residual table or a derived one."""
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise FeatureError(f"feature set name {name!r}: use letters, digits, '_' or '-'")
    columns = tuple(c.strip() for c in columns if c.strip())
    if not columns:
        raise FeatureError(f"feature set {name!r} has no columns")
    if len(set(columns)) != len(columns):
        raise FeatureError(f"feature set {name!r} lists a column twice: {list(columns)}")
    leaky = [c for c in columns if c.startswith(("a_meas_w_", "sf_b_", "f_meas_b_", "tau_meas_b_", "omega_dot_b_",
                                                 "f_res_", "tau_res_"))]
    return FeatureSet(name, columns, description or "+".join(columns), causal=not leaky,
                      note=f"measured from the target's sensors: {', '.join(leaky)}" if leaky else "")


def parse(spec: str | list[str] | None) -> list[FeatureSet]:
    """``"physics,vel_rate,mine=v_b_x_mps+T_N"`` -> feature sets (None/empty: the defaults)."""
    items = spec if isinstance(spec, list) else [s for s in (spec or "").split(",")]
    items = [s.strip() for s in items if s and s.strip()]
    if not items:
        return [FEATURE_SETS[n] for n in DEFAULT_FEATURE_SETS]
    out: list[FeatureSet] = []
    for item in items:
        if "=" in item:
            name, _, columns = item.partition("=")
            out.append(custom(name.strip(), columns.split("+")))
        elif item in FEATURE_SETS:
            out.append(FEATURE_SETS[item])
        else:
            raise FeatureError(f"unknown feature set {item!r}; known: {', '.join(FEATURE_SETS)} "
                               "(or define one as name=col1+col2+...)")
    names = [fs.name for fs in out]
    if len(set(names)) != len(names):
        raise FeatureError(f"a feature set is named twice: {names}")
    return out


def with_derived(table: pl.DataFrame) -> pl.DataFrame:
    """The table plus derived columns: ``R_wb_ij`` (first two columns of the rotation matrix)
    and ``qc_*`` (the attitude quaternion with the sign that makes ``qc_w >= 0``, so that ``q``
    and ``-q``, the same attitude, are one input)."""
    if "q_w" not in table.columns or "R_wb_00" in table.columns:
        return table
    q = table.select("q_x", "q_y", "q_z", "q_w").to_numpy().astype(np.float64)
    R = rotations.rotation_matrix(q)
    sign = np.where(q[:, 3] < 0, -1.0, 1.0)
    extra = {f"R_wb_{i}{j}": R[:, i, j] for j in (0, 1) for i in (0, 1, 2)}
    extra.update({f"qc_{a}": q[:, k] * sign for k, a in enumerate(("x", "y", "z", "w"))})
    return table.with_columns(**{k: pl.Series(v) for k, v in extra.items()})


def missing_columns(fs: FeatureSet, table: pl.DataFrame) -> list[str]:
    return [c for c in fs.columns if c not in table.columns]


def check(fs: FeatureSet, table: pl.DataFrame, where: str = "table") -> None:
    missing = missing_columns(fs, table)
    if missing:
        raise FeatureError(f"feature set {fs.name!r}: {where} has no column(s) {', '.join(missing)}")


def usable(table: pl.DataFrame) -> np.ndarray:
    """Rows to learn from and score on: not ``near_gap`` (in a feature table, rows with a
    non-finite feature or target are flagged ``near_gap`` as well)."""
    ok = ~table["near_gap"].to_numpy() if "near_gap" in table.columns else np.ones(table.height, bool)
    return ok


def feature_table(residual_table: pl.DataFrame, fs: FeatureSet) -> pl.DataFrame:
    """``t_s``, ``near_gap``, the feature columns (float32) and the targets (float64) of one
    flight: what a learned model reads and what it is scored against. Rows with a non-finite
    feature or target are flagged ``near_gap`` too (so that they are never used)."""
    t = with_derived(residual_table)
    check(fs, t, "residual table")
    out = t.select("t_s", "near_gap", *[pl.col(c).cast(pl.Float32) for c in fs.columns],
                   *[pl.col(c).cast(pl.Float64) for c in TARGETS if c in t.columns])
    finite = np.isfinite(out.select(*fs.columns, *[c for c in TARGETS if c in out.columns]).to_numpy()).all(axis=1)
    if not finite.all():
        out = out.with_columns(near_gap=pl.Series(out["near_gap"].to_numpy() | ~finite))
    return out


def matrix(table: pl.DataFrame, fs: FeatureSet) -> np.ndarray:
    """(n, k) float32 C-contiguous input matrix (derived columns computed when needed)."""
    t = table if all(c in table.columns for c in fs.columns) else with_derived(table)
    check(fs, t)
    return np.ascontiguousarray(t.select(fs.columns).to_numpy().astype(np.float32))


def targets(table: pl.DataFrame) -> np.ndarray:
    """(n, 6) residual force (N) and torque (N m), body frame."""
    missing = [c for c in TARGETS if c not in table.columns]
    if missing:
        raise FeatureError(f"table has no target column(s) {', '.join(missing)}")
    return table.select(TARGETS).to_numpy().astype(np.float64)


@dataclass
class Scaler:
    """Per-column standardisation ``(x - mean) / std``; a constant column gets std 1."""

    names: list[str]
    mean: np.ndarray
    std: np.ndarray
    fitted_on: list[str] = field(default_factory=list)  # flights
    rows: int = 0

    @classmethod
    def fit(cls, X: np.ndarray, names: list[str], fitted_on: list[str] | None = None) -> Scaler:
        X = np.asarray(X, dtype=np.float64)
        if X.shape[0] == 0:
            raise FeatureError("cannot fit a scaler on zero rows")
        mean = X.mean(axis=0)
        std = X.std(axis=0)
        std = np.where(std > 1e-12 * np.maximum(np.abs(mean), 1e-300), std, 1.0)
        std = np.where(std > 0, std, 1.0)
        return cls(list(names), mean, std, list(fitted_on or []), int(X.shape[0]))

    def transform(self, X: np.ndarray, dtype=np.float32) -> np.ndarray:
        return ((np.asarray(X, dtype=np.float64) - self.mean) / self.std).astype(dtype)

    def inverse(self, Z: np.ndarray) -> np.ndarray:
        return np.asarray(Z, dtype=np.float64) * self.std + self.mean

    def to_dict(self) -> dict:
        return {"names": self.names, "mean": self.mean.tolist(), "std": self.std.tolist(),
                "fitted_on": self.fitted_on, "rows": self.rows}

    @classmethod
    def from_dict(cls, d: dict) -> Scaler:
        return cls(list(d["names"]), np.asarray(d["mean"], float), np.asarray(d["std"], float),
                   list(d.get("fitted_on", [])), int(d.get("rows", 0)))


# ---------------------------------------------------------------------------------------
# Feature tables on disk, and what kind each flight is
# ---------------------------------------------------------------------------------------

def feature_path(root: Path, feature_set: str, flight: str) -> Path:
    return store.table_path(store.as_root(root) / "features", feature_set, flight)


def write_feature_tables(root: Path, residual_tables: Mapping[str, pl.DataFrame], sets: list[FeatureSet],
                         provenance: dict | None = None) -> dict[str, list[Path]]:
    """``<root>/features/<set>/flight=<id>/data.parquet`` for every set and flight; a set whose
    columns a table lacks raises :class:`FeatureError`. Returns set name -> paths."""
    out: dict[str, list[Path]] = {fs.name: [] for fs in sets}
    for fid in residual_tables:  # flight by flight: each residual table is read once, whatever the sets
        table = residual_tables[fid]
        for fs in sets:
            ft = feature_table(table, fs)
            meta = {"flight": fid, "feature_set": fs.to_dict(), "targets": TARGETS, **(provenance or {})}
            out[fs.name].append(store.write_parquet(ft, feature_path(root, fs.name, fid), meta))
    return out


def replace_feature_tables(root: Path, residual_tables: Mapping[str, pl.DataFrame], sets: list[FeatureSet],
                           provenance: dict | None = None) -> dict[str, list[Path]]:
    """Write every feature table into a staging folder, then swap it for ``<root>/features`` in
    two renames: a failure half-way leaves the previous tables whole, and readers never see a
    half-written set. In an object store (no renames) each table is replaced whole, in place,
    and the tables of sets and flights no longer there are removed."""
    root = store.as_root(root)
    if store.is_remote(root):  # no folder renames in an object store: each table is replaced whole, in place
        written = write_feature_tables(root, residual_tables, sets, provenance)
        for folder in (root / "features").iterdir() if (root / "features").is_dir() else []:
            for table in folder.glob("flight=*") if folder.name in written else [folder]:
                if folder.name not in written or table.name.split("=", 1)[1] not in residual_tables:
                    store.remove_tree(table)  # a set no longer asked for, or a flight no longer there
        return written
    # staging and old folders named as every writer's (safewrite): the sweep knows them by their pid
    staging = safewrite.staging_folder(root / "features")
    try:
        write_feature_tables(staging, residual_tables, sets, provenance)
        safewrite.replace_folder(staging / "features", root / "features")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {fs.name: [feature_path(root, fs.name, f) for f in residual_tables] for fs in sets}


# Each feature set's tables keep at most this many bytes of recently read flights: a training run
# reads its flights twice (usable rows, then the rows it holds), and the five sets' caches
# together stay small whatever the fleet (the 19 real flights' tables fit in it: each is read once).
FEATURE_CACHE_BYTES = 64 << 20


def read_feature_tables(root: Path) -> tuple[list[FeatureSet], dict[str, Mapping[str, pl.DataFrame]]]:
    """Every feature set under ``<root>/features`` (its definition from the files' metadata)
    and its tables, each read when it is looked up: (sets, {set name: {flight: table}})."""
    sets: list[FeatureSet] = []
    tables: dict[str, Mapping[str, pl.DataFrame]] = {}
    base = store.as_root(root) / "features"
    for folder in sorted(p for p in base.glob("*") if p.is_dir()) if base.is_dir() else []:
        files = sorted(folder.glob("flight=*/data.parquet"))
        if not files:
            continue
        meta = store.read_metadata(files[0])
        sets.append(FeatureSet.from_dict(meta["feature_set"]))
        tables[folder.name] = store.flight_tables(folder, FEATURE_CACHE_BYTES)
    return sets, tables


def read_residual_tables(root: Path) -> Mapping[str, pl.DataFrame]:
    """Every ``<root>/residuals/flight=<id>/data.parquet`` by flight id, sorted, each read when
    it is looked up (:class:`quadcore.store.store.FlightTables`)."""
    return store.flight_tables(store.as_root(root) / "residuals")


def read_flight_kinds(path: str | Path | None) -> dict[str, str]:
    """``flights.csv`` (columns ``flight``, ``kind``) -> {flight: kind}; {} when absent."""
    if not path or not store.as_root(path).is_file():
        return {}
    with store.as_root(path).open("r", newline="") as fh:  # here or in an object store
        return {row["flight"].strip(): row["kind"].strip() for row in csv.DictReader(fh)
                if row.get("flight") and row.get("kind")}


def find_flights_csv(*folders: str | Path | None) -> Path | None:
    """The first ``flights.csv`` in the given folders or their parents."""
    for folder in folders:
        if not folder:
            continue

        folder = store.as_root(folder)
        for cand in (folder / "flights.csv", folder.parent / "flights.csv"):
            if cand.is_file():
                return cand
    return None


def feature_tables(residual_tables: Mapping[str, pl.DataFrame],
                   sets: list[FeatureSet]) -> dict[str, dict[str, pl.DataFrame]]:
    """{set name: {flight: feature table}} for every set and flight (in memory)."""
    return {fs.name: {fid: feature_table(t, fs) for fid, t in residual_tables.items()} for fs in sets}


__all__ = ["FeatureSet", "FEATURE_SETS", "TARGETS", "Scaler", "feature_table", "matrix", "targets", "parse", "custom",
           "with_derived", "usable", "feature_tables", "XYZ"]
