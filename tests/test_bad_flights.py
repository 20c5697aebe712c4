"""The 17 kinds of physically bad log (tests/fuzz/badlogs.py), each beside good flights: the CLI
and the main job finish with exit 0, every good flight gets its full outputs, and each bad
flight is reported with its reason."""

from __future__ import annotations

import contextlib
import io
import json

import dagster as dg
import pytest
from fuzz.badlogs import KINDS, bad_logs

from pipeline.resources import DataRoot, ModelConfig
from pipeline.run.main import run_all
from quadcore import cli
from quadcore.physics import gate
from quadcore.sim import simulation
from quadcore.store import store

GOOD = ["sim000", "sim001", "sim002"]
# Physically odd but usable: processed, with a failed decode check that says why.
USABLE_WITH_WARNING = {"gap_10s": "sample_gaps", "stuck_battery": "stuck_sensors"}
REFUSED = {f"bad_{k}" for k in KINDS if k not in USABLE_WITH_WARNING}
REASON_WORDS = {
    "nan_values": "non-finite", "inf_values": "non-finite", "nan_at_ends": "non-finite", "huge_values": "absurd",
    "one_record": "samples", "no_records": "samples", "short_flight": "samples", "equal_timestamps": "time",
    "stuck_clock": "time", "zero_quaternion": "quaternion", "unnormalised_quaternion": "quaternion",
    "zero_battery": "battery", "motors_idle": "flight phase", "missing_event": "fixedFrequency",
    "missing_variable": "stateEstimate.vx",
}
# Refused by the pipeline's decoding with one message naming every missing log variable
# (quadcore.logs.required): quarantined. `quadcore decode` decodes any log.
QUARANTINED = {"bad_missing_event", "bad_missing_variable"}


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    folder = tmp_path_factory.mktemp("raw_bad")
    configs = [simulation.SimConfig(kind="random", duration_s=5.0, seed=s) for s in (1, 2, 3)]
    simulation.simulate_set(folder, configs, {})
    for kind, data in bad_logs((folder / "sim000").read_bytes()).items():
        (folder / f"bad_{kind}").write_bytes(data)
    return folder


def _cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def test_there_are_17_kinds():
    assert len(KINDS) == 17 and set(REASON_WORDS) | set(USABLE_WITH_WARNING) == set(KINDS)


@pytest.mark.slow  # diagnose on 20 flights
def test_cli_diagnose_skips_each_bad_flight_with_its_reason(raw, tmp_path):
    code, _, err = _cli("diagnose", str(raw), "--json", str(tmp_path / "d.json"), "--quiet")
    assert code == 0, err
    result = json.loads((tmp_path / "d.json").read_text())
    skipped = result["skipped_flights"]
    assert set(skipped) == REFUSED
    for kind, word in REASON_WORDS.items():
        assert word in skipped[f"bad_{kind}"], (kind, skipped[f"bad_{kind}"])
        assert f"bad_{kind} skipped: " in err
    assert set(GOOD) <= set(result["evaluation"]["eval_flights"])


def test_cli_decode_and_residuals_go_on_past_bad_flights(raw, tmp_path):
    code, stdout, _ = _cli("decode", str(raw), "--out", str(tmp_path / "out"))
    assert code == 0 and f"{len(GOOD) + len(KINDS)} flights decoded" in stdout
    code, stdout, err = _cli("residuals", str(raw), "--out", str(tmp_path / "out"))
    assert code == 0, err
    for fid in GOOD:
        assert (tmp_path / "out" / "residuals" / f"flight={fid}" / "data.parquet").is_file()
    assert not any((tmp_path / "out" / "residuals" / f"flight={fid}").exists() for fid in REFUSED)


@pytest.mark.slow
def test_main_job_gives_every_good_flight_its_outputs(raw, tmp_path, monkeypatch, capfd):
    monkeypatch.setenv("QUADCORE_ALLOW_SIMULATED", "1")  # the bad logs are edited copies of simulated ones
    root = tmp_path / "root"
    lines: list[str] = []
    with dg.instance_for_test() as instance:
        code = run_all(DataRoot(root=str(root), raw=str(raw)), ModelConfig(), instance, log=lines.append)
        text = "\n".join(lines)
        assert code == 0, text
        for fid in [*GOOD, *(f"bad_{k}" for k in USABLE_WITH_WARNING)]:
            for stage in ("residuals", "rollouts"):
                assert (root / stage / f"flight={fid}" / "data.parquet").is_file(), (fid, stage, text)
            assert (root / "mcap" / f"{fid}.mcap").is_file()
        assert any((root / "learned").iterdir()) and (root / "reports" / "learning.json").is_file()
        diagnosis = json.loads((root / "reports" / "diagnosis.json").read_text())
        assert set(diagnosis["skipped_flights"]) == REFUSED - QUARANTINED  # quarantined: not decoded
        for kind, word in REASON_WORDS.items():  # one line per skipped flight, with its reason
            said = [line for line in lines if f" bad_{kind}: " in line]
            assert len(said) == 1 and f"bad_{kind}: skipped: " in said[0] and word in said[0], (kind, text)
        console = capfd.readouterr()
        assert "ERROR" not in console.out + console.err and "Stack Trace" not in console.out + console.err
    for kind, check in USABLE_WITH_WARNING.items():  # what the decoded_flight asset check reports
        passed, description, _ = gate.ALL_CHECKS[check](store.read_decoded(root, "fixedFrequency", f"bad_{kind}"))
        assert not passed, (kind, description)


def test_filters_do_not_reach_across_a_long_gap():
    import numpy as np

    from quadcore.physics import signals

    t = np.concatenate([np.arange(500) * 0.002, 10.0 + np.arange(500) * 0.002])
    x = np.where(t < 5, 0.0, 5.0)  # constant on each side, a jump across the 10 s gap
    assert np.abs(signals.derivative(x, t)).max() < 1e-9
    assert np.abs(signals.smooth(x, t_s=t) - x).max() < 1e-9
    assert np.abs(signals.matched_to_derivative(x, t, 0.002) - x).max() < 1e-6
