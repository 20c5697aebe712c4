"""A bad ``QUADCORE_*`` setting is a user error: ``python -m pipeline`` says so in one line and
exits 2, never with a traceback, before any work."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _main_job(tmp_path: Path, timeout: float = 120, **settings: str) -> subprocess.CompletedProcess:
    """``python -m pipeline`` from this checkout with the given ``QUADCORE_*`` settings and the data
    root ``tmp_path/root`` (no inherited Dagster home)."""
    env = {**os.environ, **settings, "QUADCORE_DATA_ROOT": str(tmp_path / "root"), "PYTHONPATH": str(REPO)}
    env.pop("DAGSTER_HOME", None)
    return subprocess.run([sys.executable, "-m", "pipeline"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_a_bad_executor_setting_is_one_line_and_exit_code_2(tmp_path):
    done = _main_job(tmp_path, QUADCORE_EXECUTOR="bogus")
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: QUADCORE_EXECUTOR='bogus': use in_process, multiprocess, k8s or celery"]
    assert not (tmp_path / "root").exists()  # nothing done


@pytest.mark.slow  # a python -m pipeline of its own; the executor test covers the mechanism in the fast tier
def test_a_bad_retrain_cron_is_one_line_and_exit_code_2(tmp_path):
    """Read when the learning assets are defined: Dagster's own check, as a user error."""
    done = _main_job(tmp_path, QUADCORE_RETRAIN_CRON="every night")
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: QUADCORE_RETRAIN_CRON='every night': not a cron schedule (e.g. '0 2 * * *')"]
    assert not (tmp_path / "root").exists()


def test_a_missing_sessions_file_stops_the_main_job_before_any_work(tmp_path, drag_fleet):
    """``QUADCORE_SESSIONS`` naming no file: one line and exit code 2 before decoding, as a bad
    model file is, not a failed fit after every flight was decoded."""
    done = _main_job(tmp_path, timeout=300, QUADCORE_SESSIONS=str(tmp_path / "nowhere.toml"),
                     QUADCORE_RAW_DIR=str(drag_fleet))
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.strip().splitlines() == [f"error: sessions file not found: {tmp_path / 'nowhere.toml'}"]
    assert not (tmp_path / "root" / "decoded").exists()
