"""A trained residual model and its folder: :class:`LearnedModel` (``predict``, ``predict_table``,
``predict_one``), :meth:`LearnedModel.save` and :func:`load`.

One folder per model under ``<root>/learned/<run name>/``: ``model.ubj`` (XGBoost) or ``model.pt``
(torch state dict), ``scaler.json``, ``features.json``, ``manifest.json`` and ``predictions.parquet``
(``docs/learning.md`` lists what each holds)::

    m = artefacts.load("data/learned/holdout-jana02__all__physics__xgboost-d6")
    f_N, tau_Nm = m.predict(table)        # (n, 3) each, body frame, SI

torch and xgboost are imported by :func:`quadcore.learn.backends.backend` when a model of their kind is
read, run or saved, so importing this module is cheap.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.identify import model as modelmod
from quadcore.learn import features as feat
from quadcore.learn.backends import backend
from quadcore.learn.features import TARGETS, FeatureSet, Scaler
from quadcore.learn.learners import LearnerSpec, LearningError
from quadcore.learn.trees import CompiledForest
from quadcore.physics import vehicle as vehiclemod
from quadcore.store import safewrite, store

FORMAT = "quadcore-learned/1"


PRED_COLUMNS = [f"f_learned_b_{a}_N" for a in "xyz"] + [f"tau_learned_b_{a}_Nm" for a in "xyz"]


class LearnedModel:
    """A trained residual model: predicts the body-frame residual force (N) and torque (N m)
    left after the physics model named in ``manifest["physics_model"]``."""

    def __init__(self, spec: LearnerSpec, feature_set: FeatureSet, x_scaler: Scaler, y_scaler: Scaler,
                 impl, manifest: dict | None = None):
        self.spec = spec
        self.feature_set = feature_set
        self.x_scaler = x_scaler
        self.y_scaler = y_scaler
        self.impl = impl  # xgboost.Booster or torch.nn.Module
        self._backend = backend(spec.kind)  # its kind's module (loaded with impl already), held for predict_one
        self.manifest = manifest or {}
        self._forest: CompiledForest | None = None

    @property
    def kind(self) -> str:
        return self.spec.kind

    @property
    def features(self) -> list[str]:
        return list(self.feature_set.columns)

    @property
    def label(self) -> str:
        return f"{self.kind}({self.feature_set.name})"

    # -- prediction ------------------------------------------------------------------
    def predict_matrix(self, X: np.ndarray) -> np.ndarray:
        """Raw feature matrix (n, k) -> (n, 6) residual [f_x, f_y, f_z, tau_x, tau_y, tau_z], SI."""
        Z = self.x_scaler.transform(X)
        out = self._backend.predict(self.impl, Z)
        return self.y_scaler.inverse(np.asarray(out).reshape(len(Z), -1))

    def predict_one(self, x: np.ndarray) -> np.ndarray:
        """One sample (k,) -> (6,), the low-latency path: the compiled forest for trees, a
        (1, k) tensor under ``no_grad`` for the MLP."""
        z = ((np.asarray(x, np.float64) - self.x_scaler.mean) / self.x_scaler.std).astype(np.float32)
        if self.kind == "xgboost":
            if self._forest is None:
                self._forest = CompiledForest(self.impl)
            y = self._forest.predict_one(z)
        else:
            y = self._backend.predict(self.impl, z[None, :])[0]
        return y * self.y_scaler.std + self.y_scaler.mean

    def _feature_source(self, table: pl.DataFrame, flight: str | None = None) -> pl.DataFrame:
        t = feat.with_derived(table)
        if not feat.missing_columns(self.feature_set, t):
            return t
        if "pwm_1" in table.columns and "T_N" not in table.columns:  # a decoded table: build the residual table
            physics = self.physics_model()
            # the residuals it was trained on: each flight's session values and thrust map
            physics = physics.for_flight(flight) if flight is not None else physics
            t = feat.with_derived(physics.residual_table(table))
        feat.check(self.feature_set, t, "flight table")
        return t

    def predict(self, table: pl.DataFrame, flight: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A flight table (residual table of the same physics model, or a decoded
        ``fixedFrequency`` table) -> residual force (n, 3) in N and torque (n, 3) in N m,
        body frame. For a decoded table of a physics model with per-session values, name the
        ``flight``: its residual is built with its session's values, as in training (without,
        the fleet values). Rows with a missing input get NaN from the MLP and the trees'
        default branch from XGBoost."""
        y = self.predict_matrix(feat.matrix(self._feature_source(table, flight), self.feature_set))
        return y[:, :3], y[:, 3:]

    def predict_table(self, table: pl.DataFrame, flight: str | None = None) -> pl.DataFrame:
        f, tau = self.predict(table, flight)
        out = {"t_s": table["t_s"]} if "t_s" in table.columns else {}
        out.update({c: v for c, v in zip(PRED_COLUMNS, np.concatenate([f, tau], axis=1).T)})
        return pl.DataFrame(out)

    def physics_model(self):
        """The physics model this model was trained against (from the manifest). Its plugin effects
        must be loaded already, from the model file the user gave: the manifest's are checked by
        name and digest, never imported (:func:`quadcore.identify.model.check_plugins`)."""
        pm = self.manifest.get("physics_model") or {}
        modelmod.check_plugins(pm, "the learned model's manifest")
        return modelmod.PhysicsModel.from_dict(pm, vehicle_of(pm))

    def importance(self) -> dict[str, float]:
        """XGBoost total gain per feature, normalised to sum 1 ({} for the MLP)."""
        if self.kind != "xgboost":
            return {}
        gain = self.impl.get_score(importance_type="total_gain")
        vals = np.array([gain.get(f"f{i}", 0.0) for i in range(len(self.features))])
        total = vals.sum() or 1.0
        return {n: float(v / total) for n, v in zip(self.features, vals)}

    # -- artefacts -------------------------------------------------------------------
    def save(self, folder: str | Path, predictions: pl.DataFrame | None = None) -> Path:
        """Write the artefacts (and ``predictions.parquet``) into a staging folder, the manifest
        last, and put it in place whole: a kill leaves the previous model or the new one, never
        a torn one."""
        dest: Path = store.as_root(folder)  # a local Path, or a UPath in an object store
        if store.is_remote(dest):  # written here, then uploaded with the manifest last
            with tempfile.TemporaryDirectory(prefix="quadcore-model-") as local:
                self._write(Path(local), dest.name, predictions)
                return store.upload_folder(Path(local), dest, last="manifest.json")
        staging = safewrite.staging_folder(dest)
        try:
            self._write(staging, dest.name, predictions)
            return safewrite.replace_folder(staging, dest)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _write(self, folder: Path, run: str, predictions: pl.DataFrame | None) -> None:
        """The artefacts into the local folder ``folder``, the manifest last."""
        if predictions is not None:
            store.write_parquet(predictions, folder / "predictions.parquet", {"run": run})
        self._backend.save(self.impl, folder)
        store.write_json({"x": self.x_scaler.to_dict(), "y": self.y_scaler.to_dict()}, folder / "scaler.json")
        store.write_json(self.feature_set.to_dict(), folder / "features.json")
        store.write_json({"format": FORMAT, **self.manifest, "kind": self.kind, "spec": self.spec.to_dict(),
                          "feature_set": self.feature_set.to_dict(), "targets": TARGETS}, folder / "manifest.json")


def vehicle_of(physics: dict):
    """The vehicle a physics-model dict (``PhysicsModel.to_dict()``) names, with its thrust map."""
    src = physics.get("vehicle_source") or physics.get("vehicle")
    name = src.split(":", 1)[1] if src and src.startswith("builtin:") else src
    veh = vehiclemod.load(name or None)
    return veh.with_thrust_map(physics["thrust_map"]) if physics.get("thrust_map") else veh


def load(folder: str | Path, threads: int = 1, torch_threads: int = 1) -> LearnedModel:
    """A model saved by :meth:`LearnedModel.save`; :class:`LearningError` for anything else
    (a missing or malformed manifest, scaler, feature list or weights)."""
    where: Path = store.as_root(folder)  # a local Path, or a UPath in an object store
    mpath = where / "manifest.json"
    if not mpath.is_file():
        raise LearningError(f"no learned model in {where} (no manifest.json)")
    try:
        if store.is_remote(where):  # the weights load from local files: copied here first
            with tempfile.TemporaryDirectory(prefix="quadcore-model-") as local:
                here = store.download_folder(where, Path(local))
                return _load(here, here / "manifest.json", threads, torch_threads)
        return _load(where, mpath, threads, torch_threads)
    except LearningError:
        raise
    except Exception as exc:  # noqa: BLE001 (json, xgboost, torch and pickle each have their own errors)
        raise LearningError(f"{where}: malformed learned model ({type(exc).__name__}: {str(exc)[:200]})") from None


def _load(folder: Path, mpath: Path, threads: int, torch_threads: int) -> LearnedModel:
    manifest = json.loads(mpath.read_text())
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise LearningError(f"{mpath}: not a {FORMAT} manifest")
    spec = LearnerSpec.from_dict(manifest["spec"])
    fs = FeatureSet.from_dict(json.loads((folder / "features.json").read_text()))
    sc = json.loads((folder / "scaler.json").read_text())
    xs, ys = Scaler.from_dict(sc["x"]), Scaler.from_dict(sc["y"])
    impl = backend(spec.kind).load(folder, spec, len(fs.columns), len(TARGETS),
                                   threads if spec.kind == "xgboost" else torch_threads)
    return LearnedModel(spec, fs, xs, ys, impl, manifest)
