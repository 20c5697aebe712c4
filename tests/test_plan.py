"""``quadcore plan``: the planned trajectory is in the lab's format, loads in the project's reader,
starts and ends at hover and respects the limits (checked by evaluating its polynomials); the
JSON contract; nothing planned when nothing needs separating; and (slow) the planned flight,
flown with the hidden truth, makes the diagnosis decide ties that the logged flights leave open."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from quadcore import cli
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.plan import bench, family, flatness, limits, pieces
from quadcore.sim import simulation, trajectories
from quadcore.sim.simulation import SimConfig

VEHICLE = vehicle.load()
LIMITS = limits.Limits()


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, out.getvalue(), err.getvalue()


def _manoeuvre(shape: str = "figure8", f0: float = 0.3, chirp: float = 2.0, bob: float = 0.3) -> family.Manoeuvre:
    return family.Manoeuvre(shape, f0, chirp, 0.9, bob, LIMITS.centre_m, 12.0)


@pytest.mark.parametrize("shape", list(family.SHAPES))
def test_pieces_follow_the_path_start_and_end_at_hover_and_load_in_the_reader(shape, tmp_path):
    m = _manoeuvre(shape)
    traj = family.trajectory(m)
    assert len(traj.durations) <= pieces.MAX_PIECES
    # the knots: position and its derivatives as the analytic path has them
    knots = family.knots(m.duration_s)
    for k in range(4):
        want = family._derivatives(m, knots)[:, :, k]
        got = traj.evaluate(np.clip(knots, 0, m.duration_s - 1e-12), k)
        assert np.allclose(got, want, atol=1e-4 * max(1.0, float(np.abs(want).max()))), k
    # starts and ends at rest at the hover point (the arena's centre)
    ends = np.array([0.0, m.duration_s])
    assert np.allclose(traj.evaluate(ends)[:, :3], [m.centre_m, m.centre_m], atol=1e-9)
    for k in (1, 2, 3):
        assert np.allclose(traj.evaluate(ends, k)[:, :3], 0.0, atol=1e-9), k
    # the CSV round trip through the project's reader, as a file
    path = pieces.write_csv(traj, tmp_path / "plan.csv")
    back = trajectories.load_plan(path)
    assert np.allclose(back.durations, traj.durations) and np.allclose(back.coeffs, traj.coeffs, rtol=1e-8, atol=1e-9)
    t = np.linspace(0, m.duration_s, 997)
    assert np.allclose(back.evaluate(t), traj.evaluate(t), atol=1e-7)
    assert path.read_text().splitlines()[0] == pieces.HEADER  # the lab's header (figure8.csv's)


def test_hermite_piece_matches_both_ends():
    start, end, h = np.array([0.1, -0.5, 2.0, 3.0]), np.array([0.7, 1.5, -1.0, 0.5]), 0.4
    c = pieces.hermite_piece(start, end, h)
    poly = np.polynomial.Polynomial(c)
    for k in range(4):
        d = poly.deriv(k) if k else poly
        assert d(0.0) == pytest.approx(start[k], abs=1e-9) and d(h) == pytest.approx(end[k], rel=1e-9, abs=1e-9)


def test_the_largest_scale_respects_every_limit_and_more_does_not():
    m = _manoeuvre("figure8", 0.6, 2.0, 0.3)
    unit = family.trajectory(m)
    s = limits.largest_scale(unit, m.centre_m, VEHICLE, LIMITS)
    assert 0 < s < 1
    ok = limits.check(family.scaled_trajectory(unit, m.centre_m, 0.98 * s), VEHICLE, LIMITS)
    assert ok.ok and ok.max_tilt_deg <= LIMITS.max_tilt_deg and ok.max_speed_mps <= LIMITS.max_speed_mps
    assert ok.max_acc_mps2 <= LIMITS.acc_mps2 and ok.in_arena
    too_much = limits.check(family.scaled_trajectory(unit, m.centre_m, 1.3 * s), VEHICLE, LIMITS)
    assert not too_much.ok


def test_flatness_gives_hover_thrust_at_rest_and_tilt_from_acceleration():
    traj = family.trajectory(_manoeuvre("line", 0.3, 1.0, 0.0))
    path = flatness.flat_path(traj, VEHICLE)
    assert path.thrust_N[0] == pytest.approx(VEHICLE.weight_N, rel=1e-9)
    assert np.allclose(path.f_rotor_N[0], VEHICLE.weight_N / 4, rtol=1e-9)
    horizontal = np.linalg.norm(path.a_w_mps2[:, :2], axis=1)
    want = np.degrees(np.arctan2(horizontal, 9.80665 + path.a_w_mps2[:, 2]))
    assert np.allclose(np.degrees(path.tilt_rad), want, atol=1e-6)


@pytest.mark.parametrize("arena, message", [("0,0,0,0.1,0.1,0.1", "too small"), ("1,2,3", "six numbers")])
def test_bad_limits_are_a_message(arena, message, tmp_path):
    code, _, err = _run(["plan", str(tmp_path), "--json", str(tmp_path / "p.json"), "--trajectory",
                         str(tmp_path / "p.csv"), "--arena", arena])
    assert code == 2 and message in err and "Traceback" not in err


@pytest.fixture(scope="module")
def hover_tie(tmp_path_factory) -> Path:
    """Three hover flights with a weak thrust map: thrust scale and added mass tie."""
    folder = tmp_path_factory.mktemp("hover_tie")
    configs = [SimConfig(kind="hover", duration_s=6.0, seed=s) for s in (1, 2, 3)]
    simulation.simulate_set(folder, configs, {"thrust_scale": {"scale": 0.92}}, VEHICLE)
    return folder


CONTRACT_KEYS = ["question", "trajectory", "duration_s", "limits", "predicted"]


def test_cli_plan_writes_the_contract_a_loadable_trajectory_within_limits_and_its_picture(hover_tie, tmp_path):
    out = tmp_path / "out"
    code, stdout, err = _run(["plan", str(hover_tie), "--json", str(out / "plan.json"), "--trajectory",
                              str(out / "plan.csv"), "--duration", "5", "--max-speed", "1.0", "--max-tilt", "20",
                              "--no-proof", "--quiet"])
    assert code == 0, err
    doc = json.loads((out / "plan.json").read_text())
    assert list(doc)[:5] == CONTRACT_KEYS
    assert doc["question"]["kind"] == "separate"
    assert sorted(doc["question"]["candidates"]) == ["added_mass", "thrust_scale"]
    assert doc["trajectory"] == str(out / "plan.csv") and doc["duration_s"] == 5.0
    lim = doc["limits"]
    assert lim["max_speed_mps"] == 1.0 and lim["max_tilt_deg"] == 20.0 and len(lim["arena"]) == 6
    assert lim["max_acc_mps2"] == pytest.approx(9.80665 * math.tan(math.radians(20)))
    assert set(doc["predicted"]) >= {"separation_sigma_before", "separation_sigma_after"}
    assert all(isinstance(doc["predicted"][k], float) for k in ("separation_sigma_before", "separation_sigma_after"))
    # the trajectory: the project's reader loads it; the limits hold on its polynomials
    traj = trajectories.load_plan(out / "plan.csv")
    assert traj.duration_s == pytest.approx(5.0)
    checked = limits.check(traj, VEHICLE, limits.Limits(1.0, 20.0))
    assert checked.ok and checked.max_speed_mps <= 1.0 and checked.max_tilt_deg <= 20.0
    t = np.linspace(0, traj.duration_s, 2001)
    speed = np.linalg.norm(traj.evaluate(t, 1)[:, :3], axis=1)
    assert speed.max() <= 1.0 + 1e-9 and speed[0] < 1e-6 and speed[-1] < 1e-6  # from and to hover
    assert (out / "plan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "thrust_scale" in stdout and "wrote" in stdout


def test_cli_plan_asks_what_it_is_told_and_refuses_unknown_candidates(hover_tie, tmp_path):
    code, _, err = _run(["plan", str(hover_tie), "--json", str(tmp_path / "p.json"), "--trajectory",
                         str(tmp_path / "p.csv"), "--between", "thrust_scale,no_such_effect", "--quiet"])
    assert code == 2 and "no_such_effect" in err and "Traceback" not in err
    assert not (tmp_path / "p.json").exists()


def test_cli_plan_for_a_parameter_writes_its_contract_and_a_flight_that_narrows_it(hover_tie, tmp_path):
    """``--parameter EFFECT.NAME``: the question is the parameter, the JSON carries its standard
    error before and as the planned flight would leave it (smaller: a flight can only add
    information), the trajectory loads and keeps the limits; a malformed or unknown parameter is
    a message, and nothing is written."""
    out = tmp_path / "out"
    code, stdout, err = _run(["plan", str(hover_tie), "--json", str(out / "plan.json"), "--trajectory",
                              str(out / "plan.csv"), "--parameter", "thrust_scale.scale", "--duration", "5",
                              "--no-proof", "--quiet"])
    assert code == 0, err
    doc = json.loads((out / "plan.json").read_text())
    assert list(doc)[:5] == CONTRACT_KEYS
    assert doc["question"] == {"kind": "parameter", "parameter": "thrust_scale.scale"}
    assert set(doc["predicted"]) == {"parameter_std_before", "parameter_std_after"}
    before, after = doc["predicted"]["parameter_std_before"], doc["predicted"]["parameter_std_after"]
    assert math.isfinite(before) and before > 0 and 0 < after < before, doc["predicted"]
    traj = trajectories.load_plan(out / "plan.csv")
    assert traj.duration_s == pytest.approx(5.0) and limits.check(traj, VEHICLE, LIMITS).ok
    assert "thrust_scale.scale" in stdout
    for bad, message in (("thrust_scale", "EFFECT.NAME"), ("thrust_scale.nope", "has no parameter")):
        code, _, err = _run(["plan", str(hover_tie), "--json", str(tmp_path / "p.json"), "--trajectory",
                             str(tmp_path / "p.csv"), "--parameter", bad, "--no-proof", "--quiet"])
        assert code == 2 and message in err and "Traceback" not in err, err
        assert not (tmp_path / "p.json").exists() and not (tmp_path / "p.csv").exists()


def test_nothing_to_separate_plans_nothing(tmp_path):
    folder = tmp_path / "still"
    simulation.simulate_set(folder, [SimConfig(kind="hover", duration_s=6.0, seed=s) for s in (4, 5)], {}, VEHICLE)
    code, stdout, err = _run(["plan", str(folder), "--json", str(tmp_path / "p.json"), "--trajectory",
                              str(tmp_path / "p.csv"), "--quiet"])
    assert code == 0, err
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["question"] == {"kind": "none"} and doc["trajectory"] is None and doc["predicted"] == {}
    assert not (tmp_path / "p.csv").exists()
    assert "nothing to plan" in stdout


def test_lag_against_delay_from_logs_below_the_command_rate_plans_nothing_and_says_to_log_faster(tmp_path):
    """At 100 Hz the log misses four commands in five and no flight logged so tells a lag from a
    delay (docs/timing.md): asked to separate them, the planner plans nothing and says why."""
    folder = tmp_path / "slow"
    configs = [SimConfig(kind="hover", duration_s=6.0, seed=s, log_rate_hz=100.0) for s in (4, 5)]
    simulation.simulate_set(folder, configs, {"thrust_delay": {"t_d_s": 0.01}}, VEHICLE)
    code, stdout, err = _run(["plan", str(folder), "--json", str(tmp_path / "p.json"), "--trajectory",
                              str(tmp_path / "p.csv"), "--between", "motor_lag,thrust_delay", "--quiet"])
    assert code == 0, err
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["question"] == {"kind": "none"} and doc["trajectory"] is None
    assert not (tmp_path / "p.csv").exists()
    assert "nothing to plan" in stdout and "every 10 ms" in stdout and "500 Hz" in stdout, stdout


# The full benchmark (benchmarks/bench_plan.py) runs 10 seeds per scenario and the lab's files
# beside the plan; CI runs the first two seeds (one per truth) of the two scenarios the logged
# flights leave open, without the files. The third, a 10 ms motor lag against a thrust delay in
# hover, is no longer open: fitted at the angular-rate level (docs/timing.md) the hover flights
# decide it already, and the planned flight must not undo that (one seed, the lag true). With the
# firmware's coloured noise the hover flights tied when the lag was true until the rate level
# modelled the gyro's noise (now 1 of 5 lag-true seeds); every flight that moves decides it, the
# plan designed at the angular-rate level by the largest separation (docs/flight-planning.md: at
# 2 ms nothing is found, at 5 ms the hovers tie and the planned flight decides, below the command rate
# nothing decides).
@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["drag", "mass"])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_planned_flight_decides_what_the_logged_flights_leave_open(scenario, seed):
    trial = bench.run(scenario, seed, files=())
    assert not trial.before.decided or trial.before.alike, trial.before  # the question is open before
    assert trial.planned.decided, (trial.manoeuvre, trial.planned)


@pytest.mark.slow
def test_a_lag_and_a_delay_are_decided_before_and_with_the_planned_flight():
    trial = bench.run("lag", 0, files=())
    assert trial.truth == "motor_lag" and trial.before.decided, trial.before
    assert trial.planned.decided, (trial.manoeuvre, trial.planned)


@pytest.mark.slow
def test_with_the_firmwares_noise_a_lag_is_decided_before_and_with_the_planned_flight():
    """The sensor noise the real logs have (coloured by the firmware's 80 Hz gyro filter): with the
    rate level's whitening filter of each flight's gyro noise (quadcore.identify.rates.gyro_noise_model)
    the three hover flights decide a 10 ms lag against the delay already (without a noise model
    they tied it, 5 of 5 lag-true seeds, docs/timing.md); the planned flight, designed at the
    angular-rate level, keeps it decided, and by far more than the lab's yaw0 flown for the same
    time (the best of the files here; all seeds and files: benchmarks/bench_plan.py)."""
    trial = bench.run("lag_firmware", 0, files=("yaw0",))
    assert trial.truth == "motor_lag" and trial.before.decided, trial.before
    assert trial.planned.decided, (trial.manoeuvre, trial.planned)
    assert trial.planned.sigma > 2 * max(trial.files["yaw0"].sigma, 1.0), (trial.planned, trial.files)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_the_objective_for_a_lag_against_a_delay_predicts_the_rate_levels_separation_and_information(seed):
    """The plan's objective for two timing candidates is the diagnosis's angular-rate level
    comparison (quadcore.plan.ratelevel): on three hover flights with white sensor noise its
    expected t (the truth's side) is within 35 % of the t the diagnosis's test measures
    (measured at b07461a: 8.4 against 9.3 with the lag true, 10.3 against 11.4 with the delay)."""
    from quadcore.identify import rates
    from quadcore.plan import planner, question, ratelevel, separation
    from quadcore.spec.model import spec_from

    pair = bench.SCENARIOS["lag"].pair
    truth = pair[seed % 2]
    old, diag = bench.old_flights("lag", seed)
    spec = spec_from(VEHICLE, [])
    a, b = (question.explanation(diag, n) for n in pair)
    obj = planner.separation_objective(a, b, planner.fitting_flights(old, spec), diag, VEHICLE)
    assert isinstance(obj, ratelevel.RateSeparation)
    predicted = obj.evaluate().by_truth[truth][0]
    measured = separation.measured(old, spec, diag, *pair).sigma_for(truth)
    assert measured > 3 and predicted == pytest.approx(measured, rel=0.35), (predicted, measured)
    # and for the truth's parameter (a --parameter question), the information the planner counts
    # per flight gives, on the logged flights, the standard error of the rate level's own fit
    # (measured: 0.468 against 0.466 ms for the lag, 0.111 against 0.130 ms for the delay)
    expl = a if truth == a.name else b
    (p,) = expl.effect.parameters
    info = ratelevel.RateInformation(expl, expl.std[p.name], planner.fitting_flights(old, spec), diag.model, VEHICLE)
    real = [rates.flight_sums(fd, diag.model, f, [expl.effect], info.logged.skip_blocks)
            for f, fd in planner.fitting_flights(old, spec).items()]
    fitted = rates.fit(expl.effect, real, rates.weights(real))
    std = 1 / math.sqrt(sum(info.flight_information(rf) for rf in info.logged.flights.values()))
    assert std == pytest.approx(fitted.std, rel=0.2), (std, fitted.std)


def test_a_data_roots_plan_is_made_from_its_stored_diagnosis_beside_it(hover_tie, tmp_path):
    """What the flight_plan asset does: the typed diagnosis rebuilt from reports/diagnosis.json,
    the plan written as reports/flight_plan.{json,csv,png}; a plan that plans nothing removes
    an earlier plan's trajectory and picture."""
    from quadcore.plan.planner import PlanRequest
    from quadcore.spec.model import spec_from
    from quadcore.store import store
    from quadcore.workflows import fleet as fleetlib, identify, plan as planflow

    spec = spec_from(VEHICLE, [])
    flights = fleetlib.fleet_from_logs([str(hover_tie)], VEHICLE, lambda m: None)
    diag = identify.diagnose(flights, spec, [])
    identify.write_diagnosis_json(diag, store.diagnosis_path(tmp_path))
    result, written = planflow.plan_data_root(tmp_path, flights, spec, PlanRequest(duration_s=4.0, prove=False))
    reports = store.reports_dir(tmp_path)
    assert result.planned and written.trajectory == reports / planflow.PLAN_CSV
    assert written.plot == reports / planflow.PLAN_PNG
    doc = json.loads(written.json.read_text())
    assert sorted(doc["question"]["candidates"]) == ["added_mass", "thrust_scale"]
    assert trajectories.load_plan(written.trajectory).duration_s == pytest.approx(4.0)
    # a diagnosis with nothing tied and nothing found: nothing to plan, and the old plan's files go
    nothing = PlanRequest(between=None, parameter=None, duration_s=4.0, prove=False)
    doc_none = store.read_json(store.diagnosis_path(tmp_path))
    for c in doc_none["candidates"]:
        c["tied_with"], c["indistinguishable_from"], c["found"] = [], [], False
    store.write_json(doc_none, store.diagnosis_path(tmp_path))
    result, written = planflow.plan_data_root(tmp_path, flights, spec, nothing)
    assert not result.planned and written.trajectory is None
    assert not (reports / planflow.PLAN_CSV).exists() and not (reports / planflow.PLAN_PNG).exists()
    assert json.loads(written.json.read_text())["question"] == {"kind": "none"}


@pytest.mark.slow
def test_the_proof_measures_the_separation_on_the_statistics_the_diagnosis_took(hover_tie, monkeypatch):
    """The proof (each explanation flown in the simulator, then diagnosed and compared with the old
    flights): the comparison takes the flights' statistics made once for the diagnosis and equals
    the comparison on the rows (tests/reference/separation.py) to rounding; each explanation flown
    is favoured by the separation when the diagnosis ranks it first."""
    from reference import separation as reference

    from quadcore.identify import diagnosis as diagnosislib
    from quadcore.plan import planner, separation
    from quadcore.spec.model import spec_from

    spec = spec_from(VEHICLE, [])
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(hover_tie)}
    compared, compare = [], separation.compare

    def recorded(tables, spec, model, a, b, n_folds=separation.N_FOLDS, skip=0, stats=None):
        out = compare(tables, spec, model, a, b, n_folds, skip, stats)
        compared.append((stats, out, reference.t_statistic(separation.flights_of(tables, spec), model, a, b,
                                                             n_folds, skip)[0]))
        return out

    monkeypatch.setattr(separation, "compare", recorded)
    result = planner.plan(tables, spec, diagnosislib.diagnose(tables, spec), planner.PlanRequest(duration_s=4.0))
    assert sorted(f.truth for f in result.proof) == ["added_mass", "thrust_scale"]
    assert len(compared) == 3  # the logged flights, then each explanation flown
    for _, out, t_rows in compared:
        assert out.t == pytest.approx(t_rows, rel=1e-9)
    assert all(stats is not None for stats, _, _ in compared[1:])  # the diagnosis's statistics, not made again
    for flown in result.proof:
        assert flown.sigma is not None and (flown.sigma > 0 or not flown.first), flown


def test_a_flight_the_simulator_cannot_fly_is_left_out_of_the_proof_with_its_reason(hover_tie):
    """One explanation's flight that cannot be flown does not stop the proof: flown with a rotor
    lag of 0.106 s (the real flights' fitted lag, which the simulator's controller cannot fly) the
    plan is left out with the reason, the other explanation is still flown and diagnosed, and the
    JSON says what was left out and why (the prediction after is then the design's)."""
    from dataclasses import replace

    from quadcore import effects as effectlib
    from quadcore.identify import diagnosis as diagnosislib
    from quadcore.plan import planner, proof, question
    from quadcore.plan.signatures import Explanation
    from quadcore.spec.model import spec_from

    spec = spec_from(VEHICLE, [])
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(hover_tie)}
    diag = diagnosislib.diagnose(tables, spec)
    result = planner.plan(tables, spec, diag, planner.PlanRequest(between=("thrust_scale", "added_mass"),
                                                                  duration_s=4.0, prove=False))
    kept = question.explanation(diag, "thrust_scale")
    unflyable = Explanation(effectlib.get("motor_lag"), {"tau_s": 0.106}, {"tau_s": 0.003})
    said: list[str] = []
    done = proof.fly(result.trajectory, tables, spec, diag.model, [unflyable, kept], None, log=said.append)
    assert [f.truth for f in done.flown] == ["thrust_scale"] and done.flown[0].top
    [left] = done.left_out
    assert left.truth == "motor_lag" and "lost control" in left.reason and "tau_s=0.106" in left.reason
    assert any("WARNING" in m and "motor_lag" in m for m in said)
    doc = replace(result, proof=done.flown, proof_left_out=done.left_out).to_dict("plan.csv")
    assert doc["proof_left_out"] == [{"truth": "motor_lag", "reason": left.reason}]
    assert [f["truth"] for f in doc["proof"]] == ["thrust_scale"]
    assert doc["predicted"]["separation_sigma_after"] == result.design["after"]["sigma"]


def test_the_plan_says_how_much_such_flying_would_decide_and_compares_like_with_like(hover_tie):
    """Without the proof the contract's before and after are one measure (the design's), the
    separation measured on the logged flights under ``measured``; ``improves`` says whether the
    planned flight raises both of the diagnosis's measures; and where one flight is not expected
    to decide, ``repeated`` gives the fewest copies of it that are (the objective at that many
    copies reaches 1 and at one fewer does not), or none up to MAX_COPIES, with the advice."""
    from quadcore.identify import diagnosis as diagnosislib
    from quadcore.plan import objective, planner, question, signatures
    from quadcore.spec.model import spec_from

    spec = spec_from(VEHICLE, [])
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(hover_tie)}
    diag = diagnosislib.diagnose(tables, spec)
    result = planner.plan(tables, spec, diag, planner.PlanRequest(duration_s=4.0, prove=False))
    doc = result.to_dict("plan.csv")
    design = doc["design"]
    pred = doc["predicted"]
    assert pred["separation_sigma_before"] == design["before"]["sigma"]
    assert pred["score_gap_before"] == design["before"]["score_gap"]
    assert pred["separation_sigma_after"] == design["after"]["sigma"]
    # in hover the torque is at its noise floor: thrust scale and payload predict the same force,
    # no held-out comparison, and the design's note says why it expects more (it counts the torque)
    assert doc["measured"]["separation_sigma_before"] == result.measured_before == 0.0
    assert "no held-out comparison" in design["note"] and "torque at the floor" in design["note"]
    raised = (design["after"]["sigma"] >= design["before"]["sigma"]
              and design["after"]["score_gap"] >= design["before"]["score_gap"])
    assert design["improves"] is raised
    # the objective with N copies of the planned flight, as the planner builds it
    a, b = (question.explanation(diag, n) for n in result.question.candidates)
    flights = planner.fitting_flights(tables, spec)
    obj = planner.separation_objective(a, b, flights, diag, VEHICLE)
    assert isinstance(obj, objective.SeparationObjective)
    fd = signatures.planned_flight(result.trajectory, VEHICLE, signatures.activity(list(flights.values())))
    assert obj.evaluate(fd).value == pytest.approx(design["after"]["value"], rel=1e-9)
    values = [obj.evaluate(fd, n).value for n in (1, 2, 4, 8)]
    assert values == sorted(values) and values[-1] > values[0]  # more such flying separates more
    copies, there = obj.copies_to_decide(fd)
    if copies is None:
        assert there.value < 1 and obj.evaluate(fd, objective.MAX_COPIES).value < 1
    else:
        assert there.value >= 1 and (copies == 1 or obj.evaluate(fd, copies - 1).value < 1)
    if design["expected_to_decide"]:
        assert "repeated" not in design and "advice" not in design
    else:
        assert design["repeated"]["copies"] == copies
        assert design["repeated"]["at"]["value"] == pytest.approx(there.value, rel=1e-9)
        assert design["advice"].startswith("one such flight does not decide it")


def test_the_search_refines_the_best_of_each_manoeuvre_length_not_only_the_best_grid_points():
    """On the 19 real flights every top grid point was a short manoeuvre (then hover) while a
    manoeuvre over the whole flight refined to twice the value (docs/flight-planning.md). Here a
    value of the same shape: every short manoeuvre scores 1.05, one over the whole flight 1 plus
    a quarter of its yaw excursion (rad) late in the flight (below 1.05 on the grid's wobble, above once refined):
    the search must return one over the whole flight."""
    from quadcore.plan import search

    duration = 10.0
    late = np.linspace(0.6 * duration, 0.9 * duration, 200)

    def value(tr: trajectories.PolyTrajectory) -> float:
        p = tr.evaluate(late)
        moving = np.ptp(p[:, :3], axis=0).max() > 1e-3
        return 1.0 + 0.25 * float(np.abs(p[:, 3]).max()) if moving else 1.05

    best = search.search(value, VEHICLE, LIMITS, duration)
    assert best.manoeuvre.active_s is None and best.value > 1.05, best.manoeuvre.describe()
