"""A bad ``QUADCORE_*`` setting is a user error: ``python -m pipeline`` says so in one line and
exits 2, never with a traceback (the setting is read when the definitions are imported)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def test_a_bad_executor_setting_is_one_line_and_exit_code_2(tmp_path):
    env = {**os.environ, "QUADCORE_EXECUTOR": "bogus", "QUADCORE_DATA_ROOT": str(tmp_path / "root"),
           "PYTHONPATH": str(REPO)}
    env.pop("DAGSTER_HOME", None)
    done = subprocess.run([sys.executable, "-m", "pipeline"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: QUADCORE_EXECUTOR='bogus': use in_process, multiprocess, k8s or celery"]
    assert not (tmp_path / "root").exists()  # nothing done


@pytest.mark.slow  # a python -m pipeline of its own; the executor test covers the mechanism in the fast tier
def test_a_bad_retrain_cron_is_one_line_and_exit_code_2(tmp_path):
    """Read when the learning assets are defined: Dagster's own check, as a user error."""
    env = {**os.environ, "QUADCORE_RETRAIN_CRON": "every night", "QUADCORE_DATA_ROOT": str(tmp_path / "root"),
           "PYTHONPATH": str(REPO)}
    env.pop("DAGSTER_HOME", None)
    done = subprocess.run([sys.executable, "-m", "pipeline"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: QUADCORE_RETRAIN_CRON='every night': not a cron schedule (e.g. '0 2 * * *')"]
    assert not (tmp_path / "root").exists()


def test_a_missing_sessions_file_stops_the_main_job_before_any_work(tmp_path, drag_fleet):
    """``QUADCORE_SESSIONS`` naming no file: one line and exit code 2 before decoding, as a bad
    model file is, not a failed fit after every flight was decoded."""
    env = {**os.environ, "QUADCORE_SESSIONS": str(tmp_path / "nowhere.toml"),
           "QUADCORE_DATA_ROOT": str(tmp_path / "root"), "QUADCORE_RAW_DIR": str(drag_fleet), "PYTHONPATH": str(REPO)}
    env.pop("DAGSTER_HOME", None)
    done = subprocess.run([sys.executable, "-m", "pipeline"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.strip().splitlines() == [f"error: sessions file not found: {tmp_path / 'nowhere.toml'}"]
    assert not (tmp_path / "root" / "decoded").exists()
