"""The search from statistics (quadcore.identify.fit.search): nonlinear effects the profiles cannot
carry, their predictions made on the flights' rows and entering the statistics as an extra column,
against the fit on rows (the reference).

Tolerances, measured on these flights (three 4 s random flights, a 30 ms motor lag hidden) when
the search was written (after bba72ce): one nonlinear parameter (the same grid, Brent's refinement and profile interval
on the same objective) and a nonlinear effect held fixed (no search) agree with the rows to float
rounding (parameters 2e-16, standard errors 2e-11 relative: 1e-9 asked). Two parameters: the rows ran
trust-region least squares on the residual vector, the statistics minimise the objective
(L-BFGS-B) and take the Gauss-Newton covariance from derivative columns; they met within 6e-4 of a
standard error (5e-6 relative) and their standard errors within 0.1 %: 0.01 σ and 1 % asked (both
optimisers stop on their own tolerances, not at one float).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reference import rows as reference

from quadcore import effects
from quadcore.identify import fit as fitlib, flightdata
from quadcore.identify.binfile import StatsError
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import vehicle

VEHICLE = vehicle.load()

SCALED_LAG = Path(__file__).resolve().parent / "plugins" / "scaled_lag.py"  # two nonlinear parameters


@pytest.fixture(scope="module")
def lagged(tmp_path_factory):
    """Three short random flights with a motor lag of 30 ms hidden, as rows; the scaled-lag plugin
    loaded (two nonlinear parameters)."""
    from quadcore.sim import simulation

    folder = tmp_path_factory.mktemp("lagged")
    configs = [simulation.SimConfig(kind="random", duration_s=4.0, seed=s, speed_min_mps=0.8) for s in (31, 32, 33)]
    simulation.simulate_set(folder, configs, {"motor_lag": {"tau_s": 0.03}}, VEHICLE)
    fds = {p.name: flightdata.flight_data(p.name, flight.decode_flight(p).tables["fixedFrequency"], VEHICLE)
           for p in flight.discover_logs(folder)}
    effects.load_plugin(SCALED_LAG)
    yield fds
    effects.unregister("scaled_lag")


def _both(fds: dict, names: list[str], layout: sufficient.Layout, fixed: dict | None = None):
    """The fit on rows and from statistics (rows only for the nonlinear effects' predictions)."""
    ids = sorted(fds)
    es = [effects.get(n) for n in names]
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE,
                               fixed, bounded=True)
    stats = [sufficient.flight_stats(fds[f], VEHICLE, layout) for f in ids]
    combined = fitlib.fit_effects(es, stats, [s.layout.target() for s in stats], VEHICLE, fixed, bounded=True,
                                  rows=lambda f: fds[f])
    return rows, combined


def _params(fit) -> list[tuple[str, str]]:
    return [(e, k) for e in fit.params for k in fit.params[e]]


@pytest.mark.parametrize("names", [["scaled_lag"], ["scaled_lag", "thrust_scale", "rotor_drag"],
                                   ["motor_lag", "thrust_delay", "rotor_drag"]])
def test_several_nonlinear_parameters_from_statistics_meet_the_row_search(lagged, names):
    rows, combined = _both(lagged, names, sufficient.library_layout())
    assert combined.params["motor_lag" if "motor_lag" in names else "scaled_lag"]["tau_s"] == pytest.approx(
        0.03, rel=0.05)  # the hidden lag found (the comparison below is not one of two wrong answers)
    for e, k in _params(rows):
        a, b, s = rows.params[e][k], combined.params[e][k], rows.std[e][k]
        assert s > 0 and abs(a - b) < 0.01 * s, f"{e}.{k}: rows {a} ± {s}, statistics {b}"
        assert combined.std[e][k] == pytest.approx(s, rel=0.01), f"{e}.{k}"


def test_one_nonlinear_parameter_without_a_profile_equals_the_row_search(lagged):
    """Statistics that hold no profile of motor_lag: its prediction on the rows is the extra column
    at every value the one-parameter search asks for."""
    layout = sufficient.layout_of([effects.get("rotor_drag"), effects.get("thrust_scale")])
    assert not layout.profiled
    rows, combined = _both(lagged, ["motor_lag", "rotor_drag"], layout)
    for e, k in _params(rows):
        assert combined.params[e][k] == pytest.approx(rows.params[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"
        assert combined.std[e][k] == pytest.approx(rows.std[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"


def test_a_fixed_nonlinear_effect_without_a_profile_is_subtracted_as_its_rows_prediction(lagged):
    """(With a profile, a fixed profiled effect is its profile's column: quadcore.identify.fit.fit_effects.)"""
    layout = sufficient.layout_of([effects.get("rotor_drag")])
    rows, combined = _both(lagged, ["motor_lag", "rotor_drag"], layout, {"motor_lag": {"tau_s": 0.03}})
    assert combined.params["motor_lag"] == {"tau_s": 0.03} and combined.std["motor_lag"] == {"tau_s": 0.0}
    for e, k in _params(rows):
        assert combined.params[e][k] == pytest.approx(rows.params[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"
        assert combined.std[e][k] == pytest.approx(rows.std[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"


def test_a_fixed_profiled_lag_beside_a_free_profiled_delay_is_fitted_from_the_profiles(lagged):
    """A model file that fixes the lag and fits a delay beside it: the fixed lag is its profile's
    column, the delay the one free profiled effect (this raised 'too many values to unpack'
    when the fixed lag was still counted as a second free one). The delay lands where the row
    search does within a tenth of a sample (the profile's grid does not resolve the delay's
    sample-period ripple: tests/test_sufficient.py), the thrust scale within 1 % of its σ."""
    names, fixed = ["motor_lag", "thrust_delay", "thrust_scale"], {"motor_lag": {"tau_s": 0.03}}
    rows, combined = _both(lagged, names, sufficient.library_layout(), fixed)
    assert combined.params["motor_lag"] == {"tau_s": 0.03}
    dt_s = float(np.median(np.diff(lagged[sorted(lagged)[0]].state.t_s)))
    assert abs(combined.params["thrust_delay"]["t_d_s"] - rows.params["thrust_delay"]["t_d_s"]) < dt_s / 10
    a, b = rows.params["thrust_scale"]["scale"], combined.params["thrust_scale"]["scale"]
    s = rows.std["thrust_scale"]["scale"]
    assert s > 0 and abs(a - b) < 0.01 * s, f"rows {a} ± {s}, statistics {b}"


def test_a_search_without_rows_says_what_it_needs(lagged):
    ids = sorted(lagged)
    stats = [sufficient.flight_stats(lagged[f], VEHICLE, sufficient.library_layout()) for f in ids]
    with pytest.raises(StatsError, match="rows"):
        fitlib.fit_effects([effects.get("scaled_lag")], stats, [s.layout.target() for s in stats], VEHICLE)


@pytest.mark.parametrize("names, fixed", [(["rotor_drag", "thrust_scale"], None), (["motor_lag", "rotor_drag"], None),
                                          (["rotor_drag", "thrust_scale"], {"thrust_scale": {"scale": 1.01}})])
def test_targets_given_as_rows_become_statistics_and_fit_as_the_rows_do(lagged, names, fixed):
    """fit_rows: each flight's target (rows) an extra column of its statistics, the fit from them."""
    ids = sorted(lagged)
    fds = [lagged[f] for f in ids]
    ys = [y * 0.5 for y in flightdata.targets_of(fds)]  # any target on the rows, not only y0
    es = [effects.get(n) for n in names]
    rows = reference.fit_effects(es, fds, ys, VEHICLE, fixed, bounded=True)
    combined = fitlib.fit_rows(es, fds, ys, VEHICLE, fixed, bounded=True)
    assert combined.weights == pytest.approx(rows.weights, rel=1e-9)
    for e, k in _params(rows):
        assert combined.params[e][k] == pytest.approx(rows.params[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"
        assert combined.std[e][k] == pytest.approx(rows.std[e][k], rel=1e-9, abs=1e-14), f"{e}.{k}"


def test_a_target_on_a_profiled_models_column_reads_that_column_on_the_rows(lagged):
    """The diagnosis's residual beside a model with a profiled lag is a vector on the statistics
    grown by the model's column ``pred:motor_lag`` (sufficient.predicted); a candidate the profiles
    cannot carry (two parameters) is fitted to it by the search, which makes that column on the
    rows (``extras``). At a value on the profile's grid (the column exact there) it meets the fit on
    rows to the residual made on rows as the search meets the row search above (0.01 σ)."""
    from quadcore.identify.stats import profiles

    ids = sorted(lagged)
    lag = effects.get("motor_lag")
    tau = float(profiles.profile_grid(lag.parameters[0].lower, lag.parameters[0].upper)[9])
    model = {"motor_lag": {"tau_s": tau}}
    stats, targets, columns = [], [], {}
    for f in ids:
        grown, v = sufficient.predicted([lag], model, sufficient.flight_stats(lagged[f], VEHICLE,
                                                                              sufficient.library_layout()), VEHICLE)
        stats.append(grown)
        targets.append(grown.layout.target() - v)
        columns[f] = {"pred:motor_lag": flightdata.prediction(lag, model["motor_lag"], lagged[f], VEHICLE)}
    ys = [y - columns[f]["pred:motor_lag"] for f, y in zip(ids, flightdata.targets_of([lagged[f] for f in ids]))]
    es = [effects.get("scaled_lag"), effects.get("thrust_scale")]
    rows = reference.fit_effects(es, [lagged[f] for f in ids], ys, VEHICLE, bounded=True)
    combined = fitlib.fit_effects(es, stats, targets, VEHICLE, bounded=True, rows=lambda f: lagged[f],
                                  extras=lambda f: columns[f])
    for e, k in _params(rows):
        a, b, s = rows.params[e][k], combined.params[e][k], rows.std[e][k]
        assert s > 0 and abs(a - b) < 0.01 * s, f"{e}.{k}: rows {a} ± {s}, statistics {b}"
