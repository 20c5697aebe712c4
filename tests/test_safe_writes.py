"""Writes that survive a kill, leftovers swept, concurrent jobs serialised, malformed learned
artefacts reported as the learning module's own error."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from fuzz import kills

from quadcore.learn import artefacts, learners
from quadcore.store import ownership, safewrite, store


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_sweep_removes_what_dead_writers_left_and_nothing_else(tmp_path):
    dead, now = _dead_pid(), time.time()
    ownership.claim(tmp_path)
    leftovers = [tmp_path / "decoded" / f".data.parquet.{dead}.abc123.tmp",
                 tmp_path / "learned" / f".xgb.{dead}.k2j4.staging",
                 tmp_path / "learned" / f".mlp.{dead}.99.old"]
    legacy = tmp_path / ".features-x1y2z3"  # an earlier version's feature staging: no pid, swept when old
    live = tmp_path / "decoded" / f".data.parquet.{os.getpid()}.zz.tmp"
    keep = [tmp_path / ".gitignore", tmp_path / "decoded" / "flight=a" / "data.parquet", live,
            tmp_path / "features" / ".recent.x9.tmp", tmp_path / "features" / ".data.parquet.x1y2.tmp"]
    for p in [*leftovers, legacy, *keep]:
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.mkdir() if p.suffix in (".staging", ".old") or p == legacy else p.write_text("x"))
    os.utime(legacy, (now - 2 * safewrite.STALE_AFTER_S,) * 2)

    removed = safewrite.sweep_stale(tmp_path)

    assert sorted(removed) == sorted([*leftovers, legacy])
    assert all(p.exists() for p in keep) and not any(p.exists() for p in removed)


def test_temp_names_carry_the_writer_and_are_unique(tmp_path, monkeypatch):
    seen = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (seen.append(Path(a).name), real(a, b)))
    store.write_json({"a": 1}, tmp_path / "x.json")
    store.write_json({"a": 2}, tmp_path / "x.json")
    assert len(set(seen)) == 2 and all(n.startswith(f".x.json.{os.getpid()}.") for n in seen)


def _hold_lock(root, env: dict[str, str] | None = None) -> subprocess.Popen:
    """Another process holding ``root``'s lock for 1.5 s (once it prints 'held')."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom quadcore.store import safewrite\n"
         "with safewrite.data_root_lock(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(1.5)\n",
         str(root)],
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), **(env or {})},
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
    return holder


def test_a_second_job_on_one_data_root_waits(tmp_path):
    holder = _hold_lock(tmp_path)
    waited, t0 = [], time.perf_counter()
    with safewrite.data_root_lock(tmp_path, on_wait=waited.append):
        elapsed = time.perf_counter() - t0
    holder.wait()
    assert waited and "waiting" in waited[0] and elapsed > 0.5


@pytest.mark.parametrize(("endpoint", "waits"), [("http://127.0.0.1:1", True), ("http://127.0.0.1:2", False)])
def test_an_object_store_root_is_locked_per_store(monkeypatch, endpoint, waits):
    """The same s3:// URL at the same endpoint is one store (a second job waits); at another
    endpoint (two local clusters' S3 servers on one machine) another store, which does not."""
    url = f"s3://quadcore-lock-test-{os.getpid()}/data"
    # the lock lives in the temp folder, which this test session moves (conftest): the holder's too
    holder = _hold_lock(url, {"AWS_ENDPOINT_URL": "http://127.0.0.1:1", "TMPDIR": tempfile.gettempdir()})
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
    waited: list[str] = []
    with safewrite.data_root_lock(url, on_wait=waited.append):
        pass
    holder.wait()
    assert bool(waited) == waits


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("kills")
    kills.train_templates(folder / kills.CHILD_TEMPLATE)
    return folder


def test_save_leaves_no_staging_and_replaces_whole(templates, tmp_path):
    model = artefacts.load(templates / kills.CHILD_TEMPLATE / "xgboost")
    target = tmp_path / "run"
    for _ in range(2):
        model.save(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert (target / "manifest.json").is_file() and artefacts.load(target).kind == "xgboost"


CORRUPTIONS = {
    "manifest not JSON": ("manifest.json", b"{not json"),
    "manifest a list": ("manifest.json", b"[1, 2]"),
    "features not JSON": ("features.json", b"\x00\x01"),
    "scaler without x": ("scaler.json", b'{"y": {}}'),
    "weights truncated": (None, b""),
    "weights garbage": (None, b"garbage" * 10),
}


@pytest.mark.parametrize("kind", ["xgboost", "mlp"])
@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_malformed_artefacts_raise_learning_error(templates, tmp_path, kind, case):
    folder = tmp_path / kind
    shutil.copytree(templates / kills.CHILD_TEMPLATE / kind, folder)
    name, data = CORRUPTIONS[case]
    name = name or ("model.ubj" if kind == "xgboost" else "model.pt")
    if case == "weights truncated":
        data = (folder / name).read_bytes()[:50]
    (folder / name).write_bytes(data)
    with pytest.raises(learners.LearningError, match="malformed|manifest"):
        artefacts.load(folder)


@pytest.mark.slow
def test_killed_writers_leave_no_torn_file_or_unloadable_model(templates):
    """Two random kills here (the fuzz harness runs 100: make fuzz)."""
    report = kills.run(templates, n_kills=2, seed=1, log=lambda m: None)
    assert report.torn_files == 0 and report.unloadable_models == 0
    assert report.leftovers_after_sweep == 0
