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


def _line(**over) -> dict:
    outcome = {"top": "motor_lag", "first": True, "tied": False, "alike": False, "sigma": 5.0}
    return {"scenario": "lag_firmware_short", "seed": 0, "truth": "motor_lag", "before": outcome,
            "planned": outcome, "files": {"circle0": outcome}, "manoeuvre": "m", "predicted_sigma": 1.0,
            "predicted_before": 0.0, "added": [], **over}


def test_a_run_at_other_limits_gets_its_own_table(bench_plan, tmp_path, capsys):
    """``--max-speed`` and the like record the plan's limits in each line; ``--table`` keeps a run
    at other limits apart from one at the default limits and from lines written before the
    limits were recorded (read as the default)."""
    from quadcore.plan.limits import Limits

    faster = Limits(max_speed_mps=2.2, max_tilt_deg=45.0).to_dict()
    trials = [bench_plan.trial_from(d) for d in (_line(), _line(limits=Limits().to_dict()), _line(limits=faster))]
    assert [bench_plan.label(t) for t in trials[:2]] == ["lag_firmware_short"] * 2
    assert bench_plan.label(trials[2]) == "lag_firmware_short (plan limits: 2.2 m/s, 9.80665 m/s², 45°)"
    bench_plan.summarise(trials)
    out = capsys.readouterr().out
    assert out.count("\nlag_firmware_short: σ for the truth") == 1
    assert out.count("\nlag_firmware_short (plan limits: 2.2 m/s, 9.80665 m/s², 45°): σ for the truth") == 1
