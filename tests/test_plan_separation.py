"""The planner's measured separation (:func:`quadcore.plan.separation.compare`) from the flights'
statistics equals the same held-out comparison on their rows (tests/reference/separation.py):
linear candidates to rounding (measured 1e-15); beside a model with a profiled nonlinear effect,
whose prediction comes from its profile interpolated between grid points, to 1e-4 (measured
8e-6); one-parameter nonlinear candidates, fitted and predicted from their profiles where the
rows search the parameter itself, to 1 % (measured 3e-3). For two timing candidates it is the
diagnosis's own angular-rate level test, not the torque channels' comparison."""

from __future__ import annotations

import pytest
from reference import separation as reference

from quadcore.identify import diagnosis, rates
from quadcore.identify.fit import model_fit
from quadcore.identify.model import PhysicsModel
from quadcore.logs import flight as flightlib
from quadcore.physics import vehicle
from quadcore.plan import separation
from quadcore.sim import simulation
from quadcore.sim.simulation import SimConfig
from quadcore.spec.model import spec_from

VEHICLE = vehicle.load()


@pytest.fixture(scope="module")
def weak_map(tmp_path_factory) -> dict:
    """Three hover flights with a weak thrust map and a 15 ms motor lag (decoded tables)."""
    folder = tmp_path_factory.mktemp("weak_map")
    configs = [SimConfig(kind="hover", duration_s=6.0, seed=s) for s in (1, 2, 3)]
    simulation.simulate_set(folder, configs, {"thrust_scale": {"scale": 0.92}, "motor_lag": {"tau_s": 0.015}},
                            VEHICLE)
    return {p.name: flightlib.decode_flight(p).tables["fixedFrequency"] for p in flightlib.discover_logs(folder)}


@pytest.mark.parametrize("effects, pair, skip, rel", [
    ([], ("thrust_scale", "added_mass"), 0, 1e-9),
    ([], ("thrust_scale", "added_mass"), 1, 1e-9),
    (["motor_lag"], ("thrust_scale", "added_mass"), 1, 1e-4),
    ([], ("motor_lag", "thrust_delay"), 1, 1e-2),
])
def test_the_separation_from_statistics_is_the_one_on_the_rows(weak_map, effects, pair, skip, rel):
    spec = spec_from(VEHICLE, effects)
    model = (model_fit.fit_model(spec, weak_map, sorted(weak_map)) if effects
             else PhysicsModel(VEHICLE, []))
    comp = separation.compare(weak_map, spec, model, *pair, skip=skip)
    t, blocks = reference.t_statistic(separation.flights_of(weak_map, spec), model, *pair, skip=skip)
    assert comp.blocks == blocks
    assert comp.t == pytest.approx(t, rel=rel), (comp.t, t)
    assert abs(t) > 1.0  # a comparison that says something (not two zero predictions)


def test_a_lag_against_a_delay_is_measured_by_the_diagnosis_s_own_rate_level_test(weak_map, monkeypatch):
    """The diagnosis decides a lag against a delay at the angular-rate level
    (:func:`quadcore.identify.rates.judge`): the planner's measured separation of the two
    (what the plan reports before, the proof after, and the benchmark per trial) is that test's t."""
    seen: list[float] = []
    test = rates.difference_test

    def spy(g, D):
        out = test(g, D)
        seen.append(out.t)
        return out

    monkeypatch.setattr(rates, "difference_test", spy)
    spec = spec_from(VEHICLE, [])
    diag = diagnosis.diagnose(weak_map, spec)
    assert len(seen) == 1, seen  # the diagnosis compared the pair once
    comp = separation.measured(weak_map, spec, diag, "motor_lag", "thrust_delay")
    assert len(seen) == 2 and comp.t == pytest.approx(seen[0], rel=1e-12, abs=1e-12)
    torque = separation.compare(weak_map, spec, diag.model, "motor_lag", "thrust_delay",
                                skip=separation.skipped_blocks(diag))
    assert abs(comp.t - torque.t) > 0.5, (comp.t, torque.t)  # a different statistic from the torque level's

