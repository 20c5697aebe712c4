"""benchmarks/bench_plan.py's ``--json`` file: a run killed mid-write leaves its last line cut
short; ``--table`` leaves that line out with a message (before: a JSONDecodeError traceback), and a
resumed run appends its trials on lines of their own after it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_plan.py"


@pytest.fixture(scope="module")
def bench_plan():
    spec = importlib.util.spec_from_file_location("bench_plan_script", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_cut_short_last_line_is_left_out_with_a_message(bench_plan, tmp_path, capsys):
    path = tmp_path / "trials.jsonl"
    path.write_text(json.dumps({"seed": 0}) + "\n" + json.dumps({"seed": 1}) + "\n" + '{"seed": 2, "tru')
    assert bench_plan.read_lines(str(path)) == [{"seed": 0}, {"seed": 1}]
    assert "line 3 is not complete JSON" in capsys.readouterr().err


def test_a_resumed_run_appends_after_the_cut_short_line(bench_plan, tmp_path, capsys):
    path = tmp_path / "trials.jsonl"
    bench_plan.append_line(str(path), json.dumps({"seed": 0}))
    path.write_text(path.read_text() + '{"seed": 1, "tru')  # killed mid-write
    bench_plan.append_line(str(path), json.dumps({"seed": 1}))
    assert bench_plan.read_lines(str(path)) == [{"seed": 0}, {"seed": 1}]
    assert "line 2 is not complete JSON" in capsys.readouterr().err
