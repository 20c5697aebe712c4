"""Bringing your own flights: the log variables the physics needs, checked once per log with one
message naming everything missing (at the raw folder's door and when the pipeline decodes), and
a vehicle file of your own from `quadcore vehicle new`, every number commented, that the vehicle
loader accepts."""

from __future__ import annotations

import contextlib
import io
import tomllib
from pathlib import Path

import dagster as dg
import numpy as np
import pytest
from fuzz.badlogs import _records

from pipeline.assets.decode import decoded_flight
from pipeline.resources import DataRoot
from pipeline.sensors import header_problem
from quadcore import cli
from quadcore.logs import logformat, required
from quadcore.physics import vehicle
from quadcore.sim import simulation
from quadcore.store import store

REPO = Path(__file__).resolve().parents[1]
SHARED_CONFIG = REPO.parent / "shared" / "crazyflie" / "usd-config.txt"


def _without(good: bytes, drop: set[str]) -> bytes:
    """``good`` re-encoded without the ``fixedFrequency`` variables in ``drop``."""
    log = logformat.decode_bytes(good)
    rec = _records(log)
    ts, v = rec[required.MAIN_EVENT]
    keep = [n for n in v.dtype.names or () if n not in drop]
    rec[required.MAIN_EVENT] = (ts, np.ascontiguousarray(v[keep]))
    types = []
    for name, (_, values) in rec.items():
        old = log.event_types[name]
        names = tuple(values.dtype.names or ())
        chars = tuple(old.type_chars[old.variables.index(n)] for n in names)
        types.append(logformat.EventType(old.event_id, name, names, chars))
    return logformat.encode(types, [(n, t, x) for n, (t, x) in rec.items()], version=log.version)


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    folder = tmp_path_factory.mktemp("own")
    simulation.simulate_set(folder, [simulation.SimConfig(kind="hover", duration_s=2.0, seed=1)], {})
    good = (folder / "sim000").read_bytes()
    (folder / "no_gyro_z_acc_x").write_bytes(_without(good, {"gyro.z", "acc.x"}))
    (folder / "rpm_only").write_bytes(_without(good, {"pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm",
                                                      "pm.vbatMV"}))
    (folder / "no_thrust_map").write_bytes(_without(good, {"pwm.m3_pwm", "rpm.m2"}))
    return folder


def test_the_documented_deck_configuration_holds_every_required_variable():
    """docs/reference/log-variables.md's lines (and DECK_CONFIG) log all of it; where the shared data
    set is here, its deck configuration is the same list."""
    listed = [line.split("#")[0].strip() for line in required.DECK_CONFIG.splitlines()]
    assert required.missing({required.MAIN_EVENT: listed}) == []
    doc = (REPO / "docs" / "reference" / "log-variables.md").read_text()
    assert all(f"\n{v}\n" in doc for v in (*required.ALWAYS, *required.PWM_VBAT, *required.MOTOR_SPEED))
    if SHARED_CONFIG.is_file():
        shared = [line.split("#")[0].strip() for line in SHARED_CONFIG.read_text().splitlines()]
        assert required.missing({required.MAIN_EVENT: shared}) == []


def test_one_message_names_every_missing_variable_at_the_door(raw):
    assert header_problem(raw / "sim000") is None
    assert header_problem(raw / "rpm_only") is None  # the motor-speed map's inputs are complete
    problem = header_problem(raw / "no_gyro_z_acc_x")
    assert problem.startswith("MissingVariablesError: not usable for the physics: its 'fixedFrequency' event "
                              "lacks 2 variable(s): gyro.z, acc.x; log them with the uSD deck"), problem
    assert "docs/reference/log-variables.md" in problem
    problem = header_problem(raw / "no_thrust_map")  # neither map complete: the default map's inputs named
    assert "lacks 1 variable(s): pwm.m3_pwm (the thrust map needs" in problem, problem


def test_the_pipeline_quarantines_such_a_log_with_that_message_and_decodes_the_others(raw, tmp_path):
    data_root = DataRoot(root=str(tmp_path / "root"), raw=str(raw))
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions("flights", ["no_gyro_z_acc_x", "sim000"])
        quiet = {"loggers": {"console": {"config": {"log_level": "ERROR"}}}}
        bad = dg.materialize([decoded_flight], partition_key="no_gyro_z_acc_x", instance=instance,
                             resources={"data_root": data_root}, run_config=quiet, raise_on_error=False)
        good = dg.materialize([decoded_flight], partition_key="sim000", instance=instance,
                              resources={"data_root": data_root}, run_config=quiet)
    assert not bad.success and good.success
    (record,) = store.quarantined(tmp_path / "root")
    assert record["flight"] == "no_gyro_z_acc_x" and record["error_type"] == "MissingVariablesError"
    assert "lacks 2 variable(s): gyro.z, acc.x" in record["reason"]
    assert not store.decoded_path(tmp_path / "root", "fixedFrequency", "no_gyro_z_acc_x").exists()


def _cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def test_vehicle_new_writes_a_commented_template_the_loader_accepts(tmp_path):
    out = tmp_path / "mine" / "myquad.toml"
    code, stdout, err = _cli("vehicle", "new", "myquad", "--out", str(out))
    assert code == 0, err
    assert f"wrote {out}" in stdout
    text = out.read_text()
    v = vehicle.load(out)
    assert v.name == "myquad" and v.n_rotors == 4 and v.thrust_map_kind == "pwm_vbat"
    builtin = vehicle.load()
    assert v.mass_kg == builtin.mass_kg and np.array_equal(v.allocation, builtin.allocation)
    # every line that sets a number says what it is in a comment, with its unit where it has one
    numbers = [line for line in text.splitlines()
               if "=" in line and not line.lstrip().startswith("#") and any(ch.isdigit() for ch in line.split("=")[1])
               and not line.strip().startswith("[")]
    assert numbers and all("#" in line for line in numbers if "inertia" not in line), \
        [line for line in numbers if "#" not in line]
    assert "kg m^2" in text and "mass_kg = 0.0347            # take-off mass" in text
    assert tomllib.loads(text)["name"] == "myquad"
    code, stdout, _ = _cli("vehicle", "check", str(out))
    assert code == 0 and "vehicle 'myquad', 34.7 g, 4 rotors, thrust map pwm_vbat" in stdout


def test_vehicle_new_refuses_to_overwrite_and_check_names_a_bad_key(tmp_path):
    out = tmp_path / "myquad.toml"
    out.write_text("keep me")
    code, _, err = _cli("vehicle", "new", "myquad", "--out", str(out))
    assert code == 2 and "exists already" in err and out.read_text() == "keep me"
    bad = tmp_path / "bad.toml"
    assert _cli("vehicle", "new", "bad", "--out", str(bad))[0] == 0
    bad.write_text(bad.read_text().replace("mass_kg = 0.0347", "mass_kg = -1"))
    code, _, err = _cli("vehicle", "check", str(bad))
    assert code == 2 and "mass_kg = -1" in err and "Traceback" not in err
