"""The commands the hints name run as printed: `make ui` / `make run` with the settings of the run
that prints them (raw folder, data root, model file, ...), the quadcore command as the shell finds it."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from pipeline.resources import ModelConfig, make_command
from quadcore.commands import quadcore_command
from quadcore.sim import simulation


@pytest.fixture
def clone(tmp_path, monkeypatch):
    """A working directory like the clone's, with none of the caller's QUADCORE_* settings."""
    for key in list(os.environ):
        if key.startswith("QUADCORE_") or key in ("DAGSTER_HOME", "PORT"):
            monkeypatch.delenv(key)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_the_ui_command_repeats_the_tutorials_settings(clone, monkeypatch, tmp_path_factory):
    flights = tmp_path_factory.mktemp("flights")
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(flights))
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(clone / "mine" / "data"))  # as the Makefile passes it: absolute
    monkeypatch.setenv("QUADCORE_MODEL", "mine/model.toml")
    monkeypatch.setenv("DAGSTER_HOME", str(clone / "mine" / "data" / ".dagster"))  # the default for that root
    assert make_command("ui", 3300) == (f"QUADCORE_RAW_DIR={flights} QUADCORE_DATA_ROOT=mine/data "
                                        "QUADCORE_MODEL=mine/model.toml PORT=3300 make ui")
    assert make_command("run") == (f"QUADCORE_RAW_DIR={flights} QUADCORE_DATA_ROOT=mine/data "
                                   "QUADCORE_MODEL=mine/model.toml make run")
    monkeypatch.setenv("DAGSTER_HOME", str(clone / "my instance"))  # another instance: named, quoted
    monkeypatch.setenv("QUADCORE_HOLDOUT", "jana02")
    assert make_command("ui") == (f"QUADCORE_RAW_DIR={flights} QUADCORE_DATA_ROOT=mine/data "
                                  "QUADCORE_MODEL=mine/model.toml QUADCORE_HOLDOUT=jana02 "
                                  "DAGSTER_HOME='my instance' make ui")


def test_the_demo_needs_no_setting_while_data_raw_holds_no_logs(clone, monkeypatch):
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(clone / "data" / "demo"))  # what choose_demo sets
    monkeypatch.setenv("DAGSTER_HOME", str(clone / "data" / "demo" / ".dagster"))
    assert make_command("ui") == "make ui"
    simulation.simulate_set(clone / "data" / "raw", [simulation.SimConfig(kind="hover", duration_s=1.0, seed=1)], {})
    # `make ui` alone would now open data/ (the user's logs): the demo's root is named
    assert make_command("ui") == "QUADCORE_DATA_ROOT=data/demo make ui"
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(clone / "data"))
    monkeypatch.setenv("DAGSTER_HOME", str(clone / "data" / ".dagster"))
    assert make_command("run") == "make run"


def test_the_main_jobs_closing_lines_name_the_commands_with_the_settings(clone, monkeypatch, tmp_path_factory):
    from pipeline.run.main import _closing

    flights = tmp_path_factory.mktemp("flights")
    root = clone / "mine" / "data"
    root.mkdir(parents=True)
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(flights))
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(root))
    monkeypatch.setenv("QUADCORE_MODEL", "mine/model.toml")
    monkeypatch.setenv("PORT", "3300")
    lines: list[str] = []
    _closing(root, ModelConfig(model_file=str(clone / "mine" / "model.toml")), "thrust_scale", False, {},
             lines.append)
    settings = f"QUADCORE_RAW_DIR={flights} QUADCORE_DATA_ROOT=mine/data QUADCORE_MODEL=mine/model.toml"
    assert (f"\nNext step: add 'thrust_scale' to `effects` in {clone / 'mine' / 'model.toml'} and run again: "
            f"{settings} make run") in lines
    assert f"\nSee it in the UI:  {settings} PORT=3300 make ui   (Dagster UI on http://127.0.0.1:3300)" in lines


def test_the_quadcore_command_is_the_one_the_shell_finds(clone, monkeypatch):
    script = Path(sys.executable).parent / "quadcore"
    if not script.is_file():
        pytest.skip(f"no quadcore script beside {sys.executable} (the package is not installed in this environment)")
    monkeypatch.setenv("PATH", "/usr/bin:/bin")  # a shell without the venv activated
    assert quadcore_command() == str(script.resolve())  # outside the working directory: absolute
    monkeypatch.chdir(script.resolve().parents[2])  # the clone: the README's spelling
    assert quadcore_command() == str(script.resolve().relative_to(script.resolve().parents[2]))
    monkeypatch.setenv("PATH", f"{script.parent}:/usr/bin:/bin")  # activated
    assert quadcore_command() == "quadcore"
