"""Issue 22: the physics gate checks the state estimate's own consistency (position against
integrated velocity, velocity against the accelerometer), not only ranges."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest

from quadcore.logs import flight
from quadcore.physics import dynamics, gate, vehicle
from quadcore.workflows import fleet


def test_every_real_flight_passes_with_a_wide_margin(real_logs):
    for path in flight.discover_logs(real_logs):
        df = flight.decode_flight(path).tables["fixedFrequency"]
        assert gate.state_estimate_problem(df) is None, path.name
        t = df["t_s"].to_numpy()
        drift, _ = gate._window_drift(t, df.select(gate.STATE_COLUMNS[:3]).to_numpy().astype(float),
                                        df.select(gate.STATE_COLUMNS[3:6]).to_numpy().astype(float))
        assert drift.max() < gate.MAX_POSITION_DRIFT_M / 5, path.name  # measured: <= 0.021 m


def _jumped(df: pl.DataFrame, column: str, rows: slice, by: float) -> pl.DataFrame:
    x = df[column].to_numpy().copy()
    x[rows] += by
    return df.with_columns(pl.Series(column, x))


@pytest.fixture(params=["real", "simulated"])
def main_table(request) -> pl.DataFrame:
    if request.param == "real":
        path = request.getfixturevalue("real_logs") / "jana02"
    else:
        path = sorted(request.getfixturevalue("drag_fleet").glob("sim00[0-9]"))[0]
    df = flight.decode_flight(path).tables["fixedFrequency"]
    assert gate.physics_problem(df, gate.NOMINAL_COLUMNS) is None
    return df


@pytest.mark.parametrize("column, rows, by, what", [
    ("p_w_x_m", slice(1000, None), 100.0, "position moves up to 100 m"),  # the case: a 100 m jump
    ("p_w_z_m", slice(1000, 1001), 0.5, "position"),  # one sample 0.5 m off
    ("v_w_y_mps", slice(1000, 1100), 3.0, "velocity"),  # a velocity step the accelerometer does not see
])
def test_a_state_estimate_that_contradicts_itself_is_refused(main_table, column, rows, by, what):
    bad = _jumped(main_table, column, rows, by)
    problem = gate.physics_problem(bad, gate.NOMINAL_COLUMNS)
    assert problem is not None and "contradicts itself" in problem and what in problem, problem
    assert gate.physics_facts(bad).problem(gate.NOMINAL_COLUMNS) == problem  # the footer's facts agree
    usable = fleet.usable({"good": main_table, "bad": bad}, vehicle.load(None))
    assert usable.ids == ["good"] and "contradicts itself" in usable.skipped["bad"]


def test_old_footer_facts_are_not_trusted_for_the_new_check(main_table):
    """Facts recorded before this check lack its key: the table is read again."""
    d = gate.physics_facts(main_table).to_dict()
    del d["state_estimate"]
    assert gate.PhysicsFacts.from_dict(d) is None


def test_footer_facts_found_by_another_gate_are_not_trusted(main_table, monkeypatch):
    """The facts carry the digest of the code that found them (gate.FACTS_MODULES): after a change
    to the gate (another digest) they are not used, and the table is read to judge it (before, only
    a missing key made them stale: a changed threshold left every footer's verdict current)."""
    d = gate.physics_facts(main_table).to_dict()
    assert gate.PhysicsFacts.from_dict(d) is not None
    monkeypatch.setattr(gate, "facts_digest", lambda: "another gate")
    assert gate.PhysicsFacts.from_dict(d) is None



def test_a_long_gap_restarts_the_integration():
    """A 10 s gap (a log paused): motion across it is not integrated, so a vehicle that moved
    while nothing was logged passes; the samples on each side are checked."""
    n = 2000
    t = np.r_[np.arange(n // 2) / 500.0, 10.0 + np.arange(n // 2) / 500.0]
    cols = {c: np.zeros(n) for c in gate.STATE_COLUMNS}
    cols.update(t_s=t, q_w=np.ones(n), sf_b_z_mps2=np.full(n, -dynamics.GRAVITY_W_MPS2[2]))
    cols["p_w_x_m"] = np.r_[np.zeros(n // 2), np.full(n // 2, 3.0)]
    assert gate.state_estimate_problem(pl.DataFrame(cols)) is None
    cols["p_w_x_m"][1500:] += 1.0
    assert "position" in (gate.state_estimate_problem(pl.DataFrame(cols)) or "")


def test_the_real_flights_planned_fast_yaw_wobble_flown_in_the_simulator_passes(tmp_path):
    """The plan for the 19 real flights (examples/real-flights/next-flight.csv: a slow line with a
    yaw wobble of ±16° at 2.1 Hz) flown closed loop with a CoM offset and the committed model's
    thrust scale and rotor drag: its state estimate agrees with its accelerometer (the gate's
    refusal of the proof's flights came from a rotor lag the controller cannot fly, not the yaw)."""
    from quadcore.sim import simulation

    plan = Path(__file__).resolve().parents[1] / "examples" / "real-flights" / "next-flight.csv"
    cfg = simulation.SimConfig(kind="plan", plan_file=str(plan), height_m=0.6, duration_s=9.0, seed=0)
    effects = {"thrust_scale": {"scale": 0.92}, "rotor_drag": {"k_x_s_per_m": 0.036, "k_y_s_per_m": 0.040,
                                                               "k_z_s_per_m": 0.040},
               "com_offset": {"x_c_m": -0.0009}}
    sim = simulation.simulate(cfg, vehicle.load(None), effects)
    assert np.ptp(sim.reference.yaw_rad[sim.t_s > 3.0]) > np.radians(15)  # the wobble is flown
    simulation.write_flight(sim, tmp_path / "planned")
    df = flight.decode_flight(tmp_path / "planned").tables["fixedFrequency"]
    assert gate.physics_problem(df, gate.NOMINAL_COLUMNS) is None
