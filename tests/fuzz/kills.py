"""Kill tests: a writer killed (SIGKILL) at a random moment never leaves a torn file or an
unloadable learned model, and what it leaves behind is swept.

A child process rewrites the same outputs in a loop: a learned XGBoost model, a learned MLP
(both :meth:`LearnedModel.save`) and a Parquet table (:func:`store.write_parquet`). The parent
kills it at a random moment, then checks that every output present loads, and after all the
kills, that :func:`safewrite.sweep_stale` leaves no temp file or staging folder.

    python -m tests.fuzz.kills [N_KILLS]      (the fuzz harness runs it: make fuzz)
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.learn import artefacts, learners, trainers
from quadcore.store import ownership, safewrite, store

CHILD_TEMPLATE = "template"  # folder of models the child copies from (trained once by the parent)
OUTPUTS = ("xgboost", "mlp")


@dataclass
class KillReport:
    kills: int
    torn_files: int
    unloadable_models: int
    leftovers_before_sweep: int
    leftovers_after_sweep: int


def train_templates(folder: Path) -> None:
    """One tiny XGBoost and one tiny MLP model, trained on random data, saved under ``folder``."""
    from quadcore.learn import features as feat

    fs = feat.FEATURE_SETS["vel_rate"]
    rng = np.random.default_rng(0)
    tables = {}
    for f in ("a", "b", "c"):
        n = 400
        cols: dict[str, np.ndarray] = {c: rng.normal(size=n).astype(np.float32) for c in fs.columns}
        cols.update({c: rng.normal(size=n) for c in feat.TARGETS})
        tables[f] = pl.DataFrame({"t_s": np.arange(n) * 0.002, "near_gap": np.zeros(n, bool), **cols})
    config = learners.TrainConfig(stride=1, threads=1)
    specs = {"xgboost": learners.LearnerSpec("xgboost", max_depth=2, n_estimators=20, early_stopping_rounds=5),
             "mlp": learners.LearnerSpec("mlp", hidden=(8,), max_epochs=3, patience=2, batch_size=128)}
    for kind, spec in specs.items():
        trainers.train(spec, fs, tables, ["a", "b"], config).save(folder / kind)


def out_folder(root: Path) -> Path:
    """Where the child writes: an output folder of a data root the project made (the only kind
    :func:`safewrite.sweep_stale` sweeps)."""
    return root / "data" / "learned"


def child(root: Path) -> None:
    """Rewrite the outputs forever (until killed)."""
    models = {k: artefacts.load(root / CHILD_TEMPLATE / k) for k in OUTPUTS}
    table = pl.DataFrame({"x": np.arange(200_000, dtype=np.float64)})
    print("ready", flush=True)
    while True:
        for kind, m in models.items():
            m.save(out_folder(root) / kind)
        store.write_parquet(table, out_folder(root) / "table.parquet", {"n": table.height})


def _check(root: Path) -> tuple[int, int]:
    """(torn files, unloadable models) among the outputs present."""
    torn = unloadable = 0
    table = out_folder(root) / "table.parquet"
    if table.exists():
        try:
            torn += pl.read_parquet(table).height != 200_000
        except Exception:  # noqa: BLE001 (any failure to read is a torn file)
            torn += 1
    for kind in OUTPUTS:
        if (out_folder(root) / kind).exists():
            try:
                artefacts.load(out_folder(root) / kind)
            except learners.LearningError:
                unloadable += 1
    return torn, unloadable


def _leftovers(root: Path) -> int:
    return sum(1 for p in (out_folder(root)).rglob(".*") if p.name.endswith((".tmp", ".staging", ".old")))


def run(root: Path, n_kills: int, seed: int = 0, log=print) -> KillReport:
    rng = random.Random(seed)
    root.mkdir(parents=True, exist_ok=True)
    ownership.claim(root / "data")
    if not (root / CHILD_TEMPLATE).exists():
        train_templates(root / CHILD_TEMPLATE)
    torn = unloadable = 0
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    for i in range(n_kills):
        proc = subprocess.Popen([sys.executable, "-m", "tests.fuzz.kills", "--child", str(root)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.0, 0.4))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        t, u = _check(root)
        torn, unloadable = torn + t, unloadable + u
        if (i + 1) % 10 == 0:
            log(f"  {i + 1} kills: torn files {torn}, unloadable models {unloadable}")
    before = _leftovers(root)
    safewrite.sweep_stale(root / "data")
    return KillReport(n_kills, torn, unloadable, before, _leftovers(root))


def check_data_root(root: Path) -> tuple[int, int]:
    """(torn Parquet or JSON files, unloadable learned models) among a data root's outputs
    (temp files, staging folders and the Dagster instance aside)."""
    def visible(p: Path) -> bool:
        return not any(part.startswith(".") for part in p.relative_to(root).parts)

    torn = unloadable = 0
    for p in filter(visible, root.rglob("*.parquet")):
        try:
            pl.read_parquet(p)
        except Exception:  # noqa: BLE001 (any failure to read is a torn file)
            torn += 1
    for p in filter(visible, root.rglob("*.json")):
        try:
            json.loads(p.read_text())
        except ValueError:
            torn += 1
    for m in filter(visible, root.glob("learned/*/manifest.json")):
        try:
            artefacts.load(m.parent)
        except learners.LearningError:
            unloadable += 1
    return torn, unloadable


@dataclass
class PipelineKillReport:
    kills: int
    torn_files: int
    unloadable_models: int
    final_exit_code: int
    leftovers_after_final_run: int


def run_pipeline(root: Path, raw: Path, n_kills: int, seed: int = 0, log=print) -> PipelineKillReport:
    """Kill ``python -m pipeline`` (its whole process group) at random moments, check the data
    root after each kill, then let one run finish: it must exit 0 and sweep every leftover."""
    rng = random.Random(seed)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), "QUADCORE_DATA_ROOT": str(root),
           "QUADCORE_RAW_DIR": str(raw), "DAGSTER_HOME": str(root / ".dagster")}
    torn = unloadable = 0

    def start():
        return subprocess.Popen([sys.executable, "-m", "pipeline"], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
    for i in range(n_kills):
        proc = start()
        time.sleep(rng.uniform(2.0, 45.0))
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        t, u = check_data_root(root)
        torn, unloadable = torn + t, unloadable + u
        log(f"  pipeline kill {i + 1}: torn files {torn}, unloadable models {unloadable}")
    final = start()
    code = final.wait()
    t, u = check_data_root(root)
    leftovers = sum(1 for p in root.rglob(".*")
                    if ".dagster" not in p.parts and p.name.endswith((".tmp", ".staging", ".old")))
    return PipelineKillReport(n_kills, torn + t, unloadable + u, code, leftovers)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(Path(sys.argv[2]))
    else:
        import tempfile

        n = int(sys.argv[1]) if len(sys.argv) > 1 else 100
        with tempfile.TemporaryDirectory(prefix="quadcore-kills-") as tmp:
            report = run(Path(tmp), n)
        print(report)
        sys.exit(0 if report.torn_files == report.unloadable_models == report.leftovers_after_sweep == 0 else 1)
